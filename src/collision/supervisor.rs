//! The collision supervisor: checks the pose a move would lead to *before* the robot sees it.
//!
//! Order of checks (cheapest and most fundamental first): finite numbers, step limits, a fresh
//! measurement, reachability (IK, leg stroke, singularity) in the robot's nominal model, then the
//! OBB broad phase (paper, 15 axes) and the exact shaft-in-bore clearance along the move. The
//! answer is allow (with the target platform pose and leg lengths) or a veto with its reason.
//! The paper's rule lives with the caller: a vetoed move is dropped, the state is read again and a
//! new move is asked for; too many vetoes in a row fail the episode.

use super::clearance::{Clearance, ContactKind, PartGeometry, clearance_along};
use super::obb::Obb;
use crate::config::cell::CellConfig;
use crate::geometry::{CellFrames, Move, Pose, pose};
use crate::kinematics::{KinematicsError, StewartGeometry};
use nalgebra::Vector3;

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
    #[error("unreachable: {0}")]
    Kinematics(KinematicsError),
    #[error("predicted {kind:?} contact: clearance {clearance_mm:.4} mm")]
    Collision {
        kind: ContactKind,
        clearance_mm: f64,
    },
}

impl VetoReason {
    /// A short stable code, for counting vetoes by reason (metrics, storage, reports).
    pub fn code(&self) -> &'static str {
        match self {
            VetoReason::NonFinite { .. } => "non_finite",
            VetoReason::StepLimit { .. } => "step_limit",
            VetoReason::StaleMeasurement => "stale_measurement",
            VetoReason::Kinematics(e) => e.code(),
            VetoReason::Collision { .. } => "collision",
        }
    }
}

/// What the supervisor lets through: where the platform goes and the legs that take it there.
#[derive(Debug, Clone, PartialEq)]
pub struct Allowed {
    pub target_platform: Pose,
    pub legs_mm: [f64; 6],
    /// Predicted smallest clearance along the move (mm); infinite when the parts are far apart.
    pub clearance_mm: f64,
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
}

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
        }
    }

    pub fn parts(&self) -> &PartGeometry {
        &self.parts
    }

    pub fn bore_obb(&self) -> &Obb {
        &self.bore_obb
    }

    /// Checks `step`, given the robot's platform setpoint (in its nominal model) and the camera's
    /// latest measurement of {F} in {M} (`None` when stale).
    pub fn check(&self, setpoint: &Pose, measured_m_f: Option<&Pose>, step: &Move) -> Verdict {
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
        let m_f = measured_m_f.ok_or(VetoReason::StaleMeasurement)?;
        if !pose::is_finite(m_f) {
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
        let to = from * step_pose;
        let clearance_mm = self.predicted_clearance(&from, &to)?;
        Ok(Allowed {
            target_platform,
            legs_mm,
            clearance_mm,
        })
    }

    /// The predicted clearance along the move, vetoing a predicted contact.
    fn predicted_clearance(&self, from: &Pose, to: &Pose) -> Result<f64, VetoReason> {
        let clearance = swept_clearance(&self.parts, &self.bore_obb, from, to);
        match clearance.contact_kind() {
            Some(kind) => Err(VetoReason::Collision {
                kind,
                clearance_mm: clearance.min_mm(),
            }),
            None => Ok(clearance.min_mm()),
        }
    }
}

/// Clearance of Segment I moving from `from` to `to` (poses of {M} in {F}). Broad phase first: an
/// OBB of the shaft at the end of the move, grown by how far any of its points can travel during
/// the move, against Segment II's OBB; only if they overlap is the exact clearance along the move
/// computed. Far apart, both gaps are reported as infinite.
pub fn swept_clearance(parts: &PartGeometry, bore_obb: &Obb, from: &Pose, to: &Pose) -> Clearance {
    let relative = from.inverse() * to;
    let reach_mm = parts.shaft_length_mm.max(parts.body_radius_mm) * 2.0;
    let sweep_mm = relative.translation.vector.norm() + reach_mm * relative.rotation.angle();
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
    clearance_along(parts, from, to)
}
