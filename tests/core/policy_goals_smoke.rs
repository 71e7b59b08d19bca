//! `celld check --smoke`: every goal the bundled policies are held to, on a few episodes each
//! (the full check, `celld check`, runs them on the episodes of the figures in
//! docs/experiments/2026-12-07-81d9a69-where-the-policies-stand.md:
//! docs/policy-rules.md, "Checking the goals"), and the check missing a goal, naming it and
//! exiting non-zero, when a policy that cannot meet it stands in for a bundled one.

use std::process::{Command, Output};

fn celld_check(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_celld"))
        .arg("check")
        .args(args)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .expect("celld runs")
}

fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

/// The line of `stdout` for `goal`, `policy` and `condition`, and whether it ends PASS.
fn goal_line<'a>(stdout: &'a str, goal: &str, policy: &str, condition: &str) -> Option<&'a str> {
    stdout.lines().find(|line| {
        let words: Vec<&str> = line.split_whitespace().collect();
        words.first() == Some(&goal)
            && words.get(1) == Some(&policy)
            && line.contains(&format!(" {condition} "))
    })
}

const CROSS_CELL: [&str; 2] = ["hierarchical-cells", "hierarchical-swift-cells"];
const HIERARCHICAL: [&str; 4] = [
    "hierarchical-reference",
    "hierarchical-cells",
    "hierarchical-swift-reference",
    "hierarchical-swift-cells",
];

/// Every goal of the bundled policies, as (goal, policy, condition): written out here, not
/// read from the command, so a goal the command stopped checking is missed.
fn every_goal() -> Vec<(&'static str, &'static str, &'static str)> {
    let mut goals = Vec::new();
    for cell in [
        "phi100-deep",
        "c120-tight-deep-small-robot",
        "c250-tight-deep",
    ] {
        goals.extend(CROSS_CELL.map(|p| ("deep-tight", p, cell)));
    }
    goals.extend(HIERARCHICAL.map(|p| ("reference", p, "phi170")));
    goals.extend(
        HIERARCHICAL[2..]
            .iter()
            .map(|p| ("reference-fast", *p, "phi170")),
    );
    goals.extend(HIERARCHICAL.map(|p| ("noise-x2", p, "phi170 noise x2")));
    goals.extend(HIERARCHICAL.map(|p| ("noise-x4", p, "phi170 noise x4")));
    goals
}

#[test]
fn every_goal_holds_on_the_smoke_episodes() {
    let output = celld_check(&["--smoke", "--json"]);
    let (stdout, stderr) = (text(&output.stdout), text(&output.stderr));
    assert!(output.status.success(), "{stdout}\n{stderr}");
    let goals = every_goal();
    for (goal, policy, condition) in &goals {
        let line = goal_line(&stdout, goal, policy, condition)
            .unwrap_or_else(|| panic!("no line for {goal} {policy} {condition}:\n{stdout}"));
        assert!(line.ends_with("PASS"), "{line}");
    }
    let json: serde_json::Value =
        serde_json::from_str(stdout.lines().last().expect("a JSON line")).unwrap();
    assert_eq!(json["held"], goals.len());
    assert_eq!(json["missed"], 0);
    let checked = json["goals"].as_array().unwrap();
    assert_eq!(checked.len(), goals.len());
    for goal in checked {
        for bound in goal["bounds"].as_array().unwrap() {
            // The figure really is on the held side of its bound.
            let (measured, limit) = (bound["measured"].as_f64(), bound["bound"].as_f64());
            let (measured, limit) = (measured.unwrap(), limit.unwrap());
            let held = match bound["relation"].as_str().unwrap() {
                ">=" => measured >= limit,
                "<=" => measured <= limit,
                "<" => measured < limit,
                other => panic!("relation {other}"),
            };
            assert!(held && bound["held"] == true, "{goal}");
        }
    }
}

/// The flat TD3 baseline succeeds in none of the reference cell's episodes: in place of
/// `hierarchical-swift-reference` it misses both of that policy's goals there, and the check
/// names them; the policy checked beside it still holds its own.
#[test]
fn a_policy_that_cannot_meet_its_goals_misses_them_and_the_check_fails() {
    let replaced = "hierarchical-swift-reference=policies/td3.safetensors";
    let output = celld_check(&[
        "--smoke",
        "--only",
        "reference,reference-fast,hierarchical-swift-reference,hierarchical-swift-cells",
        "--policy",
        replaced,
    ]);
    let (stdout, stderr) = (text(&output.stdout), text(&output.stderr));
    assert!(!output.status.success(), "{stdout}\n{stderr}");
    for goal in ["reference", "reference-fast"] {
        let missed = goal_line(&stdout, goal, replaced, "phi170").expect(&stdout);
        assert!(missed.ends_with("MISS"), "{missed}");
        let held = goal_line(&stdout, goal, "hierarchical-swift-cells", "phi170").expect(&stdout);
        assert!(held.ends_with("PASS"), "{held}");
    }
    assert_eq!(
        stdout
            .lines()
            .filter(|l| l.starts_with("reference"))
            .count(),
        4
    );
    assert!(stdout.contains("successes 0 ≥ expert's"), "{stdout}");
    assert!(stdout.contains("steps - (no success) ≤ 40"), "{stdout}");
    assert!(
        stderr.contains(&format!(
            "missed 2 of 4 goals: reference ({replaced} on phi170), reference-fast ({replaced} \
             on phi170)"
        )),
        "{stderr}"
    );
}

#[test]
fn names_that_are_no_goal_or_policy_are_refused_before_any_episode() {
    for (args, expected) in [
        (vec!["--only", "noise-x3"], "--only noise-x3: not a goal"),
        (
            vec!["--policy", "expert=policies/td3.safetensors"],
            "expert is not a policy the goals check",
        ),
        (vec!["--policy", "hierarchical-cells"], "expected NAME=FILE"),
        (
            vec!["--policy", "hierarchical-cells=no/such.safetensors"],
            "--policy hierarchical-cells=no/such.safetensors",
        ),
    ] {
        let output = celld_check(&args);
        let stderr = text(&output.stderr);
        assert!(!output.status.success(), "{args:?}");
        assert!(stderr.contains(expected), "{args:?}: {stderr}");
        assert!(output.stdout.is_empty(), "{args:?}");
    }
}
