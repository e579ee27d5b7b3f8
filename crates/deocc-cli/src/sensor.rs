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
    /// Frames the sensor takes from each camera pose (a robot holding still), each with its own
    /// noise; the pipeline fuses them into one (its `burst` stage).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=16))]
    pub burst: u32,
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

    /// The sensor in force for a command that measures frames one at a time: `--burst` above 1
    /// is refused, naming `command`, rather than ignored.
    pub fn kind_without_burst(&self, command: &str) -> anyhow::Result<SensorKind> {
        if self.burst > 1 {
            anyhow::bail!(
                "--burst {}: `{command}` does not take bursts (they are for `deocc synth scenes` \
                 and `deocc eval objects | grasp | place`)",
                self.burst
            );
        }
        self.kind()
    }

    /// Sets `preset`'s sensor and burst and names them in the preset's name.
    pub fn apply(&self, preset: &mut deocc_synth::dataset::Preset) -> anyhow::Result<()> {
        deocc_eval::with_sensor(preset, self.kind()?);
        if self.burst > 1 {
            preset.config.burst = self.burst as usize;
            preset.name = format!("{}, bursts of {} frames", preset.name, self.burst);
        }
        Ok(())
    }
}
