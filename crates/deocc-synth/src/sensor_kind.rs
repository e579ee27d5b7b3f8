//! The names of the depth sensor models ([`crate::sensor`] has the models): plain data that a
//! scene or pair configuration carries without depending on the renderer.

use serde::{Deserialize, Serialize};

/// Which sensor measures the depth.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SensorKind {
    /// The renderer's depth, exactly.
    #[default]
    Clean,
    /// The project's first model: Gaussian noise of 0.0012 z^2 m and no depth at grazing angles
    /// (incidence cosine under 0.15). Kept to reproduce older figures.
    Gaussian,
    /// A Kinect v1-class structured-light camera (projector 7.5 cm beside the IR camera).
    StructuredLight,
    /// A RealSense D4xx-class active stereo camera (two IR cameras 5 cm apart).
    ActiveStereo,
    /// An Azure Kinect-class time-of-flight camera.
    TimeOfFlight,
    /// One of the three real sensors per render, each parameter drawn within its range
    /// ([`crate::sensor::Sensor::randomised`]).
    Random,
}

impl SensorKind {
    pub const NAMES: [&'static str; 6] = [
        "clean",
        "gaussian",
        "structured-light",
        "active-stereo",
        "time-of-flight",
        "random",
    ];

    pub fn parse(s: &str) -> Result<Self, String> {
        Ok(match s {
            "clean" | "none" => Self::Clean,
            "gaussian" => Self::Gaussian,
            "structured-light" | "structured_light" | "kinect" => Self::StructuredLight,
            "active-stereo" | "active_stereo" | "realsense" => Self::ActiveStereo,
            "time-of-flight" | "time_of_flight" | "tof" => Self::TimeOfFlight,
            "random" => Self::Random,
            other => {
                return Err(format!(
                    "unknown sensor {other:?}: one of {}",
                    Self::NAMES.join(", ")
                ))
            }
        })
    }

    pub fn name(self) -> &'static str {
        match self {
            Self::Clean => "clean",
            Self::Gaussian => "gaussian",
            Self::StructuredLight => "structured-light",
            Self::ActiveStereo => "active-stereo",
            Self::TimeOfFlight => "time-of-flight",
            Self::Random => "random",
        }
    }
}
