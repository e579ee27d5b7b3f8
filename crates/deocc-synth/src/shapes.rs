//! Furniture and household objects with realistic dimensions (metres), each built in its own frame:
//! centred on the z axis, standing on z = 0.

use nalgebra::{Point3, Vector3};
use rand::Rng;
use serde::{Deserialize, Serialize};

use crate::mesh::{box_on, cuboid, cylinder, lathe, tube_arc, TriMesh};

/// Object categories. `Vase` and `LBracket` are held out of training (never in `train` pairs) so
/// that the test split measures generalisation to unseen shapes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Category {
    Floor,
    Wall,
    Table,
    Chair,
    Shelf,
    Box,
    Bottle,
    Mug,
    Bowl,
    Can,
    Book,
    Jar,
    Vase,
    LBracket,
    UserMesh,
    /// A T-shaped block (a stem under a crossbar): non-convex.
    TBracket,
    /// A U-shaped channel standing upright: non-convex, with a gap between its arms.
    UChannel,
    /// A picture frame standing upright: a hollow rectangle.
    Frame,
    /// A stool: a round or square seat on three or four legs, table-top scale.
    Stool,
    /// A small table: a top on four legs, table-top scale (the chair-legs case in miniature).
    MiniTable,
    /// A bottle whose body is a hexagonal or octagonal prism under a shoulder and neck: faceted
    /// (pickup-v2's targets).
    FacetedBottle,
    /// A flask: a shouldered bottle squashed to an elliptical section, twice as wide one way as
    /// the other: not a solid of revolution (pickup-v2's targets).
    Flask,
}

impl Category {
    /// Support surfaces and room structure: segments of their own, never "objects to complete".
    pub fn is_structure(self) -> bool {
        matches!(self, Category::Floor | Category::Wall)
    }

    /// Categories whose shapes never appear in training pairs.
    pub fn is_held_out(self) -> bool {
        matches!(self, Category::Vase | Category::LBracket)
    }

    pub fn name(self) -> &'static str {
        match self {
            Category::Floor => "floor",
            Category::Wall => "wall",
            Category::Table => "table",
            Category::Chair => "chair",
            Category::Shelf => "shelf",
            Category::Box => "box",
            Category::Bottle => "bottle",
            Category::Mug => "mug",
            Category::Bowl => "bowl",
            Category::Can => "can",
            Category::Book => "book",
            Category::Jar => "jar",
            Category::Vase => "vase",
            Category::LBracket => "l_bracket",
            Category::UserMesh => "user_mesh",
            Category::TBracket => "t_bracket",
            Category::UChannel => "u_channel",
            Category::Frame => "frame",
            Category::Stool => "stool",
            Category::MiniTable => "mini_table",
            Category::FacetedBottle => "faceted_bottle",
            Category::Flask => "flask",
        }
    }

    /// Small objects that stand on tables and shelves.
    pub const TABLETOP_TRAIN: [Category; 7] = [
        Category::Box,
        Category::Bottle,
        Category::Mug,
        Category::Bowl,
        Category::Can,
        Category::Book,
        Category::Jar,
    ];
    pub const TABLETOP_HELD_OUT: [Category; 2] = [Category::Vase, Category::LBracket];
    /// Training families whose silhouettes the geometric priors get wrong (holes, gaps, legs,
    /// non-convex outlines); in scenes with `SceneConfig::extra_families` (the pair splits).
    pub const TABLETOP_EXTRA: [Category; 5] = [
        Category::TBracket,
        Category::UChannel,
        Category::Frame,
        Category::Stool,
        Category::MiniTable,
    ];

    /// pickup-v2's target families the other pools lack (faceted bottles, flasks); in the
    /// training-pair splits made with `PairConfig::grasp_families`.
    pub const TABLETOP_GRASP: [Category; 2] = [Category::FacetedBottle, Category::Flask];

    /// Every category, in declaration order (the order of the `u8` codes in pair shards).
    pub const ALL: [Category; 22] = [
        Category::Floor,
        Category::Wall,
        Category::Table,
        Category::Chair,
        Category::Shelf,
        Category::Box,
        Category::Bottle,
        Category::Mug,
        Category::Bowl,
        Category::Can,
        Category::Book,
        Category::Jar,
        Category::Vase,
        Category::LBracket,
        Category::UserMesh,
        Category::TBracket,
        Category::UChannel,
        Category::Frame,
        Category::Stool,
        Category::MiniTable,
        Category::FacetedBottle,
        Category::Flask,
    ];

    /// The category of a `u8` code of a pair shard.
    pub fn from_code(code: u8) -> Option<Category> {
        Self::ALL.get(code as usize).copied()
    }
}

/// A built shape: mesh in its own frame plus the radius of its footprint (for placement).
pub struct Shape {
    pub mesh: TriMesh,
    pub footprint_radius: f32,
    pub height: f32,
}

fn u(r: &mut impl Rng, lo: f32, hi: f32) -> f32 {
    r.random_range(lo..hi)
}

const SEG: usize = 24;

pub fn table(r: &mut impl Rng) -> (Shape, Vector3<f32>) {
    let (w, d, h) = (u(r, 0.9, 1.6), u(r, 0.6, 1.0), u(r, 0.70, 0.78));
    let t = u(r, 0.03, 0.05);
    let leg = u(r, 0.04, 0.07);
    let inset = u(r, 0.03, 0.1);
    let mut parts = vec![box_on(Vector3::new(w, d, t), (0.0, 0.0), h - t)];
    for (sx, sy) in [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)] {
        let c = (
            sx * (w / 2.0 - inset - leg / 2.0),
            sy * (d / 2.0 - inset - leg / 2.0),
        );
        parts.push(box_on(Vector3::new(leg, leg, h - t), c, 0.0));
    }
    (
        Shape {
            mesh: TriMesh::merged(&parts),
            footprint_radius: (w * w + d * d).sqrt() / 2.0,
            height: h,
        },
        Vector3::new(w, d, h),
    )
}

/// A chair facing -y (its back at +y). With probability `hollow_back` its back is hollow (two
/// posts and a top rail), the non-convex case that fragments masks.
pub fn chair(r: &mut impl Rng, hollow_back: f64) -> Shape {
    let (w, d) = (u(r, 0.40, 0.50), u(r, 0.40, 0.50));
    let seat_h = u(r, 0.42, 0.48);
    let t = 0.04;
    let leg = u(r, 0.03, 0.045);
    let back_h = u(r, 0.35, 0.50);
    let mut parts = vec![box_on(Vector3::new(w, d, t), (0.0, 0.0), seat_h - t)];
    for (sx, sy) in [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)] {
        let c = (sx * (w - leg) / 2.0, sy * (d - leg) / 2.0);
        parts.push(box_on(Vector3::new(leg, leg, seat_h - t), c, 0.0));
    }
    let back_y = d / 2.0 - 0.02;
    if r.random_bool(1.0 - hollow_back) {
        parts.push(box_on(Vector3::new(w, 0.03, back_h), (0.0, back_y), seat_h));
    } else {
        for sx in [-1.0, 1.0] {
            parts.push(box_on(
                Vector3::new(leg, 0.03, back_h),
                (sx * (w - leg) / 2.0, back_y),
                seat_h,
            ));
        }
        parts.push(box_on(
            Vector3::new(w, 0.03, 0.08),
            (0.0, back_y),
            seat_h + back_h - 0.08,
        ));
    }
    Shape {
        mesh: TriMesh::merged(&parts),
        footprint_radius: (w * w + d * d).sqrt() / 2.0,
        height: seat_h + back_h,
    }
}

/// An open shelf unit facing -y: two sides, a back, and `levels` boards. Returns the shape and the
/// heights of the boards' top surfaces.
pub fn shelf(r: &mut impl Rng) -> (Shape, Vector3<f32>, Vec<f32>) {
    let (w, d, h) = (u(r, 0.6, 1.0), u(r, 0.3, 0.4), u(r, 0.9, 1.4));
    let t = 0.02;
    let levels = r.random_range(3..5usize);
    let mut parts = vec![
        cuboid(
            Point3::new(-w / 2.0, -d / 2.0, 0.0),
            Point3::new(-w / 2.0 + t, d / 2.0, h),
        ),
        cuboid(
            Point3::new(w / 2.0 - t, -d / 2.0, 0.0),
            Point3::new(w / 2.0, d / 2.0, h),
        ),
        cuboid(
            Point3::new(-w / 2.0, d / 2.0 - t, 0.0),
            Point3::new(w / 2.0, d / 2.0, h),
        ),
    ];
    let mut tops = Vec::new();
    for k in 0..levels {
        let z = 0.05 + (h - 0.05 - t) * k as f32 / (levels - 1) as f32;
        parts.push(cuboid(
            Point3::new(-w / 2.0 + t, -d / 2.0, z),
            Point3::new(w / 2.0 - t, d / 2.0 - t, z + t),
        ));
        tops.push(z + t);
    }
    (
        Shape {
            mesh: TriMesh::merged(&parts),
            footprint_radius: (w * w + d * d).sqrt() / 2.0,
            height: h,
        },
        Vector3::new(w, d, h),
        tops,
    )
}

/// A tabletop object of the given category.
pub fn tabletop(category: Category, r: &mut impl Rng) -> Shape {
    match category {
        Category::Box => {
            let s = Vector3::new(u(r, 0.06, 0.25), u(r, 0.06, 0.2), u(r, 0.05, 0.25));
            Shape {
                footprint_radius: (s.x * s.x + s.y * s.y).sqrt() / 2.0,
                height: s.z,
                mesh: box_on(s, (0.0, 0.0), 0.0),
            }
        }
        Category::Book => {
            // Standing upright: thin in x.
            let s = Vector3::new(u(r, 0.02, 0.05), u(r, 0.13, 0.22), u(r, 0.18, 0.28));
            Shape {
                footprint_radius: (s.x * s.x + s.y * s.y).sqrt() / 2.0,
                height: s.z,
                mesh: box_on(s, (0.0, 0.0), 0.0),
            }
        }
        Category::Can => {
            let (rad, h) = (u(r, 0.03, 0.045), u(r, 0.10, 0.16));
            Shape {
                footprint_radius: rad,
                height: h,
                mesh: cylinder(rad, h, 0.0, SEG),
            }
        }
        Category::Jar => {
            let (rad, h) = (u(r, 0.04, 0.07), u(r, 0.10, 0.20));
            let lid = rad * 0.9;
            let m = lathe(
                &[(rad, 0.0), (rad, h * 0.85), (lid, h * 0.87), (lid, h)],
                SEG,
                true,
                true,
            );
            Shape {
                footprint_radius: rad,
                height: h,
                mesh: m,
            }
        }
        Category::Bottle => {
            let (rad, h) = (u(r, 0.03, 0.05), u(r, 0.2, 0.32));
            let neck = rad * u(r, 0.3, 0.45);
            let body = h * u(r, 0.55, 0.7);
            bottle(rad, h, neck, body, SEG)
        }
        Category::Mug => mug(r, 0.035, 0.05),
        Category::FacetedBottle => {
            let (rad, h) = (u(r, 0.028, 0.036), u(r, 0.18, 0.28));
            let sides = if r.random_bool(0.5) { 6 } else { 8 };
            let neck = rad * u(r, 0.35, 0.45);
            let body = h * u(r, 0.55, 0.7);
            bottle(rad, h, neck, body, sides)
        }
        Category::Flask => {
            let (rad, h) = (u(r, 0.045, 0.06), u(r, 0.16, 0.24));
            let squash = u(r, 0.45, 0.6);
            let neck = 0.012;
            let body = h * u(r, 0.6, 0.72);
            let m = lathe(
                &[
                    (rad, 0.0),
                    (rad, body),
                    (neck / squash, body + (h - body) * 0.6),
                    (neck / squash, h),
                ],
                SEG,
                true,
                true,
            )
            .scaled(Vector3::new(1.0, squash, 1.0));
            Shape {
                footprint_radius: rad,
                height: h,
                mesh: m,
            }
        }
        _ => tabletop_other(category, r),
    }
}

/// A shouldered bottle of body radius `rad` and height `h`: the body up to `body`, a shoulder
/// halfway up the rest, a neck of radius `neck`; `segments` sides around (6 or 8: faceted).
fn bottle(rad: f32, h: f32, neck: f32, body: f32, segments: usize) -> Shape {
    let mesh = lathe(
        &[
            (rad, 0.0),
            (rad, body),
            (neck, body + (h - body) * 0.5),
            (neck, h),
        ],
        segments,
        true,
        true,
    );
    Shape {
        footprint_radius: rad,
        height: h,
        mesh,
    }
}

/// A mug whose body radius is drawn from `[lo, hi)`: a wall with a rim and an inner bottom, and
/// a handle on +x.
pub fn mug(r: &mut impl Rng, lo: f32, hi: f32) -> Shape {
    let (rad, h) = (u(r, lo, hi), u(r, 0.08, 0.12));
    let wall = 0.006;
    // Outer wall, rim, inner wall down to an inner bottom.
    let body = lathe(
        &[(rad, 0.0), (rad, h), (rad - wall, h), (rad - wall, wall)],
        SEG,
        true,
        true,
    );
    let handle =
        tube_arc(h * 0.3, 0.008, -1.4, 1.4, 10, 6).translated(Vector3::new(rad, 0.0, h * 0.5));
    Shape {
        footprint_radius: rad + h * 0.3,
        height: h,
        mesh: TriMesh::merged(&[body, handle]),
    }
}

fn tabletop_other(category: Category, r: &mut impl Rng) -> Shape {
    match category {
        Category::Bowl => {
            let (rad, h) = (u(r, 0.06, 0.11), u(r, 0.04, 0.07));
            let wall = 0.005;
            let base = rad * 0.45;
            let m = lathe(
                &[
                    (base, 0.0),
                    (rad * 0.85, h * 0.6),
                    (rad, h),
                    (rad - wall, h),
                    (rad * 0.85 - wall, h * 0.6 + wall),
                    (base - wall, wall),
                ],
                SEG,
                true,
                true,
            );
            Shape {
                footprint_radius: rad,
                height: h,
                mesh: m,
            }
        }
        Category::Vase => {
            let (rad, h) = (u(r, 0.04, 0.07), u(r, 0.18, 0.3));
            let m = lathe(
                &[
                    (rad * 0.6, 0.0),
                    (rad, h * 0.35),
                    (rad * 0.45, h * 0.75),
                    (rad * 0.6, h),
                ],
                SEG,
                true,
                true,
            );
            Shape {
                footprint_radius: rad,
                height: h,
                mesh: m,
            }
        }
        Category::LBracket => {
            // An L-shaped block: non-convex, so the convex hull of its visible part is wrong.
            let (w, d, h) = (u(r, 0.12, 0.22), u(r, 0.06, 0.1), u(r, 0.12, 0.22));
            let t = u(r, 0.03, 0.05);
            let m = TriMesh::merged(&[
                cuboid(
                    Point3::new(-w / 2.0, -d / 2.0, 0.0),
                    Point3::new(w / 2.0, d / 2.0, t),
                ),
                cuboid(
                    Point3::new(-w / 2.0, -d / 2.0, t),
                    Point3::new(-w / 2.0 + t, d / 2.0, h),
                ),
            ]);
            Shape {
                footprint_radius: (w * w + d * d).sqrt() / 2.0,
                height: h,
                mesh: m,
            }
        }
        Category::TBracket => {
            let (w, d, h) = (u(r, 0.10, 0.22), u(r, 0.04, 0.08), u(r, 0.12, 0.24));
            let (t, stem) = (u(r, 0.025, 0.05), u(r, 0.025, 0.05));
            let m = TriMesh::merged(&[
                cuboid(
                    Point3::new(-stem / 2.0, -d / 2.0, 0.0),
                    Point3::new(stem / 2.0, d / 2.0, h - t),
                ),
                cuboid(
                    Point3::new(-w / 2.0, -d / 2.0, h - t),
                    Point3::new(w / 2.0, d / 2.0, h),
                ),
            ]);
            Shape {
                footprint_radius: (w * w + d * d).sqrt() / 2.0,
                height: h,
                mesh: m,
            }
        }
        Category::UChannel => {
            let (w, d, h) = (u(r, 0.10, 0.22), u(r, 0.04, 0.08), u(r, 0.10, 0.22));
            let t = u(r, 0.02, 0.04);
            let m = TriMesh::merged(&[
                cuboid(
                    Point3::new(-w / 2.0, -d / 2.0, 0.0),
                    Point3::new(w / 2.0, d / 2.0, t),
                ),
                cuboid(
                    Point3::new(-w / 2.0, -d / 2.0, t),
                    Point3::new(-w / 2.0 + t, d / 2.0, h),
                ),
                cuboid(
                    Point3::new(w / 2.0 - t, -d / 2.0, t),
                    Point3::new(w / 2.0, d / 2.0, h),
                ),
            ]);
            Shape {
                footprint_radius: (w * w + d * d).sqrt() / 2.0,
                height: h,
                mesh: m,
            }
        }
        Category::Frame => {
            // Upright in the x-z plane, thin in y, on a small foot so it stands.
            let (w, h, d) = (u(r, 0.12, 0.26), u(r, 0.12, 0.26), u(r, 0.015, 0.03));
            let t = u(r, 0.015, 0.035);
            let m = TriMesh::merged(&[
                cuboid(
                    Point3::new(-w / 2.0, -d / 2.0, 0.0),
                    Point3::new(w / 2.0, d / 2.0, t),
                ),
                cuboid(
                    Point3::new(-w / 2.0, -d / 2.0, h - t),
                    Point3::new(w / 2.0, d / 2.0, h),
                ),
                cuboid(
                    Point3::new(-w / 2.0, -d / 2.0, t),
                    Point3::new(-w / 2.0 + t, d / 2.0, h - t),
                ),
                cuboid(
                    Point3::new(w / 2.0 - t, -d / 2.0, t),
                    Point3::new(w / 2.0, d / 2.0, h - t),
                ),
                cuboid(
                    Point3::new(-w / 4.0, -2.0 * d, 0.0),
                    Point3::new(w / 4.0, 2.0 * d, t / 2.0),
                ),
            ]);
            Shape {
                footprint_radius: (w * w + 16.0 * d * d).sqrt() / 2.0,
                height: h,
                mesh: m,
            }
        }
        Category::Stool | Category::MiniTable => {
            let mini_table = category == Category::MiniTable;
            let (w, d) = if mini_table {
                (u(r, 0.12, 0.26), u(r, 0.10, 0.20))
            } else {
                let s = u(r, 0.08, 0.16);
                (s, s)
            };
            let h = u(r, 0.08, 0.2);
            let (top, leg) = (u(r, 0.012, 0.025), u(r, 0.008, 0.016));
            let mut parts = vec![if !mini_table && r.random_bool(0.5) {
                cylinder(w / 2.0, top, h - top, SEG)
            } else {
                box_on(Vector3::new(w, d, top), (0.0, 0.0), h - top)
            }];
            let legs: &[(f32, f32)] = if !mini_table && r.random_bool(0.4) {
                &[(0.0, -1.0), (-0.87, 0.5), (0.87, 0.5)]
            } else {
                &[(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)]
            };
            let inset = 0.75;
            for &(sx, sy) in legs {
                let c = (sx * inset * (w - leg) / 2.0, sy * inset * (d - leg) / 2.0);
                parts.push(box_on(Vector3::new(leg, leg, h - top), c, 0.0));
            }
            Shape {
                footprint_radius: (w * w + d * d).sqrt() / 2.0,
                height: h,
                mesh: TriMesh::merged(&parts),
            }
        }
        other => panic!("{other:?} is not a tabletop category"),
    }
}
