//! GL-DoT training pairs on disk: one safetensors shard holds N crops at resolution R, one
//! tensor per field (`crop_rgb` (N, R, R, 3) u8, `visible_mask` (N, R, R) u8, `visible_depth`,
//! `scene_depth`, `whole_depth`, `whole_back_depth` (N, R, R) f32, `whole_rgb`, `amodal_mask`,
//! `group` (N) u32, `category` and `held_out` (N) u8, `occlusion` and `crop_width_m` (N) f32;
//! shards from before `crop_width_m` load with it unknown, NaN). The renderer writes
//! them (`deocc synth pairs`); the model reads them. Depth is relative to the object's median
//! visible depth, in crop widths (see `deocc_completion::crop`).

use std::path::Path;

use safetensors::tensor::{Dtype, TensorView};

use crate::error::{IoError, Result};

/// A struct of arrays holding N pairs at resolution R (row-major, channels last).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PairSet {
    pub resolution: u32,
    pub crop_rgb: Vec<u8>,       // (N, R, R, 3)
    pub visible_mask: Vec<u8>,   // (N, R, R) 0/1
    pub visible_depth: Vec<f32>, // (N, R, R)
    pub scene_depth: Vec<f32>,   // (N, R, R)
    pub whole_rgb: Vec<u8>,      // (N, R, R, 3)
    pub amodal_mask: Vec<u8>,    // (N, R, R) 0/1
    pub whole_depth: Vec<f32>,   // (N, R, R)
    /// Depth of the object's far side (its back surface) per pixel: what no view of it shows.
    pub whole_back_depth: Vec<f32>, // (N, R, R)
    pub group: Vec<u32>,         // object identity across views
    pub category: Vec<u8>,       // Category as u8 (declaration order)
    pub held_out: Vec<u8>,
    pub occlusion: Vec<f32>, // 1 - visible / amodal, in the crop
    /// The crop's width in metres at the object's median visible depth: the unit of relative
    /// depth (NaN where unknown: shards written before it was stored).
    pub crop_width_m: Vec<f32>, // (N)
    /// Other views' observations of the object reprojected into the crop: colour (N, R, R, 3)
    /// and relative depth (N, R, R), infinite where no point landed. Both empty in sets made without
    /// them (shards from before they were stored).
    pub elsewhere_rgb: Vec<u8>,
    pub elsewhere_depth: Vec<f32>,
}

impl PairSet {
    pub fn len(&self) -> usize {
        self.group.len()
    }
    pub fn is_empty(&self) -> bool {
        self.group.is_empty()
    }
    pub fn pixels(&self) -> usize {
        (self.resolution * self.resolution) as usize
    }
    /// Keeps the first `n` pairs.
    pub fn truncate(&mut self, n: usize) {
        let n = n.min(self.len());
        let px = self.pixels();
        self.crop_rgb.truncate(n * px * 3);
        self.whole_rgb.truncate(n * px * 3);
        self.visible_mask.truncate(n * px);
        self.amodal_mask.truncate(n * px);
        self.visible_depth.truncate(n * px);
        self.scene_depth.truncate(n * px);
        self.whole_depth.truncate(n * px);
        self.whole_back_depth.truncate(n * px);
        self.group.truncate(n);
        self.category.truncate(n);
        self.held_out.truncate(n);
        self.occlusion.truncate(n);
        self.crop_width_m.truncate(n);
        if self.has_elsewhere() {
            self.elsewhere_rgb.truncate(n * px * 3);
            self.elsewhere_depth.truncate(n * px);
        }
    }

    /// Whether the set carries other views' reprojected observations.
    pub fn has_elsewhere(&self) -> bool {
        !self.elsewhere_depth.is_empty()
    }

    pub fn extend(&mut self, o: &PairSet) {
        // A set with reprojected observations and one without: the latter's pairs have none.
        if self.has_elsewhere() || o.has_elsewhere() {
            let (mine, theirs) = (self.len() * self.pixels(), o.len() * o.pixels());
            if !self.has_elsewhere() {
                self.elsewhere_rgb = vec![0; 3 * mine];
                self.elsewhere_depth = vec![f32::INFINITY; mine];
            }
            if o.has_elsewhere() {
                self.elsewhere_rgb.extend_from_slice(&o.elsewhere_rgb);
                self.elsewhere_depth.extend_from_slice(&o.elsewhere_depth);
            } else {
                self.elsewhere_rgb
                    .extend(std::iter::repeat_n(0, 3 * theirs));
                self.elsewhere_depth
                    .extend(std::iter::repeat_n(f32::INFINITY, theirs));
            }
        }
        self.resolution = o.resolution;
        self.crop_rgb.extend_from_slice(&o.crop_rgb);
        self.visible_mask.extend_from_slice(&o.visible_mask);
        self.visible_depth.extend_from_slice(&o.visible_depth);
        self.scene_depth.extend_from_slice(&o.scene_depth);
        self.whole_rgb.extend_from_slice(&o.whole_rgb);
        self.amodal_mask.extend_from_slice(&o.amodal_mask);
        self.whole_depth.extend_from_slice(&o.whole_depth);
        self.whole_back_depth.extend_from_slice(&o.whole_back_depth);
        self.group.extend_from_slice(&o.group);
        self.category.extend_from_slice(&o.category);
        self.held_out.extend_from_slice(&o.held_out);
        self.occlusion.extend_from_slice(&o.occlusion);
        self.crop_width_m.extend_from_slice(&o.crop_width_m);
    }
}

fn bytes_of_f32(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}
fn bytes_of_u32(v: &[u32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// Saves pairs as safetensors (tensors named like the fields; shapes (N, R, R[, 3])).
pub fn save_pairs(path: &Path, set: &PairSet) -> Result<()> {
    let (n, r) = (set.len(), set.resolution as usize);
    let f = [
        (
            "crop_rgb",
            Dtype::U8,
            vec![n, r, r, 3],
            set.crop_rgb.clone(),
        ),
        (
            "visible_mask",
            Dtype::U8,
            vec![n, r, r],
            set.visible_mask.clone(),
        ),
        (
            "visible_depth",
            Dtype::F32,
            vec![n, r, r],
            bytes_of_f32(&set.visible_depth),
        ),
        (
            "scene_depth",
            Dtype::F32,
            vec![n, r, r],
            bytes_of_f32(&set.scene_depth),
        ),
        (
            "whole_rgb",
            Dtype::U8,
            vec![n, r, r, 3],
            set.whole_rgb.clone(),
        ),
        (
            "amodal_mask",
            Dtype::U8,
            vec![n, r, r],
            set.amodal_mask.clone(),
        ),
        (
            "whole_depth",
            Dtype::F32,
            vec![n, r, r],
            bytes_of_f32(&set.whole_depth),
        ),
        (
            "whole_back_depth",
            Dtype::F32,
            vec![n, r, r],
            bytes_of_f32(&set.whole_back_depth),
        ),
        ("group", Dtype::U32, vec![n], bytes_of_u32(&set.group)),
        ("category", Dtype::U8, vec![n], set.category.clone()),
        ("held_out", Dtype::U8, vec![n], set.held_out.clone()),
        (
            "occlusion",
            Dtype::F32,
            vec![n],
            bytes_of_f32(&set.occlusion),
        ),
        (
            "crop_width_m",
            Dtype::F32,
            vec![n],
            bytes_of_f32(&set.crop_width_m),
        ),
    ];
    let elsewhere = set.has_elsewhere().then(|| {
        [
            (
                "elsewhere_rgb",
                Dtype::U8,
                vec![n, r, r, 3],
                set.elsewhere_rgb.clone(),
            ),
            (
                "elsewhere_depth",
                Dtype::F32,
                vec![n, r, r],
                bytes_of_f32(&set.elsewhere_depth),
            ),
        ]
    });
    let views: Vec<(&str, TensorView)> = f
        .iter()
        .chain(elsewhere.iter().flatten())
        .map(|(name, dt, shape, data)| {
            TensorView::new(*dt, shape.clone(), data).map(|v| (*name, v))
        })
        .collect::<std::result::Result<_, _>>()
        .map_err(|e| IoError::invalid(path, e.to_string()))?;
    let bytes =
        safetensors::serialize(views, None).map_err(|e| IoError::invalid(path, e.to_string()))?;
    crate::atomic::write_bytes_atomic(path, &bytes)
}

/// Loads pairs saved by [`save_pairs`], checking every tensor's type and shape.
pub fn load_pairs(path: &Path) -> Result<PairSet> {
    let err = |msg: String| IoError::invalid(path, msg);
    let bytes = std::fs::read(path).map_err(|e| IoError::new(path, e))?;
    let st = safetensors::SafeTensors::deserialize(&bytes)
        .map_err(|e| err(format!("not a safetensors file: {e}")))?;
    let get = |name: &str, dt: Dtype| -> Result<(Vec<usize>, &[u8])> {
        let t = st
            .tensor(name)
            .map_err(|_| err(format!("missing tensor '{name}'")))?;
        if t.dtype() != dt {
            return Err(err(format!(
                "tensor '{name}' is {:?}, expected {dt:?}",
                t.dtype()
            )));
        }
        Ok((t.shape().to_vec(), t.data()))
    };
    let f32s = |b: &[u8]| {
        b.chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect::<Vec<f32>>()
    };
    let (shape, crop_rgb) = get("crop_rgb", Dtype::U8)?;
    let [n, r, r2, 3] = shape[..] else {
        return Err(err(format!(
            "crop_rgb has shape {shape:?}, expected (N, R, R, 3)"
        )));
    };
    if r != r2 {
        return Err(err("crops are not square".into()));
    }
    let set = PairSet {
        resolution: r as u32,
        crop_rgb: crop_rgb.to_vec(),
        visible_mask: get("visible_mask", Dtype::U8)?.1.to_vec(),
        visible_depth: f32s(get("visible_depth", Dtype::F32)?.1),
        scene_depth: f32s(
            get("scene_depth", Dtype::F32)
                .map_err(|_| {
                    err(
                        "missing tensor 'scene_depth': pairs from before it was added; \
                         make them again with `deocc synth pairs`"
                            .into(),
                    )
                })?
                .1,
        ),
        whole_rgb: get("whole_rgb", Dtype::U8)?.1.to_vec(),
        amodal_mask: get("amodal_mask", Dtype::U8)?.1.to_vec(),
        whole_depth: f32s(get("whole_depth", Dtype::F32)?.1),
        whole_back_depth: f32s(get("whole_back_depth", Dtype::F32)?.1),
        group: get("group", Dtype::U32)?
            .1
            .chunks_exact(4)
            .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect(),
        category: get("category", Dtype::U8)?.1.to_vec(),
        held_out: get("held_out", Dtype::U8)?.1.to_vec(),
        occlusion: f32s(get("occlusion", Dtype::F32)?.1),
        // Optional: older shards do not store it.
        crop_width_m: match st.tensor("crop_width_m") {
            Ok(_) => f32s(get("crop_width_m", Dtype::F32)?.1),
            Err(_) => vec![f32::NAN; n],
        },
        // Optional: sets made without other views' observations.
        elsewhere_rgb: match st.tensor("elsewhere_rgb") {
            Ok(_) => get("elsewhere_rgb", Dtype::U8)?.1.to_vec(),
            Err(_) => Vec::new(),
        },
        elsewhere_depth: match st.tensor("elsewhere_depth") {
            Ok(_) => f32s(get("elsewhere_depth", Dtype::F32)?.1),
            Err(_) => Vec::new(),
        },
    };
    let px = r * r;
    let ok = set.visible_mask.len() == n * px
        && set.amodal_mask.len() == n * px
        && set.whole_rgb.len() == n * px * 3
        && set.visible_depth.len() == n * px
        && set.scene_depth.len() == n * px
        && set.whole_depth.len() == n * px
        && set.whole_back_depth.len() == n * px
        && set.group.len() == n
        && set.category.len() == n
        && set.held_out.len() == n
        && set.occlusion.len() == n
        && set.crop_width_m.len() == n
        && (set.elsewhere_rgb.len() == n * px * 3 || set.elsewhere_rgb.is_empty())
        && (set.elsewhere_depth.len() == n * px || set.elsewhere_depth.is_empty())
        && set.elsewhere_rgb.is_empty() == set.elsewhere_depth.is_empty();
    if !ok {
        return Err(err("tensor sizes disagree with the number of pairs".into()));
    }
    Ok(set)
}

/// The number of pairs in a shard, from its header alone (no tensor data is read).
pub fn count_pairs(path: &Path) -> Result<usize> {
    use std::io::Read;
    let mut f = std::fs::File::open(path).map_err(|e| IoError::new(path, e))?;
    let mut len = [0u8; 8];
    f.read_exact(&mut len).map_err(|e| IoError::new(path, e))?;
    let n = u64::from_le_bytes(len);
    let size = f.metadata().map_err(|e| IoError::new(path, e))?.len();
    if n == 0 || n > size.saturating_sub(8) || n > 100 << 20 {
        return Err(IoError::invalid(
            path,
            format!("not a safetensors file (header of {n} bytes in a file of {size})"),
        ));
    }
    let mut header = vec![0u8; n as usize];
    f.read_exact(&mut header)
        .map_err(|e| IoError::new(path, e))?;
    let json: serde_json::Value = serde_json::from_slice(&header)
        .map_err(|e| IoError::invalid(path, format!("safetensors header: {e}")))?;
    json.get("group")
        .and_then(|g| g.get("shape"))
        .and_then(|s| s.get(0))
        .and_then(|n| n.as_u64())
        .map(|n| n as usize)
        .ok_or_else(|| IoError::invalid(path, "no 'group' tensor: not a pair shard"))
}
