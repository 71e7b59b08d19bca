//! The collision supervisor as a decorator: a [`Robot`] that checks every move before the robot
//! it wraps sees it (openrr arci's pattern for safety limits).

use super::{Robot, RobotError};
use crate::collision::clearance::clearance;
use crate::collision::supervisor::{Allowed, Supervisor, VetoReason};
use crate::geometry::{Belief, Move, Pose};

/// `inner` behind the supervisor. The supervisor judges a move against the robot's setpoint
/// and the cell's latest estimate of {F} in {M} with its uncertainty, given by
/// [`Supervised::observe`]; with no estimate (a stale camera) every move is vetoed.
pub struct Supervised<'s, R> {
    supervisor: &'s Supervisor,
    belief: Option<&'s dyn Belief>,
    inner: R,
}

impl<'s, R: Robot> Supervised<'s, R> {
    /// Wraps `inner`; until [`Supervised::observe`] is called there is no estimate.
    pub fn new(supervisor: &'s Supervisor, inner: R) -> Self {
        Supervised {
            supervisor,
            belief: None,
            inner,
        }
    }

    /// The cell's latest estimate of {F} in {M}; `None` when it is stale.
    pub fn observe(&mut self, belief: Option<&'s dyn Belief>) {
        self.belief = belief;
    }

    pub fn inner(&self) -> &R {
        &self.inner
    }

    /// Executes `step`; when the supervisor is not sure enough of it (`uncertain`), the longest
    /// share of it down to a quarter (`CAUTIOUS_FACTORS`) that it is sure of instead: the cell
    /// slows down rather than holds. A move deeper that also steers and would take Segment I
    /// under the wall margin (`wall_margin`) is shortened the same way: a shorter move carries
    /// less of the robot's drift. One straight along the axis is refused as it is.
    ///
    /// If no share is allowed and the move goes deeper along the shaft's axis, its sideways and
    /// turning part alone (`sideways_parts`), provided its probability of contact
    /// is within the bound: the cell centres the shaft before it goes on, rather than holding
    /// off-centre while the controller keeps asking to go in. Failing that, with the tip in the
    /// bore, the sideways part that leaves the most room, if that is more than there is now
    /// and the supervisor allows it (it adds no risk to where the cell stands, and the
    /// estimate is sure enough of where it ends): without it a shaft that stopped a few
    /// hundredths of a millimetre off the axis holds there until the episode ends, every share
    /// of the move going deeper and a partial centring not bringing the probability of contact
    /// from where it stands under the bound. Only in the bore, where waiting makes a settled
    /// estimate no surer: above it a controller that searches for the entrance by its refusals
    /// (`spiral`) is still told, and a shaft at the entrance on an unsure estimate is not moved
    /// about. Answers the move executed; the first refusal when none is allowed.
    pub fn execute_cautiously(&mut self, step: &Move) -> Result<Move, RobotError> {
        let setpoint = self.inner.setpoint();
        let mut refusal = None;
        let steers_deeper = step.translation_mm.z < 0.0 && asks_sideways(step);
        for factor in CAUTIOUS_FACTORS {
            let candidate = step.scaled(factor);
            match self.supervisor.check(&setpoint, self.belief, &candidate) {
                Ok(_) => {
                    self.inner.execute(&candidate)?;
                    return Ok(candidate);
                }
                Err(reason @ VetoReason::Uncertain { .. }) => {
                    refusal.get_or_insert(reason);
                }
                Err(reason @ VetoReason::WallMargin { .. }) if steers_deeper => {
                    refusal.get_or_insert(reason);
                }
                Err(reason) => return Err(RobotError::Vetoed(refusal.unwrap_or(reason))),
            }
        }
        let refusal = refusal.expect("every share was refused as uncertain or near the wall");
        // Deeper is −z of {M}: Segment I's tip leads along −z.
        if step.translation_mm.z < 0.0 {
            let bound = self.supervisor.risk_bound();
            let centring = self
                .roomiest_sideways_part(step, |allowed, _| allowed.contact_risk <= bound)
                .or_else(|| {
                    self.tip_in_the_bore()
                        .then(|| {
                            let now_mm = self.clearance_after(&Move::default());
                            self.roomiest_sideways_part(step, |_, after_mm| after_mm > now_mm)
                        })
                        .flatten()
                });
            if let Some(centring) = centring {
                self.inner.execute(&centring)?;
                return Ok(centring);
            }
        }
        Err(RobotError::Vetoed(refusal))
    }

    /// Of `step`'s sideways parts (`sideways_parts`) that the supervisor allows and `good_enough`
    /// accepts (given the verdict and the clearance where the part ends, mm), the one that
    /// leaves Segment I the most room.
    fn roomiest_sideways_part(
        &self,
        step: &Move,
        good_enough: impl Fn(&Allowed, f64) -> bool,
    ) -> Option<Move> {
        let setpoint = self.inner.setpoint();
        self.sideways_parts(step)
            .into_iter()
            .filter_map(|candidate| {
                let allowed = self
                    .supervisor
                    .check(&setpoint, self.belief, &candidate)
                    .ok()?;
                let after_mm = self.clearance_after(&candidate);
                good_enough(&allowed, after_mm).then_some((candidate, after_mm))
            })
            .max_by(|a, b| a.1.total_cmp(&b.1))
            .map(|(candidate, _)| candidate)
    }

    /// Whether the tip is past the bore's entrance by the estimate.
    fn tip_in_the_bore(&self) -> bool {
        self.belief.is_some_and(|belief| {
            self.supervisor
                .parts()
                .tip_depth_mm(&belief.m_f().inverse())
                > 0.0
        })
    }

    /// The room (mm) `step` leaves Segment I, by the estimate (drift included): its clearance,
    /// or above the bore, where the clearance is the gap below the tip whichever way the tip
    /// moves sideways, the room the tip's rim would have at the entrance. Sideways parts are
    /// then told apart by how near the axis they bring the tip; by the gap below it they tied,
    /// and once the filter learned the axial drift a micrometre of predicted height chose
    /// between them (decision 0045).
    fn clearance_after(&self, step: &Move) -> f64 {
        self.belief.map_or(f64::NEG_INFINITY, |belief| {
            let parts = self.supervisor.parts();
            let f_m = belief.m_f_after(step).inverse();
            let along = clearance(parts, &f_m);
            if along.wall_mm.is_finite() {
                along.min_mm()
            } else {
                parts.bore_radius_mm - parts.shaft_radius_mm - parts.tip_off_axis_mm(&f_m)
            }
        })
    }

    /// The sideways and turning part of `step` alone, two ways: as commanded, and as far
    /// sideways as the whole move would really take Segment I with the calibration drift the
    /// estimate has learned. A controller that steers against the drift of the move along the
    /// axis asks for a sideways command that only makes sense with that move; one that does not
    /// asks for the sideways move it wants. The cell takes whichever leaves more room where it
    /// ends. A move straight along the axis has only the first: the drift alone is no centring
    /// the controller asked for.
    fn sideways_parts(&self, step: &Move) -> Vec<Move> {
        let mut as_commanded = *step;
        as_commanded.translation_mm.z = 0.0;
        let mut parts = vec![as_commanded];
        if let Some(belief) = self.belief.filter(|_| asks_sideways(step)) {
            let really = (belief.m_f_after(step) * belief.m_f().inverse()).inverse();
            let drift = really.translation.vector - step.as_pose().translation.vector;
            let mut as_drifted = as_commanded;
            as_drifted.translation_mm.x += drift.x;
            as_drifted.translation_mm.y += drift.y;
            parts.push(as_drifted);
        }
        parts
    }
}

/// Whether `step` moves Segment I sideways or turns it, beside any move along the axis.
fn asks_sideways(step: &Move) -> bool {
    step.translation_mm.xy() != nalgebra::Vector2::zeros()
        || step.rotation_deg != nalgebra::Vector3::zeros()
}

/// The shares of a move tried, longest first, when the whole is too uncertain: fine enough
/// that a refused move still goes most of the way it may.
const CAUTIOUS_FACTORS: [f64; 6] = [1.0, 0.8, 0.6, 0.45, 0.33, 0.25];

impl<R: Robot> Robot for Supervised<'_, R> {
    fn setpoint(&self) -> Pose {
        self.inner.setpoint()
    }

    fn encoders_mm(&self) -> [f64; 6] {
        self.inner.encoders_mm()
    }

    fn execute(&mut self, step: &Move) -> Result<(), RobotError> {
        self.supervisor
            .check(&self.inner.setpoint(), self.belief, step)
            .map_err(RobotError::Vetoed)?;
        self.inner.execute(step)
    }

    fn hold(&mut self) {
        self.inner.hold()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::cell::CellConfig;
    use crate::geometry::Exact;
    use nalgebra::Isometry3;

    /// A robot that records what reaches it and goes nowhere.
    #[derive(Default)]
    struct Recorder {
        executed: Vec<Move>,
        holds: u32,
    }

    impl Robot for Recorder {
        fn setpoint(&self) -> Pose {
            Isometry3::translation(0.0, 0.0, CellConfig::reference().robot.home_height_mm)
        }
        fn encoders_mm(&self) -> [f64; 6] {
            [0.0; 6]
        }
        fn execute(&mut self, step: &Move) -> Result<(), RobotError> {
            self.executed.push(*step);
            Ok(())
        }
        fn hold(&mut self) {
            self.holds += 1;
        }
    }

    /// {F} in {M} with Segment I 30 mm into the bore and 0.04 mm off its axis: 0.01 mm of the
    /// 0.05 mm radial clearance is left towards +x.
    fn inserted_off_axis() -> Pose {
        Isometry3::translation(0.04, 0.0, 60.0 - 30.0).inverse()
    }

    #[test]
    fn only_moves_the_supervisor_allows_reach_the_robot() {
        let supervisor = Supervisor::new(&CellConfig::reference());
        let mut recorder = Recorder::default();
        let mut robot = Supervised::new(&supervisor, &mut recorder);

        let towards_axis = Move::translation(-0.03, 0.0, -1.0);
        let into_wall = Move::translation(0.02, 0.0, 0.0);
        // No estimate yet: blind, so nothing moves.
        assert_eq!(
            robot.execute(&towards_axis),
            Err(RobotError::Vetoed(
                crate::collision::supervisor::VetoReason::StaleMeasurement
            ))
        );
        let known = Exact(inserted_off_axis());
        robot.observe(Some(&known));
        assert_eq!(robot.execute(&towards_axis), Ok(()));
        match robot.execute(&into_wall) {
            Err(RobotError::Vetoed(reason)) => assert_eq!(reason.code(), "collision"),
            other => panic!("a move into the wall must be vetoed, got {other:?}"),
        }
        let too_big = Move::translation(0.0, 0.0, -50.0);
        assert!(matches!(
            robot.execute(&too_big),
            Err(RobotError::Vetoed(reason)) if reason.code() == "step_limit"
        ));
        robot.hold();
        assert_eq!(recorder.executed, vec![towards_axis]);
        assert_eq!(recorder.holds, 1, "hold goes straight through");
    }

    /// A belief with σ `sd_mm` sideways (x and y of {M}) and a well-known rest.
    struct Unsure(Pose, f64);

    impl Belief for Unsure {
        fn m_f(&self) -> Pose {
            self.0
        }
        fn covariance(&self) -> nalgebra::Matrix6<f64> {
            let v = self.1 * self.1;
            nalgebra::Matrix6::from_diagonal(&nalgebra::Vector6::new(
                v, v, 1e-8, 1e-12, 1e-12, 1e-12,
            ))
        }
        fn covariance_after(&self, _step: &Move) -> nalgebra::Matrix6<f64> {
            self.covariance()
        }
    }

    #[test]
    fn an_uncertain_move_deeper_that_centres_is_made_and_one_back_to_the_wall_refused() {
        let supervisor = Supervisor::new(&CellConfig::reference());
        let mut recorder = Recorder::default();
        let mut robot = Supervised::new(&supervisor, &mut recorder);
        // 0.04 mm off the axis with σ 0.004 mm sideways: 0.01 mm from the wall is 2.5 σ, too
        // little for 1e-4. A move that centres as it goes deeper brings the grown shaft no
        // nearer the wall anywhere along it and leaves the seat's gap open, so it adds no risk
        // to where the shaft stands and is made whole (decision 0042).
        let belief = Unsure(inserted_off_axis(), 0.004);
        robot.observe(Some(&belief));
        let centre_and_go_in = Move::translation(-0.04, 0.0, -4.0);
        let executed = robot.execute_cautiously(&centre_and_go_in);
        assert_eq!(executed, Ok(centre_and_go_in));
        // Coming back out towards the wall is never cut down to its sideways part: it is
        // judged as it is, and refused.
        let out_towards_wall = Move::translation(0.005, 0.0, 1.0);
        assert!(matches!(
            robot.execute_cautiously(&out_towards_wall),
            Err(RobotError::Vetoed(_))
        ));
        assert_eq!(recorder.executed, vec![centre_and_go_in]);
    }

    /// [`Unsure`] on a robot whose moves along the axis also carry Segment I sideways, by
    /// `drift_per_mm` along x per mm along z (as the state filter's learned drift does).
    struct Drifting {
        unsure: Unsure,
        drift_per_mm: f64,
    }

    impl Belief for Drifting {
        fn m_f(&self) -> Pose {
            self.unsure.m_f()
        }
        fn covariance(&self) -> nalgebra::Matrix6<f64> {
            self.unsure.covariance()
        }
        fn covariance_after(&self, step: &Move) -> nalgebra::Matrix6<f64> {
            self.unsure.covariance_after(step)
        }
        fn m_f_after(&self, step: &Move) -> Pose {
            let mut after = step.as_pose().inverse() * self.m_f();
            after.translation.vector.x -= self.drift_per_mm * step.translation_mm.z;
            after
        }
    }

    #[test]
    fn the_cell_centres_whether_or_not_the_controller_steers_against_the_drift() {
        let supervisor = Supervisor::new(&CellConfig::reference());
        // A 4 mm move deeper carries Segment I 0.02 mm towards −x.
        let belief = Drifting {
            unsure: Unsure(inserted_off_axis(), 0.004),
            drift_per_mm: 0.005,
        };
        // One controller steers against the drift: −0.02 mm commanded is −0.04 mm done. The
        // other asks for the sideways move it wants and overshoots by the drift. Each move
        // brings the grown shaft no nearer the wall along it and leaves the seat's gap open,
        // so it is made whole (decision 0042); where it really ends, x mm off the axis:
        for (asked, off_after_mm) in [
            (Move::translation(-0.02, 0.0, -4.0), 0.0),
            (Move::translation(-0.04, 0.0, -4.0), -0.02),
        ] {
            let mut recorder = Recorder::default();
            let mut robot = Supervised::new(&supervisor, &mut recorder);
            robot.observe(Some(&belief));
            let executed = robot
                .execute_cautiously(&asked)
                .expect("centring is allowed");
            let ends_mm = belief.m_f_after(&executed).inverse().translation.vector.x;
            assert!(
                executed == asked && (ends_mm - off_after_mm).abs() < 1e-9,
                "{asked:?} gave {executed:?}, ending {ends_mm} mm off the axis"
            );
        }
    }

    #[test]
    fn above_the_entrance_the_sideways_part_that_centres_the_tip_is_made() {
        let supervisor = Supervisor::new(&CellConfig::reference());
        // The tip 0.07 mm above the entrance and 0.04 mm off the axis, σ 0.004 mm sideways:
        // going in now would start 0.01 mm from the wall, too near for the bound, at every
        // share of the move. A 4 mm move deeper carries Segment I 0.04 mm towards −x, so the
        // move's sideways part as the drift would take it goes 0.08 mm, past the axis by 0.04;
        // as commanded it centres. Above the bore the gap below the tip is the same for both.
        let belief = Drifting {
            unsure: Unsure(Isometry3::translation(0.04, 0.0, 60.07).inverse(), 0.004),
            drift_per_mm: 0.01,
        };
        let mut recorder = Recorder::default();
        let mut robot = Supervised::new(&supervisor, &mut recorder);
        robot.observe(Some(&belief));
        assert!(!robot.tip_in_the_bore());
        let centre_and_go_in = Move::translation(-0.04, 0.0, -4.0);
        let made = robot
            .execute_cautiously(&centre_and_go_in)
            .expect("a centring above the bore is allowed");
        let ends_mm = belief.m_f_after(&made).inverse().translation.vector.x;
        assert!(
            made == Move::translation(-0.04, 0.0, 0.0) && ends_mm.abs() < 1e-9,
            "made {made:?}, ending {ends_mm} mm off the axis"
        );
    }

    #[test]
    fn a_steering_move_too_near_the_wall_is_shortened_and_a_straight_one_refused() {
        let supervisor = Supervisor::new(&CellConfig::reference());
        // 0.025 mm off the axis (0.025 mm from the wall), well known; 4 mm deeper carries
        // Segment I 0.008 mm further towards the wall, under the 0.02 mm margin.
        let belief = Drifting {
            unsure: Unsure(Isometry3::translation(0.025, 0.0, 30.0).inverse(), 1e-4),
            drift_per_mm: -0.002,
        };
        let mut recorder = Recorder::default();
        let mut robot = Supervised::new(&supervisor, &mut recorder);
        robot.observe(Some(&belief));
        // A move that steers is shortened to the longest share that stays outside the margin:
        // 0.8 of it ends 0.0194 mm from the wall, 0.6 of it 0.0208 mm.
        let steering = Move::translation(-0.001, 0.0, -4.0);
        assert_eq!(
            robot.execute_cautiously(&steering),
            Ok(steering.scaled(0.6))
        );
        // A move straight along the axis is refused as it is: a controller that searches by
        // the supervisor's refusals (`spiral`) is told.
        let straight = Move::translation(0.0, 0.0, -4.0);
        assert!(matches!(
            robot.execute_cautiously(&straight),
            Err(RobotError::Vetoed(reason)) if reason.code() == "wall_margin"
        ));
        assert_eq!(recorder.executed, vec![steering.scaled(0.6)]);
    }

    #[test]
    fn in_the_bore_a_centring_that_leaves_more_room_is_made_beyond_the_bound() {
        let supervisor = Supervisor::new(&CellConfig::reference());
        let mut recorder = Recorder::default();
        let mut robot = Supervised::new(&supervisor, &mut recorder);
        // 0.04 mm off the axis, 30 mm into the bore, σ 0.004 mm sideways. Centring by
        // 0.01 mm starts 0.01 mm from the wall, so its probability of contact (about 3e-3) is
        // above the bound, but it ends 0.02 mm from the wall, 5 σ, and adds no risk to where
        // the shaft stands: it is made. By 0.005 mm it ends 0.015 mm from the wall, under the
        // 4.57 σ the supervisor wants for its bound of 1e-4, and the whole move is refused.
        let belief = Unsure(inserted_off_axis(), 0.004);
        robot.observe(Some(&belief));
        assert!(robot.tip_in_the_bore());
        let a_little = Move::translation(-0.005, 0.0, -4.0);
        assert!(matches!(
            robot.execute_cautiously(&a_little),
            Err(RobotError::Vetoed(reason)) if reason.code() == "uncertain"
        ));
        // By 0.01 mm the move is made whole: no nearer the wall along it, the seat's gap open
        // (decision 0042).
        let more = Move::translation(-0.01, 0.0, -4.0);
        let centred = robot
            .execute_cautiously(&more)
            .expect("the centring is made");
        let expected = more;
        assert!(
            (centred.to_array().iter().zip(expected.to_array()))
                .all(|(a, b)| (a - b).abs() < 1e-12),
            "{centred:?}"
        );
        // Above the entrance the rule does not act: 1 mm above it the tip is not in the bore.
        let above = Exact(Isometry3::translation(0.04, 0.0, 61.0).inverse());
        robot.observe(Some(&above));
        assert!(!robot.tip_in_the_bore());
        assert_eq!(recorder.executed, vec![centred]);
    }
}
