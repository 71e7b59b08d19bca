//! `celld train` end to end, at toy sizes: the run directory, resuming, refusing to overwrite,
//! determinism under a seed, and bad input named before any work.

use crate::common;

use common::celld;
use serde_json::json;
use std::path::{Path, PathBuf};

const TINY: [&str; 18] = [
    "--demos",
    "12",
    "--bc-epochs",
    "2",
    "--lstm-epochs",
    "2",
    "--lstm-hidden",
    "8",
    "--actor-width",
    "16",
    "--eval-every",
    "2",
    "--eval-episodes",
    "4",
    "--checkpoint-every",
    "1",
    "--seed",
    "7",
];

fn train(stage: &str, out: &Path, extra: &[&str]) -> std::process::Output {
    let mut args = vec!["train", stage, "--out", out.to_str().unwrap()];
    args.extend_from_slice(&TINY);
    args.extend_from_slice(extra);
    celld(&args)
}

/// `train`, with some of the toy settings' values replaced.
fn train_overriding(
    stage: &str,
    out: &Path,
    overrides: &[(&str, &str)],
    extra: &[&str],
) -> std::process::Output {
    let mut args = vec!["train", stage, "--out", out.to_str().unwrap()];
    for pair in TINY.chunks(2) {
        let value = overrides
            .iter()
            .find(|(flag, _)| *flag == pair[0])
            .map_or(pair[1], |(_, value)| *value);
        args.extend_from_slice(&[pair[0], value]);
    }
    args.extend_from_slice(extra);
    celld(&args)
}

fn stderr(output: &std::process::Output) -> String {
    String::from_utf8_lossy(&output.stderr).into_owned()
}

#[test]
fn train_all_makes_a_policy_resumes_and_is_deterministic() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = (dir.path().join("a"), dir.path().join("b"));
    let first = train("all", &a, &["--td3-episodes", "3"]);
    assert!(first.status.success(), "{}", stderr(&first));
    for name in [
        "demos.jsonl",
        "bc.safetensors",
        "bc_curve.csv",
        "lstm.safetensors",
        "lstm_curve.csv",
        "bc-policy.safetensors",
        "td3_checkpoint.safetensors",
        "td3_progress.json",
        "td3_curve.csv",
        "td3_curve.json",
        "policy.safetensors",
        "run.json",
    ] {
        assert!(a.join(name).is_file(), "{name} missing");
    }
    let curve = std::fs::read_to_string(a.join("td3_curve.csv")).unwrap();
    assert_eq!(curve.lines().next(), Some("episode,return,success,steps"));
    assert_eq!(curve.lines().count(), 1 + 3);
    // The policy is a valid policy file that celld runs.
    let policy = a.join("policy.safetensors");
    let eval = celld(&[
        "eval",
        "--controller",
        policy.to_str().unwrap(),
        "--episodes",
        "2",
    ]);
    assert!(eval.status.success(), "{}", stderr(&eval));

    // The same seed gives the same files, whether `all` trains BC and the selector at once or
    // the stages run one by one.
    for stage in ["bc", "lstm", "td3"] {
        let second = train(stage, &b, &["--td3-episodes", "3", "--resume"]);
        assert!(second.status.success(), "{stage}: {}", stderr(&second));
    }
    for name in [
        "bc.safetensors",
        "lstm.safetensors",
        "bc-policy.safetensors",
        "policy.safetensors",
    ] {
        assert_eq!(
            std::fs::read(a.join(name)).unwrap(),
            std::fs::read(b.join(name)).unwrap(),
            "{name} differs between two runs with one seed"
        );
    }

    // A second run into the same directory refuses to overwrite it…
    let again = train("all", &a, &["--td3-episodes", "3"]);
    assert!(!again.status.success());
    assert!(stderr(&again).contains("--resume"), "{}", stderr(&again));
    // …and with --resume, TD3 continues from its checkpoint, which holds its own progress (a
    // crash after the checkpoint and before the readable progress file loses nothing).
    std::fs::remove_file(a.join("td3_progress.json")).unwrap();
    let more = train("td3", &a, &["--td3-episodes", "5", "--resume"]);
    assert!(more.status.success(), "{}", stderr(&more));
    assert!(
        stderr(&more).contains("resuming TD3 at episode 3"),
        "{}",
        stderr(&more)
    );
    let progress: serde_json::Value =
        serde_json::from_slice(&std::fs::read(a.join("td3_progress.json")).unwrap()).unwrap();
    assert_eq!(progress["episode"], 5);
    assert_eq!(progress["curve"].as_array().unwrap().len(), 5);
}

#[test]
fn a_run_across_randomised_cells_is_deterministic_and_writes_a_cell_relative_policy() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = (dir.path().join("a"), dir.path().join("b"));
    let across = [
        "--inputs",
        "cell-relative",
        "--randomise-cells",
        "--td3-episodes",
        "2",
        // TD3 beside the demonstrator: its episodes in the replay, on randomised cells too.
        "--td3-demonstrations",
        "2",
    ];
    for out in [&a, &b] {
        let run = train("all", out, &across);
        assert!(run.status.success(), "{}", stderr(&run));
    }
    for name in ["demos.jsonl", "bc-policy.safetensors", "policy.safetensors"] {
        assert_eq!(
            std::fs::read(a.join(name)).unwrap(),
            std::fs::read(b.join(name)).unwrap(),
            "{name} differs between two randomised runs with one seed"
        );
    }
    // Each episode had a cell of its own: the bore's depth, which the recorded inputs carry
    // in slot 1, differs from episode to episode and from the reference cell's 60 mm.
    let depths: std::collections::BTreeSet<String> = demo_lines(&a)
        .iter()
        .map(|line| line["state"][1].to_string())
        .collect();
    assert!(depths.len() > 5, "{depths:?}");
    assert!(!depths.contains("60.0"), "{depths:?}");
    // The policy is a version 2 file that names its inputs, and it runs on another cell.
    let policy = a.join("policy.safetensors");
    let file = assembly_cell::policy::file::PolicyFile::from_path(&policy).unwrap();
    assert_eq!(file.metadata().format_version, "2");
    assert_eq!(
        file.metadata().inputs,
        assembly_cell::policy::inputs::PolicyInputs::CellRelative
    );
    let cell = Path::new(env!("CARGO_MANIFEST_DIR")).join("cells/phi140-robot.toml");
    let eval = celld(&[
        "eval",
        "--controller",
        policy.to_str().unwrap(),
        "--cell",
        cell.to_str().unwrap(),
        "--episodes",
        "2",
    ]);
    assert!(eval.status.success(), "{}", stderr(&eval));

    // Randomised cells need inputs that can tell them apart; the flat baseline reads the
    // paper's state only.
    let absolute = train("all", &dir.path().join("c"), &["--randomise-cells"]);
    assert!(!absolute.status.success());
    assert!(
        stderr(&absolute).contains("--randomise-cells needs --inputs cell-relative"),
        "{}",
        stderr(&absolute)
    );
    // The noise of drawn cells may be widened, within reason, and only for drawn cells.
    let alone = train(
        "all",
        &dir.path().join("c"),
        &["--randomise-noise-up-to", "4"],
    );
    assert!(!alone.status.success());
    assert!(
        stderr(&alone).contains("required arguments were not provided:\n  --randomise-cells"),
        "{}",
        stderr(&alone)
    );
    let beyond = train(
        "all",
        &dir.path().join("c"),
        &[
            "--inputs",
            "cell-scaled",
            "--randomise-cells",
            "--randomise-noise-up-to",
            "40",
        ],
    );
    assert!(!beyond.status.success());
    assert!(
        stderr(&beyond).contains("--randomise-noise-up-to 40 is outside 0.5..=16"),
        "{}",
        stderr(&beyond)
    );
    let unknown = train("all", &dir.path().join("c"), &["--inputs", "pixels"]);
    assert!(!unknown.status.success());
    assert!(
        stderr(&unknown).contains("--inputs pixels: expected one of absolute, cell-relative"),
        "{}",
        stderr(&unknown)
    );
    let flat = train(
        "flat",
        &dir.path().join("c"),
        &["--inputs", "cell-relative"],
    );
    assert!(!flat.status.success());
    assert!(
        stderr(&flat).contains("absolute inputs only"),
        "{}",
        stderr(&flat)
    );
}

#[test]
fn bad_training_requests_are_refused_before_any_work() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    let missing = train("lstm", &out, &[]);
    assert!(!missing.status.success());
    assert!(
        stderr(&missing).contains("bc.safetensors is missing"),
        "{}",
        stderr(&missing)
    );
    let few = celld(&[
        "train",
        "all",
        "--out",
        out.to_str().unwrap(),
        "--demos",
        "3",
    ]);
    assert!(!few.status.success());
    assert!(stderr(&few).contains("--demos must be at least 10"));
    let lr = celld(&["train", "bc", "--out", out.to_str().unwrap(), "--bc-lr=-1"]);
    assert!(!lr.status.success());
    assert!(stderr(&lr).contains("--bc-lr must be a finite number > 0"));
    let sigma = celld(&[
        "train",
        "bc",
        "--out",
        out.to_str().unwrap(),
        "--norm-tilt-std-deg",
        "0",
    ]);
    assert!(!sigma.status.success());
    assert!(stderr(&sigma).contains("--norm-tilt-std-deg must be a finite number > 0"));
    let demonstrator = celld(&[
        "train",
        "all",
        "--out",
        out.to_str().unwrap(),
        "--demonstrator",
        "spiral",
    ]);
    assert!(!demonstrator.status.success());
    assert!(
        stderr(&demonstrator).contains("--demonstrator spiral: not a demonstrator"),
        "{}",
        stderr(&demonstrator)
    );
    let file = celld(&[
        "train",
        "bc",
        "--out",
        out.to_str().unwrap(),
        "--demos-file",
        "no/such.jsonl",
    ]);
    assert!(!file.status.success());
    assert!(stderr(&file).contains("no/such.jsonl: no such file"));
    for (flag, value, message) in [
        (
            "--bc-anneal-fraction",
            "1.5",
            "--bc-anneal-fraction must be between 0 and 1",
        ),
        (
            "--bc-anneal-factor",
            "0",
            "--bc-anneal-factor must be > 0 and at most 1",
        ),
        (
            "--td3-trust-region",
            "inf",
            "--td3-trust-region must be a finite number >= 0",
        ),
        (
            "--td3-noise",
            "0",
            "--td3-noise must be a finite number > 0",
        ),
        (
            "--bc-orientation-label-floor",
            "1.5",
            "--bc-orientation-label-floor must be in (0, 1], got 1.5",
        ),
        (
            "--bc-position-label-floor",
            "0",
            "--bc-position-label-floor must be in (0, 1], got 0",
        ),
    ] {
        let bad = celld(&["train", "bc", "--out", out.to_str().unwrap(), flag, value]);
        assert!(!bad.status.success());
        assert!(stderr(&bad).contains(message), "{}", stderr(&bad));
    }
    assert!(!out.join("demos.jsonl").exists(), "no work was done");
}

/// The tensors of a checkpoint or policy file whose names start with `prefix`, by name.
fn tensors(path: &Path, prefix: &str) -> Vec<(String, Vec<f32>)> {
    let mut named: Vec<(String, Vec<f32>)> =
        candle_core::safetensors::load(path, &candle_core::Device::Cpu)
            .unwrap()
            .into_iter()
            .filter(|(name, _)| name.starts_with(prefix))
            .map(|(name, t)| (name, t.flatten_all().unwrap().to_vec1::<f32>().unwrap()))
            .collect();
    named.sort_by(|a, b| a.0.cmp(&b.0));
    assert!(
        !named.is_empty(),
        "no `{prefix}` tensors in {}",
        path.display()
    );
    named
}

#[test]
fn fine_tuning_starts_from_the_given_policy_and_keeps_its_normaliser() {
    let dir = tempfile::tempdir().unwrap();
    let (first, tuned) = (dir.path().join("first"), dir.path().join("tuned"));
    for stage in ["bc", "lstm"] {
        let run = train(stage, &first, &[]);
        assert!(run.status.success(), "{stage}: {}", stderr(&run));
    }
    let start = first.join("bc-policy.safetensors");
    // At a vanishing learning rate nothing moves, so what the stages write is where they
    // started: the given policy's weights and normaliser, not fresh ones. Other demonstrations
    // (seed 8), whose own normaliser would differ.
    let vanishing = [
        "--init-policy",
        start.to_str().unwrap(),
        "--bc-lr",
        "1e-30",
        "--lstm-lr",
        "1e-30",
    ];
    let seed_8 = [("--seed", "8")];
    for stage in ["bc", "lstm"] {
        let run = train_overriding(stage, &tuned, &seed_8, &vanishing);
        assert!(run.status.success(), "{stage}: {}", stderr(&run));
    }
    for prefix in ["obs_", "pos.", "ori.", "high."] {
        assert_eq!(
            tensors(&tuned.join("bc-policy.safetensors"), prefix),
            tensors(&start, prefix),
            "{prefix}"
        );
    }
    // At the default rate the actors move from there.
    let moved = dir.path().join("moved");
    let run = train_overriding("bc", &moved, &seed_8, &vanishing[..2]);
    assert!(run.status.success(), "{}", stderr(&run));
    assert_ne!(
        tensors(&moved.join("bc.safetensors"), "pos."),
        tensors(&start, "pos.")
    );
    assert_eq!(
        tensors(&moved.join("bc.safetensors"), "obs_"),
        tensors(&start, "obs_")
    );

    // A policy of other sizes is refused before any work.
    let wide = dir.path().join("wide");
    let refused = train_overriding(
        "bc",
        &wide,
        &[("--actor-width", "32")],
        &["--init-policy", start.to_str().unwrap()],
    );
    assert!(!refused.status.success());
    assert!(
        stderr(&refused).contains("its size is 16, this run's --actor-width is 32"),
        "{}",
        stderr(&refused)
    );
    assert!(!wide.join("demos.jsonl").exists(), "no work was done");
}

fn demo_lines(run: &Path) -> Vec<serde_json::Value> {
    std::fs::read_to_string(run.join("demos.jsonl"))
        .unwrap()
        .lines()
        .map(|line| serde_json::from_str(line).unwrap())
        .collect()
}

#[test]
fn dagger_episodes_come_before_the_demonstrations_which_are_unchanged() {
    let dir = tempfile::tempdir().unwrap();
    let (plain, dagger) = (dir.path().join("plain"), dir.path().join("dagger"));
    let policy =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/policy_small.safetensors");
    let policy = policy.to_str().unwrap();
    let first = train("bc", &plain, &[]);
    assert!(first.status.success(), "{}", stderr(&first));
    let extra = [
        "--dagger-policy",
        policy,
        "--dagger-policy",
        policy,
        "--dagger-episodes",
        "3",
    ];
    let second = train("bc", &dagger, &extra);
    assert!(second.status.success(), "{}", stderr(&second));

    let run: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dagger.join("run.json")).unwrap()).unwrap();
    let rounds = run["demos"]["figures"]["dagger"].as_array().unwrap();
    assert_eq!(rounds.len(), 2);
    assert!(rounds.iter().all(|r| r["episodes"] == 3), "{rounds:?}");

    // Episodes are numbered 0, 1, … in file order: 2 rounds × 3, then the 12 demonstrations,
    // which are the plain run's, step for step.
    let (plain, dagger) = (demo_lines(&plain), demo_lines(&dagger));
    let episodes: Vec<u64> = dagger
        .iter()
        .map(|l| l["episode"].as_u64().unwrap())
        .collect();
    assert!(
        episodes
            .windows(2)
            .all(|w| w[1] == w[0] || w[1] == w[0] + 1)
    );
    assert_eq!((episodes[0], *episodes.last().unwrap()), (0, 6 + 12 - 1));
    let demonstrated = &dagger[dagger.len() - plain.len()..];
    for (a, b) in plain.iter().zip(demonstrated) {
        assert_eq!(a["state"], b["state"]);
        assert_eq!(a["action"], b["action"]);
        assert_eq!(
            b["episode"].as_u64().unwrap(),
            a["episode"].as_u64().unwrap() + 6
        );
    }
    // Two rounds of one policy with their own seeds: different episodes.
    let round = |k: u64| -> Vec<_> {
        dagger
            .iter()
            .filter(|l| l["episode"].as_u64().unwrap() / 3 == k)
            .map(|l| l["state"].clone())
            .collect()
    };
    assert_ne!(round(0), round(1));
}

/// With `--dagger-actors-only` the DAgger episodes teach the actors as before, and the selector
/// learns from the demonstrator's own episodes only: its weights differ from a plain DAgger
/// run's, and match a run whose selector is trained on those episodes alone.
#[test]
fn dagger_actors_only_keeps_the_dagger_episodes_from_the_selector() {
    let dir = tempfile::tempdir().unwrap();
    let policy =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/policy_small.safetensors");
    let dagger = [
        "--dagger-policy",
        policy.to_str().unwrap(),
        "--dagger-episodes",
        "6",
    ];
    let runs: Vec<_> = ["plain", "actors-only"]
        .iter()
        .map(|name| dir.path().join(name))
        .collect();
    for (run, only) in runs.iter().zip([false, true]) {
        let mut extra = dagger.to_vec();
        if only {
            extra.push("--dagger-actors-only");
        }
        for stage in ["bc", "lstm"] {
            let output = train(stage, run, &extra);
            assert!(output.status.success(), "{}", stderr(&output));
        }
    }
    let lstm = |run: &Path, prefix: &str| tensors(&run.join("lstm.safetensors"), prefix);
    assert_eq!(lstm(&runs[0], "pos."), lstm(&runs[1], "pos."));
    assert_eq!(lstm(&runs[0], "obs_"), lstm(&runs[1], "obs_"));
    assert_ne!(lstm(&runs[0], "high."), lstm(&runs[1], "high."));

    // The same selector, trained by hand on the demonstrator's episodes: the actors-only run's
    // demonstrations without the DAgger ones, with its BC stage (and so its normaliser) copied.
    let own = dir.path().join("own");
    std::fs::create_dir_all(&own).unwrap();
    let lines = std::fs::read_to_string(runs[1].join("demos.jsonl")).unwrap();
    let kept: String = lines
        .lines()
        .filter(|line| {
            let line: serde_json::Value = serde_json::from_str(line).unwrap();
            line["episode"].as_u64().unwrap() >= 6
        })
        .map(|line| format!("{line}\n"))
        .collect();
    std::fs::write(own.join("demos.jsonl"), kept).unwrap();
    std::fs::copy(runs[1].join("bc.safetensors"), own.join("bc.safetensors")).unwrap();
    let output = train("lstm", &own, &[]);
    assert!(output.status.success(), "{}", stderr(&output));
    assert_eq!(lstm(&own, "high."), lstm(&runs[1], "high."));
}

#[test]
fn a_bad_dagger_policy_is_refused_before_any_work() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    let missing = train("bc", &out, &["--dagger-policy", "no/such.safetensors"]);
    assert!(!missing.status.success());
    assert!(
        stderr(&missing).contains("--dagger-policy no/such.safetensors"),
        "{}",
        stderr(&missing)
    );
    let demos = dir.path().join("demos.jsonl");
    std::fs::write(&demos, "").unwrap();
    let extra = [
        "--dagger-policy",
        "x.safetensors",
        "--demos-file",
        demos.to_str().unwrap(),
    ];
    let with_file = train("bc", &out, &extra);
    assert!(!with_file.status.success());
    assert!(
        stderr(&with_file).contains("it cannot add to --demos-file"),
        "{}",
        stderr(&with_file)
    );
    assert!(!out.join("demos.jsonl").exists(), "no work was done");
}

const TINY_FLAT: [&str; 12] = [
    "--demos",
    "12",
    "--flat-hidden",
    "16",
    "--eval-every",
    "2",
    "--eval-episodes",
    "4",
    "--checkpoint-every",
    "1",
    "--seed",
    "7",
];

fn train_flat(out: &Path, extra: &[&str]) -> std::process::Output {
    let mut args = vec!["train", "flat", "--out", out.to_str().unwrap()];
    args.extend_from_slice(&TINY_FLAT);
    args.extend_from_slice(extra);
    celld(&args)
}

#[test]
fn train_flat_makes_a_td3_policy_resumes_and_is_deterministic() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = (dir.path().join("a"), dir.path().join("b"));
    let first = train_flat(&a, &["--td3-episodes", "3"]);
    assert!(first.status.success(), "{}", stderr(&first));
    for name in [
        "demos.jsonl",
        "td3-flat_checkpoint.safetensors",
        "td3-flat_progress.json",
        "td3-flat_curve.csv",
        "td3-flat_curve.json",
        "td3-flat-policy.safetensors",
        "run.json",
    ] {
        assert!(a.join(name).is_file(), "{name} missing");
    }
    // No stage of the hierarchy ran.
    assert!(!a.join("bc.safetensors").exists());
    let curve = std::fs::read_to_string(a.join("td3-flat_curve.csv")).unwrap();
    assert_eq!(curve.lines().next(), Some("episode,return,success,steps"));
    assert_eq!(curve.lines().count(), 1 + 3);
    // The JSON curve has the shape `celld report --curve` reads, with the validations.
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(a.join("td3-flat_curve.json")).unwrap()).unwrap();
    assert_eq!(json["episodes"].as_array().unwrap().len(), 3);
    assert_eq!(json["episodes"][2]["episode"], 2);
    assert!(json["episodes"][0]["return"].is_number());
    let validated: Vec<u64> = json["validations"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v["episode"].as_u64().unwrap())
        .collect();
    assert_eq!(validated, vec![2, 3]);
    let run: serde_json::Value =
        serde_json::from_slice(&std::fs::read(a.join("run.json")).unwrap()).unwrap();
    assert!(run["td3-flat"]["wall_s"].is_number(), "{run}");

    // The policy is a flat policy file that `celld eval --controller FILE` runs.
    let policy = a.join("td3-flat-policy.safetensors");
    let eval = celld(&[
        "eval",
        "--controller",
        policy.to_str().unwrap(),
        "--episodes",
        "2",
    ]);
    assert!(eval.status.success(), "{}", stderr(&eval));

    // The same seed gives the same files.
    let second = train_flat(&b, &["--td3-episodes", "3"]);
    assert!(second.status.success(), "{}", stderr(&second));
    for name in ["td3-flat-policy.safetensors", "td3-flat_curve.csv"] {
        assert_eq!(
            std::fs::read(a.join(name)).unwrap(),
            std::fs::read(b.join(name)).unwrap(),
            "{name} differs between two runs with one seed"
        );
    }

    // A second run into the same directory refuses to overwrite it…
    let again = train_flat(&a, &["--td3-episodes", "3"]);
    assert!(!again.status.success());
    assert!(stderr(&again).contains("--resume"), "{}", stderr(&again));
    // …and with --resume, it continues from its checkpoint.
    let more = train_flat(&a, &["--td3-episodes", "5", "--resume"]);
    assert!(more.status.success(), "{}", stderr(&more));
    assert!(
        stderr(&more).contains("resuming flat TD3 at episode 3"),
        "{}",
        stderr(&more)
    );
    let progress: serde_json::Value =
        serde_json::from_slice(&std::fs::read(a.join("td3-flat_progress.json")).unwrap()).unwrap();
    assert_eq!(progress["episode"], 5);
    assert_eq!(progress["curve"].as_array().unwrap().len(), 5);
}

#[test]
fn bad_flat_training_requests_are_refused_before_any_work() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    let none = train_flat(&out, &["--td3-episodes", "0"]);
    assert!(!none.status.success());
    assert!(
        stderr(&none).contains("--td3-episodes must be at least 1"),
        "{}",
        stderr(&none)
    );
    let narrow = celld(&[
        "train",
        "flat",
        "--out",
        out.to_str().unwrap(),
        "--flat-hidden",
        "0",
    ]);
    assert!(!narrow.status.success());
    assert!(
        stderr(&narrow).contains("--flat-hidden must be at least 1"),
        "{}",
        stderr(&narrow)
    );
    assert!(!out.join("demos.jsonl").exists(), "no work was done");
}

/// `train policy`'s toy sizes: [`TINY`] without the seed (its last flag), which `train policy`
/// takes itself, and as many DAgger episodes as demonstrations.
fn tiny_policy() -> Vec<&'static str> {
    let (flags, seed) = TINY.split_at(TINY.len() - 2);
    assert_eq!(seed[0], "--seed");
    let mut flags = flags.to_vec();
    // Two TD3 episodes a round: the polish's own 500 give way to the caller's.
    flags.extend(["--dagger-episodes", "12", "--td3-episodes", "2"]);
    flags
}

#[test]
fn train_policy_is_train_all_then_a_dagger_round_that_teaches_the_actors_then_a_polish() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("policy");
    let mut args = vec![
        "train",
        "policy",
        "--out",
        out.to_str().unwrap(),
        "--seed",
        "7",
        "--dagger-rounds",
        "1",
    ];
    args.push("--");
    args.extend(tiny_policy());
    let run = celld(&args);
    assert!(run.status.success(), "{}", stderr(&run));

    // The same three runs by hand, with the recipe docs/learning-reference.md states.
    let recipe = [
        "--seed",
        "7",
        "--demonstrator",
        "expert-swift",
        "--bc-bore-lateral-weight",
        "30",
        "--inputs",
        "cell-scaled",
        "--randomise-cells",
        "--bc-orientation-label-floor",
        "0.2",
        // The recipe's `--demos 1600 --bc-epochs 100 --td3-episodes 1` are tiny's here.
    ];
    let (first, second, third) = (
        dir.path().join("first"),
        dir.path().join("second"),
        dir.path().join("third"),
    );
    let by_hand = |to: &Path, dagger: &[&str], polish: &[&str]| {
        let mut args = vec!["train", "all", "--out", to.to_str().unwrap()];
        args.extend_from_slice(&recipe);
        args.extend_from_slice(dagger);
        // tiny's flags, but those the polish sets itself.
        for pair in tiny_policy().chunks(2) {
            if !polish.contains(&pair[0]) {
                args.extend_from_slice(pair);
            }
        }
        args.extend_from_slice(polish);
        let output = celld(&args);
        assert!(output.status.success(), "{}", stderr(&output));
    };
    by_hand(&first, &[], &[]);
    let driver = first.join("policy.safetensors");
    by_hand(
        &second,
        &[
            "--dagger-actors-only",
            "--dagger-policy",
            driver.to_str().unwrap(),
        ],
        &[],
    );
    // The polish starts from the last round's policy, on its own schedule, and its TD3 also
    // refines the step size on 10 kept robots.
    let polished_from = second.join("policy.safetensors");
    by_hand(
        &third,
        &[],
        &[
            "--td3-step-size",
            "--robots",
            "10",
            "--bc-position-label-floor",
            "0.3",
            "--bc-lr",
            "0.002",
            "--bc-anneal-fraction",
            "0.5",
            "--bc-epochs",
            "6",
            "--bc-anneal-factor",
            "0.25",
            "--bc-orientation-epochs",
            "100",
            "--lstm-lr",
            "5e-4",
            "--lstm-epochs",
            "1",
            "--init-policy",
            polished_from.to_str().unwrap(),
        ],
    );
    let read = |path: PathBuf| std::fs::read(&path).unwrap_or_else(|e| panic!("{path:?}: {e}"));
    for (ours, by_hand) in [
        (
            "round-0/policy.safetensors",
            first.join("policy.safetensors"),
        ),
        ("round-1/demos.jsonl", second.join("demos.jsonl")),
        (
            "round-1/policy.safetensors",
            second.join("policy.safetensors"),
        ),
        (
            "polish/policy.safetensors",
            third.join("policy.safetensors"),
        ),
        ("policy.safetensors", third.join("policy.safetensors")),
    ] {
        assert!(read(out.join(ours)) == read(by_hand), "{ours} differs");
    }
    assert_ne!(
        read(third.join("policy.safetensors")),
        read(second.join("policy.safetensors")),
        "the polish changed the policy"
    );
    // Only the polish's TD3 refined the step size, on kept robots.
    let td3_run = |round: &str| {
        let text = std::fs::read_to_string(out.join(round).join("run.json")).unwrap();
        let run: serde_json::Value = serde_json::from_str(&text).unwrap();
        let figures = &run["td3"]["figures"];
        (figures["step_size"].clone(), figures["kept_robots"].clone())
    };
    assert_eq!(td3_run("round-0"), (json!(false), json!(0)));
    assert_eq!(td3_run("polish"), (json!(true), json!(10)));
    let episodes = |run: &Path| {
        let numbers: std::collections::BTreeSet<u64> = demo_lines(run)
            .iter()
            .map(|line| line["episode"].as_u64().unwrap())
            .collect();
        numbers.len()
    };
    assert_eq!((episodes(&first), episodes(&out.join("round-1"))), (12, 24));

    // A finished run resumes to the same policy; without --resume it is not overwritten.
    let before = read(out.join("policy.safetensors"));
    let mut again = args.clone();
    again.insert(4, "--resume");
    let resumed = celld(&again);
    assert!(resumed.status.success(), "{}", stderr(&resumed));
    assert_eq!(read(out.join("policy.safetensors")), before);
    let twice = celld(&args);
    assert!(!twice.status.success());
    assert!(
        stderr(&twice).contains("pass --resume"),
        "{}",
        stderr(&twice)
    );
}

#[test]
fn bad_train_policy_requests_are_refused_before_any_work() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("policy");
    let refused = |extra: &[&str], message: &str| {
        let mut args = vec!["train", "policy", "--out", out.to_str().unwrap(), "--"];
        args.extend_from_slice(extra);
        let output = celld(&args);
        assert!(!output.status.success(), "{extra:?} was accepted");
        assert!(stderr(&output).contains(message), "{}", stderr(&output));
    };
    refused(
        &["--dagger-policy", "p.safetensors"],
        "--dagger-policy after --: `celld train policy` sets it",
    );
    refused(&["--seed=3"], "--seed after --");
    refused(&["--bc-lr=-1"], "--bc-lr must be a finite number > 0");
    refused(&["--no-such-flag"], "the flags after --");
    assert!(
        !out.join("round-0/demos.jsonl").exists(),
        "no work was done"
    );
}
