//! The learned hierarchical policy (paper §3.1, docs/design.md §6): an LSTM over the state sequence
//! whose head gives ω1, ω2 (softmax: position vs orientation actor) and ω3 (step size), and two
//! actors (Linear-ReLU-Linear-ReLU-Linear-Tanh, [`super::mlp`]) that each give 3 values in [-1, 1].
//!
//! The forward pass, fixed so that every implementation gives the same move:
//!
//! ```text
//! x            = (s - obs_mean) / obs_std
//! h, c         = LSTM step on x (PyTorch equations, gates i, f, g, o), h = c = 0 at episode start
//! ω1, ω2, ω3   = high.head(h)
//! p_pos, p_ori = softmax(ω1, ω2); the position actor acts if p_pos >= p_ori
//! scale        = sigmoid(ω3)
//! a            = actor(x)
//! move         = position:    (a · scale · step_limit_mm, 0)
//!                orientation: (0, a · scale · step_limit_deg)
//! ```
//!
//! A policy with cell-scaled inputs multiplies the orientation move's x and y by the tilt
//! unit its inputs carry in slot 3 ([`super::inputs`]).
//!
//! Two implementations read the same weights by name. Plain f32 loops (`plain.rs`) run
//! [`HierarchicalPolicy::step`] (one episode) and [`HierarchicalPolicy::step_batch`] (B episodes,
//! on all cores): at these sizes candle's per-op overhead dominates, and the loops evaluate only
//! the actor that acts. candle ([`HierarchicalNet`], [`HierarchicalPolicy::step_batch_candle`]) is
//! the reference they are checked against and the model training builds on. Both match an
//! independent numpy implementation (tests/fixtures, scripts/make_policy_fixture.py) to 1e-5.
//! The normalisation runs in f64 (states hold values like 2000 mm), the network in f32.
//!
//! What the networks propose goes through the rules of the shield before it is made
//! ([`super::shield`], [`super::learned::LearnedPolicy`]): [`HierarchicalPolicy::propose`]
//! gives the selector's choice and, where the shield's first rule hands the step to the other
//! actor, that actor's move too. The CPU thread setup is the process's
//! ([`crate::threads::init_cpu_threads`]).
//! `celld policy run` prints the forward pass alone.

use super::file::{ACTOR_DIM, HEAD_DIM, PolicyFile, STATE_DIM};
use super::inputs::PolicyInputs;
use super::mlp::{Mlp, MlpConfig};
use super::{Actor, Decision};
use crate::geometry::Move;
use candle_core::{DType, Device, Module, Tensor};
use candle_nn::rnn::{LSTMState, RNN};
use candle_nn::{LSTM, LSTMConfig, Linear, VarBuilder};
use serde::Serialize;

mod plain;
use plain::{PlainNet, Scratch};

/// Which actor acts, from the selector's choice.
type ChooseActor<'a> = &'a dyn Fn(Actor) -> Actor;

/// Sizes and step limits of a policy.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PolicyConfig {
    /// H: the LSTM's hidden size.
    pub hidden_size: usize,
    /// D: the actors' hidden width.
    pub actor_width: usize,
    /// The position actor's output is scaled by this (mm) × scale.
    pub step_limit_mm: f64,
    /// The orientation actor's output is scaled by this (deg) × scale.
    pub step_limit_deg: f64,
    /// What the network reads (`super::inputs`).
    pub inputs: PolicyInputs,
}

impl PolicyConfig {
    /// Sizes from the tensors' shapes, step limits from the metadata.
    pub fn from_file(file: &PolicyFile) -> Self {
        PolicyConfig {
            hidden_size: file.hidden_size(),
            actor_width: file.actor_width(),
            step_limit_mm: file.step_limit_mm(),
            step_limit_deg: file.step_limit_deg(),
            inputs: file.metadata().inputs,
        }
    }
}

/// The result of one step of the policy.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct PolicyOutput {
    /// ω1, ω2, ω3 as the head outputs them.
    pub omega: [f32; 3],
    /// The actor that acted (position if p_pos >= p_ori).
    pub actor: Actor,
    /// sigmoid(ω3).
    pub scale: f32,
    /// The move `[Δx, Δy, Δz, θx, θy, θz]` (mm, deg).
    pub action: [f64; 6],
}

impl PolicyOutput {
    pub fn is_finite(&self) -> bool {
        self.omega.iter().all(|v| v.is_finite())
            && self.scale.is_finite()
            && self.action.iter().all(|v| v.is_finite())
    }

    /// The move as the twin takes it.
    pub fn to_move(&self) -> Move {
        Move::from_array(self.action)
    }

    /// The decision of this output: its move, actor and step scale.
    pub fn to_decision(&self) -> Decision {
        Decision {
            action: self.to_move(),
            actor: Some(self.actor),
            scale: Some(f64::from(self.scale)),
            shield: None,
        }
    }
}

/// The network's step as the policy acts: what the selector chose, and the move of the actor
/// that acts (the same unless the shield handed the step to the other actor).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Proposal {
    pub selected: PolicyOutput,
    pub acting: PolicyOutput,
}

impl Proposal {
    pub fn is_finite(&self) -> bool {
        self.selected.is_finite() && self.acting.is_finite()
    }
}

/// The actor choice and step scale of the fixed forward pass, from ω.
pub fn select(omega: [f32; 3]) -> (Actor, f32) {
    let m = omega[0].max(omega[1]);
    let (e_pos, e_ori) = ((omega[0] - m).exp(), (omega[1] - m).exp());
    let sum = e_pos + e_ori;
    let (p_pos, p_ori) = (e_pos / sum, e_ori / sum);
    let actor = if p_pos >= p_ori {
        Actor::Position
    } else {
        Actor::Orientation
    };
    (actor, sigmoid(omega[2]))
}

/// Assembles the output from ω and both actors' outputs (only the chosen one is used), for
/// the cell of `inputs` (cell-scaled inputs carry the unit of the tilting moves).
fn compose(
    config: &PolicyConfig,
    inputs: &[f64; 12],
    omega: [f32; 3],
    actor: Actor,
    scale: f32,
    a: [f32; 3],
) -> PolicyOutput {
    let mut action = [0.0f64; 6];
    let (offset, limit) = match actor {
        Actor::Position => (0, config.step_limit_mm),
        Actor::Orientation => (3, config.step_limit_deg),
    };
    for i in 0..3 {
        action[offset + i] = a[i] as f64 * scale as f64 * limit;
    }
    PolicyOutput {
        omega,
        actor,
        scale,
        action: config.inputs.move_from_units(inputs, action),
    }
}

fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// Normalises a state (in f64) into the network's input.
fn normalise(state: &[f64; 12], mean: &[f64; 12], std: &[f64; 12], x: &mut [f32]) {
    for i in 0..STATE_DIM {
        x[i] = ((state[i] - mean[i]) / std[i]) as f32;
    }
}

fn state_error(state: &[f64; 12]) -> Option<candle_core::Error> {
    state.iter().position(|v| !v.is_finite()).map(|i| {
        candle_core::Error::Msg(format!(
            "state value {i} is {}, not a finite number",
            state[i]
        ))
    })
}

// ---------------------------------------------------------------------------------------------
// candle implementation

/// The configuration of each actor of width `width`: the 12-value state in, 3 values in [−1, 1]
/// out (PyTorch `nn.Sequential` names `0`, `2`, `4`).
pub fn actor_config(width: usize) -> MlpConfig {
    MlpConfig::actor(STATE_DIM, width, ACTOR_DIM)
}

/// The whole policy network in candle (f32), loaded by PyTorch `state_dict` names.
#[derive(Debug, Clone)]
pub struct HierarchicalNet {
    lstm: LSTM,
    head: Linear,
    pos: Mlp,
    ori: Mlp,
    obs_mean: [f64; 12],
    obs_std: [f64; 12],
    config: PolicyConfig,
    device: Device,
}

/// What [`HierarchicalNet::forward`] returns for a batch of B rows.
#[derive(Debug, Clone)]
pub struct NetOutput {
    /// [B, 3]: ω1, ω2, ω3.
    pub omega: Tensor,
    /// [B, 3]: the position actor's output.
    pub pos: Tensor,
    /// [B, 3]: the orientation actor's output.
    pub ori: Tensor,
    /// The LSTM state after the step.
    pub state: LSTMState,
}

impl HierarchicalNet {
    pub fn load(vb: VarBuilder, config: &PolicyConfig) -> candle_core::Result<Self> {
        let (h, d) = (config.hidden_size, config.actor_width);
        let high = vb.pp("high");
        let lstm = candle_nn::lstm(STATE_DIM, h, LSTMConfig::default(), high.pp("lstm"))?;
        let head = candle_nn::linear(h, HEAD_DIM, high.pp("head"))?;
        let pos = Mlp::load(vb.pp("pos"), &actor_config(d))?;
        let ori = Mlp::load(vb.pp("ori"), &actor_config(d))?;
        let to_array = |t: Tensor| -> candle_core::Result<[f64; 12]> {
            let v = t.to_dtype(DType::F64)?.to_vec1::<f64>()?;
            Ok(std::array::from_fn(|i| v[i]))
        };
        let obs_mean = to_array(vb.get(STATE_DIM, "obs_mean")?)?;
        let obs_std = to_array(vb.get(STATE_DIM, "obs_std")?)?;
        Ok(HierarchicalNet {
            lstm,
            head,
            pos,
            ori,
            obs_mean,
            obs_std,
            config: *config,
            device: vb.device().clone(),
        })
    }

    pub fn config(&self) -> &PolicyConfig {
        &self.config
    }

    pub fn device(&self) -> &Device {
        &self.device
    }

    /// The normalised input [B, 12] for a batch of states.
    pub fn normalise(&self, states: &[[f64; 12]]) -> candle_core::Result<Tensor> {
        let mut x = vec![0f32; states.len() * STATE_DIM];
        for (s, row) in states.iter().zip(x.chunks_exact_mut(STATE_DIM)) {
            normalise(s, &self.obs_mean, &self.obs_std, row);
        }
        Tensor::from_vec(x, (states.len(), STATE_DIM), &self.device)
    }

    /// One step for a batch: `x` normalised [B, 12], `state` h, c [B, H].
    pub fn forward(&self, x: &Tensor, state: &LSTMState) -> candle_core::Result<NetOutput> {
        let state = self.lstm.step(x, state)?;
        let omega = self.head.forward(&state.h)?;
        let pos = self.pos.forward(x)?;
        let ori = self.ori.forward(x)?;
        Ok(NetOutput {
            omega,
            pos,
            ori,
            state,
        })
    }
}

// ---------------------------------------------------------------------------------------------
// the policy

/// One row of [`HierarchicalPolicy::step_batch`]: its state, LSTM state, and where the next
/// LSTM state goes.
struct BatchRow<'a> {
    x: &'a [f64; 12],
    h: &'a [f32],
    c: &'a [f32],
    h_out: &'a mut [f32],
    c_out: &'a mut [f32],
}

/// Batches at least this large are stepped on all cores.
const PARALLEL_BATCH: usize = 8;

/// The hierarchical policy, ready to run: a single episode through [`HierarchicalPolicy::step`]
/// (its LSTM state runs across the steps until [`HierarchicalPolicy::reset`]) or a batch of
/// episodes through [`HierarchicalPolicy::step_batch`] with a [`BatchState`].
#[derive(Debug, Clone)]
pub struct HierarchicalPolicy {
    name: String,
    net: HierarchicalNet,
    plain: PlainNet,
    scratch: Scratch,
    /// The single episode's LSTM state, and the buffers its next state is computed into.
    h: Vec<f32>,
    c: Vec<f32>,
    h_next: Vec<f32>,
    c_next: Vec<f32>,
}

impl HierarchicalPolicy {
    /// Loads the network by PyTorch `state_dict` names from `vb` (f32, CPU).
    pub fn load(vb: VarBuilder, config: &PolicyConfig) -> candle_core::Result<Self> {
        let net = HierarchicalNet::load(vb.clone(), config)?;
        let plain = PlainNet::load(&vb, config)?;
        let h = config.hidden_size;
        Ok(HierarchicalPolicy {
            name: "hierarchical".to_string(),
            net,
            scratch: plain.scratch(),
            plain,
            h: vec![0.0; h],
            c: vec![0.0; h],
            h_next: vec![0.0; h],
            c_next: vec![0.0; h],
        })
    }

    /// The policy of a checked policy file, on the CPU.
    pub fn from_file(file: &PolicyFile) -> candle_core::Result<Self> {
        let device = Device::Cpu;
        Self::load(file.var_builder(&device)?, &PolicyConfig::from_file(file))
    }

    /// Reads, checks and loads a policy file; the controller is named after the file's stem.
    pub fn from_path(path: impl AsRef<std::path::Path>) -> anyhow::Result<Self> {
        let path = path.as_ref();
        let file = PolicyFile::from_path(path)?;
        let policy = Self::from_file(&file)?;
        let name = path.file_stem().map_or("hierarchical".to_string(), |s| {
            s.to_string_lossy().into_owned()
        });
        Ok(policy.with_name(name))
    }

    /// The name the policy runs under.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Renames the controller (default "hierarchical").
    pub fn with_name(mut self, name: impl Into<String>) -> Self {
        self.name = name.into();
        self
    }

    pub fn config(&self) -> &PolicyConfig {
        &self.net.config
    }

    /// The candle network.
    pub fn net(&self) -> &HierarchicalNet {
        &self.net
    }

    /// Starts a new episode: h = c = 0.
    pub fn reset(&mut self) {
        self.h.iter_mut().for_each(|v| *v = 0.0);
        self.c.iter_mut().for_each(|v| *v = 0.0);
    }

    /// The single episode's LSTM state (h, c).
    pub fn lstm_state(&self) -> (&[f32], &[f32]) {
        (&self.h, &self.c)
    }

    /// One step of the single episode. A non-finite state is refused and leaves the LSTM state
    /// as it was; so does a step whose LSTM state would not be finite.
    pub fn step(&mut self, state: &[f64; 12]) -> candle_core::Result<PolicyOutput> {
        self.step_choosing(state, &|actor| actor)
    }

    /// One step of the single episode as the policy acts: the selector's choice, and where
    /// `choose` hands the step to the other actor (the shield's rule 1), that actor's move.
    pub fn propose(
        &mut self,
        state: &[f64; 12],
        choose: ChooseActor<'_>,
    ) -> candle_core::Result<Proposal> {
        let acting = self.step_choosing(state, choose)?;
        let (selected_actor, _) = select(acting.omega);
        let selected = if selected_actor == acting.actor {
            acting
        } else {
            self.plain
                .actor_output(state, &mut self.scratch, acting.omega, selected_actor)
        };
        Ok(Proposal { selected, acting })
    }

    fn step_choosing(
        &mut self,
        state: &[f64; 12],
        choose: ChooseActor<'_>,
    ) -> candle_core::Result<PolicyOutput> {
        let out = self.plain.step(
            state,
            (&self.h, &self.c),
            (&mut self.h_next, &mut self.c_next),
            &mut self.scratch,
            choose,
        )?;
        std::mem::swap(&mut self.h, &mut self.h_next);
        std::mem::swap(&mut self.c, &mut self.c_next);
        Ok(out)
    }

    /// A zero state for `batch` episodes.
    pub fn batch_state(&self, batch: usize) -> BatchState {
        BatchState::new(batch, self.net.config.hidden_size)
    }

    fn check_batch(&self, states: &[[f64; 12]], state: &BatchState) -> candle_core::Result<()> {
        let (b, h) = (state.batch, state.hidden);
        if states.len() != b || h != self.net.config.hidden_size {
            return Err(candle_core::Error::Msg(format!(
                "{} states for a batch state of {b} rows of H = {h} (policy H = {})",
                states.len(),
                self.net.config.hidden_size
            )));
        }
        for (row, s) in states.iter().enumerate() {
            if let Some(e) = state_error(s) {
                return Err(candle_core::Error::Msg(format!("row {row}: {e}")));
            }
        }
        Ok(())
    }

    /// One step of B episodes at once: `states[i]` is episode i's state, `state` holds their
    /// LSTM states (updated). Rows run the same code as [`HierarchicalPolicy::step`], on all
    /// cores for larger batches. On an error (a non-finite state in any row) no row moves on.
    pub fn step_batch(
        &self,
        states: &[[f64; 12]],
        state: &mut BatchState,
    ) -> candle_core::Result<Vec<PolicyOutput>> {
        use rayon::prelude::*;
        self.check_batch(states, state)?;
        let hidden = state.hidden;
        let mut h_next = vec![0f32; state.h.len()];
        let mut c_next = vec![0f32; state.c.len()];
        let rows: Vec<BatchRow<'_>> = states
            .iter()
            .zip(state.h.chunks_exact(hidden))
            .zip(state.c.chunks_exact(hidden))
            .zip(h_next.chunks_exact_mut(hidden))
            .zip(c_next.chunks_exact_mut(hidden))
            .map(|((((x, h), c), h_out), c_out)| BatchRow {
                x,
                h,
                c,
                h_out,
                c_out,
            })
            .collect();
        let run = |s: &mut Scratch, r: BatchRow<'_>| {
            self.plain
                .step(r.x, (r.h, r.c), (r.h_out, r.c_out), s, &|actor| actor)
        };
        let out: candle_core::Result<Vec<PolicyOutput>> = if rows.len() >= PARALLEL_BATCH {
            rows.into_par_iter()
                .map_init(|| self.plain.scratch(), run)
                .collect()
        } else {
            let mut s = self.plain.scratch();
            rows.into_iter().map(|r| run(&mut s, r)).collect()
        };
        let out = out?;
        state.h = h_next;
        state.c = c_next;
        Ok(out)
    }

    /// [`HierarchicalPolicy::step_batch`] through candle (both actors for every row, then the
    /// chosen one): the same results to f32 rounding. Slower on a few cores; kept as the
    /// reference the plain path is checked against, and for GPU-style batching.
    pub fn step_batch_candle(
        &self,
        states: &[[f64; 12]],
        state: &mut BatchState,
    ) -> candle_core::Result<Vec<PolicyOutput>> {
        self.check_batch(states, state)?;
        let (b, h) = (state.batch, state.hidden);
        if b == 0 {
            return Ok(Vec::new());
        }
        let device = &self.net.device;
        let x = self.net.normalise(states)?;
        let lstm_state = LSTMState::new(
            Tensor::from_slice(&state.h, (b, h), device)?,
            Tensor::from_slice(&state.c, (b, h), device)?,
        );
        let out = self.net.forward(&x, &lstm_state)?;
        let all = Tensor::cat(&[&out.omega, &out.pos, &out.ori], 1)?
            .flatten_all()?
            .to_vec1::<f32>()?;
        let rows = all
            .chunks_exact(9)
            .zip(states)
            .map(|(row, inputs)| {
                let omega = [row[0], row[1], row[2]];
                let (actor, scale) = select(omega);
                let a = match actor {
                    Actor::Position => [row[3], row[4], row[5]],
                    Actor::Orientation => [row[6], row[7], row[8]],
                };
                compose(&self.net.config, inputs, omega, actor, scale, a)
            })
            .collect();
        let h_new: Vec<f32> = out.state.h.flatten_all()?.to_vec1()?;
        let c_new: Vec<f32> = out.state.c.flatten_all()?.to_vec1()?;
        if !h_new.iter().chain(&c_new).all(|v| v.is_finite()) {
            return Err(candle_core::Error::Msg(
                "the LSTM state is not finite after this step".into(),
            ));
        }
        state.h = h_new;
        state.c = c_new;
        Ok(rows)
    }
}

/// The LSTM states of B episodes for [`HierarchicalPolicy::step_batch`]; rows reset one by one
/// as episodes finish at different times.
#[derive(Debug, Clone, PartialEq)]
pub struct BatchState {
    batch: usize,
    hidden: usize,
    /// [B, H] row-major.
    h: Vec<f32>,
    /// [B, H] row-major.
    c: Vec<f32>,
}

impl BatchState {
    /// B episodes at their start (h = c = 0).
    pub fn new(batch: usize, hidden: usize) -> Self {
        BatchState {
            batch,
            hidden,
            h: vec![0.0; batch * hidden],
            c: vec![0.0; batch * hidden],
        }
    }

    pub fn len(&self) -> usize {
        self.batch
    }

    pub fn is_empty(&self) -> bool {
        self.batch == 0
    }

    /// Starts episode `row` afresh (h = c = 0 for that row).
    pub fn reset_row(&mut self, row: usize) {
        let r = row * self.hidden..(row + 1) * self.hidden;
        self.h[r.clone()].iter_mut().for_each(|v| *v = 0.0);
        self.c[r].iter_mut().for_each(|v| *v = 0.0);
    }

    /// Starts every episode afresh.
    pub fn reset_all(&mut self) {
        self.h.iter_mut().for_each(|v| *v = 0.0);
        self.c.iter_mut().for_each(|v| *v = 0.0);
    }

    /// Row `row`'s h.
    pub fn h(&self, row: usize) -> &[f32] {
        &self.h[row * self.hidden..(row + 1) * self.hidden]
    }

    /// Row `row`'s c.
    pub fn c(&self, row: usize) -> &[f32] {
        &self.c[row * self.hidden..(row + 1) * self.hidden]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::policy::file::TENSOR_NAMES;
    use crate::threads::init_cpu_threads;

    /// A small policy with deterministic pseudo-random weights.
    fn tiny() -> HierarchicalPolicy {
        tiny_reading(PolicyInputs::Absolute)
    }

    /// [`tiny`] reading `inputs`.
    fn tiny_reading(inputs: PolicyInputs) -> HierarchicalPolicy {
        let (h, d) = (4, 8);
        let shape = |name: &str| -> Vec<usize> {
            match name {
                "high.lstm.weight_ih_l0" => vec![4 * h, 12],
                "high.lstm.weight_hh_l0" => vec![4 * h, h],
                "high.lstm.bias_ih_l0" | "high.lstm.bias_hh_l0" => vec![4 * h],
                "high.head.weight" => vec![3, h],
                "high.head.bias" | "pos.4.bias" | "ori.4.bias" => vec![3],
                "pos.0.weight" | "ori.0.weight" => vec![d, 12],
                "pos.2.weight" | "ori.2.weight" => vec![d, d],
                "pos.4.weight" | "ori.4.weight" => vec![3, d],
                "obs_mean" | "obs_std" => vec![12],
                _ => vec![d],
            }
        };
        let mut seed = 12345u32;
        let tensors = TENSOR_NAMES
            .iter()
            .map(|&n| {
                let s = shape(n);
                let len = s.iter().product();
                let data = (0..len)
                    .map(|_| {
                        seed = seed.wrapping_mul(1664525).wrapping_add(1013904223);
                        let u = (seed >> 8) as f32 / (1u32 << 24) as f32;
                        if n == "obs_std" { 1.0 + u } else { u - 0.5 }
                    })
                    .collect();
                (n.to_string(), s, data)
            })
            .collect();
        let mut metadata = PolicyFile::standard_metadata(5.0, 1.0);
        inputs.mark(&mut metadata);
        let file = PolicyFile::new(tensors, metadata).unwrap();
        HierarchicalPolicy::from_file(&file).unwrap()
    }

    #[test]
    fn a_cell_scaled_policy_tilts_in_the_unit_its_inputs_carry() {
        init_cpu_threads();
        // The same weights read the same twelve numbers; only the tilt about x and y of an
        // orientation move is multiplied by the unit in slot 3, on both paths.
        let mut degrees = tiny_reading(PolicyInputs::CellRelative);
        let mut scaled = tiny_reading(PolicyInputs::CellScaled);
        let mut tilts = 0;
        for t in 0..40 {
            let mut state: [f64; 12] =
                std::array::from_fn(|i| ((t * 5 + i * 7) % 13) as f64 * 0.4 - 2.4);
            state[3] = 0.25;
            let a = degrees.step(&state).unwrap();
            let b = scaled.step(&state).unwrap();
            let mut batch = BatchState::new(1, 4);
            let c = scaled.step_batch_candle(&[state], &mut batch).unwrap()[0];
            assert_eq!((a.actor, a.scale), (b.actor, b.scale));
            let expected = PolicyInputs::CellScaled.move_from_units(&state, a.action);
            for (got, want) in b.action.iter().zip(expected) {
                assert!((got - want).abs() < 1e-12);
            }
            if b.actor == Actor::Orientation && a.action[3] != 0.0 {
                tilts += 1;
                assert!((b.action[3] - 0.25 * a.action[3]).abs() < 1e-12);
                assert_eq!(b.action[5], a.action[5]);
            }
            if t == 0 {
                for (got, want) in c.action.iter().zip(b.action) {
                    assert!((got - want).abs() < 1e-5);
                }
            }
        }
        assert!(tilts > 0, "no orientation move among the states");
    }

    /// An observation on the reference cell, the tip `above_mm` above the entrance, level and
    /// on the axis.
    fn observation_above(above_mm: f64) -> crate::sim::Observation {
        crate::policy::shield::tests::observation_above(above_mm)
    }

    #[test]
    fn acting_hands_the_step_to_the_actor_with_work_and_leaves_the_lstm_alone() {
        init_cpu_threads();
        let (mut acting, mut forward) = (tiny(), tiny());
        let mut handed = 0;
        for t in 0..40 {
            let state: [f64; 12] =
                std::array::from_fn(|i| ((t * 7 + i * 3) % 11) as f64 * 0.3 - 1.5);
            // Tilted 1° on even steps; level on odd ones; 10 mm above the bore.
            let mut observation = observation_above(10.0);
            let expected = if t % 2 == 0 {
                (observation.state[9], observation.state[10]) = (0.6, 0.8);
                Actor::Orientation
            } else {
                Actor::Position
            };
            let rule = crate::policy::shield::ActorWithWork::default();
            let proposal = acting
                .propose(&state, &|selected| rule.actor(selected, &observation))
                .unwrap();
            assert_eq!(proposal.selected.omega, proposal.acting.omega);
            let acted = proposal.acting;
            let chosen = forward.step(&state).unwrap();
            assert_eq!((acted.omega, acted.scale), (chosen.omega, chosen.scale));
            assert_eq!(acted.actor, expected);
            if chosen.actor == expected {
                assert_eq!(acted, chosen);
            } else {
                handed += 1;
                let (moved, still) = match expected {
                    Actor::Orientation => (3..6, 0..3),
                    Actor::Position => (0..3, 3..6),
                };
                assert!(acted.action[still].iter().all(|v| *v == 0.0));
                assert!(acted.action[moved].iter().any(|v| *v != 0.0));
            }
        }
        assert!(handed > 0, "the rule never changed the choice");
    }

    #[test]
    fn selection_follows_the_fixed_pass() {
        assert_eq!(select([1.0, 1.0, 0.0]), (Actor::Position, 0.5));
        assert_eq!(select([0.0, 0.5, 0.0]).0, Actor::Orientation);
        assert_eq!(select([0.5, 0.0, 0.0]).0, Actor::Position);
        assert!(select([0.0, 0.0, 200.0]).1 == 1.0 && select([0.0, 0.0, -200.0]).1 == 0.0);
    }

    #[test]
    fn plain_and_candle_paths_agree_and_reset_restarts() {
        init_cpu_threads();
        let mut p = tiny();
        let states: Vec<[f64; 12]> = (0..15)
            .map(|t| std::array::from_fn(|i| ((t * 7 + i * 3) % 11) as f64 * 0.3 - 1.5))
            .collect();
        let first: Vec<PolicyOutput> = states.iter().map(|s| p.step(s).unwrap()).collect();
        p.reset();
        let mut batch = p.batch_state(1);
        for (s, f) in states.iter().zip(&first) {
            let a = p.step(s).unwrap();
            let b = p
                .step_batch_candle(std::slice::from_ref(s), &mut batch)
                .unwrap()[0];
            assert_eq!(&a, f);
            assert_eq!(a.actor, b.actor);
            for (x, y) in a.action.iter().zip(b.action) {
                assert!((x - y).abs() < 1e-5, "{a:?} {b:?}");
            }
            assert!(a.action.iter().all(|v| v.abs() <= 5.0));
        }
    }

    #[test]
    fn a_non_finite_state_is_refused_and_leaves_the_episode_alone() {
        let mut p = tiny();
        let s = [0.25; 12];
        let mut reference = p.clone();
        p.step(&s).unwrap();
        reference.step(&s).unwrap();
        let mut bad = s;
        bad[4] = f64::NAN;
        assert!(
            p.step(&bad)
                .unwrap_err()
                .to_string()
                .contains("state value 4")
        );
        let mut batch = p.batch_state(2);
        assert!(p.step_batch(&[s, bad], &mut batch).is_err());
        assert_eq!(batch, p.batch_state(2));
        assert_eq!(p.step(&s).unwrap(), reference.step(&s).unwrap());
    }

    #[test]
    fn batch_rows_reset_alone() {
        let p = tiny();
        let mut b = p.batch_state(2);
        let s = [[0.1; 12], [0.2; 12]];
        p.step_batch(&s, &mut b).unwrap();
        assert!(b.h(0).iter().any(|v| *v != 0.0) && b.c(1).iter().any(|v| *v != 0.0));
        let row0 = b.h(0).to_vec();
        b.reset_row(1);
        assert!(b.h(1).iter().chain(b.c(1)).all(|v| *v == 0.0));
        assert_eq!(b.h(0), row0.as_slice());
        assert_eq!(b.len(), 2);
    }
}
