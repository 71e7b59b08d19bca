//! The product speaks of itself alone: no development history (numbered sessions or issues),
//! no scratch paths and no references outside the repository in what a user reads: README.md,
//! docs/, src/, benches/ and static/.

use std::path::{Path, PathBuf};

/// Case-insensitive phrases followed by a digit, and plain phrases, that must not appear (put
/// together from parts, so this file does not hold them itself).
const FOLLOWED_BY_DIGIT: &[&str] = &[
    concat!("sess", "ion "),
    concat!("iss", "ue "),
    concat!("/tmp", "/s"),
];
const ANYWHERE: &[&str] = &[concat!("..", "/shared")];

fn files_under(path: &Path, found: &mut Vec<PathBuf>) {
    if path.is_file() {
        found.push(path.to_path_buf());
    } else if let Ok(entries) = std::fs::read_dir(path) {
        for entry in entries.flatten() {
            files_under(&entry.path(), found);
        }
    }
}

/// Every (line number, phrase) in `text` that breaks the rule.
fn leaks(text: &str) -> Vec<(usize, String)> {
    let mut found = Vec::new();
    for (number, line) in text.lines().enumerate() {
        let lower = line.to_lowercase();
        for phrase in FOLLOWED_BY_DIGIT {
            for (at, _) in lower.match_indices(phrase) {
                let next = lower[at + phrase.len()..].chars().next();
                if next.is_some_and(|c| c.is_ascii_digit()) {
                    found.push((number + 1, phrase.trim().to_string()));
                }
            }
        }
        for phrase in ANYWHERE {
            if lower.contains(phrase) {
                found.push((number + 1, phrase.to_string()));
            }
        }
    }
    found
}

#[test]
fn the_rule_catches_what_it_should_and_nothing_else() {
    for (phrase, rest) in [
        (FOLLOWED_BY_DIGIT[0], "12 measured it"),
        (FOLLOWED_BY_DIGIT[1], "3, item 5"),
        (FOLLOWED_BY_DIGIT[2], "16/W30"),
        (ANYWHERE[0], "/DESIGN.md"),
    ] {
        let capitalised = format!("As {}{rest}", phrase.to_uppercase());
        assert_eq!(leaks(&capitalised).len(), 1, "{capitalised}");
    }
    assert!(leaks("one session of training; an issue with the camera; /tmp/celld").is_empty());
}

#[test]
fn readme_docs_code_examples_and_dashboard_carry_no_development_history() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut files = Vec::new();
    for place in [
        "README.md",
        "docs",
        "src",
        "benches",
        "static",
        "examples",
        "research",
        "scripts",
    ] {
        files_under(&root.join(place), &mut files);
    }
    assert!(files.len() > 50, "only {} files found", files.len());
    let mut report = Vec::new();
    for file in &files {
        // Binary files (images, vendored bundles) are skipped: they are not text a user reads.
        let Ok(text) = std::fs::read_to_string(file) else {
            continue;
        };
        for (line, phrase) in leaks(&text) {
            let shown = file.strip_prefix(root).unwrap_or(file).display();
            report.push(format!("{shown}:{line}: `{phrase}`"));
        }
    }
    assert!(
        report.is_empty(),
        "history in the product:\n{}",
        report.join("\n")
    );
}
