//! A learned policy of either kind — hierarchical (docs/design.md §6) or the flat TD3 baseline
//! (`super::flat`) — chosen by the file's `__metadata__["format"]`. This is what a policy file
//! given by path (`celld eval --controller FILE`, `celld report --policy`), an uploaded policy
//! and a bundled policy load as. A file whose format is not the flat one is checked as a
//! hierarchical policy file, with that loader's messages.
//!
//! As it runs, a learned policy's proposal goes through the shield ([`super::shield`]): the
//! rules between the networks and the supervisor, built from the cell file's `[rules]`, each
//! recorded where it changes the move (docs/policy-rules.md).

use super::file::{PolicyFile, PolicyFileError, PolicyKind, PolicyMetadata};
use super::flat::{FlatPolicy, FlatPolicyFile};
use super::hierarchical::HierarchicalPolicy;
use super::shield::{
    RuleContext, RuleId, RuleSelection, RuleSet, RulesConfig, Shaped, Shield, ShieldTrace,
};
use super::{Controller, Decision};
use crate::sim::Observation;
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

/// The network of a learned policy, of either kind.
#[derive(Debug, Clone)]
pub enum LearnedNetwork {
    // Boxed: both are several hundred bytes inline (normalisers, layers, scratch).
    Hierarchical(Box<HierarchicalPolicy>),
    Flat(Box<FlatPolicy>),
}

/// A runnable learned policy: its network and the shield of rules the cell runs it with.
#[derive(Debug, Clone)]
pub struct LearnedPolicy {
    network: LearnedNetwork,
    shield: Shield,
}

impl LearnedPolicy {
    /// `network` run with every rule, today's parameters.
    fn new(network: LearnedNetwork) -> Self {
        Self {
            network,
            shield: Shield::default(),
        }
    }

    /// The policy run with the rules of `rules` (a cell file's `[rules]`, or a selection of
    /// them).
    pub fn with_rules(self, rules: &RulesConfig) -> Self {
        Self {
            shield: Shield::new(rules),
            ..self
        }
    }

    /// The policy without rule `rule`, the others as they are (to measure what it is worth).
    pub fn without(self, rule: RuleId) -> Self {
        let config = self.shield.config();
        let on = config.enabled().iter().filter(|id| *id != rule).collect();
        let rules = config.selected(&RuleSelection::Only(on));
        self.with_rules(&rules)
    }

    /// A hierarchical policy run with every rule.
    pub fn hierarchical(policy: HierarchicalPolicy) -> Self {
        Self::new(LearnedNetwork::Hierarchical(Box::new(policy)))
    }

    /// A flat policy run with every rule.
    pub fn flat(policy: FlatPolicy) -> Self {
        Self::new(LearnedNetwork::Flat(Box::new(policy)))
    }

    /// The policy of a checked file, on the CPU (named "hierarchical" or "td3").
    pub fn from_file(file: &LearnedPolicyFile) -> candle_core::Result<Self> {
        Ok(match file {
            LearnedPolicyFile::Hierarchical(f) => {
                Self::hierarchical(HierarchicalPolicy::from_file(f)?)
            }
            LearnedPolicyFile::Flat(f) => Self::flat(FlatPolicy::from_file(f)),
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
        let network = match self.network {
            LearnedNetwork::Hierarchical(p) => {
                LearnedNetwork::Hierarchical(Box::new(p.with_name(name)))
            }
            LearnedNetwork::Flat(p) => LearnedNetwork::Flat(Box::new(p.with_name(name))),
        };
        Self { network, ..self }
    }

    pub fn kind(&self) -> PolicyKind {
        match self.network {
            LearnedNetwork::Hierarchical(_) => PolicyKind::Hierarchical,
            LearnedNetwork::Flat(_) => PolicyKind::Flat,
        }
    }

    /// The network's proposal, the move of the actor that acts (where the shield's rule 1
    /// chose another than the selector) and the step limits (mm, deg). A step that fails or
    /// is not finite holds still, as does a step without a fresh frame (the LSTM then does not
    /// advance: the demonstrations have no such steps).
    fn propose(&mut self, observation: &Observation) -> (Decision, Decision, f64, f64) {
        match &mut self.network {
            LearnedNetwork::Hierarchical(p) => {
                let (limit_mm, limit_deg) = (p.config().step_limit_mm, p.config().step_limit_deg);
                if !observation.measurement_fresh {
                    return (Decision::hold(), Decision::hold(), limit_mm, limit_deg);
                }
                let inputs = p.config().inputs.of(observation);
                let shield = &self.shield;
                let choose = |selected| shield.choose_actor(observation, selected);
                match p.propose(&inputs, &choose) {
                    Ok(proposal) if proposal.is_finite() => (
                        proposal.selected.to_decision(),
                        proposal.acting.to_decision(),
                        limit_mm,
                        limit_deg,
                    ),
                    _ => (Decision::hold(), Decision::hold(), limit_mm, limit_deg),
                }
            }
            LearnedNetwork::Flat(p) => {
                let decision = p.act(observation);
                (decision, decision, p.step_limit_mm(), p.step_limit_deg())
            }
        }
    }
}

impl Controller for LearnedPolicy {
    fn name(&self) -> &str {
        match &self.network {
            LearnedNetwork::Hierarchical(p) => p.name(),
            LearnedNetwork::Flat(p) => p.name(),
        }
    }

    fn reset(&mut self, seed: u64) {
        self.shield.reset();
        match &mut self.network {
            LearnedNetwork::Hierarchical(p) => p.reset(),
            LearnedNetwork::Flat(p) => p.reset(seed),
        }
    }

    /// The network's proposal through the shield; the decision carries the proposal and the
    /// rules that changed it.
    fn act(&mut self, observation: &Observation) -> Decision {
        let (proposed, acting, step_limit_mm, step_limit_deg) = self.propose(observation);
        let mut fired = RuleSet::default();
        if acting.actor != proposed.actor {
            fired.insert(RuleId::ActorWithWork);
        }
        let mut shaped = Shaped {
            actor: acting.actor,
            action: acting.action,
            exact_sideways: false,
        };
        let context = RuleContext {
            observation,
            step_limit_mm,
            step_limit_deg,
        };
        self.shield.shape(&context, &mut shaped, &mut fired);
        Decision {
            action: shaped.action,
            shield: Some(ShieldTrace {
                proposed: proposed.action,
                proposed_actor: proposed.actor,
                fired,
            }),
            ..acting
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::collision::supervisor::VetoReason;
    use crate::policy::flat::TENSOR_NAMES;
    use crate::policy::shield::{FullStepAfterUncertainty, demonstrators_centring_mm};

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
        let bundled = crate::policy::bundled_policy("hierarchical-reference").unwrap();
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

    /// A hierarchical policy with the rules training runs it with (1–8), not those of the cell
    /// where it runs.
    fn as_trained(policy: HierarchicalPolicy) -> LearnedPolicy {
        LearnedPolicy::hierarchical(policy).with_rules(&RulesConfig::default().in_training())
    }

    /// The bundled hierarchical policy `name`'s network.
    fn bundled_hierarchical(name: &str) -> HierarchicalPolicy {
        let bytes = crate::policy::bundled_policy(name).unwrap();
        let LearnedNetwork::Hierarchical(bare) = LearnedPolicy::from_bytes(bytes).unwrap().network
        else {
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
        let bare = bundled_hierarchical("hierarchical-reference");
        let wanted = as_trained(bare.clone())
            .act(&observation)
            .action
            .translation_mm;
        let mut steered = LearnedPolicy::hierarchical(bare);
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
        let asked = as_trained(bare.clone())
            .act(&observation)
            .action
            .translation_mm;
        assert!(asked.xy() != nalgebra::Vector2::zeros(), "{asked}");
        let made = LearnedPolicy::hierarchical(bare).act(&observation);
        assert_eq!(made.actor, Some(Actor::Position), "{made:?}");
        assert_eq!(made.action.translation_mm.xy(), centring);
        assert_eq!(made.action.translation_mm.z, 0.0, "{made:?}");
    }

    /// 10 mm into the bore and 0.02 mm off the axis, on a robot whose drift the cell has
    /// learned: with the camera at its data sheet's noise the policy's move down is steered
    /// against the drift; at four times, it is the demonstrators' move, their exact centring
    /// and not steered (`descends_as_the_demonstrators`), no longer than `expert-careful`'s
    /// 2 mm step this near the entrance (`no_longer_than_the_careful_step_mm`).
    #[test]
    fn under_a_noisy_camera_a_move_down_the_bore_is_the_demonstrators() {
        use crate::policy::Actor;
        use nalgebra::{Vector2, Vector6};
        let per_mm = Vector6::new(0.0, 0.0, 0.01, 0.0, 0.0, -0.008);
        let observation = observed_with_drift([0.02, -0.01, -50.0], per_mm, 1e-4);
        let bare = bundled_hierarchical("hierarchical-cells");
        let step_limit_mm = bare.config().step_limit_mm;
        let act = |noise_scale: f64| {
            let mut observation = observation.clone();
            observation.estimate.set_noise_scale(noise_scale);
            let asked = as_trained(bare.clone()).act(&observation);
            let made = LearnedPolicy::hierarchical(bare.clone()).act(&observation);
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
        assert_eq!(noisy.action.translation_mm.z, dz.max(-2.0));
    }

    /// The fast policy learnt from `expert-swift`, 0.02 mm off the axis: at four times the
    /// camera's noise its move down is no longer than `expert-careful`'s 2 mm over the first
    /// 35 mm of the bore, and as asked deeper in; at the data sheet's noise, as asked
    /// everywhere (`no_longer_than_the_careful_step_mm`).
    #[test]
    fn under_a_noisy_camera_a_move_down_the_first_35_mm_is_the_careful_step() {
        use nalgebra::Vector6;
        let bare = bundled_hierarchical("hierarchical-swift-cells");
        let act = |inserted_mm: f64, noise_scale: f64| {
            let mut observation =
                observed_with_drift([0.02, -0.01, inserted_mm - 60.0], Vector6::zeros(), 1e-4);
            observation.estimate.set_noise_scale(noise_scale);
            // A fresh selector opens with the orientation actor (no move, the shaft level);
            // its second decision is the position actor's.
            let mut network = as_trained(bare.clone());
            let mut policy = LearnedPolicy::hierarchical(bare.clone());
            network.act(&observation);
            policy.act(&observation);
            let asked = network.act(&observation).action.translation_mm.z;
            (asked, policy.act(&observation).action.translation_mm.z)
        };
        let (asked, made) = act(10.0, 4.0);
        assert!(asked < -2.5, "the fast policy asks {asked} mm 10 mm in");
        assert_eq!(made, -2.0);
        let (asked, made) = act(10.0, 1.0);
        assert_eq!(made, asked);
        let (asked, made) = act(40.0, 4.0);
        assert!(asked < -2.5, "the fast policy asks {asked} mm 40 mm in");
        assert_eq!(made, asked);
    }

    /// A move refused as uncertain, 10 mm into the reference bore (60 mm deep).
    fn uncertain() -> VetoReason {
        VetoReason::Uncertain {
            risk: 2e-3,
            bound: 1e-3,
            clearance_mm: 0.03,
        }
    }

    /// The reference cell 0.02 mm off the axis, P_z = `p_z_mm` (the tip `60 + p_z_mm` into
    /// the bore), right after `veto`.
    fn in_the_bore(p_z_mm: f64, veto: Option<VetoReason>) -> Observation {
        let zero = nalgebra::Vector6::zeros();
        let mut observation = observed_with_drift([0.02, -0.01, p_z_mm], zero, 1e-4);
        observation.last_veto = veto;
        observation
    }

    /// Where the rule applies, by hand on the reference cell (60 mm deep, 5 mm steps): from
    /// 0.2 mm in to 54 mm in (a 5 mm step then ends 1 mm short of the seat), a move down, right
    /// after a refusal as uncertain, and not after a refusal for the wall until a move is made.
    #[test]
    fn the_full_step_follows_a_refusal_as_uncertain_in_the_bore_and_not_near_the_wall() {
        let wall = VetoReason::WallMargin {
            clearance_mm: 0.019,
            margin_mm: 0.02,
            start_mm: 0.021,
        };
        let mut rule = FullStepAfterUncertainty::default();
        let mut full = |p_z_mm: f64, veto: Option<VetoReason>, asked_z_mm: f64| {
            rule.step(&in_the_bore(p_z_mm, veto), asked_z_mm, 5.0)
        };
        assert!(full(-50.0, Some(uncertain()), -2.0), "10 mm in");
        assert!(!full(-50.0, Some(uncertain()), 0.5), "a move up");
        assert!(!full(-50.0, None, -2.0), "no refusal");
        assert!(
            !full(-50.0, Some(VetoReason::StaleMeasurement), -2.0),
            "not uncertain"
        );
        assert!(!full(-59.9, Some(uncertain()), -2.0), "0.1 mm in");
        assert!(full(-59.7, Some(uncertain()), -2.0), "0.3 mm in");
        assert!(full(-6.1, Some(uncertain()), -2.0), "53.9 mm in");
        assert!(!full(-5.9, Some(uncertain()), -2.0), "54.1 mm in");
        // Refused for the wall: no full step after refusals as uncertain until a move is made.
        assert!(!full(-50.0, Some(wall), -2.0));
        assert!(!full(-50.0, Some(uncertain()), -2.0));
        assert!(!full(-50.0, Some(VetoReason::StaleMeasurement), -2.0));
        assert!(!full(-50.0, Some(uncertain()), -2.0));
        assert!(!full(-50.0, None, -2.0), "a move made");
        assert!(full(-50.0, Some(uncertain()), -2.0));
    }

    /// The bundled careful policy 0.01 mm off the axis 2 mm above the entrance, with a camera
    /// so noisy that the estimate's sideways σ is above the cell's 0.05 mm of clearance: its
    /// move down stops 1 mm above the entrance, its sideways part and turn as the network
    /// asks; switched off, the move is the network's.
    #[test]
    fn unsure_a_learned_policy_comes_no_nearer_than_the_standoff() {
        use crate::config::cell::CellConfig;
        use crate::sim::{AssemblyEnv, EnvOptions};
        let cell = CellConfig::reference();
        let options = EnvOptions {
            noise_scale: 40.0,
            ..EnvOptions::from_cell(&cell)
        };
        let mut observation = AssemblyEnv::new(&cell, options).reset(4).unwrap();
        observation.state[6..9].copy_from_slice(&[0.01, 0.0, -62.0]);
        observation.state[9..12].fill(0.0);
        let sd_mm = observation.estimate.lateral_sd_mm();
        assert!(sd_mm > observation.cell.radial_clearance_mm, "σ {sd_mm} mm");
        let bare = bundled_hierarchical("hierarchical-cells");
        let own = LearnedPolicy::hierarchical(bare.clone())
            .without(RuleId::StandoffWhileUnsure)
            .act(&observation);
        let held = LearnedPolicy::hierarchical(bare).act(&observation);
        assert!(own.action.translation_mm.z < -1.0, "{own:?}");
        assert!(
            (held.action.translation_mm.z + 1.0).abs() < 1e-9,
            "{held:?}"
        );
        assert_eq!(
            held.action.translation_mm.xy(),
            own.action.translation_mm.xy()
        );
        assert_eq!(held.action.rotation_deg, own.action.rotation_deg);
    }

    /// The bundled careful policy 10 mm into the bore: right after a refusal as uncertain its
    /// move is the one it makes without the refusal but for the depth, the full step.
    #[test]
    fn a_learned_policy_asks_the_full_step_down_after_a_refusal_as_uncertain() {
        let bare = bundled_hierarchical("hierarchical-cells");
        let step_limit_mm = bare.config().step_limit_mm;
        let own = LearnedPolicy::hierarchical(bare.clone()).act(&in_the_bore(-50.0, None));
        let bare_again = bare.clone();
        let after = LearnedPolicy::hierarchical(bare).act(&in_the_bore(-50.0, Some(uncertain())));
        let z = own.action.translation_mm.z;
        assert!(z < 0.0 && z > -step_limit_mm, "{own:?}");
        assert_eq!(after.action.translation_mm.z, -step_limit_mm, "{after:?}");
        assert_eq!(
            after.action.translation_mm.xy(),
            own.action.translation_mm.xy()
        );
        assert_eq!(after.action.rotation_deg, own.action.rotation_deg);
        let switched_off = LearnedPolicy::hierarchical(bare_again)
            .without(RuleId::FullStepAfterUncertainty)
            .act(&in_the_bore(-50.0, Some(uncertain())));
        assert_eq!(switched_off, own);
    }
}
