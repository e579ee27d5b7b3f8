//! Depth Anything V2 (DINOv2 encoder, DPT head) as a [`DepthSource`]: relative inverse depth from
//! RGB, which the pipeline's depth stage puts at the sensor's metric scale and writes into the
//! pixels the sensor did not measure.
//!
//! No weights ship with deocc (none can be downloaded at run time, and only the small model's
//! licence is Apache-2.0): the user gives a safetensors file in the layout of the original
//! checkpoints (`pretrained.*` for the encoder, `depth_head.*` for the head; convert the `.pth`
//! with `safetensors.torch.save_file(torch.load(p), out)`). The size (small, base, large) is read
//! from the file. The network is candle-transformers' implementation; the encoder's ImageNet
//! classifier, which the depth checkpoints do not carry and the depth head does not use, is
//! given zeros.

use std::collections::HashMap;
use std::path::Path;
use std::sync::Arc;

use candle_core::{DType, Device, Module, Tensor};
use candle_nn::VarBuilder;
use candle_transformers::models::depth_anything_v2::{DepthAnythingV2, DepthAnythingV2Config};
use candle_transformers::models::dinov2::DinoVisionTransformer;
use deocc_io::depth_source::{DepthEstimate, DepthSource, DepthSourceError};
use deocc_io::scene::Frame;

use crate::train::{Result, TrainError};

/// The network's square input side (37 patches of 14 pixels).
pub const INPUT_SIDE: usize = 518;
const MEAN: [f32; 3] = [0.485, 0.456, 0.406];
const STD: [f32; 3] = [0.229, 0.224, 0.225];
/// Classes of the DINOv2 classifier head candle's encoder is built with.
const CLASSIFIER_CLASSES: usize = 1000;

/// The architecture: the encoder's depth, width and heads, and the head's channels.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthAnythingShape {
    pub name: String,
    pub blocks: usize,
    pub embed_dim: usize,
    pub heads: usize,
    pub out_channels: [usize; 4],
    pub features: usize,
    pub layer_ids: Vec<usize>,
}

impl DepthAnythingShape {
    pub fn small() -> Self {
        Self {
            name: "small".into(),
            blocks: 12,
            embed_dim: 384,
            heads: 6,
            out_channels: [48, 96, 192, 384],
            features: 64,
            layer_ids: vec![2, 5, 8, 11],
        }
    }
    pub fn base() -> Self {
        Self {
            name: "base".into(),
            blocks: 12,
            embed_dim: 768,
            heads: 12,
            out_channels: [96, 192, 384, 768],
            features: 128,
            layer_ids: vec![2, 5, 8, 11],
        }
    }
    pub fn large() -> Self {
        Self {
            name: "large".into(),
            blocks: 24,
            embed_dim: 1024,
            heads: 16,
            out_channels: [256, 512, 1024, 1024],
            features: 256,
            layer_ids: vec![4, 11, 17, 23],
        }
    }
    /// The preset whose encoder width is `embed_dim`.
    pub fn for_embed_dim(embed_dim: usize) -> Option<Self> {
        [Self::small(), Self::base(), Self::large()]
            .into_iter()
            .find(|s| s.embed_dim == embed_dim)
    }
    fn config(&self) -> DepthAnythingV2Config {
        DepthAnythingV2Config::new(
            self.out_channels,
            self.embed_dim,
            self.features,
            false,
            false,
            self.layer_ids.clone(),
            INPUT_SIDE,
            INPUT_SIDE / 14,
        )
    }
}

/// A loaded Depth Anything V2 model.
pub struct DepthAnything {
    model: DepthAnythingV2,
    shape: DepthAnythingShape,
    name: String,
    device: Device,
}

fn file_err(path: &Path, msg: impl std::fmt::Display) -> TrainError {
    TrainError::File {
        path: path.to_path_buf(),
        msg: msg.to_string(),
    }
}

impl DepthAnything {
    /// Builds the network of `shape` from a variable builder (the weights' root).
    pub fn build(shape: DepthAnythingShape, vb: VarBuilder, device: &Device) -> Result<Self> {
        let encoder = DinoVisionTransformer::new(
            vb.pp("pretrained"),
            shape.blocks,
            shape.embed_dim,
            shape.heads,
        )?;
        let model = DepthAnythingV2::new(Arc::new(encoder), shape.config(), vb)?;
        Ok(Self {
            model,
            name: format!("depth-anything-v2-{}", shape.name),
            shape,
            device: device.clone(),
        })
    }

    /// Loads a safetensors file in the original checkpoints' layout; the size is read from the
    /// encoder's width.
    pub fn load(path: &Path, device: &Device) -> Result<Self> {
        let tensors = read_tensors(path, device)?;
        let cls = tensors.get("pretrained.cls_token").ok_or_else(|| {
            file_err(
                path,
                "no tensor pretrained.cls_token: not a Depth Anything V2 checkpoint in the \
                 original layout (pretrained.*, depth_head.*)",
            )
        })?;
        let embed_dim = cls.dims().last().copied().unwrap_or(0);
        let shape = DepthAnythingShape::for_embed_dim(embed_dim).ok_or_else(|| {
            file_err(
                path,
                format!(
                    "encoder width {embed_dim} is none of small (384), base (768), large (1024)"
                ),
            )
        })?;
        Self::from_tensors(tensors, shape, path, device)
    }

    /// Loads a safetensors file for a given architecture (the presets, or a smaller one for
    /// tests).
    pub fn load_shaped(path: &Path, shape: DepthAnythingShape, device: &Device) -> Result<Self> {
        let tensors = read_tensors(path, device)?;
        Self::from_tensors(tensors, shape, path, device)
    }

    fn from_tensors(
        mut tensors: HashMap<String, Tensor>,
        shape: DepthAnythingShape,
        path: &Path,
        device: &Device,
    ) -> Result<Self> {
        for (name, dims) in [
            (
                "pretrained.head.weight",
                vec![CLASSIFIER_CLASSES, 2 * shape.embed_dim],
            ),
            ("pretrained.head.bias", vec![CLASSIFIER_CLASSES]),
        ] {
            if !tensors.contains_key(name) {
                tensors.insert(name.into(), Tensor::zeros(dims, DType::F32, device)?);
            }
        }
        let tensors = tensors
            .into_iter()
            .map(|(k, t)| Ok((k, t.to_dtype(DType::F32)?)))
            .collect::<candle_core::Result<HashMap<_, _>>>()?;
        let vb = VarBuilder::from_tensors(tensors, DType::F32, device);
        Self::build(shape, vb, device)
            .map_err(|e| file_err(path, format!("weights do not fit Depth Anything V2: {e}")))
    }

    pub fn shape(&self) -> &DepthAnythingShape {
        &self.shape
    }

    /// Relative inverse depth (larger = nearer) of an RGB image, at the image's size, row-major.
    pub fn disparity(&self, rgb: &image::RgbImage) -> Result<Vec<f32>> {
        let (w, h) = (rgb.width() as usize, rgb.height() as usize);
        if w < 2 || h < 2 {
            return Err(TrainError::Config(format!(
                "a {w}x{h} image is too small for a depth model"
            )));
        }
        let s = INPUT_SIDE;
        let mut input = vec![0f32; 3 * s * s];
        for y in 0..s {
            for x in 0..s {
                let px = bilinear_rgb(
                    rgb,
                    (x as f32 + 0.5) * w as f32 / s as f32 - 0.5,
                    (y as f32 + 0.5) * h as f32 / s as f32 - 0.5,
                );
                for c in 0..3 {
                    input[c * s * s + y * s + x] = (px[c] / 255.0 - MEAN[c]) / STD[c];
                }
            }
        }
        let x = Tensor::from_vec(input, (1, 3, s, s), &self.device)?;
        let out = self.model.forward(&x)?;
        // The head answers near the input's size (candle-transformers' gives 520 x 520).
        let (_, _, oh, ow) = out.dims4()?;
        let out: Vec<f32> = out.flatten_all()?.to_vec1()?;
        if oh < 2 || ow < 2 || out.len() != oh * ow {
            return Err(TrainError::Config(format!(
                "the depth model answered {} values ({ow}x{oh}) for a {s}x{s} input",
                out.len()
            )));
        }
        let mut disparity = Vec::with_capacity(w * h);
        for v in 0..h {
            for u in 0..w {
                let x = (u as f32 + 0.5) * ow as f32 / w as f32 - 0.5;
                let y = (v as f32 + 0.5) * oh as f32 / h as f32 - 0.5;
                disparity.push(bilinear(&out, ow, oh, x, y));
            }
        }
        Ok(disparity)
    }
}

fn read_tensors(path: &Path, device: &Device) -> Result<HashMap<String, Tensor>> {
    if !path.is_file() {
        return Err(file_err(
            path,
            "no such file (a Depth Anything V2 safetensors file)",
        ));
    }
    // The header first: a file that is not weights is refused before it is read.
    let header = deocc_io::weights::check_safetensors(path, MAX_WEIGHTS_BYTES)
        .map_err(|e| file_err(path, e))?;
    if !header.names.iter().any(|n| n == "pretrained.cls_token") {
        return Err(file_err(
            path,
            "no tensor pretrained.cls_token: not a Depth Anything V2 checkpoint in the \
             original layout (pretrained.*, depth_head.*)",
        ));
    }
    candle_core::safetensors::load(path, device).map_err(|e| file_err(path, e))
}

/// Largest depth-model file read (Depth Anything V2 large is 1.3 GB in f32).
pub const MAX_WEIGHTS_BYTES: u64 = 4 << 30;

/// Bilinear sample at continuous pixel `(x, y)` (clamped to the image) of a `w x h` grid read
/// through `at(x, y)`.
fn bilinear_with(w: usize, h: usize, x: f32, y: f32, at: impl Fn(usize, usize) -> f32) -> f32 {
    let x = x.clamp(0.0, (w - 1) as f32);
    let y = y.clamp(0.0, (h - 1) as f32);
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (fx, fy) = (x - x0 as f32, y - y0 as f32);
    let top = at(x0, y0) * (1.0 - fx) + at(x1, y0) * fx;
    let bottom = at(x0, y1) * (1.0 - fx) + at(x1, y1) * fx;
    top * (1.0 - fy) + bottom * fy
}

fn bilinear(data: &[f32], w: usize, h: usize, x: f32, y: f32) -> f32 {
    bilinear_with(w, h, x, y, |xx, yy| data[yy * w + xx])
}

fn bilinear_rgb(img: &image::RgbImage, x: f32, y: f32) -> [f32; 3] {
    let (w, h) = (img.width() as usize, img.height() as usize);
    let raw = img.as_raw();
    std::array::from_fn(|c| bilinear_with(w, h, x, y, |xx, yy| raw[(yy * w + xx) * 3 + c] as f32))
}

impl DepthSource for DepthAnything {
    fn name(&self) -> &str {
        &self.name
    }
    fn estimate(
        &self,
        frame: &Frame,
    ) -> std::result::Result<Option<DepthEstimate>, DepthSourceError> {
        let d = self
            .disparity(&frame.rgb)
            .map_err(|e| DepthSourceError(e.to_string()))?;
        Ok(Some(DepthEstimate::Disparity(d)))
    }
}
