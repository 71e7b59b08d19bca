//! The rules' tests: each rule against hand-computed cases and properties, and the pipeline
//! against the policies it shapes.

use super::*;
use crate::collision::supervisor::VetoReason;
use crate::policy::Controller;
use crate::policy::Decision;
use crate::policy::expert::engaged_middle_off_axis_mm;
use crate::policy::file::PolicyFile;
use crate::policy::hierarchical::{HierarchicalPolicy, PolicyConfig};
use crate::policy::inputs::PolicyInputs;
use crate::policy::learned::LearnedPolicy;
use crate::sim::Observation;
use nalgebra::{Point3, Vector3};

// The rules as functions of the observation and the move, as the tests below read them.

fn shaped(decision: &Decision) -> Shaped {
    Shaped {
        actor: decision.actor,
        action: decision.action,
        exact_sideways: false,
    }
}

fn descends_as_the_demonstrators(observation: &Observation, decision: &Decision) -> bool {
    let rule = NoisyCameraDescent::default();
    noisy_camera_descent::descends_under_noise(
        observation,
        &shaped(decision),
        rule.noisy_camera_scale,
        rule.from_mm,
    )
}

fn centres_after_a_refusal(observation: &Observation, decision: &Decision) -> bool {
    let mut after = shaped(decision);
    let context = RuleContext {
        observation,
        step_limit_mm: 5.0,
        step_limit_deg: 1.0,
    };
    centres_after_a_refusal::apply(&context, &mut after);
    after.exact_sideways
}

fn turned_as_the_demonstrators(
    observation: &Observation,
    rotation_deg: Vector3<f64>,
    step_limit_deg: f64,
) -> Vector3<f64> {
    TurnedAsDemonstrated::default().turned(observation, rotation_deg, step_limit_deg)
}

fn actor_with_work(selected: Actor, observation: &Observation) -> Actor {
    ActorWithWork::default().actor(selected, observation)
}

fn full_step(translation_mm: Vector3<f64>, step_limit_mm: f64) -> Vector3<f64> {
    FullStep::default().stretched(translation_mm, step_limit_mm)
}

fn centred_as_the_demonstrators(
    observation: &Observation,
    translation_mm: Vector3<f64>,
    step_limit_mm: f64,
) -> Vector3<f64> {
    CentredAsDemonstrated::default().centred(observation, translation_mm, step_limit_mm)
}

/// The move the rules that read the network's output and limit it (2–8) make of `step`.
fn asked_move(observation: &Observation, config: &PolicyConfig, actor: Actor, step: Move) -> Move {
    let mut shield = Shield::new(&RulesConfig::default().in_training());
    let mut made = Shaped {
        actor: Some(actor),
        action: step,
        exact_sideways: false,
    };
    let context = RuleContext {
        observation,
        step_limit_mm: config.step_limit_mm,
        step_limit_deg: config.step_limit_deg,
    };
    shield.shape(&context, &mut made, &mut RuleSet::default());
    made.action
}

/// The move the limiting rules (5–8) make of `step`.
fn limit_move(observation: &Observation, actor: Actor, step: Move) -> Move {
    let mut made = Shaped {
        actor: Some(actor),
        action: step,
        exact_sideways: false,
    };
    let context = RuleContext {
        observation,
        step_limit_mm: 5.0,
        step_limit_deg: 1.0,
    };
    Shield::default().limit(&context, &mut made);
    made.action
}

/// A position move as the limiting rules make it (5, 6).
fn limit_position_move(observation: &Observation, translation_mm: Vector3<f64>) -> Vector3<f64> {
    limit_move(
        observation,
        Actor::Position,
        Move::translation(translation_mm.x, translation_mm.y, translation_mm.z),
    )
    .translation_mm
}

/// A hierarchical policy as training runs it: the rules that read and limit its moves (1–8).
fn as_trained(policy: HierarchicalPolicy) -> LearnedPolicy {
    LearnedPolicy::hierarchical(policy).with_rules(&RulesConfig::default().in_training())
}

/// An observation on the reference cell, the tip `above_mm` above the entrance (negative
/// in the bore), level and on the axis.
pub(crate) fn observation_above(above_mm: f64) -> Observation {
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
        shield: None,
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
        shield: None,
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
        PolicyFile::from_bytes(crate::policy::bundled_policy("hierarchical-reference").unwrap())
            .unwrap();
    let mut policy = as_trained(HierarchicalPolicy::from_file(&file).unwrap());
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
        PolicyFile::from_bytes(crate::policy::bundled_policy("hierarchical-reference").unwrap())
            .unwrap();
    let mut policy = as_trained(HierarchicalPolicy::from_file(&file).unwrap());
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

/// Along episodes of a bundled policy on the reference cell at four times the camera's noise
/// (where every kind of rule has work), under every rule, none, and all but one: a decision
/// no rule changed is the proposal within the step limit; no rule switched off ever fires; and
/// the rules that fired account for every change (with none on, the move is the proposal).
#[test]
fn the_trace_names_exactly_the_rules_that_changed_the_move_and_only_those_switched_on() {
    use crate::config::cell::CellConfig;
    use crate::policy::eval::{episode_seed, run_episode_watched};
    use crate::sim::{AssemblyEnv, EnvOptions};
    let cell = CellConfig::reference();
    let options = EnvOptions {
        noise_scale: 4.0,
        ..EnvOptions::from_cell(&cell)
    };
    let bytes = crate::policy::bundled_policy("hierarchical-swift-cells").unwrap();
    let without_steering = RulesConfig::default()
        .selected(&RuleSelection::parse("actor_with_work,full_step,centred_as_demonstrated,turned_as_demonstrated,deepest_move,not_past_the_axis,not_past_level,pivot_in_bore,careful_step_under_noise,noisy_camera_descent,centres_after_a_refusal,full_step_after_uncertainty,standoff_while_unsure").unwrap());
    for rules in [
        RulesConfig::default(),
        RulesConfig::default().selected(&RuleSelection::None),
        without_steering,
    ] {
        let mut policy = LearnedPolicy::from_bytes(bytes).unwrap().with_rules(&rules);
        let mut env = AssemblyEnv::new(&cell, options);
        let mut fired_at_all = RuleSet::default();
        let mut decisions = 0;
        for index in 0..6 {
            run_episode_watched(
                &mut env,
                &mut policy,
                index,
                episode_seed(3, index),
                &mut |_, decision, _| {
                    let trace = decision
                        .shield
                        .expect("a learned policy's decision is traced");
                    decisions += 1;
                    for id in trace.fired.iter() {
                        assert!(rules.is_on(id), "{id} fired switched off");
                        fired_at_all.insert(id);
                    }
                    if trace.fired.is_empty() {
                        let limit_mm = 5.0;
                        let within = trace
                            .proposed
                            .translation_mm
                            .map(|v| v.clamp(-limit_mm, limit_mm));
                        assert_eq!(decision.action.translation_mm, within, "{trace:?}");
                        assert_eq!(decision.action.rotation_deg, trace.proposed.rotation_deg);
                        assert_eq!(decision.actor, trace.proposed_actor);
                    }
                },
            );
        }
        assert!(decisions > 100, "{decisions} decisions");
        if rules.enabled().is_empty() {
            assert!(fired_at_all.is_empty());
        } else {
            // The rules that read the network's output fire on every episode.
            assert!(fired_at_all.contains(RuleId::FullStep), "{fired_at_all:?}");
            assert!(
                fired_at_all.contains(RuleId::CentredAsDemonstrated),
                "{fired_at_all:?}"
            );
        }
        assert_eq!(
            fired_at_all.contains(RuleId::SteeredAgainstDrift),
            rules.is_on(RuleId::SteeredAgainstDrift) && rules.enabled().len() == 14
        );
    }
}
