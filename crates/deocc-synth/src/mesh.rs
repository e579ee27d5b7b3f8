//! Triangle meshes and the parametric shapes scenes are built from. Dimensions in metres, z up.

use nalgebra::{Isometry3, Point3, Vector3};

/// An indexed triangle mesh.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TriMesh {
    pub vertices: Vec<Point3<f32>>,
    pub triangles: Vec<[u32; 3]>,
}

impl TriMesh {
    /// Appends another mesh (its indices shifted).
    pub fn merge(&mut self, other: &TriMesh) {
        let base = self.vertices.len() as u32;
        self.vertices.extend_from_slice(&other.vertices);
        self.triangles
            .extend(other.triangles.iter().map(|t| t.map(|i| i + base)));
    }

    pub fn merged(parts: &[TriMesh]) -> TriMesh {
        let mut m = TriMesh::default();
        for p in parts {
            m.merge(p);
        }
        m
    }

    pub fn transformed(mut self, iso: &Isometry3<f32>) -> Self {
        for v in &mut self.vertices {
            *v = iso.transform_point(v);
        }
        self
    }

    pub fn translated(self, t: Vector3<f32>) -> Self {
        self.transformed(&Isometry3::translation(t.x, t.y, t.z))
    }

    /// Scales about the origin, per axis.
    pub fn scaled(mut self, s: Vector3<f32>) -> Self {
        for v in &mut self.vertices {
            v.coords.component_mul_assign(&s);
        }
        self
    }

    pub fn triangle(&self, i: usize) -> [Point3<f32>; 3] {
        self.triangles[i].map(|k| self.vertices[k as usize])
    }

    /// Total surface area, m^2.
    pub fn area(&self) -> f64 {
        (0..self.triangles.len())
            .map(|i| {
                let [a, b, c] = self.triangle(i);
                0.5 * (b - a).cross(&(c - a)).norm() as f64
            })
            .sum()
    }

    pub fn bounds(&self) -> Option<(Point3<f32>, Point3<f32>)> {
        let first = *self.vertices.first()?;
        Some(
            self.vertices
                .iter()
                .fold((first, first), |(lo, hi), p| (lo.inf(p), hi.sup(p))),
        )
    }
}

/// An axis-aligned box spanning `min..max`.
pub fn cuboid(min: Point3<f32>, max: Point3<f32>) -> TriMesh {
    let v = |x: bool, y: bool, z: bool| {
        Point3::new(
            if x { max.x } else { min.x },
            if y { max.y } else { min.y },
            if z { max.z } else { min.z },
        )
    };
    let vertices = vec![
        v(false, false, false),
        v(true, false, false),
        v(true, true, false),
        v(false, true, false),
        v(false, false, true),
        v(true, false, true),
        v(true, true, true),
        v(false, true, true),
    ];
    let quads = [
        [0, 3, 2, 1], // bottom
        [4, 5, 6, 7], // top
        [0, 1, 5, 4],
        [1, 2, 6, 5],
        [2, 3, 7, 6],
        [3, 0, 4, 7],
    ];
    let triangles = quads
        .iter()
        .flat_map(|q| [[q[0], q[1], q[2]], [q[0], q[2], q[3]]])
        .collect();
    TriMesh {
        vertices,
        triangles,
    }
}

/// A box of size `size` centred on (0, 0) with its bottom at z = z0.
pub fn box_on(size: Vector3<f32>, center_xy: (f32, f32), z0: f32) -> TriMesh {
    cuboid(
        Point3::new(center_xy.0 - size.x / 2.0, center_xy.1 - size.y / 2.0, z0),
        Point3::new(
            center_xy.0 + size.x / 2.0,
            center_xy.1 + size.y / 2.0,
            z0 + size.z,
        ),
    )
}

/// A surface of revolution about the z axis through a profile of (radius, z) points, with
/// `segments` around. Radius 0 at an end closes it with a single apex; `cap_bottom` / `cap_top`
/// close an end of non-zero radius with a flat disc.
pub fn lathe(profile: &[(f32, f32)], segments: usize, cap_bottom: bool, cap_top: bool) -> TriMesh {
    let mut m = TriMesh::default();
    let ring = |r: f32, z: f32| -> Vec<Point3<f32>> {
        (0..segments)
            .map(|s| {
                let a = s as f32 / segments as f32 * std::f32::consts::TAU;
                Point3::new(r * a.cos(), r * a.sin(), z)
            })
            .collect()
    };
    for &(r, z) in profile {
        m.vertices.extend(ring(r, z));
    }
    let n = segments as u32;
    for k in 0..profile.len() as u32 - 1 {
        for s in 0..n {
            let (a, b) = (k * n + s, k * n + (s + 1) % n);
            let (c, d) = (a + n, b + n);
            m.triangles.push([a, b, d]);
            m.triangles.push([a, d, c]);
        }
    }
    let mut cap = |k: u32, z: f32, up: bool| {
        let c = m.vertices.len() as u32;
        m.vertices.push(Point3::new(0.0, 0.0, z));
        for s in 0..n {
            let (a, b) = (k * n + s, k * n + (s + 1) % n);
            m.triangles.push(if up { [c, a, b] } else { [c, b, a] });
        }
    };
    if cap_bottom {
        cap(0, profile[0].1, false);
    }
    if cap_top {
        let last = profile.len() - 1;
        cap(last as u32, profile[last].1, true);
    }
    m
}

/// A closed cylinder of radius `r` from z0 to z0 + h.
pub fn cylinder(r: f32, h: f32, z0: f32, segments: usize) -> TriMesh {
    lathe(&[(r, z0), (r, z0 + h)], segments, true, true)
}

/// A torus-like ring (for mug handles): a circle of radius `major` in the xz plane, tube `minor`,
/// only the arc from `a0` to `a1` (radians).
pub fn tube_arc(
    major: f32,
    minor: f32,
    a0: f32,
    a1: f32,
    segments: usize,
    sides: usize,
) -> TriMesh {
    let mut m = TriMesh::default();
    for i in 0..=segments {
        let a = a0 + (a1 - a0) * i as f32 / segments as f32;
        let center = Vector3::new(major * a.cos(), 0.0, major * a.sin());
        let radial = center.normalize();
        for j in 0..sides {
            let b = j as f32 / sides as f32 * std::f32::consts::TAU;
            let off = radial * (minor * b.cos()) + Vector3::y() * (minor * b.sin());
            m.vertices.push(Point3::from(center + off));
        }
    }
    let s = sides as u32;
    for i in 0..segments as u32 {
        for j in 0..s {
            let (a, b) = (i * s + j, i * s + (j + 1) % s);
            m.triangles.push([a, b, b + s]);
            m.triangles.push([a, b + s, a + s]);
        }
    }
    m
}

/// A UV sphere.
pub fn sphere(r: f32, center: Point3<f32>, rings: usize, segments: usize) -> TriMesh {
    let profile: Vec<(f32, f32)> = (0..=rings)
        .map(|i| {
            let t = std::f32::consts::PI * i as f32 / rings as f32;
            (r * t.sin(), -r * t.cos())
        })
        .collect();
    lathe(&profile, segments, false, false).translated(center.coords)
}
