//! Differential drive: Beetle-One steers like an electric wheelchair, by the speed difference
//! of its left and right wheels.

use nalgebra::{Isometry2, Vector2};

/// Wheel geometry.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DiffDrive {
    /// Wheel radius, m.
    pub wheel_radius: f64,
    /// Distance between the wheels' contact points, m.
    pub track: f64,
}

impl DiffDrive {
    /// Beetle-One: 0.15 m wheels, 0.5 m apart.
    pub const BEETLE: DiffDrive = DiffDrive {
        wheel_radius: 0.15,
        track: 0.5,
    };

    /// Wheel speeds (left, right; rad/s) that produce `linear` m/s and `angular` rad/s.
    pub fn wheel_speeds(&self, linear: f64, angular: f64) -> (f64, f64) {
        let half = angular * self.track / 2.0;
        (
            (linear - half) / self.wheel_radius,
            (linear + half) / self.wheel_radius,
        )
    }

    /// Body velocity (linear m/s, angular rad/s) of wheel speeds (rad/s): the inverse of
    /// [`DiffDrive::wheel_speeds`].
    pub fn body_velocity(&self, left: f64, right: f64) -> (f64, f64) {
        let (vl, vr) = (left * self.wheel_radius, right * self.wheel_radius);
        ((vl + vr) / 2.0, (vr - vl) / self.track)
    }

    /// Pose change (in the rover's frame) when the wheels roll `left` and `right` metres of
    /// ground each, moving along a circular arc.
    pub fn arc(&self, left: f64, right: f64) -> Isometry2<f64> {
        let ds = (left + right) / 2.0;
        let dth = (right - left) / self.track;
        let (dx, dy) = if dth.abs() < 1e-9 {
            (ds, 0.0)
        } else {
            let r = ds / dth;
            (r * dth.sin(), r * (1.0 - dth.cos()))
        };
        Isometry2::new(Vector2::new(dx, dy), dth)
    }
}

/// Wraps an angle to (-π, π].
pub fn wrap(angle: f64) -> f64 {
    let a = angle.rem_euclid(std::f64::consts::TAU);
    if a > std::f64::consts::PI {
        a - std::f64::consts::TAU
    } else {
        a
    }
}

/// Scales wheel speeds down together so neither exceeds `max` (keeps the path's curvature).
pub fn saturate(left: f64, right: f64, max: f64) -> (f64, f64) {
    let peak = left.abs().max(right.abs());
    if peak > max && peak > 0.0 {
        let k = max / peak;
        (left * k, right * k)
    } else {
        (left, right)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use std::f64::consts::PI;

    const D: DiffDrive = DiffDrive::BEETLE;

    proptest! {
        #[test]
        fn odometry_inverts_the_mixer(v in -2.0..2.0f64, w in -3.0..3.0f64) {
            let (l, r) = D.wheel_speeds(v, w);
            let (v2, w2) = D.body_velocity(l, r);
            prop_assert!((v - v2).abs() < 1e-9 && (w - w2).abs() < 1e-9);
        }

        #[test]
        fn many_small_arcs_equal_one_arc(l in -1.0..1.0f64, r in -1.0..1.0f64, n in 1usize..50) {
            let one = D.arc(l, r);
            let mut many = Isometry2::identity();
            for _ in 0..n {
                many *= D.arc(l / n as f64, r / n as f64);
            }
            prop_assert!((one.translation.vector - many.translation.vector).norm() < 1e-9);
            prop_assert!(wrap(one.rotation.angle() - many.rotation.angle()).abs() < 1e-9);
        }
    }

    #[test]
    fn known_arcs() {
        // Straight: both wheels roll 1 m.
        let s = D.arc(1.0, 1.0);
        assert!((s.translation.x - 1.0).abs() < 1e-12 && s.translation.y.abs() < 1e-12);
        // Spin in place: wheels roll ±track·π/4 → a quarter turn, no translation.
        let q = D.track * PI / 4.0;
        let spin = D.arc(-q, q);
        assert!(spin.translation.vector.norm() < 1e-12);
        assert!((spin.rotation.angle() - PI / 2.0).abs() < 1e-12);
        // A half circle of radius 1 m to the left: inner wheel at 0.75 m, outer at 1.25 m.
        let (inner, outer) = ((1.0 - D.track / 2.0) * PI, (1.0 + D.track / 2.0) * PI);
        let half = D.arc(inner, outer);
        assert!((half.translation.x).abs() < 1e-9, "{half}");
        assert!((half.translation.y - 2.0).abs() < 1e-9, "{half}");
        assert!((wrap(half.rotation.angle()).abs() - PI).abs() < 1e-9);
        // Constant wheel speeds give the radius R = track/2 · (ωr+ωl)/(ωr−ωl).
        let (l, r) = D.wheel_speeds(0.5, 0.25);
        let radius = D.track / 2.0 * (r + l) / (r - l);
        assert!((radius - 2.0).abs() < 1e-12);
    }

    #[test]
    fn saturation_keeps_curvature() {
        let (l, r) = saturate(20.0, 10.0, 10.0);
        assert_eq!((l, r), (10.0, 5.0));
        assert_eq!(saturate(1.0, -2.0, 10.0), (1.0, -2.0));
        assert!((wrap(3.0 * PI) - PI).abs() < 1e-12);
        assert!((wrap(-PI / 2.0) + PI / 2.0).abs() < 1e-12);
    }
}
