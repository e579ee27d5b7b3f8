#!/usr/bin/env python3
"""Chooses the quality gate's limits from `deocc eval objects --tuning` run with the gate off:
for each pair of limits, the share of the completer's generated points on a true surface
(within 2 cm) among the completions the gate keeps, and the share of the true-surface points it
throws away.

    deocc eval objects --tuning --scenes 20 --options bench/gate-off.json \
        --json bench/objects-tuning.json
    python3 scripts/gate_study.py bench/objects-tuning.json [--row gldot]
"""
import argparse
import json


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("report")
    ap.add_argument("--row", default="gldot")
    a = ap.parse_args()
    rep = json.load(open(a.report))
    row = next(r for r in rep["rows"] if r["completer"] == a.row)
    study = [s for s in row["gate_study"] if s["points"] > 0]
    total = sum(s["points"] for s in study)
    good = sum(s["points"] * s["within_2cm"] for s in study)
    print(f"{a.row}: {len(study)} completed instances, {total} generated points, "
          f"{100 * good / max(total, 1):.1f}% within 2 cm with no gate")
    print(f"{'min conf':>8} {'max s-thr':>9} {'kept inst':>9} {'kept pts':>8} "
          f"{'within 2cm':>10} {'good lost':>9}")
    for c in [0.0, 0.3, 0.4, 0.5, 0.6, 0.7]:
        for x in [1.0, 0.75, 0.5, 0.3, 0.2]:
            kept = [s for s in study
                    if s["mean_confidence"] >= c and s["seen_through_fraction"] <= x]
            kp = sum(s["points"] for s in kept)
            kg = sum(s["points"] * s["within_2cm"] for s in kept)
            print(f"{c:8.2f} {x:9.2f} {len(kept):9d} {kp:8d} "
                  f"{100 * kg / max(kp, 1):9.1f}% {100 * (good - kg) / max(good, 1):8.1f}%")


if __name__ == "__main__":
    main()
