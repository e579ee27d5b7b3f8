//! Images on disk: 16-bit depth PNG in millimetres (TUM / ScanNet convention, 0 = no measurement),
//! u16 instance maps (0 = background), 8-bit masks and RGB.

use std::io::Cursor;
use std::path::Path;

use deocc_geometry::DepthMap;
use image::codecs::png::{CompressionType, FilterType, PngEncoder};
use image::{ImageBuffer, Luma, Rgb, RgbImage};

use crate::atomic::write_bytes_atomic;
use crate::error::{IoError, IoErrorKind, Result};

/// Largest image side accepted (pixels): far beyond any sensor, far below a decompression bomb.
pub const MAX_IMAGE_SIDE: u32 = 16_384;
/// Largest image accepted (pixels): 64 megapixels, eight times a 4K frame.
pub const MAX_IMAGE_PIXELS: u64 = 1 << 26;

fn open_image(path: &Path) -> Result<image::DynamicImage> {
    open_image_expecting(path, None)
}

/// Decodes an image, first checking the size its header declares (against `expected` when given,
/// and against [`MAX_IMAGE_SIDE`]) so that a small file declaring a huge image is refused
/// before anything is decoded.
fn open_image_expecting(path: &Path, expected: Option<(u32, u32)>) -> Result<image::DynamicImage> {
    let bytes = std::fs::read(path).map_err(|e| IoError::new(path, e))?;
    let image_err = |e: image::ImageError| IoError::new(path, IoErrorKind::Image(e.to_string()));
    let reader = || {
        image::ImageReader::new(Cursor::new(&bytes))
            .with_guessed_format()
            .map_err(|e| IoError::new(path, e))
    };
    // The header alone, without the decoder's memory limits (reading a size allocates nothing;
    // the checks below say what is wrong in words).
    let mut header = reader()?;
    header.no_limits();
    let (w, h) = header.into_dimensions().map_err(image_err)?;
    if let Some((ew, eh)) = expected {
        if (w, h) != (ew, eh) {
            return Err(IoError::invalid(
                path,
                format!("image is {w}x{h} but cameras.json says {ew}x{eh}"),
            ));
        }
    }
    if w > MAX_IMAGE_SIDE || h > MAX_IMAGE_SIDE || w as u64 * h as u64 > MAX_IMAGE_PIXELS {
        return Err(IoError::invalid(
            path,
            format!(
                "image is {w}x{h}, larger than {MAX_IMAGE_SIDE} pixels a side or {} megapixels",
                MAX_IMAGE_PIXELS >> 20
            ),
        ));
    }
    reader()?.decode().map_err(image_err)
}

/// An image's (width, height) from its header, nothing decoded.
pub fn image_size(path: &Path) -> Result<(u32, u32)> {
    let mut r = image::ImageReader::open(path)
        .map_err(|e| IoError::new(path, e))?
        .with_guessed_format()
        .map_err(|e| IoError::new(path, e))?;
    r.no_limits();
    r.into_dimensions()
        .map_err(|e| IoError::new(path, IoErrorKind::Image(e.to_string())))
}

fn encode_png<P, C>(path: &Path, img: &ImageBuffer<P, C>, filter: FilterType) -> Result<()>
where
    P: image::Pixel + image::PixelWithColorType,
    [P::Subpixel]: image::EncodableLayout,
    C: std::ops::Deref<Target = [P::Subpixel]>,
{
    // Fast compression: depth and instance maps compress well anyway, and writing 50+ views a
    // second matters more than the last 20% of file size. `filter`: Adaptive (five filters tried
    // per row) for photographs and depth; Sub for piecewise-constant maps and masks, where it
    // turns every run into zeros (what the fast compressor is made for) at a fifth of the cost.
    let mut bytes = Vec::new();
    let encoder =
        PngEncoder::new_with_quality(Cursor::new(&mut bytes), CompressionType::Fast, filter);
    img.write_with_encoder(encoder)
        .map_err(|e| IoError::new(path, IoErrorKind::Image(e.to_string())))?;
    write_bytes_atomic(path, &bytes)
}

fn read_u16_png(
    path: &Path,
    what: &str,
    expected: Option<(u32, u32)>,
) -> Result<(u32, u32, Vec<u16>)> {
    match open_image_expecting(path, expected)? {
        image::DynamicImage::ImageLuma16(img) => Ok((img.width(), img.height(), img.into_raw())),
        other => Err(IoError::invalid(
            path,
            format!(
                "expected a 16-bit single-channel PNG ({what}), found {:?}",
                other.color()
            ),
        )),
    }
}

/// Reads a 16-bit depth PNG in millimetres into metres.
pub fn read_depth_png(path: &Path) -> Result<DepthMap> {
    read_depth_png_expecting(path, None)
}

/// [`read_depth_png`], refusing before decoding an image of another size than `expected`.
pub fn read_depth_png_expecting(path: &Path, expected: Option<(u32, u32)>) -> Result<DepthMap> {
    let (w, h, mm) = read_u16_png(path, "depth in millimetres", expected)?;
    DepthMap::new(w, h, mm.iter().map(|&v| v as f32 / 1000.0).collect())
        .map_err(|e| IoError::new(path, e))
}

/// Reads a depth image in either form deocc takes: a 16-bit PNG of `scale` metres per unit
/// (0.001 for millimetres), or a NumPy `.npy` array (`<f4` metres, NaN/inf/0 = none; or `<u2`
/// units of `scale`), of `expected` size when given.
pub fn read_depth_expecting(
    path: &Path,
    expected: Option<(u32, u32)>,
    scale: f64,
) -> Result<DepthMap> {
    let is_npy = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("npy"));
    let (w, h, metres) = if is_npy {
        let bytes = std::fs::read(path).map_err(|e| IoError::new(path, e))?;
        let (h, w, values) = crate::npy::read_depth_npy(&bytes, scale, MAX_IMAGE_SIDE)
            .map_err(|e| IoError::invalid(path, e))?;
        if let Some((ew, eh)) = expected {
            if (w, h) != (ew, eh) {
                return Err(IoError::invalid(
                    path,
                    format!("array is {w}x{h} (width x height) but cameras.json says {ew}x{eh}"),
                ));
            }
        }
        (w, h, values)
    } else {
        let what = if scale == 0.001 {
            "depth in millimetres".to_string()
        } else {
            format!("depth in units of {scale} m")
        };
        let (w, h, raw) = read_u16_png(path, &what, expected)?;
        (
            w,
            h,
            raw.iter().map(|&v| (v as f64 * scale) as f32).collect(),
        )
    };
    DepthMap::new(w, h, metres).map_err(|e| IoError::new(path, e))
}

/// Writes depth in metres as a 16-bit PNG in millimetres. Depth beyond 65.535 m cannot be stored
/// and is written as 0 (no measurement).
pub fn write_depth_png(path: &Path, depth: &DepthMap) -> Result<()> {
    let mm: Vec<u16> = depth
        .data()
        .iter()
        .map(|&d| {
            let v = (d * 1000.0).round();
            if v > 0.0 && v <= 65535.0 {
                v as u16
            } else {
                0
            }
        })
        .collect();
    let img = ImageBuffer::<Luma<u16>, _>::from_raw(depth.width(), depth.height(), mm)
        .ok_or_else(|| IoError::invalid(path, "depth buffer size does not match its dimensions"))?;
    encode_png(path, &img, FilterType::Adaptive)
}

/// An instance map: one u16 id per pixel, 0 = background.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct InstanceMap {
    pub width: u32,
    pub height: u32,
    pub ids: Vec<u16>,
}

impl InstanceMap {
    pub fn get(&self, u: u32, v: u32) -> u16 {
        self.ids[v as usize * self.width as usize + u as usize]
    }
}

/// Reads a u16 instance map PNG. 8-bit single-channel PNGs are accepted too (ids up to 255).
pub fn read_instance_png(path: &Path) -> Result<InstanceMap> {
    read_instance_png_expecting(path, None)
}

/// [`read_instance_png`], refusing before decoding an image of another size than `expected`.
pub fn read_instance_png_expecting(
    path: &Path,
    expected: Option<(u32, u32)>,
) -> Result<InstanceMap> {
    let (width, height, ids) = match open_image_expecting(path, expected)? {
        image::DynamicImage::ImageLuma16(img) => (img.width(), img.height(), img.into_raw()),
        image::DynamicImage::ImageLuma8(img) => (
            img.width(),
            img.height(),
            img.into_raw().into_iter().map(u16::from).collect(),
        ),
        other => {
            return Err(IoError::invalid(
                path,
                format!(
                    "expected a single-channel 8- or 16-bit instance map, found {:?}",
                    other.color()
                ),
            ))
        }
    };
    Ok(InstanceMap { width, height, ids })
}

pub fn write_instance_png(path: &Path, map: &InstanceMap) -> Result<()> {
    let img = ImageBuffer::<Luma<u16>, _>::from_raw(map.width, map.height, map.ids.clone())
        .ok_or_else(|| {
            IoError::invalid(path, "instance buffer size does not match its dimensions")
        })?;
    encode_png(path, &img, FilterType::Sub)
}

/// Writes a binary mask (true = 255) as an 8-bit PNG.
pub fn write_mask_png(path: &Path, width: u32, height: u32, mask: &[bool]) -> Result<()> {
    let px: Vec<u8> = mask.iter().map(|&m| if m { 255 } else { 0 }).collect();
    let img = ImageBuffer::<Luma<u8>, _>::from_raw(width, height, px)
        .ok_or_else(|| IoError::invalid(path, "mask size does not match its dimensions"))?;
    encode_png(path, &img, FilterType::Sub)
}

/// Reads a mask PNG: any non-zero pixel of the first channel is inside.
pub fn read_mask_png(path: &Path) -> Result<(u32, u32, Vec<bool>)> {
    let img = open_image(path)?.to_luma8();
    Ok((
        img.width(),
        img.height(),
        img.into_raw().into_iter().map(|v| v > 0).collect(),
    ))
}

pub fn read_rgb_png(path: &Path) -> Result<RgbImage> {
    read_rgb_png_expecting(path, None)
}

/// [`read_rgb_png`], refusing before decoding an image of another size than `expected`.
pub fn read_rgb_png_expecting(path: &Path, expected: Option<(u32, u32)>) -> Result<RgbImage> {
    Ok(open_image_expecting(path, expected)?.to_rgb8())
}

pub fn write_rgb_png(path: &Path, img: &RgbImage) -> Result<()> {
    encode_png::<Rgb<u8>, _>(path, img, FilterType::Adaptive)
}
