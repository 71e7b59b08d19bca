//! The forward pass as plain f32 loops, one episode (row) at a time: at the policy's sizes
//! candle's per-op overhead dominates a batch-1 step, and the loops evaluate only the actor
//! that acts (`cargo bench --bench policy`).

use super::{
    ChooseActor, PolicyConfig, PolicyOutput, actor_config, compose, normalise, select, sigmoid,
    state_error,
};
use crate::policy::Actor;
use crate::policy::file::{ACTOR_DIM, HEAD_DIM, STATE_DIM};
use crate::policy::mlp::{Dense, PlainMlp};
use candle_nn::VarBuilder;

/// The network as plain f32 loops, one episode (row) at a time.
#[derive(Debug, Clone)]
pub(super) struct PlainNet {
    hidden: usize,
    width: usize,
    /// [W_ih | W_hh]: [4H, 12 + H], so one matrix-vector product gives the gates.
    w_gates: Dense,
    head: Dense,
    pos: PlainMlp,
    ori: PlainMlp,
    obs_mean: [f64; 12],
    obs_std: [f64; 12],
    config: PolicyConfig,
}

/// Working memory of the plain path (no allocation per step).
#[derive(Debug, Clone)]
pub(super) struct Scratch {
    /// [x (12) | h (H)]: the LSTM's input.
    xh: Vec<f32>,
    gates: Vec<f32>,
    s1: Vec<f32>,
    s2: Vec<f32>,
}

impl PlainNet {
    pub(super) fn load(vb: &VarBuilder, config: &PolicyConfig) -> candle_core::Result<Self> {
        let (h, d) = (config.hidden_size, config.actor_width);
        let lstm = vb.pp("high").pp("lstm");
        let get = |shape: (usize, usize), name: &str| -> candle_core::Result<Vec<f32>> {
            lstm.get(shape, name)?.flatten_all()?.to_vec1()
        };
        let w_ih = get((4 * h, STATE_DIM), "weight_ih_l0")?;
        let w_hh = get((4 * h, h), "weight_hh_l0")?;
        let b_ih: Vec<f32> = lstm.get(4 * h, "bias_ih_l0")?.to_vec1()?;
        let b_hh: Vec<f32> = lstm.get(4 * h, "bias_hh_l0")?.to_vec1()?;
        let mut w = Vec::with_capacity(4 * h * (STATE_DIM + h));
        for (ri, rh) in w_ih.chunks_exact(STATE_DIM).zip(w_hh.chunks_exact(h)) {
            w.extend_from_slice(ri);
            w.extend_from_slice(rh);
        }
        let b = b_ih.iter().zip(&b_hh).map(|(a, b)| a + b).collect();
        let to_array = |name: &str| -> candle_core::Result<[f64; 12]> {
            let v: Vec<f32> = vb.get(STATE_DIM, name)?.to_vec1()?;
            Ok(std::array::from_fn(|i| v[i] as f64))
        };
        Ok(PlainNet {
            hidden: h,
            width: d,
            w_gates: Dense::new(&w, b, STATE_DIM + h),
            head: Dense::from_linear(&vb.pp("high").pp("head"), h, HEAD_DIM)?,
            pos: PlainMlp::load(&vb.pp("pos"), &actor_config(d))?,
            ori: PlainMlp::load(&vb.pp("ori"), &actor_config(d))?,
            obs_mean: to_array("obs_mean")?,
            obs_std: to_array("obs_std")?,
            config: *config,
        })
    }

    pub(super) fn scratch(&self) -> Scratch {
        Scratch {
            xh: vec![0.0; STATE_DIM + self.hidden],
            gates: vec![0.0; 4 * self.hidden],
            s1: vec![0.0; self.width],
            s2: vec![0.0; self.width],
        }
    }

    /// One step of one episode: reads h, c and writes the next ones into `h_out`, `c_out`; the
    /// actor `choose` names for the selector's choice acts. On an error the caller keeps h, c
    /// (the outputs are then garbage).
    pub(super) fn step(
        &self,
        state: &[f64; 12],
        (h, c): (&[f32], &[f32]),
        (h_out, c_out): (&mut [f32], &mut [f32]),
        s: &mut Scratch,
        choose: ChooseActor<'_>,
    ) -> candle_core::Result<PolicyOutput> {
        if let Some(e) = state_error(state) {
            return Err(e);
        }
        let hidden = self.hidden;
        normalise(state, &self.obs_mean, &self.obs_std, &mut s.xh[..STATE_DIM]);
        s.xh[STATE_DIM..].copy_from_slice(h);
        self.w_gates.forward(&s.xh, &mut s.gates);
        // PyTorch: gates i, f, g, o; c' = f c + i g; h' = o tanh(c').
        let (i_g, rest) = s.gates.split_at(hidden);
        let (f_g, rest) = rest.split_at(hidden);
        let (g_g, o_g) = rest.split_at(hidden);
        for k in 0..hidden {
            let c_new = sigmoid(f_g[k]) * c[k] + sigmoid(i_g[k]) * g_g[k].tanh();
            c_out[k] = c_new;
            h_out[k] = sigmoid(o_g[k]) * c_new.tanh();
        }
        if !c_out.iter().chain(h_out.iter()).all(|v| v.is_finite()) {
            return Err(candle_core::Error::Msg(
                "the LSTM state is not finite after this step".into(),
            ));
        }
        let mut omega = [0f32; 3];
        self.head.forward(h_out, &mut omega);
        let (selected, _) = select(omega);
        Ok(self.actor_output(state, s, omega, choose(selected)))
    }

    /// The output with `actor` acting, for the step whose normalised input `s` holds (the last
    /// [`PlainNet::step`] on `state`) and whose head gave `omega`.
    pub(super) fn actor_output(
        &self,
        state: &[f64; 12],
        s: &mut Scratch,
        omega: [f32; 3],
        actor: Actor,
    ) -> PolicyOutput {
        let (_, scale) = select(omega);
        let actor_net = match actor {
            Actor::Position => &self.pos,
            Actor::Orientation => &self.ori,
        };
        let mut a = [0f32; ACTOR_DIM];
        actor_net.forward(&s.xh[..STATE_DIM], &mut s.s1, &mut s.s2, &mut a);
        compose(&self.config, state, omega, actor, scale, a)
    }
}
