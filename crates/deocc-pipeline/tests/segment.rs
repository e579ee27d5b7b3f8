//! The default segmenter can label pixels without depth from the colour image
//! (`hole_max_cost`): a projector's shadow on the wall behind a box goes to the wall, a drop-out
//! inside the box to the box, a large hole stays unlabelled; without RGB, or with the rule off
//! (the default), nothing changes.

use deocc_geometry::camera::{Camera, Intrinsics};
use deocc_geometry::DepthMap;
use deocc_pipeline::segment::ConvexitySegmenter;
use image::{Rgb, RgbImage};
use nalgebra::Isometry3;

const W: u32 = 80;
const H: u32 = 60;

/// A textured wall at 2 m, a red box at 1 m in columns 20..36, rows 15..45; a shadow band of
/// five columns (36..41) right of the box with the wall's colours and no depth; a 2x2 drop-out
/// inside the box; a 20x16 hole without depth in the bottom-left corner.
fn frame() -> (DepthMap, RgbImage, Camera) {
    let mut depth = vec![2.0f32; (W * H) as usize];
    let mut rgb = RgbImage::new(W, H);
    for v in 0..H {
        for u in 0..W {
            let i = (v * W + u) as usize;
            let in_box = (20..36).contains(&u) && (15..45).contains(&v);
            let checker = ((u / 4) + (v / 4)) % 2 == 0;
            let wall = if checker {
                Rgb([200, 200, 190])
            } else {
                Rgb([60, 70, 60])
            };
            rgb.put_pixel(u, v, if in_box { Rgb([200, 30, 30]) } else { wall });
            if in_box {
                depth[i] = 1.0;
            }
            let shadow = (36..41).contains(&u) && (15..45).contains(&v);
            let dropout = (27..29).contains(&u) && (30..32).contains(&v);
            let corner = u < 20 && v >= 44;
            if shadow || dropout || corner {
                depth[i] = 0.0;
            }
        }
    }
    let camera = Camera {
        intrinsics: Intrinsics::from_fov(W, H, 60.0).unwrap(),
        world_from_camera: Isometry3::identity(),
    };
    (DepthMap::new(W, H, depth).unwrap(), rgb, camera)
}

/// The segmenter with hole labelling on, at the value tuned for masks.
fn colour_holes() -> ConvexitySegmenter {
    ConvexitySegmenter {
        hole_max_cost: 10.0,
        ..Default::default()
    }
}

fn id_at(ids: &[u16], u: u32, v: u32) -> u16 {
    ids[(v * W + u) as usize]
}

#[test]
fn holes_take_the_label_of_the_surface_they_match_in_colour() {
    let (depth, rgb, camera) = frame();
    let seg = colour_holes();
    let map = seg.segment_rgbd(&depth, Some(&rgb), &camera);
    let (wall, boxx) = (id_at(&map.ids, 60, 30), id_at(&map.ids, 25, 20));
    assert!(
        wall != 0 && boxx != 0 && wall != boxx,
        "wall {wall}, box {boxx}"
    );
    // The box's own drop-out joins the box.
    for (u, v) in [(27, 30), (28, 31)] {
        assert_eq!(id_at(&map.ids, u, v), boxx, "drop-out ({u}, {v})");
    }
    // No shadow pixel goes to the box; the column next to the measured wall (the same checker
    // square as its neighbour) goes to the wall.
    for v in 15..45 {
        for u in 36..41 {
            assert_ne!(
                id_at(&map.ids, u, v),
                boxx,
                "shadow ({u}, {v}) went to the box"
            );
        }
        assert_eq!(
            id_at(&map.ids, 40, v),
            wall,
            "shadow (40, {v}) next to the wall"
        );
    }
    // Deep inside the large hole nothing is measured within reach: unlabelled.
    assert_eq!(id_at(&map.ids, 8, 54), 0);
    // Without depth-only segmentation's holes labelled, the same pixels are 0; measured pixels
    // keep their labels.
    let plain = seg.segment_depth(&depth, &camera);
    for ((&z, &p), &m) in depth.data().iter().zip(&plain.ids).zip(&map.ids) {
        if z > 0.0 {
            assert_eq!(p, m);
        } else {
            assert_eq!(p, 0);
        }
    }
}

#[test]
fn without_rgb_or_with_the_rule_off_holes_stay_unlabelled() {
    let (depth, rgb, camera) = frame();
    let plain = ConvexitySegmenter::default().segment_depth(&depth, &camera);
    // Off by default.
    let default = ConvexitySegmenter::default();
    assert_eq!(default.hole_max_cost, 0.0);
    assert_eq!(
        default.segment_rgbd(&depth, Some(&rgb), &camera).ids,
        plain.ids
    );
    // On, but without RGB or with a colour image of another size: not used.
    let on = colour_holes();
    assert_eq!(on.segment_rgbd(&depth, None, &camera).ids, plain.ids);
    let small = RgbImage::new(W / 2, H / 2);
    assert_eq!(
        on.segment_rgbd(&depth, Some(&small), &camera).ids,
        plain.ids
    );
    // And on with the right image, it does label something.
    assert_ne!(on.segment_rgbd(&depth, Some(&rgb), &camera).ids, plain.ids);
}
