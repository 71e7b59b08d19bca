//! `celld policy run`: a policy file's answers for one episode of states, one JSON line each, to
//! check a policy file against another implementation (e.g. PyTorch or numpy).

use super::hierarchical::HierarchicalPolicy;
use anyhow::{Context, Result, bail};
use std::io::{BufRead, Write};

/// Reads one state per line (a JSON array of 12 numbers, or an object `{"state": [...]}`) as one
/// episode (the policy is reset first) and writes one JSON line per state:
/// `{"omega":[ω1,ω2,ω3],"actor":"position"|"orientation","scale":s,"action":[6 values]}`.
/// Blank lines are skipped; any other line that is not a state stops the run with an error that
/// names its line number (1-based). Returns the number of states processed.
pub fn run_states(
    policy: &mut HierarchicalPolicy,
    reader: impl BufRead,
    mut writer: impl Write,
) -> Result<usize> {
    policy.reset();
    let mut count = 0;
    for (i, line) in reader.lines().enumerate() {
        let number = i + 1;
        let line = line.with_context(|| format!("line {number}: cannot read"))?;
        if line.trim().is_empty() {
            continue;
        }
        let state = parse_state(&line).with_context(|| format!("line {number}"))?;
        let out = policy
            .step(&state)
            .map_err(|e| anyhow::anyhow!("line {number}: the policy failed: {e}"))?;
        serde_json::to_writer(&mut writer, &out).context("cannot write the output")?;
        writer.write_all(b"\n").context("cannot write the output")?;
        count += 1;
    }
    writer.flush().context("cannot write the output")?;
    Ok(count)
}

/// One state from a JSON line: `[12 numbers]` or `{"state": [12 numbers], ...}`.
pub fn parse_state(line: &str) -> Result<[f64; 12]> {
    let value: serde_json::Value =
        serde_json::from_str(line).map_err(|e| anyhow::anyhow!("not JSON: {e}"))?;
    let array = match &value {
        serde_json::Value::Array(a) => a,
        serde_json::Value::Object(o) => match o.get("state") {
            Some(serde_json::Value::Array(a)) => a,
            Some(other) => bail!("`state` must be an array of 12 numbers, found {other}"),
            None => bail!("an object needs a `state` array of 12 numbers"),
        },
        other => bail!("expected an array of 12 numbers (or {{\"state\": [...]}}), found {other}"),
    };
    if array.len() != 12 {
        bail!("expected 12 numbers, found {}", array.len());
    }
    let mut state = [0.0; 12];
    for (k, (slot, v)) in state.iter_mut().zip(array).enumerate() {
        *slot = v
            .as_f64()
            .filter(|x| x.is_finite())
            .ok_or_else(|| anyhow::anyhow!("value {k} is {v}, not a number"))?;
    }
    Ok(state)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_arrays_and_objects() {
        let s = parse_state("[1,2,3,4,5,6,7,8,9,10,11,12.5]").unwrap();
        assert_eq!(s[11], 12.5);
        let s = parse_state(r#"{"state":[0,0,0,0,0,0,0,0,0,0,0,-1], "step": 3}"#).unwrap();
        assert_eq!(s[11], -1.0);
    }

    #[test]
    fn refuses_bad_lines() {
        let msg = |l: &str| parse_state(l).unwrap_err().to_string();
        assert!(msg("[1,2,3]").contains("found 3"));
        assert!(msg(r#"[1,2,3,4,5,6,7,8,9,10,11,"x"]"#).contains("value 11"));
        assert!(msg("nope").contains("not JSON"));
        assert!(msg(r#"{"s":[]}"#).contains("`state`"));
        assert!(msg("7").contains("expected an array"));
    }
}
