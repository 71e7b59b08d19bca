//! The episode's judge apart from the environment: Segment I's errors against the goal for a
//! pose of {M} in {F}, success, and the workspace. The twin's environment judges the true pose;
//! a real cell's backend, which has no truth, judges its fused estimate with the same rules.

use super::PoseErrors;
use crate::collision::clearance::PartGeometry;
use crate::config::cell::CellConfig;
use crate::geometry::Pose;
use nalgebra::{Point3, Vector3};

/// A cell's tolerances and workspace.
#[derive(Debug, Clone)]
pub struct Judge {
    parts: PartGeometry,
    bore_depth_mm: f64,
    hole_pitch_deg: f64,
    depth_tolerance_mm: f64,
    hole_arc_tolerance_mm: f64,
    workspace_radius_mm: f64,
    workspace_tilt_deg: f64,
}

impl Judge {
    pub fn new(cell: &CellConfig) -> Self {
        Judge {
            parts: PartGeometry::from_config(cell),
            bore_depth_mm: cell.bore.depth_mm,
            hole_pitch_deg: cell.hole_pitch_deg(),
            depth_tolerance_mm: cell.success.depth_tolerance_mm,
            hole_arc_tolerance_mm: cell.success.hole_arc_tolerance_mm,
            workspace_radius_mm: cell.episode.workspace_radius_mm,
            workspace_tilt_deg: cell.episode.workspace_tilt_deg,
        }
    }

    /// Segment I's errors when {M} is at `f_m` in {F} (mm and deg).
    pub fn errors(&self, f_m: &Pose) -> PoseErrors {
        let tip = f_m * Point3::new(0.0, 0.0, -self.parts.shaft_length_mm);
        let axis = f_m.rotation * Vector3::z();
        let q = f_m.rotation.quaternion();
        // Twist about the bore axis (swing-twist decomposition), wrapped to the hole pitch.
        let twist_deg = (2.0 * q.k.atan2(q.w)).to_degrees();
        let pitch = self.hole_pitch_deg;
        let wrapped = (twist_deg + pitch / 2.0).rem_euclid(pitch) - pitch / 2.0;
        PoseErrors {
            lateral_mm: f_m.translation.vector.xy().norm(),
            depth_error_mm: -tip.z - self.bore_depth_mm,
            tilt_deg: axis.z.clamp(-1.0, 1.0).acos().to_degrees(),
            hole_arc_mm: self.parts.bore_radius_mm * wrapped.abs().to_radians(),
        }
    }

    /// Inserted to depth with the holes lined up.
    pub fn is_success(&self, errors: &PoseErrors) -> bool {
        errors.depth_error_mm.abs() <= self.depth_tolerance_mm
            && errors.hole_arc_mm <= self.hole_arc_tolerance_mm
    }

    /// Segment I has left the workspace.
    pub fn outside_workspace(&self, f_m: &Pose, errors: &PoseErrors) -> bool {
        f_m.translation.vector.norm() > self.workspace_radius_mm
            || errors.tilt_deg > self.workspace_tilt_deg
    }

    /// Segment I's tip is inside the bore when {F} is at `m_f` in {M}.
    pub fn tip_in_bore(&self, m_f: &Pose) -> bool {
        let tip = m_f.inverse() * Point3::new(0.0, 0.0, -self.parts.shaft_length_mm);
        tip.z < 0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::{AssemblyEnv, EnvOptions, InitialConditions};

    #[test]
    fn the_judge_sees_the_errors_the_twin_environment_sees() {
        let cell = CellConfig::reference();
        let judge = Judge::new(&cell);
        let mut env = AssemblyEnv::new(&cell, EnvOptions::from_cell(&cell));
        for seed in 0..5 {
            let initial = InitialConditions {
                offset_mm: 0.1 * seed as f64,
                orientation_deg: 0.2,
            };
            env.reset_with(seed, initial).unwrap();
            assert_eq!(
                judge.errors(&env.true_f_m()),
                env.true_errors(),
                "seed {seed}"
            );
        }
    }
}
