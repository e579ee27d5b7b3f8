//! Scenes for the robot-task benchmarks, in the same room as bench-v1:
//!
//! - **pickup** ([`pickup_scene`]): a graspable target (bottle, can or mug, at most 7.2 cm
//!   across) on the table
//!   behind a large box, a few other things around, one robot-head view 1.2-1.5 m high and
//!   1.0-1.5 m (horizontally) from the target. Attempts are redrawn until 5-95% of the target's
//!   silhouette is visible (a target nobody sees cannot be asked for; one nobody hides tests
//!   nothing).
//! - **pickup-v2** ([`pickup_v2_scene`]): the same room and robot, harder targets and
//!   occluders: shouldered, faceted and flattened (not round) bottles, cans, mugs with
//!   handles, small boxes ([`PICKUP_V2_TARGETS`], the kind fixed by the seed, each no wider
//!   than 7.4 cm across its narrow side); behind a large box, a tall carton or a wide jar; redrawn until 5-50% of the
//!   target's silhouette is visible (50-95% hidden).
//! - **place** ([`place_scene`]): a cluttered table (`tabletop_objects_min..=max` things: 6-10
//!   in place-v1, 12-18 in place-v2) seen once from 1.5-2.5 m; redrawn until at least 30% of the
//!   table's free surface is hidden from the view.
//!
//! Attempt `k` of seed `s` draws from the generator seeded `s * 64 + k`, so a seed fixes the
//! scene.

use deocc_geometry::camera::{look_at, Camera, Intrinsics};
use nalgebra::{Point3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::ground_truth::visible_in;
use crate::mesh::box_on;
use crate::render::{rasterize_coverage, render_scene, SceneTriangles};
use crate::scene::{
    add_object, appearance, find_spot, place, room_and_table, Scene, SceneConfig, SceneObject,
    TablePose,
};
use crate::shapes::{self, Category};
use crate::SynthError;

/// Targets of pickup scenes: things a parallel-jaw gripper can hold, drawn until they are at
/// most [`MAX_TARGET_RADIUS_M`] in radius (the default gripper opens 8.5 cm).
pub const PICKUP_TARGETS: [Category; 3] = [Category::Bottle, Category::Can, Category::Mug];
pub const MAX_TARGET_RADIUS_M: f32 = 0.036;

/// pickup-v2's targets ([`pickup_v2_scene`]).
pub const PICKUP_V2_TARGETS: [Category; 6] = [
    Category::Bottle,
    Category::FacetedBottle,
    Category::Flask,
    Category::Can,
    Category::Mug,
    Category::Box,
];
/// The widest a pickup-v2 target is across its narrow side.
pub const MAX_V2_NARROW_SIDE_M: f32 = 0.074;

const ATTEMPTS: u64 = 64;

fn camera(config: &SceneConfig, eye: Point3<f32>, at: Point3<f32>) -> Result<Camera, SynthError> {
    Ok(Camera {
        intrinsics: Intrinsics::from_fov(config.width, config.height, config.hfov_deg)?,
        world_from_camera: look_at(&eye, &at, &Vector3::z())?,
    })
}

/// Whether table-top point (x, y) (table frame) is at least `margin` inside the top.
fn on_top(t: &TablePose, x: f32, y: f32, margin: f32) -> bool {
    x.abs() <= t.size.x / 2.0 - margin && y.abs() <= t.size.y / 2.0 - margin
}

/// World x, y to table-top coordinates.
fn to_table(t: &TablePose, x: f32, y: f32) -> (f32, f32) {
    let (c, s) = (t.yaw.cos(), t.yaw.sin());
    let (dx, dy) = (x - t.x, y - t.y);
    (c * dx + s * dy, -s * dx + c * dy)
}

/// Things from the training pool on free spots of the table top.
fn scatter(
    r: &mut impl Rng,
    objects: &mut Vec<SceneObject>,
    table: &TablePose,
    taken: &mut Vec<(f32, f32, f32)>,
    count: usize,
) {
    let half = (table.size.x / 2.0 - 0.03, table.size.y / 2.0 - 0.03);
    for _ in 0..count {
        let c = Category::TABLETOP_TRAIN[r.random_range(0..Category::TABLETOP_TRAIN.len())];
        let shape = shapes::tabletop(c, r);
        let Some((x, y)) = find_spot(r, half, (0.0, 0.0), shape.footprint_radius, taken) else {
            continue;
        };
        taken.push((x, y, shape.footprint_radius));
        let (wx, wy) = table.to_world(x, y);
        let yaw = r.random_range(0.0..std::f32::consts::TAU);
        let app = appearance(r);
        add_object(
            objects,
            c,
            place(shape.mesh, wx, wy, table.size.z, yaw),
            app,
        );
    }
}

/// A pickup scene (see the module docs); `Scene::target` names the target.
pub fn pickup_scene(config: &SceneConfig, seed: u64) -> Result<Scene, SynthError> {
    pickup_of(config, seed, false)
}

/// A pickup-v2 scene (see the module docs); `Scene::target` names the target.
pub fn pickup_v2_scene(config: &SceneConfig, seed: u64) -> Result<Scene, SynthError> {
    pickup_of(config, seed, true)
}

fn pickup_of(config: &SceneConfig, seed: u64, v2: bool) -> Result<Scene, SynthError> {
    let visible = if v2 { 0.05..=0.5 } else { 0.05..=0.95 };
    for k in 0..ATTEMPTS {
        let stream = seed.wrapping_mul(64).wrapping_add(k);
        let Some(scene) = pickup_attempt(config, seed, stream, v2)? else {
            continue;
        };
        if target_visible_fraction(&scene).is_some_and(|f| visible.contains(&f)) {
            return Ok(scene);
        }
    }
    Err(SynthError::Config(format!(
        "pickup seed {seed}: no attempt of {ATTEMPTS} left {:.0}-{:.0}% of the target visible",
        visible.start() * 100.0,
        visible.end() * 100.0
    )))
}

/// A pickup-v2 target of `category` narrow enough for the gripper; `None` when 50 draws were
/// all too wide.
fn v2_target(category: Category, r: &mut impl Rng) -> Option<shapes::Shape> {
    for _ in 0..50 {
        let shape = match category {
            Category::Mug => shapes::mug(r, 0.03, 0.037),
            Category::Box => {
                let s = Vector3::<f32>::new(
                    r.random_range(0.04..0.07),
                    r.random_range(0.04..0.09),
                    r.random_range(0.08..0.18),
                );
                shapes::Shape {
                    footprint_radius: (s.x * s.x + s.y * s.y).sqrt() / 2.0,
                    height: s.z,
                    mesh: box_on(s, (0.0, 0.0), 0.0),
                }
            }
            c => shapes::tabletop(c, r),
        };
        let (lo, hi) = shape.mesh.bounds()?;
        if (hi.x - lo.x).min(hi.y - lo.y) <= MAX_V2_NARROW_SIDE_M {
            return Some(shape);
        }
    }
    None
}

/// The target's visible share of its silhouette in the first view; `None` when it is out of
/// view or touches the image border.
fn target_visible_fraction(scene: &Scene) -> Option<f32> {
    let target = scene.target?;
    let k = scene.objects.iter().position(|o| o.instance_id == target)?;
    let tris = SceneTriangles::new(scene);
    let cam = scene.cameras[0];
    let frame = render_scene(&cam, scene, &tris);
    let visible = frame.instance.iter().filter(|&&i| i == target).count();
    let (w, h) = (frame.width, frame.height);
    let mut coverage = vec![false; w as usize * h as usize];
    let [u0, v0, u1, v1] =
        rasterize_coverage(&cam, &tris, tris.object_ranges[k].clone(), &mut coverage)?;
    if u0 == 0 || v0 == 0 || u1 == w - 1 || v1 == h - 1 {
        return None;
    }
    let amodal = coverage.iter().filter(|&&c| c).count();
    (amodal > 0).then(|| visible as f32 / amodal as f32)
}

fn pickup_attempt(
    config: &SceneConfig,
    seed: u64,
    stream: u64,
    v2: bool,
) -> Result<Option<Scene>, SynthError> {
    let mut r = ChaCha8Rng::seed_from_u64(stream);
    let mut objects = Vec::new();
    let table = room_and_table(&mut r, &mut objects);
    // The target near the middle of the table, the robot on the room's open side.
    let (lx, ly) = (r.random_range(-0.15..0.15), r.random_range(-0.1..0.1));
    let (tx, ty) = table.to_world(lx, ly);
    let top = table.size.z;
    let (category, shape) = if v2 {
        // The seed fixes the kind, so that every kind has its share of the scenes.
        let category = PICKUP_V2_TARGETS[(seed % PICKUP_V2_TARGETS.len() as u64) as usize];
        let Some(shape) = v2_target(category, &mut r) else {
            return Ok(None);
        };
        (category, shape)
    } else {
        let category = PICKUP_TARGETS[r.random_range(0..PICKUP_TARGETS.len())];
        let mut shape = shapes::tabletop(category, &mut r);
        for _ in 0..50 {
            if shape.footprint_radius <= MAX_TARGET_RADIUS_M {
                break;
            }
            shape = shapes::tabletop(category, &mut r);
        }
        if shape.footprint_radius > MAX_TARGET_RADIUS_M {
            return Ok(None);
        }
        (category, shape)
    };
    let az = r.random_range(200f32..250.0).to_radians();
    let to_robot = Vector3::new(az.cos(), az.sin(), 0.0);
    let side = Vector3::new(-az.sin(), az.cos(), 0.0);
    // The occluder between the robot and the target: a large box facing the robot (pickup-v1's
    // only kind), or in pickup-v2 also a tall carton or a wide jar.
    let kind = if v2 { r.random_range(0..3u8) } else { 0 };
    let (w, d) = match kind {
        0 => (r.random_range(0.16..0.3f32), r.random_range(0.05..0.1f32)),
        1 => {
            let s = r.random_range(0.07..0.1f32);
            (s, s)
        }
        _ => {
            let s = 2.0 * r.random_range(0.05..0.08f32);
            (s, s)
        }
    };
    let h = match kind {
        0 => (shape.height * r.random_range(0.6..1.25f32)).clamp(0.08, 0.35),
        1 => r.random_range(0.18..0.26f32).max(shape.height * 0.8),
        _ => (shape.height * r.random_range(0.7..1.2f32)).clamp(0.1, 0.3),
    };
    let gap = r.random_range(0.02..0.08f32);
    let reach = if v2 { 0.6 } else { 1.0 };
    let lateral = r.random_range(-reach..reach) * (w / 2.0 + shape.footprint_radius);
    let oc = Point3::new(tx, ty, top)
        + to_robot * (shape.footprint_radius + d / 2.0 + gap)
        + side * lateral;
    let (ox, oy) = to_table(&table, oc.x, oc.y);
    if !on_top(&table, ox, oy, w / 2.0 + 0.02) || !on_top(&table, lx, ly, 0.1) {
        return Ok(None);
    }
    let yaw = r.random_range(0.0..std::f32::consts::TAU);
    let app = appearance(&mut r);
    let target = add_object(
        &mut objects,
        category,
        place(shape.mesh, tx, ty, top, yaw),
        app,
    );
    let app = appearance(&mut r);
    let (occluder, mesh) = if kind == 2 {
        (Category::Jar, crate::mesh::cylinder(w / 2.0, h, 0.0, 32))
    } else {
        (
            Category::Box,
            box_on(Vector3::new(w, d, h), (0.0, 0.0), 0.0),
        )
    };
    add_object(
        &mut objects,
        occluder,
        place(mesh, oc.x, oc.y, top, az + std::f32::consts::FRAC_PI_2),
        app,
    );
    let mut taken = vec![(lx, ly, shape.footprint_radius), (ox, oy, w / 2.0 + 0.01)];
    let extra = r.random_range(0..=2);
    scatter(&mut r, &mut objects, &table, &mut taken, extra);
    let dist = r.random_range(1.0..1.5f32);
    let eye = Point3::new(tx, ty, 0.0) + to_robot * dist + Vector3::z() * r.random_range(1.2..1.5);
    let at = Point3::new(tx, ty, top + shape.height / 2.0)
        + Vector3::new(
            r.random_range(-0.03..0.03),
            r.random_range(-0.03..0.03),
            0.0,
        );
    Ok(Some(Scene {
        seed,
        objects,
        cameras: vec![camera(config, eye, at)?],
        focus: Point3::new(table.x, table.y, top),
        target: Some(target),
        table: Some(table),
    }))
}

/// A place scene (see the module docs).
pub fn place_scene(config: &SceneConfig, seed: u64) -> Result<Scene, SynthError> {
    for k in 0..ATTEMPTS {
        let scene = place_attempt(config, seed, seed.wrapping_mul(64).wrapping_add(k))?;
        if hidden_free_fraction(&scene) >= 0.3 {
            return Ok(scene);
        }
    }
    Err(SynthError::Config(format!(
        "place seed {seed}: no attempt of {ATTEMPTS} hid 30% of the free table top"
    )))
}

fn place_attempt(config: &SceneConfig, seed: u64, stream: u64) -> Result<Scene, SynthError> {
    let mut r = ChaCha8Rng::seed_from_u64(stream);
    let mut objects = Vec::new();
    let table = room_and_table(&mut r, &mut objects);
    let mut taken = Vec::new();
    let n = r.random_range(
        config.tabletop_objects_min..=config.tabletop_objects_max.max(config.tabletop_objects_min),
    );
    scatter(&mut r, &mut objects, &table, &mut taken, n);
    let az = r.random_range(200f32..250.0).to_radians();
    let dist = r.random_range(1.5..2.5f32);
    let top = table.size.z;
    let eye = Point3::new(table.x + dist * az.cos(), table.y + dist * az.sin(), 0.0)
        + Vector3::z() * r.random_range(1.2..1.6);
    let at = Point3::new(table.x, table.y, top);
    Ok(Scene {
        seed,
        objects,
        cameras: vec![camera(config, eye, at)?],
        focus: at,
        target: None,
        table: Some(table),
    })
}

/// Share of the table top's free surface (2 cm grid, not under a thing's footprint disc) that
/// the scene's first camera does not see.
pub fn hidden_free_fraction(scene: &Scene) -> f32 {
    let Some(table) = scene.table else {
        return 0.0;
    };
    let tris = SceneTriangles::new(scene);
    let cam = scene.cameras[0];
    let frame = render_scene(&cam, scene, &tris);
    let discs: Vec<(f32, f32, f32)> = scene
        .objects
        .iter()
        .filter(|o| !o.category.is_structure() && o.category != Category::Table)
        .filter_map(|o| {
            let (lo, hi) = o.mesh.bounds()?;
            let c = nalgebra::center(&lo, &hi);
            Some((c.x, c.y, (hi.x - lo.x).hypot(hi.y - lo.y) / 2.0))
        })
        .collect();
    let (mut free, mut hidden) = (0usize, 0usize);
    let step = 0.02;
    let (nx, ny) = (
        (table.size.x / step) as i32 / 2,
        (table.size.y / step) as i32 / 2,
    );
    for i in -nx..=nx {
        for j in -ny..=ny {
            let (x, y) = (i as f32 * step, j as f32 * step);
            if !on_top(&table, x, y, 0.01) {
                continue;
            }
            let (wx, wy) = table.to_world(x, y);
            if discs
                .iter()
                .any(|&(cx, cy, rad)| (wx - cx).hypot(wy - cy) <= rad)
            {
                continue;
            }
            free += 1;
            let p = Point3::new(wx, wy, table.size.z);
            if !visible_in(&p, table.instance_id, &cam, &frame) {
                hidden += 1;
            }
        }
    }
    if free == 0 {
        0.0
    } else {
        hidden as f32 / free as f32
    }
}
