//! The NumPy `.npy` format (version 1 and 2 headers), as far as depth images need it: a 2-D
//! C-order array of little-endian `f4` (metres) or `u2` (units of a scale). Many drivers and
//! Python pipelines write depth this way; see
//! <https://numpy.org/doc/stable/reference/generated/numpy.lib.format.html>.

/// Largest header accepted (bytes); NumPy writes under 200.
const MAX_HEADER: usize = 1 << 16;

/// Parses `bytes` into (height, width, metres), refusing arrays over `max_side` a side before
/// reading their body. Non-finite and non-positive values are "no measurement" (0).
pub fn read_depth_npy(
    bytes: &[u8],
    scale: f64,
    max_side: u32,
) -> Result<(u32, u32, Vec<f32>), String> {
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return Err("not a NumPy .npy file (no \\x93NUMPY magic)".into());
    }
    let (header_len, start) = match bytes[6] {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 if bytes.len() >= 12 => (
            u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
            12,
        ),
        v => {
            return Err(format!(
                ".npy format version {v} is not supported (1, 2 or 3)"
            ))
        }
    };
    if header_len > MAX_HEADER || start + header_len > bytes.len() {
        return Err(format!(
            ".npy header of {header_len} bytes is cut short or too long"
        ));
    }
    let header = std::str::from_utf8(&bytes[start..start + header_len])
        .map_err(|_| ".npy header is not text".to_string())?;
    let field = |key: &str| -> Option<&str> {
        let at = header.find(&format!("'{key}'"))? + key.len() + 2;
        let rest = header[at..].trim_start().strip_prefix(':')?.trim_start();
        Some(rest)
    };
    let descr = field("descr")
        .and_then(|r| r.strip_prefix('\''))
        .and_then(|r| r.split('\'').next())
        .ok_or(".npy header has no 'descr'")?;
    if field("fortran_order").is_some_and(|r| r.starts_with("True")) {
        return Err(
            ".npy array is in Fortran order; save it C-ordered (np.ascontiguousarray)".into(),
        );
    }
    let shape_text = field("shape")
        .and_then(|r| r.strip_prefix('('))
        .and_then(|r| r.split(')').next())
        .ok_or(".npy header has no 'shape'")?;
    let dims: Vec<usize> = shape_text
        .split(',')
        .map(str::trim)
        .filter(|t| !t.is_empty())
        .map(|t| {
            t.parse::<usize>()
                .map_err(|_| format!(".npy shape entry {t:?}"))
        })
        .collect::<Result<_, _>>()?;
    // (H, W) or (H, W, 1).
    let (h, w) = match dims[..] {
        [h, w] | [h, w, 1] => (h, w),
        _ => {
            return Err(format!(
                ".npy depth must be a 2-D (height, width) array, found shape {dims:?}"
            ))
        }
    };
    let side = max_side as usize;
    if h == 0 || w == 0 || h > side || w > side {
        return Err(format!(
            ".npy depth of {h}x{w} is empty or over {side} a side"
        ));
    }
    let n = h * w;
    let body = &bytes[start + header_len..];
    let values: Vec<f32> = match descr {
        "<f4" => {
            if body.len() != n * 4 {
                return Err(format!(
                    ".npy body has {} bytes, {n} f4 need {}",
                    body.len(),
                    n * 4
                ));
            }
            body.chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .map(|d| if d.is_finite() && d > 0.0 { d } else { 0.0 })
                .collect()
        }
        "<u2" => {
            if body.len() != n * 2 {
                return Err(format!(
                    ".npy body has {} bytes, {n} u2 need {}",
                    body.len(),
                    n * 2
                ));
            }
            body.chunks_exact(2)
                .map(|b| (u16::from_le_bytes([b[0], b[1]]) as f64 * scale) as f32)
                .collect()
        }
        other => {
            return Err(format!(
                ".npy dtype {other:?} is not supported: float32 metres ('<f4') or uint16 units \
                 ('<u2')"
            ))
        }
    };
    Ok((h as u32, w as u32, values))
}

/// Writes a (height, width) little-endian `f4` array (used by tests and converters).
pub fn depth_npy_bytes(width: u32, height: u32, metres: &[f32]) -> Vec<u8> {
    let mut header =
        format!("{{'descr': '<f4', 'fortran_order': False, 'shape': ({height}, {width}), }}");
    // Pad so the data starts on a 64-byte boundary, ending in a newline (as NumPy does).
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend((header.len() as u16).to_le_bytes());
    out.extend(header.as_bytes());
    for v in metres {
        out.extend(v.to_le_bytes());
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn float_depth_round_trips_and_bad_values_are_holes() {
        let v = [1.5f32, f32::NAN, 0.0, -1.0, f32::INFINITY, 2.25];
        let (h, w, got) = read_depth_npy(&depth_npy_bytes(3, 2, &v), 0.001, 16_384).unwrap();
        assert_eq!((h, w), (2, 3));
        assert_eq!(got, vec![1.5, 0.0, 0.0, 0.0, 0.0, 2.25]);
    }

    #[test]
    fn bad_arrays_are_refused_with_the_reason() {
        let good = depth_npy_bytes(3, 2, &[1.0; 6]);
        assert!(read_depth_npy(&good[..good.len() - 1], 0.001, 16_384)
            .unwrap_err()
            .contains("body has"));
        // Header edits of the same length keep the body where it was.
        let edit = |from: &[u8], to: &[u8]| {
            let at = good.windows(from.len()).position(|w| w == from).unwrap();
            let mut b = good.clone();
            b[at..at + to.len()].copy_from_slice(to);
            b
        };
        let f8 = edit(b"<f4", b"<f8");
        assert!(read_depth_npy(&f8, 0.001, 16_384)
            .unwrap_err()
            .contains("<f8"));
        let three = edit(b"(2, 3), ", b"(2, 3, 3)");
        assert!(read_depth_npy(&three, 0.001, 16_384)
            .unwrap_err()
            .contains("2-D"));
        assert!(read_depth_npy(b"PNG....nonsense", 0.001, 16_384).is_err());
        // Over the side limit: refused before the body is read.
        let e = read_depth_npy(&good, 0.001, 2).unwrap_err();
        assert!(e.contains("over 2 a side"), "{e}");
    }
}
