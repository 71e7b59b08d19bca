//! What the cell believes about the relative pose of the parts, with how sure it is: the
//! estimate of {F} in {M} and the standard deviations of its errors. The state filter produces
//! it; the collision supervisor judges every move against it (docs/estimation.md).

use super::{Move, Pose};

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
}
