//! The one multilayer perceptron of every actor and critic: Linear-ReLU-Linear-ReLU-Linear,
//! with a tanh on the output for actors. Layers carry PyTorch `nn.Sequential` names, `0`, `2`
//! and `4` (the ReLUs are `1` and `3`), so an actor under `pos` has the tensors
//! `pos.0.weight`, `pos.0.bias`, … `pos.4.bias`.
//!
//! Two evaluators read the same definition ([`MlpConfig::layers`]):
//!
//! - [`Mlp`], in candle: training (behaviour cloning, TD3's actors and critics) and the
//!   reference the fast path is checked against;
//! - [`PlainMlp`], plain f32 loops for one state at a time: the learned controllers' decisions,
//!   where candle's per-op overhead would dominate at these sizes.

use candle_core::{Module, Tensor};
use candle_nn::{Linear, VarBuilder};

/// Each layer's name, in order: the indices of the Linear modules in PyTorch's
/// `nn.Sequential(Linear, ReLU, Linear, ReLU, Linear[, Tanh])`.
pub const LAYER_NAMES: [&str; 3] = ["0", "2", "4"];

/// Sizes of one MLP, and whether its output goes through tanh.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MlpConfig {
    /// Size of the input.
    pub inputs: usize,
    /// Width of both hidden layers.
    pub hidden: usize,
    /// Size of the output.
    pub outputs: usize,
    /// tanh on the output (actors: outputs in [−1, 1]); none for critics.
    pub tanh: bool,
}

impl MlpConfig {
    /// An actor: outputs in [−1, 1] (tanh).
    pub fn actor(inputs: usize, hidden: usize, outputs: usize) -> Self {
        MlpConfig {
            inputs,
            hidden,
            outputs,
            tanh: true,
        }
    }

    /// A critic: one unbounded value.
    pub fn critic(inputs: usize, hidden: usize) -> Self {
        MlpConfig {
            inputs,
            hidden,
            outputs: 1,
            tanh: false,
        }
    }

    /// The layers, in order: name ([`LAYER_NAMES`]), inputs, outputs. Loading, initialising
    /// and the plain evaluator all go through this list.
    pub fn layers(&self) -> [(&'static str, usize, usize); 3] {
        [
            (LAYER_NAMES[0], self.inputs, self.hidden),
            (LAYER_NAMES[1], self.hidden, self.hidden),
            (LAYER_NAMES[2], self.hidden, self.outputs),
        ]
    }
}

/// The MLP in candle (f32), loaded by name from a `VarBuilder`.
#[derive(Debug, Clone)]
pub struct Mlp {
    layers: [Linear; 3],
    config: MlpConfig,
}

impl Mlp {
    /// Loads the layers `{vb prefix}.0`, `.2`, `.4` (`weight` [out, in] and `bias` [out]).
    pub fn load(vb: VarBuilder, config: &MlpConfig) -> candle_core::Result<Self> {
        let [l0, l2, l4] = config.layers();
        let linear = |(name, inputs, outputs): (&str, usize, usize)| {
            candle_nn::linear(inputs, outputs, vb.pp(name))
        };
        Ok(Mlp {
            layers: [linear(l0)?, linear(l2)?, linear(l4)?],
            config: *config,
        })
    }

    pub fn config(&self) -> &MlpConfig {
        &self.config
    }
}

impl Module for Mlp {
    /// `x` [B, inputs] → [B, outputs].
    fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        let x = self.layers[0].forward(x)?.relu()?;
        let x = self.layers[1].forward(&x)?.relu()?;
        let y = self.layers[2].forward(&x)?;
        if self.config.tanh { y.tanh() } else { Ok(y) }
    }
}

/// A dense layer y = W x + b. W is kept transposed, [in, out] (PyTorch stores [out, in]), so the
/// product runs as a sum of scaled columns, which the compiler vectorises without reordering any
/// reduction.
#[derive(Debug, Clone)]
pub(crate) struct Dense {
    outputs: usize,
    /// W transposed: column j of W (the weights of input j) at `wt[j * outputs..]`.
    wt: Vec<f32>,
    b: Vec<f32>,
}

impl Dense {
    /// From PyTorch's row-major [out, in] weights.
    pub(crate) fn new(w: &[f32], b: Vec<f32>, inputs: usize) -> Self {
        let outputs = b.len();
        assert_eq!(w.len(), inputs * outputs, "weights of a dense layer");
        let mut wt = vec![0.0; w.len()];
        for (o, row) in w.chunks_exact(inputs).enumerate() {
            for (i, v) in row.iter().enumerate() {
                wt[i * outputs + o] = *v;
            }
        }
        Dense { outputs, wt, b }
    }

    /// The `Linear(inputs → outputs)` under `vb` (`weight`, `bias`).
    pub(crate) fn from_linear(
        vb: &VarBuilder,
        inputs: usize,
        outputs: usize,
    ) -> candle_core::Result<Self> {
        let w: Vec<f32> = vb
            .get((outputs, inputs), "weight")?
            .flatten_all()?
            .to_vec1()?;
        Ok(Dense::new(&w, vb.get(outputs, "bias")?.to_vec1()?, inputs))
    }

    /// y = W x + b.
    pub(crate) fn forward(&self, x: &[f32], y: &mut [f32]) {
        let n = self.outputs;
        let y = &mut y[..n];
        y.copy_from_slice(&self.b);
        // Four columns at a time: a quarter of the loads and stores of y.
        let mut cols = self.wt.chunks_exact(4 * n);
        let mut xs = x.chunks_exact(4);
        for (c, xq) in cols.by_ref().zip(xs.by_ref()) {
            let (c0, rest) = c.split_at(n);
            let (c1, rest) = rest.split_at(n);
            let (c2, c3) = rest.split_at(n);
            let (x0, x1, x2, x3) = (xq[0], xq[1], xq[2], xq[3]);
            for i in 0..n {
                y[i] += (c0[i] * x0 + c1[i] * x1) + (c2[i] * x2 + c3[i] * x3);
            }
        }
        for (c, &xj) in cols.remainder().chunks_exact(n).zip(xs.remainder()) {
            for (yi, wi) in y.iter_mut().zip(c) {
                *yi += wi * xj;
            }
        }
    }
}

/// The MLP as plain f32 loops, for one input at a time: the same layers as [`Mlp`], the same
/// results to f32 rounding.
#[derive(Debug, Clone)]
pub(crate) struct PlainMlp {
    layers: [Dense; 3],
    config: MlpConfig,
}

impl PlainMlp {
    /// From each layer's row-major [out, in] weights and its bias: `weights(name, inputs,
    /// outputs)` for every layer of [`MlpConfig::layers`].
    pub(crate) fn new<E>(
        config: &MlpConfig,
        mut weights: impl FnMut(&str, usize, usize) -> Result<(Vec<f32>, Vec<f32>), E>,
    ) -> Result<Self, E> {
        let [l0, l2, l4] = config.layers().map(|(name, inputs, outputs)| {
            weights(name, inputs, outputs).map(|(w, b)| Dense::new(&w, b, inputs))
        });
        Ok(PlainMlp {
            layers: [l0?, l2?, l4?],
            config: *config,
        })
    }

    /// Loads the layers under `vb`, as [`Mlp::load`] does.
    pub(crate) fn load(vb: &VarBuilder, config: &MlpConfig) -> candle_core::Result<Self> {
        let [l0, l2, l4] = config.layers();
        let dense = |(name, inputs, outputs): (&str, usize, usize)| {
            Dense::from_linear(&vb.pp(name), inputs, outputs)
        };
        Ok(PlainMlp {
            layers: [dense(l0)?, dense(l2)?, dense(l4)?],
            config: *config,
        })
    }

    pub(crate) fn config(&self) -> &MlpConfig {
        &self.config
    }

    /// `y` (`outputs` values) for the input `x`; `s1` and `s2` (`hidden` values each) are
    /// working memory for the hidden layers.
    pub(crate) fn forward(&self, x: &[f32], s1: &mut [f32], s2: &mut [f32], y: &mut [f32]) {
        self.layers[0].forward(x, s1);
        s1.iter_mut().for_each(|v| *v = v.max(0.0));
        self.layers[1].forward(s1, s2);
        s2.iter_mut().for_each(|v| *v = v.max(0.0));
        self.layers[2].forward(s2, y);
        if self.config.tanh {
            y[..self.config.outputs]
                .iter_mut()
                .for_each(|v| *v = v.tanh());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device};
    use candle_nn::VarMap;

    /// The candle and plain evaluators of one definition agree, with and without tanh, and
    /// the tensors are named as PyTorch names them.
    #[test]
    fn candle_and_plain_evaluators_agree() {
        for config in [MlpConfig::actor(5, 7, 3), MlpConfig::critic(6, 4)] {
            let vars = VarMap::new();
            let vb = VarBuilder::from_varmap(&vars, DType::F32, &Device::Cpu);
            let mlp = Mlp::load(vb.pp("net"), &config).unwrap();
            let mut names: Vec<String> = vars.data().lock().unwrap().keys().cloned().collect();
            names.sort();
            assert_eq!(
                names,
                [
                    "net.0.bias",
                    "net.0.weight",
                    "net.2.bias",
                    "net.2.weight",
                    "net.4.bias",
                    "net.4.weight"
                ]
            );
            let plain = PlainMlp::load(&vb.pp("net"), &config).unwrap();
            assert_eq!(plain.config(), mlp.config());
            let x: Vec<f32> = (0..config.inputs).map(|i| i as f32 * 0.3 - 0.7).collect();
            let want: Vec<f32> = mlp
                .forward(&Tensor::from_slice(&x, (1, config.inputs), &Device::Cpu).unwrap())
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1()
                .unwrap();
            let (mut s1, mut s2) = (vec![0.0; config.hidden], vec![0.0; config.hidden]);
            let mut got = vec![0.0; config.outputs];
            plain.forward(&x, &mut s1, &mut s2, &mut got);
            for (g, w) in got.iter().zip(&want) {
                assert!((g - w).abs() < 1e-5, "{got:?} vs {want:?}");
            }
        }
    }
}
