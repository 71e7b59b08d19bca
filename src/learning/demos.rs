//! Expert demonstrations: what the expert saw and did, step by step, as JSON Lines.
//!
//! In the real cell a person guides Segment I by hand and the camera records at 4 Hz; in the twin
//! the scripted expert stands in (docs/design.md §5). One line per step:
//!
//! ```json
//! {"episode":0,"step":0,"state":[12 numbers],"action":[6 numbers],"actor":"position","scale":0.93}
//! ```
//!
//! `state` is the 12-dim state the expert decided on, `action` the move it made (mm, deg),
//! `actor` and `scale` its choice of actor and step size (the LSTM selector's labels). Reading
//! refuses a bad line with its line number and stores nothing.

use std::io::{BufRead, Write};

/// Recording lives with the controllers (`policy::record`); its types and functions are
/// reachable from here too, next to the file format.
pub use crate::policy::record::{
    DEFAULT_DEMONSTRATOR, DEMONSTRATORS, DemoEpisode, DemoStep, DriverFactory, ExecutionNoise,
    Recording, check_demonstrator, demonstrator_seed, record, record_expert, record_with,
    relabel_rollouts,
};

#[derive(Debug, thiserror::Error)]
pub enum DemoError {
    #[error("line {line}: {reason}")]
    BadLine { line: usize, reason: String },
    #[error(
        "episode {episode}, step {step}: {field} = {} {unit} is beyond ±{limit} {unit}, {why}",
        readable(*value)
    )]
    OutOfBounds {
        episode: u32,
        step: u32,
        /// `state[6] (Px)` or `action[3]`.
        field: String,
        value: f64,
        limit: f64,
        unit: &'static str,
        why: &'static str,
    },
    #[error("reading demonstrations: {0}")]
    Io(#[from] std::io::Error),
}

/// The names of the paper's state's slots (absolute inputs): where the robot carries {M} in
/// the world (A1..A3 mm, A4..A6 a rotation vector in deg), {F} in {M} (Px..Pz mm, Ox..Oz deg).
const STATE_NAMES: [&str; 12] = [
    "A1", "A2", "A3", "A4", "A5", "A6", "Px", "Py", "Pz", "Ox", "Oy", "Oz",
];

/// The largest numbers a cell can hold in a demonstration step with absolute inputs, derived
/// from the cell file: what is beyond them was never measured on this cell, and one such
/// number (1e308) is enough to make training diverge.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DemoBounds {
    /// Any length of the state (A1..A3, Px..Pz), mm: twice the furthest the shaft's tip
    /// reaches from the base's origin (base radius + longest leg + platform radius + Segment
    /// I's mount + its engaged length), so no two points of the cell are further apart.
    pub length_mm: f64,
    /// Any angle of the state (A4..A6, Ox..Oz), deg: a rotation vector turns at most 180°.
    pub angle_deg: f64,
    /// A move's components, mm: the cell's step limit (`steps.position_mm`); the supervisor
    /// vetoes a larger move, so the cell never makes one.
    pub move_mm: f64,
    /// A move's rotation components, deg (`steps.orientation_deg`).
    pub move_deg: f64,
}

impl DemoBounds {
    pub fn for_cell(cell: &crate::config::cell::CellConfig) -> Self {
        let robot = &cell.robot;
        let reach_mm = robot.base_radius_mm
            + robot.leg_max_mm
            + robot.platform_radius_mm
            + robot.segment_mount_mm
            + cell.shaft.engaged_length_mm;
        DemoBounds {
            length_mm: 2.0 * reach_mm,
            angle_deg: 180.0,
            move_mm: cell.steps.position_mm,
            move_deg: cell.steps.orientation_deg,
        }
    }
}

/// Refuses the first number of `episodes` (absolute inputs) beyond `bounds`, naming its episode,
/// step and field. A move at the step limit passes (the supervisor's rounding tolerance).
pub fn check_bounds(episodes: &[DemoEpisode], bounds: &DemoBounds) -> Result<(), DemoError> {
    const LENGTH: &str = "no two points of the cell are further apart";
    const ANGLE: &str = "a rotation vector turns at most 180°";
    const MOVE: &str = "the cell's step limit (the supervisor vetoes a larger move)";
    for step in episodes.iter().flat_map(|e| &e.steps) {
        let state = step.state.iter().enumerate().map(|(i, &value)| {
            let (limit, unit, why) = if matches!(i, 3..=5 | 9..=11) {
                (bounds.angle_deg, "deg", ANGLE)
            } else {
                (bounds.length_mm, "mm", LENGTH)
            };
            let name = format!("state[{i}] ({})", STATE_NAMES[i]);
            (name, value, limit, 1.0, unit, why)
        });
        let action = step.action.iter().enumerate().map(|(i, &value)| {
            let (limit, unit) = if i < 3 {
                (bounds.move_mm, "mm")
            } else {
                (bounds.move_deg, "deg")
            };
            (format!("action[{i}]"), value, limit, 1.0 + 1e-9, unit, MOVE)
        });
        for (field, value, limit, tolerance, unit, why) in state.chain(action) {
            if value.is_nan() || value.abs() > limit * tolerance {
                return Err(DemoError::OutOfBounds {
                    episode: step.episode,
                    step: step.step,
                    field,
                    value,
                    limit,
                    unit,
                    why,
                });
            }
        }
    }
    Ok(())
}

/// A number as people read it: 1e308, not its 309 digits.
fn readable(value: f64) -> String {
    if value.abs() >= 1e6 {
        format!("{value:e}")
    } else {
        value.to_string()
    }
}

/// Writes episodes as JSON Lines.
pub fn write_jsonl(episodes: &[DemoEpisode], mut out: impl Write) -> std::io::Result<()> {
    for step in episodes.iter().flat_map(|e| &e.steps) {
        serde_json::to_writer(&mut out, step)?;
        out.write_all(b"\n")?;
    }
    Ok(())
}

/// Reads JSON Lines into episodes (grouped by `episode`, in file order). Every line must parse,
/// carry finite numbers and a scale in [0, 1]; the first bad line is reported by number.
pub fn read_jsonl(input: impl BufRead) -> Result<Vec<DemoEpisode>, DemoError> {
    let mut episodes: Vec<DemoEpisode> = Vec::new();
    for (index, line) in input.lines().enumerate() {
        let line_no = index + 1;
        let line = line?;
        if line.trim().is_empty() {
            continue;
        }
        let step: DemoStep = serde_json::from_str(&line).map_err(|e| DemoError::BadLine {
            line: line_no,
            reason: e.to_string(),
        })?;
        if !step.state.iter().chain(&step.action).all(|v| v.is_finite()) {
            return Err(DemoError::BadLine {
                line: line_no,
                reason: "state and action must be finite numbers".into(),
            });
        }
        if !(0.0..=1.0).contains(&step.scale) {
            return Err(DemoError::BadLine {
                line: line_no,
                reason: format!("scale {} is not in [0, 1]", step.scale),
            });
        }
        match episodes.last_mut() {
            Some(last) if last.steps.last().is_some_and(|s| s.episode == step.episode) => {
                last.steps.push(step)
            }
            _ => episodes.push(DemoEpisode {
                steps: vec![step],
                succeeded: true,
            }),
        }
    }
    Ok(episodes)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::cell::CellConfig;
    use crate::policy::Actor;
    use crate::sim::EnvOptions;

    #[test]
    fn recorded_demonstrations_round_trip_through_jsonl() {
        let cell = CellConfig::reference();
        let episodes = record_expert(&cell, EnvOptions::from_cell(&cell), 3, 5);
        assert_eq!(episodes.len(), 3);
        assert!(episodes.iter().all(|e| e.steps.len() > 10));
        assert!(
            episodes
                .iter()
                .flat_map(|e| &e.steps)
                .any(|s| s.actor == Actor::Orientation)
        );
        let mut bytes = Vec::new();
        write_jsonl(&episodes, &mut bytes).unwrap();
        let back = read_jsonl(bytes.as_slice()).unwrap();
        assert_eq!(back.len(), 3);
        // What the cell records is within what the cell can hold.
        check_bounds(&back, &DemoBounds::for_cell(&cell)).unwrap();
        for (a, b) in episodes.iter().zip(&back) {
            assert_eq!(a.steps, b.steps, "exact round trip");
        }
    }

    /// A number no cell can hold is refused naming its episode, step and field; the bound
    /// comes from the cell file (the reference cell: 2 × (500 + 1050 + 300 + 100 + 60) mm).
    #[test]
    fn a_number_beyond_the_cell_is_named() {
        let cell = CellConfig::reference();
        let bounds = DemoBounds::for_cell(&cell);
        assert_eq!(bounds.length_mm, 4020.0);
        let step = |episode: u32, number: u32, state: [f64; 12], action: [f64; 6]| DemoStep {
            episode,
            step: number,
            state,
            action,
            actor: Actor::Position,
            scale: 0.5,
        };
        let episode = |steps: Vec<DemoStep>| DemoEpisode {
            steps,
            succeeded: true,
        };
        let mut state = [0.0; 12];
        state[8] = -4020.0;
        state[9] = 180.0;
        let fine = step(0, 0, state, [5.0, -5.0, 0.0, 1.0, 0.0, -1.0]);
        check_bounds(&[episode(vec![fine.clone()])], &bounds).unwrap();

        let mut far = state;
        far[6] = 1e308;
        let episodes = [
            episode(vec![fine.clone()]),
            episode(vec![step(4, 0, state, [0.0; 6]), step(4, 7, far, [0.0; 6])]),
        ];
        let error = check_bounds(&episodes, &bounds).unwrap_err().to_string();
        assert!(
            error.starts_with("episode 4, step 7: state[6] (Px) = 1e308 mm is beyond ±4020 mm"),
            "{error}"
        );
        let mut turned = state;
        turned[4] = -180.5;
        let error = check_bounds(&[episode(vec![step(1, 2, turned, [0.0; 6])])], &bounds)
            .unwrap_err()
            .to_string();
        assert!(error.contains("step 2: state[4] (A5)"), "{error}");
        let error = check_bounds(
            &[episode(vec![step(
                2,
                3,
                state,
                [0.0, 0.0, 5.1, 0.0, 0.0, 0.0],
            )])],
            &bounds,
        )
        .unwrap_err()
        .to_string();
        assert!(
            error.contains("episode 2, step 3: action[2] = 5.1 mm is beyond ±5 mm"),
            "{error}"
        );
    }

    #[test]
    fn a_bad_line_is_named() {
        let good = r#"{"episode":0,"step":0,"state":[0,0,0,0,0,0,1,2,3,0,0,0],"action":[1,0,0,0,0,0],"actor":"position","scale":0.2}"#;
        let text = format!("{good}\n{good}\n{{\"episode\":0}}\n");
        let error = read_jsonl(text.as_bytes()).unwrap_err().to_string();
        assert!(error.starts_with("line 3:"), "{error}");
        let text = good.replace("0.2}", "1.5}");
        let error = read_jsonl(text.as_bytes()).unwrap_err().to_string();
        assert!(
            error.contains("line 1") && error.contains("scale"),
            "{error}"
        );
    }
}
