//! `celld eval` end to end: the JSON summary, determinism, and clear errors for bad input.

use crate::common;

use common::{celld, last_json};

#[test]
fn json_summary_has_the_promised_fields_and_repeats_under_a_seed() {
    let args = [
        "eval",
        "--controller",
        "expert",
        "--episodes",
        "40",
        "--seed",
        "3",
        "--json",
    ];
    let first = celld(&args);
    assert!(
        first.status.success(),
        "{}",
        String::from_utf8_lossy(&first.stderr)
    );
    let summary = last_json(&first);
    assert_eq!(summary["episodes"], 40);
    let rate = summary["success_rate"].as_f64().unwrap();
    assert!((0.0..=1.0).contains(&rate));
    let successes = summary["successes"].as_u64().unwrap();
    let failures: u64 = summary["failures"]
        .as_object()
        .unwrap()
        .values()
        .map(|v| v.as_u64().unwrap())
        .sum();
    assert_eq!(successes + failures, 40, "{summary}");
    for key in ["avg_steps", "avg_reward", "wall_s"] {
        assert!(summary.get(key).is_some(), "missing {key}");
    }
    let mut again = last_json(&celld(&args));
    let mut first = summary;
    first["wall_s"] = 0.into();
    again["wall_s"] = 0.into();
    assert_eq!(first, again, "same seed, same summary");
}

#[test]
fn initial_conditions_and_switches_are_applied() {
    let output = celld(&[
        "eval",
        "--controller",
        "spiral",
        "--episodes",
        "10",
        "--init-pos-mm",
        "10",
        "--init-ori-deg",
        "3",
        "--noise-scale",
        "0",
        "--calibration-scale",
        "2.5",
        "--fault",
        "robot_lag",
        "--without",
        "calibration_error,latency",
        "--cell",
        "cells/phi200.toml",
        "--json",
    ]);
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let summary = last_json(&output);
    assert_eq!(summary["init_pos_mm"], 10.0);
    assert_eq!(summary["init_ori_deg"], 3.0);
    assert_eq!(summary["noise_scale"], 0.0);
    assert_eq!(summary["calibration_scale"], 2.5);
    assert_eq!(summary["fault"], "robot_lag");
    let first = String::from_utf8_lossy(&output.stdout);
    assert!(
        first.contains("noise ×0, calibration ×2.5, fault robot_lag"),
        "{first}"
    );
    assert_eq!(summary["cell"], "phi200");
}

#[test]
fn drawn_cells_are_named_and_repeat_under_a_seed() {
    let args = [
        "eval",
        "--controller",
        "expert",
        "--randomise-cells",
        "--robots",
        "3",
        "--episodes",
        "6",
        "--seed",
        "4",
        "--json",
    ];
    let output = celld(&args);
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let mut summary = last_json(&output);
    assert_eq!(summary["drawn_cells"], 3);
    assert_eq!(summary["episodes"], 6);
    let first = String::from_utf8_lossy(&output.stdout);
    assert!(
        first.contains("on 3 cells drawn around phi170: 6 episodes")
            && first.contains("noise ×0.5–2 drawn, calibration ×0–3 drawn"),
        "{first}"
    );
    let mut again = last_json(&celld(&args));
    summary["wall_s"] = 0.into();
    again["wall_s"] = 0.into();
    assert_eq!(summary, again, "same seed, same cells and episodes");
    // The same cells with their camera noise drawn up to four times the data sheet's.
    let wider_args = [&args[..], &["--randomise-noise-up-to", "4"]].concat();
    let wider = celld(&wider_args);
    assert!(String::from_utf8_lossy(&wider.stdout).contains("noise ×0.5–4 drawn"));
    let wider = last_json(&wider);
    assert_eq!(wider["drawn_cells"], 3);
    assert_ne!(wider["avg_steps"], summary["avg_steps"], "{wider}");
    // One cell's summary says nothing of drawn cells.
    let one = last_json(&celld(&["eval", "--episodes", "1", "--json"]));
    assert!(one.get("drawn_cells").is_none(), "{one}");
}

/// `--per-cell`: every drawn cell with its own episodes, which add up to the evaluation's, and
/// the count of cells at the threshold agreeing with the cells' rates.
#[test]
fn per_cell_the_drawn_cells_add_up_to_the_evaluation() {
    let output = celld(&[
        "eval",
        "--controller",
        "expert",
        "--randomise-cells",
        "--robots",
        "3",
        "--episodes",
        "7",
        "--seed",
        "4",
        "--per-cell",
        "--threshold",
        "0.6",
        "--json",
    ]);
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let summary = last_json(&output);
    let cells = summary["per_cell"].as_array().unwrap();
    assert_eq!(cells.len(), 3, "{summary}");
    // Consecutive blocks of 7 episodes among 3 robots: 2, 2 and 3.
    let episodes: Vec<u64> = cells
        .iter()
        .map(|c| c["episodes"].as_u64().unwrap())
        .collect();
    assert_eq!(episodes, vec![2, 2, 3]);
    let successes: u64 = cells.iter().map(|c| c["successes"].as_u64().unwrap()).sum();
    assert_eq!(
        successes,
        summary["successes"].as_u64().unwrap(),
        "{summary}"
    );
    let reaching = cells
        .iter()
        .filter(|c| c["success_rate"].as_f64().unwrap() >= 0.6)
        .count();
    assert_eq!(summary["cells_reaching"], reaching as u64);
    assert_eq!(summary["threshold"], 0.6);
    let text = String::from_utf8_lossy(&output.stdout);
    assert!(
        text.contains(&format!("{reaching} of 3 cells reach 0.6")),
        "{text}"
    );
    // Without --threshold, the service's activation threshold.
    let default = last_json(&celld(&[
        "eval",
        "--randomise-cells",
        "--robots",
        "2",
        "--episodes",
        "2",
        "--per-cell",
        "--json",
    ]));
    assert_eq!(default["threshold"], 0.95, "{default}");
}

fn refused(args: &[&str], needle: &str) {
    let output = celld(args);
    assert!(!output.status.success(), "{args:?} should fail");
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(stderr.contains(needle), "{args:?}: {stderr}");
}

#[test]
fn bad_input_is_refused_with_a_message() {
    refused(
        &["eval", "--controller", "teleport", "--episodes", "1"],
        "unknown controller `teleport`",
    );
    refused(
        &["eval", "--cell", "cells/missing.toml"],
        "cells/missing.toml",
    );
    refused(&["eval", "--noise-scale=-1"], "--noise-scale");
    refused(&["eval", "--episodes", "0"], "--episodes");
    refused(&["eval", "--init-ori-deg", "45"], "--init-ori-deg");
    refused(&["eval", "--without", "gravity"], "gravity");
    refused(&["eval", "--calibration-scale=-1"], "--calibration-scale");
    refused(
        &["eval", "--calibration-scale", "inf"],
        "--calibration-scale",
    );
    refused(
        &["eval", "--randomise-cells", "--noise-scale", "2"],
        "cannot be used with '--noise-scale",
    );
    refused(
        &["eval", "--randomise-noise-up-to", "4"],
        "--randomise-cells",
    );
    refused(
        &[
            "eval",
            "--randomise-cells",
            "--randomise-noise-up-to",
            "0.2",
        ],
        "--randomise-noise-up-to 0.2 is outside 0.5..=16",
    );
    refused(
        &["eval", "--controller", "hierarchical", "--episodes", "1"],
        "`hierarchical` was renamed `hierarchical-reference` (the reference-cell policy); \
         the default for any cell is `hierarchical-swift-cells`",
    );
    refused(
        &[
            "eval",
            "--controller",
            "hierarchical-swift",
            "--episodes",
            "1",
        ],
        "`hierarchical-swift` was renamed `hierarchical-swift-reference`",
    );
    refused(&["eval", "--per-cell"], "--randomise-cells");
    refused(
        &[
            "eval",
            "--randomise-cells",
            "--per-cell",
            "--threshold",
            "1.5",
        ],
        "--threshold must lie in [0, 1], got 1.5",
    );
    refused(
        &["eval", "--fault", "gravity"],
        "unknown fault `gravity`: expected one of camera_shift, occlusion",
    );
}

#[test]
fn a_reader_that_goes_away_ends_the_output_without_a_panic() {
    // `celld eval … | head`: the pipe's reading end is closed before celld writes anything.
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_celld"))
        .args(["eval", "--controller", "expert", "--episodes", "5"])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("celld runs");
    drop(child.stdout.take());
    let output = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!stderr.contains("panicked"), "{stderr}");
    // Ended by SIGPIPE, as Unix tools are (a panic exits with code 101).
    use std::os::unix::process::ExitStatusExt;
    assert_eq!(output.status.signal(), Some(13), "{:?}", output.status);
}
