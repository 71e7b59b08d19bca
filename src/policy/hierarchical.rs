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
//! As a [`Controller`] the policy adds rules to the forward pass. The actor that acts is one
//! the demonstrators would use in the state ([`actor_with_work`]), a position move at the top
//! of the actor's range is the full step its labels stand for ([`full_step`]), a sideways move
//! towards the axis covers the demonstrators' share of the offset, no less and no more
//! ([`centred_as_the_demonstrators`]), and the move is limited ([`limit_move`]): after a move
//! refused for a predicted contact the next move does not go deeper ([`holds_depth_after`]), a
//! sideways move stops just past the axis, a turn at level, and a turn in the bore pivots
//! about the engaged shaft ([`pivot_in_bore`]). Where a learned policy runs, the move after
//! such a refusal centres as the demonstrators do ([`centres_after_a_refusal`]).
//! `celld policy run` prints the forward pass alone.

use super::expert::{ExpertTuning, engaged_middle_off_axis_mm, tip_in_bore};
use super::file::{ACTOR_DIM, HEAD_DIM, PolicyFile, STATE_DIM};
use super::inputs::PolicyInputs;
use super::mlp::{Mlp, MlpConfig};
use super::{Actor, Controller, Decision};
use crate::collision::supervisor::VetoReason;
use crate::config::cell::CellShape;
use crate::geometry::Move;
use crate::sim::Observation;
use candle_core::{DType, Device, Module, Tensor};
use candle_nn::rnn::{LSTMState, RNN};
use candle_nn::{LSTM, LSTMConfig, Linear, VarBuilder};
use nalgebra::{Point3, Vector2, Vector3};
use serde::Serialize;
use std::sync::Once;

mod plain;
use plain::{PlainNet, Scratch};

/// Sets `RAYON_NUM_THREADS` (to the number of available cores) when it is unset. Without it,
/// candle 0.11 re-reads /proc/cpuinfo on every matmul, which makes a batch-1 step several times
/// slower. Call it at the start of `main`, before any thread is spawned and any candle call;
/// further calls do nothing.
pub fn init_cpu_threads() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        if std::env::var_os("RAYON_NUM_THREADS").is_none() {
            let n = std::thread::available_parallelism().map_or(1, |n| n.get());
            // SAFETY: called once, at start-up, before the program reads the environment from
            // other threads (documented requirement of this function).
            unsafe { std::env::set_var("RAYON_NUM_THREADS", n.to_string()) };
        }
    });
}

/// Whether the move after `last_veto` may not go deeper into the bore (Δz < 0 in {M}).
///
/// The paper's rule for a refused move (§2.2, collision detection): the state is read again and the policy asks
/// for a new move. At the entrance, a few hundredths of a millimetre off sideways, the new move
/// is the refused one again up to the camera's noise (sideways and down at once), and 20
/// refusals in a row fail the episode. Holding the depth after a refusal for contact lets the
/// sideways part through; the next move goes in once the shaft is centred (docs/learning.md).
pub fn holds_depth_after(last_veto: Option<&VetoReason>) -> bool {
    last_veto.is_some_and(VetoReason::is_about_contact)
}

/// The deepest move along the axis (Δz, mm in {M}, negative is deeper) the position actor may
/// ask for now: never past the seated depth the estimate sees (P_z; from beyond it, a move
/// back), and no deeper at all after a refusal for contact ([`holds_depth_after`]).
///
/// The demonstrators never go past the goal, so a cloned actor's answer there is arbitrary:
/// one that overshot its last step by a few tenths of a millimetre kept pushing against the
/// seat until the step limit (docs/learning.md).
pub fn deepest_move_mm(observation: &Observation) -> f64 {
    let to_goal_mm = observation.state[8];
    if holds_depth_after(observation.last_veto.as_ref()) {
        to_goal_mm.max(0.0)
    } else {
        to_goal_mm
    }
}

/// How far past the bore's axis a sideways move may carry the shoulder (mm): half the radial
/// clearance beside the supervisor's wall margin, 0.015 mm on the reference cell and 0.005 mm
/// on a Φ100 bore 100 mm deep with 0.03 mm of clearance.
///
/// The demonstrators centre a point of the engaged shaft, not the shoulder, and leave a tilt
/// of at most half the cell's clearance tilt ([`CellShape::clearance_tilt_deg`]); over the
/// engaged length (the bore's depth) the two points then differ by at most this. A fixed
/// 0.05 mm, ten times the deep cell's figure, let a cloned actor answer a 0.006 mm offset
/// with a 0.017 mm move into the wall margin, refused until 20 refusals ended the episode
/// (docs/learning.md).
pub fn past_the_axis_mm(cell: &CellShape) -> f64 {
    (cell.clearance_beside_margin_mm() / 2.0).max(0.0)
}

/// `translation_mm` with each sideways component (x, y in {M}) that moves the shoulder towards
/// the bore's axis cut to the offset the estimate sees (P_x, P_y) plus [`past_the_axis_mm`].
///
/// The demonstrators move sideways by at most the offset (`expert`: the offset, less above
/// the entrance), so a cloned actor's longer move is an error of the imitation: a policy
/// 1–2 mm off the axis above the entrance crossed it by about twice the offset each step and
/// swung there until the step limit (docs/learning.md).
pub fn not_past_the_axis(observation: &Observation, translation_mm: Vector3<f64>) -> Vector3<f64> {
    let mut cut = translation_mm;
    let past_mm = past_the_axis_mm(&observation.cell);
    for axis in 0..2 {
        // A move of +P_x carries the shoulder onto the axis (P is {F}'s origin in {M}).
        let offset_mm = observation.state[6 + axis];
        let towards = cut[axis] * offset_mm > 0.0;
        let widest_mm = offset_mm.abs() + past_mm;
        if towards && cut[axis].abs() > widest_mm {
            cut[axis] = widest_mm.copysign(cut[axis]);
        }
    }
    cut
}

/// A position move (mm in {M}) as the policy may make it: no deeper than [`deepest_move_mm`],
/// and no further sideways than [`not_past_the_axis`].
pub fn limit_position_move(
    observation: &Observation,
    translation_mm: Vector3<f64>,
) -> Vector3<f64> {
    let mut limited = translation_mm;
    limited.z = limited.z.max(deepest_move_mm(observation));
    not_past_the_axis(observation, limited)
}

/// `rotation_deg` with each component (θx, θy, θz in {M}) kept between zero and the
/// orientation error the estimate sees (O_x, O_y, O_z): a tilting move never carries the shaft
/// past level, nor the holes past their line, and never turns away from them.
///
/// The demonstrators turn by the error times a factor of at most 1, so a cloned actor's longer
/// or opposite turn is an error of the imitation: a policy 11 mm off the axis above the
/// entrance answered a 0.026° tilt with 0.06° each way and swung there until the step limit
/// (docs/learning.md).
pub fn not_past_level(observation: &Observation, rotation_deg: Vector3<f64>) -> Vector3<f64> {
    Vector3::from_fn(|axis, _| {
        let error_deg = observation.state[9 + axis];
        rotation_deg[axis].clamp(error_deg.min(0.0), error_deg.max(0.0))
    })
}

/// Ceiling of the step-size label (the target of sigmoid(ω3)) behaviour cloning gives a move.
pub const MAX_SCALE_LABEL: f64 = 0.98;
/// Ceiling of each component of the direction label (the target of an actor's tanh output).
pub const MAX_DIRECTION_LABEL: f64 = 0.95;
/// From this share of the step limit up, a position move is read as the start of a full step
/// ([`full_step`]).
pub const FULL_STEP_FROM: f64 = 0.85;

/// `translation_mm` (a position move of the network) with its largest component stretched
/// from [`FULL_STEP_FROM`] of `step_limit_mm` up so that the labels of a full step give the
/// limit.
///
/// Behaviour cloning keeps its labels off tanh's and the sigmoid's asymptotes, so a move at
/// the step limit is labelled as [`MAX_SCALE_LABEL`] × [`MAX_DIRECTION_LABEL`] = 0.931 of it
/// (4.66 mm of 5), and a policy fitted to those labels gives 4.5–4.8 mm where its demonstrator
/// took 5: on the reference cell `hierarchical-swift` took 1.1 steps more per episode than
/// with this rule (docs/learning.md). Between `FULL_STEP_FROM` and 0.931 of the limit the
/// largest component maps linearly onto the rest of the way to the limit, with the direction
/// kept; shorter moves, which the labels carry exactly, are left as they are.
pub fn full_step(translation_mm: Vector3<f64>, step_limit_mm: f64) -> Vector3<f64> {
    let largest_mm = translation_mm.amax();
    let from_mm = FULL_STEP_FROM * step_limit_mm;
    let label_mm = MAX_SCALE_LABEL * MAX_DIRECTION_LABEL * step_limit_mm;
    if largest_mm <= from_mm {
        return translation_mm;
    }
    let stretched_mm = (from_mm
        + (largest_mm - from_mm) * (step_limit_mm - from_mm) / (label_mm - from_mm))
        .min(step_limit_mm);
    (translation_mm * (stretched_mm / largest_mm)).map(|v| v.clamp(-step_limit_mm, step_limit_mm))
}

/// The shortest share of the offset to the axis that a demonstrator's sideways move covers:
/// `expert` moves by 0.8 of it above the entrance within 0.5 mm of the axis, by all of it
/// elsewhere (by 0.85–1 of it, a person's variability, when the move is over 1 mm).
pub const SHORTEST_CENTRING_SHARE: f64 = 0.8;

/// The approach ends this many times the demonstrators' standoff above the entrance: half as
/// much again as the standoff, for the estimate's jitter there.
pub const APPROACH_STANDOFF_FACTOR: f64 = 1.5;

/// Height of the tip above the bore's entrance (mm) above which a learned position move goes
/// neither away from the axis nor up: [`APPROACH_STANDOFF_FACTOR`] times the demonstrators'
/// standoff ([`ExpertTuning::standoff_mm`], 1 mm), so 1.5 mm.
pub fn approach_above_mm() -> f64 {
    APPROACH_STANDOFF_FACTOR * ExpertTuning::default().standoff_mm
}

/// `translation_mm` with each sideways component (x, y in {M}) that moves towards the axis
/// made at least [`SHORTEST_CENTRING_SHARE`] of the demonstrators' centring move
/// ([`engaged_middle_off_axis_mm`]), up to `step_limit_mm`, and at most the whole centring
/// move: no demonstrator goes further. On the approach, with the tip more than
/// [`approach_above_mm`] above the entrance, a component away from the axis and a move up
/// are dropped, as no demonstrator makes them; lower down they are left as they are. A hold
/// is left as it is, and [`not_past_the_axis`] still bounds the shoulder.
///
/// A cloned actor's sideways move is the small part of a move that is mostly along the axis,
/// and it is off by about a hundredth of a millimetre: a policy centred to 0.01–0.02 mm where
/// its demonstrator centres exactly, and its moves into the bore were refused or shortened;
/// on a loose, shallow cell one policy hovered 0.02 mm off the axis at the standoff, moving
/// sideways by 0.001 mm each way, until the step limit; and on the approach the policy went
/// 3.9–4.5 mm sideways where its demonstrator goes the whole 5 mm. Past the centring move,
/// up to [`not_past_the_axis`]'s allowance, it carried the engaged shaft across the axis and
/// back (decisions 0030, 0031). On the approach the sideways part of a 5 mm move down was off
/// by about 1 % of the move, 0.05 mm away from the axis, which the next steps spent centring
/// again at the standoff, and the policy went up by up to 0.7 mm between moves down. At the
/// standoff and in the bore, at four times the camera's noise, a move partly away from the
/// noisy estimate's axis is worth keeping: dropping it there too ended 0.7 % more episodes
/// (decision 0032).
pub fn centred_as_the_demonstrators(
    observation: &Observation,
    translation_mm: Vector3<f64>,
    step_limit_mm: f64,
) -> Vector3<f64> {
    let centring = demonstrators_centring_mm(observation, step_limit_mm);
    let approaching = observation.insertion_mm() < -approach_above_mm();
    let mut centred = translation_mm;
    for axis in 0..2 {
        let whole_mm = centring[axis].abs();
        let shortest_mm = (whole_mm * SHORTEST_CENTRING_SHARE).min(step_limit_mm);
        if centred[axis] * centring[axis] > 0.0 {
            // Towards the axis: between the shortest share and the whole move, same direction.
            centred[axis] = centred[axis]
                .abs()
                .clamp(shortest_mm, whole_mm)
                .copysign(centring[axis]);
        } else if approaching {
            centred[axis] = 0.0;
        }
    }
    if approaching {
        centred.z = centred.z.min(0.0);
    }
    centred
}

/// The demonstrators' centring move in the estimated state (x and y of {M}, mm): minus
/// [`engaged_middle_off_axis_mm`] for a step of `step_limit_mm`.
pub fn demonstrators_centring_mm(observation: &Observation, step_limit_mm: f64) -> Vector2<f64> {
    let s = &observation.state;
    -engaged_middle_off_axis_mm(
        Vector3::new(s[6], s[7], s[8]),
        Vector3::new(s[9], s[10], s[11]),
        observation.cell.bore_depth_mm,
        step_limit_mm,
    )
}

/// The camera's point noise, as a multiple of its data sheet and as the cell learns it from
/// its fits' residuals ([`crate::camera::StateFilter::noise_scale`]), above which a learned
/// policy moves down the bore as its demonstrators do ([`descends_as_the_demonstrators`]).
/// Midway between what the cell learns of a camera twice and four times as noisy as its data
/// sheet: over 200 episodes in the bore it read 0.90–1.08, 1.84–2.16 and 3.74–4.25 at one,
/// two and four times.
pub const NOISY_CAMERA_SCALE: f64 = 3.0;

/// How far past the bore's entrance (mm) the tip is when [`descends_as_the_demonstrators`]
/// starts to apply.
pub const DESCENT_AS_DEMONSTRATED_FROM_MM: f64 = 0.2;

/// Whether `decision` is a position move down the bore, the tip more than
/// [`DESCENT_AS_DEMONSTRATED_FROM_MM`] past the entrance, with a camera noisier than
/// [`NOISY_CAMERA_SCALE`]. A learned policy then makes it as its demonstrators do: sideways,
/// exactly their centring move ([`demonstrators_centring_mm`]), not steered against the
/// learned drift, and over the first 35 mm no longer than `expert-careful`'s step
/// (`LearnedPolicy`; decision 0047). At four times the camera's noise that ends fewer episodes
/// on the step limit; on a quieter camera the steering is what lets the long steps of a fast
/// policy through whole (decision 0034).
pub fn descends_as_the_demonstrators(observation: &Observation, decision: &Decision) -> bool {
    decision.actor == Some(Actor::Position)
        && decision.action.translation_mm.z < 0.0
        && observation.insertion_mm() > DESCENT_AS_DEMONSTRATED_FROM_MM
        && observation.estimate.noise_scale() > NOISY_CAMERA_SCALE
}

/// Whether `decision` is a position move right after a move refused for a predicted contact
/// ([`holds_depth_after`]): the move that holds the depth so that its sideways part can centre
/// the shaft. A learned policy then moves sideways exactly by its demonstrators' centring move
/// ([`demonstrators_centring_mm`]), not steered against the learned drift (`LearnedPolicy`).
///
/// A cloned actor's sideways part is the small part of a move that is mostly along the axis,
/// and after a refusal it is all there is. On a deep, tight bore it went away from the axis
/// the demonstrators centre (the middle of the engaged shaft): in the bore it narrowed the
/// gap to the wall, the supervisor refused it for the wall margin and the policy asked the
/// same again until 20 refusals ended the episode; at the entrance, refused for the wall, it
/// went 0.1 mm further off and hovered there until the step limit (decision 0035).
pub fn centres_after_a_refusal(observation: &Observation, decision: &Decision) -> bool {
    decision.actor == Some(Actor::Position) && holds_depth_after(observation.last_veto.as_ref())
}

/// The shortest share of the orientation error the estimate sees that a demonstrator's turn
/// covers: `expert` turns by 0.85–1 of it (a person's variability), by 0.9 of it below 0.2°.
pub const SHORTEST_TURN_SHARE: f64 = 0.85;

/// `rotation_deg` (an orientation move of the network) with every component made a turn
/// towards level of at least [`SHORTEST_TURN_SHARE`] of the error the estimate sees on that
/// axis (O_x, O_y, O_z), up to `step_limit_deg`, and of at most the whole error, as the
/// demonstrators turn. Only where there is a tilt or a roll to turn by the demonstrators'
/// tolerances ([`has_turn_to_make`]): elsewhere in the bore a chosen turn with nothing to
/// turn stands for a hold while the estimate settles, and is left as it is.
///
/// A cloned actor's turn is a move of hundredths of a degree read off a tanh. Above the
/// entrance with a tilt just over the tolerance (0.016–0.024° against 0.0143°), the swift
/// cross-cell recipe's policy asked for turns of under 0.0005° at every step until the step
/// limit (decision 0036).
pub fn turned_as_the_demonstrators(
    observation: &Observation,
    rotation_deg: Vector3<f64>,
    step_limit_deg: f64,
) -> Vector3<f64> {
    if !has_turn_to_make(observation, 1.0) {
        return rotation_deg;
    }
    Vector3::from_fn(|axis, _| {
        let error_deg = observation.state[9 + axis];
        let whole_deg = error_deg.abs();
        let shortest_deg = (whole_deg * SHORTEST_TURN_SHARE).min(step_limit_deg);
        // The turn along the error's direction, between the shortest share and the whole.
        (rotation_deg[axis] * error_deg.signum())
            .clamp(shortest_deg, whole_deg)
            .copysign(error_deg)
    })
}

/// The move the policy makes of `step`, the forward pass's move by `actor`: a position move
/// read by [`full_step`] and [`centred_as_the_demonstrators`], an orientation move by
/// [`turned_as_the_demonstrators`], then the move of either actor limited by [`limit_move`].
/// The controller and TD3's episodes and validations all make it here.
pub fn asked_move(
    observation: &Observation,
    config: &PolicyConfig,
    actor: Actor,
    step: Move,
) -> Move {
    let step = match actor {
        Actor::Position => Move {
            translation_mm: centred_as_the_demonstrators(
                observation,
                full_step(step.translation_mm, config.step_limit_mm),
                config.step_limit_mm,
            ),
            ..step
        },
        Actor::Orientation => Move {
            rotation_deg: turned_as_the_demonstrators(
                observation,
                step.rotation_deg,
                config.step_limit_deg,
            ),
            ..step
        },
    };
    limit_move(observation, actor, step)
}

/// A move of `actor` as the policy may make it: a position move by [`limit_position_move`], an
/// orientation move by [`not_past_level`] and [`pivot_in_bore`]. The controller and TD3's
/// episodes both limit the actor's move here, so TD3 learns from the moves the deployed policy
/// makes, but for the steering against the learned drift that a policy gets where it runs
/// (`super::learned`).
pub fn limit_move(observation: &Observation, actor: Actor, step: Move) -> Move {
    match actor {
        Actor::Position => Move {
            translation_mm: limit_position_move(observation, step.translation_mm),
            ..step
        },
        Actor::Orientation => pivot_in_bore(
            observation,
            Move {
                rotation_deg: not_past_level(observation, step.rotation_deg),
                ..step
            },
        ),
    }
}

/// `step` with the translation that keeps the middle of the shaft's engaged length in place
/// once the tip is in the bore, so that a turn pivots there rather than about {M}'s origin at
/// the shoulder.
///
/// The demonstrators level the shaft above the bore and turn about the shoulder; a policy that
/// enters with a little tilt left and levels it 1 mm in swings its tip sideways by the depth
/// times the turn (0.025 mm for 0.024° on the reference cell). The supervisor refused that
/// turn for the wall margin 20 times in a row, ending the episode, and on a Φ100 bore 100 mm
/// deep such turns ended 13 of 4000 episodes (decision 0025).
pub fn pivot_in_bore(observation: &Observation, step: Move) -> Move {
    let insertion_mm = observation.insertion_mm();
    if !tip_in_bore(insertion_mm) {
        return step;
    }
    let length_mm = observation.cell.bore_depth_mm;
    let engaged_mm = insertion_mm.clamp(0.0, length_mm);
    let engaged_middle = Point3::new(0.0, 0.0, -length_mm + engaged_mm / 2.0);
    let keep = engaged_middle - step.as_pose().rotation * engaged_middle;
    Move {
        translation_mm: step.translation_mm + keep,
        ..step
    }
}

/// How far past the demonstrators' tolerance (a factor on the tilt and on the roll) the
/// position actor may still act above the bore. In the bore it acts only within the
/// tolerances, as the demonstrators do.
const TOLERANCE_FACTOR_TO_MOVE_WITH_ABOVE_THE_BORE: f64 = 1.5;

/// The actor that acts for the selector's choice `selected` on `observation`: the choice,
/// but for two states where the demonstrators never use the chosen actor.
///
/// - The position actor, with a tilt or a roll of more than the demonstrators' tolerance on
///   this cell ([`ExpertTuning::tilt_tolerance_deg_on`], the roll tolerance) in the bore, or
///   of more than 1.5 times it above the bore: the orientation actor acts. A demonstrator
///   turns first.
/// - The orientation actor, with nothing to turn (tilt and roll within the tolerances) and
///   the tip above the bore or the shaft being seated (within [`BEING_SEATED_WITHIN_MM`] of
///   the seated depth): the position actor acts. A demonstrator moves. Elsewhere in the bore
///   a chosen turn with nothing to turn stands for a hold while the estimate settles, and is
///   left alone.
///
/// Without it, selectors kept choosing the position actor at the entrance with a 0.022–0.031°
/// tilt or, seated, with the holes 0.05–0.12° off, and the orientation actor with nothing to
/// turn 11–15 mm off the axis above the bore, each until the step limit (decision 0024).
/// Seated to within 0.05–0.2 mm, with nothing left to turn, a selector held until the step
/// limit (decision 0035). Above the bore the extra half saves a few turns on the reference
/// cell. In the bore a tilt left there narrows the gap to the wall along the whole engaged
/// length: at four times the camera's noise, with 1.5 times the tolerance in the bore too,
/// the supervisor refused the moves down until more episodes ran out of steps (decision
/// 0033).
pub fn actor_with_work(selected: Actor, observation: &Observation) -> Actor {
    let inside = tip_in_bore(observation.insertion_mm());
    let factor = if inside {
        1.0
    } else {
        TOLERANCE_FACTOR_TO_MOVE_WITH_ABOVE_THE_BORE
    };
    match selected {
        Actor::Position if has_turn_to_make(observation, factor) => Actor::Orientation,
        Actor::Orientation
            if !has_turn_to_make(observation, 1.0) && (!inside || being_seated(observation)) =>
        {
            Actor::Position
        }
        actor => actor,
    }
}

/// Whether the estimate sees a tilt or a roll of more than `factor` times the demonstrators'
/// tolerance on this cell, with the tip where it is
/// ([`ExpertTuning::tilt_tolerance_deg_on`], the roll tolerance).
fn has_turn_to_make(observation: &Observation, factor: f64) -> bool {
    let s = &observation.state;
    let demonstrators = ExpertTuning::default();
    let inside = tip_in_bore(observation.insertion_mm());
    let tilt_tolerance =
        demonstrators.tilt_tolerance_deg_on(observation.cell.clearance_tilt_deg(), inside);
    s[9].hypot(s[10]) > factor * tilt_tolerance
        || s[11].abs() > factor * demonstrators.roll_tolerance_deg
}

/// How far short of the seated depth (mm, by the estimate) the tip is when the shaft counts
/// as being seated ([`actor_with_work`]).
pub const BEING_SEATED_WITHIN_MM: f64 = 1.0;

/// Whether the tip is within [`BEING_SEATED_WITHIN_MM`] of the seated depth the estimate sees,
/// or past it.
fn being_seated(observation: &Observation) -> bool {
    // P_z is 0 seated, negative short of it.
    -observation.state[8] < BEING_SEATED_WITHIN_MM
}

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

    /// One step of the single episode as the policy acts: the forward pass, with the actor
    /// that acts kept to one with work to do ([`actor_with_work`]).
    pub fn step_to_act(
        &mut self,
        state: &[f64; 12],
        observation: &Observation,
    ) -> candle_core::Result<PolicyOutput> {
        self.step_choosing(state, &|actor| actor_with_work(actor, observation))
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

impl Controller for HierarchicalPolicy {
    fn name(&self) -> &str {
        &self.name
    }

    fn reset(&mut self, _seed: u64) {
        HierarchicalPolicy::reset(self);
    }

    /// The policy's move; a step that fails or is not finite holds still (a zero move). Without
    /// a fresh frame the cell holds still and the LSTM does not advance (the expert's
    /// demonstrations have no such steps). The move is made by [`asked_move`]: a position
    /// move at the top of the actor's range is a full step, not past the goal, not deeper after
    /// a refusal for contact, and not past the axis; an orientation move not past level.
    fn act(&mut self, observation: &Observation) -> Decision {
        if !observation.measurement_fresh {
            return Decision::hold();
        }
        let inputs = self.config().inputs.of(observation);
        match self.step_to_act(&inputs, observation) {
            Ok(out) if out.is_finite() => Decision {
                action: asked_move(observation, self.config(), out.actor, out.to_move()),
                actor: Some(out.actor),
                scale: Some(out.scale as f64),
            },
            _ => Decision::hold(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::policy::file::TENSOR_NAMES;

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

    /// An observation on the reference cell, the tip `above_mm` above the entrance (negative
    /// in the bore), level and on the axis.
    fn observation_above(above_mm: f64) -> Observation {
        use crate::config::cell::CellConfig;
        use crate::sim::{AssemblyEnv, EnvOptions};
        let cell = CellConfig::reference();
        let mut env = AssemblyEnv::new(&cell, EnvOptions::from_cell(&cell));
        let mut observation = env.reset(4).unwrap();
        assert_eq!(observation.cell.bore_depth_mm, 60.0);
        observation.state[6..12].copy_from_slice(&[0.0, 0.0, -60.0 - above_mm, 0.0, 0.0, 0.0]);
        observation
    }

    #[test]
    fn only_a_position_move_down_the_bore_under_a_noisy_camera_descends_as_demonstrated() {
        let down = |actor| Decision {
            action: Move::translation(0.01, 0.0, -2.0),
            actor: Some(actor),
            scale: None,
        };
        let at = |above_mm: f64, noise_scale: f64| {
            let mut observation = observation_above(above_mm);
            observation.estimate.set_noise_scale(noise_scale);
            observation
        };
        let position = down(Actor::Position);
        // 10 mm into the bore with the camera four times as noisy as its data sheet.
        assert!(descends_as_the_demonstrators(&at(-10.0, 4.0), &position));
        // At twice the noise, or just below the threshold, the policy moves as it asks.
        assert!(!descends_as_the_demonstrators(&at(-10.0, 2.2), &position));
        assert!(!descends_as_the_demonstrators(&at(-10.0, 2.99), &position));
        // Above the bore and at the entrance, neither.
        assert!(!descends_as_the_demonstrators(&at(5.0, 4.0), &position));
        assert!(!descends_as_the_demonstrators(&at(-0.1, 4.0), &position));
        // Nor a turn, a hold, a move up or a move with no actor (a flat policy).
        assert!(!descends_as_the_demonstrators(
            &at(-10.0, 4.0),
            &down(Actor::Orientation)
        ));
        assert!(!descends_as_the_demonstrators(
            &at(-10.0, 4.0),
            &Decision::hold()
        ));
        let up = Decision {
            action: Move::translation(0.0, 0.0, 1.0),
            ..position
        };
        assert!(!descends_as_the_demonstrators(&at(-10.0, 4.0), &up));
        let flat = Decision::plain(position.action);
        assert!(!descends_as_the_demonstrators(&at(-10.0, 4.0), &flat));
    }

    #[test]
    fn only_a_position_move_after_a_refusal_for_contact_centres_as_the_demonstrators() {
        let wall = VetoReason::WallMargin {
            clearance_mm: 0.017,
            margin_mm: 0.02,
            start_mm: 0.025,
        };
        let after = |veto: Option<VetoReason>| {
            let mut observation = observation_above(-3.0);
            observation.last_veto = veto;
            observation
        };
        let position = Decision {
            action: Move::translation(0.0, 0.007, 0.0),
            actor: Some(Actor::Position),
            scale: None,
        };
        let contact = VetoReason::Collision {
            kind: crate::collision::clearance::ContactKind::Wall,
            clearance_mm: -0.25,
        };
        assert!(centres_after_a_refusal(
            &after(Some(wall.clone())),
            &position
        ));
        assert!(centres_after_a_refusal(&after(Some(contact)), &position));
        // Refused as uncertain, or not refused, the policy moves as it asks.
        let uncertain = VetoReason::Uncertain {
            risk: 2e-4,
            bound: 1e-4,
            clearance_mm: 0.02,
        };
        assert!(!centres_after_a_refusal(&after(Some(uncertain)), &position));
        assert!(!centres_after_a_refusal(&after(None), &position));
        // Nor a turn, or a move with no actor (a flat policy).
        let turn = Decision {
            actor: Some(Actor::Orientation),
            ..position
        };
        assert!(!centres_after_a_refusal(&after(Some(wall.clone())), &turn));
        let flat = Decision::plain(position.action);
        assert!(!centres_after_a_refusal(&after(Some(wall)), &flat));
    }

    #[test]
    fn a_turn_covers_the_demonstrators_share_of_the_error_where_there_is_one_to_make() {
        let at = |above_mm: f64, o: [f64; 3]| {
            let mut observation = observation_above(above_mm);
            observation.state[9..12].copy_from_slice(&o);
            observation
        };
        let close = |a: Vector3<f64>, b: [f64; 3]| (a - Vector3::from(b)).amax() < 1e-12;
        // A 0.036° tilt above the reference bore (tolerance 0.0143°): a turn to make.
        let tilted = at(10.0, [0.03, -0.02, 0.01]);
        // x: 0.012° of 0.03° becomes 0.85 of it, 0.0255°; y: -0.02° of -0.02° is whole and
        // stays; z, a turn away from level, becomes 0.85 of the roll, 0.0085°.
        let turned = turned_as_the_demonstrators(&tilted, Vector3::new(0.012, -0.02, -0.005), 0.2);
        assert!(close(turned, [0.0255, -0.02, 0.0085]), "{turned:?}");
        // Never past the whole error; the shortest share no longer than the step limit.
        let long = turned_as_the_demonstrators(&tilted, Vector3::new(0.05, -0.001, 0.0), 0.2);
        assert!(close(long, [0.03, -0.017, 0.0085]), "{long:?}");
        let limited = turned_as_the_demonstrators(&tilted, Vector3::new(0.012, 0.0, 0.0), 0.02);
        assert!(close(limited, [0.02, -0.017, 0.0085]), "{limited:?}");
        // Within the tolerances (tilt 0.01°, roll 0.02°) above the bore, or in the bore with
        // nothing to turn, a chosen turn is left as it is.
        let small = Vector3::new(0.001, 0.001, 0.001);
        assert_eq!(
            turned_as_the_demonstrators(&at(10.0, [0.006, 0.008, 0.02]), small, 0.2),
            small
        );
        assert_eq!(
            turned_as_the_demonstrators(&at(-30.0, [0.0; 3]), small, 0.2),
            small
        );
        // A roll alone past its tolerance (0.025°) is a turn to make; with no tilt there is
        // nothing to turn about x and y.
        let rolled = turned_as_the_demonstrators(&at(-30.0, [0.0, 0.0, -0.04]), small, 0.2);
        assert!(close(rolled, [0.0, 0.0, -0.034]), "{rolled:?}");
        // The move the policy makes of an orientation actor's step turns so too, and a
        // position actor's step is not turned.
        let config = PolicyConfig {
            hidden_size: 64,
            actor_width: 64,
            step_limit_mm: 5.0,
            step_limit_deg: 0.2,
            inputs: PolicyInputs::Absolute,
        };
        let step = Move {
            translation_mm: Vector3::zeros(),
            rotation_deg: small,
        };
        let asked = asked_move(&tilted, &config, Actor::Orientation, step);
        assert!(
            close(asked.rotation_deg, [0.0255, -0.017, 0.0085]),
            "{asked:?}"
        );
        assert_eq!(asked.translation_mm, Vector3::zeros());
        let position = asked_move(&tilted, &config, Actor::Position, step);
        assert_eq!(position.rotation_deg, small);
    }

    #[test]
    fn an_actor_acts_only_where_a_demonstrator_would_use_it() {
        let (pos, ori) = (Actor::Position, Actor::Orientation);
        let at = |above_mm: f64, o: [f64; 3]| {
            let mut observation = observation_above(above_mm);
            observation.state[9..12].copy_from_slice(&o);
            observation
        };
        // The reference cell's tolerances: tilt min(0.02°, 0.029°/2) = 0.0143°, roll 0.025°.
        // Above the bore the position actor acts up to 1.5 times them: 0.0215° and 0.0375°;
        // in the bore (a tip 0.1 mm above the entrance counts as in it) up to them.
        assert_eq!(actor_with_work(pos, &at(10.0, [0.012, 0.016, 0.0])), pos);
        assert_eq!(actor_with_work(pos, &at(10.0, [0.018, 0.024, 0.0])), ori);
        assert_eq!(actor_with_work(pos, &at(10.0, [0.0, 0.0, 0.035])), pos);
        assert_eq!(actor_with_work(pos, &at(0.1, [0.012, 0.016, 0.0])), ori);
        assert_eq!(actor_with_work(pos, &at(-30.0, [0.0072, 0.0096, 0.0])), pos);
        assert_eq!(actor_with_work(pos, &at(-30.0, [0.009, 0.012, 0.0])), ori);
        assert_eq!(actor_with_work(pos, &at(-59.9, [0.0, 0.0, 0.024])), pos);
        assert_eq!(actor_with_work(pos, &at(-59.9, [0.0, 0.0, 0.035])), ori);
        assert_eq!(actor_with_work(pos, &at(-59.9, [0.0, 0.0, -0.04])), ori);
        // Nothing to turn above the bore: the position actor.
        assert_eq!(actor_with_work(ori, &at(10.0, [0.006, 0.008, 0.02])), pos);
        // A roll or a tilt to turn, or the tip in the bore (0.1 mm above the entrance counts
        // as in it): the choice stands.
        assert_eq!(actor_with_work(ori, &at(10.0, [0.006, 0.008, 0.03])), ori);
        assert_eq!(actor_with_work(ori, &at(10.0, [0.012, 0.012, 0.0])), ori);
        assert_eq!(actor_with_work(ori, &at(0.1, [0.0; 3])), ori);
        assert_eq!(actor_with_work(ori, &at(-30.0, [0.0; 3])), ori);
        // Being seated (the reference bore is 60 mm deep), with nothing to turn: the position
        // actor; 1.5 mm short, the choice stands; with a roll to turn, it stands too.
        assert_eq!(actor_with_work(ori, &at(-59.5, [0.0; 3])), pos);
        assert_eq!(actor_with_work(ori, &at(-60.02, [0.0; 3])), pos);
        assert_eq!(actor_with_work(ori, &at(-58.5, [0.0; 3])), ori);
        assert_eq!(actor_with_work(ori, &at(-59.5, [0.0, 0.0, 0.03])), ori);
        // On a Φ100 bore 100 mm deep with 0.03 mm of clearance the tilt tolerance is
        // atan(0.01 / 100) / 2 = 0.00286°: a 0.005° tilt is past 1.5 times it.
        let mut tight = at(10.0, [0.003, 0.004, 0.0]);
        assert_eq!(actor_with_work(pos, &tight), pos);
        tight.cell.radial_clearance_mm = 0.03;
        tight.cell.bore_depth_mm = 100.0;
        tight.state[8] = -110.0;
        assert_eq!(actor_with_work(pos, &tight), ori);
    }

    #[test]
    fn a_turn_in_the_bore_pivots_about_the_middle_of_the_engaged_shaft() {
        let turn = Move {
            translation_mm: Vector3::zeros(),
            rotation_deg: Vector3::new(0.0, 0.024, 0.0),
        };
        // Above the bore the turn is left as asked.
        assert_eq!(pivot_in_bore(&observation_above(5.0), turn), turn);
        // 1 mm into the reference cell's 60 mm bore: the engaged middle is 59.5 mm below
        // {M}'s origin, and a turn of θ about y would swing it by 59.5 sin θ along x
        // (0.0249 mm for 0.024°), so the pivot moves {M} back by that much.
        let inside = observation_above(-1.0);
        let pivoted = pivot_in_bore(&inside, turn);
        assert_eq!(pivoted.rotation_deg, turn.rotation_deg);
        let theta = 0.024f64.to_radians();
        let expected = Vector3::new(59.5 * theta.sin(), 0.0, -59.5 * (1.0 - theta.cos()));
        assert!((pivoted.translation_mm - expected).norm() < 1e-12);
        assert!((0.0249..0.0250).contains(&pivoted.translation_mm.x));
        // The point stays where it was, for any turn (a round trip through the move's pose).
        let middle = Point3::new(0.0, 0.0, -59.5);
        let any = Move {
            translation_mm: Vector3::new(0.01, -0.02, 0.0),
            rotation_deg: Vector3::new(0.03, -0.02, 0.05),
        };
        let moved = pivot_in_bore(&inside, any).as_pose() * middle;
        assert!((moved - (middle + any.translation_mm)).norm() < 1e-9);
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
            let acted = acting.step_to_act(&state, &observation).unwrap();
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

    /// Along an episode of the bundled policy in the twin, the position move asked for after a
    /// refusal for contact equals the plain move except that it does not go deeper; a turn, or
    /// any move after a refusal for another reason, is the plain move.
    #[test]
    fn after_a_refusal_for_contact_the_move_keeps_its_depth_and_nothing_else_changes() {
        use crate::collision::clearance::ContactKind;
        use crate::config::cell::CellConfig;
        use crate::sim::{AssemblyEnv, EnvOptions};
        let cell = CellConfig::reference();
        let file =
            PolicyFile::from_bytes(super::super::bundled_policy("hierarchical").unwrap()).unwrap();
        let mut policy = HierarchicalPolicy::from_file(&file).unwrap();
        let mut env = AssemblyEnv::new(&cell, EnvOptions::from_cell(&cell));
        let mut observation = env.reset(11).unwrap();
        let refused = |observation: &Observation, veto: VetoReason| Observation {
            last_veto: Some(veto),
            ..observation.clone()
        };
        let contact = VetoReason::Collision {
            kind: ContactKind::Wall,
            clearance_mm: -0.01,
        };
        let mut held = 0;
        loop {
            let plain = observation.clone();
            let (mut after_contact, mut after_stale) = (policy.clone(), policy.clone());
            let asked = policy.act(&Observation {
                last_veto: None,
                ..plain.clone()
            });
            let stale = after_stale.act(&refused(&plain, VetoReason::StaleMeasurement));
            assert_eq!(stale.action, asked.action);
            let got = after_contact.act(&refused(&plain, contact.clone())).action;
            let want = asked.action;
            assert_eq!(got.rotation_deg, want.rotation_deg);
            assert_eq!(got.translation_mm.xy(), want.translation_mm.xy());
            if asked.actor == Some(Actor::Position) {
                assert_eq!(got.translation_mm.z, want.translation_mm.z.max(0.0));
                held += usize::from(want.translation_mm.z < 0.0);
            } else {
                // A turn's translation (the pivot in the bore) is not a move of the position
                // actor: the rule leaves it alone.
                assert_eq!(got.translation_mm.z, want.translation_mm.z);
            }
            let result = env.step(&want).unwrap();
            if result.outcome.is_some() {
                break;
            }
            observation = result.observation;
        }
        assert!(held > 0, "no move went deeper: the rule was not exercised");
    }

    /// A sideways move towards the axis stops half the clearance beside the wall margin past
    /// it (0.015 mm on the reference cell: 0.05 mm clearance, 0.02 mm margin; 0.005 mm with
    /// 0.03 mm clearance); one away from it, and the move along the axis, are left as they are.
    #[test]
    fn a_sideways_move_stops_just_past_the_axis() {
        use crate::config::cell::CellConfig;
        use crate::sim::{AssemblyEnv, EnvOptions};
        let cell = CellConfig::reference();
        let mut env = AssemblyEnv::new(&cell, EnvOptions::from_cell(&cell));
        let mut observation = env.reset(4).unwrap();
        assert!((observation.cell.radial_clearance_mm - 0.05).abs() < 1e-12);
        assert!((observation.cell.wall_margin_mm - 0.02).abs() < 1e-12);
        observation.state[6] = 1.6;
        observation.state[7] = -0.5;
        let cut_is = |observation: &Observation, asked: [f64; 3], expected: [f64; 3]| {
            let cut = not_past_the_axis(observation, Vector3::from(asked));
            assert!(
                (cut - Vector3::from(expected)).norm() < 1e-12,
                "{asked:?}: {cut}"
            );
        };
        cut_is(&observation, [3.5, -0.2, -1.0], [1.615, -0.2, -1.0]);
        cut_is(&observation, [1.0, -0.9, 0.0], [1.0, -0.515, 0.0]);
        cut_is(&observation, [-2.0, 1.0, 4.0], [-2.0, 1.0, 4.0]);
        cut_is(&observation, [1.6, -0.5, 0.0], [1.6, -0.5, 0.0]);
        // A tighter cell: 0.005 mm past the axis at most.
        let mut tight = observation.clone();
        tight.cell.radial_clearance_mm = 0.03;
        tight.state[6] = -0.003;
        tight.state[7] = 0.004;
        cut_is(&tight, [-0.017, 0.02, -2.0], [-0.008, 0.009, -2.0]);
        cut_is(&tight, [0.017, 0.006, 0.0], [0.017, 0.006, 0.0]);
        // A position move takes both limits: 0.3 mm above the goal, and the axis.
        observation.state[8] = -0.3;
        assert!(observation.last_veto.is_none());
        let limited = limit_position_move(&observation, Vector3::new(3.5, -0.2, -1.0));
        assert!(
            (limited - Vector3::new(1.615, -0.2, -0.3)).norm() < 1e-12,
            "{limited}"
        );
    }

    #[test]
    fn a_move_covers_the_demonstrators_share_and_on_the_approach_goes_neither_away_nor_up() {
        // Level, 3 mm above the entrance: the demonstrators centre the shoulder's offset.
        let mut observation = observation_above(3.0);
        observation.state[6] = 0.02;
        observation.state[7] = -0.01;
        let centred_is = |observation: &Observation, asked: [f64; 3], expected: [f64; 3]| {
            let centred = centred_as_the_demonstrators(observation, Vector3::from(asked), 5.0);
            assert!(
                (centred - Vector3::from(expected)).norm() < 1e-9,
                "{asked:?}: {centred}"
            );
        };
        // Towards the axis on both: at least 0.8 of the offset, the move down kept.
        centred_is(&observation, [0.001, -0.002, -2.0], [0.016, -0.008, -2.0]);
        // Away from the axis or up, 3 mm above the entrance: dropped; 1 mm above it, in the
        // bore, and a hold: as they are.
        centred_is(&observation, [-0.001, 0.002, -2.0], [0.0, 0.0, -2.0]);
        centred_is(&observation, [-0.001, -0.002, 0.4], [0.0, -0.008, 0.0]);
        for above_mm in [1.0, -20.0] {
            let mut lower = observation_above(above_mm);
            lower.state[6..8].copy_from_slice(&[0.02, -0.01]);
            centred_is(&lower, [-0.001, 0.002, 0.4], [-0.001, 0.002, 0.4]);
        }
        centred_is(&observation, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]);
        centred_is(&observation, [0.019, -0.009, 0.0], [0.019, -0.009, 0.0]);
        // Further than the offset (within not_past_the_axis's allowance): cut to it.
        centred_is(&observation, [0.03, -0.012, -2.0], [0.02, -0.01, -2.0]);
        // Far off the axis: the whole step, no more.
        observation.state[6] = 20.0;
        observation.state[7] = 3.0;
        centred_is(&observation, [4.2, 1.0, -1.0], [5.0, 2.4, -1.0]);
        // Tilted by 0.01° about y, 0.5 mm above: the point centred is the middle of the 5 mm a
        // full step engages, (0, 0, −57.5) in {M}, 3 mm from P along the axis; seen from {F}
        // turned by 0.01° it is 3 × sin(0.01°) mm further along x than P.
        let mut tilted = observation_above(0.5);
        tilted.state[6] = 0.02;
        tilted.state[10] = 0.01;
        let centring = -engaged_middle_off_axis_mm(
            Vector3::new(0.02, 0.0, -60.5),
            Vector3::new(0.0, 0.01, 0.0),
            60.0,
            5.0,
        );
        let by_hand = 0.02 * 0.01f64.to_radians().cos() + 3.0 * 0.01f64.to_radians().sin();
        assert!((centring.x - by_hand).abs() < 1e-12, "{centring}");
        centred_is(&tilted, [0.001, 0.0, -1.0], [0.8 * centring.x, 0.0, -1.0]);
        centred_is(&tilted, [0.05, 0.0, -1.0], [centring.x, 0.0, -1.0]);
    }

    /// A turn goes at most to level (and the holes to their line), never past it or away from
    /// it; a move of the other actor keeps its turn, and a position move is limited as before.
    #[test]
    fn a_turn_stops_at_level() {
        use crate::config::cell::CellConfig;
        use crate::sim::{AssemblyEnv, EnvOptions};
        let cell = CellConfig::reference();
        let mut env = AssemblyEnv::new(&cell, EnvOptions::from_cell(&cell));
        let mut observation = env.reset(4).unwrap();
        observation.state[9..12].copy_from_slice(&[0.03, -0.01, 0.2]);
        let cut_is = |asked: [f64; 3], expected: [f64; 3]| {
            let cut = not_past_level(&observation, Vector3::from(asked));
            assert!(
                (cut - Vector3::from(expected)).norm() < 1e-12,
                "{asked:?}: {cut}"
            );
        };
        cut_is([0.06, -0.02, 0.1], [0.03, -0.01, 0.1]);
        cut_is([0.02, 0.005, -0.3], [0.02, 0.0, 0.0]);
        cut_is([0.03, -0.01, 0.2], [0.03, -0.01, 0.2]);
        let asked = Move {
            translation_mm: Vector3::new(3.5, -0.2, -1.0),
            rotation_deg: Vector3::new(0.06, 0.0, 0.0),
        };
        let turned = limit_move(&observation, Actor::Orientation, asked);
        assert_eq!(turned.translation_mm, asked.translation_mm);
        assert!((turned.rotation_deg - Vector3::new(0.03, 0.0, 0.0)).norm() < 1e-12);
        let moved = limit_move(&observation, Actor::Position, asked);
        assert_eq!(moved.rotation_deg, asked.rotation_deg);
        assert_eq!(
            moved.translation_mm,
            limit_position_move(&observation, asked.translation_mm)
        );
    }

    /// Moves up to 0.85 of the limit are left alone; above, the largest component maps
    /// linearly from (0.85, 0.931) of the limit onto (0.85, 1), with the direction kept
    /// (hand-computed for the 5 mm limit: 4.25 mm and 4.655 mm are the ends).
    #[test]
    fn a_move_at_the_top_of_the_actors_range_is_a_full_step() {
        let short = Vector3::new(3.0, 0.5, -4.25);
        assert_eq!(full_step(short, 5.0), short);
        let label = full_step(Vector3::new(0.0, 0.0, -4.655), 5.0);
        assert!(
            (label - Vector3::new(0.0, 0.0, -5.0)).norm() < 1e-12,
            "{label}"
        );
        // 4.45 mm: 4.25 + 0.2 × 0.75 / 0.405 = 4.62037 mm, the other component in proportion.
        let between = full_step(Vector3::new(4.45, -2.0, 0.0), 5.0);
        let factor = (4.25 + 0.2 * 0.75 / 0.405) / 4.45;
        assert!((between - Vector3::new(4.45, -2.0, 0.0) * factor).norm() < 1e-12);
        assert!((between.x - 4.620_370_37).abs() < 1e-8, "{between}");
        // Past the label's share the move is the limit, never more.
        assert_eq!(full_step(Vector3::new(-4.9, 1.0, 0.0), 5.0).x, -5.0);
        // On another limit the shares scale with it.
        let other = full_step(Vector3::new(0.0, 2.0 * 0.931, 0.0), 2.0);
        assert!((other.y - 2.0).abs() < 1e-12, "{other}");
    }

    /// A position move goes no deeper than the goal the estimate sees, and one from past the
    /// goal comes back; a refusal for contact holds the depth besides.
    #[test]
    fn a_position_move_never_goes_past_the_goal() {
        use crate::collision::clearance::ContactKind;
        use crate::config::cell::CellConfig;
        use crate::sim::{AssemblyEnv, EnvOptions};
        let cell = CellConfig::reference();
        let mut env = AssemblyEnv::new(&cell, EnvOptions::from_cell(&cell));
        let mut observation = env.reset(4).unwrap();
        let at = |to_goal_mm: f64, veto: Option<VetoReason>| {
            let mut o = observation.clone();
            o.state[8] = to_goal_mm;
            o.last_veto = veto;
            deepest_move_mm(&o)
        };
        let contact = VetoReason::Collision {
            kind: ContactKind::Seat,
            clearance_mm: -0.1,
        };
        assert_eq!(at(-3.0, None), -3.0);
        assert_eq!(at(0.4, None), 0.4);
        assert_eq!(at(-3.0, Some(contact.clone())), 0.0);
        assert_eq!(at(0.4, Some(contact)), 0.4);
        assert_eq!(at(-3.0, Some(VetoReason::StaleMeasurement)), -3.0);

        let file =
            PolicyFile::from_bytes(super::super::bundled_policy("hierarchical").unwrap()).unwrap();
        let mut policy = HierarchicalPolicy::from_file(&file).unwrap();
        let mut past_goal = 0;
        loop {
            // The same state, as if the shaft had gone 0.3 mm past the goal.
            let mut beyond = observation.clone();
            beyond.state[8] = 0.3;
            let decision = policy.clone().act(&beyond);
            if decision.actor == Some(Actor::Position) {
                assert!(decision.action.translation_mm.z >= 0.3);
                past_goal += 1;
            }
            let decision = policy.act(&observation);
            if decision.actor == Some(Actor::Position) {
                assert!(decision.action.translation_mm.z >= observation.state[8]);
            }
            let result = env.step(&decision.action).unwrap();
            if result.outcome.is_some() {
                break;
            }
            observation = result.observation;
        }
        assert!(
            past_goal > 0,
            "no position move: the rule was not exercised"
        );
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
