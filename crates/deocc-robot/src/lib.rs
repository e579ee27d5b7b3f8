//! # deocc-robot
//!
//! Robot tasks on a point cloud, completed or not: where a parallel-jaw gripper can grasp a
//! target ([`grasp`]), where an object of a given footprint can be put down ([`place`]), and how
//! good those answers are against ground-truth geometry ([`grasp_eval`], [`place`]'s map
//! comparison). Plain data in and out; no renderer, no ML stack. The planners are traits
//! ([`grasp::GraspPlanner`], [`place::PlacePlanner`]) with defaults that need no weights.

pub mod grasp;
pub mod grasp_eval;
pub mod gripper;
pub mod picture;
pub mod place;
pub mod range;
pub mod target;

pub use grasp::{AntipodalPlanner, GraspOptions, GraspPlanner, PlanStats};
pub use gripper::{Grasp, GripperConfig};
pub use place::{GridPlacer, PlaceMap, PlaceOptions, PlacePlanner, UnseenSpace};

#[derive(Debug, thiserror::Error)]
pub enum RobotError {
    /// A setting out of range, naming it.
    #[error("{0}")]
    Config(String),
    /// Input the task cannot work with (too few points, no support plane, ...).
    #[error("{0}")]
    Input(String),
    #[error(transparent)]
    Geometry(#[from] deocc_geometry::GeometryError),
}
