//! PLY point clouds and triangle meshes, ASCII and binary (little- and big-endian).
//!
//! A small reader/writer of our own: the `ply-rs` crate is unmaintained, and our needs are narrow
//! (one vertex element with scalar properties, optionally a face element with index lists), so a
//! focused implementation is shorter than adapting a general one and reads 1M binary points in tens
//! of milliseconds. Any unknown element or property is parsed and skipped, so files from Open3D,
//! MeshLab, CloudCompare or Blender load.
//!
//! Written clouds carry `x y z` (float), `nx ny nz` (float), `red green blue` (uchar), `instance`
//! (uint), `generated` (uchar) and `confidence` (float), each only when the cloud has that
//! attribute.

use std::io::{BufRead, BufReader, Read, Write};
use std::path::Path;

use deocc_geometry::PointCloud;
use nalgebra::{Point3, Vector3};

use crate::atomic::write_atomic;
use crate::error::{IoError, IoErrorKind, Result};

/// On-disk encoding of a PLY body.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PlyEncoding {
    Ascii,
    BinaryLittleEndian,
    BinaryBigEndian,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    fn parse(s: &str) -> Option<Self> {
        Some(match s {
            "char" | "int8" => Self::I8,
            "uchar" | "uint8" => Self::U8,
            "short" | "int16" => Self::I16,
            "ushort" | "uint16" => Self::U16,
            "int" | "int32" => Self::I32,
            "uint" | "uint32" => Self::U32,
            "float" | "float32" => Self::F32,
            "double" | "float64" => Self::F64,
            _ => return None,
        })
    }
    fn size(self) -> usize {
        match self {
            Self::I8 | Self::U8 => 1,
            Self::I16 | Self::U16 => 2,
            Self::I32 | Self::U32 | Self::F32 => 4,
            Self::F64 => 8,
        }
    }
    fn decode(self, b: &[u8], big_endian: bool) -> f64 {
        macro_rules! num {
            ($t:ty, $n:expr) => {{
                let a: [u8; $n] = b[..$n].try_into().unwrap_or([0; $n]);
                (if big_endian {
                    <$t>::from_be_bytes(a)
                } else {
                    <$t>::from_le_bytes(a)
                }) as f64
            }};
        }
        match self {
            Self::I8 => b[0] as i8 as f64,
            Self::U8 => b[0] as f64,
            Self::I16 => num!(i16, 2),
            Self::U16 => num!(u16, 2),
            Self::I32 => num!(i32, 4),
            Self::U32 => num!(u32, 4),
            Self::F32 => num!(f32, 4),
            Self::F64 => num!(f64, 8),
        }
    }
}

#[derive(Debug, Clone)]
enum PropertyKind {
    Scalar(Scalar),
    List { count: Scalar, item: Scalar },
}

#[derive(Debug, Clone)]
struct Property {
    name: String,
    kind: PropertyKind,
}

#[derive(Debug, Clone)]
struct Element {
    name: String,
    count: usize,
    properties: Vec<Property>,
}

#[derive(Debug)]
struct Header {
    encoding: PlyEncoding,
    elements: Vec<Element>,
}

fn header_err(path: &Path, msg: impl Into<String>) -> IoError {
    IoError::new(path, IoErrorKind::PlyHeader(msg.into()))
}
fn data_err(path: &Path, msg: impl Into<String>) -> IoError {
    IoError::new(path, IoErrorKind::PlyData(msg.into()))
}

/// Longest header line read (a PLY header line is a few words).
pub const MAX_HEADER_LINE_BYTES: u64 = 4096;
/// Longest ASCII body line read (a row of a few dozen numbers).
pub const MAX_BODY_LINE_BYTES: u64 = 1 << 16;
/// Most header lines read (comments included).
pub const MAX_HEADER_LINES: usize = 10_000;

fn read_header(path: &Path, r: &mut impl BufRead) -> Result<Header> {
    let mut line = String::new();
    // Each line is read through a cap: a file of zeros (or /dev/zero) has no newline, and an
    // uncapped `read_line` would hold all of it.
    let mut read_line = |line: &mut String, n: usize| -> Result<()> {
        line.clear();
        if n > MAX_HEADER_LINES {
            return Err(header_err(
                path,
                format!("no end_header in the first {MAX_HEADER_LINES} lines"),
            ));
        }
        let got = (&mut *r)
            .take(MAX_HEADER_LINE_BYTES + 1)
            .read_line(line)
            .map_err(|e| {
                if e.kind() == std::io::ErrorKind::InvalidData {
                    header_err(path, format!("line {n} is not text"))
                } else {
                    IoError::new(path, e)
                }
            })?;
        if got == 0 {
            return Err(header_err(
                path,
                format!("file ends in the header (line {n})"),
            ));
        }
        if got as u64 > MAX_HEADER_LINE_BYTES {
            return Err(header_err(
                path,
                format!("header line {n} is longer than {MAX_HEADER_LINE_BYTES} bytes: not a PLY header"),
            ));
        }
        Ok(())
    };
    read_line(&mut line, 1)?;
    if line.trim_end() != "ply" {
        return Err(header_err(path, "the file does not start with 'ply'"));
    }
    let mut encoding = None;
    let mut elements: Vec<Element> = Vec::new();
    for n in 2.. {
        read_line(&mut line, n)?;
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.as_slice() {
            [] | ["comment", ..] | ["obj_info", ..] => {}
            ["format", fmt, _version] => {
                encoding = Some(match *fmt {
                    "ascii" => PlyEncoding::Ascii,
                    "binary_little_endian" => PlyEncoding::BinaryLittleEndian,
                    "binary_big_endian" => PlyEncoding::BinaryBigEndian,
                    other => {
                        return Err(header_err(
                            path,
                            format!("line {n}: unknown format '{other}'"),
                        ))
                    }
                })
            }
            ["element", name, count] => {
                let count = count.parse().map_err(|_| {
                    header_err(path, format!("line {n}: bad element count '{count}'"))
                })?;
                elements.push(Element {
                    name: name.to_string(),
                    count,
                    properties: Vec::new(),
                });
            }
            ["property", "list", count, item, name] => {
                let (Some(count), Some(item)) = (Scalar::parse(count), Scalar::parse(item)) else {
                    return Err(header_err(path, format!("line {n}: unknown list types")));
                };
                let el = elements.last_mut().ok_or_else(|| {
                    header_err(path, format!("line {n}: property before any element"))
                })?;
                el.properties.push(Property {
                    name: name.to_string(),
                    kind: PropertyKind::List { count, item },
                });
            }
            ["property", ty, name] => {
                let ty = Scalar::parse(ty)
                    .ok_or_else(|| header_err(path, format!("line {n}: unknown type '{ty}'")))?;
                let el = elements.last_mut().ok_or_else(|| {
                    header_err(path, format!("line {n}: property before any element"))
                })?;
                el.properties.push(Property {
                    name: name.to_string(),
                    kind: PropertyKind::Scalar(ty),
                });
            }
            ["end_header"] => break,
            _ => {
                return Err(header_err(
                    path,
                    format!("line {n}: cannot parse '{}'", line.trim_end()),
                ))
            }
        }
    }
    let encoding = encoding.ok_or_else(|| header_err(path, "no 'format' line"))?;
    Ok(Header { encoding, elements })
}

/// A triangle mesh (faces with more than three corners are fan-triangulated on load).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Mesh {
    pub vertices: PointCloud,
    pub triangles: Vec<[u32; 3]>,
    /// Vertex properties we do not interpret (e.g. the benchmark's `seen` flag), by name.
    pub extras: Vec<(String, Vec<f64>)>,
}

impl Mesh {
    /// An uninterpreted vertex property by name.
    pub fn extra(&self, name: &str) -> Option<&[f64]> {
        self.extras
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, v)| v.as_slice())
    }
}

/// Row source over either encoding.
enum Body<R: BufRead> {
    Ascii {
        reader: R,
        line: String,
        tokens: Vec<f64>,
        pos: usize,
        line_no: usize,
    },
    Binary {
        reader: R,
        big_endian: bool,
        buf: Vec<u8>,
    },
}

impl<R: BufRead> Body<R> {
    fn next_value(&mut self, path: &Path, ty: Scalar, what: &str) -> Result<f64> {
        match self {
            Body::Ascii {
                reader,
                line,
                tokens,
                pos,
                line_no,
            } => {
                while *pos >= tokens.len() {
                    line.clear();
                    *line_no += 1;
                    let got = (&mut *reader)
                        .take(MAX_BODY_LINE_BYTES + 1)
                        .read_line(line)
                        .map_err(|e| IoError::new(path, e))?;
                    if got == 0 {
                        return Err(data_err(
                            path,
                            format!("file ends early while reading {what}"),
                        ));
                    }
                    if got as u64 > MAX_BODY_LINE_BYTES {
                        return Err(data_err(
                            path,
                            format!(
                                "body line {line_no} is longer than {MAX_BODY_LINE_BYTES} bytes"
                            ),
                        ));
                    }
                    tokens.clear();
                    for t in line.split_whitespace() {
                        tokens.push(t.parse().map_err(|_| {
                            data_err(path, format!("body line {line_no}: '{t}' is not a number"))
                        })?);
                    }
                    *pos = 0;
                }
                *pos += 1;
                Ok(tokens[*pos - 1])
            }
            Body::Binary {
                reader,
                big_endian,
                buf,
            } => {
                let n = ty.size();
                buf.resize(n, 0);
                reader.read_exact(&mut buf[..n]).map_err(|e| {
                    if e.kind() == std::io::ErrorKind::UnexpectedEof {
                        data_err(path, format!("file is truncated while reading {what}"))
                    } else {
                        IoError::new(path, e)
                    }
                })?;
                Ok(ty.decode(buf, *big_endian))
            }
        }
    }
}

/// Reads a PLY file as a mesh: vertices with every attribute we know, and triangles if there is a
/// face element (a point cloud has none).
pub fn read_ply(path: &Path) -> Result<Mesh> {
    let file = std::fs::File::open(path).map_err(|e| IoError::new(path, e))?;
    let size = file.metadata().map_err(|e| IoError::new(path, e))?.len();
    read_ply_sized(path, BufReader::with_capacity(1 << 20, file), Some(size))
}

/// Reads PLY from any buffered reader; `path` only names the source in errors.
pub fn read_ply_from(path: &Path, reader: impl BufRead) -> Result<Mesh> {
    read_ply_sized(path, reader, None)
}

/// Fewest bytes one row of an element can take: binary rows hold every scalar and every list's
/// count, ASCII rows a digit and a separator per property.
fn min_row_bytes(el: &Element, encoding: PlyEncoding) -> u64 {
    el.properties
        .iter()
        .map(|p| match (encoding, &p.kind) {
            (PlyEncoding::Ascii, _) => 2,
            (_, PropertyKind::Scalar(t)) => t.size() as u64,
            (_, PropertyKind::List { count, .. }) => count.size() as u64,
        })
        .sum::<u64>()
        .max(1)
}

/// Rows allocated up front: never more than the file can hold (or 1M without a size), so a
/// header that lies costs nothing before the data runs out.
fn capacity(count: usize, max_rows: Option<u64>) -> usize {
    count.min(max_rows.unwrap_or(1 << 20).min(usize::MAX as u64) as usize)
}

fn read_ply_sized(path: &Path, mut reader: impl BufRead, size: Option<u64>) -> Result<Mesh> {
    let header = read_header(path, &mut reader)?;
    if let Some(size) = size {
        // What the header declares must fit in the file, before anything is allocated.
        let needed = header.elements.iter().fold(0u64, |acc, el| {
            acc.saturating_add((el.count as u64).saturating_mul(min_row_bytes(el, header.encoding)))
        });
        if needed > size {
            let el = header
                .elements
                .iter()
                .max_by_key(|el| el.count)
                .map(|el| format!("{} {}", el.count, el.name))
                .unwrap_or_default();
            return Err(header_err(
                path,
                format!(
                    "the header declares {el} rows (at least {needed} bytes), but the file has {size} bytes"
                ),
            ));
        }
    }
    let max_rows = |el: &Element| size.map(|s| s / min_row_bytes(el, header.encoding));
    let mut body = match header.encoding {
        PlyEncoding::Ascii => Body::Ascii {
            reader,
            line: String::new(),
            tokens: Vec::new(),
            pos: 0,
            line_no: 0,
        },
        e => Body::Binary {
            reader,
            big_endian: e == PlyEncoding::BinaryBigEndian,
            buf: Vec::new(),
        },
    };
    let mut mesh = Mesh::default();
    let mut saw_vertex = false;
    for el in &header.elements {
        if el.name == "vertex" {
            saw_vertex = true;
            (mesh.vertices, mesh.extras) =
                read_vertices(path, el, &mut body, capacity(el.count, max_rows(el)))?;
        } else if el.name == "face" {
            mesh.triangles = read_faces(path, el, &mut body, capacity(el.count, max_rows(el)))?;
        } else {
            for row in 0..el.count {
                for p in &el.properties {
                    skip_property(
                        path,
                        p,
                        &mut body,
                        &format!("element '{}' row {row}", el.name),
                    )?;
                }
            }
        }
    }
    if !saw_vertex {
        return Err(header_err(path, "no 'vertex' element"));
    }
    let n = mesh.vertices.len() as u32;
    if let Some((i, t)) = mesh
        .triangles
        .iter()
        .enumerate()
        .find(|(_, t)| t.iter().any(|&v| v >= n))
    {
        return Err(data_err(
            path,
            format!("face {i} refers to vertex {:?}, but there are only {n}", t),
        ));
    }
    mesh.vertices
        .validate()
        .map_err(|e| IoError::new(path, e))?;
    Ok(mesh)
}

/// Reads a PLY file as a point cloud (faces, if any, are ignored). Errors on an empty cloud.
pub fn read_point_cloud(path: &Path) -> Result<PointCloud> {
    let cloud = read_ply(path)?.vertices;
    if cloud.is_empty() {
        return Err(data_err(path, "the cloud has no points"));
    }
    Ok(cloud)
}

fn skip_property<R: BufRead>(
    path: &Path,
    p: &Property,
    body: &mut Body<R>,
    what: &str,
) -> Result<()> {
    match p.kind {
        PropertyKind::Scalar(t) => {
            body.next_value(path, t, what)?;
        }
        PropertyKind::List { count, item } => {
            let n = body.next_value(path, count, what)?;
            for _ in 0..(n.max(0.0) as usize) {
                body.next_value(path, item, what)?;
            }
        }
    }
    Ok(())
}

const KNOWN_VERTEX_PROPERTIES: [&str; 20] = [
    "x",
    "y",
    "z",
    "nx",
    "ny",
    "nz",
    "red",
    "green",
    "blue",
    "r",
    "g",
    "b",
    "diffuse_red",
    "diffuse_green",
    "diffuse_blue",
    "instance",
    "instance_id",
    "generated",
    "confidence",
    "expected_error",
];

type VertexData = (PointCloud, Vec<(String, Vec<f64>)>);

fn read_vertices<R: BufRead>(
    path: &Path,
    el: &Element,
    body: &mut Body<R>,
    cap: usize,
) -> Result<VertexData> {
    // Column of each known attribute, looked up once.
    let find = |names: &[&str]| {
        el.properties
            .iter()
            .position(|p| names.contains(&p.name.as_str()))
    };
    let (Some(ix), Some(iy), Some(iz)) = (find(&["x"]), find(&["y"]), find(&["z"])) else {
        return Err(header_err(path, "the vertex element lacks x, y or z"));
    };
    let color = match (
        find(&["red", "r", "diffuse_red"]),
        find(&["green", "g", "diffuse_green"]),
        find(&["blue", "b", "diffuse_blue"]),
    ) {
        (Some(r), Some(g), Some(b)) => Some([r, g, b]),
        _ => None,
    };
    let normal = match (find(&["nx"]), find(&["ny"]), find(&["nz"])) {
        (Some(a), Some(b), Some(c)) => Some([a, b, c]),
        _ => None,
    };
    let instance = find(&["instance", "instance_id", "label"]);
    let generated = find(&["generated"]);
    let confidence = find(&["confidence"]);
    let expected_error = find(&["expected_error"]);
    // Colours stored as float (0..1) are scaled to bytes.
    let color_is_float = color.is_some_and(|c| {
        matches!(
            el.properties[c[0]].kind,
            PropertyKind::Scalar(Scalar::F32 | Scalar::F64)
        )
    });

    let n = el.count;
    let mut cloud = PointCloud {
        positions: Vec::with_capacity(cap),
        colors: color.map(|_| Vec::with_capacity(cap)),
        normals: normal.map(|_| Vec::with_capacity(cap)),
        instance: instance.map(|_| Vec::with_capacity(cap)),
        generated: generated.map(|_| Vec::with_capacity(cap)),
        confidence: confidence.map(|_| Vec::with_capacity(cap)),
        expected_error: expected_error.map(|_| Vec::with_capacity(cap)),
    };
    let extra_columns: Vec<usize> = (0..el.properties.len())
        .filter(|&j| {
            matches!(el.properties[j].kind, PropertyKind::Scalar(_))
                && !KNOWN_VERTEX_PROPERTIES.contains(&el.properties[j].name.as_str())
                && !(el.properties[j].name == "label" && instance == Some(j))
        })
        .collect();
    let mut extras: Vec<(String, Vec<f64>)> = extra_columns
        .iter()
        .map(|&j| (el.properties[j].name.clone(), Vec::with_capacity(cap)))
        .collect();
    let mut row = vec![0.0f64; el.properties.len()];
    for r in 0..n {
        for (j, p) in el.properties.iter().enumerate() {
            match p.kind {
                PropertyKind::Scalar(t) => {
                    row[j] = body.next_value(path, t, &format!("vertex {r}"))?
                }
                PropertyKind::List { .. } => skip_property(path, p, body, &format!("vertex {r}"))?,
            }
        }
        let p = Point3::new(row[ix] as f32, row[iy] as f32, row[iz] as f32);
        if !(p.x.is_finite() && p.y.is_finite() && p.z.is_finite()) {
            return Err(data_err(
                path,
                format!(
                    "vertex {r} has a non-finite coordinate ({}, {}, {})",
                    p.x, p.y, p.z
                ),
            ));
        }
        cloud.positions.push(p);
        if let (Some(c), Some(out)) = (color, cloud.colors.as_mut()) {
            let scale = if color_is_float { 255.0 } else { 1.0 };
            out.push(c.map(|k| (row[k] * scale).round().clamp(0.0, 255.0) as u8));
        }
        if let (Some(c), Some(out)) = (normal, cloud.normals.as_mut()) {
            out.push(Vector3::new(
                row[c[0]] as f32,
                row[c[1]] as f32,
                row[c[2]] as f32,
            ));
        }
        if let (Some(k), Some(out)) = (instance, cloud.instance.as_mut()) {
            out.push(row[k].max(0.0) as u32);
        }
        if let (Some(k), Some(out)) = (generated, cloud.generated.as_mut()) {
            out.push(row[k].clamp(0.0, 255.0) as u8);
        }
        if let (Some(k), Some(out)) = (confidence, cloud.confidence.as_mut()) {
            let c = row[k] as f32;
            if !(0.0..=1.0).contains(&c) {
                return Err(data_err(
                    path,
                    format!("vertex {r} has confidence {c}, outside [0, 1]"),
                ));
            }
            out.push(c);
        }
        if let (Some(k), Some(out)) = (expected_error, cloud.expected_error.as_mut()) {
            let e = row[k] as f32;
            if !(e.is_finite() && e >= 0.0) {
                return Err(data_err(
                    path,
                    format!("vertex {r} has expected_error {e}: it must be finite and >= 0"),
                ));
            }
            out.push(e);
        }
        for (e, &j) in extras.iter_mut().zip(&extra_columns) {
            e.1.push(row[j]);
        }
    }
    Ok((cloud, extras))
}

fn read_faces<R: BufRead>(
    path: &Path,
    el: &Element,
    body: &mut Body<R>,
    cap: usize,
) -> Result<Vec<[u32; 3]>> {
    let idx = el.properties.iter().position(|p| {
        matches!(p.kind, PropertyKind::List { .. })
            && (p.name == "vertex_indices" || p.name == "vertex_index")
    });
    let Some(idx) = idx else {
        return Err(header_err(
            path,
            "the face element has no vertex_indices list",
        ));
    };
    let mut tris = Vec::with_capacity(cap);
    let mut corners = Vec::new();
    for r in 0..el.count {
        for (j, p) in el.properties.iter().enumerate() {
            let what = format!("face {r}");
            if j != idx {
                skip_property(path, p, body, &what)?;
                continue;
            }
            let PropertyKind::List { count, item } = p.kind else {
                unreachable!()
            };
            let k = body.next_value(path, count, &what)?;
            if !(0.0..=1e6).contains(&k) {
                return Err(data_err(path, format!("face {r} has {k} corners")));
            }
            corners.clear();
            for _ in 0..k as usize {
                let v = body.next_value(path, item, &what)?;
                if v < 0.0 {
                    return Err(data_err(
                        path,
                        format!("face {r} has a negative vertex index"),
                    ));
                }
                corners.push(v as u32);
            }
            for i in 1..corners.len().saturating_sub(1) {
                tris.push([corners[0], corners[i], corners[i + 1]]);
            }
        }
    }
    Ok(tris)
}

/// Writes a point cloud as PLY, atomically (a temporary file renamed into place).
pub fn write_point_cloud(path: &Path, cloud: &PointCloud, encoding: PlyEncoding) -> Result<()> {
    write_mesh(path, cloud, &[], encoding)
}

/// A per-vertex u8 property beyond the ones [`PointCloud`] knows (e.g. `seen`).
pub type ExtraU8<'a> = (&'a str, &'a [u8]);

/// Writes a point cloud with extra u8 vertex properties, atomically.
pub fn write_point_cloud_with_extras(
    path: &Path,
    cloud: &PointCloud,
    extras: &[ExtraU8],
    encoding: PlyEncoding,
) -> Result<()> {
    write_ply_impl(path, cloud, &[], extras, encoding)
}

/// Writes vertices (with their attributes) and triangles as PLY, atomically.
pub fn write_mesh(
    path: &Path,
    vertices: &PointCloud,
    triangles: &[[u32; 3]],
    encoding: PlyEncoding,
) -> Result<()> {
    write_ply_impl(path, vertices, triangles, &[], encoding)
}

fn write_ply_impl(
    path: &Path,
    vertices: &PointCloud,
    triangles: &[[u32; 3]],
    extras: &[ExtraU8],
    encoding: PlyEncoding,
) -> Result<()> {
    vertices.validate().map_err(|e| IoError::new(path, e))?;
    if let Some((name, v)) = extras.iter().find(|(_, v)| v.len() != vertices.len()) {
        return Err(IoError::invalid(
            path,
            format!(
                "extra property '{name}' has {} values for {} points",
                v.len(),
                vertices.len()
            ),
        ));
    }
    write_atomic(path, |w| {
        let fmt = match encoding {
            PlyEncoding::Ascii => "ascii",
            PlyEncoding::BinaryLittleEndian => "binary_little_endian",
            PlyEncoding::BinaryBigEndian => "binary_big_endian",
        };
        writeln!(w, "ply\nformat {fmt} 1.0\ncomment written by deocc")?;
        writeln!(w, "element vertex {}", vertices.len())?;
        writeln!(w, "property float x\nproperty float y\nproperty float z")?;
        if vertices.normals.is_some() {
            writeln!(w, "property float nx\nproperty float ny\nproperty float nz")?;
        }
        if vertices.colors.is_some() {
            writeln!(
                w,
                "property uchar red\nproperty uchar green\nproperty uchar blue"
            )?;
        }
        if vertices.instance.is_some() {
            writeln!(w, "property uint instance")?;
        }
        if vertices.generated.is_some() {
            writeln!(w, "property uchar generated")?;
        }
        if vertices.confidence.is_some() {
            writeln!(w, "property float confidence")?;
        }
        if vertices.expected_error.is_some() {
            writeln!(w, "property float expected_error")?;
        }
        for (name, _) in extras {
            writeln!(w, "property uchar {name}")?;
        }
        if !triangles.is_empty() {
            writeln!(
                w,
                "element face {}\nproperty list uchar uint vertex_indices",
                triangles.len()
            )?;
        }
        writeln!(w, "end_header")?;
        match encoding {
            PlyEncoding::Ascii => write_ascii_body(w, vertices, triangles, extras),
            e => write_binary_body(
                w,
                vertices,
                triangles,
                extras,
                e == PlyEncoding::BinaryBigEndian,
            ),
        }
    })
}

fn write_ascii_body(
    w: &mut impl Write,
    c: &PointCloud,
    tris: &[[u32; 3]],
    extras: &[ExtraU8],
) -> std::io::Result<()> {
    for i in 0..c.len() {
        let p = c.positions[i];
        // `{}` on f32 prints the shortest string that parses back to the same value: bit-exact.
        write!(w, "{} {} {}", p.x, p.y, p.z)?;
        if let Some(n) = &c.normals {
            write!(w, " {} {} {}", n[i].x, n[i].y, n[i].z)?;
        }
        if let Some(col) = &c.colors {
            write!(w, " {} {} {}", col[i][0], col[i][1], col[i][2])?;
        }
        if let Some(ids) = &c.instance {
            write!(w, " {}", ids[i])?;
        }
        if let Some(g) = &c.generated {
            write!(w, " {}", g[i])?;
        }
        if let Some(k) = &c.confidence {
            write!(w, " {}", k[i])?;
        }
        if let Some(e) = &c.expected_error {
            write!(w, " {}", e[i])?;
        }
        for (_, v) in extras {
            write!(w, " {}", v[i])?;
        }
        writeln!(w)?;
    }
    for t in tris {
        writeln!(w, "3 {} {} {}", t[0], t[1], t[2])?;
    }
    Ok(())
}

fn write_binary_body(
    w: &mut impl Write,
    c: &PointCloud,
    tris: &[[u32; 3]],
    extras: &[ExtraU8],
    big_endian: bool,
) -> std::io::Result<()> {
    let f = |v: f32| {
        if big_endian {
            v.to_be_bytes()
        } else {
            v.to_le_bytes()
        }
    };
    let u = |v: u32| {
        if big_endian {
            v.to_be_bytes()
        } else {
            v.to_le_bytes()
        }
    };
    let mut row = Vec::with_capacity(64);
    for i in 0..c.len() {
        row.clear();
        let p = c.positions[i];
        for v in [p.x, p.y, p.z] {
            row.extend_from_slice(&f(v));
        }
        if let Some(n) = &c.normals {
            for v in [n[i].x, n[i].y, n[i].z] {
                row.extend_from_slice(&f(v));
            }
        }
        if let Some(col) = &c.colors {
            row.extend_from_slice(&col[i]);
        }
        if let Some(ids) = &c.instance {
            row.extend_from_slice(&u(ids[i]));
        }
        if let Some(g) = &c.generated {
            row.push(g[i]);
        }
        if let Some(k) = &c.confidence {
            row.extend_from_slice(&f(k[i]));
        }
        if let Some(e) = &c.expected_error {
            row.extend_from_slice(&f(e[i]));
        }
        for (_, v) in extras {
            row.push(v[i]);
        }
        w.write_all(&row)?;
    }
    for t in tris {
        row.clear();
        row.push(3);
        for &v in t {
            row.extend_from_slice(&u(v));
        }
        w.write_all(&row)?;
    }
    Ok(())
}
