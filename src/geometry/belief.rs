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
    /// Component-wise sum: a bound on the σ of a sum of errors, however they are correlated
    /// (σ of a sum ≤ sum of the σ).
    pub fn plus(&self, other: &PoseSd) -> PoseSd {
        PoseSd {
            lateral_mm: self.lateral_mm + other.lateral_mm,
            axial_mm: self.axial_mm + other.axial_mm,
            tilt_rad: self.tilt_rad + other.tilt_rad,
            twist_rad: self.twist_rad + other.twist_rad,
        }
    }

    pub fn is_finite(&self) -> bool {
        [self.lateral_mm, self.axial_mm, self.tilt_rad, self.twist_rad]
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
    /// σ of the error an executed `step` adds (the robot's execution error and what is not yet
    /// known of its calibration).
    fn sd_added_by(&self, step: &Move) -> PoseSd;
}
