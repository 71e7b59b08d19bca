//! How long a move of the platform takes: the time limits that wait on a real hexapod follow
//! each move's length at the platform's speeds, instead of one fixed figure that suits only
//! some moves.

use crate::config::cell::RobotConfig;
use crate::geometry::Pose;

/// The platform's Cartesian speeds: mm/s along its path, deg/s about it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlatformSpeeds {
    pub mm_s: f64,
    pub deg_s: f64,
}

impl PlatformSpeeds {
    /// The cell file's `robot.speed_mm_s` and `robot.speed_deg_s`.
    pub fn of_cell(robot: &RobotConfig) -> Self {
        PlatformSpeeds {
            mm_s: robot.speed_mm_s,
            deg_s: robot.speed_deg_s,
        }
    }

    /// At a platform velocity of `mm_s` (a controller's `VLS`), turns slowed or sped up alike.
    pub fn at_velocity(self, mm_s: f64) -> Self {
        PlatformSpeeds {
            mm_s,
            deg_s: self.deg_s * mm_s / self.mm_s,
        }
    }

    /// The time from `from` to `to` along a straight path, s: the longer of the translation's
    /// and the turn's, each at its speed.
    pub fn move_time_s(&self, from: &Pose, to: &Pose) -> f64 {
        let distance_mm = (to.translation.vector - from.translation.vector).norm();
        let angle_deg = from.rotation.angle_to(&to.rotation).to_degrees();
        (distance_mm / self.mm_s).max(angle_deg / self.deg_s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion, Vector3};

    #[test]
    fn a_move_takes_the_longer_of_its_translation_and_its_turn() {
        let speeds = PlatformSpeeds {
            mm_s: 30.0,
            deg_s: 6.0,
        };
        let from = Pose::identity();
        // 5 mm at 30 mm/s: 1/6 s; no turn.
        let step = Pose::from_parts(Translation3::new(3.0, 4.0, 0.0), UnitQuaternion::identity());
        assert!((speeds.move_time_s(&from, &step) - 5.0 / 30.0).abs() < 1e-12);
        // 3 degrees at 6 deg/s: 0.5 s, longer than the 1 mm.
        let turn = Pose::from_parts(
            Translation3::new(0.0, 0.0, 1.0),
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), 3f64.to_radians()),
        );
        assert!((speeds.move_time_s(&from, &turn) - 0.5).abs() < 1e-12);
        assert!((speeds.move_time_s(&turn, &from) - 0.5).abs() < 1e-12);
        // At half the velocity, twice the time, the turn's too.
        let slow = speeds.at_velocity(15.0);
        assert!((slow.move_time_s(&from, &turn) - 1.0).abs() < 1e-12);
    }
}
