#!/usr/bin/env python3
"""How far the revolve stage's fitted radius lies from the true one, per target kind.

Renders a preset's tuning scenes, runs `deocc run` on each and compares, for every target the
revolve stage fitted, each fitted slice's radius with a circle fitted to the true surface
(`ground_truth.ply`, the target's points) at the same height. Standard library only.

    python3 scripts/revolve_radius_study.py --deocc target/release/deocc --work /tmp/radius \\
        --preset pickup-v2 --from-seed 9450000 --scenes 60 --sensor structured-light

docs/decisions.md ("What keeps pickup-v2 under structured light short of the true cloud")
quotes its output. The scenes are tuning scenes, never the test split.
"""

import argparse
import json
import math
import os
import statistics
import struct
import subprocess
import sys

PLY_TYPES = {"float": "f", "uchar": "B", "uint": "I", "int": "i", "double": "d"}


def read_ply(path):
    """The vertices of a binary little-endian PLY as a list of dicts."""
    with open(path, "rb") as f:
        props, n = [], 0
        while True:
            line = f.readline().decode().strip()
            if line.startswith("element vertex"):
                n = int(line.split()[-1])
            elif line.startswith("property"):
                _, kind, name = line.split()
                props.append((name, PLY_TYPES[kind]))
            elif line == "end_header":
                break
        fmt = "<" + "".join(k for _, k in props)
        size = struct.calcsize(fmt)
        data = f.read(n * size)
    names = [name for name, _ in props]
    return [dict(zip(names, struct.unpack_from(fmt, data, i * size))) for i in range(n)]


def circle(points):
    """Kasa's algebraic circle through (x, y) points: (cx, cy, r), or None."""
    # x^2 + y^2 = a x + b y + c, least squares via the 3x3 normal equations.
    m = [[0.0] * 3 for _ in range(3)]
    v = [0.0] * 3
    for x, y in points:
        row = (x, y, 1.0)
        rhs = x * x + y * y
        for i in range(3):
            v[i] += row[i] * rhs
            for j in range(3):
                m[i][j] += row[i] * row[j]
    try:
        a, b, c = solve3(m, v)
    except ZeroDivisionError:
        return None
    cx, cy = a / 2, b / 2
    r2 = c + cx * cx + cy * cy
    return (cx, cy, math.sqrt(r2)) if r2 > 0 else None


def solve3(m, v):
    """Gaussian elimination with partial pivoting on a 3x3 system."""
    a = [row[:] + [v[i]] for i, row in enumerate(m)]
    for k in range(3):
        p = max(range(k, 3), key=lambda i: abs(a[i][k]))
        if abs(a[p][k]) < 1e-15:
            raise ZeroDivisionError
        a[k], a[p] = a[p], a[k]
        for i in range(k + 1, 3):
            f = a[i][k] / a[k][k]
            for j in range(k, 4):
                a[i][j] -= f * a[k][j]
    x = [0.0] * 3
    for i in (2, 1, 0):
        x[i] = (a[i][3] - sum(a[i][j] * x[j] for j in range(i + 1, 3))) / a[i][i]
    return x


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--deocc", default="target/release/deocc")
    ap.add_argument("--work", required=True, help="folder for the scenes and runs")
    ap.add_argument("--preset", default="pickup-v2")
    ap.add_argument("--from-seed", type=int, default=9_450_000)
    ap.add_argument("--scenes", type=int, default=60)
    ap.add_argument("--sensor", default="structured-light")
    ap.add_argument("--options", help="pipeline options JSON for `deocc run`")
    a = ap.parse_args()
    scenes = os.path.join(a.work, "scenes")
    if not os.path.isdir(scenes):
        subprocess.run(
            [a.deocc, "synth", "scenes", "--preset", a.preset, "--from-seed", str(a.from_seed),
             "--first", str(a.scenes), "--sensor", a.sensor, "--out", scenes],
            check=True,
        )
    by_kind = {}
    for k in range(a.scenes):
        scene = os.path.join(scenes, f"scene_{k:06d}")
        run = os.path.join(a.work, f"run_{k:06d}")
        cmd = [a.deocc, "run", scene, "--out", run]
        if a.options:
            cmd += ["--options", a.options]
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        info = json.load(open(os.path.join(scene, "scene.json")))
        target = info["target"]
        kind = next(o["category"] for o in info["objects"] if o["instance_id"] == target)
        report = json.load(open(os.path.join(run, "report.json")))
        inst = next((i for i in report["instances"] if i["instance_id"] == target), None)
        fit = inst and inst.get("revolve") and inst["revolve"].get("fit")
        if not fit:
            continue
        truth = [
            (p["x"], p["y"], p["z"])
            for p in read_ply(os.path.join(scene, "ground_truth.ply"))
            if p["instance"] == target
        ]
        errors = []
        for z0, r in fit["radii"]:
            ring = [(x, y) for x, y, z in truth if z0 <= z < z0 + 0.01]
            if len(ring) < 3:
                ring = [(x, y) for x, y, z in truth if abs(z - z0 - 0.005) < 0.02]
            c = circle(ring) if len(ring) >= 3 else None
            if c and c[2] < 0.2:  # a degenerate ring (a few collinear points) says nothing
                errors.append(r - c[2])
        if errors:
            e = statistics.mean(errors)
            by_kind.setdefault(kind, []).append(e)
            print(f"{info['seed']} {kind:15s} fitted {fit['radii'][0][1] * 1e3:5.1f} mm, "
                  f"error {e * 1e3:+5.1f} mm, arc {fit['arc_deg']:.0f} deg"
                  f"{' (from the top)' if fit['from_top'] else ''}")
    print("kind: fitted targets, radius error median / mean (mm)")
    for kind, errs in sorted(by_kind.items()):
        print(f"  {kind:15s} {len(errs):3d}  {statistics.median(errs) * 1e3:+.1f} / "
              f"{statistics.mean(errs) * 1e3:+.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
