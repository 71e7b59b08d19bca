//! What the cell believes about the relative pose of the parts, with how sure it is: the
//! estimate of {F} in {M} and the standard deviations of its errors. The state filter produces
//! it; the collision supervisor judges every move against it (docs/estimation.md).

use super::{Move, Pose};
use nalgebra::Matrix6;

/// Standard deviations of the errors of an estimate of {F} in {M}, in {M}. The rotation errors
/// are small rotations applied on the left (about axes of {M}).
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize)]
pub struct PoseSd {
    /// Sideways position error, the larger of the x and y axes of {M} (mm).
    pub lateral_mm: f64,
    /// Position error along the shaft's axis (mm).
    pub axial_mm: f64,
    /// Tilt error, the larger of the rotations about x and y of {M} (rad).
    pub tilt_rad: f64,
    /// Twist error, the rotation about the shaft's axis (rad).
    pub twist_rad: f64,
}

impl PoseSd {
    /// From a covariance ordered `(δP mm, δO rad)`: the sideways position and the tilt take
    /// the σ of their worst direction (the largest eigenvalue of their 2×2 block).
    pub fn from_covariance(c: &Matrix6<f64>) -> PoseSd {
        let largest = |i: usize| {
            let (a, b, d) = (c[(i, i)], c[(i, i + 1)], c[(i + 1, i + 1)]);
            let mean = 0.5 * (a + d);
            (mean + (0.25 * (a - d).powi(2) + b * b).sqrt())
                .max(0.0)
                .sqrt()
        };
        PoseSd {
            lateral_mm: largest(0),
            axial_mm: c[(2, 2)].max(0.0).sqrt(),
            tilt_rad: largest(3),
            twist_rad: c[(5, 5)].max(0.0).sqrt(),
        }
    }

    /// Component-wise maximum.
    pub fn max(&self, other: &PoseSd) -> PoseSd {
        PoseSd {
            lateral_mm: self.lateral_mm.max(other.lateral_mm),
            axial_mm: self.axial_mm.max(other.axial_mm),
            tilt_rad: self.tilt_rad.max(other.tilt_rad),
            twist_rad: self.twist_rad.max(other.twist_rad),
        }
    }

    pub fn is_finite(&self) -> bool {
        [
            self.lateral_mm,
            self.axial_mm,
            self.tilt_rad,
            self.twist_rad,
        ]
        .iter()
        .all(|v| v.is_finite() && *v >= 0.0)
    }
}

/// An estimate of {F} in {M} with its uncertainty.
pub trait Belief {
    /// The mean estimate of {F} in {M}.
    fn m_f(&self) -> Pose;
    /// σ of its errors now.
    fn sd(&self) -> PoseSd;
    /// σ of its errors once `step` is executed: the error now carried along, the robot's
    /// execution error and what is not yet known of its calibration. Along the move the error
    /// is the error now plus a growing share of the move's, so its σ is never above the larger
    /// of [`Belief::sd`] and this (the variance is convex in the share).
    fn sd_after(&self, step: &Move) -> PoseSd;
    /// Covariance of its errors now, ordered `(δP mm, δO rad)` in {M}, the rotation on the left.
    fn covariance(&self) -> Matrix6<f64>;
    /// The same once `step` is executed.
    fn covariance_after(&self, step: &Move) -> Matrix6<f64>;
}

/// A pose known exactly (no uncertainty): for tests, and for a supervisor judging geometry alone.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Exact(pub Pose);

impl Belief for Exact {
    fn m_f(&self) -> Pose {
        self.0
    }

    fn sd(&self) -> PoseSd {
        PoseSd::default()
    }

    fn sd_after(&self, _step: &Move) -> PoseSd {
        PoseSd::default()
    }

    fn covariance(&self) -> Matrix6<f64> {
        Matrix6::zeros()
    }

    fn covariance_after(&self, _step: &Move) -> Matrix6<f64> {
        Matrix6::zeros()
    }
}
