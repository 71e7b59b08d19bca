//! The flat TD3 baseline: one actor that gives the whole 6-DoF move, with no
//! LSTM selector and no behaviour cloning: the paper's "TD3" comparison and its third Fig. 7
//! curve ("a single 6-DoF policy"). `celld train flat` trains it (`learning::flat`); the bundled
//! one is the controller `td3`.
//!
//! A flat policy file is a safetensors file, f32, with PyTorch `state_dict` names:
//!
//! ```text
//! actor.0.weight [D, 12]  actor.0.bias [D]  actor.2.weight [D, D]  actor.2.bias [D]
//! actor.4.weight [6, D]   actor.4.bias [6]      (Linear-ReLU-Linear-ReLU-Linear-Tanh)
//! obs_mean [12]  obs_std [12]
//! ```
//!
//! and `__metadata__` `format = "assembly-cell/flat-policy"`, `format_version = "1"`,
//! `step_limit_mm`, `step_limit_deg`. It is checked by the same code as a hierarchical policy
//! file (`super::file`): container, metadata, names, dtypes, shapes and values, each refusal
//! naming the tensor or key.
//!
//! The forward pass:
//!
//! ```text
//! x    = (s - obs_mean) / obs_std            in f64, then f32
//! a    = actor(x)                             6 values in [-1, 1] (tanh output)
//! move = (a0, a1, a2) · step_limit_mm  (Δx, Δy, Δz),  (a3, a4, a5) · step_limit_deg  (θx, θy, θz)
//! ```

use super::file::{
    self, Checked, PolicyFileError, PolicyKind, PolicyMetadata, PolicyTensor, STATE_DIM,
};
use super::inputs::PolicyInputs;
use super::mlp::{MlpConfig, PlainMlp};
use super::{Controller, Decision};
use crate::geometry::Move;
use crate::sim::Observation;
use std::collections::BTreeMap;
use std::path::Path;

/// The flat file's format and tensors are declared with the container's (`super::file`), which
/// tells the two kinds of policy file apart.
pub use super::file::{FLAT_FORMAT as FORMAT, FLAT_TENSOR_NAMES as TENSOR_NAMES};

/// Outputs of the actor: the whole move.
pub const ACTION_DIM: usize = 6;

/// The actor's configuration for a hidden width `width`: the 12-value state in, the 6-value
/// move in [−1, 1] out (`actor.0`, `.2`, `.4`).
pub fn actor_config(width: usize) -> MlpConfig {
    MlpConfig::actor(STATE_DIM, width, ACTION_DIM)
}

/// A checked flat policy file: every tensor of [`TENSOR_NAMES`] with consistent shapes and
/// finite values, and the metadata (format, version, step limits).
#[derive(Debug, Clone, PartialEq)]
pub struct FlatPolicyFile {
    tensors: BTreeMap<String, PolicyTensor>,
    raw_metadata: BTreeMap<String, String>,
    metadata: PolicyMetadata,
    width: usize,
}

impl FlatPolicyFile {
    /// Reads and checks a flat policy file.
    pub fn from_path(path: impl AsRef<Path>) -> Result<Self, PolicyFileError> {
        Self::from_bytes(&file::read_path(path.as_ref())?)
    }

    /// Parses and checks the bytes of a flat policy file.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, PolicyFileError> {
        Ok(Self::from_checked(file::check_bytes(
            bytes,
            PolicyKind::Flat,
            check_shapes,
        )?))
    }

    /// A flat policy from tensors built in memory (name, shape, row-major values) and the
    /// metadata, checked exactly as a file is.
    pub fn new(
        tensors: Vec<(String, Vec<usize>, Vec<f32>)>,
        metadata: BTreeMap<String, String>,
    ) -> Result<Self, PolicyFileError> {
        Ok(Self::from_checked(file::check_in_memory(
            tensors,
            metadata,
            PolicyKind::Flat,
            check_shapes,
        )?))
    }

    fn from_checked(checked: Checked<usize>) -> Self {
        FlatPolicyFile {
            tensors: checked.tensors,
            raw_metadata: checked.raw_metadata,
            metadata: checked.metadata,
            width: checked.sizes,
        }
    }

    /// The metadata a flat policy file needs (format, version, step limits); add any provenance
    /// keys to the returned map.
    pub fn standard_metadata(step_limit_mm: f64, step_limit_deg: f64) -> BTreeMap<String, String> {
        file::standard_metadata(PolicyKind::Flat, step_limit_mm, step_limit_deg)
    }

    /// The bytes of a safetensors file holding this policy (deterministic: tensors in
    /// [`TENSOR_NAMES`] order, header keys sorted).
    pub fn to_bytes(&self) -> Vec<u8> {
        file::encode(&self.raw_metadata, &TENSOR_NAMES, &self.tensors)
    }

    /// Writes [`FlatPolicyFile::to_bytes`] to `path`.
    pub fn save(&self, path: impl AsRef<Path>) -> Result<(), PolicyFileError> {
        file::write_path(path.as_ref(), &self.to_bytes())
    }

    /// The checked metadata.
    pub fn metadata(&self) -> &PolicyMetadata {
        &self.metadata
    }

    /// `__metadata__` exactly as stored (all keys, required and extra).
    pub fn raw_metadata(&self) -> &BTreeMap<String, String> {
        &self.raw_metadata
    }

    pub fn step_limit_mm(&self) -> f64 {
        self.metadata.step_limit_mm
    }

    pub fn step_limit_deg(&self) -> f64 {
        self.metadata.step_limit_deg
    }

    /// D: the actor's hidden width, from `actor.0.weight` [D, 12].
    pub fn width(&self) -> usize {
        self.width
    }

    /// One tensor by name.
    pub fn tensor(&self, name: &str) -> Option<&PolicyTensor> {
        self.tensors.get(name)
    }

    /// Every tensor, in [`TENSOR_NAMES`] order.
    pub fn tensors(&self) -> impl Iterator<Item = (&'static str, &PolicyTensor)> {
        TENSOR_NAMES.iter().map(|&n| (n, &self.tensors[n]))
    }

    /// Name → shape of every tensor, in [`TENSOR_NAMES`] order.
    pub fn shapes(&self) -> Vec<(String, Vec<usize>)> {
        self.tensors()
            .map(|(n, t)| (n.to_string(), t.shape.clone()))
            .collect()
    }

    /// Total number of parameters.
    pub fn parameter_count(&self) -> usize {
        self.tensors.values().map(|t| t.data.len()).sum()
    }
}

/// Checks every shape of a flat policy; returns D.
fn check_shapes(shapes: &BTreeMap<&str, &[usize]>) -> Result<usize, PolicyFileError> {
    let d = match *shapes["actor.0.weight"] {
        [d, STATE_DIM] if d > 0 => d,
        _ => {
            return Err(file::wrong_shape(
                shapes,
                "actor.0.weight",
                format!("[D, {STATE_DIM}] with D ≥ 1 (the actor's first layer)"),
            ));
        }
    };
    let from_d = format!("with D = {d} from actor.0.weight");
    file::expect_shapes(
        shapes,
        vec![
            ("actor.0.bias", vec![d], format!("D {from_d}")),
            ("actor.2.weight", vec![d, d], format!("D×D {from_d}")),
            ("actor.2.bias", vec![d], format!("D {from_d}")),
            (
                "actor.4.weight",
                vec![ACTION_DIM, d],
                format!("6×D {from_d}"),
            ),
            (
                "actor.4.bias",
                vec![ACTION_DIM],
                "the actor's 6 outputs".to_string(),
            ),
            (
                "obs_mean",
                vec![STATE_DIM],
                "the 12 state means".to_string(),
            ),
            (
                "obs_std",
                vec![STATE_DIM],
                "the 12 state deviations".to_string(),
            ),
        ],
    )?;
    Ok(d)
}

/// The flat policy, ready to run (plain f32 loops; the normalisation in f64).
#[derive(Debug, Clone)]
pub struct FlatPolicy {
    name: String,
    actor: PlainMlp,
    obs_mean: [f64; 12],
    obs_std: [f64; 12],
    step_limit_mm: f64,
    step_limit_deg: f64,
    /// What the network reads (`super::inputs`).
    inputs: PolicyInputs,
    /// Working memory: the two hidden layers.
    s1: Vec<f32>,
    s2: Vec<f32>,
}

impl FlatPolicy {
    /// The longest move along any axis of {M} (mm).
    pub fn step_limit_mm(&self) -> f64 {
        self.step_limit_mm
    }

    /// The longest turn about any axis of {M} (deg).
    pub fn step_limit_deg(&self) -> f64 {
        self.step_limit_deg
    }

    /// The policy of a checked flat policy file (named "td3").
    pub fn from_file(file: &FlatPolicyFile) -> Self {
        let d = file.width();
        let weights = |layer: &str, _, _| {
            let tensor = |part: &str| file.tensors[&format!("actor.{layer}.{part}")].data.clone();
            Ok::<_, std::convert::Infallible>((tensor("weight"), tensor("bias")))
        };
        let Ok(actor) = PlainMlp::new(&actor_config(d), weights);
        let array = |name: &str| -> [f64; 12] {
            let v = &file.tensors[name].data;
            std::array::from_fn(|i| f64::from(v[i]))
        };
        FlatPolicy {
            name: "td3".to_string(),
            actor,
            obs_mean: array("obs_mean"),
            obs_std: array("obs_std"),
            step_limit_mm: file.step_limit_mm(),
            step_limit_deg: file.step_limit_deg(),
            inputs: file.metadata.inputs,
            s1: vec![0.0; d],
            s2: vec![0.0; d],
        }
    }

    /// Reads, checks and loads a flat policy file; the controller is named after the file's
    /// stem.
    pub fn from_path(path: impl AsRef<Path>) -> anyhow::Result<Self> {
        let path = path.as_ref();
        let policy = Self::from_file(&FlatPolicyFile::from_path(path)?);
        let name = path
            .file_stem()
            .map_or("td3".to_string(), |s| s.to_string_lossy().into_owned());
        Ok(policy.with_name(name))
    }

    /// Renames the controller (default "td3").
    pub fn with_name(mut self, name: impl Into<String>) -> Self {
        self.name = name.into();
        self
    }

    /// D: the actor's hidden width.
    pub fn width(&self) -> usize {
        self.actor.config().hidden
    }

    /// The step limits (mm, deg) the actor's outputs are scaled by.
    pub fn step_limits(&self) -> (f64, f64) {
        (self.step_limit_mm, self.step_limit_deg)
    }

    /// The network's input: (s − obs_mean) / obs_std, in f64, then f32.
    pub fn normalise(&self, state: &[f64; 12]) -> [f32; 12] {
        std::array::from_fn(|i| ((state[i] - self.obs_mean[i]) / self.obs_std[i]) as f32)
    }

    /// The actor's tanh outputs for a normalised input: 6 values in [−1, 1].
    pub fn actor(&mut self, x: &[f32; 12]) -> [f32; 6] {
        let mut a = [0f32; ACTION_DIM];
        self.actor.forward(x, &mut self.s1, &mut self.s2, &mut a);
        a
    }

    /// The move `[Δx, Δy, Δz, θx, θy, θz]` (mm, deg) of the actor's outputs `a`.
    pub fn to_move(&self, a: &[f32; 6]) -> [f64; 6] {
        std::array::from_fn(|i| {
            let limit = if i < 3 {
                self.step_limit_mm
            } else {
                self.step_limit_deg
            };
            f64::from(a[i]) * limit
        })
    }

    /// The move for a state. A non-finite state, or a non-finite output, is an error.
    pub fn step(&mut self, state: &[f64; 12]) -> candle_core::Result<[f64; 6]> {
        if let Some(i) = state.iter().position(|v| !v.is_finite()) {
            candle_core::bail!("state value {i} is {}, not a finite number", state[i]);
        }
        let x = self.normalise(state);
        let a = self.actor(&x);
        if a.iter().any(|v| !v.is_finite()) {
            candle_core::bail!("the flat policy's output {a:?} is not finite");
        }
        Ok(self.to_move(&a))
    }
}

impl Controller for FlatPolicy {
    fn name(&self) -> &str {
        &self.name
    }

    fn reset(&mut self, _seed: u64) {}

    /// The actor's move, with no actor or scale labels (there is no hierarchy). Without a fresh
    /// frame, or when the step fails, it holds still.
    fn act(&mut self, observation: &Observation) -> Decision {
        if !observation.measurement_fresh {
            return Decision::hold();
        }
        match self.step(&self.inputs.of(observation)) {
            Ok(action) => Decision::plain(Move::from_array(action)),
            Err(_) => Decision::hold(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::cell::CellConfig;
    use crate::sim::{AssemblyEnv, EnvOptions};

    /// The hand-computed case: D = 2, limits 5 mm / 1 deg.
    fn hand() -> Vec<(String, Vec<usize>, Vec<f32>)> {
        let mut w0 = vec![0.0f32; 24];
        w0[0] = 1.0; // row 0 reads x0
        w0[12 + 1] = -1.0; // row 1 reads −x1
        #[rustfmt::skip]
        let w4 = vec![
            0.1, 0.0,
            0.0, 0.1,
            -0.2, 0.0,
            0.0, 0.0,
            0.4, -0.4,
            0.0, -1.0,
        ];
        vec![
            ("actor.0.weight".into(), vec![2, 12], w0),
            ("actor.0.bias".into(), vec![2], vec![0.5, 0.25]),
            (
                "actor.2.weight".into(),
                vec![2, 2],
                vec![1.0, 0.0, 1.0, 1.0],
            ),
            ("actor.2.bias".into(), vec![2], vec![0.0, -1.0]),
            ("actor.4.weight".into(), vec![6, 2], w4),
            (
                "actor.4.bias".into(),
                vec![6],
                vec![0.0, 0.0, 0.0, 0.5, 0.0, 0.0],
            ),
            ("obs_mean".into(), vec![12], vec![1.0; 12]),
            ("obs_std".into(), vec![12], vec![2.0; 12]),
        ]
    }

    fn meta() -> BTreeMap<String, String> {
        FlatPolicyFile::standard_metadata(5.0, 1.0)
    }

    /// A safetensors file written by hand (any dtype, any tensors), to build bad files.
    fn raw(
        tensors: &[(&str, &str, Vec<usize>, Vec<u8>)],
        meta: &BTreeMap<String, String>,
    ) -> Vec<u8> {
        let mut header = serde_json::Map::new();
        header.insert("__metadata__".into(), serde_json::json!(meta));
        let mut offset = 0;
        for (name, dtype, shape, data) in tensors {
            header.insert(
                name.to_string(),
                serde_json::json!({"dtype": dtype, "shape": shape, "data_offsets": [offset, offset + data.len()]}),
            );
            offset += data.len();
        }
        let header = serde_json::to_vec(&header).unwrap();
        let mut out = (header.len() as u64).to_le_bytes().to_vec();
        out.extend_from_slice(&header);
        for (_, _, _, data) in tensors {
            out.extend_from_slice(data);
        }
        out
    }

    fn f32_bytes(values: &[f32]) -> Vec<u8> {
        values.iter().flat_map(|v| v.to_le_bytes()).collect()
    }

    /// The hand case as raw parts, for breaking one thing at a time.
    fn parts() -> Vec<(&'static str, &'static str, Vec<usize>, Vec<u8>)> {
        hand()
            .into_iter()
            .map(|(n, s, d)| {
                let name = TENSOR_NAMES.iter().find(|t| **t == n).unwrap();
                (*name, "F32", s, f32_bytes(&d))
            })
            .collect()
    }

    #[test]
    fn forward_pass_matches_the_hand_computed_case() {
        let file = FlatPolicyFile::new(hand(), meta()).unwrap();
        assert_eq!(file.width(), 2);
        let mut policy = FlatPolicy::from_file(&file);
        assert_eq!(policy.name(), "td3");
        // s = 3 everywhere but s0 = 5: x = (s − 1) / 2 = 1, x0 = 2.
        let mut s = [3.0; 12];
        s[0] = 5.0;
        // h1 = relu(2 + 0.5, −1 + 0.25) = (2.5, 0); h2 = relu(2.5, 2.5 − 1) = (2.5, 1.5);
        // pre = (0.25, 0.15, −0.5, 0.5, 1.0 − 0.6, −1.5).
        let pre = [0.25f64, 0.15, -0.5, 0.5, 0.4, -1.5];
        let expected: Vec<f64> = pre
            .iter()
            .enumerate()
            .map(|(i, p)| p.tanh() * if i < 3 { 5.0 } else { 1.0 })
            .collect();
        let got = policy.step(&s).unwrap();
        for (g, e) in got.iter().zip(&expected) {
            assert!((g - e).abs() < 1e-6, "{got:?} vs {expected:?}");
        }
        // Through the file's bytes, the same.
        let back = FlatPolicyFile::from_bytes(&file.to_bytes()).unwrap();
        assert_eq!(back, file);
        assert_eq!(FlatPolicy::from_file(&back).step(&s).unwrap(), got);
        assert_eq!(back.parameter_count(), 24 + 2 + 4 + 2 + 12 + 6 + 24);
        // A non-finite state is refused by name.
        let mut bad = s;
        bad[7] = f64::NAN;
        assert!(
            policy
                .step(&bad)
                .unwrap_err()
                .to_string()
                .contains("state value 7")
        );
    }

    #[test]
    fn the_loader_refuses_each_fault_by_name() {
        let good = raw(&parts(), &meta());
        FlatPolicyFile::from_bytes(&good).unwrap();
        assert_eq!(PolicyKind::declared_by(&good), PolicyKind::Flat);

        // A missing tensor.
        let mut p = parts();
        p.retain(|t| t.0 != "actor.2.bias");
        let e = FlatPolicyFile::from_bytes(&raw(&p, &meta())).unwrap_err();
        assert_eq!(
            (e.code(), e.subject()),
            ("missing_tensor", Some("actor.2.bias"))
        );
        assert!(
            e.to_string().contains(
                "tensor `actor.2.bias` is missing: a flat policy needs all of actor.0.weight"
            ),
            "{e}"
        );

        // A wrong shape: a 3-output last layer (a hierarchical actor's).
        let mut p = parts();
        p[4] = ("actor.4.weight", "F32", vec![3, 2], f32_bytes(&[0.0; 6]));
        let e = FlatPolicyFile::from_bytes(&raw(&p, &meta())).unwrap_err();
        assert_eq!(
            (e.code(), e.subject()),
            ("wrong_shape", Some("actor.4.weight"))
        );
        assert!(
            e.to_string()
                .contains("has shape [3, 2], expected [6, 2] (6×D with D = 2 from actor.0.weight)"),
            "{e}"
        );

        // f16.
        let mut p = parts();
        p[0] = ("actor.0.weight", "F16", vec![2, 12], vec![0; 48]);
        let e = FlatPolicyFile::from_bytes(&raw(&p, &meta())).unwrap_err();
        assert_eq!(e.code(), "wrong_dtype");
        assert!(
            e.to_string()
                .contains("tensor `actor.0.weight` is F16, expected F32"),
            "{e}"
        );

        // NaN.
        let mut p = parts();
        let mut w = vec![0.0f32; 4];
        w[3] = f32::NAN;
        p[2] = ("actor.2.weight", "F32", vec![2, 2], f32_bytes(&w));
        let e = FlatPolicyFile::from_bytes(&raw(&p, &meta())).unwrap_err();
        assert_eq!(
            (e.code(), e.subject()),
            ("non_finite", Some("actor.2.weight"))
        );
        assert!(e.to_string().contains("NaN at index [1, 1]"), "{e}");

        // A zero σ.
        let mut p = parts();
        let mut std = vec![2.0f32; 12];
        std[4] = 0.0;
        p[7] = ("obs_std", "F32", vec![12], f32_bytes(&std));
        let e = FlatPolicyFile::from_bytes(&raw(&p, &meta())).unwrap_err();
        assert_eq!((e.code(), e.subject()), ("bad_value", Some("obs_std")));

        // A tensor of the hierarchy.
        let mut p = parts();
        p.push(("pos.0.bias", "F32", vec![2], f32_bytes(&[0.0; 2])));
        let e = FlatPolicyFile::from_bytes(&raw(&p, &meta())).unwrap_err();
        assert_eq!(
            (e.code(), e.subject()),
            ("unexpected_tensor", Some("pos.0.bias"))
        );
        assert!(
            e.to_string().contains("is not part of a flat policy"),
            "{e}"
        );

        // Wrong metadata: the hierarchical format, a version, a missing or bad step limit.
        let mut m = meta();
        m.insert("format".into(), file::FORMAT.into());
        let e = FlatPolicyFile::from_bytes(&raw(&parts(), &m)).unwrap_err();
        assert_eq!((e.code(), e.subject()), ("bad_metadata", Some("format")));
        assert!(
            e.to_string()
                .contains("expected \"assembly-cell/flat-policy\""),
            "{e}"
        );
        let mut m = meta();
        m.insert("format_version".into(), "3".into());
        let e = FlatPolicyFile::from_bytes(&raw(&parts(), &m)).unwrap_err();
        assert_eq!(
            (e.code(), e.subject()),
            ("bad_metadata", Some("format_version"))
        );
        let mut m = meta();
        m.remove("step_limit_mm");
        let e = FlatPolicyFile::from_bytes(&raw(&parts(), &m)).unwrap_err();
        assert_eq!(
            (e.code(), e.subject()),
            ("missing_metadata", Some("step_limit_mm"))
        );
        let mut m = meta();
        m.insert("step_limit_deg".into(), "nan".into());
        let e = FlatPolicyFile::from_bytes(&raw(&parts(), &m)).unwrap_err();
        assert_eq!(
            (e.code(), e.subject()),
            ("bad_metadata", Some("step_limit_deg"))
        );

        // In memory, the same checks.
        let mut t = hand();
        t[5].2[2] = f32::INFINITY;
        let e = FlatPolicyFile::new(t, meta()).unwrap_err();
        assert_eq!(
            (e.code(), e.subject()),
            ("non_finite", Some("actor.4.bias"))
        );
    }

    #[test]
    fn declared_kind_follows_the_format_metadata() {
        let mut m = meta();
        m.insert("format".into(), file::FORMAT.into());
        assert_eq!(
            PolicyKind::declared_by(&raw(&parts(), &m)),
            PolicyKind::Hierarchical
        );
        assert_eq!(
            PolicyKind::declared_by(b"nonsense"),
            PolicyKind::Hierarchical
        );
        let flat = FlatPolicyFile::new(hand(), meta()).unwrap();
        assert_eq!(PolicyKind::declared_by(&flat.to_bytes()), PolicyKind::Flat);
    }

    #[test]
    fn holds_still_without_a_fresh_frame_and_gives_no_labels() {
        let cell = CellConfig::reference();
        let mut env = AssemblyEnv::new(&cell, EnvOptions::from_cell(&cell));
        let mut observation = env.reset(3).unwrap();
        let mut policy = FlatPolicy::from_file(&FlatPolicyFile::new(hand(), meta()).unwrap())
            .with_name("flat-test");
        assert_eq!(policy.name(), "flat-test");
        observation.measurement_fresh = true;
        let decision = policy.act(&observation);
        assert_eq!((decision.actor, decision.scale), (None, None));
        assert_ne!(decision.action, Move::default());
        let expected = policy.step(&observation.state).unwrap();
        assert_eq!(decision.action, Move::from_array(expected));
        observation.measurement_fresh = false;
        assert_eq!(policy.act(&observation), Decision::hold());
        observation.measurement_fresh = true;
        observation.state[2] = f64::INFINITY;
        assert_eq!(policy.act(&observation), Decision::hold());
    }
}
