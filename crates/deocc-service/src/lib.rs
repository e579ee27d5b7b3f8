//! deocc as a gRPC service (tonic): the `Complete` call (frames in, progress events and the
//! completed cloud in the sensor_msgs/PointCloud2 layout out), `Grasp` and `Place` on a
//! completed cloud, `Health`; the server's engineering (shared model, bounded queue, deadlines,
//! cancellation, message limits, token) in [`server`]; a client in [`client`].
//!
//! The wire format is `proto/deocc/v1/deocc.proto`, compiled at build time by protox (no system
//! `protoc`).

pub mod client;
pub mod cloud2;
pub mod guard;
pub mod local;
pub mod raw;
pub mod request;
pub mod server;

pub use tonic::Code;

/// The generated messages, client and server of `deocc.v1`.
pub mod proto {
    #![allow(clippy::all, clippy::pedantic, missing_docs)]
    tonic::include_proto!("deocc.v1");
}

/// A bad field of a request: answered INVALID_ARGUMENT with the field named.
#[derive(Debug, Clone, thiserror::Error)]
#[error("{field}: {msg}")]
pub struct FieldError {
    pub field: String,
    pub msg: String,
}

impl FieldError {
    pub fn new(field: impl Into<String>, msg: impl Into<String>) -> Self {
        Self {
            field: field.into(),
            msg: msg.into(),
        }
    }
}
