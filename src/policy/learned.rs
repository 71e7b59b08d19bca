//! A learned policy of either kind — hierarchical (docs/design.md §6) or the flat TD3 baseline
//! (`super::flat`) — chosen by the file's `__metadata__["format"]`. This is what a policy file
//! given by path (`celld eval --controller FILE`, `celld report --policy`), an uploaded policy
//! and a bundled policy load as. A file whose format is not the flat one is checked as a
//! hierarchical policy file, with that loader's messages.
//!
//! As it runs, a learned policy's translation is steered against the sideways drift the cell's
//! state filter has learned of its robot ([`super::steered_against_drift`]), as `expert` steers
//! its own: the network says where {M} should go, the cell makes the robot go there. The
//! demonstrators the policies learn from decide on the state alone and do not steer, so
//! training (behaviour cloning, DAgger's episodes, TD3's episodes) runs the bare policy and the
//! steering is added here, where a policy is run (decision 0026); TD3's validations run the
//! policy as it is deployed, through this type (decision 0029). With a camera three times
//! noisier than its data sheet or more, a position move down the bore is made as the
//! demonstrators make it instead: their exact centring, not steered
//! ([`super::hierarchical::descends_as_the_demonstrators`], decision 0034).

use super::file::{PolicyFile, PolicyFileError, PolicyKind, PolicyMetadata};
use super::flat::{FlatPolicy, FlatPolicyFile};
use super::hierarchical::{
    HierarchicalPolicy, centres_after_a_refusal, demonstrators_centring_mm,
    descends_as_the_demonstrators,
};
use super::{Controller, Decision, clamp_components, steered_against_drift};
use crate::sim::Observation;
use nalgebra::Vector3;
use std::collections::BTreeMap;
use std::path::Path;

/// A checked policy file of either kind.
#[derive(Debug, Clone, PartialEq)]
pub enum LearnedPolicyFile {
    Hierarchical(PolicyFile),
    Flat(FlatPolicyFile),
}

impl LearnedPolicyFile {
    /// Parses and checks a policy file of the kind its metadata declares.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, PolicyFileError> {
        match PolicyKind::declared_by(bytes) {
            PolicyKind::Flat => FlatPolicyFile::from_bytes(bytes).map(Self::Flat),
            PolicyKind::Hierarchical => PolicyFile::from_bytes(bytes).map(Self::Hierarchical),
        }
    }

    /// Reads and checks a policy file of either kind.
    pub fn from_path(path: impl AsRef<Path>) -> Result<Self, PolicyFileError> {
        Self::from_bytes(&super::file::read_path(path.as_ref())?)
    }

    pub fn kind(&self) -> PolicyKind {
        match self {
            Self::Hierarchical(_) => PolicyKind::Hierarchical,
            Self::Flat(_) => PolicyKind::Flat,
        }
    }

    /// Name → shape of every tensor, in the file's order.
    pub fn shapes(&self) -> Vec<(String, Vec<usize>)> {
        match self {
            Self::Hierarchical(f) => f.shapes(),
            Self::Flat(f) => f.shapes(),
        }
    }

    /// The checked metadata.
    pub fn metadata(&self) -> &PolicyMetadata {
        match self {
            Self::Hierarchical(f) => f.metadata(),
            Self::Flat(f) => f.metadata(),
        }
    }

    /// `__metadata__` exactly as stored.
    pub fn raw_metadata(&self) -> &BTreeMap<String, String> {
        match self {
            Self::Hierarchical(f) => f.raw_metadata(),
            Self::Flat(f) => f.raw_metadata(),
        }
    }
}

/// A runnable learned policy of either kind.
#[derive(Debug, Clone)]
pub enum LearnedPolicy {
    // Boxed: both are several hundred bytes inline (normalisers, layers, scratch).
    Hierarchical(Box<HierarchicalPolicy>),
    Flat(Box<FlatPolicy>),
}

impl LearnedPolicy {
    /// The policy of a checked file, on the CPU (named "hierarchical" or "td3").
    pub fn from_file(file: &LearnedPolicyFile) -> candle_core::Result<Self> {
        Ok(match file {
            LearnedPolicyFile::Hierarchical(f) => {
                Self::Hierarchical(Box::new(HierarchicalPolicy::from_file(f)?))
            }
            LearnedPolicyFile::Flat(f) => Self::Flat(Box::new(FlatPolicy::from_file(f))),
        })
    }

    /// Parses, checks and loads a policy file's bytes.
    pub fn from_bytes(bytes: &[u8]) -> anyhow::Result<Self> {
        Ok(Self::from_file(&LearnedPolicyFile::from_bytes(bytes)?)?)
    }

    /// Reads, checks and loads a policy file; the controller is named after the file's stem.
    pub fn from_path(path: impl AsRef<Path>) -> anyhow::Result<Self> {
        let path = path.as_ref();
        let policy = Self::from_file(&LearnedPolicyFile::from_path(path)?)?;
        Ok(match path.file_stem() {
            Some(stem) => policy.with_name(stem.to_string_lossy()),
            None => policy,
        })
    }

    /// Renames the controller.
    pub fn with_name(self, name: impl Into<String>) -> Self {
        match self {
            Self::Hierarchical(p) => Self::Hierarchical(Box::new(p.with_name(name))),
            Self::Flat(p) => Self::Flat(Box::new(p.with_name(name))),
        }
    }

    pub fn kind(&self) -> PolicyKind {
        match self {
            Self::Hierarchical(_) => PolicyKind::Hierarchical,
            Self::Flat(_) => PolicyKind::Flat,
        }
    }
}

impl Controller for LearnedPolicy {
    fn name(&self) -> &str {
        match self {
            Self::Hierarchical(p) => p.name(),
            Self::Flat(p) => p.name(),
        }
    }

    fn reset(&mut self, seed: u64) {
        match self {
            Self::Hierarchical(p) => Controller::reset(p.as_mut(), seed),
            Self::Flat(p) => p.reset(seed),
        }
    }

    fn act(&mut self, observation: &Observation) -> Decision {
        let (mut decision, step_limit_mm) = match self {
            Self::Hierarchical(p) => (p.act(observation), p.config().step_limit_mm),
            Self::Flat(p) => (p.act(observation), p.step_limit_mm()),
        };
        let wanted_mm = decision.action.translation_mm;
        let command_mm = if descends_as_the_demonstrators(observation, &decision)
            || centres_after_a_refusal(observation, &decision)
        {
            let centring = demonstrators_centring_mm(observation, step_limit_mm);
            Vector3::new(centring.x, centring.y, wanted_mm.z)
        } else {
            steered_against_drift(&observation.estimate.drift(), wanted_mm)
        };
        decision.action.translation_mm = clamp_components(command_mm, step_limit_mm);
        decision
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::policy::flat::TENSOR_NAMES;

    fn flat_bytes() -> Vec<u8> {
        let tensors = TENSOR_NAMES
            .iter()
            .map(|&n| {
                let shape = match n {
                    "actor.0.weight" => vec![4, 12],
                    "actor.2.weight" => vec![4, 4],
                    "actor.4.weight" => vec![6, 4],
                    "actor.4.bias" => vec![6],
                    "obs_mean" | "obs_std" => vec![12],
                    _ => vec![4],
                };
                let len = shape.iter().product();
                (n.to_string(), shape, vec![0.5; len])
            })
            .collect();
        FlatPolicyFile::new(tensors, FlatPolicyFile::standard_metadata(5.0, 1.0))
            .unwrap()
            .to_bytes()
    }

    #[test]
    fn either_kind_loads_by_its_format() {
        let flat = LearnedPolicy::from_bytes(&flat_bytes()).unwrap();
        assert_eq!((flat.kind(), flat.name()), (PolicyKind::Flat, "td3"));
        let file = LearnedPolicyFile::from_bytes(&flat_bytes()).unwrap();
        assert_eq!(file.shapes()[4], ("actor.4.weight".to_string(), vec![6, 4]));
        let bundled = crate::policy::bundled_policy("hierarchical").unwrap();
        let hierarchical = LearnedPolicy::from_bytes(bundled).unwrap();
        assert_eq!(hierarchical.kind(), PolicyKind::Hierarchical);
        assert_eq!(hierarchical.with_name("x").name(), "x");
        // Anything else is refused as a hierarchical file is.
        let e = LearnedPolicyFile::from_bytes(b"12345678").unwrap_err();
        assert_eq!(e, PolicyFile::from_bytes(b"12345678").unwrap_err());
    }

    /// The policy trained across randomised cells reads cell-scaled inputs and assembles on
    /// a cell none of its demonstrations was recorded on (the report measures it over 1000
    /// episodes on each generalisation cell).
    #[test]
    fn the_bundled_policy_for_any_cell_assembles_on_a_cell_it_was_not_trained_on() {
        use crate::config::cell::CellConfig;
        use crate::policy::inputs::PolicyInputs;
        use crate::sim::EnvOptions;
        let bytes = crate::policy::bundled_policy("hierarchical-cells").unwrap();
        let file = LearnedPolicyFile::from_bytes(bytes).unwrap();
        assert_eq!(file.metadata().inputs, PolicyInputs::CellScaled);
        let cell =
            CellConfig::parse(include_str!("../../cells/phi250-shallow.toml"), "cell").unwrap();
        let make = crate::policy::builtin_factory("hierarchical-cells", &cell).unwrap();
        let (summary, _) = crate::policy::eval::evaluate(
            &cell,
            EnvOptions::from_cell(&cell),
            20,
            3,
            &make,
            &|_| {},
        );
        assert!(summary.successes >= 15, "{summary:?}");
        assert_eq!(summary.failures.get("contact"), None);
    }

    /// An observation on the reference cell with the estimated pose `p_mm` ({F} in {M}),
    /// level, on a robot whose drift per mm (`StateFilter::drift`, x then y per mm along x, y
    /// and z) the cell has learned to σ `drift_sd`.
    fn observed_with_drift(
        p_mm: [f64; 3],
        per_mm: nalgebra::Vector6<f64>,
        drift_sd: f64,
    ) -> crate::sim::Observation {
        use crate::camera::drift::DriftKnowledge;
        use crate::config::cell::CellConfig;
        use crate::sim::{AssemblyEnv, EnvOptions};
        let cell = CellConfig::reference();
        let mut env = AssemblyEnv::new(&cell, EnvOptions::from_cell(&cell));
        let mut observation = env.reset(4).unwrap();
        observation.state[6..9].copy_from_slice(&p_mm);
        observation.state[9..12].fill(0.0);
        let covariance = nalgebra::Matrix6::identity() * drift_sd.powi(2);
        let known = DriftKnowledge::new(&per_mm, &covariance, 5);
        observation.estimate.reset_from(&known);
        observation
    }

    /// The bundled hierarchical policy `name`, bare (without the rules `LearnedPolicy` adds).
    fn bundled_hierarchical(name: &str) -> HierarchicalPolicy {
        let bytes = crate::policy::bundled_policy(name).unwrap();
        let LearnedPolicy::Hierarchical(bare) = LearnedPolicy::from_bytes(bytes).unwrap() else {
            panic!("the bundled policy {name} is hierarchical");
        };
        *bare
    }

    /// On a robot whose drift the cell has learned, the command a learned policy gives, moved
    /// as that robot moves it (c + drift · c sideways), lands where the bare network asked, to
    /// second order in the drift; the bare network's own command would land drift · w off.
    #[test]
    fn a_learned_policy_steers_its_moves_against_the_drift_the_cell_has_learned() {
        use nalgebra::{Vector2, Vector6};
        // 3 mm and 2 mm off the axis, 20 mm above the entrance.
        let per_mm = Vector6::new(0.02, -0.01, 0.004, 0.015, 0.01, -0.003);
        let observation = observed_with_drift([3.0, -2.0, -80.0], per_mm, 1e-3);
        let drift = observation.estimate.drift();
        let bare = bundled_hierarchical("hierarchical");
        let wanted = bare.clone().act(&observation).action.translation_mm;
        let mut steered = LearnedPolicy::Hierarchical(Box::new(bare));
        let command = steered.act(&observation).action.translation_mm;
        assert!(wanted.norm() > 1.0, "{wanted}");
        let lands = |c: nalgebra::Vector3<f64>| Vector2::new(c.x, c.y) + drift * c;
        let off = |c| (lands(c) - Vector2::new(wanted.x, wanted.y)).norm();
        assert!(off(command) < 0.005, "{command} lands {} off", off(command));
        assert!(
            off(wanted) > 0.05,
            "unsteered, {wanted} lands {} off",
            off(wanted)
        );
        assert_eq!(command.z, wanted.z);
    }

    /// 10 mm into the bore and 0.02 mm off the axis, right after a move refused for the wall
    /// margin, on a robot that drifts a fifth of each sideways move: the policy's move holds
    /// the depth and is the demonstrators' exact centring, not steered against the drift
    /// (`centres_after_a_refusal`).
    #[test]
    fn after_a_refusal_for_the_wall_margin_the_move_is_the_demonstrators_centring() {
        use crate::collision::supervisor::VetoReason;
        use crate::policy::Actor;
        use crate::policy::hierarchical::demonstrators_centring_mm;
        use nalgebra::Vector6;
        let per_mm = Vector6::new(0.2, 0.0, 0.01, 0.0, 0.2, -0.008);
        let mut observation = observed_with_drift([0.02, -0.01, -50.0], per_mm, 1e-4);
        observation.last_veto = Some(VetoReason::WallMargin {
            clearance_mm: 0.019,
            margin_mm: 0.02,
            start_mm: 0.021,
        });
        let bare = bundled_hierarchical("hierarchical-cells");
        let centring = demonstrators_centring_mm(&observation, bare.config().step_limit_mm);
        let asked = bare.clone().act(&observation).action.translation_mm;
        assert!(asked.xy() != nalgebra::Vector2::zeros(), "{asked}");
        let made = LearnedPolicy::Hierarchical(Box::new(bare)).act(&observation);
        assert_eq!(made.actor, Some(Actor::Position), "{made:?}");
        assert_eq!(made.action.translation_mm.xy(), centring);
        assert_eq!(made.action.translation_mm.z, 0.0, "{made:?}");
    }

    /// 10 mm into the bore and 0.02 mm off the axis, on a robot whose drift the cell has
    /// learned: with the camera at its data sheet's noise the policy's move down is steered
    /// against the drift; at four times, it is the demonstrators' move, their exact centring
    /// and not steered (`descends_as_the_demonstrators`).
    #[test]
    fn under_a_noisy_camera_a_move_down_the_bore_is_the_demonstrators() {
        use crate::policy::Actor;
        use crate::policy::hierarchical::demonstrators_centring_mm;
        use nalgebra::{Vector2, Vector6};
        let per_mm = Vector6::new(0.0, 0.0, 0.01, 0.0, 0.0, -0.008);
        let observation = observed_with_drift([0.02, -0.01, -50.0], per_mm, 1e-4);
        let bare = bundled_hierarchical("hierarchical-cells");
        let step_limit_mm = bare.config().step_limit_mm;
        let act = |noise_scale: f64| {
            let mut observation = observation.clone();
            observation.estimate.set_noise_scale(noise_scale);
            let asked = bare.clone().act(&observation);
            let made = LearnedPolicy::Hierarchical(Box::new(bare.clone())).act(&observation);
            (asked, made)
        };
        let ((asked, quiet), (asked_noisy, noisy)) = (act(1.0), act(4.0));
        assert_eq!(
            asked, asked_noisy,
            "the network does not see the noise scale"
        );
        assert_eq!(asked.actor, Some(Actor::Position), "{asked:?}");
        let dz = asked.action.translation_mm.z;
        assert!(dz < -0.5, "{asked:?}");
        // Quiet: steered, the drift of the move down (0.01 and −0.008 per mm) taken off.
        let steered = asked.action.translation_mm.xy() - Vector2::new(0.01 * dz, -0.008 * dz);
        assert!((quiet.action.translation_mm.xy() - steered).norm() < 1e-12);
        assert_eq!(quiet.action.translation_mm.z, dz);
        // Noisy: the demonstrators' centring, {M} moved by {F}'s offset in it (level, so
        // the engaged middle is as far off the axis as {F}'s origin).
        let centring = demonstrators_centring_mm(&observation, step_limit_mm);
        assert!(
            (centring - Vector2::new(0.02, -0.01)).norm() < 1e-12,
            "{centring}"
        );
        assert_eq!(noisy.action.translation_mm.xy(), centring);
        assert_eq!(noisy.action.translation_mm.z, dz);
    }
}
