//! Visual servoing as the paper's baseline describes it (§4.2, after its ref. [22]): bring
//! Segment I to a mooring point in front of the bore, take several captures there and adjust the
//! pose from their average, then dock by pure translation along the bore axis. No feedback during
//! the docking itself, except a final averaged check of the depth.

use super::{Controller, Decision, clamp_components};
use crate::config::cell::CellConfig;
use crate::geometry::Move;
use crate::sim::Observation;
use nalgebra::Vector3;

/// Height of the tip above the entrance at the mooring point (mm).
const MOORING_STANDOFF_MM: f64 = 10.0;
/// Captures averaged at the mooring point and before the final depth correction.
const CAPTURES: usize = 4;
/// Averaged errors below which the mooring adjustment is done.
const LATERAL_TOLERANCE_MM: f64 = 0.01;
const ORIENTATION_TOLERANCE_DEG: f64 = 0.02;
/// Adjustment rounds at the mooring point before docking regardless.
const MAX_ROUNDS: u32 = 4;

#[derive(Debug, Clone, PartialEq)]
enum Phase {
    /// Single captures, full corrections: orientation, then position, to the mooring point.
    Coarse,
    /// Holding at the mooring point and averaging captures.
    Mooring { rounds: u32 },
    /// Open-loop translation along the axis; `remaining_mm` still to go (negative = towards
    /// the bore, as a {M} z move).
    Docking { remaining_mm: f64 },
    /// Averaging captures to correct the final depth.
    Final { rounds: u32 },
}

pub struct VisualServo {
    limit_mm: f64,
    limit_deg: f64,
    shaft_length_mm: f64,
    phase: Phase,
    captures: Vec<[f64; 12]>,
    last_move: Move,
}

impl VisualServo {
    pub fn new(cell: &CellConfig) -> Self {
        VisualServo {
            limit_mm: cell.steps.position_mm,
            limit_deg: cell.steps.orientation_deg,
            shaft_length_mm: cell.shaft.engaged_length_mm,
            phase: Phase::Coarse,
            captures: Vec::with_capacity(CAPTURES),
            last_move: Move::default(),
        }
    }

    fn mooring_point(&self) -> Vector3<f64> {
        Vector3::new(0.0, 0.0, -(self.shaft_length_mm + MOORING_STANDOFF_MM))
    }

    fn average(&self) -> (Vector3<f64>, Vector3<f64>) {
        let n = self.captures.len() as f64;
        let mut p = Vector3::zeros();
        let mut o = Vector3::zeros();
        for s in &self.captures {
            p += Vector3::new(s[6], s[7], s[8]) / n;
            o += Vector3::new(s[9], s[10], s[11]) / n;
        }
        (p, o)
    }

    fn rotate(&self, o: Vector3<f64>) -> Move {
        Move {
            translation_mm: Vector3::zeros(),
            rotation_deg: clamp_components(o, self.limit_deg),
        }
    }

    fn translate(&self, delta: Vector3<f64>) -> Move {
        Move {
            translation_mm: clamp_components(delta, self.limit_mm),
            rotation_deg: Vector3::zeros(),
        }
    }

    fn decide(&mut self, observation: &Observation) -> Move {
        let s = &observation.state;
        let p = Vector3::new(s[6], s[7], s[8]);
        let o = Vector3::new(s[9], s[10], s[11]);
        match self.phase.clone() {
            Phase::Coarse => {
                let to_mooring = p - self.mooring_point();
                if o.norm() > 0.05 {
                    self.rotate(o)
                } else if to_mooring.norm() > 0.2 {
                    self.translate(to_mooring)
                } else {
                    self.phase = Phase::Mooring { rounds: 0 };
                    self.captures.clear();
                    self.decide(observation)
                }
            }
            Phase::Mooring { rounds } => {
                self.captures.push(*s);
                if self.captures.len() < CAPTURES {
                    return Move::default();
                }
                let (p, o) = self.average();
                self.captures.clear();
                let to_mooring = p - self.mooring_point();
                let done = rounds >= MAX_ROUNDS;
                self.phase = Phase::Mooring { rounds: rounds + 1 };
                if !done && o.norm() > ORIENTATION_TOLERANCE_DEG {
                    self.rotate(o)
                } else if !done && to_mooring.xy().norm() > LATERAL_TOLERANCE_MM {
                    self.translate(to_mooring)
                } else {
                    // Dock from here: the averaged P_z is how far the shoulder is from home.
                    self.phase = Phase::Docking { remaining_mm: p.z };
                    self.decide(observation)
                }
            }
            Phase::Docking { remaining_mm } => {
                if remaining_mm.abs() < 1e-9 {
                    self.phase = Phase::Final { rounds: 0 };
                    self.captures.clear();
                    return self.decide(observation);
                }
                self.translate(Vector3::new(0.0, 0.0, remaining_mm))
            }
            Phase::Final { rounds } => {
                self.captures.push(*s);
                if self.captures.len() < CAPTURES {
                    return Move::default();
                }
                let (p, _) = self.average();
                self.captures.clear();
                self.phase = Phase::Final { rounds: rounds + 1 };
                if rounds < MAX_ROUNDS && p.z.abs() > 0.01 {
                    self.translate(Vector3::new(0.0, 0.0, p.z))
                } else {
                    Move::default()
                }
            }
        }
    }
}

impl Controller for VisualServo {
    fn name(&self) -> &str {
        "visual-servo"
    }

    fn reset(&mut self, _seed: u64) {
        self.phase = Phase::Coarse;
        self.captures.clear();
        self.last_move = Move::default();
    }

    fn act(&mut self, observation: &Observation) -> Decision {
        // Dead reckoning of the docking: count only the moves that were executed.
        if observation.last_veto.is_none()
            && let Phase::Docking { remaining_mm } = &mut self.phase
        {
            *remaining_mm -= self.last_move.translation_mm.z;
        }
        let action = if observation.measurement_fresh {
            self.decide(observation)
        } else {
            Move::default()
        };
        self.last_move = action;
        Decision::plain(action)
    }
}
