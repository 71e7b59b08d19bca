//! The twin's soft limits (`TMN?`, `TMX?`): how far each axis travels from the home pose with
//! the other five at home, where the nominal model still reaches the pose (legs within their
//! stroke, away from singularities). A hexapod's travel is coupled: a pose with several axes
//! moved reaches less far, which `MOV` (error 7) and `VMO?` check pose by pose.

use super::super::protocol::axes_to_pose;
use crate::sim::rig::TwinRig;

/// The scan's step along an axis: mm for X Y Z, deg for U V W.
const STEP: [f64; 6] = [1.0, 1.0, 1.0, 0.1, 0.1, 0.1];
/// The scan's reach: no hexapod axis travels farther, mm or deg.
const FARTHEST: [f64; 6] = [5000.0, 5000.0, 5000.0, 90.0, 90.0, 90.0];
/// The limits are written to this resolution, rounded towards home (mm or deg).
const RESOLUTION: f64 = 1e-3;

/// The lowest (`TMN?`) and highest (`TMX?`) value of each axis X Y Z (mm) U V W (deg).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TravelLimits {
    pub min: [f64; 6],
    pub max: [f64; 6],
}

impl TravelLimits {
    /// Each axis's travel from `rig`'s home pose ({P} `home_height_mm` above {O}, unrotated):
    /// stepped outwards to the first pose the nominal model does not reach, then bisected.
    pub fn of(rig: &TwinRig) -> TravelLimits {
        let home = [0.0, 0.0, rig.cell().robot.home_height_mm, 0.0, 0.0, 0.0];
        let reaches = |k: usize, value: f64| {
            let mut axes = home;
            axes[k] = value;
            rig.reaches(&axes_to_pose(&axes))
        };
        let mut limits = TravelLimits {
            min: home,
            max: home,
        };
        if !rig.reaches(&axes_to_pose(&home)) {
            return limits;
        }
        for k in 0..6 {
            for (sign, limit) in [(-1.0, &mut limits.min[k]), (1.0, &mut limits.max[k])] {
                let travel = farthest(|d| reaches(k, home[k] + sign * d), STEP[k], FARTHEST[k]);
                let travel = (travel / RESOLUTION).floor() * RESOLUTION;
                *limit = home[k] + sign * travel;
            }
        }
        limits
    }
}

/// The farthest distance `d` in `[0, most]` with `reaches(d)`, given `reaches(0)`: stepped by
/// `step` to the first miss, then bisected to 1e-9.
fn farthest(reaches: impl Fn(f64) -> bool, step: f64, most: f64) -> f64 {
    let mut inside = 0.0;
    let mut outside = loop {
        let next = inside + step;
        if next > most {
            return most;
        }
        if !reaches(next) {
            break next;
        }
        inside = next;
    };
    while outside - inside > 1e-9 {
        let middle = 0.5 * (inside + outside);
        if reaches(middle) {
            inside = middle;
        } else {
            outside = middle;
        }
    }
    inside
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::cell::CellConfig;

    #[test]
    fn the_farthest_reach_is_found_to_the_bisections_precision() {
        assert!((farthest(|d| d <= 12.345, 1.0, 100.0) - 12.345).abs() < 1e-8);
        assert_eq!(farthest(|_| true, 1.0, 100.0), 100.0);
        assert!(farthest(|d| d <= 0.25, 1.0, 100.0) < 0.25 + 1e-8);
    }

    #[test]
    fn each_limit_is_reached_and_a_little_beyond_it_is_not() {
        let cell = CellConfig::reference();
        let rig = TwinRig::new(&cell);
        let limits = TravelLimits::of(&rig);
        let home = [0.0, 0.0, cell.robot.home_height_mm, 0.0, 0.0, 0.0];
        for k in 0..6 {
            assert!(
                limits.min[k] < home[k] && home[k] < limits.max[k],
                "{limits:?}"
            );
            for (limit, outwards) in [(limits.min[k], -1.0), (limits.max[k], 1.0)] {
                let mut axes = home;
                axes[k] = limit;
                assert!(rig.reaches(&axes_to_pose(&axes)), "axis {k} at {limit}");
                axes[k] = limit + outwards * 2.0 * RESOLUTION;
                assert!(!rig.reaches(&axes_to_pose(&axes)), "axis {k} past {limit}");
            }
        }
        // Z, hand-computed: unrotated above the base, a leg is as long as
        // sqrt(horizontal² + z²); the longest one reaches the stroke's end first.
        let (base, platform) = (cell.robot.base_joints_mm(), cell.robot.platform_joints_mm());
        let widest = (0..6)
            .map(|i| (base[i] - platform[i]).xy().norm())
            .fold(0.0, f64::max);
        let z_max = (cell.robot.leg_max_mm.powi(2) - widest.powi(2)).sqrt();
        assert!(
            (limits.max[2] - z_max).abs() < 2.0 * RESOLUTION,
            "{} {z_max}",
            limits.max[2]
        );
    }
}
