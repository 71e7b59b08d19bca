//! One commanded move of Segment I: a small rigid motion of {M} expressed in {M} (docs/design.md §5).

use super::pose::{Pose, pose_from_mm_deg};
use nalgebra::Vector3;

/// A move of frame {M} in its own coordinates: translate by `translation_mm`, rotate by the
/// rotation vector `rotation_deg` about {M}'s origin. The paper's action `[Δx, Δy, Δz, θx, θy, θz]`.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Move {
    pub translation_mm: Vector3<f64>,
    pub rotation_deg: Vector3<f64>,
}

impl Move {
    pub fn translation(x_mm: f64, y_mm: f64, z_mm: f64) -> Self {
        Move {
            translation_mm: Vector3::new(x_mm, y_mm, z_mm),
            rotation_deg: Vector3::zeros(),
        }
    }

    pub fn rotation(x_deg: f64, y_deg: f64, z_deg: f64) -> Self {
        Move {
            translation_mm: Vector3::zeros(),
            rotation_deg: Vector3::new(x_deg, y_deg, z_deg),
        }
    }

    /// From the six action values `[Δx, Δy, Δz, θx, θy, θz]` (mm, deg).
    pub fn from_array(a: [f64; 6]) -> Self {
        Move {
            translation_mm: Vector3::new(a[0], a[1], a[2]),
            rotation_deg: Vector3::new(a[3], a[4], a[5]),
        }
    }

    pub fn to_array(&self) -> [f64; 6] {
        let (t, r) = (self.translation_mm, self.rotation_deg);
        [t.x, t.y, t.z, r.x, r.y, r.z]
    }

    /// The move as a transform of {M}: new {M} = old {M} · `as_pose()`.
    pub fn as_pose(&self) -> Pose {
        pose_from_mm_deg(self.translation_mm, self.rotation_deg)
    }

    /// The same move, `factor` times as long (translation and rotation alike).
    pub fn scaled(&self, factor: f64) -> Move {
        Move {
            translation_mm: self.translation_mm * factor,
            rotation_deg: self.rotation_deg * factor,
        }
    }

    pub fn is_finite(&self) -> bool {
        self.to_array().iter().all(|v| v.is_finite())
    }

    /// Largest translation component (mm) and rotation component (deg), for the step limits.
    pub fn max_components(&self) -> (f64, f64) {
        (self.translation_mm.amax(), self.rotation_deg.amax())
    }

    /// Time the robot needs for this move at the given Cartesian speed limits (s).
    pub fn duration_s(&self, speed_mm_s: f64, speed_deg_s: f64) -> f64 {
        (self.translation_mm.norm() / speed_mm_s).max(self.rotation_deg.norm() / speed_deg_s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_move_of_m_changes_the_relative_pose_as_expected() {
        // {F} 10 mm ahead of {M} along x; moving {M} by +4 mm in x leaves 6 mm.
        let m_f = pose_from_mm_deg(Vector3::new(10.0, 0.0, 0.0), Vector3::zeros());
        let after = Move::translation(4.0, 0.0, 0.0).as_pose().inverse() * m_f;
        assert!((after.translation.vector - Vector3::new(6.0, 0.0, 0.0)).norm() < 1e-12);
        // A pure rotation equal to the relative rotation cancels it.
        let m_f = pose_from_mm_deg(Vector3::zeros(), Vector3::new(0.0, 0.5, 0.0));
        let after = Move::rotation(0.0, 0.5, 0.0).as_pose().inverse() * m_f;
        assert!(after.rotation.angle() < 1e-12);
    }

    #[test]
    fn array_round_trip_and_limits() {
        let m = Move::from_array([1.0, -5.0, 2.0, 0.1, -0.7, 0.2]);
        assert_eq!(m.to_array(), [1.0, -5.0, 2.0, 0.1, -0.7, 0.2]);
        assert_eq!(m.max_components(), (5.0, 0.7));
    }
}
