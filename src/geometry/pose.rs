//! Rigid poses and the conversions the cell uses everywhere.
//!
//! A [`Pose`] is a nalgebra `Isometry3<f64>`: translation in millimetres, rotation as a unit
//! quaternion. `T_AB` (written `a_b` in code) maps coordinates in frame B to frame A.

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

/// A rigid transform, translation in mm.
pub type Pose = Isometry3<f64>;

/// Builds a pose from a translation (mm) and a rotation vector (deg).
pub fn pose_from_mm_deg(translation_mm: Vector3<f64>, rotation_vector_deg: Vector3<f64>) -> Pose {
    Isometry3::from_parts(
        Translation3::from(translation_mm),
        UnitQuaternion::from_scaled_axis(rotation_vector_deg.map(f64::to_radians)),
    )
}

/// The rotation vector (axis × angle) of a pose's rotation, in degrees; angle in [0, 180].
pub fn rotation_vector_deg(pose: &Pose) -> Vector3<f64> {
    pose.rotation.scaled_axis().map(f64::to_degrees)
}

/// The rotation angle of a pose, in degrees, in [0, 180].
pub fn rotation_angle_deg(pose: &Pose) -> f64 {
    pose.rotation.angle().to_degrees()
}

/// The pose a fraction `s` (0 = `from`, 1 = `to`) along the straight path between two poses:
/// translation linearly, rotation by spherical interpolation. This is the path a Cartesian
/// robot controller follows for one move.
pub fn interpolate(from: &Pose, to: &Pose, s: f64) -> Pose {
    let translation = from.translation.vector.lerp(&to.translation.vector, s);
    let rotation = from
        .rotation
        .try_slerp(&to.rotation, s, 1e-12)
        .unwrap_or(to.rotation);
    Isometry3::from_parts(Translation3::from(translation), rotation)
}

/// Rotation about the x axis by `deg` degrees, as a pose.
pub fn rotation_x_deg(deg: f64) -> Pose {
    Isometry3::from_parts(
        Translation3::identity(),
        UnitQuaternion::from_axis_angle(&Vector3::x_axis(), deg.to_radians()),
    )
}

/// Whether every number in the pose is finite.
pub fn is_finite(pose: &Pose) -> bool {
    pose.translation.vector.iter().all(|v| v.is_finite())
        && pose.rotation.coords.iter().all(|v| v.is_finite())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rotation_vector_round_trip() {
        let p = pose_from_mm_deg(Vector3::new(1.0, -2.0, 3.0), Vector3::new(0.3, -0.7, 12.0));
        let r = rotation_vector_deg(&p);
        assert!((r - Vector3::new(0.3, -0.7, 12.0)).norm() < 1e-12);
        assert!((p.translation.vector - Vector3::new(1.0, -2.0, 3.0)).norm() < 1e-15);
    }

    #[test]
    fn interpolate_ends_and_middle() {
        let a = pose_from_mm_deg(Vector3::new(0.0, 0.0, 0.0), Vector3::new(0.0, 0.0, 0.0));
        let b = pose_from_mm_deg(Vector3::new(10.0, 0.0, 0.0), Vector3::new(0.0, 0.0, 2.0));
        let m = interpolate(&a, &b, 0.5);
        assert!((m.translation.vector.x - 5.0).abs() < 1e-12);
        assert!((rotation_vector_deg(&m).z - 1.0).abs() < 1e-12);
        assert!((interpolate(&a, &b, 1.0).translation.vector.x - 10.0).abs() < 1e-12);
    }
}
