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
