//! Procedural indoor scenes: a room corner, a table with things on it, chairs (some pushed under
//! the table), an optional shelf with things on it, and a camera path. Everything random comes
//! from one ChaCha8 generator seeded by the scene's seed, so a config and a seed fix the scene.

use std::path::PathBuf;

use deocc_geometry::camera::{look_at, Camera, Intrinsics};
use nalgebra::{Isometry3, Point3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::mesh::{cuboid, TriMesh};
use crate::shapes::{self, Category};
use crate::SynthError;

/// How the cameras move.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CameraPath {
    /// A robot head 1.0-1.6 m high, looking at the table from a 90 degree arc.
    RobotHead,
    /// A wider arc (150 degrees) around the table.
    Arc,
    /// One view.
    Single,
}

/// A user mesh to place on the table as an object.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct UserMesh {
    pub path: PathBuf,
    /// Largest extent after scaling, metres.
    pub size_m: f32,
}

/// What kind of scene to build.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SceneKind {
    /// A room corner with a table, chairs, things on the table and a shelf (bench-v1).
    #[default]
    Indoor,
    /// A grasp target hidden behind a large occluder on a table, one robot-head view
    /// ([`crate::tasks::pickup_scene`]).
    Pickup,
    /// pickup-v2: harder targets (faceted, flattened, handled, boxes) behind occluders of three
    /// kinds, 50-95% hidden ([`crate::tasks::pickup_v2_scene`]).
    PickupV2,
    /// A cluttered table whose free surface is partly hidden, one view
    /// ([`crate::tasks::place_scene`]).
    Place,
}

/// Everything that shapes a scene except its seed.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(default)]
pub struct SceneConfig {
    pub kind: SceneKind,
    pub width: u32,
    pub height: u32,
    pub hfov_deg: f32,
    pub views: usize,
    pub camera_path: CameraPath,
    pub tabletop_objects_min: usize,
    pub tabletop_objects_max: usize,
    pub chairs_min: usize,
    pub chairs_max: usize,
    /// Probability that a chair has a hollow back.
    pub hollow_back_probability: f64,
    /// Probability of a shelf with objects against the back wall.
    pub shelf_probability: f64,
    /// Allow the held-out shapes (vase, L-bracket): true for test scenes only.
    pub held_out_shapes: bool,
    /// Add the training families the geometric priors get wrong ([`Category::TABLETOP_EXTRA`]:
    /// T and U shapes, frames, stools, small tables) to the table-top pool. Off in the
    /// benchmarks (bench-v1's scenes do not change), on in the training-pair splits.
    pub extra_families: bool,
    /// Add pickup-v2's target families the other pools lack ([`Category::TABLETOP_GRASP`]:
    /// faceted bottles, flasks) to the table-top pool. Off everywhere but the training pairs
    /// made with `PairConfig::grasp_families`.
    pub grasp_families: bool,
    /// Ground-truth surface samples per square metre.
    pub gt_points_per_m2: f32,
    /// The project's first sensor model ([`crate::sensor_kind::SensorKind::Gaussian`]); kept so that
    /// older figures and files reproduce. `sensor` is the general choice.
    pub sensor_noise: bool,
    /// The depth sensor that measures every view ([`crate::sensor`]).
    pub sensor: crate::sensor_kind::SensorKind,
    pub user_meshes: Vec<UserMesh>,
    /// Frames taken from each camera pose (a robot holding still): 1 = one. Each repeat is a
    /// view of its own, measured by the sensor with its own noise, drop-outs and flying pixels;
    /// the scene itself does not change.
    pub burst: usize,
}

impl SceneConfig {
    /// The sensor in force: `sensor`, or the first model when only `sensor_noise` is set.
    pub fn sensor_kind(&self) -> crate::sensor_kind::SensorKind {
        match (self.sensor, self.sensor_noise) {
            (crate::sensor_kind::SensorKind::Clean, true) => {
                crate::sensor_kind::SensorKind::Gaussian
            }
            (k, _) => k,
        }
    }
}

impl Default for SceneConfig {
    fn default() -> Self {
        Self {
            kind: SceneKind::Indoor,
            width: 640,
            height: 480,
            hfov_deg: 60.0,
            views: 10,
            camera_path: CameraPath::RobotHead,
            tabletop_objects_min: 4,
            tabletop_objects_max: 8,
            chairs_min: 0,
            chairs_max: 3,
            hollow_back_probability: 0.5,
            shelf_probability: 0.4,
            held_out_shapes: false,
            extra_families: false,
            grasp_families: false,
            gt_points_per_m2: 10_000.0,
            sensor_noise: false,
            sensor: crate::sensor_kind::SensorKind::Clean,
            user_meshes: Vec::new(),
            burst: 1,
        }
    }
}

/// Surface pattern of an object's albedo.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Texture {
    Solid,
    Stripes { period_m: f32, axis: u8 },
    Checker { period_m: f32 },
    Noise { period_m: f32 },
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Appearance {
    pub color_a: [u8; 3],
    pub color_b: [u8; 3],
    pub texture: Texture,
}

/// One object of a scene, its mesh already in the world frame.
#[derive(Debug, Clone)]
pub struct SceneObject {
    /// 1-based; 0 is "no object" in instance maps.
    pub instance_id: u16,
    pub category: Category,
    pub mesh: TriMesh,
    pub appearance: Appearance,
}

#[derive(Debug, Clone)]
pub struct Scene {
    pub seed: u64,
    pub objects: Vec<SceneObject>,
    pub cameras: Vec<Camera>,
    /// Centre of the table top, what the cameras look at.
    pub focus: Point3<f32>,
    /// The object a task scene is about (the grasp target of `pickup` scenes).
    pub target: Option<u16>,
    pub table: Option<TablePose>,
}

/// A palette shared by all objects, so colour alone does not separate instances.
const PALETTE: [[u8; 3]; 14] = [
    [200, 60, 50],
    [60, 120, 200],
    [230, 190, 60],
    [90, 160, 80],
    [160, 110, 70],
    [220, 220, 215],
    [70, 70, 75],
    [150, 80, 160],
    [240, 140, 60],
    [120, 180, 190],
    [190, 170, 140],
    [110, 40, 40],
    [180, 200, 120],
    [100, 100, 160],
];

impl Scene {
    /// Instance ids of room structure (floor, walls): never completed.
    pub fn structure_ids(&self) -> Vec<u16> {
        self.objects
            .iter()
            .filter(|o| o.category.is_structure())
            .map(|o| o.instance_id)
            .collect()
    }
}

pub(crate) fn appearance(r: &mut impl Rng) -> Appearance {
    let color_a = PALETTE[r.random_range(0..PALETTE.len())];
    let color_b = PALETTE[r.random_range(0..PALETTE.len())];
    let texture = match r.random_range(0..4) {
        0 => Texture::Solid,
        1 => Texture::Stripes {
            period_m: r.random_range(0.01..0.05),
            axis: r.random_range(0..3),
        },
        2 => Texture::Checker {
            period_m: r.random_range(0.02..0.08),
        },
        _ => Texture::Noise {
            period_m: r.random_range(0.02..0.1),
        },
    };
    Appearance {
        color_a,
        color_b,
        texture,
    }
}

pub(crate) fn place(mesh: TriMesh, x: f32, y: f32, z: f32, yaw: f32) -> TriMesh {
    mesh.transformed(&Isometry3::from_parts(
        nalgebra::Translation3::new(x, y, z),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw),
    ))
}

/// Rejection sampling of non-overlapping discs in a rectangle; `None` when it does not fit.
pub(crate) fn find_spot(
    r: &mut impl Rng,
    half: (f32, f32),
    center: (f32, f32),
    radius: f32,
    taken: &[(f32, f32, f32)],
) -> Option<(f32, f32)> {
    if radius >= half.0 || radius >= half.1 {
        return None;
    }
    for _ in 0..60 {
        let x = center.0 + r.random_range(-(half.0 - radius)..(half.0 - radius));
        let y = center.1 + r.random_range(-(half.1 - radius)..(half.1 - radius));
        if taken
            .iter()
            .all(|&(tx, ty, tr)| (tx - x).hypot(ty - y) > tr + radius + 0.005)
        {
            return Some((x, y));
        }
    }
    None
}

/// Room half-size: the floor spans [-ROOM, ROOM]^2; walls stand at x = ROOM and y = ROOM.
const ROOM: f32 = 2.5;

/// A point inside every generated room (above the floor's centre, below the wall tops). The
/// room's structure (floor slab, wall slabs) is solid; only its faces towards this point are
/// surfaces of the scene: the floor's underside and the walls' outsides are not.
pub const ROOM_INTERIOR: Point3<f32> = Point3::new(0.0, 0.0, 1.0);

/// The table of a scene and where it stands.
#[derive(Debug, Clone, Copy)]
pub struct TablePose {
    pub instance_id: u16,
    /// Width, depth and height of the table top.
    pub size: Vector3<f32>,
    pub x: f32,
    pub y: f32,
    pub yaw: f32,
}

impl TablePose {
    /// Table-top coordinates (x along the width, y along the depth) to world x, y.
    pub fn to_world(&self, x: f32, y: f32) -> (f32, f32) {
        let (c, s) = (self.yaw.cos(), self.yaw.sin());
        (self.x + c * x - s * y, self.y + s * x + c * y)
    }
}

/// Appends an object with the next instance id.
pub(crate) fn add_object(
    objects: &mut Vec<SceneObject>,
    category: Category,
    mesh: TriMesh,
    appearance: Appearance,
) -> u16 {
    let instance_id = objects.len() as u16 + 1;
    objects.push(SceneObject {
        instance_id,
        category,
        mesh,
        appearance,
    });
    instance_id
}

/// The floor, the two walls and the table near the room's centre, rotated a little.
pub(crate) fn room_and_table(r: &mut impl Rng, objects: &mut Vec<SceneObject>) -> TablePose {
    let floor_app = Appearance {
        color_a: [150, 140, 130],
        color_b: [120, 110, 100],
        texture: Texture::Checker { period_m: 0.3 },
    };
    add_object(
        objects,
        Category::Floor,
        cuboid(
            Point3::new(-ROOM, -ROOM, -0.02),
            Point3::new(ROOM, ROOM, 0.0),
        ),
        floor_app,
    );
    let wall_app = Appearance {
        color_a: [215, 210, 200],
        color_b: [200, 195, 185],
        texture: Texture::Noise { period_m: 0.5 },
    };
    add_object(
        objects,
        Category::Wall,
        cuboid(
            Point3::new(ROOM, -ROOM, 0.0),
            Point3::new(ROOM + 0.05, ROOM, 2.5),
        ),
        wall_app,
    );
    add_object(
        objects,
        Category::Wall,
        cuboid(
            Point3::new(-ROOM, ROOM, 0.0),
            Point3::new(ROOM, ROOM + 0.05, 2.5),
        ),
        wall_app,
    );
    let (table, size) = shapes::table(r);
    let (tx, ty) = (r.random_range(-0.3..0.3), r.random_range(-0.3..0.3));
    let table_yaw = r.random_range(-0.3..0.3f32);
    let app = appearance(r);
    let instance_id = add_object(
        objects,
        Category::Table,
        place(table.mesh, tx, ty, 0.0, table_yaw),
        app,
    );
    TablePose {
        instance_id,
        size,
        x: tx,
        y: ty,
        yaw: table_yaw,
    }
}

/// An indoor scene (bench-v1's kind); [`crate::generate::generate_scene`] picks the kind.
pub fn indoor_scene(config: &SceneConfig, seed: u64) -> Result<Scene, SynthError> {
    let mut r = ChaCha8Rng::seed_from_u64(seed);
    let mut objects = Vec::new();
    let add = |objects: &mut Vec<SceneObject>, category, mesh, app| {
        add_object(objects, category, mesh, app);
    };
    let table = room_and_table(&mut r, &mut objects);
    let (size, tx, ty, table_yaw) = (table.size, table.x, table.y, table.yaw);
    let to_world = |x: f32, y: f32| table.to_world(x, y);

    // Chairs along the long sides, some pushed under the table.
    let n_chairs = r.random_range(config.chairs_min.min(config.chairs_max)..=config.chairs_max);
    for k in 0..n_chairs {
        let chair = shapes::chair(&mut r, config.hollow_back_probability);
        let side = if k % 2 == 0 { -1.0 } else { 1.0 };
        let along = r.random_range(-size.x * 0.3..size.x * 0.3);
        let pushed_in = r.random_bool(0.5);
        let off = size.y / 2.0
            + if pushed_in {
                -0.05
            } else {
                r.random_range(0.15..0.35)
            };
        let (x, y) = to_world(along, side * off);
        // Chair back away from the table: the chair faces -y in its frame.
        let yaw = table_yaw
            + if side < 0.0 {
                0.0
            } else {
                std::f32::consts::PI
            }
            + r.random_range(-0.2..0.2);
        let app = appearance(&mut r);
        add(
            &mut objects,
            Category::Chair,
            place(chair.mesh, x, y, 0.0, yaw),
            app,
        );
    }

    // Things on the table.
    let mut pool: Vec<Category> = Category::TABLETOP_TRAIN.to_vec();
    if config.extra_families {
        pool.extend(Category::TABLETOP_EXTRA);
    }
    if config.grasp_families {
        pool.extend(Category::TABLETOP_GRASP);
    }
    if config.held_out_shapes {
        pool.extend(Category::TABLETOP_HELD_OUT);
    }
    let user_meshes = load_user_meshes(config)?;
    let n_objects = r.random_range(
        config.tabletop_objects_min..=config.tabletop_objects_max.max(config.tabletop_objects_min),
    );
    let mut taken = Vec::new();
    let half = (size.x / 2.0 - 0.03, size.y / 2.0 - 0.03);
    // User meshes first, so that they find room (the scene is generated around them), and an
    // error when one cannot be placed: a user's mesh is never silently left out.
    let n_user = user_meshes.len();
    for k in 0..n_objects + n_user {
        let (category, shape) = if let Some(m) = user_meshes.get(k) {
            (
                Category::UserMesh,
                shapes::Shape {
                    mesh: m.0.clone(),
                    footprint_radius: m.1,
                    height: m.2,
                },
            )
        } else {
            // Held-out shapes appear with a boosted rate in test scenes so their figures mean something.
            let c = if config.held_out_shapes && r.random_bool(0.25) {
                Category::TABLETOP_HELD_OUT[r.random_range(0..2)]
            } else {
                pool[r.random_range(0..pool.len())]
            };
            (c, shapes::tabletop(c, &mut r))
        };
        let Some((x, y)) = find_spot(&mut r, half, (0.0, 0.0), shape.footprint_radius, &taken)
        else {
            if let Some(u) = config.user_meshes.get(k) {
                return Err(SynthError::Config(format!(
                    "{}: a mesh {} m across (footprint radius {:.2} m) does not fit on this \
                     scene's {:.2} x {:.2} m table top; give a smaller size (at most about {:.2} m)",
                    u.path.display(),
                    u.size_m,
                    shape.footprint_radius,
                    size.x,
                    size.y,
                    (half.0.min(half.1) * std::f32::consts::SQRT_2).max(0.0)
                )));
            }
            continue;
        };
        taken.push((x, y, shape.footprint_radius));
        let (wx, wy) = to_world(x, y);
        let yaw = r.random_range(0.0..std::f32::consts::TAU);
        let app = appearance(&mut r);
        add(
            &mut objects,
            category,
            place(shape.mesh, wx, wy, size.z, yaw),
            app,
        );
    }

    // A shelf against the back wall (y = ROOM), with things on its boards.
    if r.random_bool(config.shelf_probability) {
        let (shelf, ssize, tops) = shapes::shelf(&mut r);
        let sx = r.random_range(-1.2..1.2f32);
        let sy = ROOM - ssize.y / 2.0 - 0.01;
        let app = appearance(&mut r);
        add(
            &mut objects,
            Category::Shelf,
            place(shelf.mesh, sx, sy, 0.0, 0.0),
            app,
        );
        for &z in &tops[..tops.len() - 1] {
            let mut taken = Vec::new();
            for _ in 0..r.random_range(1..4) {
                let c = pool[r.random_range(0..pool.len())];
                let shape = shapes::tabletop(c, &mut r);
                let board_gap = (tops[1] - tops[0]) - 0.03;
                if shape.height > board_gap {
                    continue;
                }
                let half = (ssize.x / 2.0 - 0.03, ssize.y / 2.0 - 0.03);
                let Some((x, y)) =
                    find_spot(&mut r, half, (0.0, 0.0), shape.footprint_radius, &taken)
                else {
                    continue;
                };
                taken.push((x, y, shape.footprint_radius));
                let yaw = r.random_range(0.0..std::f32::consts::TAU);
                let app = appearance(&mut r);
                add(
                    &mut objects,
                    c,
                    place(shape.mesh, sx + x, sy + y, z, yaw),
                    app,
                );
            }
        }
    }

    let focus = Point3::new(tx, ty, size.z);
    let cameras = camera_path(config, &mut r, &focus)?;
    Ok(Scene {
        seed,
        objects,
        cameras,
        focus,
        target: None,
        table: Some(table),
    })
}

fn load_user_meshes(config: &SceneConfig) -> Result<Vec<(TriMesh, f32, f32)>, SynthError> {
    config
        .user_meshes
        .iter()
        .map(|u| {
            let m = deocc_io::mesh::read_mesh(&u.path)?;
            let mesh = TriMesh {
                vertices: m.vertices.positions,
                triangles: m.triangles,
            };
            let (lo, hi) = mesh
                .bounds()
                .ok_or_else(|| SynthError::Config(format!("{}: empty mesh", u.path.display())))?;
            // In f64: coordinates near f32's limits (or its denormals) have extents f32 cannot
            // hold.
            let (lo, hi) = (lo.cast::<f64>(), hi.cast::<f64>());
            let extent = (hi - lo).max();
            if !(extent.is_finite() && extent > 0.0) {
                return Err(SynthError::Config(format!(
                    "{}: the mesh's extent ({extent:e}) is not a positive finite size",
                    u.path.display()
                )));
            }
            if !(u.size_m.is_finite() && u.size_m > 0.0) {
                return Err(SynthError::Config(format!(
                    "{}: size {} m must be positive",
                    u.path.display(),
                    u.size_m
                )));
            }
            let s = f64::from(u.size_m) / extent;
            let c = nalgebra::center(&lo, &hi);
            let vertices = mesh
                .vertices
                .iter()
                .map(|v| {
                    let v = v.cast::<f64>();
                    nalgebra::Point3::new((v.x - c.x) * s, (v.y - c.y) * s, (v.z - lo.z) * s)
                        .cast::<f32>()
                })
                .collect();
            let mesh = TriMesh {
                vertices,
                triangles: mesh.triangles,
            };
            let radius = (((hi.x - lo.x).hypot(hi.y - lo.y)) * s / 2.0) as f32;
            Ok((mesh, radius, ((hi.z - lo.z) * s) as f32))
        })
        .collect()
}

fn camera_path(
    config: &SceneConfig,
    r: &mut impl Rng,
    focus: &Point3<f32>,
) -> Result<Vec<Camera>, SynthError> {
    let intrinsics = Intrinsics::from_fov(config.width, config.height, config.hfov_deg)?;
    // Cameras stay on the open side of the room (walls at +x and +y).
    let center_az = r.random_range(200f32..250.0).to_radians();
    let (span, n) = match config.camera_path {
        CameraPath::RobotHead => (90f32.to_radians(), config.views),
        CameraPath::Arc => (150f32.to_radians(), config.views),
        CameraPath::Single => (0.0, 1),
    };
    let n = n.max(1);
    let dist = r.random_range(1.3..1.9f32);
    let height = r.random_range(1.0..1.6f32);
    (0..n)
        .map(|i| {
            let t = if n == 1 {
                0.5
            } else {
                i as f32 / (n - 1) as f32
            };
            let az = center_az + span * (t - 0.5);
            let d = dist + r.random_range(-0.1..0.1);
            let eye = Point3::new(
                focus.x + d * az.cos(),
                focus.y + d * az.sin(),
                height + r.random_range(-0.05..0.05),
            );
            let target = focus
                + Vector3::new(
                    r.random_range(-0.1..0.1),
                    r.random_range(-0.1..0.1),
                    r.random_range(-0.1..0.05),
                );
            Ok(Camera {
                intrinsics,
                world_from_camera: look_at(&eye, &target, &Vector3::z())?,
            })
        })
        .collect()
}
