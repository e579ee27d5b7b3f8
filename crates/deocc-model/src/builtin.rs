//! The shipped model (weights/gldot-small), built into whatever links this: the CLI, the Python
//! package and the service work from any folder without a weights path.

use candle_core::Device;

use crate::infer::GlDotCompleter;

pub const TRAIN_JSON: &str = include_str!("../../../weights/gldot-small/train.json");
pub const WEIGHTS: &[u8] = include_bytes!("../../../weights/gldot-small/ema.safetensors");

/// The built-in GL-DoT.
pub fn load(device: &Device) -> crate::train::Result<GlDotCompleter> {
    GlDotCompleter::from_bytes(TRAIN_JSON, WEIGHTS, device)
}

/// A stable fingerprint of the built-in weights (FNV-1a, not a security hash), for health
/// answers and logs.
pub fn fingerprint() -> String {
    let h = WEIGHTS.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| {
        (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
    });
    format!("gldot-small fnv64 {h:016x}")
}
