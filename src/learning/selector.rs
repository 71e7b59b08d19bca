//! The high-level LSTM selector (paper §3.1, Algorithm 1; Table 1: Adam, lr 1e-3): from the
//! sequence of states of an episode it learns the expert's choice of actor (ω1, ω2 through a
//! softmax: cross-entropy) and step size (sigmoid(ω3): binary cross-entropy against the scale
//! label of `dataset::StepLabels`). The paper writes a squared loss on the LSTM's output; these
//! are the usual losses for a choice and for a fraction, with the same optimum.

use super::bc::{init_linear, vars_under};
use super::dataset::{Normaliser, StepLabels, StepLimits};
use super::demos::DemoEpisode;
use crate::policy::Actor;
use candle_core::{D, DType, Device, Tensor, Var};
use candle_nn::rnn::{LSTM, LSTMConfig, RNN};
use candle_nn::{AdamW, Linear, Module, Optimizer, ParamsAdamW, VarBuilder, VarMap};
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Selector training settings; defaults from Table 1 of the paper.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SelectorConfig {
    pub hidden_size: usize,
    pub epochs: usize,
    /// Episodes per batch.
    pub batch_size: usize,
    pub learning_rate: f64,
    pub seed: u64,
}

impl Default for SelectorConfig {
    fn default() -> Self {
        SelectorConfig {
            hidden_size: 64,
            epochs: 100,
            batch_size: 32,
            learning_rate: 1e-3,
            seed: 0,
        }
    }
}

/// Adds `high.lstm.*` (PyTorch's LSTM initialisation: uniform within ±1/√H) and `high.head.*`.
pub fn init_selector(
    varmap: &VarMap,
    hidden: usize,
    rng: &mut impl Rng,
) -> candle_core::Result<()> {
    let bound = 1.0 / (hidden as f64).sqrt();
    let mut uniform = |shape: &[usize]| -> candle_core::Result<Var> {
        let n = shape.iter().product();
        let values: Vec<f32> = (0..n)
            .map(|_| rng.random_range(-bound..bound) as f32)
            .collect();
        Var::from_tensor(&Tensor::from_vec(values, shape, &Device::Cpu)?)
    };
    let tensors = [
        ("high.lstm.weight_ih_l0", uniform(&[4 * hidden, 12])?),
        ("high.lstm.weight_hh_l0", uniform(&[4 * hidden, hidden])?),
        ("high.lstm.bias_ih_l0", uniform(&[4 * hidden])?),
        ("high.lstm.bias_hh_l0", uniform(&[4 * hidden])?),
    ];
    {
        let mut data = varmap.data().lock().expect("var map lock");
        for (name, var) in tensors {
            data.insert(name.to_string(), var);
        }
    }
    init_linear(varmap, "high.head", hidden, 3, rng)
}

/// One episode as training input: normalised states, actor classes (0 = position), scales.
#[derive(Debug, Clone)]
pub struct SelectorSequence {
    pub inputs: Vec<[f32; 12]>,
    pub classes: Vec<u32>,
    pub scales: Vec<f32>,
}

pub fn sequences(
    episodes: &[DemoEpisode],
    normaliser: &Normaliser,
    limits: &StepLimits,
) -> Vec<SelectorSequence> {
    episodes
        .iter()
        .filter(|e| !e.steps.is_empty())
        .map(|e| SelectorSequence {
            inputs: e.steps.iter().map(|s| normaliser.apply(&s.state)).collect(),
            classes: e
                .steps
                .iter()
                .map(|s| u32::from(s.actor == Actor::Orientation))
                .collect(),
            scales: e
                .steps
                .iter()
                .map(|s| StepLabels::of(s, limits).scale as f32)
                .collect(),
        })
        .collect()
}

/// The selector network: the LSTM and its head, by the policy file's names.
pub struct Selector {
    lstm: LSTM,
    head: Linear,
}

impl Selector {
    pub fn load(vb: VarBuilder, hidden: usize) -> candle_core::Result<Self> {
        let high = vb.pp("high");
        Ok(Selector {
            lstm: candle_nn::lstm(12, hidden, LSTMConfig::default(), high.pp("lstm"))?,
            head: candle_nn::linear(hidden, 3, high.pp("head"))?,
        })
    }

    /// ω for a batch of sequences padded to one length: input [B, T, 12] → [B, T, 3].
    pub fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        let states = self.lstm.seq(x)?;
        let h = self.lstm.states_to_tensor(&states)?;
        self.head.forward(&h)
    }
}

/// Pads a batch: inputs [B, T, 12], class one-hots [B, T, 2], scales [B, T], mask [B, T].
fn pad(batch: &[&SelectorSequence]) -> candle_core::Result<[Tensor; 4]> {
    let length = batch.iter().map(|s| s.inputs.len()).max().unwrap_or(0);
    let rows = batch.len();
    let (mut x, mut onehot, mut scale, mut mask) = (
        vec![0f32; rows * length * 12],
        vec![0f32; rows * length * 2],
        vec![0f32; rows * length],
        vec![0f32; rows * length],
    );
    for (b, sequence) in batch.iter().enumerate() {
        for t in 0..sequence.inputs.len() {
            let at = b * length + t;
            x[at * 12..at * 12 + 12].copy_from_slice(&sequence.inputs[t]);
            onehot[at * 2 + sequence.classes[t] as usize] = 1.0;
            scale[at] = sequence.scales[t];
            mask[at] = 1.0;
        }
    }
    let device = &Device::Cpu;
    Ok([
        Tensor::from_vec(x, (rows, length, 12), device)?,
        Tensor::from_vec(onehot, (rows, length, 2), device)?,
        Tensor::from_vec(scale, (rows, length), device)?,
        Tensor::from_vec(mask, (rows, length), device)?,
    ])
}

/// Masked mean of cross-entropy (actor) plus binary cross-entropy (scale).
fn loss(selector: &Selector, batch: &[&SelectorSequence]) -> candle_core::Result<Tensor> {
    let [x, onehot, scale, mask] = pad(batch)?;
    let omega = selector.forward(&x)?;
    let logits = omega.narrow(D::Minus1, 0, 2)?;
    let z = omega.narrow(D::Minus1, 2, 1)?.squeeze(D::Minus1)?;
    let cross_entropy = (candle_nn::ops::log_softmax(&logits, D::Minus1)? * onehot)?
        .sum(D::Minus1)?
        .neg()?;
    // BCE with logits, stably: max(z, 0) − z·s + log(1 + e^−|z|).
    let bce = ((z.relu()? - (&z * &scale)?)? + (z.abs()?.neg()?.exp()? + 1.0)?.log()?)?;
    let per_step = ((cross_entropy + bce)? * &mask)?;
    per_step.sum_all()? / mask.sum_all()?.to_scalar::<f32>()? as f64
}

/// Trains `high.*` (already in `varmap`) with Adam; `on_epoch(epoch, loss)` after each epoch.
pub fn train_selector(
    varmap: &VarMap,
    data: &[SelectorSequence],
    config: &SelectorConfig,
    on_epoch: &mut dyn FnMut(usize, f64),
) -> candle_core::Result<Vec<f64>> {
    if data.is_empty() {
        candle_core::bail!("no demonstrations to train the selector on");
    }
    let vb = VarBuilder::from_varmap(varmap, DType::F32, &Device::Cpu);
    let selector = Selector::load(vb, config.hidden_size)?;
    let params = ParamsAdamW {
        lr: config.learning_rate,
        weight_decay: 0.0,
        ..ParamsAdamW::default()
    };
    let mut optimizer = AdamW::new(vars_under(varmap, "high."), params)?;
    let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
    let mut order: Vec<usize> = (0..data.len()).collect();
    let mut losses = Vec::with_capacity(config.epochs);
    for epoch in 0..config.epochs {
        order.shuffle(&mut rng);
        let mut total = 0.0;
        for rows in order.chunks(config.batch_size.max(1)) {
            let batch: Vec<&SelectorSequence> = rows.iter().map(|&i| &data[i]).collect();
            let loss = loss(&selector, &batch)?;
            total += f64::from(loss.to_scalar::<f32>()?) * rows.len() as f64;
            optimizer.backward_step(&loss)?;
        }
        let epoch_loss = total / data.len() as f64;
        if !epoch_loss.is_finite() {
            candle_core::bail!("selector training diverged at epoch {epoch} (loss {epoch_loss})");
        }
        on_epoch(epoch, epoch_loss);
        losses.push(epoch_loss);
    }
    Ok(losses)
}

/// The fraction of steps at which the selector picks the expert's actor (the position actor
/// when p_pos ≥ p_ori, docs/design.md §6), over whole episodes run from a zero LSTM state.
pub fn agreement(
    varmap: &VarMap,
    hidden: usize,
    data: &[SelectorSequence],
) -> candle_core::Result<f64> {
    let vb = VarBuilder::from_varmap(varmap, DType::F32, &Device::Cpu);
    let selector = Selector::load(vb, hidden)?;
    let (mut agree, mut total) = (0usize, 0usize);
    for sequence in data {
        let [x, ..] = pad(&[sequence])?;
        let omega = selector.forward(&x)?.squeeze(0)?.to_vec2::<f32>()?;
        for (w, class) in omega.iter().zip(&sequence.classes) {
            let picked = u32::from(w[0] < w[1]);
            agree += usize::from(picked == *class);
            total += 1;
        }
    }
    Ok(agree as f64 / total.max(1) as f64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::cell::CellConfig;
    use crate::learning::dataset::GoalScales;
    use crate::learning::demos::{DEFAULT_DEMONSTRATOR, record};
    use crate::policy::inputs::PolicyInputs;
    use crate::sim::EnvOptions;

    #[test]
    fn the_selector_agrees_with_the_expert_on_held_out_demonstrations() {
        // As `celld train` trains it: the default demonstrator, the goal-centred normaliser.
        let cell = CellConfig::reference();
        let options = EnvOptions::from_cell(&cell);
        let train = record(&cell, options, DEFAULT_DEMONSTRATOR, 128, 11);
        let held_out = record(&cell, options, DEFAULT_DEMONSTRATOR, 16, 12);
        let normaliser =
            Normaliser::fit(&train).goal_centred(GoalScales::default(), PolicyInputs::Absolute);
        let limits = StepLimits {
            position_mm: 5.0,
            orientation_deg: 1.0,
            inputs: PolicyInputs::Absolute,
        };
        let config = SelectorConfig {
            hidden_size: 64,
            epochs: 60,
            batch_size: 8,
            learning_rate: 5e-3,
            seed: 4,
        };
        let varmap = VarMap::new();
        init_selector(
            &varmap,
            config.hidden_size,
            &mut ChaCha8Rng::seed_from_u64(4),
        )
        .unwrap();
        let losses = train_selector(
            &varmap,
            &sequences(&train, &normaliser, &limits),
            &config,
            &mut |_, _| {},
        )
        .unwrap();
        assert!(losses[losses.len() - 1] < losses[0], "{losses:?}");
        let agreement = agreement(
            &varmap,
            config.hidden_size,
            &sequences(&held_out, &normaliser, &limits),
        )
        .unwrap();
        eprintln!(
            "held-out agreement {agreement:.4}; loss {:.4} → {:.4}",
            losses[0],
            losses[losses.len() - 1]
        );
        assert!(agreement >= 0.95, "agreement {agreement}");
    }
}
