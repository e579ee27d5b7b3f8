//! `--sensor NAME`: which depth sensor measures the rendered scenes of a synth or eval command.

use clap::Args;
use deocc_synth::sensor::SensorKind;

#[derive(Args, Clone, Debug)]
pub struct SensorArgs {
    /// The depth sensor that measures the rendered views: clean (the renderer's depth),
    /// structured-light (Kinect v1-class), active-stereo (RealSense D4xx-class), time-of-flight
    /// (Azure Kinect-class), gaussian (the project's first model), or random (a sensor drawn per
    /// scene within documented ranges, with colour realism). See `deocc_synth::sensor`.
    #[arg(long, value_parser = SensorKind::parse, default_value = "clean")]
    pub sensor: SensorKind,
    /// The first sensor model (Gaussian noise of 0.0012 z^2, no depth at grazing angles): the
    /// same as `--sensor gaussian`.
    #[arg(long)]
    pub sensor_noise: bool,
}

impl SensorArgs {
    /// The sensor in force; refuses `--sensor-noise` beside another `--sensor`.
    pub fn kind(&self) -> anyhow::Result<SensorKind> {
        match (self.sensor, self.sensor_noise) {
            (SensorKind::Clean, true) => Ok(SensorKind::Gaussian),
            (k, true) if k != SensorKind::Gaussian => anyhow::bail!(
                "--sensor-noise is --sensor gaussian; it cannot go with --sensor {}",
                k.name()
            ),
            (k, _) => Ok(k),
        }
    }

    /// Sets `preset`'s sensor and names it in the preset's name.
    pub fn apply(&self, preset: &mut deocc_synth::dataset::Preset) -> anyhow::Result<()> {
        deocc_eval::with_sensor(preset, self.kind()?);
        Ok(())
    }
}
