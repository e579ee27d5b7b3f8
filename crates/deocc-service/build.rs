//! Compiles proto/deocc/v1/deocc.proto with protox (no system protoc) into tonic's client and
//! server code.

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let proto = "proto/deocc/v1/deocc.proto";
    println!("cargo:rerun-if-changed={proto}");
    let fds = protox::compile([proto], ["proto"])?;
    tonic_prost_build::configure().compile_fds(fds)?;
    Ok(())
}
