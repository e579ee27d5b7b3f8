//! What `deocc run` reads besides scene folders: TUM RGB-D sequences and MCAP recordings, and
//! which of their frames become views.

use anyhow::{bail, Result};
use clap::Args;
use deocc_io::tum::FramePick;
use deocc_pipeline::recording::RecordingOptions;

#[derive(Args, Clone, Default)]
pub struct InputArgs {
    /// Recording input: the colour topic; `*` stands for one path segment to take one camera
    /// per view (default `/deocc/camera/*/rgb`, as `deocc run --mcap` writes).
    #[arg(long, value_name = "TOPIC")]
    rgb: Option<String>,
    /// Recording input: the depth topic (registered to colour); default the colour topic's
    /// sibling `depth`.
    #[arg(long, value_name = "TOPIC")]
    depth_topic: Option<String>,
    /// Recording input: the CameraInfo / calibration topic; default the sibling `calibration`
    /// or `camera_info`.
    #[arg(long, value_name = "TOPIC")]
    info: Option<String>,
    /// Recording input: the /tf child frame whose transform is the camera pose (default each
    /// image's frame_id; without transforms the views are registered by ICP).
    #[arg(long, value_name = "TF-FRAME")]
    poses: Option<String>,
    /// Recording or sequence input: take every N-th frame.
    #[arg(long, default_value_t = 1, value_name = "N")]
    every: usize,
    /// Recording or sequence input with poses: a frame becomes a view once the camera moved
    /// METRES or turned DEGREES since the last view (overrides --every).
    #[arg(long, value_name = "METRES,DEGREES")]
    keyframes: Option<String>,
    /// Recording or sequence input: at most this many views.
    #[arg(long, default_value_t = 10, value_name = "N")]
    max_frames: usize,
}

impl InputArgs {
    pub fn options(&self) -> Result<RecordingOptions> {
        if self.every == 0 || self.max_frames == 0 {
            bail!("--every and --max-frames must be at least 1");
        }
        let keyframes = match &self.keyframes {
            None => None,
            Some(t) => {
                let v: Vec<f32> = t
                    .split(',')
                    .map(|x| x.trim().parse::<f32>())
                    .collect::<Result<_, _>>()
                    .map_err(|_| anyhow::anyhow!("--keyframes {t:?}: expected METRES,DEGREES"))?;
                match v[..] {
                    [m, d] if m >= 0.0 && d >= 0.0 && m.is_finite() && d.is_finite() => {
                        Some((m, d))
                    }
                    _ => bail!("--keyframes {t:?}: expected two non-negative numbers"),
                }
            }
        };
        Ok(RecordingOptions {
            rgb: self.rgb.clone(),
            depth: self.depth_topic.clone(),
            info: self.info.clone(),
            poses: self.poses.clone(),
            pick: FramePick {
                every: self.every,
                keyframes,
                max_frames: self.max_frames,
            },
        })
    }
}
