//! What the cell believes about the relative pose of the parts, with how sure it is: the
//! estimate of {F} in {M} and the standard deviations of its errors. The state filter produces
//! it; the collision supervisor judges every move against it (docs/estimation.md).

use super::{Move, Pose};
use nalgebra::{Matrix2, Matrix6};

/// Standard deviations of the errors of an estimate of {F} in {M}, in {M}. The rotation errors
/// are small rotations applied on the left (about axes of {M}).
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize)]
pub struct PoseSd {
    /// Sideways position error in its worst direction across the axis of {M} (mm).
    pub lateral_mm: f64,
    /// Position error along the shaft's axis (mm).
    pub axial_mm: f64,
    /// Tilt error in its worst direction, about an axis across z of {M} (rad).
    pub tilt_rad: f64,
    /// Twist error, the rotation about the shaft's axis (rad).
    pub twist_rad: f64,
}

impl PoseSd {
    /// From a covariance ordered `(δP mm, δO rad)`: the sideways position and the tilt take
    /// the σ of their worst direction (the largest eigenvalue of their 2×2 block).
    pub fn from_covariance(c: &Matrix6<f64>) -> PoseSd {
        PoseSd {
            lateral_mm: largest_sd(&c.fixed_view::<2, 2>(0, 0).into_owned()),
            axial_mm: c[(2, 2)].max(0.0).sqrt(),
            tilt_rad: largest_sd(&c.fixed_view::<2, 2>(3, 3).into_owned()),
            twist_rad: c[(5, 5)].max(0.0).sqrt(),
        }
    }
}

/// σ of the worst direction of a 2-D covariance: the square root of its largest eigenvalue.
pub fn largest_sd(c: &Matrix2<f64>) -> f64 {
    let mean = 0.5 * (c[(0, 0)] + c[(1, 1)]);
    let half_gap = (0.25 * (c[(0, 0)] - c[(1, 1)]).powi(2) + c[(0, 1)] * c[(1, 0)]).max(0.0);
    (mean + half_gap.sqrt()).max(0.0).sqrt()
}

/// An estimate of {F} in {M} with its uncertainty.
pub trait Belief {
    /// The mean estimate of {F} in {M}.
    fn m_f(&self) -> Pose;
    /// Covariance of its errors now, ordered `(δP mm, δO rad)` in {M}, the rotation on the left.
    fn covariance(&self) -> Matrix6<f64>;
    /// The same once `step` is executed: the error now carried along, the robot's execution
    /// error and what is not yet known of its calibration. Along the move the error is the
    /// error now plus a growing share of the move's; its variance in any direction is convex in
    /// that share, so it is never above the larger of the two.
    fn covariance_after(&self, step: &Move) -> Matrix6<f64>;
    /// The mean estimate of {F} in {M} once `step` is executed: the command, and whatever the
    /// estimate knows of how the robot really moves (a learned calibration drift).
    fn m_f_after(&self, step: &Move) -> Pose {
        step.as_pose().inverse() * self.m_f()
    }
}

/// A pose known exactly (no uncertainty): for tests, and for a supervisor judging geometry alone.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Exact(pub Pose);

impl Belief for Exact {
    fn m_f(&self) -> Pose {
        self.0
    }

    fn covariance(&self) -> Matrix6<f64> {
        Matrix6::zeros()
    }

    fn covariance_after(&self, _step: &Move) -> Matrix6<f64> {
        Matrix6::zeros()
    }
}
