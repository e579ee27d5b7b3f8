//! The one place the robot tasks' numeric settings are checked: each is given a closed range
//! (stated in its error), so a value from any interface (an options file, gRPC, Python, ROS 2)
//! that would make a planner loop for hours, allocate without bound, or silently find nothing
//! is refused naming the setting.

use crate::RobotError;

/// `name = v` must lie in `[lo, hi]` (NaN never does).
pub fn real(name: &str, v: f32, lo: f32, hi: f32, unit: &str) -> Result<(), RobotError> {
    if v.is_finite() && (lo..=hi).contains(&v) {
        Ok(())
    } else {
        Err(RobotError::Config(format!(
            "{name} = {v}: must be in [{lo}, {hi}]{unit}"
        )))
    }
}

/// `name = v` must lie in `lo..=hi`.
pub fn count(name: &str, v: usize, lo: usize, hi: usize) -> Result<(), RobotError> {
    if (lo..=hi).contains(&v) {
        Ok(())
    } else {
        Err(RobotError::Config(format!(
            "{name} = {v}: must be in {lo}..={hi}"
        )))
    }
}

/// A direction: three finite numbers, not all zero.
pub fn direction(name: &str, v: [f32; 3]) -> Result<(), RobotError> {
    let n = nalgebra::Vector3::from(v).norm();
    if n.is_finite() && n > 1e-6 {
        Ok(())
    } else {
        Err(RobotError::Config(format!(
            "{name} = {v:?}: must be a non-zero finite vector"
        )))
    }
}
