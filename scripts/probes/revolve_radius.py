#!/usr/bin/env python3
"""How far the revolve stage's fitted radius lies from the true one, per target kind.

Renders a preset's tuning scenes, runs `deocc run` on each and compares, for every target the
revolve stage fitted, each fitted slice's radius with a circle fitted to the true surface
(`ground_truth.ply`, the target's points) at the same height.

    python3 -m venv /tmp/venv && /tmp/venv/bin/pip install numpy
    /tmp/venv/bin/python scripts/probes/revolve_radius.py --deocc target/release/deocc \\
        --work /tmp/radius --preset pickup-v2 --from-seed 9450000 --scenes 60 \\
        --sensor structured-light

docs/decisions.md ("What keeps pickup-v2 under structured light short of the true cloud")
quotes its output. The scenes are tuning scenes, never the test split.
"""

import argparse
import json
import os
import statistics
import subprocess
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from ply import read_ply  # noqa: E402


def circle(x, y):
    """Kasa's algebraic circle through the points (x, y): (cx, cy, r), or None."""
    a = np.stack([x, y, np.ones_like(x)], 1)
    (p, q, c), *_ = np.linalg.lstsq(a, x * x + y * y, rcond=None)
    cx, cy = p / 2, q / 2
    r2 = c + cx * cx + cy * cy
    return (cx, cy, float(np.sqrt(r2))) if r2 > 0 else None


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
        g = read_ply(os.path.join(scene, "ground_truth.ply"))
        own = g["instance"] == target
        x, y, z = g["x"][own], g["y"][own], g["z"][own]
        errors, centres = [], []
        for z0, r in fit["radii"]:
            ring = (z >= z0) & (z < z0 + 0.01)
            if ring.sum() < 3:
                ring = np.abs(z - z0 - 0.005) < 0.02
            c = circle(x[ring], y[ring]) if ring.sum() >= 3 else None
            if c and c[2] < 0.2:  # a degenerate ring (a few collinear points) says nothing
                errors.append(r - c[2])
                centres.append(np.hypot(fit["axis"][0] - c[0], fit["axis"][1] - c[1]))
        if errors:
            e = statistics.mean(errors)
            by_kind.setdefault(kind, []).append(e)
            print(f"{info['seed']} {kind:15s} fitted {fit['radii'][0][1] * 1e3:5.1f} mm, "
                  f"error {e * 1e3:+5.1f} mm, axis off {statistics.mean(centres) * 1e3:4.1f} mm, "
                  f"arc {fit['arc_deg']:.0f} deg"
                  f"{'' if fit.get('outline_offset_m') is None else ', outline %+.1f mm' % (fit['outline_offset_m'] * 1e3)}"
                  f"{' (from the top)' if fit['from_top'] else ''}")
    print("kind: fitted targets, radius error median / mean (mm)")
    for kind, errs in sorted(by_kind.items()):
        print(f"  {kind:15s} {len(errs):3d}  {statistics.median(errs) * 1e3:+.1f} / "
              f"{statistics.mean(errs) * 1e3:+.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
