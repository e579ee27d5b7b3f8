//! # deocc-ros2
//!
//! deocc for ROS 2 robots. [`msgs`]: the sensor_msgs / geometry_msgs / std_srvs messages the
//! bridge speaks (CDR via serde); [`convert`]: those messages to and from deocc's service
//! messages, checked by the service's own request decoder; [`sync`]: colour, depth, calibration
//! and pose matched into views by stamp; [`node`] (feature `ros2`): the bridge node on
//! `ros2-client`, with the `deocc-ros2` binary on top.

pub mod bag;
pub mod convert;
pub mod msgs;
pub mod sync;

#[cfg(feature = "ros2")]
pub mod node;
