//! TD3 (paper §3.3, Algorithm 3; Fujimoto et al. 2018): twin critics, target policy smoothing
//! with clipped noise, delayed actor and target updates. Table 1 defaults: batch 32, actor/critic
//! lr 3e-4/3e-3 (Adam), noise clip 0.1, policy delay 2, τ = 5e-3, replay 1e6, γ = 0.98.
//!
//! Generic over state and action sizes; actions live in [−1, 1] (tanh). Deterministic under its
//! seed: weights are created here (PyTorch's default initialisation) and every random draw comes
//! from one seeded generator.
//!
//! An optional trust region ([`Td3Config::trust_region`]) keeps the actor's outputs near those of
//! the actor it started from: the BC actors of this cell are right to a few micrometres, and the
//! critic's gradient, learned from a policy that almost always succeeds, points every update the
//! same wrong way.
//!
//! Beyond the paper, for learning that starts from a demonstrator and improves on it:
//! - **asymmetric critics** ([`Td3Config::privileged_dim`]): the critics read numbers the actor
//!   cannot (in the twin, the true pose), so their values are not blurred by the camera's noise;
//!   the actor, the deployed policy, still reads only its observation;
//! - **demonstrations in the replay** ([`Td3::update_with`]): a share of every minibatch
//!   ([`Td3Config::demo_fraction`]) comes from a buffer of the demonstrator's transitions, so the
//!   critics keep knowing the values of good moves (Večerík et al. 2017);
//! - **regularised actor updates** ([`Td3Config::demo_regularisation`], TD3+BC, Fujimoto & Gu
//!   2021, with the Q filter of Nair et al. 2018): the actor's loss is the normalised −Q plus the
//!   squared distance to the demonstrated action on demonstration rows where the critic rates
//!   the demonstrated action above the actor's, so it leaves the demonstrator only where the
//!   critic says it is better to;
//! - [`Td3::clone_behaviour`] and a frozen actor ([`Td3::freeze_actor`]) for behaviour cloning
//!   and critic pre-training on the demonstrations before the actor moves.

use super::bc::{init_mlp, vars_under};
use crate::policy::mlp::{Mlp, MlpConfig};
use candle_core::{DType, Device, Tensor};
use candle_nn::{AdamW, Module, Optimizer, ParamsAdamW, VarBuilder, VarMap};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use std::collections::HashMap;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Td3Config {
    pub gamma: f64,
    pub tau: f64,
    pub actor_learning_rate: f64,
    pub critic_learning_rate: f64,
    pub batch_size: usize,
    pub policy_delay: usize,
    /// σ of the target-policy smoothing noise, and its clip.
    pub target_noise: f64,
    pub noise_clip: f64,
    /// σ of the exploration noise added by [`Td3::explore`].
    pub exploration_noise: f64,
    pub replay_capacity: usize,
    pub hidden: usize,
    pub seed: u64,
    /// A trust region around the starting actor: after each actor update, no output (tanh units)
    /// on [`TRUST_REGION_PROBES`] replayed states may be further than this from the starting
    /// actor's; if one is, the weights are pulled back along the line to the starting weights
    /// until none is. `None`: plain TD3.
    pub trust_region: Option<f64>,
    /// A wider trust region on coarse states ([`Transition::coarse`]: where moves are
    /// millimetres, not micrometres). With it the actor's loss is −Q on the coarse rows of a
    /// minibatch only, plus the squared distance (in units of the trust region) to the
    /// starting actor's output on the others, so that it learns where it may move and holds
    /// where it may not. `None`: every state has `trust_region`.
    pub coarse_trust_region: Option<f64>,
    /// Numbers the critics read beside the actor's state ([`Transition::privileged`]); 0: the
    /// critics read what the actor reads (symmetric TD3).
    pub privileged_dim: usize,
    /// Share of each minibatch drawn from the demonstrations when [`Td3::update_with`] is given
    /// any (Table 1 has none; 0.25 is DDPGfD's order).
    pub demo_fraction: f64,
    /// α of TD3+BC: the actor's loss is −α·Q/mean|Q| plus the squared distance to the
    /// demonstrated action on the demonstration rows the Q filter keeps. `None`: plain −Q.
    pub demo_regularisation: Option<f64>,
}

impl Td3Config {
    /// Target-policy smoothing of σ `sigma`, clipped at half of it (Table 1's ratio); `None`
    /// keeps the current one. Table 1's 0.2 (clipped at 0.1) suits exploration of the same
    /// order; next to the refinement's σ 0.002 it asks the critics for the value of moves up
    /// to fifty times further from the policy's than any explored. Matching it to the
    /// exploration did not keep plain TD3 from undoing BC (docs/learning-reference.md).
    pub fn with_target_noise(self, sigma: Option<f64>) -> Self {
        match sigma {
            Some(sigma) => Td3Config {
                target_noise: sigma,
                noise_clip: sigma / 2.0,
                ..self
            },
            None => self,
        }
    }
}

/// Replayed states on which each actor update is checked against the trust region.
pub const TRUST_REGION_PROBES: usize = 256;

impl Default for Td3Config {
    fn default() -> Self {
        Td3Config {
            gamma: 0.98,
            tau: 5e-3,
            actor_learning_rate: 3e-4,
            critic_learning_rate: 3e-3,
            batch_size: 32,
            policy_delay: 2,
            target_noise: 0.2,
            noise_clip: 0.1,
            exploration_noise: 0.1,
            replay_capacity: 1_000_000,
            hidden: 256,
            seed: 0,
            trust_region: None,
            coarse_trust_region: None,
            privileged_dim: 0,
            demo_fraction: 0.25,
            demo_regularisation: None,
        }
    }
}

/// A copy of every variable of `from` into a new map (for target networks and kept policies).
pub(crate) fn clone_varmap(from: &VarMap) -> candle_core::Result<VarMap> {
    let to = VarMap::new();
    {
        let source = from.data().lock().expect("var map lock");
        let mut target = to.data().lock().expect("var map lock");
        for (name, var) in source.iter() {
            target.insert(
                name.clone(),
                candle_core::Var::from_tensor(&var.as_tensor().copy()?)?,
            );
        }
    }
    Ok(to)
}

/// Sets every variable of `to` to its namesake in `from`.
fn copy_vars(from: &VarMap, to: &VarMap) -> candle_core::Result<()> {
    let from = from.data().lock().expect("var map lock");
    let to = to.data().lock().expect("var map lock");
    for (name, var) in from.iter() {
        to[name].set(var.as_tensor())?;
    }
    Ok(())
}

/// target ← τ·online + (1 − τ)·target, variable by variable.
fn soft_update(online: &VarMap, target: &VarMap, tau: f64) -> candle_core::Result<()> {
    let online = online.data().lock().expect("var map lock");
    let target = target.data().lock().expect("var map lock");
    for (name, var) in online.iter() {
        let t = &target[name];
        t.set(&((var.as_tensor() * tau)? + (t.as_tensor() * (1.0 - tau))?)?)?;
    }
    Ok(())
}

/// One transition (s, a, r, s', done), with what only the critics read at s and s'.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Transition {
    pub state: Vec<f32>,
    pub action: Vec<f32>,
    pub reward: f32,
    pub next_state: Vec<f32>,
    pub done: bool,
    /// [`Td3Config::privileged_dim`] numbers at s (empty for symmetric critics).
    pub privileged: Vec<f32>,
    /// The same at s'.
    pub next_privileged: Vec<f32>,
    /// s is a coarse state ([`Td3Config::coarse_trust_region`]).
    pub coarse: bool,
}

/// Replay memory: a ring of the latest `capacity` transitions.
#[derive(Debug, Clone)]
pub struct ReplayBuffer {
    capacity: usize,
    items: Vec<Transition>,
    next: usize,
}

impl ReplayBuffer {
    pub fn new(capacity: usize) -> Self {
        ReplayBuffer {
            capacity: capacity.max(1),
            items: Vec::new(),
            next: 0,
        }
    }

    pub fn push(&mut self, transition: Transition) {
        if self.items.len() < self.capacity {
            self.items.push(transition);
        } else {
            self.items[self.next] = transition;
        }
        self.next = (self.next + 1) % self.capacity;
    }

    pub fn len(&self) -> usize {
        self.items.len()
    }

    pub fn is_empty(&self) -> bool {
        self.items.is_empty()
    }

    /// The transitions held, in no particular order.
    pub fn items(&self) -> &[Transition] {
        &self.items
    }
}

/// An actor network: the MLP of every actor, or one linear layer with a tanh (a selector's
/// step-size output, `actor.weight` [outputs, inputs] and `actor.bias`).
#[derive(Debug, Clone)]
enum ActorNet {
    Mlp(Mlp),
    Linear(candle_nn::Linear),
}

impl ActorNet {
    /// Loads the actor under `vb`: one linear layer when `vb` holds `weight`, else the MLP of
    /// `config`.
    fn load(vb: VarBuilder, config: &MlpConfig, linear: bool) -> candle_core::Result<Self> {
        Ok(if linear {
            ActorNet::Linear(candle_nn::linear(config.inputs, config.outputs, vb)?)
        } else {
            ActorNet::Mlp(Mlp::load(vb, config)?)
        })
    }

    fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        match self {
            ActorNet::Mlp(mlp) => mlp.forward(x),
            ActorNet::Linear(linear) => linear.forward(x)?.tanh(),
        }
    }
}

/// The TD3 learner: an actor and two critics, each with a target copy.
pub struct Td3 {
    config: Td3Config,
    state_dim: usize,
    action_dim: usize,
    actor_vars: VarMap,
    critic_vars: VarMap,
    actor: ActorNet,
    critics: [Mlp; 2],
    actor_target: ActorNet,
    critic_targets: [Mlp; 2],
    actor_target_vars: VarMap,
    critic_target_vars: VarMap,
    /// The starting actor, kept for the trust region (see [`Td3Config::trust_region`]).
    anchor: Option<Anchor>,
    actor_optimizer: AdamW,
    critic_optimizer: AdamW,
    rng: ChaCha8Rng,
    updates: usize,
    actor_frozen: bool,
}

impl Td3 {
    /// A learner with freshly initialised networks. `actor_init`, if given, holds the actor's
    /// starting weights under `actor.0/2/4` (e.g. from behaviour cloning; its width is read
    /// from `actor.0.weight`) or, for a one-layer actor, `actor.weight` and `actor.bias`;
    /// `config.hidden` sizes the critics.
    pub fn new(
        state_dim: usize,
        action_dim: usize,
        config: Td3Config,
        actor_init: Option<VarMap>,
    ) -> candle_core::Result<Self> {
        let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
        let h = config.hidden;
        let mut linear = false;
        let (actor_vars, actor_width) = match actor_init {
            Some(vars) => {
                let width = {
                    let data = vars.data().lock().expect("var map lock");
                    linear = data.contains_key("actor.weight");
                    match data.get("actor.0.weight") {
                        Some(first) => first.as_tensor().dim(0)?,
                        None if linear => 0,
                        None => candle_core::bail!(
                            "TD3 actor weights have neither `actor.0.weight` nor `actor.weight`"
                        ),
                    }
                };
                (vars, width)
            }
            None => {
                let vars = VarMap::new();
                let fresh = MlpConfig::actor(state_dim, h, action_dim);
                init_mlp(&vars, "actor", &fresh, &mut rng)?;
                (vars, h)
            }
        };
        let actor_config = MlpConfig::actor(state_dim, actor_width, action_dim);
        let critic_config = MlpConfig::critic(state_dim + config.privileged_dim + action_dim, h);
        let critic_vars = VarMap::new();
        for prefix in ["critic1", "critic2"] {
            init_mlp(&critic_vars, prefix, &critic_config, &mut rng)?;
        }
        let actor_target_vars = clone_varmap(&actor_vars)?;
        let critic_target_vars = clone_varmap(&critic_vars)?;
        let device = Device::Cpu;
        let vb = |vars: &VarMap| VarBuilder::from_varmap(vars, DType::F32, &device);
        let anchor = match config.trust_region {
            Some(_) => Some(Anchor {
                actor: ActorNet::load(
                    vb(&clone_varmap(&actor_vars)?).pp("actor"),
                    &actor_config,
                    linear,
                )?,
                weights: actor_weights(&actor_vars)?,
            }),
            None => None,
        };
        let actor = ActorNet::load(vb(&actor_vars).pp("actor"), &actor_config, linear)?;
        let actor_target =
            ActorNet::load(vb(&actor_target_vars).pp("actor"), &actor_config, linear)?;
        let critic = |vars: &VarMap, prefix: &str| Mlp::load(vb(vars).pp(prefix), &critic_config);
        let critics = [
            critic(&critic_vars, "critic1")?,
            critic(&critic_vars, "critic2")?,
        ];
        let critic_targets = [
            critic(&critic_target_vars, "critic1")?,
            critic(&critic_target_vars, "critic2")?,
        ];
        let adam = |lr: f64| ParamsAdamW {
            lr,
            weight_decay: 0.0,
            ..ParamsAdamW::default()
        };
        Ok(Td3 {
            actor_optimizer: AdamW::new(
                vars_under(&actor_vars, "actor."),
                adam(config.actor_learning_rate),
            )?,
            critic_optimizer: AdamW::new(
                vars_under(&critic_vars, "critic"),
                adam(config.critic_learning_rate),
            )?,
            config,
            state_dim,
            action_dim,
            actor_vars,
            critic_vars,
            actor,
            critics,
            actor_target,
            critic_targets,
            actor_target_vars,
            critic_target_vars,
            anchor,
            rng,
            updates: 0,
            actor_frozen: false,
        })
    }

    /// While frozen, updates train the critics only (so that they learn the values of a
    /// pre-trained actor before it is moved by them).
    pub fn freeze_actor(&mut self, frozen: bool) {
        self.actor_frozen = frozen;
    }

    /// Every weight of the learner (online and target networks), for a checkpoint.
    pub fn checkpoint(&self) -> HashMap<String, Tensor> {
        let mut out = HashMap::new();
        for (prefix, vars) in self.var_maps() {
            let data = vars.data().lock().expect("var map lock");
            for (name, var) in data.iter() {
                out.insert(format!("{prefix}{name}"), var.as_tensor().clone());
            }
        }
        out
    }

    /// Sets every weight from a [`Td3::checkpoint`]; names and shapes must match.
    pub fn restore(&mut self, tensors: &HashMap<String, Tensor>) -> candle_core::Result<()> {
        for (prefix, vars) in self.var_maps() {
            let data = vars.data().lock().expect("var map lock");
            for (name, var) in data.iter() {
                let key = format!("{prefix}{name}");
                let Some(value) = tensors.get(&key) else {
                    candle_core::bail!("TD3 checkpoint has no `{key}`");
                };
                var.set(value)?;
            }
        }
        Ok(())
    }

    fn var_maps(&self) -> [(&'static str, &VarMap); 4] {
        [
            ("online.", &self.actor_vars),
            ("online.", &self.critic_vars),
            ("target.", &self.actor_target_vars),
            ("target.", &self.critic_target_vars),
        ]
    }

    /// The actor's action for a state (no noise).
    pub fn act(&self, state: &[f32]) -> candle_core::Result<Vec<f32>> {
        let x = Tensor::from_slice(state, (1, self.state_dim), &Device::Cpu)?;
        self.actor.forward(&x)?.squeeze(0)?.to_vec1::<f32>()
    }

    /// The actor's action with Gaussian exploration noise, clipped to [−1, 1].
    pub fn explore(&mut self, state: &[f32]) -> candle_core::Result<Vec<f32>> {
        let sigma = self.config.exploration_noise;
        let mut action = self.act(state)?;
        for a in &mut action {
            let noise: f64 = self.rng.sample(StandardNormal);
            *a = (f64::from(*a) + sigma * noise).clamp(-1.0, 1.0) as f32;
        }
        Ok(action)
    }

    /// The actor's weights (names `actor.0.weight` …).
    pub fn actor_vars(&self) -> &VarMap {
        &self.actor_vars
    }

    /// One TD3 update from a minibatch of the replay buffer; returns the critic loss (and the
    /// actor loss when this update also moved the actor). Does nothing until the buffer holds a
    /// batch.
    pub fn update(
        &mut self,
        buffer: &ReplayBuffer,
    ) -> candle_core::Result<Option<(f64, Option<f64>)>> {
        self.update_with(buffer, &ReplayBuffer::new(1))
    }

    /// One TD3 update from a minibatch drawn from `online` and, for
    /// [`Td3Config::demo_fraction`] of it, from `demos` (all of it while `online` is empty:
    /// critic pre-training). Does nothing until the two hold a batch between them.
    pub fn update_with(
        &mut self,
        online: &ReplayBuffer,
        demos: &ReplayBuffer,
    ) -> candle_core::Result<Option<(f64, Option<f64>)>> {
        let n = self.config.batch_size;
        if online.len() + demos.len() < n {
            return Ok(None);
        }
        let from_demos = if online.is_empty() {
            n
        } else if demos.is_empty() {
            0
        } else {
            ((n as f64 * self.config.demo_fraction).round() as usize)
                .min(demos.len())
                .max(n.saturating_sub(online.len()))
        };
        let BatchTensors {
            state: s,
            action: a,
            critic_state: critic_s,
            critic_next_state: critic_s2,
            next_state: s2,
            reward: r,
            not_done,
            coarse,
        } = self.sample(online, demos, n, from_demos).tensors(self)?;
        // Target: y = r + γ (1 − done) min_k Q'_k(s', clip(μ'(s') + clip(ε, −c, c), −1, 1)).
        let (ad, device) = (self.action_dim, &Device::Cpu);
        let c = self.config.noise_clip;
        let noise: Vec<f32> = (0..n * ad)
            .map(|_| {
                let e: f64 = self.rng.sample(StandardNormal);
                (self.config.target_noise * e).clamp(-c, c) as f32
            })
            .collect();
        let a2 = (self.actor_target.forward(&s2)? + Tensor::from_vec(noise, (n, ad), device)?)?
            .clamp(-1f32, 1f32)?;
        let sa2 = Tensor::cat(&[&critic_s2, &a2], 1)?;
        let q_next = self.critic_targets[0]
            .forward(&sa2)?
            .minimum(&self.critic_targets[1].forward(&sa2)?)?;
        let y = (r + ((q_next * not_done)? * self.config.gamma)?)?.detach();
        let sa = Tensor::cat(&[&critic_s, &a], 1)?;
        let critic_loss = ((self.critics[0].forward(&sa)? - &y)?.sqr()?.mean_all()?
            + (self.critics[1].forward(&sa)? - &y)?.sqr()?.mean_all()?)?;
        self.critic_optimizer.backward_step(&critic_loss)?;
        let critic_loss = f64::from(critic_loss.to_scalar::<f32>()?);
        if !critic_loss.is_finite() {
            candle_core::bail!(
                "TD3 critic loss is {critic_loss} at update {}",
                self.updates
            );
        }
        self.updates += 1;
        let mut actor_loss = None;
        if self.updates.is_multiple_of(self.config.policy_delay.max(1)) {
            if !self.actor_frozen {
                let loss = self.actor_loss(&s, &critic_s, &a, &coarse, from_demos)?;
                // Only the actor's variables are in this optimizer: the critic stays as it is.
                self.actor_optimizer.backward_step(&loss)?;
                self.keep_within_trust_region(online)?;
                actor_loss = Some(f64::from(loss.to_scalar::<f32>()?));
                soft_update(&self.actor_vars, &self.actor_target_vars, self.config.tau)?;
            }
            soft_update(&self.critic_vars, &self.critic_target_vars, self.config.tau)?;
        }
        Ok(Some((critic_loss, actor_loss)))
    }

    /// The actor's loss on a minibatch whose first `demo_rows` rows are demonstrations: −Q, or
    /// with [`Td3Config::demo_regularisation`] α, −α·Q/mean|Q| + the Q-filtered squared
    /// distance to the demonstrated actions, or with [`Td3Config::coarse_trust_region`] the
    /// zoned loss described there (`coarse`: [n, 1], 1 on coarse rows).
    fn actor_loss(
        &self,
        s: &Tensor,
        critic_s: &Tensor,
        a: &Tensor,
        coarse: &Tensor,
        demo_rows: usize,
    ) -> candle_core::Result<Tensor> {
        let pi = self.actor.forward(s)?;
        let q = self.critics[0].forward(&Tensor::cat(&[critic_s, &pi], 1)?)?;
        let scale = f64::from(q.abs()?.mean_all()?.to_scalar::<f32>()?).max(1e-6);
        let Some(alpha) = self.config.demo_regularisation else {
            return match (
                &self.anchor,
                self.config.trust_region,
                self.config.coarse_trust_region,
            ) {
                (Some(anchor), Some(radius), Some(_)) => {
                    let coarse_rows = f64::from(coarse.sum_all()?.to_scalar::<f32>()?);
                    let fine = coarse.affine(-1.0, 1.0)?;
                    let fine_rows = f64::from(fine.sum_all()?.to_scalar::<f32>()?);
                    let q_term = (q * coarse)?.sum_all()? * (-1.0 / (scale * coarse_rows.max(1.0)));
                    let held = (pi - anchor.actor.forward(s)?.detach())?
                        .sqr()?
                        .sum_keepdim(1)?;
                    let hold = (held * fine)?.sum_all()?
                        / (fine_rows.max(1.0) * self.action_dim as f64 * radius * radius);
                    q_term? + hold?
                }
                _ => q.mean_all()?.neg(),
            };
        };
        let q_term = (q.mean_all()? * (-alpha / scale))?;
        if demo_rows == 0 {
            return Ok(q_term);
        }
        let (pi_demo, a_demo) = (pi.narrow(0, 0, demo_rows)?, a.narrow(0, 0, demo_rows)?);
        let critic_demo = critic_s.narrow(0, 0, demo_rows)?;
        // The Q filter: imitate only where the critic prefers the demonstrated action.
        let q_demo = self.critics[0].forward(&Tensor::cat(&[&critic_demo, &a_demo], 1)?)?;
        let keep = q_demo
            .gt(&q.narrow(0, 0, demo_rows)?)?
            .to_dtype(DType::F32)?
            .detach();
        let kept = f64::from(keep.sum_all()?.to_scalar::<f32>()?);
        if kept == 0.0 {
            return Ok(q_term);
        }
        let distance = (pi_demo - a_demo)?.sqr()?.sum_keepdim(1)?;
        let imitation = ((distance * keep)?.sum_all()? / (kept * self.action_dim as f64))?;
        q_term + imitation
    }

    /// Rows for a minibatch: `from_demos` drawn from `demos` first, the rest from `online`.
    fn sample<'a>(
        &mut self,
        online: &'a ReplayBuffer,
        demos: &'a ReplayBuffer,
        n: usize,
        from_demos: usize,
    ) -> Batch<'a> {
        let mut rows = Vec::with_capacity(n);
        for k in 0..n {
            let buffer = if k < from_demos { demos } else { online };
            rows.push(&buffer.items[self.rng.random_range(0..buffer.len())]);
        }
        Batch(rows)
    }

    /// Behaviour cloning of the actor on `demos` (mean squared error to the demonstrated
    /// actions, minibatches of the TD3 batch size, the actor's learning rate); returns the last
    /// loss. For a learner whose actor did not start from cloned weights.
    pub fn clone_behaviour(
        &mut self,
        demos: &ReplayBuffer,
        updates: usize,
    ) -> candle_core::Result<Option<f64>> {
        let n = self.config.batch_size;
        if demos.is_empty() {
            return Ok(None);
        }
        let mut last = None;
        for _ in 0..updates {
            let batch = self.sample(demos, demos, n, n).tensors(self)?;
            let loss = (self.actor.forward(&batch.state)? - batch.action)?
                .sqr()?
                .mean_all()?;
            self.actor_optimizer.backward_step(&loss)?;
            last = Some(f64::from(loss.to_scalar::<f32>()?));
        }
        copy_vars(&self.actor_vars, &self.actor_target_vars)?;
        Ok(last)
    }

    /// With a trust region: if the actor is now too far from the anchor on probe states drawn
    /// from the buffer (each with its own region: [`Td3Config::coarse_trust_region`] on coarse
    /// states), sets its weights to anchor + β·(weights − anchor) with the largest β
    /// (bisection, 8 halvings) that is within the region.
    fn keep_within_trust_region(&mut self, buffer: &ReplayBuffer) -> candle_core::Result<()> {
        let (Some(anchor), Some(radius)) = (&self.anchor, self.config.trust_region) else {
            return Ok(());
        };
        let n = TRUST_REGION_PROBES.min(buffer.len());
        if n == 0 {
            return Ok(());
        }
        let coarse_radius = self.config.coarse_trust_region.unwrap_or(radius);
        let mut states = Vec::with_capacity(n * self.state_dim);
        let mut inverse_radii = Vec::with_capacity(n);
        for _ in 0..n {
            let t = &buffer.items[self.rng.random_range(0..buffer.len())];
            states.extend_from_slice(&t.state);
            let r = if t.coarse { coarse_radius } else { radius };
            inverse_radii.push((1.0 / r) as f32);
        }
        let probes = Tensor::from_vec(states, (n, self.state_dim), &Device::Cpu)?;
        let inverse_radii = Tensor::from_vec(inverse_radii, (n, 1), &Device::Cpu)?;
        let reference = anchor.actor.forward(&probes)?;
        // The largest gap as a share of its probe's region: within the region at most 1.
        let distance = || -> candle_core::Result<f64> {
            let gap = (self.actor.forward(&probes)? - &reference)?;
            let share = gap.abs()?.broadcast_mul(&inverse_radii)?;
            Ok(f64::from(share.max_all()?.to_scalar::<f32>()?))
        };
        if distance()? <= 1.0 {
            return Ok(());
        }
        let stepped = actor_weights(&self.actor_vars)?;
        let data = self.actor_vars.data().lock().expect("var map lock");
        let set = |beta: f64| -> candle_core::Result<()> {
            for ((name, start), (_, now)) in anchor.weights.iter().zip(&stepped) {
                data[name].set(&(start + ((now - start)? * beta)?)?)?;
            }
            Ok(())
        };
        let (mut inside, mut outside) = (0.0, 1.0);
        for _ in 0..8 {
            let beta = 0.5 * (inside + outside);
            set(beta)?;
            if distance()? <= 1.0 {
                inside = beta;
            } else {
                outside = beta;
            }
        }
        set(inside)
    }
}

/// The transitions of one minibatch.
struct Batch<'a>(Vec<&'a Transition>);

impl Batch<'_> {
    /// The minibatch as tensors, one row per transition.
    fn tensors(&self, td3: &Td3) -> candle_core::Result<BatchTensors> {
        let n = self.0.len();
        let (sd, ad, pd) = (td3.state_dim, td3.action_dim, td3.config.privileged_dim);
        let column = |f: &dyn Fn(&Transition) -> Vec<f32>, width: usize| {
            let values: Vec<f32> = self.0.iter().flat_map(|t| f(t)).collect();
            Tensor::from_vec(values, (n, width), &Device::Cpu)
        };
        let critic = |state: &dyn Fn(&Transition) -> &Vec<f32>,
                      privileged: &dyn Fn(&Transition) -> &Vec<f32>|
         -> candle_core::Result<Tensor> {
            for t in &self.0 {
                if privileged(t).len() != pd {
                    candle_core::bail!(
                        "a transition has {} privileged numbers, the critics read {pd}",
                        privileged(t).len()
                    );
                }
            }
            column(
                &|t| [state(t).as_slice(), privileged(t).as_slice()].concat(),
                sd + pd,
            )
        };
        Ok(BatchTensors {
            state: column(&|t| t.state.clone(), sd)?,
            action: column(&|t| t.action.clone(), ad)?,
            critic_state: critic(&|t| &t.state, &|t| &t.privileged)?,
            critic_next_state: critic(&|t| &t.next_state, &|t| &t.next_privileged)?,
            next_state: column(&|t| t.next_state.clone(), sd)?,
            reward: column(&|t| vec![t.reward], 1)?,
            not_done: column(&|t| vec![if t.done { 0.0 } else { 1.0 }], 1)?,
            coarse: column(&|t| vec![if t.coarse { 1.0 } else { 0.0 }], 1)?,
        })
    }
}

/// A minibatch's columns. The critics' states are the actor's followed by the privileged
/// numbers.
struct BatchTensors {
    state: Tensor,
    action: Tensor,
    critic_state: Tensor,
    critic_next_state: Tensor,
    next_state: Tensor,
    reward: Tensor,
    not_done: Tensor,
    coarse: Tensor,
}

/// The starting actor and its weights (names in [`actor_weights`]'s order).
struct Anchor {
    actor: ActorNet,
    weights: Vec<(String, Tensor)>,
}

/// A copy of every actor weight, by name, in a fixed order.
fn actor_weights(vars: &VarMap) -> candle_core::Result<Vec<(String, Tensor)>> {
    let data = vars.data().lock().expect("var map lock");
    let mut weights = data
        .iter()
        .map(|(name, var)| Ok((name.clone(), var.as_tensor().copy()?)))
        .collect::<candle_core::Result<Vec<_>>>()?;
    weights.sort_by(|a, b| a.0.cmp(&b.0));
    Ok(weights)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A task with a known optimum: state s ∈ [−1, 1], one-step episodes, reward −(a − s/2)².
    /// The best action is a* = s/2. Returns the learner after 3000 steps, and its actions on
    /// `grid` before them.
    fn train_on_the_known_optimum_task(trust_region: Option<f64>, grid: &[f32]) -> (Td3, Vec<f32>) {
        train_on_the_known_optimum_task_zoned(trust_region, None, grid)
    }

    /// The same, with the states s > 0 coarse ([`Td3Config::coarse_trust_region`]).
    fn train_on_the_known_optimum_task_zoned(
        trust_region: Option<f64>,
        coarse_trust_region: Option<f64>,
        grid: &[f32],
    ) -> (Td3, Vec<f32>) {
        let config = Td3Config {
            hidden: 32,
            actor_learning_rate: 1e-3,
            exploration_noise: 0.3,
            tau: 0.02,
            seed: 5,
            trust_region,
            coarse_trust_region,
            ..Td3Config::default()
        };
        let mut td3 = Td3::new(1, 1, config, None).unwrap();
        let start = grid.iter().map(|&s| td3.act(&[s]).unwrap()[0]).collect();
        let mut buffer = ReplayBuffer::new(10_000);
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        for _ in 0..3000 {
            let s = rng.random_range(-1.0f32..1.0);
            let a = td3.explore(&[s]).unwrap()[0];
            buffer.push(Transition {
                state: vec![s],
                action: vec![a],
                reward: -(a - s / 2.0).powi(2),
                next_state: vec![s],
                done: true,
                coarse: s > 0.0,
                ..Transition::default()
            });
            td3.update(&buffer).unwrap();
        }
        (td3, start)
    }

    fn grid() -> Vec<f32> {
        (-10..=10).map(|k| k as f32 / 10.0).collect()
    }

    #[test]
    fn td3_learns_a_task_with_a_known_optimum() {
        let (td3, _) = train_on_the_known_optimum_task(None, &[]);
        let worst = grid()
            .into_iter()
            .map(|s| (td3.act(&[s]).unwrap()[0] - s / 2.0).abs())
            .fold(0.0f32, f32::max);
        eprintln!("largest error from the optimum a* = s/2: {worst:.4}");
        assert!(worst < 0.1, "largest error from the optimum {worst}");
    }

    /// The same task with a trust region of 0.05 around the untrained actor: the actor moves
    /// towards a* = s/2 as far as the region allows and no further, while plain TD3 (the
    /// same seed) leaves the region.
    #[test]
    fn a_trust_region_keeps_the_actor_near_its_start_and_lets_it_improve() {
        let radius = 0.05;
        let grid = grid();
        let train = |trust_region: Option<f64>| {
            let (td3, start) = train_on_the_known_optimum_task(trust_region, &grid);
            let end: Vec<f32> = grid.iter().map(|&s| td3.act(&[s]).unwrap()[0]).collect();
            let moved = start
                .iter()
                .zip(&end)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0f32, f32::max);
            let error = |actions: &[f32]| -> f32 {
                grid.iter()
                    .zip(actions)
                    .map(|(s, a)| (a - s / 2.0).abs())
                    .sum::<f32>()
                    / grid.len() as f32
            };
            (moved, error(&start), error(&end))
        };
        let (moved, before, after) = train(Some(radius));
        eprintln!("within the region: moved {moved:.4}, mean error {before:.4} -> {after:.4}");
        // The probes are replayed states; between them the actor may stray a little further.
        assert!(moved <= 1.2 * radius as f32, "moved {moved} from the start");
        assert!(
            moved >= 0.8 * radius as f32,
            "moved only {moved}: the region was not used"
        );
        assert!(
            after < before - 0.5 * radius as f32,
            "error {before} -> {after}"
        );
        let (free, _, _) = train(None);
        assert!(free > 2.0 * radius as f32, "plain TD3 moved only {free}");
    }

    /// A trust region of 0.02 with 0.3 on the coarse states (s > 0): there the actor moves
    /// well past 0.02 towards a* = s/2; on the others it stays within 0.02 of its start.
    #[test]
    fn a_zoned_trust_region_lets_the_actor_move_further_on_coarse_states_only() {
        let (radius, coarse) = (0.02, 0.3);
        let grid = grid();
        let (td3, start) = train_on_the_known_optimum_task_zoned(Some(radius), Some(coarse), &grid);
        let (mut fine_moved, mut coarse_moved) = (0.0f32, 0.0f32);
        let (mut coarse_before, mut coarse_after) = (0.0f32, 0.0f32);
        for (&s, &a0) in grid.iter().zip(&start) {
            let a = td3.act(&[s]).unwrap()[0];
            if s <= -0.2 {
                fine_moved = fine_moved.max((a - a0).abs());
            } else if s >= 0.2 {
                coarse_moved = coarse_moved.max((a - a0).abs());
                coarse_before += (a0 - s / 2.0).abs();
                coarse_after += (a - s / 2.0).abs();
            }
        }
        eprintln!(
            "fine states moved {fine_moved:.4}, coarse {coarse_moved:.4}; coarse error \
             {coarse_before:.3} -> {coarse_after:.3}"
        );
        // The probes are replayed states; between them the actor may stray a little further.
        assert!(
            fine_moved <= 1.2 * radius as f32,
            "fine states moved {fine_moved}"
        );
        assert!(
            coarse_moved > 3.0 * radius as f32,
            "coarse states moved {coarse_moved}"
        );
        // Further towards the optimum than the fine region alone would let it come.
        let coarse_points = grid.iter().filter(|&&s| s >= 0.2).count() as f32;
        assert!(
            coarse_before - coarse_after > coarse_points * 1.2 * radius as f32,
            "coarse error {coarse_before} -> {coarse_after}"
        );
    }

    #[test]
    fn replay_buffer_keeps_the_latest() {
        let mut buffer = ReplayBuffer::new(2);
        for k in 0..3 {
            buffer.push(Transition {
                state: vec![k as f32],
                action: vec![],
                reward: 0.0,
                next_state: vec![],
                done: false,
                ..Transition::default()
            });
        }
        assert_eq!(buffer.len(), 2);
        let kept: Vec<f32> = buffer.items.iter().map(|t| t.state[0]).collect();
        assert_eq!(kept, vec![2.0, 1.0]);
    }
}
