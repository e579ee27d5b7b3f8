"""Ray Data over scene folders with the deocc Python package: each task reads a scene, runs the
pipeline in-process (the GIL is released, so a worker's threads overlap) and writes the completed
cloud as .npz. Install the wheel on every node (scripts/test_python.sh builds it).

    python deploy/ray_batch.py scenes.txt out/
"""

import os
import sys

import numpy as np
import ray

import deocc


def complete(row):
    scene = row["scene"]
    out = os.path.join(row["out"], os.path.basename(scene.rstrip("/")) + ".npz")
    if os.path.exists(out):
        return {"scene": scene, "status": "skipped", "points": -1}
    frames, structure = deocc.read_scene(scene)
    res = deocc.run(frames, structure_ids=structure)
    tmp = out + ".partial.npz"
    np.savez_compressed(tmp, points=res["points"], colors=res["colors"],
                        instance=res["instance"], provenance=res["provenance"])
    os.replace(tmp, out)  # complete or absent, never half-written
    return {"scene": scene, "status": "done", "points": len(res["points"])}


def main(manifest, out):
    os.makedirs(out, exist_ok=True)
    base = os.path.dirname(os.path.abspath(manifest))
    with open(manifest) as f:
        scenes = [os.path.join(base, l.strip()) for l in f if l.strip() and not l.startswith("#")]
    ds = ray.data.from_items([{"scene": s, "out": out} for s in scenes])
    for row in ds.map(complete, num_cpus=2).iter_rows():
        print(row)


if __name__ == "__main__":
    main(*sys.argv[1:3])
