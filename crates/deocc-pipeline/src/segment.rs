//! Instance segmentation behind a trait ([`Segmenter`]): the default RGB-D segmenter here needs no
//! weights; masks given with the input need no segmenter ([`crate::instances`]).
//!
//! The default segmenter grows regions over the pixel grid by local convexity (the criterion of
//! LCCP, Stein et al. 2014, applied to neighbouring pixels): two neighbouring pixels belong to the
//! same segment when their depths are continuous and the surface between them is flat or convex
//! (normals turning away from each other, as on the edge of a box). Depth jumps separate objects
//! from what is behind them; concave creases separate an object from the table it stands on, a
//! table from the floor, the floor from the walls. Support planes therefore come out as segments of
//! their own.
//!
//! Parts of one object also meet at concave creases (a table's legs under its top, a shelf's boards
//! between its sides), so a second stage merges touching segments back together, guided by gravity:
//! two segments that touch (no depth jump across their shared boundary) are one object unless one
//! *rests on* the other, that is, the contact lies at the bottom of one and on an upward-facing
//! surface of the other (a mug on a table, a table's legs on the floor). A table's legs meet the
//! top at its rim or underside, which faces sideways or down, so they join the top. Merges stop at
//! `max_object_extent_m` so that rooms (floor, walls) never merge. Known weakness, measured by
//! `deocc eval perception`: a chair's back stands on its seat and stays a segment of its own.

use deocc_geometry::camera::Camera;
use deocc_geometry::noise::DepthNoise;
use deocc_geometry::DepthMap;
use deocc_io::images::InstanceMap;
use deocc_io::scene::Frame;
use nalgebra::{Point3, Vector3};
use std::collections::HashMap;

use crate::PipelineError;

/// Turns an RGB-D frame into an instance map whose ids are local to the frame (0 = background);
/// [`crate::instances::ensure_instances`] matches them across views. A learned segmenter loading
/// weights from a path the user gives plugs in here.
pub trait Segmenter: Send + Sync {
    fn segment(&self, frame: &Frame) -> Result<InstanceMap, PipelineError>;
}

/// The default RGB-D segmenter (see the module docs). Concave bends gentler than `smooth_deg`
/// count as curvature (the inside of a bowl), not as a crease.
#[derive(Debug, Clone)]
pub struct ConvexitySegmenter {
    /// Depth continuity: neighbours closer than `abs + rel * z` in depth are continuous.
    pub depth_abs_m: f32,
    pub depth_rel: f32,
    /// Surface continuity: the tangent plane of each of two neighbours predicts the other's depth
    /// within `step_abs_m + step_rel * z`. Catches the small depth steps the plain test lets
    /// through: a box's top face and the table top seen just behind it are parallel and a few
    /// centimetres apart in depth, but not one surface.
    pub step_abs_m: f32,
    pub step_rel: f32,
    /// Normals are estimated from neighbours this many pixels away (noise against detail); next
    /// to missing depth, from the farthest measured neighbour up to that far on each side.
    pub normal_step: usize,
    /// Tolerance of the concavity test, `(n_i - n_j) . (p_i - p_j) >= -tol * |p_i - p_j|`: absorbs
    /// normal noise on flat surfaces; a crease smoothed over a few pixels still fails it.
    pub concave_tolerance: f32,
    /// Concave bends gentler than this (degrees, between the normals `crease_reach` pixels either
    /// side) are curvature, not a crease between two objects.
    pub smooth_deg: f32,
    /// Creases are judged from normals this many pixels away on either side.
    pub crease_reach: usize,
    /// Segments smaller than this (pixels) are dropped (id 0).
    pub min_segment_px: usize,
    /// Unlabelled pixels join a neighbouring segment up to this many pixels deep.
    pub fill_passes: usize,
    /// Gravity in the world frame points along `-up_world` (z-up, as in ROS REP-103 and the
    /// benchmark).
    pub up_world: Vector3<f32>,
    /// Touching: neighbouring pixels of two segments closer than `contact_abs_m + contact_rel * z`.
    pub contact_abs_m: f32,
    pub contact_rel: f32,
    /// A contact within this height of a segment's lowest point is at its bottom.
    pub rest_height_m: f32,
    /// A segment whose top is at most this far under another's bottom, inside its footprint and
    /// hidden by it, hangs under it (legs under a table top, seen from above).
    pub hang_gap_m: f32,
    /// Merged objects never grow beyond this box diagonal (metres).
    pub max_object_extent_m: f32,
    /// Two segments touch when they share at least this many neighbouring pixel pairs.
    pub min_contact_px: usize,
    /// The depth tolerances grow by this many times the frame's own depth noise above its
    /// 0.5 mm floor ([`DepthNoise::estimate`], at each pixel's depth), so that the same settings
    /// hold on exact depth and on a real sensor's; 0 = fixed tolerances only.
    pub noise_sigmas: f32,
    /// Pixels without depth (a projector's shadow, dropped edges, dark or grazing surfaces) take
    /// the label of the measured pixel within [`ConvexitySegmenter::hole_radius_px`] that is
    /// closest in colour (L1 over RGB, 0-765) plus [`ConvexitySegmenter::hole_step_cost`] per
    /// pixel of distance, if that cost is at most this: a shadow on the surface behind an edge has
    /// that surface's colour, not the occluder's, and on a textured surface one of its nearby
    /// colours. Needs RGB. **Off (0) by default**: with 10 (tuned on the tuning scenes under the
    /// structured-light model) the masks gain (object mIoU 0.583 -> 0.616) but the completion
    /// downstream loses (objects-only hidden-region gain +7.7% -> +1.2%, docs/decisions.md):
    /// use it where the masks themselves are the product.
    pub hole_max_cost: f32,
    /// The cost of one pixel of distance: prefers the nearer of two sources of the same colour.
    pub hole_step_cost: f32,
    /// How far (pixels) a hole pixel looks for measured pixels.
    pub hole_radius_px: usize,
}

impl Default for ConvexitySegmenter {
    fn default() -> Self {
        Self {
            depth_abs_m: 0.01,
            depth_rel: 0.02,
            step_abs_m: 0.002,
            step_rel: 0.0015,
            normal_step: 2,
            concave_tolerance: 0.15,
            smooth_deg: 12.0,
            crease_reach: 3,
            min_segment_px: 80,
            fill_passes: 3,
            up_world: Vector3::z(),
            contact_abs_m: 0.01,
            contact_rel: 0.01,
            rest_height_m: 0.03,
            hang_gap_m: 0.15,
            max_object_extent_m: 2.2,
            min_contact_px: 4,
            noise_sigmas: 3.0,
            hole_max_cost: 0.0,
            hole_step_cost: 4.0,
            hole_radius_px: 3,
        }
    }
}

fn find(parent: &mut [u32], i: u32) -> u32 {
    let mut r = i;
    while parent[r as usize] != r {
        r = parent[r as usize];
    }
    let mut i = i;
    while parent[i as usize] != r {
        let next = parent[i as usize];
        parent[i as usize] = r;
        i = next;
    }
    r
}

impl ConvexitySegmenter {
    /// Camera-frame points and unit normals (zero where unknown), from neighbours `s` pixels away.
    fn geometry(
        &self,
        depth: &DepthMap,
        camera: &Camera,
        s: usize,
    ) -> (Vec<Point3<f32>>, Vec<Vector3<f32>>) {
        let (w, h) = (depth.width() as usize, depth.height() as usize);
        let k = &camera.intrinsics;
        let d = depth.data();
        let pts: Vec<Point3<f32>> = (0..w * h)
            .map(|i| k.unproject((i % w) as f32 + 0.5, (i / w) as f32 + 0.5, d[i]))
            .collect();
        let mut normals = vec![Vector3::zeros(); w * h];
        // The farthest measured pixel up to `s` away along (du, dv), or `i` itself: next to a
        // hole (a real sensor has many) the normal comes from the side that is measured.
        let reach = |u: usize, v: usize, du: i64, dv: i64| -> usize {
            for o in (1..=s as i64).rev() {
                let (x, y) = (u as i64 + du * o, v as i64 + dv * o);
                if x >= 0 && y >= 0 && x < w as i64 && y < h as i64 {
                    let j = y as usize * w + x as usize;
                    if d[j] > 0.0 {
                        return j;
                    }
                }
            }
            v * w + u
        };
        for v in 1..h.saturating_sub(1) {
            for u in 1..w.saturating_sub(1) {
                let i = v * w + u;
                if d[i] <= 0.0 {
                    continue;
                }
                let (l, r, t, b) = (
                    reach(u, v, -1, 0),
                    reach(u, v, 1, 0),
                    reach(u, v, 0, -1),
                    reach(u, v, 0, 1),
                );
                if l == r || t == b {
                    continue;
                }
                let n = (pts[r] - pts[l]).cross(&(pts[b] - pts[t]));
                if let Some(n) = n.try_normalize(1e-12) {
                    // Face the camera.
                    normals[i] = if n.dot(&pts[i].coords) > 0.0 { -n } else { n };
                }
            }
        }
        (pts, normals)
    }

    /// The gravity-guided merge of touching parts (see the module docs). `roots[i]` is pixel i's
    /// segment; merged segments get a common root.
    fn merge_parts(
        &self,
        roots: &mut [u32],
        d: &[f32],
        pts: &[Point3<f32>],
        normals: &[Vector3<f32>],
        camera: &Camera,
        w: usize,
    ) {
        // Segment boxes in a gravity-aligned frame (z up), from which heights are read.
        let level = nalgebra::Rotation3::rotation_between(&self.up_world, &Vector3::z())
            .unwrap_or_else(|| {
                nalgebra::Rotation3::from_axis_angle(&Vector3::x_axis(), std::f32::consts::PI)
            });
        let world = |p: &Point3<f32>| level * (camera.world_from_camera * p);
        let (seg, mut bbox) = segment_boxes(roots, d, pts, &world);
        let up = camera
            .world_from_camera
            .rotation
            .inverse_transform_vector(&self.up_world)
            .normalize();
        let contacts = self.boundary_contacts(&seg, d, pts, normals, &up, &world, w);
        let candidates = self.merge_candidates(&contacts, &bbox);
        let rep = self.union_candidates(candidates, &mut bbox);
        // Back to pixel roots: every pixel of a merged group takes the group's representative.
        for i in 0..roots.len() {
            if seg[i] != usize::MAX {
                roots[i] = rep[seg[i]];
            }
        }
    }

    /// Neighbouring pixel pairs across segment boundaries, per pair of segments: how many, how
    /// many touch in 3-D (no depth jump), at what height, how many of the touching ones see an
    /// upward-facing surface on either side (normals from `crease_reach` inside), and which side
    /// is nearer.
    #[allow(clippy::too_many_arguments)]
    fn boundary_contacts(
        &self,
        seg: &[usize],
        d: &[f32],
        pts: &[Point3<f32>],
        normals: &[Vector3<f32>],
        up: &Vector3<f32>,
        world: &dyn Fn(&Point3<f32>) -> Point3<f32>,
        w: usize,
    ) -> HashMap<(usize, usize), Contact> {
        let n = seg.len();
        let mut contacts: HashMap<(usize, usize), Contact> = HashMap::new();
        let reach = self.crease_reach;
        let cos_up = 30f32.to_radians().cos();
        let h = n / w;
        for v in 0..h {
            for u in 0..w {
                let i = v * w + u;
                for (j, step) in [
                    (u + 1 < w).then_some((i + 1, 1)),
                    (v + 1 < h).then_some((i + w, w)),
                ]
                .into_iter()
                .flatten()
                {
                    let (a, b) = (seg[i], seg[j]);
                    if a == usize::MAX || b == usize::MAX || a == b {
                        continue;
                    }
                    let (key, swap) = if a < b {
                        ((a, b), false)
                    } else {
                        ((b, a), true)
                    };
                    let c = contacts.entry(key).or_default();
                    c.adjacent += 1;
                    let i_nearer = d[i] < d[j];
                    c.nearer[(i_nearer == swap) as usize] += 1;
                    let z = d[i].min(d[j]);
                    if (pts[i] - pts[j]).norm() > self.contact_abs_m + self.contact_rel * z {
                        continue;
                    }
                    let inside_i = i
                        .checked_sub(reach * step)
                        .filter(|&x| seg[x] == a)
                        .unwrap_or(i);
                    let inside_j = Some(j + reach * step)
                        .filter(|&x| x < n && seg[x] == b)
                        .unwrap_or(j);
                    let up_i = normals[inside_i].dot(up) > cos_up;
                    let up_j = normals[inside_j].dot(up) > cos_up;
                    let ups = if swap { [up_j, up_i] } else { [up_i, up_j] };
                    c.pairs += 1;
                    c.height_sum += 0.5 * world(&pts[i]).z + 0.5 * world(&pts[j]).z;
                    for (count, up) in c.up_facing.iter_mut().zip(ups) {
                        *count += up as usize;
                    }
                }
            }
        }
        contacts
    }

    /// The pairs of segments to merge, most adjacent pixels first: touching without one resting
    /// on the other, or one hanging under the other.
    fn merge_candidates(
        &self,
        contacts: &HashMap<(usize, usize), Contact>,
        bbox: &[(Point3<f32>, Point3<f32>)],
    ) -> Vec<(usize, usize)> {
        let lowest: Vec<f32> = bbox.iter().map(|b| b.0.z).collect();
        // `low` hangs under `high`: its top is just under `high`'s bottom, within its footprint,
        // and `high` hides it along their shared boundary (a table's legs under its top).
        let hangs_under = |low: usize, high: usize, c: &Contact, high_side: usize| -> bool {
            let (l, hb) = (&bbox[low], &bbox[high]);
            let gap = hb.0.z - l.1.z;
            let margin = 0.02;
            c.adjacent >= self.min_contact_px
                && 2 * c.nearer[high_side] > c.adjacent
                && gap > -margin
                && gap < self.hang_gap_m
                && l.0.x >= hb.0.x - margin
                && l.1.x <= hb.1.x + margin
                && l.0.y >= hb.0.y - margin
                && l.1.y <= hb.1.y + margin
        };
        // `top` rests on the other: the contact is at `top`'s bottom, on an upward-facing surface
        // of the other.
        let rests_on = |top: usize, top_side: usize, c: &Contact, height: f32| -> bool {
            height - lowest[top] < self.rest_height_m && 2 * c.up_facing[1 - top_side] > c.pairs
        };
        let mut candidates: Vec<((usize, usize), usize)> = contacts
            .iter()
            .filter(|(&(a, b), c)| {
                let touching = c.pairs >= self.min_contact_px && {
                    let height = c.height_sum / c.pairs as f32;
                    !rests_on(a, 0, c, height) && !rests_on(b, 1, c, height)
                };
                touching || hangs_under(a, b, c, 1) || hangs_under(b, a, c, 0)
            })
            .map(|(&k, c)| (k, c.adjacent))
            .collect();
        candidates.sort_by_key(|&((a, b), pairs)| (std::cmp::Reverse(pairs), a, b));
        candidates.into_iter().map(|(k, _)| k).collect()
    }

    /// Merges the candidate pairs in order (union-find), never the floor and never past
    /// `max_object_extent_m`; returns each segment's group representative.
    fn union_candidates(
        &self,
        candidates: Vec<(usize, usize)>,
        bbox: &mut [(Point3<f32>, Point3<f32>)],
    ) -> Vec<u32> {
        // The floor (flat and lowest in view) never merges: anything it touches stands on it, but a
        // partly visible object can meet it at its side.
        let floor_z = bbox.iter().map(|b| b.0.z).fold(f32::INFINITY, f32::min);
        let floor: Vec<bool> = bbox
            .iter()
            .map(|b| b.0.z < floor_z + 0.03 && b.1.z < floor_z + 0.05)
            .collect();
        let mut parent: Vec<u32> = (0..bbox.len() as u32).collect();
        for (a, b) in candidates {
            if floor[a] || floor[b] {
                continue;
            }
            let (ra, rb) = (
                find(&mut parent, a as u32) as usize,
                find(&mut parent, b as u32) as usize,
            );
            if ra == rb {
                continue;
            }
            let merged = (bbox[ra].0.inf(&bbox[rb].0), bbox[ra].1.sup(&bbox[rb].1));
            if (merged.1 - merged.0).norm() > self.max_object_extent_m {
                continue;
            }
            parent[ra] = rb as u32;
            bbox[rb] = merged;
        }
        (0..bbox.len() as u32)
            .map(|k| find(&mut parent, k))
            .collect()
    }
}

impl Segmenter for ConvexitySegmenter {
    fn segment(&self, frame: &Frame) -> Result<InstanceMap, PipelineError> {
        Ok(self.segment_rgbd(&frame.depth, Some(&frame.rgb), &frame.camera))
    }
}

impl ConvexitySegmenter {
    /// Segments an RGB-D frame: [`ConvexitySegmenter::segment_depth`], then the pixels without
    /// depth labelled by colour ([`ConvexitySegmenter::hole_max_cost`]) when `rgb` matches the
    /// depth map's size.
    pub fn segment_rgbd(
        &self,
        depth: &DepthMap,
        rgb: Option<&image::RgbImage>,
        camera: &Camera,
    ) -> InstanceMap {
        let mut map = self.segment_depth(depth, camera);
        if let Some(rgb) = rgb.filter(|c| c.dimensions() == (depth.width(), depth.height())) {
            if self.hole_max_cost > 0.0 {
                label_holes_by_colour(
                    &mut map,
                    depth.data(),
                    rgb,
                    self.hole_step_cost,
                    self.hole_max_cost,
                    self.hole_radius_px,
                );
            }
        }
        map
    }

    /// Segments a depth map seen by `camera` (gravity from its pose); pixels without depth stay
    /// unlabelled ([`ConvexitySegmenter::segment_rgbd`] labels them from the colour image).
    pub fn segment_depth(&self, depth: &DepthMap, camera: &Camera) -> InstanceMap {
        let (w, h) = (depth.width() as usize, depth.height() as usize);
        let d = depth.data();
        let noise = if self.noise_sigmas > 0.0 {
            DepthNoise::estimate(depth)
        } else {
            DepthNoise::default()
        };
        let (pts, normals) = self.geometry(depth, camera, self.normal_step);
        let mut parent: Vec<u32> = (0..(w * h) as u32).collect();
        let k = self.crease_reach;
        // The noise's share of a tolerance at depth z (two pixels' noise), above the floor that
        // the fixed tolerances were set for (exact depth in millimetre PNGs): exact depth is
        // segmented as it always was.
        let slack = |z: f32| {
            let excess = (noise.sigma(z) - deocc_geometry::noise::SIGMA_FLOOR_M).max(0.0);
            self.noise_sigmas * excess * std::f32::consts::SQRT_2
        };
        let cos_smooth = self.smooth_deg.to_radians().cos();
        // `step`: 1 for a horizontal neighbour pair, w for a vertical one.
        let connect = |i: usize, j: usize, step: usize| -> bool {
            let (zi, zj) = (d[i], d[j]);
            if zi <= 0.0 || zj <= 0.0 {
                return false;
            }
            if (zi - zj).abs() > self.depth_abs_m + self.depth_rel * zi.min(zj) + slack(zi.min(zj))
            {
                return false;
            }
            // Each neighbour's tangent plane must predict the other's depth along its ray: a box's
            // top and the table just behind it are parallel, a few centimetres apart, and pass
            // every other test.
            let tol = self.step_abs_m + self.step_rel * zi.min(zj) + slack(zi.min(zj));
            for (from, to, z_to) in [(i, j, zj), (j, i, zi)] {
                let n = normals[from];
                if n == Vector3::zeros() {
                    continue;
                }
                let denom = n.dot(&(pts[to].coords / z_to));
                if denom.abs() < 1e-3 || (n.dot(&pts[from].coords) / denom - z_to).abs() > tol {
                    return false;
                }
            }
            // Judge the crease between (i, j) from a little way off on either side: normals
            // estimated right at a crease blend both surfaces and hide it.
            // The farthest of 1..=k pixels out on each side that has depth and a normal (the
            // pixel itself when none has).
            let out = |from: usize, towards: bool| -> usize {
                for kk in (1..=k).rev() {
                    let o = if towards {
                        from.checked_add(kk * step).filter(|&x| x < w * h)
                    } else {
                        from.checked_sub(kk * step)
                    };
                    if let Some(o) = o {
                        if (step != 1 || o / w == from / w)
                            && d[o] > 0.0
                            && normals[o] != Vector3::zeros()
                        {
                            return o;
                        }
                    }
                }
                from
            };
            let (a, b) = (out(i, false), out(j, true));
            let (na, nb) = (normals[a], normals[b]);
            if na == Vector3::zeros() || nb == Vector3::zeros() || d[a] <= 0.0 || d[b] <= 0.0 {
                // No normal (image border, next to missing depth): do not connect, or creases that
                // reach the border would leak through it.
                return false;
            }
            // Gently curved (the inside of a bowl), or flat or convex (normals not turning towards
            // each other across the crease): the same surface.
            if na.dot(&nb) >= cos_smooth {
                return true;
            }
            let dp = pts[a] - pts[b];
            (na - nb).dot(&dp) >= -self.concave_tolerance * dp.norm()
        };
        for v in 0..h {
            for u in 0..w {
                let i = v * w + u;
                for (j, step) in [
                    if u + 1 < w { Some((i + 1, 1)) } else { None },
                    if v + 1 < h { Some((i + w, w)) } else { None },
                ]
                .into_iter()
                .flatten()
                {
                    if connect(i, j, step) {
                        let (a, b) = (find(&mut parent, i as u32), find(&mut parent, j as u32));
                        if a != b {
                            parent[a as usize] = b;
                        }
                    }
                }
            }
        }
        let mut size = vec![0usize; w * h];
        let mut roots: Vec<u32> = (0..w * h).map(|i| find(&mut parent, i as u32)).collect();
        self.merge_parts(&mut roots, d, &pts, &normals, camera, w);
        for (i, &r) in roots.iter().enumerate() {
            if d[i] > 0.0 {
                size[r as usize] += 1;
            }
        }
        let mut label = std::collections::HashMap::new();
        let ids = roots
            .iter()
            .enumerate()
            .map(|(i, &r)| {
                if d[i] <= 0.0 || size[r as usize] < self.min_segment_px {
                    return 0;
                }
                let next = label.len() + 1;
                (*label.entry(r).or_insert(next)).min(u16::MAX as usize) as u16
            })
            .collect();
        let mut map = InstanceMap {
            width: w as u32,
            height: h as u32,
            ids,
        };
        self.fill_gaps(&mut map, d);
        map
    }
}

impl ConvexitySegmenter {
    /// Pixels with depth left unlabelled (dropped slivers along edges, where normals blend two
    /// surfaces) join the neighbouring segment closest in depth, a few pixels deep. Without this a
    /// seam of unlabelled pixels separates an occluder from what it hides and the occlusion
    /// analysis, which looks at shared boundaries, misses it.
    fn fill_gaps(&self, map: &mut InstanceMap, d: &[f32]) {
        let (w, h) = (map.width as usize, map.height as usize);
        for _ in 0..self.fill_passes {
            let ids = map.ids.clone();
            let mut changed = false;
            for v in 0..h {
                for u in 0..w {
                    let i = v * w + u;
                    if ids[i] != 0 || d[i] <= 0.0 {
                        continue;
                    }
                    let tol = self.depth_abs_m + self.depth_rel * d[i];
                    let best = crate::depth_clean::neighbours4(i, w, h)
                        .filter(|&j| ids[j] != 0 && (d[j] - d[i]).abs() <= tol)
                        .min_by(|&a, &b| (d[a] - d[i]).abs().total_cmp(&(d[b] - d[i]).abs()));
                    if let Some(j) = best {
                        map.ids[i] = ids[j];
                        changed = true;
                    }
                }
            }
            if !changed {
                break;
            }
        }
    }
}

/// Labels each pixel without depth like the measured pixel within `radius` px that is closest in
/// colour (L1 over RGB, 0-765) plus `step_cost` per pixel of distance: on a textured surface the
/// hole's colour is one of its surface's nearby colours, whatever lies between. A measured but
/// unlabelled pixel (background) wins for id 0. No measured pixel within the radius, or a best cost
/// over `max_cost`: the pixel keeps id 0.
fn label_holes_by_colour(
    map: &mut InstanceMap,
    d: &[f32],
    rgb: &image::RgbImage,
    step_cost: f32,
    max_cost: f32,
    radius: usize,
) {
    let (w, h) = (map.width as usize, map.height as usize);
    let raw = rgb.as_raw();
    let colour = |i: usize| [raw[3 * i], raw[3 * i + 1], raw[3 * i + 2]];
    let ids = map.ids.clone();
    let r = radius as i64;
    for i in 0..w * h {
        if d[i] > 0.0 {
            continue;
        }
        let (u, v) = ((i % w) as i64, (i / w) as i64);
        let ci = colour(i);
        let mut best = (max_cost, None);
        for y in (v - r).max(0)..=(v + r).min(h as i64 - 1) {
            for x in (u - r).max(0)..=(u + r).min(w as i64 - 1) {
                let j = y as usize * w + x as usize;
                if d[j] <= 0.0 {
                    continue;
                }
                let cj = colour(j);
                let dist = (((x - u).pow(2) + (y - v).pow(2)) as f32).sqrt();
                let cost = (0..3)
                    .map(|c| (ci[c] as f32 - cj[c] as f32).abs())
                    .sum::<f32>()
                    + step_cost * dist;
                if cost < best.0 {
                    best = (cost, Some(ids[j]));
                }
            }
        }
        if let (_, Some(id)) = best {
            map.ids[i] = id;
        }
    }
}

/// What two segments share along their boundary (see `boundary_contacts`).
#[derive(Default)]
struct Contact {
    adjacent: usize,
    nearer: [usize; 2],
    pairs: usize,
    height_sum: f32,
    up_facing: [usize; 2],
}

/// Each pixel's segment index (`usize::MAX` without depth) and each segment's box in the
/// gravity-aligned frame `world`.
#[allow(clippy::type_complexity)]
fn segment_boxes(
    roots: &[u32],
    d: &[f32],
    pts: &[Point3<f32>],
    world: &dyn Fn(&Point3<f32>) -> Point3<f32>,
) -> (Vec<usize>, Vec<(Point3<f32>, Point3<f32>)>) {
    let mut index: HashMap<u32, usize> = HashMap::new();
    let mut seg = vec![usize::MAX; roots.len()];
    let mut bbox: Vec<(Point3<f32>, Point3<f32>)> = Vec::new();
    for i in 0..roots.len() {
        if d[i] <= 0.0 {
            continue;
        }
        let k = *index.entry(roots[i]).or_insert_with(|| {
            bbox.push((
                Point3::from([f32::INFINITY; 3]),
                Point3::from([f32::NEG_INFINITY; 3]),
            ));
            bbox.len() - 1
        });
        seg[i] = k;
        let p = world(&pts[i]);
        let b = &mut bbox[k];
        b.0 = b.0.inf(&p);
        b.1 = b.1.sup(&p);
    }
    (seg, bbox)
}
