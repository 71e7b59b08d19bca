//! Policy files (docs/design.md §6): the PyTorch-layout fixture written by
//! scripts/make_policy_fixture.py loads and its forward pass matches the script's independent
//! numpy implementation to 1e-5, one episode at a time, batched and through `celld policy run`;
//! and the loader refuses each kind of bad file with its own message.

use assembly_cell::policy::Actor;
use assembly_cell::policy::file::{PolicyFile, PolicyFileError};
use assembly_cell::policy::hierarchical::{HierarchicalPolicy, PolicyOutput};
use assembly_cell::policy::run::run_states;
use assembly_cell::threads::init_cpu_threads;
use serde_json::{Map, Value, json};
use std::path::PathBuf;

const TOL: f64 = 1e-5;

fn fixture(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

fn good_bytes() -> Vec<u8> {
    std::fs::read(fixture("policy_small.safetensors")).unwrap()
}

fn policy() -> HierarchicalPolicy {
    init_cpu_threads();
    HierarchicalPolicy::from_path(fixture("policy_small.safetensors")).unwrap()
}

fn states() -> Vec<[f64; 12]> {
    std::fs::read_to_string(fixture("policy_small_states.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

fn expected() -> Vec<Value> {
    std::fs::read_to_string(fixture("policy_small_expected.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

fn floats(v: &Value) -> Vec<f64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect()
}

/// Compares one output line (as JSON) with the expected one.
fn assert_matches(got: &Value, want: &Value, what: &str) {
    assert_eq!(got["actor"], want["actor"], "{what}: actor");
    let close = |a: &[f64], b: &[f64], field: &str| {
        assert_eq!(a.len(), b.len(), "{what}: {field} length");
        for (k, (x, y)) in a.iter().zip(b).enumerate() {
            assert!(
                (x - y).abs() <= TOL,
                "{what}: {field}[{k}] = {x}, expected {y} (diff {:e})",
                (x - y).abs()
            );
        }
    };
    close(&floats(&got["omega"]), &floats(&want["omega"]), "omega");
    close(&floats(&got["action"]), &floats(&want["action"]), "action");
    close(
        &[got["scale"].as_f64().unwrap()],
        &[want["scale"].as_f64().unwrap()],
        "scale",
    );
}

fn as_json(out: &PolicyOutput) -> Value {
    serde_json::to_value(out).unwrap()
}

#[test]
fn fixture_loads_with_its_sizes_and_metadata() {
    let file = PolicyFile::from_path(fixture("policy_small.safetensors")).unwrap();
    assert_eq!((file.hidden_size(), file.actor_width()), (16, 32));
    assert_eq!(file.step_limit_mm(), 5.0);
    assert_eq!(file.step_limit_deg(), 1.0);
    assert_eq!(file.metadata().format, "assembly-cell/hierarchical-policy");
    assert!(file.metadata().extra.contains_key("fixture_seed"));
    let shapes = file.shapes();
    assert_eq!(shapes.len(), 20);
    assert!(shapes.contains(&("high.lstm.weight_hh_l0".to_string(), vec![64, 16])));
    // Our writer's bytes load back to the same policy.
    let again = PolicyFile::from_bytes(&file.to_bytes()).unwrap();
    assert_eq!(again, file);
}

#[test]
fn single_episode_matches_the_numpy_reference() {
    let mut p = policy();
    let (states, expected) = (states(), expected());
    assert_eq!(states.len(), expected.len());
    // Both actors and a range of scales occur, so the comparison covers the whole pass.
    let actors: Vec<&str> = expected
        .iter()
        .map(|e| e["actor"].as_str().unwrap())
        .collect();
    assert!(actors.contains(&"position") && actors.contains(&"orientation"));
    for pass in 0..2 {
        p.reset();
        for (t, (s, want)) in states.iter().zip(&expected).enumerate() {
            let out = p.step(s).unwrap();
            assert_matches(&as_json(&out), want, &format!("pass {pass}, step {t}"));
            // The move is zero on the other actor's axes.
            let zero = match out.actor {
                Actor::Position => &out.action[3..],
                Actor::Orientation => &out.action[..3],
            };
            assert!(zero.iter().all(|v| *v == 0.0));
        }
    }
}

#[test]
fn candle_path_matches_the_numpy_reference() {
    let p = policy();
    let mut batch = p.batch_state(1);
    for (t, (s, want)) in states().iter().zip(&expected()).enumerate() {
        let out = p
            .step_batch_candle(std::slice::from_ref(s), &mut batch)
            .unwrap();
        assert_matches(&as_json(&out[0]), want, &format!("candle step {t}"));
    }
}

/// Runs `rows` copies of the episode in one batch; row 1 is reset after `restart` steps and
/// runs the episode again from the start. Every row must match the reference throughout.
fn batched_run(rows: usize, candle: bool) {
    let p = policy();
    let (states, expected) = (states(), expected());
    let n = states.len();
    let restart = 7;
    let mut batch = p.batch_state(rows);
    for t in 0..n + restart {
        if t == restart {
            batch.reset_row(1);
        }
        // Row 1's step in its (restarted) episode; the other rows idle on the first state once
        // their episode is over.
        let row1 = if t < restart { t } else { t - restart };
        let others = if t < n { t } else { 0 };
        let input: Vec<[f64; 12]> = (0..rows)
            .map(|r| states[if r == 1 { row1 } else { others }])
            .collect();
        let out = if candle {
            p.step_batch_candle(&input, &mut batch).unwrap()
        } else {
            p.step_batch(&input, &mut batch).unwrap()
        };
        assert_eq!(out.len(), rows);
        let what =
            |r: usize, k: usize| format!("candle {candle}, row {r}, step {k} (batch step {t})");
        for (r, o) in out.iter().enumerate() {
            if r == 1 {
                assert_matches(&as_json(o), &expected[row1], &what(r, row1));
            } else if t < n {
                assert_matches(&as_json(o), &expected[t], &what(r, t));
                assert_eq!(o, &out[0]);
            }
        }
    }
    // Mismatched sizes are refused, and leave the state alone.
    let before = batch.clone();
    assert!(p.step_batch(&states[..rows - 1], &mut batch).is_err());
    assert!(
        p.step_batch_candle(&states[..rows - 1], &mut batch)
            .is_err()
    );
    assert_eq!(batch, before);
}

#[test]
fn batched_episodes_match_and_rows_reset_independently() {
    batched_run(3, false);
    // Large enough to run on all cores.
    batched_run(10, false);
}

#[test]
fn candle_batches_match_and_rows_reset_independently() {
    batched_run(3, true);
    batched_run(10, true);
}

#[test]
fn batch_of_one_equals_the_single_episode() {
    let mut single = policy();
    let p = policy();
    let mut b1 = p.batch_state(1);
    for s in &states() {
        let a = single.step(s).unwrap();
        let b = p.step_batch(std::slice::from_ref(s), &mut b1).unwrap()[0];
        assert_eq!(a, b);
        assert_eq!(single.lstm_state().0, b1.h(0));
    }
}

#[test]
fn policy_run_reproduces_the_expected_lines() {
    let mut p = policy();
    let input = std::fs::read(fixture("policy_small_states.jsonl")).unwrap();
    let mut output = Vec::new();
    let n = run_states(&mut p, input.as_slice(), &mut output).unwrap();
    let expected = expected();
    assert_eq!(n, expected.len());
    let text = String::from_utf8(output).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines.len(), expected.len());
    for (t, (line, want)) in lines.iter().zip(&expected).enumerate() {
        let got: Value = serde_json::from_str(line).unwrap();
        let keys: Vec<&String> = got.as_object().unwrap().keys().collect();
        assert_eq!(keys.len(), 4, "line {t}: {line}");
        assert_matches(&got, want, &format!("line {}", t + 1));
    }
    // Running again starts a fresh episode: the same output.
    let mut again = Vec::new();
    run_states(&mut p, input.as_slice(), &mut again).unwrap();
    assert_eq!(again, text.as_bytes());
}

#[test]
fn policy_run_names_the_bad_line() {
    let mut p = policy();
    let s = states();
    let line = |v: &[f64; 12]| serde_json::to_string(v).unwrap();
    let input = format!(
        "{}\n{{\"state\": {}}}\n[1, 2, 3]\n",
        line(&s[0]),
        line(&s[1])
    );
    let mut out = Vec::new();
    let err = run_states(&mut p, input.as_bytes(), &mut out).unwrap_err();
    let msg = format!("{err:#}");
    assert!(
        msg.contains("line 3") && msg.contains("expected 12 numbers"),
        "{msg}"
    );
    let err = run_states(&mut p, "not json\n".as_bytes(), Vec::new()).unwrap_err();
    assert!(format!("{err:#}").contains("line 1"), "{err:#}");
}

// ---------------------------------------------------------------------------------------------
// Bad files, built from the good one.

/// The good fixture as (name, dtype, shape, bytes) and its metadata.
struct Parts {
    tensors: Vec<(String, String, Vec<usize>, Vec<u8>)>,
    metadata: Option<Map<String, Value>>,
}

fn parts() -> Parts {
    let bytes = good_bytes();
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let header: Map<String, Value> = serde_json::from_slice(&bytes[8..8 + n]).unwrap();
    let data = &bytes[8 + n..];
    let mut tensors = Vec::new();
    let mut metadata = None;
    for (name, info) in header {
        if name == "__metadata__" {
            metadata = Some(info.as_object().unwrap().clone());
            continue;
        }
        let offsets = floats(&info["data_offsets"]);
        let (s, e) = (offsets[0] as usize, offsets[1] as usize);
        let shape = floats(&info["shape"]).iter().map(|&d| d as usize).collect();
        tensors.push((
            name,
            info["dtype"].as_str().unwrap().to_string(),
            shape,
            data[s..e].to_vec(),
        ));
    }
    Parts { tensors, metadata }
}

impl Parts {
    fn encode(&self) -> Vec<u8> {
        let mut header = Map::new();
        if let Some(m) = &self.metadata {
            header.insert("__metadata__".into(), Value::Object(m.clone()));
        }
        let mut data = Vec::new();
        for (name, dtype, shape, bytes) in &self.tensors {
            let start = data.len();
            data.extend_from_slice(bytes);
            header.insert(
                name.clone(),
                json!({"dtype": dtype, "shape": shape, "data_offsets": [start, data.len()]}),
            );
        }
        let header = serde_json::to_vec(&header).unwrap();
        let mut out = (header.len() as u64).to_le_bytes().to_vec();
        out.extend_from_slice(&header);
        out.extend_from_slice(&data);
        out
    }

    fn tensor(&mut self, name: &str) -> &mut (String, String, Vec<usize>, Vec<u8>) {
        self.tensors.iter_mut().find(|t| t.0 == name).unwrap()
    }

    fn set_f32(&mut self, name: &str, index: usize, value: f32) {
        let t = self.tensor(name);
        t.3[4 * index..4 * index + 4].copy_from_slice(&value.to_le_bytes());
    }

    fn set_meta(&mut self, key: &str, value: Option<&str>) {
        let m = self.metadata.as_mut().unwrap();
        match value {
            Some(v) => m.insert(key.into(), Value::String(v.into())),
            None => m.remove(key),
        };
    }
}

fn refuse(bytes: &[u8]) -> PolicyFileError {
    PolicyFile::from_bytes(bytes).unwrap_err()
}

#[test]
fn re_encoded_good_file_still_loads() {
    // The test's own encoder is sound, so each refusal below is due to its one defect.
    PolicyFile::from_bytes(&parts().encode()).unwrap();
}

#[test]
fn loader_refuses_each_bad_file_with_its_own_message() {
    let mut cases: Vec<(&str, PolicyFileError)> = Vec::new();

    // A missing tensor.
    let mut p = parts();
    p.tensors.retain(|t| t.0 != "ori.2.bias");
    let e = refuse(&p.encode());
    assert_eq!(e.code(), "missing_tensor");
    assert!(
        e.to_string().contains("tensor `ori.2.bias` is missing"),
        "{e}"
    );
    cases.push(("missing tensor", e));

    // An unknown tensor.
    let mut p = parts();
    let extra = p.tensor("high.lstm.weight_ih_l0").clone();
    p.tensors
        .push(("high.lstm.weight_ih_l1".into(), extra.1, extra.2, extra.3));
    let e = refuse(&p.encode());
    assert_eq!(e.code(), "unexpected_tensor");
    assert!(e.to_string().contains("`high.lstm.weight_ih_l1`"), "{e}");
    cases.push(("unexpected tensor", e));

    // A wrong shape: W_hh stored transposed.
    let mut p = parts();
    p.tensor("high.lstm.weight_hh_l0").2 = vec![16, 64];
    let e = refuse(&p.encode());
    assert_eq!(e.code(), "wrong_shape");
    let msg = e.to_string();
    assert!(
        msg.contains("`high.lstm.weight_hh_l0` has shape [16, 64], expected [64, 16]")
            && msg.contains("H = 16 from high.lstm.weight_ih_l0"),
        "{msg}"
    );
    cases.push(("wrong shape", e));

    // A wrong actor width in one layer.
    let mut p = parts();
    let t = p.tensor("ori.2.weight");
    t.2 = vec![32, 16];
    t.3.truncate(32 * 16 * 4);
    let e = refuse(&p.encode());
    assert_eq!(
        (e.code(), e.subject()),
        ("wrong_shape", Some("ori.2.weight"))
    );
    assert!(e.to_string().contains("D = 32 from pos.0.weight"), "{e}");

    // f16 instead of f32.
    let mut p = parts();
    let t = p.tensor("pos.0.weight");
    t.1 = "F16".into();
    let half = t.3.len() / 2;
    t.3 = vec![0x3c; half];
    let e = refuse(&p.encode());
    assert_eq!(e.code(), "wrong_dtype");
    assert!(
        e.to_string()
            .contains("tensor `pos.0.weight` is F16, expected F32"),
        "{e}"
    );
    cases.push(("f16", e));

    // NaN weights.
    let mut p = parts();
    p.set_f32("pos.2.weight", 3 * 32 + 5, f32::NAN);
    let e = refuse(&p.encode());
    assert_eq!(e.code(), "non_finite");
    let msg = e.to_string();
    assert!(
        msg.contains("`pos.2.weight`") && msg.contains("NaN") && msg.contains("[3, 5]"),
        "{msg}"
    );
    cases.push(("NaN", e));

    // Inf weights.
    let mut p = parts();
    p.set_f32("high.lstm.bias_hh_l0", 7, f32::NEG_INFINITY);
    let e = refuse(&p.encode());
    assert_eq!(e.code(), "non_finite");
    let msg = e.to_string();
    assert!(
        msg.contains("`high.lstm.bias_hh_l0`") && msg.contains("-inf") && msg.contains("[7]"),
        "{msg}"
    );
    cases.push(("Inf", e));

    // A zero standard deviation.
    let mut p = parts();
    p.set_f32("obs_std", 4, 0.0);
    let e = refuse(&p.encode());
    assert_eq!((e.code(), e.subject()), ("bad_value", Some("obs_std")));
    cases.push(("zero std", e));

    // A truncated file.
    let good = good_bytes();
    let e = refuse(&good[..good.len() - 10]);
    assert_eq!(e.code(), "truncated");
    assert!(e.to_string().contains("truncated"), "{e}");
    cases.push(("truncated", e));
    assert_eq!(refuse(&good[..5]).code(), "truncated");

    // A header longer than the file.
    let mut bad = good.clone();
    bad[..8].copy_from_slice(&(good.len() as u64).to_le_bytes());
    let e = refuse(&bad);
    assert_eq!(e.code(), "header_too_long");
    assert!(e.to_string().contains("longer than the file"), "{e}");
    cases.push(("header too long", e));
    // Cut inside the header: the header is then longer than what is left.
    assert_eq!(refuse(&good[..40]).code(), "header_too_long");

    // A header that is not JSON.
    let mut bad = good.clone();
    bad[8] = b'#';
    let e = refuse(&bad);
    assert_eq!(e.code(), "bad_header");
    cases.push(("bad header", e));

    // Trailing bytes after the data.
    let mut bad = good.clone();
    bad.extend_from_slice(&[0; 8]);
    assert_eq!(refuse(&bad).code(), "bad_header");

    // No metadata at all.
    let mut p = parts();
    p.metadata = None;
    let e = refuse(&p.encode());
    assert_eq!(
        (e.code(), e.subject()),
        ("missing_metadata", Some("format"))
    );
    cases.push(("no metadata", e));

    // A missing step limit.
    let mut p = parts();
    p.set_meta("step_limit_deg", None);
    let e = refuse(&p.encode());
    assert_eq!(
        (e.code(), e.subject()),
        ("missing_metadata", Some("step_limit_deg"))
    );
    assert!(
        e.to_string()
            .contains("metadata `step_limit_deg` is missing"),
        "{e}"
    );
    cases.push(("missing step limit", e));

    // The wrong format.
    let mut p = parts();
    p.set_meta("format", Some("pytorch/lstm"));
    let e = refuse(&p.encode());
    assert_eq!((e.code(), e.subject()), ("bad_metadata", Some("format")));
    assert!(
        e.to_string().contains("assembly-cell/hierarchical-policy"),
        "{e}"
    );
    cases.push(("wrong format", e));

    // A version this build does not know.
    let mut p = parts();
    p.set_meta("format_version", Some("3"));
    let e = refuse(&p.encode());
    assert_eq!(
        (e.code(), e.subject()),
        ("bad_metadata", Some("format_version"))
    );
    cases.push(("wrong version", e));

    // Version 2 names its inputs, and only the inputs this build can make.
    let mut p = parts();
    p.set_meta("format_version", Some("2"));
    let e = refuse(&p.encode());
    assert_eq!(
        (e.code(), e.subject()),
        ("missing_metadata", Some("inputs"))
    );
    cases.push(("version 2 without its inputs", e));
    p.set_meta("inputs", Some("pixels"));
    let e = refuse(&p.encode());
    assert_eq!((e.code(), e.subject()), ("bad_metadata", Some("inputs")));
    assert!(e.to_string().contains("cell-relative"), "{e}");
    cases.push(("version 2 with unknown inputs", e));

    // A step limit that is not a number, and one that is not positive.
    let mut p = parts();
    p.set_meta("step_limit_mm", Some("five"));
    let e = refuse(&p.encode());
    assert_eq!(
        (e.code(), e.subject()),
        ("bad_metadata", Some("step_limit_mm"))
    );
    assert!(e.to_string().contains("\"five\""), "{e}");
    cases.push(("non-numeric step limit", e));
    let mut p = parts();
    p.set_meta("step_limit_mm", Some("-5"));
    assert_eq!(refuse(&p.encode()).subject(), Some("step_limit_mm"));
    let mut p = parts();
    p.set_meta("step_limit_mm", Some("NaN"));
    assert_eq!(refuse(&p.encode()).subject(), Some("step_limit_mm"));

    // Every case says something different.
    let messages: Vec<String> = cases.iter().map(|(_, e)| e.to_string()).collect();
    for (i, a) in messages.iter().enumerate() {
        for b in &messages[i + 1..] {
            assert_ne!(a, b);
        }
    }
}

#[test]
fn a_file_from_our_writer_runs_like_the_fixture() {
    let file = PolicyFile::from_path(fixture("policy_small.safetensors")).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("copy.safetensors");
    file.save(&path).unwrap();
    let mut p = HierarchicalPolicy::from_path(&path).unwrap();
    assert_eq!(p.name(), "copy", "named after the file stem");
    for (t, (s, want)) in states().iter().zip(&expected()).enumerate() {
        assert_matches(&as_json(&p.step(s).unwrap()), want, &format!("step {t}"));
    }
}
