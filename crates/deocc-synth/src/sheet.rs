//! Contact sheets: one PNG showing a rendered view's RGB, depth, instances and amodal masks, so a
//! person can look at what was made.

use image::{Rgb, RgbImage};

use crate::dataset::RenderedView;

/// A distinct colour per instance id (0 = black).
pub fn id_color(id: u16) -> [u8; 3] {
    if id == 0 {
        return [0, 0, 0];
    }
    let h = (id as u32).wrapping_mul(2_654_435_761);
    [
        64 + (h & 0xbf) as u8,
        64 + ((h >> 8) & 0xbf) as u8,
        64 + ((h >> 16) & 0xbf) as u8,
    ]
}

/// Depth to grey, near = bright; 0 (no depth) = dark red.
fn depth_color(d: f32, lo: f32, hi: f32) -> [u8; 3] {
    if d <= 0.0 {
        return [80, 0, 0];
    }
    let t = 1.0 - ((d - lo) / (hi - lo).max(1e-6)).clamp(0.0, 1.0);
    let g = (30.0 + 225.0 * t) as u8;
    [g, g, g]
}

/// Rows of views; each row: RGB | depth | visible instances | amodal masks overlaid (each object's
/// silhouette in its colour, hidden parts dimmed).
pub fn contact_sheet(views: &[RenderedView]) -> RgbImage {
    let Some(first) = views.first() else {
        return RgbImage::new(1, 1);
    };
    let (w, h) = (first.frame.width, first.frame.height);
    let mut sheet = RgbImage::new(4 * w, h * views.len() as u32);
    for (row, view) in views.iter().enumerate() {
        let y0 = row as u32 * h;
        let valid: Vec<f32> = view
            .depth
            .data()
            .iter()
            .copied()
            .filter(|&d| d > 0.0)
            .collect();
        let lo = valid.iter().copied().fold(f32::INFINITY, f32::min);
        let hi = valid.iter().copied().fold(0.0, f32::max);
        for v in 0..h {
            for u in 0..w {
                let i = (v * w + u) as usize;
                sheet.put_pixel(u, y0 + v, *view.rgb.get_pixel(u, v));
                sheet.put_pixel(
                    w + u,
                    y0 + v,
                    Rgb(depth_color(view.depth.data()[i], lo, hi)),
                );
                sheet.put_pixel(2 * w + u, y0 + v, Rgb(id_color(view.frame.instance[i])));
                let mut c = [0u8; 3];
                for m in &view.amodal {
                    if m.contains(u, v) && view.frame.instance[i] != m.instance_id {
                        c = id_color(m.instance_id).map(|x| x / 2);
                    }
                }
                if view.frame.instance[i] != 0 && c == [0, 0, 0] {
                    c = id_color(view.frame.instance[i]);
                }
                sheet.put_pixel(3 * w + u, y0 + v, Rgb(c));
            }
        }
    }
    sheet
}

/// Rows of training pairs: crop as seen | visible mask | whole object | amodal mask | whole depth.
pub fn pair_sheet(set: &crate::pairs::PairSet, indices: &[usize]) -> RgbImage {
    let r = set.resolution;
    let px = set.pixels();
    let mut sheet = RgbImage::new(5 * r, r * indices.len().max(1) as u32);
    for (row, &k) in indices.iter().enumerate() {
        let y0 = row as u32 * r;
        let depth = &set.whole_depth[k * px..(k + 1) * px];
        let amodal = &set.amodal_mask[k * px..(k + 1) * px];
        let (lo, hi) = depth
            .iter()
            .zip(amodal)
            .filter(|(_, &m)| m > 0)
            .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), (&d, _)| {
                (lo.min(d), hi.max(d))
            });
        for i in 0..px {
            let (u, v) = ((i % r as usize) as u32, (i / r as usize) as u32);
            let c = |buf: &[u8]| {
                Rgb([
                    buf[3 * (k * px + i)],
                    buf[3 * (k * px + i) + 1],
                    buf[3 * (k * px + i) + 2],
                ])
            };
            let m = |buf: &[u8]| {
                if buf[k * px + i] > 0 {
                    Rgb([255u8, 255, 255])
                } else {
                    Rgb([0, 0, 0])
                }
            };
            sheet.put_pixel(u, y0 + v, c(&set.crop_rgb));
            sheet.put_pixel(r + u, y0 + v, m(&set.visible_mask));
            sheet.put_pixel(2 * r + u, y0 + v, c(&set.whole_rgb));
            sheet.put_pixel(3 * r + u, y0 + v, m(&set.amodal_mask));
            // Shifted so the nearest point is just above 0 (depth_color reserves <= 0 for "no depth").
            let d = if amodal[i] > 0 {
                depth_color(depth[i] - lo + 1e-3, 0.0, hi - lo)
            } else {
                [0, 0, 0]
            };
            sheet.put_pixel(4 * r + u, y0 + v, Rgb(d));
        }
    }
    sheet
}
