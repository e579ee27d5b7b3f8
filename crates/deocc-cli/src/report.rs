//! Reports of the eval and bench commands: a JSON file (its folder created) and the same JSON on
//! standard output.

use std::path::Path;

use anyhow::{Context, Result};
use serde::Serialize;

pub fn write_report<T: Serialize>(path: &Path, report: &T) -> Result<()> {
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent)
            .with_context(|| format!("{}: cannot create", parent.display()))?;
    }
    deocc_io::cameras::write_json(path, report)?;
    println!("{}", serde_json::to_string_pretty(report)?);
    Ok(())
}

/// A picture sink for a benchmark's `--pictures DIR`: creates DIR, then writes each picture it
/// is handed to DIR/PREFIX-SEED.png. `None` without a folder.
pub struct PictureWriter<'a> {
    dir: &'a Path,
    prefix: &'static str,
}

impl<'a> PictureWriter<'a> {
    pub fn new(dir: Option<&'a Path>, prefix: &'static str) -> Result<Option<Self>> {
        let Some(dir) = dir else {
            return Ok(None);
        };
        std::fs::create_dir_all(dir)
            .with_context(|| format!("cannot create the pictures folder {}", dir.display()))?;
        Ok(Some(Self { dir, prefix }))
    }

    pub fn write(
        &self,
        seed: u64,
        img: deocc_robot::picture::RgbImage,
    ) -> Result<(), deocc_eval::EvalError> {
        let path = self.dir.join(format!("{}-{seed}.png", self.prefix));
        img.save(&path).map_err(|e| {
            deocc_eval::EvalError::Data(format!("cannot write {}: {e}", path.display()))
        })
    }
}
