#!/usr/bin/env python3
"""Prints the rows of bench/objects.json (deocc eval objects): per-object hidden recall by each
completer's own points, the paired differences against the rules completer (absolute, and
relative to the rules' recall), and the share of generated points on a true surface.

    python3 scripts/summarize_objects.py [A.json] [--against B.json]

With --against, each row both reports have is compared object by object (A minus B, paired,
bootstrap over scenes, 2,000 draws): two runs of the same scenes with other options or weights.
"""
import json
import random
import sys

args = sys.argv[1:]
against = None
if "--against" in args:
    i = args.index("--against")
    if i + 1 >= len(args):
        sys.exit("--against needs a report file")
    against = args[i + 1]
    del args[i:i + 2]


def load(path):
    try:
        with open(path) as f:
            return json.load(f)
    except (OSError, json.JSONDecodeError) as e:
        sys.exit(f"{path}: cannot read the report ({e}); make it with `deocc eval objects --json {path}`")


r = load(args[0] if args else "bench/objects.json")
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


def paired(a, b, scenes, draws=2000, seed=7):
    """Mean of a - b and its 95% bootstrap interval, resampling scenes."""
    by_scene = {}
    for x, y, sc in zip(a, b, scenes):
        by_scene.setdefault(sc, []).append(x - y)
    keys = sorted(by_scene)
    rng = random.Random(seed)
    diff = sum(sum(v) for v in by_scene.values()) / len(a)
    means = []
    for _ in range(draws):
        pick = [by_scene[rng.choice(keys)] for _ in keys]
        n = sum(len(v) for v in pick)
        means.append(sum(sum(v) for v in pick) / n)
    means.sort()
    return diff, means[int(0.025 * draws)], means[int(0.975 * draws) - 1]


if against:
    o = load(against)
    key = lambda obj: (obj["scene_seed"], obj["instance_id"])
    if "objects" not in r or "objects" not in o:
        sys.exit("both reports need per-object recall (made by deocc eval objects since December 2026)")
    if [key(x) for x in r["objects"]] != [key(x) for x in o["objects"]]:
        sys.exit(f"{against}: not the same scored objects (other scenes or segmentation)")
    furniture = [x["furniture"] for x in r["objects"]]
    scenes = [x["scene_seed"] for x in r["objects"]]
    other = {row["completer"]: row for row in o["rows"]}
    print(f"against {against} (A minus B, paired by object, bootstrap over scenes):")
    for row in r["rows"]:
        b = other.get(row["completer"])
        if b is None:
            continue
        for name, keep in (("all", lambda f: True), ("table-top", lambda f: not f), ("furniture", lambda f: f)):
            ks = [i for i, f in enumerate(furniture) if keep(f)]
            if not ks:
                continue
            d, lo, hi = paired([row["hidden_recall_by_object"][i] for i in ks],
                               [b["hidden_recall_by_object"][i] for i in ks], [scenes[i] for i in ks])
            print(f"{row['completer']:>12} {name:>9}: hidden recall {d:+.4f} [{lo:+.4f}, {hi:+.4f}]")
        ga, gb = row["generated"].get("model"), b["generated"].get("model")
        if ga and gb:
            print(f"{'':>12} {'':>9}  GL-DoT points {ga['points']} vs {gb['points']}, "
                  f"within 2 cm {ga['within_2cm']:.3f} vs {gb['within_2cm']:.3f}")
