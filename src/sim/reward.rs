//! The paper's reward (§3.3, Table 1), computed from the state the agent sees.
//!
//! R = λg·R_g + Σ_t (λP·r_P + λO·r_O + λerr·r_err) plus the step penalty, with
//! - R_g = r_su on success, r_fa on failure, else 0 (once, at the end);
//! - r_P = 1 − |P|/P_init while the shaft tip is outside the bore, and 1 − |P_z|/|P_z,init| once
//!   it is inside (the paper's two forms: approach, then insertion);
//! - r_O = 1 − |O|/O_init;
//! - r_err = error_penalty while countP or countO exceeds the limit, where countP (countO) counts
//!   the steps at which |P| (|O|) grew.
//!
//! `P_init`, `|P_z,init|` and `O_init` are floored (1 mm, 1 mm, 0.01 deg) so that an episode that
//! starts on the goal does not divide by zero.

use crate::config::cell::RewardConfig;
use nalgebra::Vector3;
use serde::Serialize;

/// Each term of one step's reward, already weighted, and their sum.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, utoipa::ToSchema)]
pub struct RewardTerms {
    pub global: f64,
    pub position: f64,
    pub orientation: f64,
    pub error: f64,
    pub step: f64,
    pub total: f64,
}

/// How an episode ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Ending {
    Success,
    Failure,
}

/// Running reward state of one episode.
#[derive(Debug, Clone)]
pub struct RewardTracker {
    config: RewardConfig,
    p_init_mm: f64,
    pz_init_mm: f64,
    o_init_deg: f64,
    previous_p_mm: f64,
    previous_o_deg: f64,
    count_p: u32,
    count_o: u32,
}

fn split(state: &[f64; 12]) -> (Vector3<f64>, Vector3<f64>) {
    (
        Vector3::new(state[6], state[7], state[8]),
        Vector3::new(state[9], state[10], state[11]),
    )
}

impl RewardTracker {
    /// Starts an episode from its first state.
    pub fn new(config: &RewardConfig, initial_state: &[f64; 12]) -> Self {
        let (p, o) = split(initial_state);
        RewardTracker {
            config: config.clone(),
            p_init_mm: p.norm().max(1.0),
            pz_init_mm: p.z.abs().max(1.0),
            o_init_deg: o.norm().max(0.01),
            previous_p_mm: p.norm(),
            previous_o_deg: o.norm(),
            count_p: 0,
            count_o: 0,
        }
    }

    /// The reward of the step that led to `state`. `tip_in_bore` selects r_P's insertion form;
    /// `ending` is set on the episode's last step.
    pub fn step(
        &mut self,
        state: &[f64; 12],
        tip_in_bore: bool,
        ending: Option<Ending>,
    ) -> RewardTerms {
        let c = &self.config;
        let (p, o) = split(state);
        if p.norm() > self.previous_p_mm {
            self.count_p += 1;
        }
        if o.norm() > self.previous_o_deg {
            self.count_o += 1;
        }
        self.previous_p_mm = p.norm();
        self.previous_o_deg = o.norm();
        let r_p = if tip_in_bore {
            1.0 - p.z.abs() / self.pz_init_mm
        } else {
            1.0 - p.norm() / self.p_init_mm
        };
        let r_o = 1.0 - o.norm() / self.o_init_deg;
        let r_err = if self.count_p > c.error_count_limit || self.count_o > c.error_count_limit {
            c.error_penalty
        } else {
            0.0
        };
        let r_g = match ending {
            Some(Ending::Success) => c.success,
            Some(Ending::Failure) => c.failure,
            None => 0.0,
        };
        let mut terms = RewardTerms {
            global: c.lambda_global * r_g,
            position: c.lambda_position * r_p,
            orientation: c.lambda_orientation * r_o,
            error: c.lambda_error * r_err,
            step: c.step_penalty,
            total: 0.0,
        };
        terms.total = terms.global + terms.position + terms.orientation + terms.error + terms.step;
        terms
    }

    pub fn counts(&self) -> (u32, u32) {
        (self.count_p, self.count_o)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::cell::CellConfig;

    fn state(p: [f64; 3], o: [f64; 3]) -> [f64; 12] {
        let mut s = [0.0; 12];
        s[6..9].copy_from_slice(&p);
        s[9..12].copy_from_slice(&o);
        s
    }

    #[test]
    fn every_term_by_hand() {
        let config = CellConfig::reference().reward;
        // Start: P = (30, 0, -40) → |P| = 50; O = (0.6, 0.8, 0) → |O| = 1.
        let mut tracker = RewardTracker::new(&config, &state([30.0, 0.0, -40.0], [0.6, 0.8, 0.0]));
        // Approach step to P = (15, 0, -20) (|P| = 25), O = (0.3, 0.4, 0) (|O| = 0.5):
        // r_P = 1 - 25/50 = 0.5 → 0.15; r_O = 1 - 0.5/1 = 0.5 → 0.15; step −0.01.
        let t = tracker.step(&state([15.0, 0.0, -20.0], [0.3, 0.4, 0.0]), false, None);
        assert!((t.position - 0.15).abs() < 1e-12);
        assert!((t.orientation - 0.15).abs() < 1e-12);
        assert_eq!(t.global, 0.0);
        assert_eq!(t.error, 0.0);
        assert!((t.total - (0.15 + 0.15 - 0.01)).abs() < 1e-12);
        // Insertion form: tip in the bore, P_z = −10 of an initial |P_z| = 40 → r_P = 0.75.
        let t = tracker.step(&state([0.0, 0.0, -10.0], [0.0, 0.0, 0.0]), true, None);
        assert!((t.position - 0.3 * 0.75).abs() < 1e-12);
        assert!((t.orientation - 0.3).abs() < 1e-12);
        // Success: +50 × λg = 50.
        let t = tracker.step(
            &state([0.0, 0.0, 0.0], [0.0, 0.0, 0.0]),
            true,
            Some(Ending::Success),
        );
        assert!((t.global - 50.0).abs() < 1e-12);
        assert!((t.total - (50.0 + 0.3 + 0.3 - 0.01)).abs() < 1e-12);
    }

    #[test]
    fn error_penalty_after_more_than_twenty_increases() {
        let config = CellConfig::reference().reward;
        let mut tracker = RewardTracker::new(&config, &state([10.0, 0.0, 0.0], [0.1, 0.0, 0.0]));
        // |P| grows 21 times; the 21st growth puts countP over 20: r_err = −5 × 0.4 = −2.
        for k in 1..=21 {
            let t = tracker.step(
                &state([10.0 + k as f64, 0.0, 0.0], [0.1, 0.0, 0.0]),
                false,
                None,
            );
            if k <= 20 {
                assert_eq!(t.error, 0.0, "step {k}");
            } else {
                assert!((t.error + 2.0).abs() < 1e-12, "step {k}");
            }
        }
        assert_eq!(tracker.counts(), (21, 0));
        // Failure: −50.
        let t = tracker.step(
            &state([40.0, 0.0, 0.0], [0.1, 0.0, 0.0]),
            false,
            Some(Ending::Failure),
        );
        assert!((t.global + 50.0).abs() < 1e-12);
    }
}
