//! Perception figures on benchmark scenes: occlusion detection against the benchmark's definition,
//! and cross-view grouping (adjusted Rand index) with the adaptive threshold and fixed ones.

use deocc_io::images::InstanceMap;
use deocc_pipeline::matching::{match_masks, MaskCentroid, Threshold};
use deocc_pipeline::occlusion::analyse_view_with;
use deocc_synth::dataset::RenderedScene;
use deocc_synth::shapes::Category;
use serde::Serialize;

#[derive(Debug, Clone, Default, Serialize)]
pub struct DetectionCounts {
    pub true_positive: usize,
    pub false_positive: usize,
    pub false_negative: usize,
    pub true_negative: usize,
}

impl DetectionCounts {
    pub fn precision(&self) -> f64 {
        self.true_positive as f64 / (self.true_positive + self.false_positive).max(1) as f64
    }
    pub fn recall(&self) -> f64 {
        self.true_positive as f64 / (self.true_positive + self.false_negative).max(1) as f64
    }
    pub fn f1(&self) -> f64 {
        let (p, r) = (self.precision(), self.recall());
        if p + r > 0.0 {
            2.0 * p * r / (p + r)
        } else {
            0.0
        }
    }
}

/// Occlusion detection with ground-truth masks in every view of a scene (room structure and
/// masks cut by the image border excluded; masks under 50 px excluded).
pub fn occlusion_counts(
    r: &RenderedScene,
    o: &deocc_pipeline::occlusion::OcclusionOptions,
    counts: &mut DetectionCounts,
) {
    let structure: Vec<u16> = r.scene.structure_ids();
    for view in &r.views {
        let map = InstanceMap {
            width: view.frame.width,
            height: view.frame.height,
            ids: view.frame.instance.clone(),
        };
        let found = analyse_view_with(&map, &view.depth, o);
        for vis in &view.visibility {
            if structure.contains(&vis.instance_id) || vis.truncated || vis.visible_px < 50 {
                continue;
            }
            let predicted = found
                .iter()
                .any(|m| m.instance_id == vis.instance_id && m.is_occluded());
            match (predicted, vis.is_occluded()) {
                (true, true) => counts.true_positive += 1,
                (true, false) => counts.false_positive += 1,
                (false, true) => counts.false_negative += 1,
                (false, false) => counts.true_negative += 1,
            }
        }
    }
}

/// Every non-structure mask of every view with its centroid and true instance id.
pub fn scene_masks(r: &RenderedScene) -> (Vec<MaskCentroid>, Vec<usize>, Vec<Category>) {
    let mut masks = Vec::new();
    let mut truth = Vec::new();
    let mut cats = Vec::new();
    for (v, view) in r.views.iter().enumerate() {
        let w = view.frame.width as usize;
        for obj in &r.scene.objects {
            if obj.category.is_structure() {
                continue;
            }
            let pts: Vec<_> = view
                .frame
                .instance
                .iter()
                .enumerate()
                .filter(|(i, &id)| id == obj.instance_id && view.depth.data()[*i] > 0.0)
                .map(|(i, _)| {
                    view.camera.unproject_pixel(
                        (i % w) as u32,
                        (i / w) as u32,
                        view.depth.data()[i],
                    )
                })
                .collect();
            if pts.len() < 50 {
                continue;
            }
            let Some(c) = deocc_geometry::cloud::centroid(&pts) else {
                continue;
            };
            masks.push(MaskCentroid {
                view: v,
                local_id: obj.instance_id,
                centroid: c,
                points: pts.len(),
            });
            truth.push(obj.instance_id as usize);
            cats.push(obj.category);
        }
    }
    (masks, truth, cats)
}

#[derive(Debug, Clone, Serialize)]
pub struct GroupingFigures {
    pub threshold: String,
    pub ari_mean: f64,
    /// ARI over chair masks only (hollow backs fragment masks and shift centroids).
    pub ari_chairs_mean: f64,
    pub tau_mean_m: f64,
}

/// ARI of the grouping of one scene's masks, and of its chairs alone.
pub fn grouping(r: &RenderedScene, threshold: Threshold) -> (f64, Option<f64>, f32) {
    let (masks, truth, cats) = scene_masks(r);
    let m = match_masks(&masks, threshold);
    let ari = adjusted_rand_index(&m.group, &truth);
    let chairs: Vec<usize> = (0..masks.len())
        .filter(|&i| cats[i] == Category::Chair)
        .collect();
    let chair_ari = (chairs.len() >= 2).then(|| {
        let a: Vec<usize> = chairs.iter().map(|&i| m.group[i]).collect();
        let b: Vec<usize> = chairs.iter().map(|&i| truth[i]).collect();
        adjusted_rand_index(&a, &b)
    });
    (ari, chair_ari, m.tau_m)
}

/// Default-segmenter mIoU of one scene's views against the ground-truth instance maps, and
/// occlusion detection run on the segmenter's masks (a predicted mask is scored by the ground-truth
/// instance it overlaps most).
/// Adds to `ious` the matched IoU of every ground-truth instance (>= 50 px) of every view.
pub fn segmenter_figures(
    r: &RenderedScene,
    seg: &deocc_pipeline::segment::ConvexitySegmenter,
    o: &deocc_pipeline::occlusion::OcclusionOptions,
    counts: &mut DetectionCounts,
    ious: &mut SegmenterIous,
) {
    ious.scenes += 1;
    let structure: Vec<u16> = r.scene.structure_ids();
    for view in &r.views {
        let truth = InstanceMap {
            width: view.frame.width,
            height: view.frame.height,
            ids: view.frame.instance.clone(),
        };
        let pred = seg.segment_rgbd(&view.depth, Some(&view.rgb), &view.camera);
        for (t, iou) in matched_ious(&pred, &truth, 50, &[]) {
            let category = r
                .scene
                .objects
                .iter()
                .find(|o| o.instance_id == t)
                .map_or("unknown", |o| o.category.name());
            ious.add(category, iou, structure.contains(&t));
        }
        for (_, l) in segment_losses(&pred, &truth, view.depth.data(), 50, &structure) {
            ious.add_losses(&l);
        }
        // Occlusion on predicted masks, judged by the majority ground-truth instance of each.
        let found = analyse_view_with(&pred, &view.depth, o);
        let mut majority: std::collections::HashMap<u16, std::collections::HashMap<u16, usize>> =
            Default::default();
        for (&p, &t) in pred.ids.iter().zip(&truth.ids) {
            if p != 0 {
                *majority.entry(p).or_default().entry(t).or_default() += 1;
            }
        }
        for m in &found {
            let Some(t) = majority
                .get(&m.instance_id)
                .and_then(|c| c.iter().max_by_key(|(_, &k)| k).map(|(&t, _)| t))
            else {
                continue;
            };
            let Some(vis) = view.visibility.iter().find(|v| v.instance_id == t) else {
                continue;
            };
            if structure.contains(&t) || t == 0 || vis.truncated || m.truncated || m.visible_px < 50
            {
                continue;
            }
            match (m.is_occluded(), vis.is_occluded()) {
                (true, true) => counts.true_positive += 1,
                (true, false) => counts.false_positive += 1,
                (false, true) => counts.false_negative += 1,
                (false, false) => counts.true_negative += 1,
            }
        }
    }
}

/// Matched IoUs of the segmenter, pooled over views and scenes, per category.
#[derive(Debug, Clone, Default)]
pub struct SegmenterIous {
    /// category -> (sum of IoU, count)
    pub by_category: std::collections::BTreeMap<String, (f64, usize)>,
    objects: (f64, usize),
    all: (f64, usize),
    /// Sum of the objects' [`SegmentLosses`] (floor and walls excluded) and their count.
    losses: (SegmentLosses, usize),
    /// Each object's IoU with the scene it belongs to, for the interval over scenes.
    object_ious: Vec<(u32, f64)>,
    /// Scenes seen so far ([`segmenter_figures`] counts them).
    scenes: u32,
}

impl SegmenterIous {
    pub fn add(&mut self, category: &str, iou: f64, structure: bool) {
        let c = self.by_category.entry(category.to_string()).or_default();
        c.0 += iou;
        c.1 += 1;
        if !structure {
            self.objects.0 += iou;
            self.objects.1 += 1;
            self.object_ious.push((self.scenes, iou));
        }
        self.all.0 += iou;
        self.all.1 += 1;
    }
    pub fn add_losses(&mut self, l: &SegmentLosses) {
        let s = &mut self.losses.0;
        s.hit += l.hit;
        s.split += l.split;
        s.unlabelled_with_depth += l.unlabelled_with_depth;
        s.without_depth += l.without_depth;
        s.spill += l.spill;
        self.losses.1 += 1;
    }
    /// Mean [`SegmentLosses`] over object instances (floor and walls excluded).
    pub fn mean_losses(&self) -> SegmentLosses {
        let (s, n) = self.losses;
        let n = n.max(1) as f64;
        SegmentLosses {
            hit: s.hit / n,
            split: s.split / n,
            unlabelled_with_depth: s.unlabelled_with_depth / n,
            without_depth: s.without_depth / n,
            spill: s.spill / n,
        }
    }
    /// Mean over object instances (floor and walls excluded).
    pub fn miou_objects(&self) -> f64 {
        self.objects.0 / self.objects.1.max(1) as f64
    }
    /// The 95% interval of [`SegmenterIous::miou_objects`] from a bootstrap over scenes.
    pub fn miou_objects_ci95(&self) -> [f64; 2] {
        let (clusters, ious): (Vec<u32>, Vec<f64>) = self.object_ious.iter().copied().unzip();
        let zero = vec![0.0; ious.len()];
        crate::stats::compare(&ious, &zero, &clusters, 2000, 11).ci95
    }
    /// Mean over every instance, floor and walls included.
    pub fn miou_all(&self) -> f64 {
        self.all.0 / self.all.1.max(1) as f64
    }
    pub fn per_category(&self) -> std::collections::BTreeMap<String, f64> {
        self.by_category
            .iter()
            .map(|(k, &(s, n))| (k.clone(), s / n.max(1) as f64))
            .collect()
    }
}

/// The named failure case on its own scenes (`chairs-v1`: hollow-back chairs).
#[derive(Debug, Clone, serde::Serialize)]
pub struct FailureCaseFigures {
    pub benchmark: String,
    pub scenes: usize,
    /// Grouping of chair masks (ground-truth masks), adaptive tau and the fixed 5 cm one.
    pub grouping_ari_chairs: f64,
    grouping_ari_chairs_fixed_0_05: f64,
    /// Default segmenter: mIoU of chairs and of every object.
    pub segmenter_miou_chairs: f64,
    pub segmenter_miou: f64,
}

#[derive(Debug, Clone, serde::Serialize)]
pub struct PerceptionReport {
    pub benchmark: String,
    pub scenes: usize,
    /// Whether the views' depth went through the depth front end first (as in the pipeline).
    pub depth_clean: bool,
    pub occlusion_precision: f64,
    pub occlusion_recall: f64,
    occlusion_f1: f64,
    pub occlusion_counts: DetectionCounts,
    /// Grouping with the adaptive threshold (the default).
    pub grouping_ari: f64,
    pub grouping_ari_chairs: f64,
    pub grouping_ablation: Vec<GroupingFigures>,
    /// Default RGB-D segmenter: mean IoU of ground-truth object instances (>= 50 px, room
    /// structure excluded) with their best segment, and occlusion detection on its masks.
    pub segmenter_miou: f64,
    /// Its 95% interval, bootstrap over scenes.
    pub segmenter_miou_ci95: [f64; 2],
    /// The same including floor and walls (split by whatever stands on them).
    pub segmenter_miou_with_structure: f64,
    pub segmenter_occlusion_precision: f64,
    pub segmenter_occlusion_recall: f64,
    segmenter_occlusion_f1: f64,
    pub segmenter_views_per_second: f64,
    /// Segmenter mIoU per category (floor and walls included).
    pub segmenter_miou_by_category: std::collections::BTreeMap<String, f64>,
    /// Where the objects' pixels went in the segmenter's maps (means over objects): in the best
    /// segment, in other segments, unlabelled, without depth, and the best segment's share
    /// outside the object.
    pub segmenter_losses: SegmentLosses,
    pub hollow_back_chairs: Option<FailureCaseFigures>,
}

fn failure_case(
    scenes: usize,
    sensor: deocc_synth::sensor::SensorKind,
    clean: &deocc_pipeline::depth_clean::DepthCleanOptions,
    segmenter: &deocc_pipeline::segment::ConvexitySegmenter,
    occlusion: &deocc_pipeline::occlusion::OcclusionOptions,
    tick: &mut dyn FnMut(),
) -> Result<FailureCaseFigures, crate::EvalError> {
    use deocc_pipeline::matching::Threshold;
    let mut preset = deocc_synth::dataset::chairs_v1();
    crate::with_sensor(&mut preset, sensor);
    preset.config.gt_points_per_m2 = 10.0;
    let n = scenes.min(preset.seeds.len());
    let mut ious = SegmenterIous::default();
    let mut counts = DetectionCounts::default();
    let (mut adaptive, mut fixed, mut k) = (0.0, 0.0, 0usize);
    for &seed in &preset.seeds[..n] {
        let mut r = deocc_synth::dataset::render_full_scene(&preset.config, seed)?;
        crate::clean_views(&mut r, clean);
        segmenter_figures(&r, segmenter, occlusion, &mut counts, &mut ious);
        if let (Some(a), Some(f)) = (
            grouping(&r, Threshold::Adaptive).1,
            grouping(&r, Threshold::Fixed(0.05)).1,
        ) {
            adaptive += a;
            fixed += f;
            k += 1;
        }
        tick();
    }
    Ok(FailureCaseFigures {
        benchmark: preset.name,
        scenes: n,
        grouping_ari_chairs: adaptive / k.max(1) as f64,
        grouping_ari_chairs_fixed_0_05: fixed / k.max(1) as f64,
        segmenter_miou_chairs: ious
            .per_category()
            .get("chair")
            .copied()
            .unwrap_or(f64::NAN),
        segmenter_miou: ious.miou_objects(),
    })
}

/// `deocc eval perception`: occlusion detection and grouping on the first `scenes` bench-v1
/// scenes, the segmenter (the default one unless a study changes it), and the hollow-back chairs
/// on `failure_scenes` chairs-v1 scenes.
#[allow(clippy::too_many_arguments)]
pub fn perception_benchmark(
    scenes: usize,
    failure_scenes: usize,
    sensor: deocc_synth::sensor::SensorKind,
    clean: &deocc_pipeline::depth_clean::DepthCleanOptions,
    segmenter: &deocc_pipeline::segment::ConvexitySegmenter,
    occlusion: &deocc_pipeline::occlusion::OcclusionOptions,
    tuning: bool,
    tick: &mut dyn FnMut(),
) -> Result<PerceptionReport, crate::EvalError> {
    use deocc_pipeline::matching::Threshold;
    let mut preset = deocc_synth::dataset::bench_v1();
    crate::with_sensor(&mut preset, sensor);
    if tuning {
        // bench-v1-like scenes of other seeds (as `eval objects --tuning`): where settings are
        // chosen, never the test scenes.
        preset.name = format!("{} tuning scenes", preset.name);
        preset.seeds = (9_050_000..9_050_000 + preset.seeds.len() as u64).collect();
    }
    preset.config.gt_points_per_m2 = 10.0; // ground truth is not used here
    let n = scenes.min(preset.seeds.len());
    let thresholds = [
        ("adaptive".to_string(), Threshold::Adaptive),
        ("fixed 0.05 m".into(), Threshold::Fixed(0.05)),
        ("fixed 0.15 m".into(), Threshold::Fixed(0.15)),
        ("fixed 0.50 m".into(), Threshold::Fixed(0.5)),
    ];
    let mut counts = DetectionCounts::default();
    let mut seg_counts = DetectionCounts::default();
    let mut seg_ious = SegmenterIous::default();
    let (mut seg_time, mut seg_views) = (0.0f64, 0usize);
    let mut sums = vec![(0.0f64, 0.0f64, 0usize, 0.0f64); thresholds.len()];
    for &seed in &preset.seeds[..n] {
        let mut r = deocc_synth::dataset::render_full_scene(&preset.config, seed)?;
        crate::clean_views(&mut r, clean);
        occlusion_counts(&r, occlusion, &mut counts);
        let t0 = std::time::Instant::now();
        segmenter_figures(&r, segmenter, occlusion, &mut seg_counts, &mut seg_ious);
        seg_time += t0.elapsed().as_secs_f64();
        seg_views += r.views.len();
        for (k, (_, t)) in thresholds.iter().enumerate() {
            let (ari, chairs, tau) = grouping(&r, *t);
            sums[k].0 += ari;
            if let Some(c) = chairs {
                sums[k].1 += c;
                sums[k].2 += 1;
            }
            sums[k].3 += tau as f64;
        }
        tick();
    }
    let ablation: Vec<GroupingFigures> = thresholds
        .iter()
        .zip(&sums)
        .map(|((name, _), s)| GroupingFigures {
            threshold: name.clone(),
            ari_mean: s.0 / n as f64,
            ari_chairs_mean: s.1 / s.2.max(1) as f64,
            tau_mean_m: s.3 / n as f64,
        })
        .collect();
    let report = PerceptionReport {
        benchmark: preset.name.clone(),
        scenes: n,
        depth_clean: clean.enabled,
        occlusion_precision: counts.precision(),
        occlusion_recall: counts.recall(),
        occlusion_f1: counts.f1(),
        occlusion_counts: counts,
        grouping_ari: ablation[0].ari_mean,
        grouping_ari_chairs: ablation[0].ari_chairs_mean,
        grouping_ablation: ablation,
        segmenter_miou: seg_ious.miou_objects(),
        segmenter_miou_ci95: seg_ious.miou_objects_ci95(),
        segmenter_miou_with_structure: seg_ious.miou_all(),
        segmenter_occlusion_precision: seg_counts.precision(),
        segmenter_occlusion_recall: seg_counts.recall(),
        segmenter_occlusion_f1: seg_counts.f1(),
        // Includes the occlusion analysis and scoring: a lower bound on the segmenter alone.
        segmenter_views_per_second: seg_views as f64 / seg_time.max(1e-9),
        segmenter_miou_by_category: seg_ious.per_category(),
        segmenter_losses: seg_ious.mean_losses(),
        hollow_back_chairs: (failure_scenes > 0)
            .then(|| failure_case(failure_scenes, sensor, clean, segmenter, occlusion, tick))
            .transpose()?,
    };
    Ok(report)
}

/// Adjusted Rand index between two labelings of the same items (1 = identical partitions).
pub fn adjusted_rand_index(a: &[usize], b: &[usize]) -> f64 {
    use std::collections::HashMap;
    let n = a.len() as f64;
    let mut table: HashMap<(usize, usize), f64> = HashMap::new();
    let mut ra: HashMap<usize, f64> = HashMap::new();
    let mut rb: HashMap<usize, f64> = HashMap::new();
    for (&x, &y) in a.iter().zip(b) {
        *table.entry((x, y)).or_default() += 1.0;
        *ra.entry(x).or_default() += 1.0;
        *rb.entry(y).or_default() += 1.0;
    }
    let c2 = |x: f64| x * (x - 1.0) / 2.0;
    let index: f64 = table.values().map(|&v| c2(v)).sum();
    let sa: f64 = ra.values().map(|&v| c2(v)).sum();
    let sb: f64 = rb.values().map(|&v| c2(v)).sum();
    let expected = sa * sb / c2(n).max(1e-12);
    let max = (sa + sb) / 2.0;
    if (max - expected).abs() < 1e-12 {
        1.0
    } else {
        (index - expected) / (max - expected)
    }
}

/// Matches every ground-truth instance to its best-overlapping segment; returns (instance id,
/// IoU) for the ground-truth instances with at least `min_px` visible pixels, not in `skip`.
pub fn matched_ious(
    predicted: &InstanceMap,
    truth: &InstanceMap,
    min_px: usize,
    skip: &[u16],
) -> Vec<(u16, f64)> {
    use std::collections::HashMap;
    let mut inter: HashMap<(u16, u16), usize> = HashMap::new();
    let mut area_t: HashMap<u16, usize> = HashMap::new();
    let mut area_p: HashMap<u16, usize> = HashMap::new();
    for (&t, &p) in truth.ids.iter().zip(&predicted.ids) {
        if t != 0 {
            *area_t.entry(t).or_default() += 1;
        }
        if p != 0 {
            *area_p.entry(p).or_default() += 1;
        }
        if t != 0 && p != 0 {
            *inter.entry((t, p)).or_default() += 1;
        }
    }
    let mut best: HashMap<u16, f64> = HashMap::new();
    for (&(t, p), &i) in &inter {
        let iou = i as f64 / (area_t[&t] + area_p[&p] - i) as f64;
        let b = best.entry(t).or_default();
        *b = b.max(iou);
    }
    let mut out: Vec<(u16, f64)> = area_t
        .iter()
        .filter(|(t, &a)| a >= min_px && !skip.contains(t))
        .map(|(&t, _)| (t, best.get(&t).copied().unwrap_or(0.0)))
        .collect();
    out.sort_by_key(|&(t, _)| t);
    out
}

/// Where an object's pixels went in a segmenter's map, as shares of its true visible mask
/// (`hit + split + unlabelled_with_depth + without_depth = 1`), and how much of its best segment
/// lies outside it (`spill`): what separates a low IoU caused by cutting (split), by leaving
/// pixels out (unlabelled, or no depth: a sensor's holes) and by merging (spill).
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct SegmentLosses {
    pub hit: f64,
    pub split: f64,
    pub unlabelled_with_depth: f64,
    pub without_depth: f64,
    pub spill: f64,
}

/// [`SegmentLosses`] of every true instance of at least `min_px` pixels not in `skip`, by id.
pub fn segment_losses(
    predicted: &InstanceMap,
    truth: &InstanceMap,
    depth: &[f32],
    min_px: usize,
    skip: &[u16],
) -> Vec<(u16, SegmentLosses)> {
    use std::collections::HashMap;
    let mut inter: HashMap<(u16, u16), usize> = HashMap::new();
    let mut area_t: HashMap<u16, usize> = HashMap::new();
    let mut area_p: HashMap<u16, usize> = HashMap::new();
    let mut unlabelled: HashMap<u16, (usize, usize)> = HashMap::new();
    for ((&t, &p), &z) in truth.ids.iter().zip(&predicted.ids).zip(depth) {
        if t != 0 {
            *area_t.entry(t).or_default() += 1;
            if p == 0 {
                let u = unlabelled.entry(t).or_default();
                if z > 0.0 {
                    u.0 += 1;
                } else {
                    u.1 += 1;
                }
            }
        }
        if p != 0 {
            *area_p.entry(p).or_default() += 1;
            if t != 0 {
                *inter.entry((t, p)).or_default() += 1;
            }
        }
    }
    let mut out: Vec<(u16, SegmentLosses)> = area_t
        .iter()
        .filter(|(t, &a)| a >= min_px && !skip.contains(t))
        .map(|(&t, &a)| {
            let mut best: Option<(f64, u16, usize)> = None;
            let mut labelled = 0;
            for (&(tt, p), &i) in &inter {
                if tt != t {
                    continue;
                }
                labelled += i;
                let iou = i as f64 / (a + area_p[&p] - i) as f64;
                if best.is_none_or(|b| iou > b.0) {
                    best = Some((iou, p, i));
                }
            }
            let (u, n) = unlabelled.get(&t).copied().unwrap_or_default();
            let a = a as f64;
            let (hit, spill) = best.map_or((0.0, 0.0), |(_, p, i)| {
                (i as f64 / a, 1.0 - i as f64 / area_p[&p] as f64)
            });
            let l = SegmentLosses {
                hit,
                split: labelled as f64 / a - hit,
                unlabelled_with_depth: u as f64 / a,
                without_depth: n as f64 / a,
                spill,
            };
            (t, l)
        })
        .collect();
    out.sort_by_key(|&(t, _)| t);
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Point3;

    #[test]
    fn segment_losses_account_for_every_pixel() {
        // One true object of 8 pixels: 4 in segment 1 (which also covers 4 background pixels),
        // 2 in segment 2, 1 unlabelled with depth, 1 without depth.
        let truth = InstanceMap {
            width: 4,
            height: 4,
            ids: vec![5, 5, 5, 5, 5, 5, 5, 5, 0, 0, 0, 0, 0, 0, 0, 0],
        };
        let pred = InstanceMap {
            width: 4,
            height: 4,
            ids: vec![1, 1, 1, 1, 2, 2, 0, 0, 1, 1, 1, 1, 0, 0, 0, 0],
        };
        let mut depth = vec![1.0; 16];
        depth[7] = 0.0;
        let l = segment_losses(&pred, &truth, &depth, 1, &[]);
        assert_eq!(l.len(), 1);
        let (t, l) = l[0];
        assert_eq!(t, 5);
        assert_eq!(
            l,
            SegmentLosses {
                hit: 0.5,
                split: 0.25,
                unlabelled_with_depth: 0.125,
                without_depth: 0.125,
                spill: 0.5,
            }
        );
    }

    #[test]
    fn ari_of_known_partitions() {
        assert!((adjusted_rand_index(&[0, 0, 1, 1], &[5, 5, 7, 7]) - 1.0).abs() < 1e-12);
        assert!(adjusted_rand_index(&[0, 0, 1, 1], &[0, 1, 0, 1]) < 0.0);
    }

    #[test]
    fn matching_groups_nearby_centroids_across_views() {
        let objs = [
            Point3::new(0.0f32, 0.0, 0.8),
            Point3::new(0.3, 0.0, 0.8),
            Point3::new(0.0, 0.4, 0.8),
        ];
        let mut masks = Vec::new();
        for view in 0..4 {
            for (k, o) in objs.iter().enumerate() {
                // Partial views shift the centroid by a couple of centimetres.
                let jitter = nalgebra::Vector3::new(0.01 * view as f32, -0.008 * k as f32, 0.005);
                masks.push(MaskCentroid {
                    view,
                    local_id: k as u16 + 1,
                    centroid: o + jitter,
                    points: 100,
                });
            }
        }
        let m = match_masks(&masks, Threshold::Adaptive);
        let truth: Vec<usize> = masks.iter().map(|m| m.local_id as usize).collect();
        assert_eq!(
            adjusted_rand_index(&m.group, &truth),
            1.0,
            "tau {}",
            m.tau_m
        );
        // A threshold far too small splits every object into its views.
        let tiny = match_masks(&masks, Threshold::Fixed(0.001));
        assert_eq!(tiny.groups, masks.len());
    }
}
