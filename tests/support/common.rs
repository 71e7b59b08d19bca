//! Helpers shared by the CLI tests: run the built `celld` and read its JSON summary.

use std::process::{Command, Output};

pub fn celld(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_celld"))
        .args(args)
        .output()
        .expect("celld runs")
}

/// The JSON object `--json` prints as the last line of stdout.
#[allow(dead_code)] // not every test binary that includes this module uses it
pub fn last_json(output: &Output) -> serde_json::Value {
    let stdout = String::from_utf8_lossy(&output.stdout);
    let last = stdout.lines().last().expect("some output");
    serde_json::from_str(last).expect("the last line is JSON")
}
