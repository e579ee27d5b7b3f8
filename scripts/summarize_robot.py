#!/usr/bin/env python3
"""Prints the rows of bench/grasp.json or bench/place.json (deocc eval grasp / eval place)."""
import json
import sys

r = json.load(open(sys.argv[1]))
ci = lambda e: "%.3f [%.3f, %.3f]" % (e["mean"], e["ci95"][0], e["ci95"][1])
if r["benchmark"].startswith("pickup"):
    print(f"{r['benchmark']}: {r['scenes']} scenes, {r['heavy_scenes']} heavy (target < 50% visible)")
    for row in r["rows"]:
        print(f"{row['cloud']:>13}  top-1@0.4 all {ci(row['all']['top1_at_04'])}  heavy {ci(row['heavy']['top1_at_04'])}  "
              f"light {ci(row['light']['top1_at_04'])}  top-1@0.8 {ci(row['all']['top1_at_08'])}  AP {ci(row['all']['ap'])}  "
              f"affordance IoU {ci(row['all']['affordance_iou'])}  vs observed {row['top1_at_04_vs_observed']['difference']:+.3f} "
              f"[{row['top1_at_04_vs_observed']['ci95'][0]:+.3f}, {row['top1_at_04_vs_observed']['ci95'][1]:+.3f}]  "
              f"heavy/GT {row['top1_at_04_over_ground_truth_heavy']:.2f}  {row['mean_seconds_per_scene']:.3f} s/scene (max {row['max_seconds_per_scene']:.3f})")
else:
    print(f"{r['benchmark']}: {r['scenes']} scenes, hidden share of the free table top {r['mean_hidden_free_fraction']:.2f}")
    for row in r["rows"]:
        v = row["iou_vs_optimistic"]
        print(f"{row['map']:>22}  IoU {ci(row['iou'])}  false-placeable {ci(row['false_placeable_rate'])}  "
              f"success {ci(row['success'])}  no placement {row['no_placement']}  IoU vs optimistic {v['difference']:+.3f} [{v['ci95'][0]:+.3f}, {v['ci95'][1]:+.3f}]")
