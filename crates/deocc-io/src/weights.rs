//! A safetensors file's header, read and checked before the file itself: a loader that reads a
//! whole file to find out it is not weights holds gigabytes for nothing (a 20 GB file of anything
//! took 12 GB in a minute). [`check_safetensors`] reads 8 bytes and the header, checks that the
//! header describes exactly the bytes that follow, and only then may the caller read the file.

use std::io::Read;
use std::path::Path;

use crate::error::{IoError, Result};

/// Largest header accepted (the format's own limit is 100 MB; real checkpoints have a few kB to
/// a few hundred kB).
pub const MAX_HEADER_BYTES: u64 = 100 << 20;

/// What a checked header says.
#[derive(Debug, Clone)]
pub struct SafetensorsHeader {
    /// Tensor names, in the header's order (`__metadata__` left out).
    pub names: Vec<String>,
    /// Bytes of tensor data after the header.
    pub data_bytes: u64,
}

/// Reads and checks the header of the safetensors file at `path`: its length fits the file and
/// [`MAX_HEADER_BYTES`], it is a JSON object of tensors with dtype, shape and data offsets, the
/// offsets tile the data exactly, and the file is at most `max_file_bytes`. Errors name the file.
pub fn check_safetensors(path: &Path, max_file_bytes: u64) -> Result<SafetensorsHeader> {
    let bad = |msg: String| IoError::invalid(path, format!("not a safetensors file: {msg}"));
    let mut file = std::fs::File::open(path).map_err(|e| IoError::new(path, e))?;
    let meta = file.metadata().map_err(|e| IoError::new(path, e))?;
    if !meta.is_file() {
        return Err(IoError::invalid(path, "not a regular file"));
    }
    let size = meta.len();
    if size > max_file_bytes {
        return Err(IoError::invalid(
            path,
            format!(
                "{size} bytes, more than the {max_file_bytes} bytes a weights file may have here"
            ),
        ));
    }
    let mut len = [0u8; 8];
    file.read_exact(&mut len)
        .map_err(|_| bad(format!("{size} bytes, too short for a header")))?;
    let n = u64::from_le_bytes(len);
    if !(2..=MAX_HEADER_BYTES).contains(&n) || n > size - 8 {
        return Err(bad(format!(
            "its header length field says {n} bytes (the file has {size}; at most {MAX_HEADER_BYTES})"
        )));
    }
    let mut header = vec![0u8; n as usize];
    file.read_exact(&mut header)
        .map_err(|e| IoError::new(path, e))?;
    let value: serde_json::Value = serde_json::from_slice(&header)
        .map_err(|e| bad(format!("its header is not JSON ({e})")))?;
    let obj = value
        .as_object()
        .ok_or_else(|| bad("its header is not a JSON object".into()))?;
    let data_bytes = size - 8 - n;
    let mut spans = Vec::new();
    let mut names = Vec::new();
    for (name, t) in obj {
        if name == "__metadata__" {
            continue;
        }
        let offsets = t
            .get("data_offsets")
            .and_then(|o| o.as_array())
            .filter(|o| o.len() == 2)
            .and_then(|o| Some((o[0].as_u64()?, o[1].as_u64()?)))
            .ok_or_else(|| bad(format!("tensor {name:?} has no data_offsets [begin, end]")))?;
        if t.get("dtype").and_then(|d| d.as_str()).is_none()
            || t.get("shape").and_then(|s| s.as_array()).is_none()
        {
            return Err(bad(format!("tensor {name:?} has no dtype or shape")));
        }
        if offsets.0 > offsets.1 || offsets.1 > data_bytes {
            return Err(bad(format!(
                "tensor {name:?} spans bytes {}..{} of {data_bytes}",
                offsets.0, offsets.1
            )));
        }
        spans.push(offsets);
        names.push(name.clone());
    }
    spans.sort_unstable();
    let mut end = 0;
    for (b, e) in &spans {
        if *b != end {
            return Err(bad(format!(
                "its tensors leave a gap or overlap at byte {end} of the data"
            )));
        }
        end = *e;
    }
    if end != data_bytes {
        return Err(bad(format!(
            "its tensors cover {end} bytes, but {data_bytes} follow the header"
        )));
    }
    Ok(SafetensorsHeader { names, data_bytes })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn file(bytes: &[u8]) -> (tempfile::TempDir, std::path::PathBuf) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("w.safetensors");
        std::fs::write(&path, bytes).unwrap();
        (dir, path)
    }

    fn safetensors(header: &str, data: usize) -> Vec<u8> {
        let mut b = (header.len() as u64).to_le_bytes().to_vec();
        b.extend_from_slice(header.as_bytes());
        b.extend(std::iter::repeat_n(0u8, data));
        b
    }

    #[test]
    fn a_good_header_gives_its_names_and_bad_ones_are_refused_by_the_file() {
        let h = r#"{"a":{"dtype":"F32","shape":[2],"data_offsets":[0,8]},"b":{"dtype":"F32","shape":[1],"data_offsets":[8,12]}}"#;
        let (_d, p) = file(&safetensors(h, 12));
        let got = check_safetensors(&p, 1 << 30).unwrap();
        assert_eq!(got.names, vec!["a", "b"]);
        assert_eq!(got.data_bytes, 12);
        for (bytes, why) in [
            (vec![0u8; 4096], "header length"),
            (vec![0xffu8; 64], "header length"),
            (vec![1u8, 2, 3], "too short"),
            (safetensors("[1,2]", 0), "not a JSON object"),
            (safetensors("{not json", 0), "not JSON"),
            (safetensors(h, 11), "spans bytes"),
            (safetensors(h, 13), "cover 12 bytes"),
        ] {
            let (_d, p) = file(&bytes);
            let e = check_safetensors(&p, 1 << 30).unwrap_err().to_string();
            assert!(e.contains("w.safetensors") && e.contains(why), "{why}: {e}");
        }
        let (_d, p) = file(&safetensors(h, 12));
        let e = check_safetensors(&p, 10).unwrap_err().to_string();
        assert!(e.contains("more than"), "{e}");
    }
}
