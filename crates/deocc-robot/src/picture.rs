//! Pictures a person would rather look at than read: gripper outlines over a rendered cloud and
//! the placement map from above.

pub use image::{Rgb, RgbImage};
use nalgebra::{Point3, Vector3};

use crate::gripper::{Grasp, GripperConfig};
use crate::place::{PlaceMap, Placement};

/// Draws a line from `a` to `b` (pixels), clipped to the image.
pub fn line(img: &mut RgbImage, a: [f32; 2], b: [f32; 2], color: [u8; 3]) {
    let steps = ((b[0] - a[0]).abs().max((b[1] - a[1]).abs()).ceil() as usize).clamp(1, 4096);
    for s in 0..=steps {
        let t = s as f32 / steps as f32;
        let (x, y) = (a[0] + (b[0] - a[0]) * t, a[1] + (b[1] - a[1]) * t);
        if x >= 0.0 && y >= 0.0 && (x as u32) < img.width() && (y as u32) < img.height() {
            img.put_pixel(x as u32, y as u32, Rgb(color));
        }
    }
}

/// The gripper's outline (two fingers, the palm and a stem back along the approach), projected
/// by `project` (world point to pixel).
pub fn draw_grasp(
    img: &mut RgbImage,
    grasp: &Grasp,
    gripper: &GripperConfig,
    project: &dyn Fn(&Point3<f32>) -> Option<[f32; 2]>,
    color: [u8; 3],
) {
    let r = grasp.rotation();
    let o = grasp.origin();
    let at = |x: f32, y: f32| o + r * Vector3::new(x, y, 0.0);
    let h = grasp.width / 2.0;
    let segments = [
        (at(0.0, -h), at(0.0, h)),
        (at(0.0, h), at(gripper.depth, h)),
        (at(0.0, -h), at(gripper.depth, -h)),
        (at(0.0, 0.0), at(-0.04, 0.0)),
    ];
    for (a, b) in segments {
        if let (Some(pa), Some(pb)) = (project(&a), project(&b)) {
            line(img, pa, pb, color);
        }
    }
}

/// The map from above, `scale` pixels a cell: placeable green, blocked red where occupied and
/// dark red near it, supported grey, unsupported black, never seen dark blue; the chosen cell's
/// footprint outlined in yellow. Image rows run from +y (top) to -y.
pub fn place_map_image(
    map: &PlaceMap,
    chosen: Option<&Placement>,
    footprint_cells: [usize; 2],
    scale: u32,
) -> RgbImage {
    let mut img = RgbImage::new(map.nx as u32 * scale, map.ny as u32 * scale);
    for i in 0..map.nx * map.ny {
        let c = if map.occupied[i] {
            [200, 40, 40]
        } else if map.placeable[i] {
            [60, 180, 75]
        } else if map.blocked[i] {
            [110, 40, 40]
        } else if !map.seen[i] {
            [25, 30, 70]
        } else if map.support[i] {
            [150, 150, 150]
        } else {
            [0, 0, 0]
        };
        let (x, y) = ((i % map.nx) as u32, (map.ny - 1 - i / map.nx) as u32);
        for dy in 0..scale {
            for dx in 0..scale {
                img.put_pixel(x * scale + dx, y * scale + dy, Rgb(c));
            }
        }
    }
    if let Some(p) = chosen {
        let (cx, cy) = (
            (p.cell % map.nx) as f32,
            (map.ny - 1 - p.cell / map.nx) as f32,
        );
        let s = scale as f32;
        let (hw, hd) = (
            footprint_cells[0] as f32 / 2.0,
            footprint_cells[1] as f32 / 2.0,
        );
        let (x0, x1) = ((cx + 0.5 - hw) * s, (cx + 0.5 + hw) * s);
        let (y0, y1) = ((cy + 0.5 - hd) * s, (cy + 0.5 + hd) * s);
        let yellow = [250, 220, 40];
        line(&mut img, [x0, y0], [x1, y0], yellow);
        line(&mut img, [x1, y0], [x1, y1], yellow);
        line(&mut img, [x1, y1], [x0, y1], yellow);
        line(&mut img, [x0, y1], [x0, y0], yellow);
    }
    img
}

/// Colours of [`comparison_image`], for legends.
pub const AGREE_PLACEABLE: [u8; 3] = [60, 180, 75];
pub const FALSE_PLACEABLE: [u8; 3] = [230, 40, 40];
pub const MISSED_BLOCKED: [u8; 3] = [245, 150, 40];
pub const MISSED_UNSUPPORTED: [u8; 3] = [70, 110, 230];
pub const AGREE_NOT_PLACEABLE: [u8; 3] = [95, 95, 95];

/// A predicted map against the true one from above, `scale` pixels a cell, over the workspace
/// (black outside it): placeable in both green, false placeable red, truly placeable but missed
/// orange where the prediction holds something in the way and blue where it lacks support, not
/// placeable in either grey. Image rows run from +y (top) to -y, as in [`place_map_image`].
pub fn comparison_image(
    pred: &PlaceMap,
    truth: &PlaceMap,
    workspace: &[bool],
    scale: u32,
) -> RgbImage {
    let mut img = RgbImage::new(pred.nx as u32 * scale, pred.ny as u32 * scale);
    let n = (pred.nx * pred.ny).min(truth.placeable.len());
    for (i, &inside) in workspace.iter().enumerate().take(n) {
        let (p, t) = (pred.placeable[i], truth.placeable[i]);
        let c = match (inside, p, t) {
            (false, _, _) => [0, 0, 0],
            (true, true, true) => AGREE_PLACEABLE,
            (true, true, false) => FALSE_PLACEABLE,
            (true, false, true) if pred.blocked[i] => MISSED_BLOCKED,
            (true, false, true) => MISSED_UNSUPPORTED,
            (true, false, false) => AGREE_NOT_PLACEABLE,
        };
        let (x, y) = ((i % pred.nx) as u32, (pred.ny - 1 - i / pred.nx) as u32);
        for dy in 0..scale {
            for dx in 0..scale {
                img.put_pixel(x * scale + dx, y * scale + dy, Rgb(c));
            }
        }
    }
    img
}

/// Height of a caption strip of [`captioned`]: 8-pixel glyphs and 2 pixels above and below.
pub const CAPTION_HEIGHT: u32 = 12;

/// Writes `text` with its top-left corner at (`x`, `y`) in 8x8 glyphs (printable ASCII; other
/// characters are left blank), clipped at the image's edges.
pub fn draw_text(img: &mut RgbImage, x: u32, y: u32, text: &str, color: [u8; 3]) {
    use font8x8::UnicodeFonts;
    for (k, ch) in text.chars().enumerate() {
        let Some(glyph) = font8x8::BASIC_FONTS.get(ch) else {
            continue;
        };
        for (row, bits) in glyph.iter().enumerate() {
            for col in 0..8 {
                if bits >> col & 1 == 1 {
                    let (px, py) = (x + 8 * k as u32 + col, y + row as u32);
                    if px < img.width() && py < img.height() {
                        img.put_pixel(px, py, Rgb(color));
                    }
                }
            }
        }
    }
}

/// `img` under a white strip of [`CAPTION_HEIGHT`] pixels that carries `caption` in black (cut
/// at the image's width).
pub fn captioned(img: &RgbImage, caption: &str) -> RgbImage {
    let mut out = RgbImage::from_pixel(
        img.width(),
        img.height() + CAPTION_HEIGHT,
        Rgb([255, 255, 255]),
    );
    image::imageops::replace(&mut out, img, 0, CAPTION_HEIGHT as i64);
    draw_text(&mut out, 2, 2, caption, [0, 0, 0]);
    out
}

/// A legend: one row a colour, a swatch and its name, on white.
pub fn legend(entries: &[([u8; 3], &str)]) -> RgbImage {
    let chars = entries
        .iter()
        .map(|e| e.1.chars().count())
        .max()
        .unwrap_or(0) as u32;
    let mut img = RgbImage::from_pixel(
        16 + 8 * chars + 2,
        CAPTION_HEIGHT * entries.len().max(1) as u32,
        Rgb([255, 255, 255]),
    );
    for (k, (color, name)) in entries.iter().enumerate() {
        let y = CAPTION_HEIGHT * k as u32;
        for dy in 2..10 {
            for dx in 2..12 {
                img.put_pixel(dx, y + dy, Rgb(*color));
            }
        }
        draw_text(&mut img, 16, y + 2, name, [0, 0, 0]);
    }
    img
}

/// The legend of [`comparison_image`].
pub fn comparison_legend() -> RgbImage {
    legend(&[
        (AGREE_PLACEABLE, "placeable, right"),
        (FALSE_PLACEABLE, "false placeable"),
        (MISSED_BLOCKED, "missed: blocked"),
        (MISSED_UNSUPPORTED, "missed: no support"),
        (AGREE_NOT_PLACEABLE, "not placeable, right"),
    ])
}

/// Images side by side with `gap` white pixels between them (rows of the tallest).
pub fn side_by_side(images: &[RgbImage], gap: u32) -> RgbImage {
    let w =
        images.iter().map(|i| i.width()).sum::<u32>() + gap * images.len().saturating_sub(1) as u32;
    let h = images.iter().map(|i| i.height()).max().unwrap_or(0);
    let mut out = RgbImage::from_pixel(w.max(1), h.max(1), Rgb([255, 255, 255]));
    let mut x0 = 0;
    for im in images {
        image::imageops::replace(&mut out, im, x0 as i64, 0);
        x0 += im.width() + gap;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A caption adds its strip above the picture, leaves the picture's pixels as they were and
    /// writes dark glyph pixels into the strip only where there is text.
    #[test]
    fn a_caption_sits_above_the_picture() {
        let img = RgbImage::from_pixel(40, 10, Rgb([0, 200, 0]));
        let out = captioned(&img, "rules");
        assert_eq!(out.dimensions(), (40, 10 + CAPTION_HEIGHT));
        assert!((0..40).all(|x| out.get_pixel(x, CAPTION_HEIGHT + 3).0 == [0, 200, 0]));
        let dark = |x0: u32, x1: u32| {
            (x0..x1)
                .flat_map(|x| (0..CAPTION_HEIGHT).map(move |y| (x, y)))
                .filter(|&(x, y)| out.get_pixel(x, y).0 == [0, 0, 0])
                .count()
        };
        // "rules" is cut at the width: 5 glyphs from x = 2 need 42 pixels; all of the first
        // four are inside, each with some ink.
        for k in 0..4 {
            assert!(dark(2 + 8 * k, 10 + 8 * k) > 3, "glyph {k}");
        }
        assert_eq!(captioned(&img, "   ").get_pixel(5, 5).0, [255, 255, 255]);
        // A legend row a colour, its swatch in that colour.
        let l = comparison_legend();
        assert_eq!(l.height(), 5 * CAPTION_HEIGHT);
        assert_eq!(l.get_pixel(6, CAPTION_HEIGHT + 5).0, FALSE_PLACEABLE);
    }
}
