//! Benchmarks against peers, in the same run, alternating rounds; each returns a report the CLI
//! writes. The peers' scripts are built into the binary.

pub mod geometry;
pub mod memory;
pub mod model;
pub mod service;
pub mod soak;
pub mod synth;
pub mod timing;
