//! A hexapod move in time: the platform goes along the straight line from where it was to
//! its target (translation interpolated linearly, rotation by slerp), as fast as the slower of
//! its two speeds allows. Pure: the time is an argument, in seconds on any fixed clock.

use super::super::protocol::{axes_to_pose, pose_to_axes};
use crate::geometry::Pose;

/// Two axis values closer than this (mm or deg) are the same: an axis whose start and target
/// differ by less does not move.
const SAME_AXIS: f64 = 1e-9;

/// How fast the platform moves: translation mm/s, rotation deg/s.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Speeds {
    pub mm_s: f64,
    pub deg_s: f64,
}

/// One move of the six axes X Y Z (mm) U V W (deg), started at `start_s`.
#[derive(Debug, Clone, PartialEq)]
pub struct Motion {
    from: [f64; 6],
    to: [f64; 6],
    start_s: f64,
    duration_s: f64,
}

impl Motion {
    /// The move from `from` to `to` starting at `start_s`: it lasts the translation distance
    /// over `speeds.mm_s` or the rotation angle over `speeds.deg_s`, whichever is longer.
    pub fn new(from: [f64; 6], to: [f64; 6], start_s: f64, speeds: Speeds) -> Motion {
        let (a, b) = (axes_to_pose(&from), axes_to_pose(&to));
        let distance_mm = (b.translation.vector - a.translation.vector).norm();
        let angle_deg = a.rotation.angle_to(&b.rotation).to_degrees();
        let duration_s = (distance_mm / speeds.mm_s).max(angle_deg / speeds.deg_s);
        Motion {
            from,
            to,
            start_s,
            duration_s: if duration_s.is_finite() {
                duration_s
            } else {
                0.0
            },
        }
    }

    pub fn duration_s(&self) -> f64 {
        self.duration_s
    }

    /// The axis values the move ends at.
    pub fn target(&self) -> [f64; 6] {
        self.to
    }

    /// Whether the platform has arrived by `now_s`.
    pub fn done(&self, now_s: f64) -> bool {
        now_s >= self.start_s + self.duration_s
    }

    /// The axis values at `now_s`: the start before the move starts, the target once done.
    pub fn at(&self, now_s: f64) -> [f64; 6] {
        if self.done(now_s) {
            return self.to;
        }
        let fraction = ((now_s - self.start_s) / self.duration_s).clamp(0.0, 1.0);
        let (a, b) = (axes_to_pose(&self.from), axes_to_pose(&self.to));
        let translation = a.translation.vector.lerp(&b.translation.vector, fraction);
        // Half a turn apart has no single shortest arc; a hexapod never tilts that far.
        let rotation = a
            .rotation
            .try_slerp(&b.rotation, fraction, 1e-12)
            .unwrap_or(if fraction < 0.5 {
                a.rotation
            } else {
                b.rotation
            });
        pose_to_axes(&Pose::from_parts(translation.into(), rotation))
    }

    /// The axes that move, as PI's `#5` writes them: bit k set while axis k (X Y Z U V W)
    /// has yet to reach a target different from where it started.
    pub fn moving_mask(&self, now_s: f64) -> u32 {
        if self.done(now_s) {
            return 0;
        }
        (0..6)
            .filter(|&k| (self.to[k] - self.from[k]).abs() > SAME_AXIS)
            .fold(0, |mask, k| mask | 1 << k)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const SPEEDS: Speeds = Speeds {
        mm_s: 30.0,
        deg_s: 6.0,
    };

    #[test]
    fn a_translation_lasts_its_length_over_the_speed_and_goes_straight() {
        let from = [0.0, 0.0, 800.0, 0.0, 0.0, 0.0];
        let to = [3.0, 4.0, 800.0, 0.0, 0.0, 0.0];
        let motion = Motion::new(from, to, 10.0, SPEEDS);
        // 5 mm at 30 mm/s.
        assert!((motion.duration_s() - 1.0 / 6.0).abs() < 1e-12);
        assert!(!motion.done(10.0 + 1.0 / 6.0 - 1e-9));
        assert!(motion.done(10.0 + 1.0 / 6.0));
        let half = motion.at(10.0 + 1.0 / 12.0);
        for (got, want) in half.iter().zip([1.5, 2.0, 800.0, 0.0, 0.0, 0.0]) {
            assert!((got - want).abs() < 1e-9, "{half:?}");
        }
        assert_eq!(motion.at(9.0), motion.at(10.0));
        assert_eq!(motion.at(11.0), to);
        assert_eq!(motion.moving_mask(10.1), 0b11);
        assert_eq!(motion.moving_mask(11.0), 0);
    }

    #[test]
    fn a_rotation_lasts_its_angle_over_the_angular_speed() {
        let from = [0.0, 0.0, 800.0, 0.0, 0.0, 0.0];
        // 3 deg about Z at 6 deg/s, with 1 mm along X at 30 mm/s: the rotation is slower.
        let to = [1.0, 0.0, 800.0, 0.0, 0.0, 3.0];
        let motion = Motion::new(from, to, 0.0, SPEEDS);
        assert!((motion.duration_s() - 0.5).abs() < 1e-12);
        let quarter = motion.at(0.125);
        assert!((quarter[0] - 0.25).abs() < 1e-9, "{quarter:?}");
        assert!((quarter[5] - 0.75).abs() < 1e-9, "{quarter:?}");
        assert_eq!(motion.moving_mask(0.1), 0b10_0001);
    }

    #[test]
    fn a_move_to_where_the_platform_is_takes_no_time() {
        let here = [1.0, 2.0, 800.0, 0.5, 0.0, 0.0];
        let motion = Motion::new(here, here, 4.0, SPEEDS);
        assert_eq!(motion.duration_s(), 0.0);
        assert!(motion.done(4.0));
        assert_eq!(motion.moving_mask(4.0), 0);
    }
}
