//! Where a learned policy loses to its demonstrator: the policy acts, but in one zone of the
//! tip's height (mm past the bore's entrance, from FROM to TO) a part of its move is replaced
//! by what the demonstrator would do on the same observation. The success rate that comes back
//! says how much that part of the policy's behaviour there costs; at four times the camera's
//! noise it splits the learned policies' gap to their demonstrators by zone and by part of the
//! move (docs/experiments/2026-11-29-a1746d1-where-the-policies-lose-at-four-times-the-noise.md).
//!
//! `cargo run --release -p cell-research -- teacher_in_the_zone
//! POLICY DEMONSTRATOR MODE [FROM [TO
//! [NOISE [EPISODES [SEED]]]]]` (built-in controllers; defaults 0.2, ∞, 4, 4000, 2). MODE:
//! - `none`: the policy alone, as `celld eval` runs it;
//! - `all`: the demonstrator's whole move;
//! - `xy`: the demonstrator's sideways move (x, y of {M}) with the policy's move along the
//!   axis and its turn;
//! - `xy-when-moving`: the same, only when the policy moves without turning (a demonstrator
//!   that turns meanwhile gives no sideways move);
//! - `z`: the demonstrator's move along the axis when either goes deeper;
//! - `turn`: the demonstrator's turn with the policy's translation.
//!
//! The demonstrator runs beside the policy on the same observations, with its own state (its
//! holds at the standoff), reset with the same seed. 10 kept robots, as `celld eval`.

use cell_research::arg;

use assembly_cell::config::cell::CellConfig;
use assembly_cell::geometry::Move;
use assembly_cell::policy::eval::evaluate;
use assembly_cell::policy::{self, Controller, Decision};
use assembly_cell::sim::{EnvOptions, Observation};

/// The move made: the policy's, with the part `mode` names taken from the demonstrator's.
fn mixed(mode: &str, policy: Move, demonstrator: Move) -> anyhow::Result<Move> {
    let mut made = policy;
    let turns = |m: &Move| m.rotation_deg.norm() > 0.0;
    match mode {
        "none" => {}
        "all" => made = demonstrator,
        "xy" => {
            made.translation_mm.x = demonstrator.translation_mm.x;
            made.translation_mm.y = demonstrator.translation_mm.y;
        }
        "xy-when-moving" => {
            if !turns(&policy) {
                made.translation_mm.x = demonstrator.translation_mm.x;
                made.translation_mm.y = demonstrator.translation_mm.y;
            }
        }
        "z" => {
            if policy.translation_mm.z < 0.0 || demonstrator.translation_mm.z < 0.0 {
                made.translation_mm.z = demonstrator.translation_mm.z;
            }
        }
        "turn" => made.rotation_deg = demonstrator.rotation_deg,
        other => anyhow::bail!("unknown mode {other:?}: none, all, xy, xy-when-moving, z or turn"),
    }
    Ok(made)
}

/// The policy acting, with its demonstrator's move mixed in while the tip is in the zone.
struct InTheZone {
    acting: Box<dyn Controller>,
    shadow: Box<dyn Controller>,
    mode: String,
    /// The zone: more than `from_mm` and at most `to_mm` past the entrance.
    from_mm: f64,
    to_mm: f64,
}

impl Controller for InTheZone {
    fn name(&self) -> &str {
        "teacher-in-the-zone"
    }

    fn reset(&mut self, seed: u64) {
        self.acting.reset(seed);
        self.shadow.reset(seed);
    }

    fn act(&mut self, observation: &Observation) -> Decision {
        let policy_move = self.acting.act(observation).action;
        let teacher_move = self.shadow.act(observation).action;
        let inserted_mm = observation.insertion_mm();
        let made = if inserted_mm > self.from_mm && inserted_mm <= self.to_mm {
            mixed(&self.mode, policy_move, teacher_move).expect("checked in main")
        } else {
            policy_move
        };
        Decision::plain(made)
    }
}

pub fn main() -> anyhow::Result<()> {
    let learned: String = arg(1, "hierarchical-cells".to_string())?;
    let teacher: String = arg(2, "expert-careful".to_string())?;
    let mode: String = arg(3, "none".to_string())?;
    let from_mm: f64 = arg(4, 0.2)?;
    let to_mm: f64 = arg(5, f64::INFINITY)?;
    let noise_scale: f64 = arg(6, 4.0)?;
    let episodes: usize = arg(7, 4000)?;
    let seed: u64 = arg(8, 2)?;
    mixed(&mode, Move::default(), Move::default())?;
    let cell = CellConfig::reference();
    let make_policy = policy::builtin_factory(&learned, &cell)?;
    let make_teacher = policy::builtin_factory(&teacher, &cell)?;
    let options = EnvOptions {
        noise_scale,
        kept_robots: 10,
        ..EnvOptions::from_cell(&cell)
    };
    let make = || {
        Box::new(InTheZone {
            acting: make_policy(),
            shadow: make_teacher(),
            mode: mode.clone(),
            from_mm,
            to_mm,
        }) as Box<dyn Controller>
    };
    let (summary, _) = evaluate(&cell, options, episodes, seed, &make, &|_| {});
    println!(
        "{learned} with {teacher}'s `{mode}` from {from_mm} to {to_mm} mm (noise ×{noise_scale}, \
         seed {seed}): {} of {} succeeded ({:.4}) in {:.2} steps",
        summary.successes,
        summary.episodes,
        summary.success_rate,
        summary.avg_steps.unwrap_or(f64::NAN),
    );
    Ok(())
}
