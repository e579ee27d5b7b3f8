//! The scene options shared by `deocc synth scenes` and `deocc synth sheet`.

use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use clap::{Args, ValueEnum};
use deocc_synth::scene::{CameraPath, SceneConfig, UserMesh};

#[derive(Clone, Copy, ValueEnum)]
pub enum PathArg {
    RobotHead,
    Arc,
    Single,
}

#[derive(Args)]
pub struct SceneOptions {
    /// Views per scene.
    #[arg(long, default_value_t = 10)]
    views: usize,
    #[arg(long, default_value_t = 640)]
    width: u32,
    #[arg(long, default_value_t = 480)]
    height: u32,
    #[arg(long, value_enum, default_value_t = PathArg::RobotHead)]
    camera_path: PathArg,
    /// Include the held-out shapes (vase, L-bracket), as test scenes do.
    #[arg(long)]
    held_out_shapes: bool,
    #[command(flatten)]
    sensor: crate::sensor::SensorArgs,
    /// Ground-truth surface samples per square metre.
    #[arg(long, default_value_t = 10_000.0)]
    gt_density: f32,
    /// A user mesh to put on the table, as PATH=SIZE_M (OBJ, PLY or STL), repeatable: scaled so
    /// that its largest side is SIZE_M, which must fit on the table top (tables are 0.6-1.0 m
    /// deep, so up to about 0.35 m; a mesh that does not fit is an error).
    #[arg(long = "mesh", value_name = "PATH=SIZE_M")]
    meshes: Vec<String>,
}

impl SceneOptions {
    /// The sensor `--sensor` (or `--sensor-noise`) names.
    pub fn sensor_kind(&self) -> Result<deocc_synth::sensor::SensorKind> {
        self.sensor.kind()
    }

    /// Frames from each camera pose (`--burst`).
    pub fn burst(&self) -> usize {
        self.sensor.burst as usize
    }

    pub fn config(&self) -> Result<SceneConfig> {
        let user_meshes = self
            .meshes
            .iter()
            .map(|m| {
                let (path, size) = m
                    .rsplit_once('=')
                    .context("--mesh takes PATH=SIZE_M, e.g. bunny.ply=0.15")?;
                let size_m: f32 = size
                    .parse()
                    .with_context(|| format!("--mesh {m}: '{size}' is not a size in metres"))?;
                if !(size_m > 0.0 && size_m < 2.0) {
                    bail!("--mesh {m}: size must be in (0, 2) metres");
                }
                Ok(UserMesh {
                    path: PathBuf::from(path),
                    size_m,
                })
            })
            .collect::<Result<_>>()?;
        if self.views == 0 || self.width < 16 || self.height < 16 {
            bail!("need at least one view and an image of at least 16x16 pixels");
        }
        Ok(SceneConfig {
            width: self.width,
            height: self.height,
            views: self.views,
            camera_path: match self.camera_path {
                PathArg::RobotHead => CameraPath::RobotHead,
                PathArg::Arc => CameraPath::Arc,
                PathArg::Single => CameraPath::Single,
            },
            held_out_shapes: self.held_out_shapes,
            sensor: self.sensor.kind()?,
            burst: self.burst(),
            gt_points_per_m2: self.gt_density,
            user_meshes,
            ..SceneConfig::default()
        })
    }
}
