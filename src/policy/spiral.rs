//! Spiral search as the paper's baseline describes it (§4.2, after its ref. [add13], with the
//! force sensor replaced by vision): coarse visual positioning just in front of the entrance, then
//! a discrete spiral x_s = r cos θ, y_s = r sin θ in the xy-plane of a frame {S} at the starting
//! position (θ grows by δθ each step, r by δr after every full turn). After each spiral move the
//! shaft advances a small step along z; while no collision is detected (no supervisor veto) it
//! keeps advancing, and when one is detected it retreats and resumes the spiral. The episode's
//! 300-step limit bounds the search.

use super::{Controller, Decision, clamp_components};
use crate::config::cell::CellConfig;
use crate::geometry::Move;
use crate::sim::Observation;
use nalgebra::Vector3;

/// Height of the tip above the entrance where the spiral starts (mm).
const START_STANDOFF_MM: f64 = 2.0;
/// Angle step δθ (deg) and radius growth δr per full turn (mm).
const DELTA_THETA_DEG: f64 = 45.0;
const DELTA_R_MM: f64 = 0.01;
/// z advance after a spiral move, and the retreat after a collision warning (mm).
const ADVANCE_MM: f64 = 1.0;

#[derive(Debug, Clone, Copy, PartialEq)]
enum Phase {
    Coarse,
    /// Spiral step `k`, at spiral point (x, y) relative to {S}.
    Spiral {
        k: u32,
        x: f64,
        y: f64,
    },
    /// Advancing along z after a spiral move that was not vetoed.
    Advance {
        k: u32,
        x: f64,
        y: f64,
    },
}

pub struct SpiralSearch {
    limit_mm: f64,
    limit_deg: f64,
    shaft_length_mm: f64,
    phase: Phase,
}

impl SpiralSearch {
    pub fn new(cell: &CellConfig) -> Self {
        SpiralSearch {
            limit_mm: cell.steps.position_mm,
            limit_deg: cell.steps.orientation_deg,
            shaft_length_mm: cell.shaft.engaged_length_mm,
            phase: Phase::Coarse,
        }
    }

    fn spiral_point(k: u32) -> (f64, f64) {
        let theta = (f64::from(k) * DELTA_THETA_DEG).to_radians();
        let turns = (f64::from(k) * DELTA_THETA_DEG / 360.0).floor();
        let r = turns * DELTA_R_MM;
        (r * theta.cos(), r * theta.sin())
    }

    /// A move to spiral point k + 1 from (x, y), with a z component.
    fn next_spiral(&mut self, k: u32, x: f64, y: f64, dz: f64) -> Move {
        let (nx, ny) = Self::spiral_point(k + 1);
        self.phase = Phase::Spiral {
            k: k + 1,
            x: nx,
            y: ny,
        };
        Move::translation(nx - x, ny - y, dz)
    }

    fn decide(&mut self, observation: &Observation) -> Move {
        let s = &observation.state;
        let p = Vector3::new(s[6], s[7], s[8]);
        let o = Vector3::new(s[9], s[10], s[11]);
        let vetoed = observation.last_veto.is_some();
        match self.phase {
            Phase::Coarse => {
                let start = Vector3::new(0.0, 0.0, -(self.shaft_length_mm + START_STANDOFF_MM));
                let to_start = p - start;
                if o.norm() > 0.03 {
                    Move {
                        translation_mm: Vector3::zeros(),
                        rotation_deg: clamp_components(o, self.limit_deg),
                    }
                } else if to_start.norm() > 0.05 {
                    Move {
                        translation_mm: clamp_components(to_start, self.limit_mm),
                        rotation_deg: Vector3::zeros(),
                    }
                } else {
                    self.next_spiral(0, 0.0, 0.0, -ADVANCE_MM)
                }
            }
            Phase::Spiral { k, x, y } => {
                if vetoed {
                    // The spiral move and its advance were refused: back off, keep spiralling.
                    self.next_spiral(k, x, y, ADVANCE_MM)
                } else {
                    self.phase = Phase::Advance { k, x, y };
                    self.decide_advance(p)
                }
            }
            Phase::Advance { k, x, y } => {
                if vetoed {
                    self.next_spiral(k, x, y, ADVANCE_MM)
                } else {
                    self.decide_advance(p)
                }
            }
        }
    }

    /// Keep going down the bore axis; near the bottom the measured depth sets the last step.
    fn decide_advance(&self, p: Vector3<f64>) -> Move {
        Move::translation(0.0, 0.0, p.z.clamp(-self.limit_mm, self.limit_mm))
    }
}

impl Controller for SpiralSearch {
    fn name(&self) -> &str {
        "spiral"
    }

    fn reset(&mut self, _seed: u64) {
        self.phase = Phase::Coarse;
    }

    fn act(&mut self, observation: &Observation) -> Decision {
        if !observation.measurement_fresh {
            return Decision::hold();
        }
        Decision::plain(self.decide(observation))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spiral_points_follow_the_papers_formula() {
        // Eight steps per turn; the radius grows by δr after each full turn.
        assert_eq!(SpiralSearch::spiral_point(0), (0.0, 0.0));
        let (x, y) = SpiralSearch::spiral_point(8);
        assert!((x - 0.01).abs() < 1e-12 && y.abs() < 1e-12);
        let (x, y) = SpiralSearch::spiral_point(18); // 2 turns + 90°: r = 0.02
        assert!(x.abs() < 1e-12 && (y - 0.02).abs() < 1e-12);
    }
}
