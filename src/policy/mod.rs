//! Controllers: everything that decides the next move from what the camera sees.
//!
//! The learned hierarchical policy and every baseline implement [`Controller`], so the twin,
//! `celld eval` and the cell service run any of them the same way.

pub mod dmp;
pub mod eval;
pub mod expert;
pub mod file;
pub mod flat;
pub mod hierarchical;
pub mod inputs;
pub mod learned;
pub mod mlp;
pub mod record;
pub mod run;
pub mod shield;
pub mod spiral;
pub mod visual_servo;

use crate::config::cell::CellConfig;
use crate::geometry::Move;
use crate::sim::Observation;
use serde::{Deserialize, Serialize};

/// Which low-level actor a decision used (the hierarchy's choice, paper §3.1).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Actor {
    Position,
    Orientation,
}

/// One decision: the move, and when the controller has them, the actor it chose and the step
/// scale in [0, 1] (ω3 after its sigmoid) — the labels the LSTM selector learns from — and,
/// for a learned policy, what its rules did ([`shield::ShieldTrace`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Decision {
    pub action: Move,
    pub actor: Option<Actor>,
    pub scale: Option<f64>,
    /// The network's proposal and the rules that changed it (learned policies only).
    pub shield: Option<shield::ShieldTrace>,
}

impl Decision {
    /// A move with no hierarchy annotation.
    pub fn plain(action: Move) -> Self {
        Decision {
            action,
            actor: None,
            scale: None,
            shield: None,
        }
    }

    /// Holding still (e.g. to take another capture).
    pub fn hold() -> Self {
        Decision::plain(Move::default())
    }
}

/// A controller of the assembly: asked once per camera cycle for the next move.
pub trait Controller: Send {
    /// The name `celld eval --controller` knows it by.
    fn name(&self) -> &str;
    /// Starts a new episode; `seed` drives any randomness of the controller's own.
    fn reset(&mut self, seed: u64);
    /// The next move for what the camera now sees.
    fn act(&mut self, observation: &Observation) -> Decision;
}

/// The controllers that need no learning, by name. `expert-state-only` is the demonstrator
/// `celld train` records by default and `expert-careful` the one `hierarchical-reference` learnt from
/// (both decide on what the policy sees; see [`expert`]).
pub const BUILTIN_CONTROLLERS: [&str; 7] = [
    "expert",
    "expert-state-only",
    "expert-careful",
    "expert-swift",
    "visual-servo",
    "spiral",
    "da-dmp",
];

/// The bundled learned policies, by name: `hierarchical-reference` (BC + LSTM + TD3 after two
/// DAgger rounds on the reference cell: the paper's policy, for its tables), `bc` (plain
/// behaviour cloning: BC actors and selector on the demonstrations alone, no DAgger, no TD3),
/// both made by `celld train all`, and `td3` (the flat baseline: one 6-DoF actor, TD3 without
/// BC or hierarchy, made by `celld train flat`), and `hierarchical-cells` (BC + LSTM on
/// cell-scaled inputs, every demonstration on a randomised cell: the careful policy for cells
/// none was trained on), and `hierarchical-swift-reference` (BC + LSTM on `expert-swift` on the
/// reference cell, a DAgger round, then TD3 on the selector's step size: a third fewer steps
/// than `hierarchical-reference`), and `hierarchical-swift-cells` ([`DEFAULT_POLICY`]: the
/// recipe of `hierarchical-cells` on `expert-swift`'s demonstrations, fast on every cell, and
/// what `celld train policy` makes by default). The reference-cell policies succeed in none of
/// the episodes on the cell files with another robot or camera placement. See the README.
pub const LEARNED_CONTROLLERS: [&str; 6] = [
    "hierarchical-reference",
    "bc",
    "td3",
    "hierarchical-cells",
    "hierarchical-swift-reference",
    "hierarchical-swift-cells",
];

/// The bundled default policy: the one the service registers and evaluates at first start
/// (`bundled-default`), the one for any cell in the specified ranges.
pub const DEFAULT_POLICY: &str = "hierarchical-swift-cells";

/// Bundled policies' earlier names, each with the name it has now: refused with both named
/// ([`UnknownController::renamed`]), never taken as the new one.
const RENAMED: [(&str, &str); 2] = [
    ("hierarchical", "hierarchical-reference"),
    ("hierarchical-swift", "hierarchical-swift-reference"),
];

/// The bundled policy file of a [`LEARNED_CONTROLLERS`] name.
pub fn bundled_policy(name: &str) -> Option<&'static [u8]> {
    match name {
        "hierarchical-reference" => Some(include_bytes!("../../policies/default.safetensors")),
        "bc" => Some(include_bytes!("../../policies/bc.safetensors")),
        "td3" => Some(include_bytes!("../../policies/td3.safetensors")),
        "hierarchical-cells" => Some(include_bytes!("../../policies/across-cells.safetensors")),
        "hierarchical-swift-reference" => Some(include_bytes!("../../policies/swift.safetensors")),
        "hierarchical-swift-cells" => {
            Some(include_bytes!("../../policies/swift-cells.safetensors"))
        }
        _ => None,
    }
}

/// The bundled policy `name`, run with `cell`'s rules.
fn load_bundled(name: &str, cell: &CellConfig) -> Option<learned::LearnedPolicy> {
    let bytes = bundled_policy(name)?;
    let file = learned::LearnedPolicyFile::from_bytes(bytes).expect("bundled policies are valid");
    let policy = learned::LearnedPolicy::from_file(&file).expect("bundled policy loads");
    Some(policy.with_name(name).with_rules(&cell.rules))
}

/// A controller name `celld` does not know; for a bundled policy's earlier name, the name it
/// has now (`renamed`), so the message says which to use instead.
#[derive(Debug, Clone, PartialEq)]
pub struct UnknownController {
    pub name: String,
    pub known: String,
    pub renamed: Option<&'static str>,
}

impl std::fmt::Display for UnknownController {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.renamed {
            Some(now) => write!(
                f,
                "`{}` was renamed `{now}` (the reference-cell policy); the default for any cell \
                 is `{DEFAULT_POLICY}`",
                self.name
            ),
            None => write!(
                f,
                "unknown controller `{}`; known: {}",
                self.name, self.known
            ),
        }
    }
}

impl std::error::Error for UnknownController {}

/// Builds a built-in controller for `cell` by name.
pub fn builtin(name: &str, cell: &CellConfig) -> Result<Box<dyn Controller>, UnknownController> {
    check_known(name)?;
    if let Some(policy) = load_bundled(name, cell) {
        return Ok(Box::new(policy));
    }
    match name {
        "expert" => Ok(Box::new(expert::Expert::new(cell))),
        "expert-state-only" => Ok(Box::new(expert::Expert::state_only(cell))),
        "expert-careful" => Ok(Box::new(expert::Expert::careful(cell))),
        "expert-swift" => Ok(Box::new(expert::Expert::swift(cell))),
        "visual-servo" => Ok(Box::new(visual_servo::VisualServo::new(cell))),
        "spiral" => Ok(Box::new(spiral::SpiralSearch::new(cell))),
        "da-dmp" => Ok(Box::new(dmp::default_dmp(cell))),
        _ => unreachable!("check_known lets only known names through"),
    }
}

/// Refuses a name that is not one of [`BUILTIN_CONTROLLERS`] or [`LEARNED_CONTROLLERS`],
/// without building anything; a bundled policy's earlier name is refused naming its new one.
pub fn check_known(name: &str) -> Result<(), UnknownController> {
    if BUILTIN_CONTROLLERS.contains(&name) || LEARNED_CONTROLLERS.contains(&name) {
        Ok(())
    } else {
        Err(UnknownController {
            name: name.to_string(),
            known: format!(
                "{}, {}",
                BUILTIN_CONTROLLERS.join(", "),
                LEARNED_CONTROLLERS.join(", ")
            ),
            renamed: RENAMED
                .iter()
                .find(|(before, _)| *before == name)
                .map(|(_, now)| *now),
        })
    }
}

/// A factory of built-in controllers for `cell` by name, for running many episodes in parallel:
/// anything costly to build (the DMP's demonstrations and fit) is built once and cloned.
pub type ControllerFactory = Box<dyn Fn() -> Box<dyn Controller> + Send + Sync>;

pub fn builtin_factory(
    name: &str,
    cell: &CellConfig,
) -> Result<ControllerFactory, UnknownController> {
    check_known(name)?;
    if name == "da-dmp" {
        let fitted = dmp::default_dmp(cell);
        return Ok(Box::new(move || Box::new(fitted.clone())));
    }
    if let Some(policy) = load_bundled(name, cell) {
        return Ok(Box::new(move || Box::new(policy.clone())));
    }
    let (name, cell) = (name.to_string(), cell.clone());
    Ok(Box::new(move || {
        builtin(&name, &cell).expect("checked above")
    }))
}

/// The command that takes {M} by `wanted_mm` on a robot whose sideways drift the cell's state
/// filter has learned as `drift` (sideways mm per mm commanded, `StateFilter::drift`): c such
/// that c + drift · c ≈ `wanted_mm`, to first order, c = wanted − drift · wanted sideways. Along
/// the axis the command is the wanted move.
pub fn steered_against_drift(
    drift: &nalgebra::Matrix2x3<f64>,
    wanted_mm: nalgebra::Vector3<f64>,
) -> nalgebra::Vector3<f64> {
    let correction = drift * wanted_mm;
    nalgebra::Vector3::new(
        wanted_mm.x - correction.x,
        wanted_mm.y - correction.y,
        wanted_mm.z,
    )
}

/// Clamps every component to ±`limit`.
pub(crate) fn clamp_components(v: nalgebra::Vector3<f64>, limit: f64) -> nalgebra::Vector3<f64> {
    v.map(|x| x.clamp(-limit, limit))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn earlier_names_are_refused_naming_the_new_one_and_the_default() {
        for (before, now) in RENAMED {
            let error = check_known(before).unwrap_err();
            assert_eq!(error.renamed, Some(now));
            let message = error.to_string();
            assert!(
                message.contains(&format!("`{before}` was renamed `{now}`"))
                    && message.contains("`hierarchical-swift-cells`"),
                "{message}"
            );
            // Refused, not taken as the new name.
            assert!(bundled_policy(before).is_none());
            assert!(LEARNED_CONTROLLERS.contains(&now) && bundled_policy(now).is_some());
        }
        let unknown = check_known("hierarchical-fast").unwrap_err();
        assert_eq!(unknown.renamed, None);
        assert!(
            unknown
                .to_string()
                .starts_with("unknown controller `hierarchical-fast`")
        );
        assert!(unknown.to_string().contains("hierarchical-reference"));
        assert!(check_known(DEFAULT_POLICY).is_ok());
        // The default is one of the bundled files, and not a reference-cell one.
        assert_eq!(
            bundled_policy(DEFAULT_POLICY),
            Some(&include_bytes!("../../policies/swift-cells.safetensors")[..])
        );
    }
}
