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
    #[error("reading demonstrations: {0}")]
    Io(#[from] std::io::Error),
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
        for (a, b) in episodes.iter().zip(&back) {
            assert_eq!(a.steps, b.steps, "exact round trip");
        }
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
