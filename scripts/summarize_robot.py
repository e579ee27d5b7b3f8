#!/usr/bin/env python3
"""Prints the rows of bench/grasp.json or bench/place.json (deocc eval grasp / eval place)."""
import json
import sys

r = json.load(open(sys.argv[1]))
ci = lambda e: "-" if e["mean"] is None else "%.3f [%.3f, %.3f]" % (e["mean"], e["ci95"][0], e["ci95"][1])
if r["benchmark"].startswith("pickup"):
    print(f"{r['benchmark']}: {r['scenes']} scenes, {r['heavy_scenes']} heavy (target < 50% visible)")
    for row in r["rows"]:
        print(f"{row['cloud']:>13}  top-1@0.4 all {ci(row['all']['top1_at_04'])}  heavy {ci(row['heavy']['top1_at_04'])}  "
              f"light {ci(row['light']['top1_at_04'])}  top-1@0.8 {ci(row['all']['top1_at_08'])}  AP {ci(row['all']['ap'])}  "
              f"affordance IoU {ci(row['all']['affordance_iou'])}  vs observed {row['top1_at_04_vs_observed']['difference']:+.3f} "
              f"[{row['top1_at_04_vs_observed']['ci95'][0]:+.3f}, {row['top1_at_04_vs_observed']['ci95'][1]:+.3f}]  "
              f"heavy/GT {row['top1_at_04_over_ground_truth_heavy']:.2f}  {row['mean_seconds_per_scene']:.3f} s/scene (max {row['max_seconds_per_scene']:.3f})")
    if "by_target" in r["rows"][0]:
        kinds = list(r["rows"][0]["by_target"])
        bins = [name for name, _ in r["rows"][0]["by_visibility"]]
        print("top-1@0.4 by target kind and by visibility (scenes):")
        print(f"{'':>15}" + "".join(f"{k:>16}" for k in kinds) + "".join(f"{b:>20}" for b in bins) + f"{'all/GT':>8}")
        for row in r["rows"]:
            cells = [f"{row['by_target'][k]['top1_at_04']['mean']:.2f} ({row['by_target'][k]['scenes']})" for k in kinds]
            vis = ["-" if s["scenes"] == 0 else f"{s['top1_at_04']['mean']:.2f} ({s['scenes']})" for _, s in row["by_visibility"]]
            print(f"{row['cloud']:>15}" + "".join(f"{c:>16}" for c in cells) + "".join(f"{v:>20}" for v in vis)
                  + f"{row['top1_at_04_over_ground_truth']:>8.2f}")
else:
    print(f"{r['benchmark']}: {r['scenes']} scenes, hidden share of the free table top {r['mean_hidden_free_fraction']:.2f}")
    print("whole table top:")
    for row in r["rows"]:
        v = row["iou_vs_optimistic"]
        print(f"{row['map']:>22}  IoU {ci(row['iou'])}  false-placeable {ci(row['false_placeable_rate'])}  "
              f"success {ci(row['success'])}  no placement {row['no_placement']}  IoU vs optimistic {v['difference']:+.3f} [{v['ci95'][0]:+.3f}, {v['ci95'][1]:+.3f}]")
        g = row.get("share_of_ground_truth_gain")
        if g and g["share"] == g["share"]:
            print(f"{'':>22}  share of the ground truth's gain over optimistic {g['share']:.2f} [{g['ci95'][0]:.2f}, {g['ci95'][1]:.2f}]")
    if "iou_behind" in r["rows"][0]:
        print(f"behind the clutter (cells the view does not see, {r['mean_behind_fraction']:.2f} of the table top):")
        for row in r["rows"]:
            v = row["iou_behind_vs_optimistic"]
            print(f"{row['map']:>22}  IoU {ci(row['iou_behind'])}  false-placeable {ci(row['false_placeable_rate_behind'])}  "
                  f"success {ci(row['success_behind'])}  no placement {row['no_placement_behind']}  IoU vs optimistic {v['difference']:+.3f} [{v['ci95'][0]:+.3f}, {v['ci95'][1]:+.3f}]")

# Paired bootstrap over scenes of every completed cloud against each rules row (grasp: top-1 at
# mu 0.4, all and heavy; place: IoU), 2000 resamples, fixed seed.
import random

rows = dict((name, rs) for name, rs in r["per_scene"])
if "rules" in rows:
    rng = random.Random(7)
    key = (lambda x: float(x["top1_at_04"])) if r["benchmark"].startswith("pickup") else (lambda x: x["iou"])
    subsets = [("all", lambda x: True)]
    keys = [("", key)]
    if not r["benchmark"].startswith("pickup") and "iou_behind" in r["rows"][0]:
        keys.append((" behind the clutter", lambda x: x["iou_behind"]))
    if r["benchmark"].startswith("pickup"):
        subsets.append(("heavy", lambda x: x["visible_fraction"] < 0.5))
    baselines = tuple(n for n in rows if n.startswith("rules"))
    for name, rs in rows.items():
        if name in ("observed", "ground_truth", "ground_truth_seen_objects", "observed_optimistic",
                    "observed_conservative") + baselines:
            continue
        for base in baselines:
            if base not in rows:
                continue
            for label, k in keys:
                for sub, keep in subsets:
                    d = [k(a) - k(b) for a, b in zip(rs, rows[base]) if keep(a)]
                    means = sorted(sum(rng.choice(d) for _ in d) / len(d) for _ in range(2000))
                    print(f"{name} vs {base}{label} ({sub}, {len(d)} scenes): {sum(d) / len(d):+.3f} "
                          f"[{means[50]:+.3f}, {means[1949]:+.3f}]")
