//! The built-in example of `deocc run --example`: bench-v1 scene 0 (ten robot-head views,
//! 640x480 RGB-D with instance maps, and its ground truth), embedded in the binary so that the
//! product binary needs neither the benchmark renderer nor a download. The files are made by
//! `deocc synth example --out crates/deocc-cli/example`; a test (with the `lab` feature) renders
//! them again and checks they are current.

use std::path::Path;

use anyhow::{Context, Result};

/// The example's files: path in the scene folder, bytes.
pub const FILES: &[(&str, &[u8])] = &[
    ("cameras.json", include_bytes!("../example/cameras.json")),
    (
        "ground_truth.ply",
        include_bytes!("../example/ground_truth.ply"),
    ),
    ("scene.json", include_bytes!("../example/scene.json")),
    (
        "rgb/000000.png",
        include_bytes!("../example/rgb/000000.png"),
    ),
    (
        "rgb/000001.png",
        include_bytes!("../example/rgb/000001.png"),
    ),
    (
        "rgb/000002.png",
        include_bytes!("../example/rgb/000002.png"),
    ),
    (
        "rgb/000003.png",
        include_bytes!("../example/rgb/000003.png"),
    ),
    (
        "rgb/000004.png",
        include_bytes!("../example/rgb/000004.png"),
    ),
    (
        "rgb/000005.png",
        include_bytes!("../example/rgb/000005.png"),
    ),
    (
        "rgb/000006.png",
        include_bytes!("../example/rgb/000006.png"),
    ),
    (
        "rgb/000007.png",
        include_bytes!("../example/rgb/000007.png"),
    ),
    (
        "rgb/000008.png",
        include_bytes!("../example/rgb/000008.png"),
    ),
    (
        "rgb/000009.png",
        include_bytes!("../example/rgb/000009.png"),
    ),
    (
        "depth/000000.png",
        include_bytes!("../example/depth/000000.png"),
    ),
    (
        "depth/000001.png",
        include_bytes!("../example/depth/000001.png"),
    ),
    (
        "depth/000002.png",
        include_bytes!("../example/depth/000002.png"),
    ),
    (
        "depth/000003.png",
        include_bytes!("../example/depth/000003.png"),
    ),
    (
        "depth/000004.png",
        include_bytes!("../example/depth/000004.png"),
    ),
    (
        "depth/000005.png",
        include_bytes!("../example/depth/000005.png"),
    ),
    (
        "depth/000006.png",
        include_bytes!("../example/depth/000006.png"),
    ),
    (
        "depth/000007.png",
        include_bytes!("../example/depth/000007.png"),
    ),
    (
        "depth/000008.png",
        include_bytes!("../example/depth/000008.png"),
    ),
    (
        "depth/000009.png",
        include_bytes!("../example/depth/000009.png"),
    ),
    (
        "instances/000000.png",
        include_bytes!("../example/instances/000000.png"),
    ),
    (
        "instances/000001.png",
        include_bytes!("../example/instances/000001.png"),
    ),
    (
        "instances/000002.png",
        include_bytes!("../example/instances/000002.png"),
    ),
    (
        "instances/000003.png",
        include_bytes!("../example/instances/000003.png"),
    ),
    (
        "instances/000004.png",
        include_bytes!("../example/instances/000004.png"),
    ),
    (
        "instances/000005.png",
        include_bytes!("../example/instances/000005.png"),
    ),
    (
        "instances/000006.png",
        include_bytes!("../example/instances/000006.png"),
    ),
    (
        "instances/000007.png",
        include_bytes!("../example/instances/000007.png"),
    ),
    (
        "instances/000008.png",
        include_bytes!("../example/instances/000008.png"),
    ),
    (
        "instances/000009.png",
        include_bytes!("../example/instances/000009.png"),
    ),
];

/// Writes the example scene folder into `dir`.
pub fn write_example_scene(dir: &Path) -> Result<()> {
    for (name, bytes) in FILES {
        let path = dir.join(name);
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent)
                .with_context(|| format!("{}: cannot create", parent.display()))?;
        }
        std::fs::write(&path, bytes)
            .with_context(|| format!("{}: cannot write", path.display()))?;
    }
    Ok(())
}

#[cfg(all(test, feature = "lab"))]
mod tests {
    /// The embedded example is what the renderer makes today (refresh it with `deocc synth
    /// example --out crates/deocc-cli/example` when the renderer changes).
    #[test]
    fn the_embedded_example_is_current() {
        let tmp = tempfile::tempdir().unwrap();
        crate::synth::write_example_scene(tmp.path()).unwrap();
        let mut made = Vec::new();
        for sub in ["", "rgb", "depth", "instances"] {
            for e in std::fs::read_dir(tmp.path().join(sub)).unwrap() {
                let e = e.unwrap();
                if e.path().is_file() {
                    let name = e
                        .path()
                        .strip_prefix(tmp.path())
                        .unwrap()
                        .to_string_lossy()
                        .into_owned();
                    made.push(name);
                }
            }
        }
        made.sort();
        let mut embedded: Vec<String> = super::FILES.iter().map(|f| f.0.to_string()).collect();
        embedded.sort();
        assert_eq!(made, embedded, "the example's files");
        for (name, bytes) in super::FILES {
            let fresh = std::fs::read(tmp.path().join(name)).unwrap();
            assert!(
                fresh == *bytes,
                "{name} differs from a fresh render: run `deocc synth example --out crates/deocc-cli/example`"
            );
        }
    }
}
