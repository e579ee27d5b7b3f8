//! Triangle meshes from OBJ, STL (ASCII or binary) and PLY, chosen by file extension.

use std::path::Path;

use deocc_geometry::PointCloud;
use nalgebra::Point3;

use crate::error::{IoError, IoErrorKind, Result};
use crate::ply::{read_ply, Mesh};

/// Reads a mesh by extension (.obj, .stl, .ply). Errors if it has no triangles.
pub fn read_mesh(path: &Path) -> Result<Mesh> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(|e| e.to_ascii_lowercase())
        .unwrap_or_default();
    let mesh = match ext.as_str() {
        "obj" => read_obj(path)?,
        "stl" => read_stl(path)?,
        "ply" => read_ply(path)?,
        other => {
            return Err(IoError::invalid(
                path,
                format!("unknown mesh format '.{other}' (use .obj, .stl or .ply)"),
            ))
        }
    };
    if mesh.triangles.is_empty() {
        return Err(IoError::invalid(path, "the mesh has no triangles"));
    }
    Ok(mesh)
}

fn parse_err(path: &Path, line: usize, msg: &str) -> IoError {
    IoError::new(path, IoErrorKind::Invalid(format!("line {line}: {msg}")))
}

/// Wavefront OBJ: `v` and `f` lines (faces fan-triangulated, negative indices resolved).
pub fn read_obj(path: &Path) -> Result<Mesh> {
    let text = std::fs::read_to_string(path).map_err(|e| IoError::new(path, e))?;
    let mut positions = Vec::new();
    let mut triangles = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let n = i + 1;
        let mut words = line.split_whitespace();
        match words.next() {
            Some("v") => {
                let xyz: Vec<f32> = words
                    .take(3)
                    .map(|w| w.parse().map_err(|_| parse_err(path, n, "bad vertex")))
                    .collect::<Result<_>>()?;
                if xyz.len() != 3 || xyz.iter().any(|v| !v.is_finite()) {
                    return Err(parse_err(
                        path,
                        n,
                        "a vertex needs three finite coordinates",
                    ));
                }
                positions.push(Point3::new(xyz[0], xyz[1], xyz[2]));
            }
            Some("f") => {
                let mut corners = Vec::new();
                for w in words {
                    let idx: i64 = w
                        .split('/')
                        .next()
                        .unwrap_or("")
                        .parse()
                        .map_err(|_| parse_err(path, n, "bad face index"))?;
                    let resolved = if idx < 0 {
                        positions.len() as i64 + idx
                    } else {
                        idx - 1
                    };
                    if resolved < 0 || resolved >= positions.len() as i64 {
                        return Err(parse_err(path, n, "face index out of range"));
                    }
                    corners.push(resolved as u32);
                }
                for k in 1..corners.len().saturating_sub(1) {
                    triangles.push([corners[0], corners[k], corners[k + 1]]);
                }
            }
            _ => {}
        }
    }
    Ok(Mesh {
        vertices: PointCloud::from_positions(positions),
        triangles,
        extras: Vec::new(),
    })
}

/// STL, binary or ASCII (vertices are not de-duplicated: every triangle has its own three).
pub fn read_stl(path: &Path) -> Result<Mesh> {
    let bytes = std::fs::read(path).map_err(|e| IoError::new(path, e))?;
    let mut positions = Vec::new();
    let binary_len = |n: usize| 84 + 50 * n;
    let is_binary = bytes.len() >= 84 && {
        let n = u32::from_le_bytes([bytes[80], bytes[81], bytes[82], bytes[83]]) as usize;
        binary_len(n) == bytes.len()
    };
    if is_binary {
        let n = u32::from_le_bytes([bytes[80], bytes[81], bytes[82], bytes[83]]) as usize;
        for t in 0..n {
            let base = 84 + 50 * t + 12;
            for v in 0..3 {
                let o = base + 12 * v;
                let f = |k: usize| {
                    f32::from_le_bytes([
                        bytes[o + 4 * k],
                        bytes[o + 4 * k + 1],
                        bytes[o + 4 * k + 2],
                        bytes[o + 4 * k + 3],
                    ])
                };
                positions.push(Point3::new(f(0), f(1), f(2)));
            }
        }
    } else {
        let text = std::str::from_utf8(&bytes).map_err(|_| {
            IoError::invalid(
                path,
                "neither binary STL (size does not match the triangle count) nor ASCII STL",
            )
        })?;
        for (i, line) in text.lines().enumerate() {
            let mut words = line.split_whitespace();
            if words.next() == Some("vertex") {
                let xyz: Vec<f32> = words
                    .take(3)
                    .map(|w| w.parse().map_err(|_| parse_err(path, i + 1, "bad vertex")))
                    .collect::<Result<_>>()?;
                if xyz.len() != 3 {
                    return Err(parse_err(path, i + 1, "a vertex needs three coordinates"));
                }
                positions.push(Point3::new(xyz[0], xyz[1], xyz[2]));
            }
        }
        if positions.len() % 3 != 0 {
            return Err(IoError::invalid(
                path,
                "ASCII STL vertex count is not a multiple of 3",
            ));
        }
    }
    if let Some(i) = positions
        .iter()
        .position(|p| !(p.x.is_finite() && p.y.is_finite() && p.z.is_finite()))
    {
        return Err(IoError::invalid(path, format!("vertex {i} is not finite")));
    }
    let triangles = (0..positions.len() as u32 / 3)
        .map(|t| [3 * t, 3 * t + 1, 3 * t + 2])
        .collect();
    Ok(Mesh {
        vertices: PointCloud::from_positions(positions),
        triangles,
        extras: Vec::new(),
    })
}
