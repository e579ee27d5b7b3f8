#!/usr/bin/env python3
"""Prints the headline figures of a `deocc eval amodal` report (a reading aid; the JSON is the
record). Usage: summarize_amodal.py REPORT.json"""
import json
import sys


def cmp(x):
    if not x or x.get("method") is None:
        return "n/a"
    lo, hi = x["ci95"]
    fmt = lambda v: "nan" if v is None else f"{v:+.4f}"
    return (f"{x['method']:.4f} vs {x['baseline']:.4f}: {x['difference']:+.4f} "
            f"[{fmt(lo)}, {fmt(hi)}] ({x['items']} pairs, {x['clusters']} objects)")


r = json.load(open(sys.argv[1]))
print(f"{r['split']}: {r['pairs']} pairs, {r['objects']} objects, {r['main_steps']} steps, model {r['model']}")
print(f"mIoU model {r['miou_model']:.4f}, prior {r['miou_prior']:.4f}, rules {r['miou_rules']:.4f}, "
      f"visible {r['miou_visible']:.4f}, hull {r['miou_convex_hull']:.4f}")
print("mask vs prior          ", cmp(r["mask_vs_prior"]))
for k, v in r["by_occlusion"].items():
    print(f"  occlusion {k:8s}     ", cmp(v["model_minus_prior"]))
print("held-out families      ", cmp(r["held_out_families"]["model_minus_prior"]))
print("training cats > 40%    ", cmp(r["training_categories_above_40"]["model_minus_prior"]))
for k, v in sorted(r["by_category"].items()):
    print(f"  {k:12s}          ", cmp(v["model_minus_prior"]))
cl = r["chair_legs"]
print(f"chair legs ({cl['pairs']})        ", cmp(cl["miou"]))
print("  bottom-region IoU    ", cmp(cl["bottom_region_iou"]))
a = r["candidate_auc"]
print(f"candidate AUC: model {a['model']:.3f}, distance to prior {a['distance_to_prior']:.3f} ({a['pixels']} px)")
print("hidden colour (MAE)    ", cmp(r["hidden_colour"]))
for k, v in r["depth"].items():
    if k == "by_category":
        for cat, d in v.items():
            for side, c in d.items():
                print(f"  depth {cat:12s} {side:12s}", cmp(c))
        continue
    print(f"depth {k:22s}", cmp(v))
e = r.get("error_head")
if e:
    for side, f in e.items():
        bins = ", ".join(
            f"<= {b['expected_up_to'] if b['expected_up_to'] is not None else 'inf'}: "
            f"{b['pixels']} px {b['mean_expected']:.3f} / {b['mean_actual']:.3f} ({b['share_large']:.2f} large)"
            for b in f["bins"]
            if b["pixels"]
        )
        print(
            f"error head {side:12s} expected {f['mean_expected']:.3f} / actual {f['mean_actual']:.3f}, "
            f"AUC(large) {f['auc_large']:.3f}; {bins}"
        )
print("cross-view             ", cmp(r.get("cross_view")))
s = r["steps"]
print(f"steps ({s['pairs']} pairs): {s['miou_by_steps']}; main vs most: {cmp(s.get('main_vs_most'))}")
print("thresholds:", r["miou_by_mask_threshold"])
print("speed:", r["speed"])
