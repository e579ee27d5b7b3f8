#!/usr/bin/env python3
"""Cross-view room on bench-v1 (issue 18, item 6): of an object's surface that one view does not
see (in frame, the object partly visible there), the share some other view observes. That share
is already observed in the fused cloud, and the pair data's cross-view condition carries no
relative pose, so a 2-D model cannot place it; the rest is hidden in every view, where other
views give no observation.

    deocc synth scenes --preset bench-v1 --first 5 --out /tmp/bv1
    python3 -m venv /tmp/venv && /tmp/venv/bin/pip install numpy pillow
    /tmp/venv/bin/python scripts/probes/crossview.py /tmp/bv1 5
"""
import json
import sys

import numpy as np
from PIL import Image

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from ply import read_ply  # noqa: E402

root, scenes = sys.argv[1], int(sys.argv[2])
hidden_total = seen_elsewhere = 0
for s in range(scenes):
    sc = f"{root}/scene_{s:06d}"
    meta = json.load(open(f"{sc}/scene.json"))
    structure = {o["instance_id"] for o in meta["objects"] if o["structure"]}
    cams = json.load(open(f"{sc}/cameras.json"))["frames"]
    gt = read_ply(f"{sc}/ground_truth.ply")
    G = np.stack([gt["x"], gt["y"], gt["z"]], 1)
    gi = gt["instance"].astype(int)
    vis, inframe = [], []
    for c in cams:
        K, T = c["intrinsics"], np.array(c["world_from_camera"])
        D = np.array(Image.open(f"{sc}/depth/{c['name']}.png")).astype(float) / 1000.0
        I = np.array(Image.open(f"{sc}/instances/{c['name']}.png")).astype(int)
        pc = (G - T[:3, 3]) @ T[:3, :3]
        z = pc[:, 2]
        ok = z > 0.05
        u = np.where(ok, K["fx"] * pc[:, 0] / np.maximum(z, 1e-6) + K["cx"], -1)
        v = np.where(ok, K["fy"] * pc[:, 1] / np.maximum(z, 1e-6) + K["cy"], -1)
        inside = ok & (u >= 0) & (v >= 0) & (u < K["width"]) & (v < K["height"])
        ui, vi = np.clip(u.astype(int), 0, K["width"] - 1), np.clip(v.astype(int), 0, K["height"] - 1)
        vis.append(inside & (I[vi, ui] == gi) & (np.abs(D[vi, ui] - z) < 0.01 + 0.01 * z))
        inframe.append(inside)
    vis, inframe = np.array(vis), np.array(inframe)
    for k in range(len(cams)):
        others = np.delete(vis, k, axis=0).any(0)
        for o in np.unique(gi):
            m = (gi == o) & inframe[k]
            if o in structure or m.sum() < 30 or vis[k][m].sum() == 0:
                continue
            hid = m & ~vis[k]
            hidden_total += int(hid.sum())
            seen_elsewhere += int((hid & others).sum())
print(f"{scenes} scenes: of {hidden_total} object surface samples one view does not see, "
      f"{seen_elsewhere / hidden_total:.3f} are observed by another view")
