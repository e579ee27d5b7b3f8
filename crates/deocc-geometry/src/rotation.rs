//! Rotations from matrices that are rotations up to rounding.
//!
//! nalgebra's `Rotation3::from_matrix` / `UnitQuaternion::from_matrix` run an iterative solver
//! started from the identity; for a half-turn (a rotation by exactly pi, such as a camera looking
//! straight back, `diag(-1, 1, -1)`) the solver's first step has no direction to move in and it
//! returns the identity: the rotation is silently lost. [`nearest_rotation`] projects onto the
//! rotations in closed form (SVD), which has no such fixed point; use it wherever a 3x3 read from
//! a user, a file or a message becomes a rotation.

use nalgebra::{Matrix3, RealField, Rotation3, UnitQuaternion};

/// The proper rotation nearest to `m` in the Frobenius norm (`U diag(1, 1, det(U V^T)) V^T` of its
/// SVD). For an exact rotation it returns `m` itself, half-turns included.
pub fn nearest_rotation<T: RealField + Copy>(m: &Matrix3<T>) -> Rotation3<T> {
    let svd = m.svd(true, true);
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        // Both were asked for; nalgebra always computes them when asked.
        return Rotation3::identity();
    };
    let mut r = u * v_t;
    if r.determinant() < T::zero() {
        let mut u = u;
        let mut c = u.column_mut(2);
        c.neg_mut();
        r = u * v_t;
    }
    Rotation3::from_matrix_unchecked(r)
}

/// [`nearest_rotation`] as a unit quaternion.
pub fn nearest_unit_quaternion<T: RealField + Copy>(m: &Matrix3<T>) -> UnitQuaternion<T> {
    UnitQuaternion::from_rotation_matrix(&nearest_rotation(m))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Unit, Vector3};
    use proptest::prelude::*;

    fn assert_same(a: &Matrix3<f64>, b: &Matrix3<f64>, tol: f64) {
        let d = (a - b).abs().max();
        assert!(d < tol, "rotation changed by {d}:\n{a}\n{b}");
    }

    #[test]
    fn every_half_turn_round_trips() {
        // The case nalgebra's iterative solver returns as the identity.
        let axes = [
            Vector3::x(),
            Vector3::y(),
            Vector3::z(),
            Vector3::new(1.0, 1.0, 0.0),
            Vector3::new(1.0, 0.0, 1.0),
            Vector3::new(0.0, 1.0, 1.0),
            Vector3::new(1.0, 1.0, 1.0),
            Vector3::new(-1.0, 2.0, 0.5),
        ];
        for axis in axes {
            let r = Rotation3::from_axis_angle(&Unit::new_normalize(axis), std::f64::consts::PI);
            let m = *r.matrix();
            assert_same(nearest_rotation(&m).matrix(), &m, 1e-12);
            let q = nearest_unit_quaternion(&m);
            assert_same(q.to_rotation_matrix().matrix(), &m, 1e-12);
        }
        // The matrix of the report: a camera turned half about its y axis.
        let m = Matrix3::new(-1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0);
        assert_same(nearest_rotation(&m).matrix(), &m, 1e-12);
    }

    #[test]
    fn a_slightly_skewed_matrix_becomes_the_nearest_proper_rotation() {
        let r = Rotation3::from_euler_angles(0.3, -0.7, 2.0);
        let noisy: Matrix3<f64> = r.matrix() + Matrix3::from_element(1e-4);
        let back = nearest_rotation(&noisy);
        assert!((back.matrix().determinant() - 1.0).abs() < 1e-9);
        assert_same(back.matrix(), r.matrix(), 1e-3);
    }

    proptest! {
        #[test]
        fn random_rotations_round_trip(
            ax in -1.0f64..1.0, ay in -1.0f64..1.0, az in -1.0f64..1.0,
            angle in 0.0f64..=std::f64::consts::PI,
        ) {
            let axis = Vector3::new(ax, ay, az);
            prop_assume!(axis.norm() > 1e-3);
            let r = Rotation3::from_axis_angle(&Unit::new_normalize(axis), angle);
            let m = *r.matrix();
            let back = nearest_rotation(&m);
            prop_assert!((back.matrix() - m).abs().max() < 1e-9);
            let f = m.cast::<f32>();
            prop_assert!((nearest_rotation(&f).matrix() - f).abs().max() < 1e-5);
        }
    }
}
