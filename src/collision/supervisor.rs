//! The collision supervisor: checks the pose a move would lead to *before* the robot sees it.
//!
//! Order of checks (cheapest and most fundamental first): finite numbers, step limits, a fresh
//! estimate, reachability (IK, leg stroke, singularity) in the robot's nominal model, then the
//! OBB broad phase (paper, 15 axes) and the exact shaft-in-bore clearance along the move from
//! the mean estimate, then the chance constraint: the move is allowed only if the probability
//! of contact along it, under the estimate's distribution, is below the cell's bound
//! (`supervisor.contact_risk_per_move`, docs/estimation.md). A move the cell cannot be sure
//! enough of is refused as `uncertain`: the cell holds for more frames. The answer is allow
//! (with the target platform pose and leg lengths) or a veto with its reason.
//! The paper's rule lives with the caller: a vetoed move is dropped, the state is read again and a
//! new move is asked for; too many vetoes in a row fail the episode.

use super::clearance::{
    Clearance, ContactKind, Growth, PartGeometry, clearance, clearance_along_grown, clearance_grown,
};
use super::obb::Obb;
use super::risk;
use crate::config::cell::CellConfig;
use crate::geometry::belief::largest_sd;
use crate::geometry::{Belief, CellFrames, Move, Pose, pose};
use crate::kinematics::{KinematicsError, StewartGeometry};
use nalgebra::Vector3;
use nalgebra::{Matrix2x6, Matrix6};

/// Why a move was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum VetoReason {
    #[error("non-finite {what}")]
    NonFinite { what: &'static str },
    #[error("{axis} step {value:.4} exceeds the limit {limit:.4}")]
    StepLimit {
        axis: &'static str,
        value: f64,
        limit: f64,
    },
    #[error("no fresh camera measurement")]
    StaleMeasurement,
    /// Not sure enough of the move: hold for more frames.
    #[error(
        "contact risk {risk:.1e} along the move is above the bound {bound:.0e} (clearance {clearance_mm:.4} mm by the estimate): holding for more frames"
    )]
    Uncertain {
        risk: f64,
        bound: f64,
        clearance_mm: f64,
    },
    #[error("unreachable: {0}")]
    Kinematics(KinematicsError),
    #[error("predicted {kind:?} contact: clearance {clearance_mm:.4} mm")]
    Collision {
        kind: ContactKind,
        clearance_mm: f64,
    },
    #[error(
        "predicted wall clearance {clearance_mm:.4} mm is below the margin {margin_mm:.4} mm (and below the {start_mm:.4} mm at the start of the move)"
    )]
    WallMargin {
        clearance_mm: f64,
        margin_mm: f64,
        start_mm: f64,
    },
}

impl VetoReason {
    /// A short stable code, for counting vetoes by reason (metrics, storage, reports).
    pub fn code(&self) -> &'static str {
        match self {
            VetoReason::NonFinite { .. } => "non_finite",
            VetoReason::StepLimit { .. } => "step_limit",
            VetoReason::StaleMeasurement => "stale_measurement",
            VetoReason::Uncertain { .. } => "uncertain",
            VetoReason::Kinematics(e) => e.code(),
            VetoReason::Collision { .. } => "collision",
            VetoReason::WallMargin { .. } => "wall_margin",
        }
    }

    /// The move was refused for the parts' sake (a predicted contact, or too near the wall),
    /// not for the robot's or the data's.
    pub fn is_about_contact(&self) -> bool {
        matches!(
            self,
            VetoReason::Collision { .. } | VetoReason::WallMargin { .. }
        )
    }
}

/// What the supervisor lets through: where the platform goes and the legs that take it there.
#[derive(Debug, Clone, PartialEq)]
pub struct Allowed {
    pub target_platform: Pose,
    pub legs_mm: [f64; 6],
    /// Smallest clearance (mm) found along the move after its start (the end pose, the entrance
    /// crossing and the sub-moves examined), by the mean estimate; infinite when the parts are
    /// far apart.
    pub clearance_mm: f64,
    /// The estimated probability of contact along the move (see [`risk::contact_risk`]).
    pub contact_risk: f64,
}

pub type Verdict = Result<Allowed, VetoReason>;

/// Checks moves against the cell's nominal robot model and part geometry.
#[derive(Debug, Clone)]
pub struct Supervisor {
    robot: StewartGeometry,
    frames: CellFrames,
    parts: PartGeometry,
    bore_obb: Obb,
    step_limit_mm: f64,
    step_limit_deg: f64,
    wall_margin_mm: f64,
    /// The bound on the probability of contact per move.
    risk_bound: f64,
    /// How many σ of each error the envelope of `Supervisor::spread` spans for that bound.
    sigmas: f64,
}

/// A move that keeps the wall gap where it was is not refused for closing it by rounding.
const GAP_ROUNDING_MM: f64 = 1e-6;

impl Supervisor {
    pub fn new(cell: &CellConfig) -> Self {
        let parts = PartGeometry::from_config(cell);
        Supervisor {
            robot: StewartGeometry::from_config(&cell.robot),
            frames: CellFrames::from_config(cell),
            bore_obb: parts.bore_obb(),
            parts,
            step_limit_mm: cell.steps.position_mm,
            step_limit_deg: cell.steps.orientation_deg,
            wall_margin_mm: cell.supervisor.wall_margin_mm,
            risk_bound: cell.supervisor.contact_risk_per_move,
            sigmas: risk::sigmas_for(cell.supervisor.contact_risk_per_move),
        }
    }

    /// The bound on the probability of contact per move.
    pub fn risk_bound(&self) -> f64 {
        self.risk_bound
    }

    pub fn parts(&self) -> &PartGeometry {
        &self.parts
    }

    pub fn bore_obb(&self) -> &Obb {
        &self.bore_obb
    }

    /// Checks `step`, given the robot's platform setpoint (in its nominal model) and the cell's
    /// latest estimate of {F} in {M} with its uncertainty (`None` when stale).
    pub fn check(&self, setpoint: &Pose, belief: Option<&dyn Belief>, step: &Move) -> Verdict {
        if !step.is_finite() {
            return Err(VetoReason::NonFinite { what: "action" });
        }
        let (max_mm, max_deg) = step.max_components();
        // A hair of tolerance so that a move exactly at the limit survives rounding.
        if max_mm > self.step_limit_mm * (1.0 + 1e-9) {
            return Err(VetoReason::StepLimit {
                axis: "position (mm)",
                value: max_mm,
                limit: self.step_limit_mm,
            });
        }
        if max_deg > self.step_limit_deg * (1.0 + 1e-9) {
            return Err(VetoReason::StepLimit {
                axis: "orientation (deg)",
                value: max_deg,
                limit: self.step_limit_deg,
            });
        }
        let belief = belief.ok_or(VetoReason::StaleMeasurement)?;
        let m_f = belief.m_f();
        let covariances = [belief.covariance(), belief.covariance_after(step)];
        if !pose::is_finite(&m_f) || covariances.iter().flatten().any(|v| !v.is_finite()) {
            return Err(VetoReason::NonFinite {
                what: "measurement",
            });
        }
        if !pose::is_finite(setpoint) {
            return Err(VetoReason::NonFinite {
                what: "platform pose",
            });
        }
        let step_pose = step.as_pose();
        let target_platform = setpoint * self.frames.p_m * step_pose * self.frames.p_m.inverse();
        let legs_mm = self
            .robot
            .inverse_checked(&target_platform)
            .map_err(VetoReason::Kinematics)?;
        let from = m_f.inverse();
        // Where the move really takes Segment I by the estimate: the command bent by the drift
        // the cell has learned (a controller that does not steer against it is judged on where
        // it will really go).
        let to = belief.m_f_after(step).inverse();
        let along = self.predicted_clearance(&from, &to)?;
        let contact_risk = self.judge_risk(&m_f, &to, &along, &covariances)?;
        Ok(Allowed {
            target_platform,
            legs_mm,
            clearance_mm: along.min_mm(),
            contact_risk,
        })
    }

    /// The chance constraint. Every point of Segment I lies within `sigmas` × `Supervisor::spread` of
    /// where the mean estimate puts it, except with probability below the bound; so if the
    /// shaft grown by that much is clear all along the move, the move is allowed. A move that
    /// leaves the grown shaft no nearer Segment II than it is now is allowed too: it adds no risk
    /// to where the cell already stands (this is how the cell backs away from a wall it is
    /// unsure of); it is judged with the move's own error, against the envelope of the estimate
    /// as it is now, on each gap the grown shaft closes (decision 0042). Otherwise the move is
    /// refused as uncertain.
    fn judge_risk(
        &self,
        m_f: &Pose,
        to: &Pose,
        along: &Clearance,
        covariances: &[Matrix6<f64>; 2],
    ) -> Result<f64, VetoReason> {
        if along.wall_mm.is_infinite() && along.seat_mm.is_infinite() {
            return Ok(0.0);
        }
        let from = &m_f.inverse();
        let spread = self.spread(m_f, to, covariances);
        let risk = risk::contact_risk(along, &spread);
        let growth = spread.scaled(self.sigmas);
        let grown = swept_clearance_grown(&self.parts, &self.bore_obb, from, to, &growth);
        if grown.is_clear() {
            return Ok(risk.min(self.risk_bound));
        }
        // Where the cell stands now: the envelope of the estimate now, at the depth it is at.
        let standing = self.spread(m_f, from, &[covariances[0], covariances[0]]);
        let now = clearance_grown(&self.parts, from, &standing.scaled(self.sigmas));
        // A gap the grown shaft keeps open (the seat far below while the shaft centres at the
        // wall) adds no risk, however little it narrows; only a gap it closes must not narrow.
        let no_nearer = |after: f64, before: f64| after > 0.0 || after >= before - GAP_ROUNDING_MM;
        // Backing away is worth its risk only to a place the cell is sure of: where the estimate
        // is so uncertain that even there the grown shaft would touch, the cell holds, and its
        // frames make it surer, rather than move on a mean that may be far off.
        let ends_sure = || {
            let after = self.spread(m_f, to, &[covariances[1], covariances[1]]);
            clearance_grown(&self.parts, to, &after.scaled(self.sigmas)).is_clear()
        };
        if no_nearer(grown.wall_mm, now.wall_mm)
            && no_nearer(grown.seat_mm, now.seat_mm)
            && ends_sure()
        {
            return Ok(risk);
        }
        Err(VetoReason::Uncertain {
            risk: risk.max(self.risk_bound),
            bound: self.risk_bound,
            clearance_mm: along.min_mm(),
        })
    }

    /// σ of how far any point of Segment I may be from where the estimate puts it, sideways and
    /// along the bore axis, during the move from the estimate `m_f` ({F} in {M}) to `to` ({M} in
    /// {F} after it), for estimate errors of covariance `covariances` (now and after the move;
    /// along the move the variance in any direction is convex in the share moved, so these two
    /// bound it). An error (δP, δθ) moves a point q of the shaft (in {M}, relative to the
    /// bore's entrance centre P) by δP + δθ × q. Sideways, for a point on the axis inside the
    /// bore (q = (−P_x, −P_y, z), z from minus the depth to 0) that is a linear function of the
    /// errors whose 2×2 covariance is computed exactly; it is largest at one end of the axis (it
    /// is affine in z). A point of the tip rim or the shoulder moves along the axis by at most
    /// its radius × the tilt error. A twist about the shaft's own axis maps the shaft onto itself.
    fn spread(&self, m_f: &Pose, to: &Pose, covariances: &[Matrix6<f64>; 2]) -> risk::Spread {
        let parts = &self.parts;
        let from = m_f.inverse();
        let depth = |f_m: &Pose| parts.tip_depth_mm(f_m).clamp(0.0, parts.shaft_length_mm);
        let lever_mm = depth(&from).max(depth(to));
        let (a, b) = (-m_f.translation.vector.x, -m_f.translation.vector.y);
        let sideways_at = |c: &Matrix6<f64>, z: f64| {
            let j = Matrix2x6::new(1.0, 0.0, 0.0, 0.0, z, -b, 0.0, 1.0, 0.0, -z, 0.0, a);
            largest_sd(&(j * c * j.transpose()))
        };
        let mut sideways = 0.0f64;
        let mut axial_sd = 0.0f64;
        let mut tilt = 0.0f64;
        for c in covariances {
            sideways = sideways
                .max(sideways_at(c, 0.0))
                .max(sideways_at(c, -lever_mm));
            axial_sd = axial_sd.max(c[(2, 2)].max(0.0).sqrt());
            tilt = tilt.max(largest_sd(&c.fixed_view::<2, 2>(3, 3).into_owned()));
        }
        let axial = axial_sd + parts.shaft_radius_mm * tilt;
        let seat = axial_sd + parts.body_radius_mm.max(parts.shaft_radius_mm) * tilt;
        // The estimate's errors are in {M}; the shaft's axis is tilted from the bore's by up to
        // α, which mixes a little of each direction into the other.
        let sin_tilt = |f_m: &Pose| (f_m.rotation * nalgebra::Vector3::z()).xy().norm();
        let mix = sin_tilt(&from).max(sin_tilt(to));
        risk::Spread {
            sideways_mm: sideways + mix * axial,
            axial_mm: axial + mix * sideways,
            seat_mm: seat + mix * sideways,
        }
    }

    /// The predicted clearance along the move by the mean estimate, vetoing a predicted contact,
    /// or a wall gap under the margin that the move would close further.
    fn predicted_clearance(&self, from: &Pose, to: &Pose) -> Result<Clearance, VetoReason> {
        let along = swept_clearance(&self.parts, &self.bore_obb, from, to);
        if let Some(kind) = along.contact_kind() {
            return Err(VetoReason::Collision {
                kind,
                clearance_mm: along.min_mm(),
            });
        }
        if along.wall_mm < self.wall_margin_mm {
            let start_mm = clearance(&self.parts, from).wall_mm;
            if along.wall_mm < start_mm - GAP_ROUNDING_MM {
                return Err(VetoReason::WallMargin {
                    clearance_mm: along.wall_mm,
                    margin_mm: self.wall_margin_mm,
                    start_mm,
                });
            }
        }
        Ok(along)
    }
}

/// Clearance of Segment I moving from `from` to `to` (poses of {M} in {F}). Broad phase first: an
/// OBB of the shaft at the end of the move, grown by how far any of its points can travel during
/// the move, against Segment II's OBB; only if they overlap is the exact clearance along the move
/// computed. Far apart, both gaps are reported as infinite.
pub fn swept_clearance(parts: &PartGeometry, bore_obb: &Obb, from: &Pose, to: &Pose) -> Clearance {
    swept_clearance_grown(parts, bore_obb, from, to, &Growth::default())
}

/// [`swept_clearance`] of the shaft grown by `growth` (see [`clearance_along_grown`]).
pub fn swept_clearance_grown(
    parts: &PartGeometry,
    bore_obb: &Obb,
    from: &Pose,
    to: &Pose,
    growth: &Growth,
) -> Clearance {
    let relative = from.inverse() * to;
    let reach_mm = parts.shaft_length_mm.max(parts.body_radius_mm) * 2.0;
    let sweep_mm = relative.translation.vector.norm()
        + reach_mm * relative.rotation.angle()
        + growth.sideways_mm.max(growth.axial_mm).max(growth.seat_mm);
    let end = parts.shaft_obb(to);
    let swept = Obb {
        edges_mm: end.edges_mm + Vector3::repeat(2.0 * sweep_mm),
        ..end
    };
    if !swept.intersects(bore_obb) {
        return Clearance {
            wall_mm: f64::INFINITY,
            seat_mm: f64::INFINITY,
        };
    }
    clearance_along_grown(parts, from, to, growth)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{Exact, PoseSd};
    use nalgebra::Isometry3;

    fn setup() -> (Supervisor, Pose) {
        let cell = CellConfig::reference();
        let supervisor = Supervisor::new(&cell);
        let home = Isometry3::translation(0.0, 0.0, cell.robot.home_height_mm);
        (supervisor, home)
    }

    /// {F} in {M} for Segment I inserted `depth` mm, `x` mm off the axis.
    fn inserted(depth: f64, x: f64) -> Pose {
        Isometry3::translation(x, 0.0, 60.0 - depth).inverse()
    }

    #[test]
    fn a_move_towards_the_axis_is_allowed_and_one_into_the_wall_is_vetoed() {
        let (supervisor, home) = setup();
        let m_f = inserted(30.0, 0.04);
        let allowed = supervisor
            .check(
                &home,
                Some(&Exact(m_f)),
                &Move::translation(-0.03, 0.0, -1.0),
            )
            .unwrap();
        // From 0.04 mm off the axis (0.01 mm of the 0.05 mm radial clearance left) to 0.01 mm
        // off (0.04 mm left): the smallest clearance seen along the way lies between.
        let c = allowed.clearance_mm;
        assert!((0.01 - 1e-9..=0.04 + 1e-9).contains(&c), "{c}");
        let veto = supervisor
            .check(&home, Some(&Exact(m_f)), &Move::translation(0.02, 0.0, 0.0))
            .unwrap_err();
        assert_eq!(veto.code(), "collision");
        assert!(
            matches!(veto, VetoReason::Collision { kind: ContactKind::Wall, clearance_mm } if clearance_mm < 0.0)
        );
    }

    /// A pose known exactly, on a robot that drifts `drift` mm along x of {M} per mm moved
    /// along its z: a calibration error the estimate has learned.
    struct Drifting {
        m_f: Pose,
        drift: f64,
    }

    impl Belief for Drifting {
        fn m_f(&self) -> Pose {
            self.m_f
        }
        fn covariance(&self) -> Matrix6<f64> {
            Matrix6::zeros()
        }
        fn covariance_after(&self, _step: &Move) -> Matrix6<f64> {
            Matrix6::zeros()
        }
        fn m_f_after(&self, step: &Move) -> Pose {
            let sideways = self.drift * step.translation_mm.z;
            let bent = Move::translation(
                step.translation_mm.x + sideways,
                step.translation_mm.y,
                step.translation_mm.z,
            );
            bent.as_pose().inverse() * self.m_f
        }
    }

    #[test]
    fn a_move_is_judged_where_the_learned_drift_takes_it() {
        let (supervisor, home) = setup();
        // Centred 10 mm in. 5 mm deeper on a robot that drifts 0.012 mm per mm moves the shaft
        // 0.06 mm sideways, beyond the 0.05 mm radial clearance: the command alone would be
        // clear, where the robot really goes is not. Steering against the drift is allowed.
        let drifting = Drifting {
            m_f: inserted(10.0, 0.0),
            drift: 0.012,
        };
        let deeper = Move::translation(0.0, 0.0, -5.0);
        assert!(
            supervisor
                .check(&home, Some(&Exact(drifting.m_f)), &deeper)
                .is_ok()
        );
        let veto = supervisor
            .check(&home, Some(&drifting), &deeper)
            .unwrap_err();
        assert_eq!(veto.code(), "collision");
        let steered = Move::translation(0.06, 0.0, -5.0);
        assert!(supervisor.check(&home, Some(&drifting), &steered).is_ok());
    }

    #[test]
    fn near_the_wall_a_move_may_not_close_the_gap_below_the_margin() {
        let (supervisor, home) = setup();
        assert_eq!(supervisor.wall_margin_mm, 0.02);
        // 0.025 mm off the axis: 0.025 mm of gap. 0.01 mm further out leaves 0.015 mm.
        let outwards = Move::translation(0.01, 0.0, -1.0);
        let veto = supervisor
            .check(&home, Some(&Exact(inserted(30.0, 0.025))), &outwards)
            .unwrap_err();
        assert_eq!(veto.code(), "wall_margin");
        match veto {
            VetoReason::WallMargin {
                clearance_mm,
                margin_mm,
                start_mm,
            } => {
                assert!((clearance_mm - 0.015).abs() < 1e-6, "{clearance_mm}");
                assert!((start_mm - 0.025).abs() < 1e-9, "{start_mm}");
                assert_eq!(margin_mm, 0.02);
            }
            other => panic!("{other:?}"),
        }
        // Already inside the margin (0.01 mm of gap): straight in keeps the gap and is allowed,
        // closing it further is not.
        let near = inserted(30.0, 0.04);
        assert!(
            supervisor
                .check(
                    &home,
                    Some(&Exact(near)),
                    &Move::translation(0.0, 0.0, -1.0)
                )
                .is_ok()
        );
        let veto = supervisor
            .check(
                &home,
                Some(&Exact(near)),
                &Move::translation(0.005, 0.0, 0.0),
            )
            .unwrap_err();
        assert_eq!(veto.code(), "wall_margin");
        // Without a margin only contact is refused.
        let mut cell = CellConfig::reference();
        cell.supervisor.wall_margin_mm = 0.0;
        let without = Supervisor::new(&cell);
        assert!(
            without
                .check(&home, Some(&Exact(inserted(30.0, 0.025))), &outwards)
                .is_ok()
        );
    }

    #[test]
    fn far_from_the_bore_the_clearance_is_not_computed() {
        let (supervisor, home) = setup();
        let m_f = Isometry3::translation(30.0, 0.0, 100.0).inverse();
        let allowed = supervisor
            .check(
                &home,
                Some(&Exact(m_f)),
                &Move::translation(-5.0, 0.0, -5.0),
            )
            .unwrap();
        assert_eq!(allowed.clearance_mm, f64::INFINITY);
    }

    #[test]
    fn stale_measurement_limits_and_non_finite_values_are_vetoed() {
        let (supervisor, home) = setup();
        let m_f = inserted(0.0, 0.0);
        let small = Move::translation(0.0, 0.0, -1.0);
        assert_eq!(
            supervisor.check(&home, None, &small),
            Err(VetoReason::StaleMeasurement)
        );
        let nan = Move::translation(f64::NAN, 0.0, 0.0);
        assert_eq!(
            supervisor
                .check(&home, Some(&Exact(m_f)), &nan)
                .unwrap_err()
                .code(),
            "non_finite"
        );
        let mut broken = m_f;
        broken.translation.vector.x = f64::INFINITY;
        assert_eq!(
            supervisor
                .check(&home, Some(&Exact(broken)), &small)
                .unwrap_err()
                .code(),
            "non_finite"
        );
        let veto = supervisor
            .check(&home, Some(&Exact(m_f)), &Move::rotation(0.0, 1.2, 0.0))
            .unwrap_err();
        assert!(
            matches!(veto, VetoReason::StepLimit { value, limit, .. } if value == 1.2 && limit == 1.0)
        );
    }

    #[test]
    fn a_target_beyond_the_leg_stroke_is_vetoed_with_the_numbers() {
        let (supervisor, home) = setup();
        // The platform 250 mm above home: every leg is past its 1050 mm maximum.
        let high = home * Isometry3::translation(0.0, 0.0, 250.0);
        let m_f = Isometry3::translation(0.0, 0.0, 400.0).inverse();
        let veto = supervisor
            .check(&high, Some(&Exact(m_f)), &Move::translation(0.0, 0.0, 1.0))
            .unwrap_err();
        match veto {
            VetoReason::Kinematics(KinematicsError::LegOutOfStroke {
                length_mm, max_mm, ..
            }) => {
                assert!(length_mm > max_mm && max_mm == 1050.0);
            }
            other => panic!("expected a stroke veto, got {other:?}"),
        }
    }

    /// An estimate with the given σ in every direction, and no move error.
    struct Spread(Pose, PoseSd);

    impl Belief for Spread {
        fn m_f(&self) -> Pose {
            self.0
        }
        fn covariance(&self) -> Matrix6<f64> {
            let sd = &self.1;
            Matrix6::from_diagonal(&nalgebra::Vector6::new(
                sd.lateral_mm.powi(2),
                sd.lateral_mm.powi(2),
                sd.axial_mm.powi(2),
                sd.tilt_rad.powi(2),
                sd.tilt_rad.powi(2),
                sd.twist_rad.powi(2),
            ))
        }
        fn covariance_after(&self, _step: &Move) -> Matrix6<f64> {
            self.covariance()
        }
    }

    /// [`Spread`] whose error grows by `growth_mm` along the bore axis over a move, as the
    /// cell's filter predicts: the axial σ after a move is a little larger than before it.
    struct GrowingAxially(Pose, PoseSd, f64);

    impl Belief for GrowingAxially {
        fn m_f(&self) -> Pose {
            self.0
        }
        fn covariance(&self) -> Matrix6<f64> {
            Spread(self.0, self.1).covariance()
        }
        fn covariance_after(&self, _step: &Move) -> Matrix6<f64> {
            let mut after = self.covariance();
            after[(2, 2)] = (self.1.axial_mm + self.2).powi(2);
            after
        }
    }

    #[test]
    fn an_unsure_shaft_at_the_wall_may_centre_though_the_far_seat_gap_narrows_by_its_growth() {
        let (supervisor, home) = setup();
        // 38 mm in, 0.02 mm off the axis (0.03 mm from the wall), the estimate unsure by 7 µm
        // sideways: the shaft grown by the chance constraint's σs touches the wall where it
        // stands, so only a move that brings it no nearer the wall is allowed. The seat is
        // 22 mm below; its gap, grown by the move's axial error (2 µm more after the move),
        // narrows by micrometres and stays wide open.
        let sd = PoseSd {
            lateral_mm: 0.007,
            axial_mm: 0.005,
            tilt_rad: 5e-5,
            twist_rad: 5e-5,
        };
        let belief = GrowingAxially(inserted(38.0, 0.02), sd, 0.002);
        let centring = Move::translation(-0.02, 0.0, 0.0);
        let verdict = supervisor.check(&home, Some(&belief), &centring);
        assert!(verdict.is_ok(), "{verdict:?}");
        // Further out is nearer the wall: refused as uncertain.
        let outwards = Move::translation(0.002, 0.0, 0.0);
        let veto = supervisor
            .check(&home, Some(&belief), &outwards)
            .unwrap_err();
        assert_eq!(veto.code(), "uncertain");
        // Going straight deeper is refused as uncertain too: it ends as near the wall, where the
        // grown shaft still touches it (the estimate is no surer there).
        let deeper = Move::translation(0.0, 0.0, -1.0);
        let veto = supervisor.check(&home, Some(&belief), &deeper).unwrap_err();
        assert_eq!(veto.code(), "uncertain");
    }

    #[test]
    fn an_allowed_move_keeps_the_contact_probability_below_the_bound_by_sampling() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, StandardNormal};
        // A bound large enough to measure by sampling: 1 in 100.
        let mut cell = CellConfig::reference();
        cell.supervisor.contact_risk_per_move = 1e-2;
        cell.supervisor.wall_margin_mm = 0.0;
        let supervisor = Supervisor::new(&cell);
        let home = Isometry3::translation(0.0, 0.0, cell.robot.home_height_mm);
        let sd = PoseSd {
            lateral_mm: 0.008,
            axial_mm: 0.01,
            tilt_rad: 6e-5,
            twist_rad: 6e-5,
        };
        let step = Move::translation(0.0, 0.0, -2.0);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        let samples = 20_000;
        let (mut allowed, mut refused) = (0, 0);
        for offset_mm in [0.0, 0.008, 0.016, 0.024, 0.028, 0.032, 0.04] {
            let m_f = inserted(30.0, offset_mm);
            let verdict = supervisor.check(&home, Some(&Spread(m_f, sd)), &step);
            let mut contacts = 0;
            for _ in 0..samples {
                let n: [f64; 6] = std::array::from_fn(|_| StandardNormal.sample(&mut rng));
                let mut truth = m_f;
                truth.translation.vector += nalgebra::Vector3::new(
                    n[0] * sd.lateral_mm,
                    n[1] * sd.lateral_mm,
                    n[2] * sd.axial_mm,
                );
                truth.rotation =
                    nalgebra::UnitQuaternion::from_scaled_axis(nalgebra::Vector3::new(
                        n[3] * sd.tilt_rad,
                        n[4] * sd.tilt_rad,
                        n[5] * sd.twist_rad,
                    )) * truth.rotation;
                let from = truth.inverse();
                let to = from * step.as_pose();
                if !super::super::clearance::clearance_along(supervisor.parts(), &from, &to)
                    .is_clear()
                {
                    contacts += 1;
                }
            }
            let sampled = contacts as f64 / samples as f64;
            // Three binomial standard errors at the bound.
            let slack = 3.0 * (1e-2 / samples as f64).sqrt();
            match verdict {
                Ok(allow) => {
                    allowed += 1;
                    assert!(sampled <= 1e-2 + slack, "{offset_mm} mm: sampled {sampled}");
                    assert!(
                        allow.contact_risk + slack >= sampled,
                        "{offset_mm} mm: claimed {} against sampled {sampled}",
                        allow.contact_risk
                    );
                }
                Err(VetoReason::Uncertain { risk, .. }) => {
                    refused += 1;
                    assert!(risk > 1e-2);
                }
                Err(other) => panic!("{offset_mm} mm: {other}"),
            }
        }
        // Both sides of the bound were exercised.
        assert!(
            allowed >= 2 && refused >= 2,
            "{allowed} allowed, {refused} refused"
        );
    }
}
