use std::collections::BTreeMap;
use std::path::Path;

use deocc_synth::dataset::{preset, render_full_scene, write_scene};
use deocc_synth::generate::generate_scene;
use deocc_synth::pairs::{load_pairs, save_pairs, scene_pairs, PairConfig};
use deocc_synth::render::{albedo, light, render_object, render_scene, shade, SceneTriangles};
use deocc_synth::scene::SceneConfig;
use nalgebra::Point3;
use sha2::{Digest, Sha256};

fn small_config() -> SceneConfig {
    SceneConfig {
        width: 160,
        height: 120,
        views: 3,
        gt_points_per_m2: 2000.0,
        ..SceneConfig::default()
    }
}

fn hash_tree(dir: &Path) -> BTreeMap<String, String> {
    let mut out = BTreeMap::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                let h = Sha256::digest(std::fs::read(&p).unwrap());
                out.insert(
                    p.strip_prefix(dir).unwrap().display().to_string(),
                    format!("{h:x}"),
                );
            }
        }
    }
    out
}

#[test]
fn same_config_and_seed_give_byte_identical_files() {
    let cfg = small_config();
    let (a, b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    write_scene(a.path(), &cfg, &render_full_scene(&cfg, 7).unwrap()).unwrap();
    write_scene(b.path(), &cfg, &render_full_scene(&cfg, 7).unwrap()).unwrap();
    let (ha, hb) = (hash_tree(a.path()), hash_tree(b.path()));
    assert!(ha.len() > 10, "expected many files, got {}", ha.len());
    assert_eq!(ha, hb);
    // And another seed differs.
    let c = tempfile::tempdir().unwrap();
    write_scene(c.path(), &cfg, &render_full_scene(&cfg, 8).unwrap()).unwrap();
    assert_ne!(
        ha.get("rgb/000000.png"),
        hash_tree(c.path()).get("rgb/000000.png")
    );
}

/// Distance from a point to a triangle (brute force, for the oracle).
fn point_triangle_distance(p: &Point3<f32>, t: &[Point3<f32>; 3]) -> f32 {
    let (a, b, c) = (t[0], t[1], t[2]);
    let n = (b - a).cross(&(c - a));
    let nn = n.norm();
    if nn > 1e-12 {
        let n = n / nn;
        let d = (p - a).dot(&n);
        let q = p - n * d;
        let inside = [(a, b), (b, c), (c, a)]
            .iter()
            .all(|(u, v)| (v - u).cross(&(q - u)).dot(&n) >= -1e-9);
        if inside {
            return d.abs();
        }
    }
    let seg = |u: Point3<f32>, v: Point3<f32>| {
        let e = v - u;
        let s = ((p - u).dot(&e) / e.norm_squared().max(1e-20)).clamp(0.0, 1.0);
        (p - (u + e * s)).norm()
    };
    seg(a, b).min(seg(b, c)).min(seg(c, a))
}

#[test]
fn visible_pixels_lie_on_their_instance_surface_within_2mm() {
    let cfg = small_config();
    let scene = generate_scene(&cfg, 11).unwrap();
    let tris = SceneTriangles::new(&scene);
    let camera = scene.cameras[0];
    let frame = render_scene(&camera, &scene, &tris);
    let w = frame.width as usize;
    let mut checked = 0;
    for i in (0..frame.depth_m.len()).step_by(7) {
        let id = frame.instance[i];
        if id == 0 {
            continue;
        }
        let p = camera.unproject_pixel((i % w) as u32, (i / w) as u32, frame.depth_m[i]);
        let k = scene
            .objects
            .iter()
            .position(|o| o.instance_id == id)
            .unwrap();
        let d = tris.object_ranges[k]
            .clone()
            .map(|t| point_triangle_distance(&p, &tris.corners[t]))
            .fold(f32::INFINITY, f32::min);
        assert!(
            d < 0.002,
            "pixel {i} of instance {id} is {d} m off its surface"
        );
        checked += 1;
    }
    assert!(checked > 500);
}

#[test]
fn shading_is_lambertian_with_ambient_light_on_the_albedo() {
    let cfg = small_config();
    let scene = generate_scene(&cfg, 12).unwrap();
    let tris = SceneTriangles::new(&scene);
    let camera = scene.cameras[1];
    // The whole scene (walls everywhere) and one object alone (mostly background).
    let object = scene
        .objects
        .iter()
        .position(|o| !o.category.is_structure())
        .unwrap();
    let frames = [
        render_scene(&camera, &scene, &tris),
        render_object(&camera, &scene, &tris, object),
    ];
    let background = [3, 5, 7];
    let (mut lit, mut empty, mut off_pixels) = (0, 0, 0usize);
    for frame in &frames {
        let rgb = shade(frame, &camera, &scene, &tris, background);
        let (w, eye) = (frame.width as usize, camera.center());
        for i in (0..frame.depth_m.len()).step_by(5) {
            let got = rgb.as_raw()[3 * i..3 * i + 3].to_vec();
            let ti = frame.triangle[i];
            if ti == u32::MAX {
                assert_eq!(got, background.to_vec(), "empty pixel {i}");
                empty += 1;
                continue;
            }
            // The plain per-pixel formula, through the camera's own unprojection.
            let p = camera.unproject_pixel((i % w) as u32, (i / w) as u32, frame.depth_m[i]);
            let obj = tris.object[ti as usize] as usize;
            let mut n = tris.normals[ti as usize];
            if n.dot(&(eye - p)) < 0.0 {
                n = -n;
            }
            let lum = 0.35 + 0.65 * n.dot(&light()).max(0.0);
            let a = albedo(&scene.objects[obj].appearance, &p, obj as u32 + 1);
            let off = (0..3).any(|c| {
                let want = (a[c] * lum * 255.0).clamp(0.0, 255.0);
                (got[c] as f32 - want).abs() > 1.0
            });
            // Within one level (the rotation is a matrix in the shader, a quaternion here); a pixel
            // whose point that rounding moves across a stripe or checker edge may differ more.
            off_pixels += off as usize;
            lit += 1;
        }
    }
    assert!(lit > 1000 && empty > 0, "{lit} lit, {empty} empty pixels");
    assert!(
        off_pixels * 1000 <= lit,
        "{off_pixels} of {lit} pixels differ from the formula by more than one level"
    );
}

#[test]
fn amodal_masks_contain_visible_masks_and_equal_them_without_occluders() {
    let cfg = small_config();
    let rendered = render_full_scene(&cfg, 12).unwrap();
    let mut unoccluded_seen = false;
    for view in &rendered.views {
        for m in &view.amodal {
            let (id, mask) = (
                m.instance_id,
                m.to_full(view.frame.width, view.frame.height),
            );
            for (i, &inst) in view.frame.instance.iter().enumerate() {
                if inst == id {
                    assert!(mask[i], "visible pixel {i} of {id} outside its amodal mask");
                }
            }
        }
    }
    // An object alone in the scene: amodal == visible exactly.
    let mut scene = generate_scene(&cfg, 12).unwrap();
    let keep = scene
        .objects
        .iter()
        .position(|o| o.category == deocc_synth::shapes::Category::Table)
        .unwrap();
    scene.objects = vec![scene.objects[keep].clone()];
    let tris = SceneTriangles::new(&scene);
    for cam in &scene.cameras {
        let frame = render_scene(cam, &scene, &tris);
        let alone = render_object(cam, &scene, &tris, 0);
        assert_eq!(frame.instance, alone.instance);
        // The depth-free coverage raster (used for amodal masks) marks exactly the same pixels.
        let mut coverage = vec![false; frame.instance.len()];
        deocc_synth::render::rasterize_coverage(
            cam,
            &tris,
            tris.object_ranges[0].clone(),
            &mut coverage,
        );
        let drawn: Vec<bool> = alone.instance.iter().map(|&i| i != 0).collect();
        assert_eq!(coverage, drawn);
        unoccluded_seen |= frame.instance.iter().any(|&i| i != 0);
    }
    assert!(unoccluded_seen);
}

#[test]
fn ground_truth_flags_some_points_seen_and_some_hidden() {
    let cfg = small_config();
    let r = render_full_scene(&cfg, 13).unwrap();
    let seen = r.ground_truth.seen.iter().filter(|&&s| s).count();
    let n = r.ground_truth.cloud.len();
    assert!(n > 10_000);
    assert!(seen > n / 10 && seen < n * 9 / 10, "{seen} of {n} seen");
}

#[test]
fn pairs_are_consistent_and_round_trip() {
    let scene = generate_scene(
        &SceneConfig {
            views: 4,
            ..SceneConfig::default()
        },
        14,
    )
    .unwrap();
    let set = scene_pairs(
        &scene,
        &PairConfig {
            keep_unoccluded: 1.0,
            ..PairConfig::default()
        },
        0,
    )
    .unwrap();
    assert!(set.len() > 5);
    let px = set.pixels();
    for k in 0..set.len() {
        let vis = &set.visible_mask[k * px..(k + 1) * px];
        let amo = &set.amodal_mask[k * px..(k + 1) * px];
        // Visible is a subset of amodal (up to the rasteriser's shared-edge pixels).
        let outside = vis
            .iter()
            .zip(amo)
            .filter(|(&v, &a)| v > 0 && a == 0)
            .count();
        assert!(
            outside <= 2,
            "pair {k}: {outside} visible pixels outside the amodal mask"
        );
        // Outside the amodal mask the whole-object image is white.
        for (i, &a) in amo.iter().enumerate() {
            if a == 0 {
                assert_eq!(
                    &set.whole_rgb[3 * (k * px + i)..3 * (k * px + i) + 3],
                    &[255, 255, 255]
                );
            }
        }
    }
    // Every crop's metric width is known: its side at the object's depth, within the scenes'
    // range of sizes (a mug's crop at a few tenths of a metre, a shelf's a few metres).
    assert_eq!(set.crop_width_m.len(), set.len());
    assert!(
        set.crop_width_m.iter().all(|&w| (0.02..10.0).contains(&w)),
        "{:?}",
        set.crop_width_m
    );
    // What other views saw, reprojected into each crop, is the object where this view does not
    // see it: on the object's silhouette (or the ring of pixels around it that its edge points
    // partly cover), at its near side's depth and in its colour (the light is fixed in the
    // world, so the colour does not depend on the view).
    assert_eq!(set.elsewhere_depth.len(), set.len() * px);
    let r = set.resolution as i64;
    let (mut on_object, mut far_off, mut depth_ok) = (0, 0, 0);
    let (mut interior_px, mut colour_ok) = (0, 0);
    for k in 0..set.len() {
        let amo = &set.amodal_mask[k * px..(k + 1) * px];
        // How many of pixel i's 3x3 neighbourhood are object (outside the crop: not).
        let object_around = |i: usize| {
            let (u, v) = ((i as i64) % r, (i as i64) / r);
            (-1..=1)
                .flat_map(|dv| (-1..=1).map(move |du| (u + du, v + dv)))
                .filter(|&(x, y)| x >= 0 && y >= 0 && x < r && y < r)
                .filter(|&(x, y)| amo[(y * r + x) as usize] > 0)
                .count()
        };
        for (i, &a) in amo.iter().enumerate() {
            let j = k * px + i;
            let d = set.elsewhere_depth[j];
            if !d.is_finite() || set.visible_mask[j] > 0 {
                continue;
            }
            if a == 0 {
                far_off += (object_around(i) == 0) as usize;
                continue;
            }
            on_object += 1;
            depth_ok += ((d - set.whole_depth[j]).abs() < 0.03) as usize;
            let diff = (0..3)
                .map(|c| set.elsewhere_rgb[3 * j + c].abs_diff(set.whole_rgb[3 * j + c]))
                .max()
                .unwrap();
            // Inside the silhouette (not on its edge, where the nearest point may lie on a side
            // face the pixel centre does not see).
            if object_around(i) == 9 {
                interior_px += 1;
                colour_ok += (diff <= 8) as usize;
            }
        }
    }
    assert!(
        on_object > 100,
        "{on_object} hidden object pixels seen elsewhere"
    );
    assert_eq!(far_off, 0, "points more than a pixel off the silhouette");
    assert!(
        depth_ok * 100 >= on_object * 90,
        "{depth_ok} of {on_object} at its depth"
    );
    assert!(interior_px > 50, "{interior_px} interior pixels");
    assert!(
        colour_ok * 100 >= interior_px * 80,
        "{colour_ok} of {interior_px} in its colour"
    );
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("p.safetensors");
    save_pairs(&p, &set).unwrap();
    assert_eq!(load_pairs(&p).unwrap(), set);
    std::fs::write(&p, b"garbage").unwrap();
    let e = load_pairs(&p).unwrap_err().to_string();
    assert!(e.contains("p.safetensors"), "{e}");
}

#[test]
fn bench_v1_is_fixed() {
    let p = preset("bench-v1").unwrap();
    assert_eq!(p.seeds.len(), 50);
    assert_eq!(p.config.views, 10);
    assert_eq!((p.config.width, p.config.height), (640, 480));
    assert!(p.config.held_out_shapes);
    assert!(preset("bench-v2").is_err());
}

#[test]
fn structure_ground_truth_lies_only_on_faces_towards_the_room() {
    use deocc_synth::scene::ROOM_INTERIOR;
    let cfg = small_config();
    let r = render_full_scene(&cfg, 13).unwrap();
    let gt = &r.ground_truth.cloud;
    let ids = gt.instance.as_deref().unwrap();
    let normals = gt.normals.as_deref().unwrap();
    let structure: Vec<u32> = r
        .scene
        .objects
        .iter()
        .filter(|o| o.category.is_structure())
        .map(|o| o.instance_id as u32)
        .collect();
    let mut floor_top = 0;
    for i in 0..gt.len() {
        if !structure.contains(&ids[i]) {
            continue;
        }
        let p = gt.positions[i];
        assert!(
            normals[i].dot(&(ROOM_INTERIOR - p)) > 0.0,
            "structure point {p:?} faces away from the room"
        );
        assert!(p.z > -1e-4, "a point on the floor's underside: {p:?}");
        floor_top += (p.z.abs() < 1e-4) as usize;
    }
    assert!(
        floor_top > 1000,
        "the floor's top is sampled ({floor_top} points)"
    );
}

/// User meshes: coordinates near f32's limits or among its denormals are scaled in f64, and a
/// mesh too large for the table is an error, never silently left out.
#[test]
fn user_meshes_are_placed_or_refused() {
    use deocc_synth::generate::generate_scene;
    use deocc_synth::scene::{SceneConfig, UserMesh};
    use deocc_synth::shapes::Category;
    let dir = tempfile::tempdir().unwrap();
    let cube = |name: &str, s: f32| {
        let path = dir.path().join(name);
        let mut obj = String::new();
        for (x, y, z) in [
            (0, 0, 0),
            (1, 0, 0),
            (1, 1, 0),
            (0, 1, 0),
            (0, 0, 1),
            (1, 0, 1),
            (1, 1, 1),
            (0, 1, 1),
        ] {
            obj += &format!(
                "v {} {} {}\n",
                x as f32 * s - s / 2.0,
                y as f32 * s,
                z as f32 * s
            );
        }
        obj += "f 1 2 3 4\nf 5 6 7 8\nf 1 2 6 5\nf 2 3 7 6\nf 3 4 8 7\nf 4 1 5 8\n";
        std::fs::write(&path, obj).unwrap();
        path
    };
    let scene_with = |path: &std::path::Path, size_m: f32, seed: u64| {
        let cfg = SceneConfig {
            views: 1,
            user_meshes: vec![UserMesh {
                path: path.to_path_buf(),
                size_m,
            }],
            ..SceneConfig::default()
        };
        generate_scene(&cfg, seed)
    };
    let huge = cube("huge.obj", 3e38);
    let tiny = cube("tiny.obj", 1e-40);
    let unit = cube("unit.obj", 1.0);
    for (path, size) in [(&huge, 0.2), (&tiny, 0.2), (&unit, 0.3)] {
        for seed in 0..8 {
            let scene = scene_with(path, size, seed).unwrap();
            assert!(
                scene
                    .objects
                    .iter()
                    .any(|o| o.category == Category::UserMesh),
                "{} at {size} m, seed {seed}: left out",
                path.display()
            );
        }
    }
    for size in [0.8, 1.9] {
        let e = scene_with(&unit, size, 0).unwrap_err().to_string();
        assert!(e.contains("unit.obj") && e.contains("does not fit"), "{e}");
    }
}

/// Task scenes keep their promises: a pickup target 5-95% visible in its one view, a place
/// table with at least 30% of its free top hidden, and the same scene from the same seed.
#[test]
fn task_scenes_hide_what_their_benchmarks_need() {
    use deocc_synth::dataset::{pickup_v1, place_v1, render_full_scene};
    use deocc_synth::tasks::hidden_free_fraction;
    let pickup = pickup_v1();
    for &seed in &pickup.seeds[..3] {
        let r = render_full_scene(&pickup.config, seed).unwrap();
        let target = r.scene.target.expect("a target");
        let v = r.views[0]
            .visibility
            .iter()
            .find(|v| v.instance_id == target)
            .expect("the target is in view");
        let visible = 1.0 - v.occlusion();
        assert!((0.05..=0.95).contains(&visible), "seed {seed}: {visible}");
        assert_eq!(r.views.len(), 1);
    }
    let place = place_v1();
    for &seed in &place.seeds[..2] {
        let s = deocc_synth::generate::generate_scene(&place.config, seed).unwrap();
        assert!(hidden_free_fraction(&s) >= 0.3, "seed {seed}");
        let again = deocc_synth::generate::generate_scene(&place.config, seed).unwrap();
        assert_eq!(s.objects.len(), again.objects.len());
        assert_eq!(
            s.cameras[0].world_from_camera,
            again.cameras[0].world_from_camera
        );
    }
    // place-v2: the same promise with twice the clutter.
    let things = |s: &deocc_synth::scene::Scene| {
        s.objects
            .iter()
            .filter(|o| {
                !o.category.is_structure() && o.category != deocc_synth::shapes::Category::Table
            })
            .count()
    };
    let dense = deocc_synth::dataset::place_v2();
    for (&seed, &sparse_seed) in dense.seeds[..2].iter().zip(&place.seeds[..2]) {
        let s = deocc_synth::generate::generate_scene(&dense.config, seed).unwrap();
        assert!(hidden_free_fraction(&s) >= 0.3, "seed {seed}");
        let sparse = deocc_synth::generate::generate_scene(&place.config, sparse_seed).unwrap();
        assert!(things(&sparse) <= 10, "place-v1 seed {sparse_seed}");
        assert!(
            things(&s) > 10,
            "place-v2 seed {seed}: {} things",
            things(&s)
        );
    }
}

/// With `edge_objects`, objects that leave the image make pairs too (tables seen from a few
/// metres): more pairs, more of them tables, and the crop holds nothing outside the image (no
/// colour, no scene depth, not visible) while the object's amodal mask goes on there.
#[test]
fn edge_objects_make_pairs_blank_outside_the_image() {
    use deocc_synth::pairs::{split_scene_pairs, Split};
    use deocc_synth::shapes::Category;
    let plain = PairConfig::default();
    let edge = PairConfig {
        edge_objects: true,
        ..PairConfig::default()
    };
    let (mut n_plain, mut n_edge, mut tables_plain, mut tables_edge) = (0, 0, 0, 0);
    let mut blank_lines_with_object = 0;
    for scene in 0..3 {
        let a = split_scene_pairs(Split::Val, scene, &plain).unwrap();
        let b = split_scene_pairs(Split::Val, scene, &edge).unwrap();
        n_plain += a.len();
        n_edge += b.len();
        let tables = |s: &deocc_io::pairs::PairSet| {
            s.category
                .iter()
                .filter(|&&c| c == Category::Table as u8)
                .count()
        };
        tables_plain += tables(&a);
        tables_edge += tables(&b);
        let r = b.resolution as usize;
        let px = b.pixels();
        for k in 0..b.len() {
            // A border line of the crop (top, bottom, left, right) with nothing observed on it.
            let lines: [Vec<usize>; 4] = [
                (0..r).collect(),
                (0..r).map(|u| (r - 1) * r + u).collect(),
                (0..r).map(|v| v * r).collect(),
                (0..r).map(|v| v * r + r - 1).collect(),
            ];
            for line in &lines {
                let blank = line.iter().all(|&p| {
                    let i = k * px + p;
                    b.scene_depth[i] == 0.0
                        && b.visible_mask[i] == 0
                        && b.crop_rgb[3 * i..3 * i + 3] == [0, 0, 0]
                });
                if blank && line.iter().any(|&p| b.amodal_mask[k * px + p] > 0) {
                    blank_lines_with_object += 1;
                }
            }
        }
    }
    assert!(n_edge > n_plain, "{n_edge} against {n_plain} pairs");
    assert!(
        tables_edge > tables_plain,
        "{tables_edge} table pairs against {tables_plain}"
    );
    assert!(
        blank_lines_with_object > 0,
        "some object goes on past the image's edge"
    );
}

/// With `sensor_noise`, the condition's depth is what a sensor measures (rougher than the
/// render) while the targets stay the noise-free render's; the pairs are as deterministic as the
/// noise-free ones.
#[test]
fn sensor_noise_pairs_carry_a_noisy_condition_and_clean_targets() {
    use deocc_synth::pairs::{split_scene_pairs, Split};
    let noisy = PairConfig {
        sensor_noise: true,
        ..PairConfig::default()
    };
    let plain = PairConfig::default();
    let (mut roughness_plain, mut roughness_noisy) = (0.0f64, 0.0f64);
    for scene in 0..3 {
        let a = split_scene_pairs(Split::Val, scene, &plain).unwrap();
        let b = split_scene_pairs(Split::Val, scene, &noisy).unwrap();
        let again = split_scene_pairs(Split::Val, scene, &noisy).unwrap();
        assert_eq!(b.scene_depth, again.scene_depth, "deterministic");
        assert!(!b.is_empty());
        // Roughness: mean |difference| of horizontally adjacent visible depths, per pair's
        // crop width (the relative depth's unit), over the object's own pixels.
        let rough = |s: &deocc_io::pairs::PairSet| {
            let (r, px) = (s.resolution as usize, s.pixels());
            let (mut sum, mut n) = (0.0f64, 0usize);
            for k in 0..s.len() {
                for p in 0..px - 1 {
                    let (i, j) = (k * px + p, k * px + p + 1);
                    if p % r != r - 1 && s.visible_mask[i] > 0 && s.visible_mask[j] > 0 {
                        sum += (s.visible_depth[i] - s.visible_depth[j]).abs() as f64;
                        n += 1;
                    }
                }
            }
            sum / n.max(1) as f64
        };
        roughness_plain += rough(&a);
        roughness_noisy += rough(&b);
        // The targets are the noise-free render's: every visible pixel lies in the amodal mask.
        let px = b.pixels();
        for i in 0..b.len() * px {
            assert!(b.visible_mask[i] == 0 || b.amodal_mask[i] > 0);
        }
    }
    assert!(
        roughness_noisy > 1.2 * roughness_plain,
        "{roughness_noisy} against {roughness_plain}"
    );
}

/// pickup-v2: each seed's target is the kind its seed fixes, narrow enough for the gripper,
/// 5-50% visible; a flask is flattened (not round), a faceted bottle has flat sides (its
/// footprint's corners stand out of the inscribed circle).
#[test]
fn pickup_v2_scenes_have_their_kind_of_target_mostly_hidden() {
    use deocc_synth::dataset::{pickup_v2, render_full_scene};
    use deocc_synth::tasks::{MAX_V2_NARROW_SIDE_M, PICKUP_V2_TARGETS};
    let preset = pickup_v2();
    for &seed in &preset.seeds[..6] {
        let r = render_full_scene(&preset.config, seed).unwrap();
        let target = r.scene.target.expect("a target");
        let object = r
            .scene
            .objects
            .iter()
            .find(|o| o.instance_id == target)
            .unwrap();
        assert_eq!(
            object.category,
            PICKUP_V2_TARGETS[(seed % 6) as usize],
            "seed {seed}"
        );
        let v = r.views[0]
            .visibility
            .iter()
            .find(|v| v.instance_id == target)
            .expect("the target is in view");
        let visible = 1.0 - v.occlusion();
        assert!((0.05..=0.5).contains(&visible), "seed {seed}: {visible}");
    }
    let mut rng = <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(4);
    let footprint = |m: &deocc_synth::mesh::TriMesh| {
        // Horizontal extents along x and y, and the largest distance from the axis.
        let (lo, hi) = m.bounds().unwrap();
        let reach = m
            .vertices
            .iter()
            .map(|p| p.x.hypot(p.y))
            .fold(0.0f32, f32::max);
        (hi.x - lo.x, hi.y - lo.y, reach)
    };
    for _ in 0..5 {
        let flask = deocc_synth::shapes::tabletop(deocc_synth::shapes::Category::Flask, &mut rng);
        let (x, y, _) = footprint(&flask.mesh);
        assert!(y < 0.65 * x, "a flask {x} x {y} is not flattened");
        let faceted =
            deocc_synth::shapes::tabletop(deocc_synth::shapes::Category::FacetedBottle, &mut rng);
        let (x, y, reach) = footprint(&faceted.mesh);
        // A hexagon or octagon: 6 or 8 corners on the base's outline.
        let mut corners: Vec<i32> = faceted
            .mesh
            .vertices
            .iter()
            .filter(|p| p.z.abs() < 1e-4 && p.x.hypot(p.y) > 0.99 * reach)
            .map(|p| (p.y.atan2(p.x).to_degrees() * 10.0).round() as i32)
            .collect();
        corners.sort_unstable();
        corners.dedup();
        assert!(
            corners.len() == 6 || corners.len() == 8,
            "{} corners",
            corners.len()
        );
        assert!(x.min(y) <= MAX_V2_NARROW_SIDE_M + 0.01);
    }
}

/// `grasp_families` puts pickup-v2's faceted bottles and flasks on the tables (the training
/// pairs for real shapes); without it they never appear, so the existing splits stay as they were.
#[test]
fn grasp_families_bring_faceted_bottles_and_flasks() {
    use deocc_synth::shapes::Category;
    let count = |grasp_families: bool| {
        let cfg = SceneConfig {
            grasp_families,
            tabletop_objects_min: 8,
            tabletop_objects_max: 8,
            ..small_config()
        };
        (0..12u64)
            .flat_map(|seed| generate_scene(&cfg, 500 + seed).unwrap().objects)
            .filter(|o| Category::TABLETOP_GRASP.contains(&o.category))
            .count()
    };
    assert_eq!(count(false), 0);
    assert!(
        count(true) >= 4,
        "{} faceted bottles and flasks",
        count(true)
    );
}
