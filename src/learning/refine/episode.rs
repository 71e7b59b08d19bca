//! One episode of the refinement in the twin, driven by the policy (with exploration) or by
//! the demonstrator, each decision kept as a transition of the agent whose actor made it.

use super::{Refinement, agent_index, local_reward};
use crate::learning::dataset::StepLabels;
use crate::learning::pipeline::{normaliser_of, step_limits};
use crate::learning::td3::Transition;
use crate::policy::Actor;
use crate::policy::hierarchical::deepest_move_mm;
use crate::policy::record::demonstrator_seed;
use crate::sim::randomise::randomised;
use crate::sim::{AssemblyEnv, Observation, Outcome};
use rand::Rng;
use rand_distr::StandardNormal;

/// Who moves the shaft in an episode of the refinement.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Driver {
    /// The policy being refined, with exploration noise.
    Policy,
    /// The scripted demonstrator ([`super::RefineConfig::demonstrator`]).
    Demonstrator,
}

impl Refinement {
    /// Runs one episode on `seed`'s cell (drawn when randomising) and keeps each agent's
    /// transitions: the policy's in the replay buffers, the demonstrator's in the
    /// demonstration buffers. Returns success, steps, return and the transitions per agent.
    pub(super) fn run_episode(
        &mut self,
        driver: Driver,
        seed: u64,
    ) -> candle_core::Result<(bool, u32, f64, [usize; 2])> {
        if let Some(ranges) = &self.config.randomise {
            let (drawn, mismatch) = randomised(&self.cell, &self.options, ranges, seed);
            self.env = AssemblyEnv::new(&drawn, mismatch);
        }
        let normaliser = normaliser_of(&self.policy_vars)?;
        let mut policy = self.policy()?;
        let mut demonstrator = match driver {
            Driver::Policy => None,
            Driver::Demonstrator => {
                let mut expert = crate::policy::builtin(self.config.demonstrator, self.env.cell())
                    .map_err(|e| candle_core::Error::Msg(e.to_string()))?;
                expert.reset(demonstrator_seed(seed));
                Some(expert)
            }
        };
        let limits = step_limits(&self.cell);
        let buffers = match driver {
            Driver::Policy => &mut self.buffers,
            Driver::Demonstrator => &mut self.demo_buffers,
        };
        let inputs = self.config.inputs;
        let asymmetric = self.config.asymmetric;
        // What each agent's critics read at the current step beside the actor's inputs.
        let privileged = |env: &AssemblyEnv, observation: &Observation| -> Vec<f32> {
            if !asymmetric {
                return Vec::new();
            }
            let truth = Observation {
                state: env.true_state(),
                ..observation.clone()
            };
            normaliser.apply(&inputs.of(&truth)).to_vec()
        };
        let mut observation = self
            .env
            .reset(seed)
            .map_err(|e| candle_core::Error::Msg(format!("twin reset failed: {e}")))?;
        let sigma = self.config.td3.exploration_noise;
        let mut pending: Option<(Actor, Transition)> = None;
        let mut taken = [0usize; 2];
        let mut return_ = 0.0;
        loop {
            let mut action = [0.0f64; 6];
            let decision = match &mut demonstrator {
                Some(expert) => {
                    let decision = expert.act(&observation);
                    action = decision.action.to_array();
                    decision.actor.zip(decision.scale)
                }
                None => None,
            };
            if observation.measurement_fresh {
                let x = normaliser.apply(&inputs.of(&observation));
                let critic_x = privileged(&self.env, &observation);
                if let Some((actor, mut t)) = pending.take() {
                    t.next_state = x.to_vec();
                    t.next_privileged = critic_x.clone();
                    buffers[agent_index(actor)].push(t);
                }
                let chosen = match &demonstrator {
                    Some(_) => decision,
                    None => {
                        let out = policy.step(&inputs.of(&observation))?;
                        if !out.is_finite() {
                            candle_core::bail!(
                                "the policy's output is not finite at episode {}",
                                self.episode
                            );
                        }
                        action = out.action.map(f64::from);
                        Some((out.actor, f64::from(out.scale)))
                    }
                };
                if let Some((actor, scale)) = chosen {
                    let a: [f32; 3] = if demonstrator.is_some() {
                        // The demonstrator's move as behaviour cloning labels it: the
                        // direction the actor learnt, its length the selector's.
                        let label = StepLabels::of_move(actor, &action, &limits);
                        label.direction.map(|d| d as f32)
                    } else {
                        let (offset, limit) = match actor {
                            Actor::Position => (0, limits.position_mm),
                            Actor::Orientation => (3, limits.orientation_deg),
                        };
                        let span = scale * limit;
                        let mut a: [f32; 3] = std::array::from_fn(|i| {
                            let clean = if span > 0.0 {
                                action[offset + i] / span
                            } else {
                                0.0
                            };
                            let noise: f64 = self.rng.sample(StandardNormal);
                            (clean + sigma * noise).clamp(-1.0, 1.0) as f32
                        });
                        // As the policy acts as a controller: not past the goal, and no
                        // deeper after a refusal for contact.
                        if actor == Actor::Position && span > 0.0 {
                            a[2] = a[2].max((deepest_move_mm(&observation) / span) as f32);
                        }
                        action = [0.0; 6];
                        for i in 0..3 {
                            action[offset + i] = f64::from(a[i]) * span;
                        }
                        a
                    };
                    taken[agent_index(actor)] += 1;
                    let state = Transition {
                        state: x.to_vec(),
                        action: a.to_vec(),
                        privileged: critic_x,
                        ..Transition::default()
                    };
                    pending = Some((actor, state));
                }
            }
            let result = self
                .env
                .step(&crate::geometry::Move::from_array(action))
                .map_err(|e| candle_core::Error::Msg(format!("twin step failed: {e}")))?;
            return_ += result.reward.total;
            if let Some((actor, t)) = pending.as_mut() {
                t.reward += local_reward(*actor, &result.reward) as f32;
            }
            if let Some(outcome) = result.outcome {
                if let Some((actor, mut t)) = pending.take() {
                    t.next_state = normaliser.apply(&inputs.of(&result.observation)).to_vec();
                    t.next_privileged = privileged(&self.env, &result.observation);
                    t.done = true;
                    buffers[agent_index(actor)].push(t);
                }
                return Ok((
                    outcome == Outcome::Success,
                    self.env.steps(),
                    return_,
                    taken,
                ));
            }
            observation = result.observation;
        }
    }
}
