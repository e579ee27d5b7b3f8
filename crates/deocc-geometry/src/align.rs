//! Alignment as the field's evaluation protocol does it: Umeyama similarity on corresponding points,
//! then rigid ICP (point-to-point or point-to-plane) with Open3D's convergence rule.

use nalgebra::{
    Isometry3, Matrix3, Matrix6, Point3, Rotation3, Translation3, UnitQuaternion, Vector3, Vector6,
};
use rayon::prelude::*;

use crate::cell_grid::CellGrid;
use crate::error::{GeometryError, Result};

/// A similarity transform `dst = scale * rotation * src + translation`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Similarity {
    pub rotation: Rotation3<f64>,
    pub translation: Vector3<f64>,
    pub scale: f64,
}

impl Similarity {
    pub fn transform_point(&self, p: &Point3<f64>) -> Point3<f64> {
        Point3::from(self.scale * (self.rotation * p.coords) + self.translation)
    }

    pub fn transform_point_f32(&self, p: &Point3<f32>) -> Point3<f32> {
        self.transform_point(&p.cast::<f64>()).cast::<f32>()
    }
}

/// Umeyama's least-squares similarity (or rigid transform, when `with_scale` is false) mapping
/// `src[i]` onto `dst[i]`, with the reflection fix (det(R) = +1 always).
///
/// Reference: S. Umeyama, "Least-squares estimation of transformation parameters between two point
/// patterns", PAMI 1991.
pub fn umeyama(src: &[Point3<f64>], dst: &[Point3<f64>], with_scale: bool) -> Result<Similarity> {
    if src.len() != dst.len() {
        return Err(GeometryError::SizeMismatch {
            what: "Umeyama correspondences",
            expected: src.len(),
            got: dst.len(),
        });
    }
    if src.len() < 3 {
        return Err(GeometryError::Degenerate(format!(
            "Umeyama needs at least 3 correspondences, got {}",
            src.len()
        )));
    }
    let n = src.len() as f64;
    let mu_s = src.iter().fold(Vector3::zeros(), |a, p| a + p.coords) / n;
    let mu_d = dst.iter().fold(Vector3::zeros(), |a, p| a + p.coords) / n;
    let mut cov = Matrix3::<f64>::zeros();
    let mut var_s = 0.0;
    for (s, d) in src.iter().zip(dst) {
        let (cs, cd) = (s.coords - mu_s, d.coords - mu_d);
        cov += cd * cs.transpose();
        var_s += cs.norm_squared();
    }
    cov /= n;
    var_s /= n;
    similarity_from_moments(&cov, var_s, &mu_s, &mu_d, with_scale)
}

/// Closed-form solution from the cross-covariance `cov = E[(d - mu_d)(s - mu_s)^T]`.
fn similarity_from_moments(
    cov: &Matrix3<f64>,
    var_s: f64,
    mu_s: &Vector3<f64>,
    mu_d: &Vector3<f64>,
    with_scale: bool,
) -> Result<Similarity> {
    if var_s <= f64::EPSILON {
        return Err(GeometryError::Degenerate(
            "source points are all the same point".into(),
        ));
    }
    let svd = cov.svd(true, true);
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return Err(GeometryError::Degenerate("SVD did not converge".into()));
    };
    let mut s = Matrix3::identity();
    if (u.determinant() * v_t.determinant()) < 0.0 {
        s[(2, 2)] = -1.0;
    }
    let r = u * s * v_t;
    let scale = if with_scale {
        (svd.singular_values[0] * s[(0, 0)]
            + svd.singular_values[1] * s[(1, 1)]
            + svd.singular_values[2] * s[(2, 2)])
            / var_s
    } else {
        1.0
    };
    let rotation = Rotation3::from_matrix_unchecked(r);
    let translation = mu_d - scale * (rotation * mu_s);
    Ok(Similarity {
        rotation,
        translation,
        scale,
    })
}

/// Which error ICP minimises.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum IcpMethod {
    PointToPoint,
    /// Needs target normals.
    PointToPlane,
}

/// ICP settings; the defaults are the evaluation protocol's (0.1 m, 30 iterations) with Open3D's
/// convergence thresholds.
#[derive(Debug, Clone, Copy)]
pub struct IcpOptions {
    pub method: IcpMethod,
    pub max_correspondence_m: f32,
    pub max_iterations: usize,
    /// Stop when fitness changes by less than this between iterations (and RMSE too).
    pub relative_fitness: f64,
    pub relative_rmse: f64,
}

impl Default for IcpOptions {
    fn default() -> Self {
        Self {
            method: IcpMethod::PointToPoint,
            max_correspondence_m: 0.1,
            max_iterations: 30,
            relative_fitness: 1e-6,
            relative_rmse: 1e-6,
        }
    }
}

/// What ICP found.
#[derive(Debug, Clone, Copy)]
pub struct IcpResult {
    pub target_from_source: Isometry3<f64>,
    /// Fraction of source points with a correspondence within the maximum distance.
    pub fitness: f64,
    /// RMSE of the inlier correspondences, metres.
    pub inlier_rmse: f64,
    /// Number of transformation updates computed.
    pub iterations: usize,
}

/// Sums over correspondences, reduced in parallel.
#[derive(Clone, Copy)]
struct Moments {
    count: usize,
    sq_err: f64,
    sum_s: Vector3<f64>,
    sum_t: Vector3<f64>,
    sum_ts: Matrix3<f64>,
    ata: Matrix6<f64>,
    atb: Vector6<f64>,
}

impl Moments {
    fn zero() -> Self {
        Self {
            count: 0,
            sq_err: 0.0,
            sum_s: Vector3::zeros(),
            sum_t: Vector3::zeros(),
            sum_ts: Matrix3::zeros(),
            ata: Matrix6::zeros(),
            atb: Vector6::zeros(),
        }
    }
    fn add(mut self, o: Self) -> Self {
        self.count += o.count;
        self.sq_err += o.sq_err;
        self.sum_s += o.sum_s;
        self.sum_t += o.sum_t;
        self.sum_ts += o.sum_ts;
        self.ata += o.ata;
        self.atb += o.atb;
        self
    }
}

/// A nearest-neighbour index over an ICP target (a [`CellGrid`]: each iteration asks for every
/// source point's correspondence at once), with its normals for point-to-plane; build once,
/// register many.
pub struct IcpTarget<'a> {
    pub points: &'a [Point3<f32>],
    pub normals: Option<&'a [Vector3<f32>]>,
    pub index: CellGrid,
}

impl<'a> IcpTarget<'a> {
    pub fn new(points: &'a [Point3<f32>], normals: Option<&'a [Vector3<f32>]>) -> Result<Self> {
        if let Some(n) = normals {
            if n.len() != points.len() {
                return Err(GeometryError::SizeMismatch {
                    what: "ICP target normals",
                    expected: points.len(),
                    got: n.len(),
                });
            }
        }
        Ok(Self {
            points,
            normals,
            index: CellGrid::build(points)?,
        })
    }
}

/// Rigid ICP of `source` onto `target`, starting from `initial` (target_from_source).
pub fn icp(
    source: &[Point3<f32>],
    target: &IcpTarget,
    initial: &Isometry3<f64>,
    options: &IcpOptions,
) -> Result<IcpResult> {
    if source.is_empty() {
        return Err(GeometryError::Empty { what: "ICP source" });
    }
    if options.method == IcpMethod::PointToPlane && target.normals.is_none() {
        return Err(GeometryError::InvalidArgument(
            "point-to-plane ICP needs target normals".into(),
        ));
    }
    // Correspondences are searched in Morton order (neighbouring queries share tree nodes in
    // cache); the moments are sums over all points, so only their rounding depends on it.
    let source: Vec<Point3<f32>> = crate::knn::morton_order(source)
        .into_iter()
        .map(|i| source[i as usize])
        .collect();
    let source = source.as_slice();
    let mut transform = *initial;
    let mut moved: Vec<Point3<f32>> = source
        .par_iter()
        .map(|p| transform.transform_point(&p.cast::<f64>()).cast::<f32>())
        .collect();

    let gather = |moved: &[Point3<f32>]| -> Moments {
        let found = target
            .index
            .nearest_batch_within(moved, options.max_correspondence_m);
        moved
            .par_chunks(4096)
            .zip(found.par_chunks(4096))
            .map(|(chunk, found)| {
                let mut m = Moments::zero();
                for (p, nb) in chunk.iter().zip(found) {
                    let Some(nb) = nb else {
                        continue;
                    };
                    let d2 = nb.distance_sq as f64;
                    let s = p.coords.cast::<f64>();
                    let t = target.points[nb.index as usize].coords.cast::<f64>();
                    m.count += 1;
                    m.sq_err += d2;
                    match options.method {
                        IcpMethod::PointToPoint => {
                            m.sum_s += s;
                            m.sum_t += t;
                            m.sum_ts += t * s.transpose();
                        }
                        IcpMethod::PointToPlane => {
                            // Linearised about the current pose: r = n.(s + w x s + v - t).
                            let n = target
                                .normals
                                .map(|n| n[nb.index as usize])
                                .unwrap_or_default();
                            let n = n.cast::<f64>();
                            let c = s.cross(&n);
                            let a = Vector6::new(c.x, c.y, c.z, n.x, n.y, n.z);
                            let b = n.dot(&(t - s));
                            m.ata += a * a.transpose();
                            m.atb += a * b;
                        }
                    }
                }
                m
            })
            .reduce(Moments::zero, Moments::add)
    };
    let score = |m: &Moments| -> (f64, f64) {
        if m.count == 0 {
            (0.0, 0.0)
        } else {
            (
                m.count as f64 / source.len() as f64,
                (m.sq_err / m.count as f64).sqrt(),
            )
        }
    };

    let mut moments = gather(&moved);
    let (mut fitness, mut rmse) = score(&moments);
    let mut iterations = 0;
    for _ in 0..options.max_iterations {
        if moments.count < 3 {
            break;
        }
        let update = match options.method {
            IcpMethod::PointToPoint => {
                let n = moments.count as f64;
                let mu_s = moments.sum_s / n;
                let mu_t = moments.sum_t / n;
                let cov = moments.sum_ts / n - mu_t * mu_s.transpose();
                let sim = similarity_from_moments(&cov, 1.0, &mu_s, &mu_t, false)?;
                Isometry3::from_parts(
                    Translation3::from(sim.translation),
                    UnitQuaternion::from_rotation_matrix(&sim.rotation),
                )
            }
            IcpMethod::PointToPlane => {
                let Some(x) = moments.ata.cholesky().map(|c| c.solve(&moments.atb)) else {
                    break;
                };
                let rotation = Rotation3::from_euler_angles(x[0], x[1], x[2]);
                Isometry3::from_parts(
                    Translation3::new(x[3], x[4], x[5]),
                    UnitQuaternion::from_rotation_matrix(&rotation),
                )
            }
        };
        transform = update * transform;
        iterations += 1;
        moved
            .par_iter_mut()
            .zip(source.par_iter())
            .for_each(|(m, p)| *m = transform.transform_point(&p.cast::<f64>()).cast::<f32>());
        moments = gather(&moved);
        let (new_fitness, new_rmse) = score(&moments);
        let converged = (new_fitness - fitness).abs() < options.relative_fitness
            && (new_rmse - rmse).abs() < options.relative_rmse;
        fitness = new_fitness;
        rmse = new_rmse;
        if converged {
            break;
        }
    }
    Ok(IcpResult {
        target_from_source: transform,
        fitness,
        inlier_rmse: rmse,
        iterations,
    })
}
