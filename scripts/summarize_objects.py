#!/usr/bin/env python3
"""Prints the rows of bench/objects.json (deocc eval objects): per-object hidden recall by each
completer's own points, the paired differences against the rules completer (absolute, and
relative to the rules' recall), and the share of generated points on a true surface."""
import json
import sys

r = json.load(open(sys.argv[1] if len(sys.argv) > 1 else "bench/objects.json"))
print(f"{r['benchmark']}: {r['scenes']} scenes, segmenter {r['segmenter']}")
for row in r["rows"]:
    gen = ", ".join(f"{k} {v['points']} points {v['within_2cm']:.3f} within 2 cm" for k, v in row["generated"].items())
    print(f"{row['completer']:>12}  {row['objects']} objects  hidden recall {row['hidden_recall']:.3f} "
          f"(table-top {row['hidden_recall_tabletop']:.3f}, furniture {row['hidden_recall_furniture']:.3f})  "
          f"completeness {row['hidden_completeness_m'] * 100:.2f} cm  {row['objects_per_second']:.1f} objects/s  [{gen}]")
    if row.get("points_uncertain_dropped"):
        print(f"              points left out as expected too far off: {row['points_uncertain_dropped']}")
    by = row.get("model_by_category", {})
    if by:
        print("              GL-DoT points by object: " + ", ".join(
            f"{k} {v['points']} ({v['within_2cm']:.2f})" for k, v in sorted(by.items(), key=lambda kv: -kv[1]["points"])))
    dist = row.get("model_by_distance", [])
    if sum(b["points"] for b in dist):
        total = sum(b["points"] for b in dist)
        edges = [b["distance_up_to_m"] for b in dist]
        names = [f"<= {e * 100:.0f} cm" if e is not None else "farther" for e in edges]
        print("              GL-DoT points by distance to a true surface: " + ", ".join(
            f"{n} {b['points'] / total:.2f}" for n, b in zip(names, dist)))
    widths = row.get("model_by_crop_width", [])
    if sum(b["points"] for b in widths):
        print("              GL-DoT points by widest crop: " + ", ".join(
            (f"<= {b['crop_width_up_to_m']:.2f} m" if b["crop_width_up_to_m"] is not None else "wider")
            + f" {b['instances']} instances {b['points']} points ({b['within_2cm']:.2f})" for b in widths))
for group in ("", "_tabletop", "_furniture"):
    for name, c in r[f"recall_vs_rules{group}"].items():
        rel = lambda x: x / c["baseline"] if c["baseline"] else float("nan")
        print(f"{name} vs rules{group or ' (all)'}: {c['method']:.3f} vs {c['baseline']:.3f}, "
              f"{c['difference']:+.3f} [{c['ci95'][0]:+.3f}, {c['ci95'][1]:+.3f}] "
              f"= {rel(c['difference']):+.1%} [{rel(c['ci95'][0]):+.1%}, {rel(c['ci95'][1]):+.1%}] of the rules' recall")
