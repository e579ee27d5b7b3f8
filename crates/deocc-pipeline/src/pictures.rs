//! Pictures that show what was completed: for each completed object a panel of its observed
//! points beside the same view with its generated points, seen from a viewpoint that looks at the
//! hidden side; captions and a legend drawn in (a 5x7 bitmap font, so no font file is needed).
//!
//! ```text
//! OUT/objects/object_NNNN.png   one completed object: observed only | observed + generated
//! OUT/render_objects.png        the completed objects' panels stacked (the first eight)
//! ```

use deocc_geometry::camera::{look_at, Camera, Intrinsics};
use deocc_geometry::{PointCloud, Provenance};
use image::{Rgb, RgbImage};
use nalgebra::{Point3, Vector3};

use crate::render::{side_by_side, splat, GENERATED_COLOR};

/// Panel size (pixels) and focal length of the object view.
pub const PANEL: (u32, u32, f32) = (360, 300, 420.0);
/// Height of a caption strip (pixels).
pub const CAPTION_H: u32 = 22;
/// How many objects `render_objects.png` stacks.
pub const MAX_STACKED: usize = 8;
/// Background of the panels.
const BACKGROUND: [u8; 3] = [20, 20, 28];
const TEXT: [u8; 3] = [235, 235, 235];
const OBSERVED_SWATCH: [u8; 3] = [170, 170, 170];

/// 5x7 glyphs, one row a byte (bit 4 = leftmost column).
const FONT: &[(char, [u8; 7])] = &[
    (
        'A',
        [
            0b01110, 0b10001, 0b10001, 0b11111, 0b10001, 0b10001, 0b10001,
        ],
    ),
    (
        'B',
        [
            0b11110, 0b10001, 0b10001, 0b11110, 0b10001, 0b10001, 0b11110,
        ],
    ),
    (
        'C',
        [
            0b01110, 0b10001, 0b10000, 0b10000, 0b10000, 0b10001, 0b01110,
        ],
    ),
    (
        'D',
        [
            0b11110, 0b10001, 0b10001, 0b10001, 0b10001, 0b10001, 0b11110,
        ],
    ),
    (
        'E',
        [
            0b11111, 0b10000, 0b10000, 0b11110, 0b10000, 0b10000, 0b11111,
        ],
    ),
    (
        'F',
        [
            0b11111, 0b10000, 0b10000, 0b11110, 0b10000, 0b10000, 0b10000,
        ],
    ),
    (
        'G',
        [
            0b01110, 0b10001, 0b10000, 0b10111, 0b10001, 0b10001, 0b01111,
        ],
    ),
    (
        'H',
        [
            0b10001, 0b10001, 0b10001, 0b11111, 0b10001, 0b10001, 0b10001,
        ],
    ),
    (
        'I',
        [
            0b01110, 0b00100, 0b00100, 0b00100, 0b00100, 0b00100, 0b01110,
        ],
    ),
    (
        'J',
        [
            0b00111, 0b00010, 0b00010, 0b00010, 0b00010, 0b10010, 0b01100,
        ],
    ),
    (
        'K',
        [
            0b10001, 0b10010, 0b10100, 0b11000, 0b10100, 0b10010, 0b10001,
        ],
    ),
    (
        'L',
        [
            0b10000, 0b10000, 0b10000, 0b10000, 0b10000, 0b10000, 0b11111,
        ],
    ),
    (
        'M',
        [
            0b10001, 0b11011, 0b10101, 0b10101, 0b10001, 0b10001, 0b10001,
        ],
    ),
    (
        'N',
        [
            0b10001, 0b11001, 0b10101, 0b10011, 0b10001, 0b10001, 0b10001,
        ],
    ),
    (
        'O',
        [
            0b01110, 0b10001, 0b10001, 0b10001, 0b10001, 0b10001, 0b01110,
        ],
    ),
    (
        'P',
        [
            0b11110, 0b10001, 0b10001, 0b11110, 0b10000, 0b10000, 0b10000,
        ],
    ),
    (
        'Q',
        [
            0b01110, 0b10001, 0b10001, 0b10001, 0b10101, 0b10010, 0b01101,
        ],
    ),
    (
        'R',
        [
            0b11110, 0b10001, 0b10001, 0b11110, 0b10100, 0b10010, 0b10001,
        ],
    ),
    (
        'S',
        [
            0b01111, 0b10000, 0b10000, 0b01110, 0b00001, 0b00001, 0b11110,
        ],
    ),
    (
        'T',
        [
            0b11111, 0b00100, 0b00100, 0b00100, 0b00100, 0b00100, 0b00100,
        ],
    ),
    (
        'U',
        [
            0b10001, 0b10001, 0b10001, 0b10001, 0b10001, 0b10001, 0b01110,
        ],
    ),
    (
        'V',
        [
            0b10001, 0b10001, 0b10001, 0b10001, 0b10001, 0b01010, 0b00100,
        ],
    ),
    (
        'W',
        [
            0b10001, 0b10001, 0b10001, 0b10101, 0b10101, 0b10101, 0b01010,
        ],
    ),
    (
        'X',
        [
            0b10001, 0b10001, 0b01010, 0b00100, 0b01010, 0b10001, 0b10001,
        ],
    ),
    (
        'Y',
        [
            0b10001, 0b10001, 0b01010, 0b00100, 0b00100, 0b00100, 0b00100,
        ],
    ),
    (
        'Z',
        [
            0b11111, 0b00001, 0b00010, 0b00100, 0b01000, 0b10000, 0b11111,
        ],
    ),
    (
        '0',
        [
            0b01110, 0b10001, 0b10011, 0b10101, 0b11001, 0b10001, 0b01110,
        ],
    ),
    (
        '1',
        [
            0b00100, 0b01100, 0b00100, 0b00100, 0b00100, 0b00100, 0b01110,
        ],
    ),
    (
        '2',
        [
            0b01110, 0b10001, 0b00001, 0b00010, 0b00100, 0b01000, 0b11111,
        ],
    ),
    (
        '3',
        [
            0b11111, 0b00010, 0b00100, 0b00010, 0b00001, 0b10001, 0b01110,
        ],
    ),
    (
        '4',
        [
            0b00010, 0b00110, 0b01010, 0b10010, 0b11111, 0b00010, 0b00010,
        ],
    ),
    (
        '5',
        [
            0b11111, 0b10000, 0b11110, 0b00001, 0b00001, 0b10001, 0b01110,
        ],
    ),
    (
        '6',
        [
            0b00110, 0b01000, 0b10000, 0b11110, 0b10001, 0b10001, 0b01110,
        ],
    ),
    (
        '7',
        [
            0b11111, 0b00001, 0b00010, 0b00100, 0b01000, 0b01000, 0b01000,
        ],
    ),
    (
        '8',
        [
            0b01110, 0b10001, 0b10001, 0b01110, 0b10001, 0b10001, 0b01110,
        ],
    ),
    (
        '9',
        [
            0b01110, 0b10001, 0b10001, 0b01111, 0b00001, 0b00010, 0b01100,
        ],
    ),
    (
        ' ',
        [
            0b00000, 0b00000, 0b00000, 0b00000, 0b00000, 0b00000, 0b00000,
        ],
    ),
    (
        ':',
        [
            0b00000, 0b00100, 0b00100, 0b00000, 0b00100, 0b00100, 0b00000,
        ],
    ),
    (
        '.',
        [
            0b00000, 0b00000, 0b00000, 0b00000, 0b00000, 0b01100, 0b01100,
        ],
    ),
    (
        '-',
        [
            0b00000, 0b00000, 0b00000, 0b11111, 0b00000, 0b00000, 0b00000,
        ],
    ),
    (
        '%',
        [
            0b11000, 0b11001, 0b00010, 0b00100, 0b01000, 0b10011, 0b00011,
        ],
    ),
    (
        '/',
        [
            0b00000, 0b00001, 0b00010, 0b00100, 0b01000, 0b10000, 0b00000,
        ],
    ),
    (
        '(',
        [
            0b00010, 0b00100, 0b01000, 0b01000, 0b01000, 0b00100, 0b00010,
        ],
    ),
    (
        ')',
        [
            0b01000, 0b00100, 0b00010, 0b00010, 0b00010, 0b00100, 0b01000,
        ],
    ),
    (
        '+',
        [
            0b00000, 0b00100, 0b00100, 0b11111, 0b00100, 0b00100, 0b00000,
        ],
    ),
    (
        ',',
        [
            0b00000, 0b00000, 0b00000, 0b00000, 0b01100, 0b00100, 0b01000,
        ],
    ),
];

/// Draws `text` (upper-cased; unknown characters as blanks) at (x, y) with `scale`-sized dots.
pub fn draw_text(img: &mut RgbImage, x: u32, y: u32, text: &str, color: [u8; 3], scale: u32) {
    let mut cx = x;
    for ch in text.chars().map(|c| c.to_ascii_uppercase()) {
        if let Some((_, rows)) = FONT.iter().find(|(c, _)| *c == ch) {
            for (r, bits) in rows.iter().enumerate() {
                for col in 0..5 {
                    if bits & (1 << (4 - col)) != 0 {
                        for dy in 0..scale {
                            for dx in 0..scale {
                                let (px, py) = (cx + col * scale + dx, y + r as u32 * scale + dy);
                                if px < img.width() && py < img.height() {
                                    img.put_pixel(px, py, Rgb(color));
                                }
                            }
                        }
                    }
                }
            }
        }
        cx += 6 * scale;
    }
}

/// Width in pixels of `text` as [`draw_text`] draws it.
pub fn text_width(text: &str, scale: u32) -> u32 {
    text.chars().count() as u32 * 6 * scale
}

/// `img` under a caption strip: `title` on the left, then legend entries (swatch, words).
pub fn captioned(img: &RgbImage, title: &str, legend: &[([u8; 3], &str)]) -> RgbImage {
    let mut out = RgbImage::from_pixel(img.width(), img.height() + CAPTION_H, Rgb([34, 34, 44]));
    image::imageops::replace(&mut out, img, 0, CAPTION_H as i64);
    draw_text(&mut out, 6, 7, title, TEXT, 1);
    let mut x = 12 + text_width(title, 1);
    for (color, words) in legend {
        for dy in 5..16 {
            for dx in 0..11 {
                if x + dx < out.width() {
                    out.put_pixel(x + dx, dy, Rgb(*color));
                }
            }
        }
        draw_text(&mut out, x + 15, 7, words, TEXT, 1);
        x += 15 + text_width(words, 1) + 12;
    }
    out
}

/// A label in the top-left corner of a panel.
fn label(img: &mut RgbImage, text: &str) {
    draw_text(img, 6, 6, text, TEXT, 1);
}

/// The camera that looks at an object's hidden side: from the first view's camera, turned
/// `TURN_DEG` about the vertical around the object and raised, far enough that the object fills
/// about two thirds of the panel.
pub fn hidden_side_camera(first: &Camera, points: &[Point3<f32>]) -> Option<Camera> {
    const TURN_DEG: f32 = 130.0;
    if points.is_empty() {
        return None;
    }
    let n = points.len() as f32;
    let c = Point3::from(points.iter().fold(Vector3::zeros(), |a, p| a + p.coords) / n);
    let mut r: Vec<f32> = points.iter().map(|p| (p - c).norm()).collect();
    r.sort_by(f32::total_cmp);
    let radius = r[(r.len() * 95 / 100).min(r.len() - 1)].max(0.02);
    let (w, h, f) = PANEL;
    let dist = (2.0 * radius * f / (0.65 * h as f32)).max(0.25);
    let mut toward = c - first.center();
    toward.z = 0.0;
    if toward.norm() < 1e-6 {
        toward = Vector3::x();
    }
    let toward = toward.normalize();
    let turn = nalgebra::Rotation3::from_axis_angle(&Vector3::z_axis(), TURN_DEG.to_radians());
    // From the object back toward the camera, turned: a view from behind and to the side.
    let out = turn * (-toward);
    let eye = c + (out * 0.85 + Vector3::z() * 0.55).normalize() * dist;
    let pose = look_at(&eye, &c, &Vector3::z()).ok()?;
    Some(Camera {
        intrinsics: Intrinsics::new(f, f, w as f32 / 2.0, h as f32 / 2.0, w, h).ok()?,
        world_from_camera: pose,
    })
}

/// One completed object's picture: observed only | observed and generated, captioned with the
/// counts and a legend. `None` for an instance without generated points.
pub fn object_panel(completed: &PointCloud, instance: u32, first: &Camera) -> Option<RgbImage> {
    let ids = completed.instance.as_deref()?;
    let gen = completed.generated.as_deref()?;
    let mine = completed.filter(|i| ids[i] == instance);
    let own_gen = mine.generated.as_deref()?;
    let generated = own_gen
        .iter()
        .filter(|&&g| g != Provenance::Observed.code())
        .count();
    if generated == 0 || gen.is_empty() {
        return None;
    }
    let observed_only = mine.filter(|i| own_gen[i] == Provenance::Observed.code());
    let camera = hidden_side_camera(first, &mine.positions)?;
    let mut left = splat(&observed_only, &camera, 2, true);
    let mut right = splat(&mine, &camera, 2, true);
    label(&mut left, "observed only");
    label(&mut right, "completed");
    let both = side_by_side(&left, &right);
    let mut framed = both.clone();
    // A thin divider between the two panels.
    for y in 0..framed.height() {
        framed.put_pixel(left.width(), y, Rgb([90, 90, 110]));
    }
    let title = format!(
        "instance {instance}: {} observed + {generated} generated",
        observed_only.len()
    );
    Some(captioned(
        &framed,
        &title,
        &[
            (OBSERVED_SWATCH, "observed"),
            (GENERATED_COLOR, "generated"),
        ],
    ))
}

/// The panels of every completed object, in instance order (at most [`MAX_STACKED`] of them in
/// the stacked picture; every one in its own file).
pub fn object_panels(
    completed: &PointCloud,
    instances: &[u32],
    first: &Camera,
) -> Vec<(u32, RgbImage)> {
    instances
        .iter()
        .filter_map(|&i| object_panel(completed, i, first).map(|p| (i, p)))
        .collect()
}

/// Panels one above the other.
pub fn stacked(panels: &[&RgbImage]) -> Option<RgbImage> {
    let w = panels.iter().map(|p| p.width()).max()?;
    let h = panels.iter().map(|p| p.height()).sum();
    let mut out = RgbImage::from_pixel(w, h, Rgb(BACKGROUND));
    let mut y = 0;
    for p in panels {
        image::imageops::replace(&mut out, *p, 0, y as i64);
        y += p.height();
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Isometry3;

    #[test]
    fn text_draws_known_glyphs_and_skips_unknown_ones() {
        let mut img = RgbImage::new(40, 10);
        draw_text(&mut img, 0, 0, "I", [255, 255, 255], 1);
        // 'I' has its stem in the middle column on rows 1-5.
        assert_eq!(img.get_pixel(2, 3).0, [255, 255, 255]);
        assert_eq!(img.get_pixel(0, 3).0, [0, 0, 0]);
        let mut blank = RgbImage::new(40, 10);
        draw_text(&mut blank, 0, 0, "~", [255, 255, 255], 1);
        assert!(blank.pixels().all(|p| p.0 == [0, 0, 0]));
        assert_eq!(text_width("abc", 2), 36);
    }

    /// A box whose front face was observed and whose back was generated: the panel's right half
    /// shows generated colour where its left half shows none, and the view sees the back.
    #[test]
    fn the_panel_shows_the_generated_back_that_the_observed_view_lacks() {
        let first = Camera {
            intrinsics: Intrinsics::new(500.0, 500.0, 320.0, 240.0, 640, 480).unwrap(),
            world_from_camera: look_at(
                &Point3::new(0.0, -1.0, 0.5),
                &Point3::new(0.0, 0.0, 0.1),
                &Vector3::z(),
            )
            .unwrap_or(Isometry3::identity()),
        };
        let mut pts = Vec::new();
        let mut gen = Vec::new();
        for i in 0..30 {
            for j in 0..30 {
                let (x, z) = (-0.05 + i as f32 * 0.1 / 29.0, j as f32 * 0.2 / 29.0);
                pts.push(Point3::new(x, -0.05, z)); // front, seen
                gen.push(Provenance::Observed.code());
                pts.push(Point3::new(x, 0.05, z)); // back, generated
                gen.push(Provenance::Model.code());
            }
        }
        let n = pts.len();
        let mut cloud = PointCloud::from_positions(pts);
        cloud.generated = Some(gen);
        cloud.instance = Some(vec![4; n]);
        cloud.colors = Some(vec![[120, 160, 90]; n]);
        let panel = object_panel(&cloud, 4, &first).expect("a completed object");
        let (w, _) = (PANEL.0, PANEL.1);
        let magenta = |x0: u32, x1: u32| {
            panel
                .enumerate_pixels()
                .filter(|(x, y, p)| {
                    *x >= x0 && *x < x1 && *y >= CAPTION_H && p.0 == GENERATED_COLOR
                })
                .count()
        };
        assert_eq!(
            magenta(0, w),
            0,
            "the observed-only half shows no generated point"
        );
        assert!(
            magenta(w, 2 * w) > 2000,
            "{} generated pixels",
            magenta(w, 2 * w)
        );
        assert!(object_panel(&cloud, 9, &first).is_none());
    }
}
