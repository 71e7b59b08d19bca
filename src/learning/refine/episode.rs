//! One episode of the refinement in the twin, driven by the policy (with exploration) or by
//! the demonstrator, each decision kept as a transition of the agent whose actor made it.
//!
//! An episode reads the refinement's settings and weights and writes nothing of it: it gathers
//! its transitions on its own twin with its own exploration noise (seeded from the episode),
//! so that [`super::RefineConfig::parallel_episodes`] episodes can run at once and give the
//! same transitions on any number of threads.

use super::step_size::{distance_to_goal_mm, is_coarse, scale_of_u, u_of_scale};
use super::{Refinement, agent_index, local_reward};
use crate::geometry::Move;
use crate::learning::dataset::StepLabels;
use crate::learning::pipeline::{normaliser_of, step_limits};
use crate::learning::td3::Transition;
use crate::policy::Actor;
use crate::policy::eval::episode_seed;
use crate::policy::hierarchical::HierarchicalPolicy;
use crate::policy::record::demonstrator_seed;
use crate::policy::shield::{RuleContext, RuleSet, Shaped, Shield};
use crate::sim::randomise::cell_for;
use crate::sim::{AssemblyEnv, Observation, Outcome};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use rayon::prelude::*;
use std::ops::Range;

/// Who moves the shaft in an episode of the refinement.
pub(super) enum Driver {
    /// The policy being refined, with Gaussian exploration noise drawn from the generator.
    Policy(Box<(HierarchicalPolicy, ChaCha8Rng)>),
    /// The scripted demonstrator ([`super::RefineConfig::demonstrator`]).
    Demonstrator,
}

/// What one episode gathered: its figures and each agent's transitions, in order.
pub(super) struct Gathered {
    pub success: bool,
    pub steps: u32,
    pub return_: f64,
    /// Per agent ([`agent_index`]).
    pub transitions: [Vec<Transition>; 2],
    /// The step-size agent's (empty without one): one per decision of the policy, from the
    /// LSTM's hidden state, with the twin's whole reward and the progress shaping.
    pub step_transitions: Vec<Transition>,
}

impl Refinement {
    /// Runs the training episodes `first..first + count` at once on all cores with the
    /// current policy and its exploration noise; returns what each gathered, in episode order.
    pub(super) fn gather_policy_episodes(
        &self,
        robots: &mut [AssemblyEnv],
        first: usize,
        count: usize,
    ) -> candle_core::Result<Vec<Gathered>> {
        self.gather_on(robots, first..first + count, &|index| {
            let noise = ChaCha8Rng::seed_from_u64(episode_seed(self.seed ^ 0x0004_015E, index));
            let driver = Driver::Policy(Box::new((self.policy()?, noise)));
            Ok((driver, episode_seed(self.seed ^ 0x7D3, index)))
        })
    }

    /// Runs the episodes `indices` at once on all cores, each with the driver and seed that
    /// `drive` gives it: on a twin of its own (on `seed`'s cell, drawn when randomising), or
    /// with kept `robots`, on robot index mod their number, each robot's episodes in turn.
    /// Returns what each gathered, in episode order, the same on any number of threads.
    pub(super) fn gather_on(
        &self,
        robots: &mut [AssemblyEnv],
        indices: Range<usize>,
        drive: &(dyn Fn(usize) -> candle_core::Result<(Driver, u64)> + Sync),
    ) -> candle_core::Result<Vec<Gathered>> {
        let run = |env: Option<&mut AssemblyEnv>, index: usize| {
            let (driver, seed) = drive(index)?;
            match env {
                Some(env) => self.gather(driver, seed, index, env),
                None => self.gather(driver, seed, index, &mut self.fresh_twin(seed)),
            }
        };
        if robots.is_empty() {
            return indices
                .into_par_iter()
                .map(|index| run(None, index))
                .collect();
        }
        let count = robots.len();
        let per_robot = robots
            .par_iter_mut()
            .enumerate()
            .map(|(robot, env)| {
                indices
                    .clone()
                    .filter(|index| index % count == robot)
                    .map(|index| Ok((index, run(Some(env), index)?)))
                    .collect::<candle_core::Result<Vec<_>>>()
            })
            .collect::<candle_core::Result<Vec<_>>>()?;
        let mut gathered: Vec<(usize, Gathered)> = per_robot.into_iter().flatten().collect();
        gathered.sort_by_key(|(index, _)| *index);
        Ok(gathered.into_iter().map(|(_, episode)| episode).collect())
    }

    /// A twin for one episode on a robot new to the cell: on `seed`'s cell when randomising.
    fn fresh_twin(&self, seed: u64) -> AssemblyEnv {
        let randomise = self.config.randomise.as_ref();
        let (cell, options) = cell_for(&self.cell, &self.options, randomise, seed);
        AssemblyEnv::new(&cell, options)
    }

    /// Runs one episode (`seed`) on `env` and returns each agent's transitions: the policy's
    /// as it explored, or the demonstrator's, labelled as behaviour cloning labels them.
    /// `index` names the episode in errors.
    fn gather(
        &self,
        driver: Driver,
        seed: u64,
        index: usize,
        env: &mut AssemblyEnv,
    ) -> candle_core::Result<Gathered> {
        let normaliser = normaliser_of(&self.policy_vars)?;
        let (mut explorer, mut demonstrator) = match driver {
            Driver::Policy(explorer) => (Some(*explorer), None),
            Driver::Demonstrator => {
                let mut expert = crate::policy::builtin(self.config.demonstrator, env.cell())
                    .map_err(|e| candle_core::Error::Msg(e.to_string()))?;
                expert.reset(demonstrator_seed(seed));
                (None, Some(expert))
            }
        };
        let inputs = self.config.inputs;
        // The policy's moves go through the cell's rules as training runs them.
        let mut shield = Shield::new(&env.cell().rules.in_training());
        let limits = step_limits(&self.cell, inputs);
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
        let mut observation = env
            .reset(seed)
            .map_err(|e| candle_core::Error::Msg(format!("twin reset failed: {e}")))?;
        let sigma = self.config.td3.exploration_noise;
        let mut gathered = Gathered {
            success: false,
            steps: 0,
            return_: 0.0,
            transitions: [Vec::new(), Vec::new()],
            step_transitions: Vec::new(),
        };
        let mut pending: Option<(Actor, Transition)> = None;
        let step_size = self.config.step_size;
        let mut pending_step: Option<(Transition, f64)> = None;
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
                let read = inputs.of(&observation);
                let x = normaliser.apply(&read);
                let critic_x = privileged(env, &observation);
                if let Some((actor, mut t)) = pending.take() {
                    t.next_state = x.to_vec();
                    t.next_privileged = critic_x.clone();
                    gathered.transitions[agent_index(actor)].push(t);
                }
                let coarse = is_coarse(&observation);
                let chosen = match &mut explorer {
                    Some((policy, noise)) => {
                        let choose = |selected| shield.choose_actor(&observation, selected);
                        let out = policy.propose(&read, &choose)?.acting;
                        if !out.is_finite() {
                            candle_core::bail!(
                                "the policy's output is not finite at episode {index}"
                            );
                        }
                        // The move in the network's units, where the actor's output lives.
                        action = inputs.move_in_units(&read, out.action);
                        let actor = out.actor;
                        let (offset, limit) = match actor {
                            Actor::Position => (0, limits.position_mm),
                            Actor::Orientation => (3, limits.orientation_deg),
                        };
                        let mut scale = out.scale;
                        if let Some(step) = step_size {
                            // The step-size agent explores the scale, and the move follows.
                            let sigma = if coarse { step.coarse_noise } else { sigma };
                            let e: f64 = noise.sample(StandardNormal);
                            let u = (f64::from(u_of_scale(scale)) + sigma * e).clamp(-1.0, 1.0);
                            let explored = scale_of_u(u as f32);
                            if scale > 0.0 {
                                let stretch = f64::from(explored / scale);
                                action.iter_mut().for_each(|v| *v *= stretch);
                            }
                            scale = explored;
                            let (h, _) = policy.lstm_state();
                            let opened = Transition {
                                state: h.to_vec(),
                                action: vec![u as f32],
                                privileged: [x.to_vec(), critic_x.clone()].concat(),
                                coarse,
                                ..Transition::default()
                            };
                            if let Some((mut t, from_mm)) = pending_step.take() {
                                t.next_state = opened.state.clone();
                                t.next_privileged = opened.privileged.clone();
                                t.reward += step.progress_reward(from_mm, &observation);
                                gathered.step_transitions.push(t);
                            }
                            pending_step = Some((opened, distance_to_goal_mm(&observation)));
                        }
                        let span = f64::from(scale) * limit;
                        let mut a: [f32; 3] = std::array::from_fn(|i| {
                            let clean = if span > 0.0 {
                                action[offset + i] / span
                            } else {
                                0.0
                            };
                            let noise: f64 = noise.sample(StandardNormal);
                            (clean + sigma * noise).clamp(-1.0, 1.0) as f32
                        });
                        // Through the shield, on the move in mm and degrees: the actor's output
                        // is what the move its limiting rules leave asks, and the move made is
                        // the one the rules make of it.
                        action = [0.0; 6];
                        for i in 0..3 {
                            action[offset + i] = f64::from(a[i]) * span;
                        }
                        let asked = Shaped {
                            actor: Some(actor),
                            action: Move::from_array(inputs.move_from_units(&read, action)),
                            exact_sideways: false,
                        };
                        let context = RuleContext {
                            observation: &observation,
                            step_limit_mm: policy.config().step_limit_mm,
                            step_limit_deg: policy.config().step_limit_deg,
                        };
                        let mut limited = asked;
                        shield.limit(&context, &mut limited);
                        if span > 0.0 {
                            let in_units = inputs.move_in_units(&read, limited.action.to_array());
                            a = std::array::from_fn(|i| (in_units[offset + i] / span) as f32);
                        }
                        let mut made = asked;
                        shield.shape(&context, &mut made, &mut RuleSet::default());
                        action = made.action.to_array();
                        Some((actor, a))
                    }
                    // The demonstrator's move as behaviour cloning labels it: the direction
                    // the actor learnt, its length the selector's.
                    None => decision.map(|(actor, _)| {
                        let label = StepLabels::of_move(actor, &action, &read, &limits);
                        (actor, label.direction.map(|d| d as f32))
                    }),
                };
                if let Some((actor, a)) = chosen {
                    let state = Transition {
                        state: x.to_vec(),
                        action: a.to_vec(),
                        privileged: critic_x,
                        coarse,
                        ..Transition::default()
                    };
                    pending = Some((actor, state));
                }
            }
            let result = env
                .step(&Move::from_array(action))
                .map_err(|e| candle_core::Error::Msg(format!("twin step failed: {e}")))?;
            gathered.return_ += result.reward.total;
            if let Some((actor, t)) = pending.as_mut() {
                t.reward += local_reward(*actor, &result.reward) as f32;
            }
            if let Some((t, _)) = pending_step.as_mut() {
                t.reward += result.reward.total as f32;
            }
            if let Some(outcome) = result.outcome {
                if let Some((actor, mut t)) = pending.take() {
                    t.next_state = normaliser.apply(&inputs.of(&result.observation)).to_vec();
                    t.next_privileged = privileged(env, &result.observation);
                    t.done = true;
                    gathered.transitions[agent_index(actor)].push(t);
                }
                if let (Some((mut t, from_mm)), Some(step)) = (pending_step.take(), step_size) {
                    t.reward += step.progress_reward(from_mm, &result.observation);
                    // Done: the next state is never read.
                    t.next_state = vec![0.0; t.state.len()];
                    t.next_privileged = vec![0.0; t.privileged.len()];
                    t.done = true;
                    gathered.step_transitions.push(t);
                }
                gathered.success = outcome == Outcome::Success;
                gathered.steps = env.steps();
                return Ok(gathered);
            }
            observation = result.observation;
        }
    }
}
