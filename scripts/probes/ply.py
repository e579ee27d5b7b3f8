"""Reads the PLY files deocc writes (ASCII or binary) into numpy arrays, one per property."""
import numpy as np
def read_ply(path):
    f = open(path, 'rb'); props = []; n = 0; fmt = None
    while True:
        line = f.readline().decode().strip()
        if line.startswith('format'): fmt = line.split()[1]
        if line.startswith('element vertex'): n = int(line.split()[2])
        if line.startswith('property'):
            t, name = line.split()[1], line.split()[2]; props.append((name, t))
        if line == 'end_header': break
    tmap = {'float':'f4','float32':'f4','uchar':'u1','uint8':'u1','uint':'u4','uint32':'u4','int':'i4','ushort':'u2','double':'f8','char':'i1'}
    if fmt == 'ascii':
        data = np.loadtxt(f, max_rows=n)
        return {name: data[:, i] for i, (name, _) in enumerate(props)}
    dt = np.dtype([(name, ('<' if fmt=='binary_little_endian' else '>') + tmap[t]) for name, t in props])
    arr = np.frombuffer(f.read(n * dt.itemsize), dtype=dt, count=n)
    return {name: arr[name] for name, _ in props}
