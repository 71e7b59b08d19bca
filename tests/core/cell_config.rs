//! The cell file: the shipped cells load; bad ones are refused with a message naming the key.

use assembly_cell::config::cell::CellConfig;
use std::path::Path;

fn reference_text() -> String {
    std::fs::read_to_string("cells/phi170.toml").unwrap()
}

fn refused(text: &str) -> String {
    CellConfig::parse(text, "test.toml")
        .expect_err("the cell must be refused")
        .to_string()
}

#[test]
fn shipped_cells_load_with_design_values() {
    let phi170 = CellConfig::load(Path::new("cells/phi170.toml")).unwrap();
    assert_eq!(phi170.shaft.diameter_mm, 169.90);
    assert_eq!(phi170.bore.diameter_mm, 170.00);
    assert!((phi170.radial_clearance_mm() - 0.05).abs() < 1e-9);
    assert_eq!(phi170.bore.holes, 8);
    assert_eq!(phi170.hole_pitch_deg(), 45.0);
    assert_eq!(phi170.robot.leg_min_mm, 650.0);
    assert_eq!(phi170.camera.points_per_fixture, 6);
    assert_eq!(phi170.episode.max_steps, 300);
    assert_eq!(phi170, CellConfig::reference());

    let phi200 = CellConfig::load(Path::new("cells/phi200.toml")).unwrap();
    assert_eq!(phi200.bore.diameter_mm, 200.0);
    assert!((phi200.radial_clearance_mm() - 0.075).abs() < 1e-9);
    assert_eq!(phi200.bore.holes, 12);
    assert_ne!(phi170.config_hash(), phi200.config_hash());
}

#[test]
fn unknown_key_is_named() {
    let text = reference_text().replace("[shaft]", "[shaft]\ncolour = \"red\"");
    let message = refused(&text);
    assert!(message.contains("colour"), "{message}");
}

#[test]
fn malformed_value_is_named() {
    let text = reference_text().replace("depth_mm = 60.0", "depth_mm = \"deep\"");
    let message = refused(&text);
    assert!(message.contains("depth_mm"), "{message}");
    let message = refused("this is = not [ toml");
    assert!(message.contains("not a valid cell"), "{message}");
}

#[test]
fn missing_key_is_named() {
    let text = reference_text().replace("rate_hz = 4.0\n", "");
    let message = refused(&text);
    assert!(message.contains("rate_hz"), "{message}");
}

#[test]
fn zero_or_negative_clearance_is_refused() {
    let text = reference_text().replace("diameter_mm = 170.00", "diameter_mm = 169.90");
    let message = refused(&text);
    assert!(
        message.contains("bore.diameter_mm") && message.contains("clearance"),
        "{message}"
    );
}

#[test]
fn a_wall_margin_must_fit_in_the_clearance_and_may_be_left_out() {
    let with = |margin: &str| {
        reference_text().replace(
            "wall_margin_mm = 0.02 ",
            &format!("wall_margin_mm = {margin} "),
        )
    };
    assert_eq!(CellConfig::reference().supervisor.wall_margin_mm, 0.02);
    for bad in ["-0.01", "0.05", "0.2", "nan"] {
        let message = refused(&with(bad));
        assert!(
            message.contains("supervisor.wall_margin_mm") && message.contains("0.05"),
            "{bad}: {message}"
        );
    }
    assert_eq!(
        CellConfig::parse(&with("0.049"), "test.toml")
            .unwrap()
            .supervisor
            .wall_margin_mm,
        0.049
    );
    let start = reference_text().find("[supervisor]").unwrap();
    let end = reference_text().find("[reward]").unwrap();
    let mut without = reference_text();
    without.replace_range(start..end, "");
    let cell = CellConfig::parse(&without, "test.toml").unwrap();
    assert_eq!(cell.supervisor.wall_margin_mm, 0.0);
    // Without the section, the bound on contact and the holds keep their defaults.
    assert_eq!(cell.supervisor.contact_risk_per_move, 1e-4);
    assert_eq!(cell.supervisor.max_uncertain_holds, 150);
}

#[test]
fn the_bound_on_contact_and_the_holds_are_checked() {
    let with = |from: &str, to: &str| reference_text().replace(from, to);
    for bad in ["0", "-1e-4", "0.5", "nan"] {
        let message = refused(&with(
            "contact_risk_per_move = 1e-4",
            &format!("contact_risk_per_move = {bad}"),
        ));
        assert!(
            message.contains("supervisor.contact_risk_per_move"),
            "{bad}: {message}"
        );
    }
    let message = refused(&with(
        "max_uncertain_holds = 150",
        "max_uncertain_holds = 0",
    ));
    assert!(
        message.contains("supervisor.max_uncertain_holds"),
        "{message}"
    );
    let cell = CellConfig::parse(
        &with(
            "contact_risk_per_move = 1e-4",
            "contact_risk_per_move = 1e-6",
        ),
        "test.toml",
    )
    .unwrap();
    assert_eq!(cell.supervisor.contact_risk_per_move, 1e-6);
}

#[test]
fn stroke_that_cannot_reach_home_is_refused() {
    let text = reference_text().replace("leg_max_mm = 1050.0", "leg_max_mm = 800.0");
    let message = refused(&text);
    assert!(
        message.contains("robot.leg_max_mm") && message.contains("home"),
        "{message}"
    );
    let text = reference_text().replace("leg_min_mm = 650.0", "leg_min_mm = 900.0");
    let message = refused(&text);
    assert!(message.contains("robot.leg_min_mm"), "{message}");
}

#[test]
fn fewer_than_three_coded_points_is_refused() {
    let text = reference_text().replace("points_per_fixture = 6", "points_per_fixture = 2");
    let message = refused(&text);
    assert!(
        message.contains("camera.points_per_fixture") && message.contains("three"),
        "{message}"
    );
}

#[test]
fn non_finite_and_out_of_range_values_are_refused() {
    let text = reference_text().replace("position_mm = 5.0", "position_mm = nan");
    assert!(refused(&text).contains("steps.position_mm"));
    let text = reference_text().replace("dropout_probability = 0.02", "dropout_probability = 1.5");
    assert!(refused(&text).contains("camera.dropout_probability"));
    let text = reference_text().replace("gamma = 0.98", "gamma = 0.0");
    assert!(refused(&text).contains("reward.gamma"));
}

#[test]
fn missing_file_is_reported_with_its_path() {
    let error = CellConfig::load(Path::new("cells/nope.toml"))
        .unwrap_err()
        .to_string();
    assert!(error.contains("cells/nope.toml"), "{error}");
}

/// A cell file's `[rules]`: a rule switched off or tuned is read, changes the config hash (so an
/// evaluation under other rules is told apart), and a parameter out of range or an unknown rule
/// is refused by name; an empty section is today's rules and keeps the hash.
#[test]
fn a_cell_files_rules_are_read_and_change_its_hash_only_when_they_differ() {
    use assembly_cell::policy::shield::RuleId;
    let reference = CellConfig::parse(&reference_text(), "phi170.toml").unwrap();
    let empty = CellConfig::parse(&format!("{}\n[rules]\n", reference_text()), "x").unwrap();
    assert_eq!(empty.config_hash(), reference.config_hash());
    let off = format!("{}\n[rules.full_step]\nenabled = false\n", reference_text());
    let off = CellConfig::parse(&off, "x").unwrap();
    assert!(!off.rules.is_on(RuleId::FullStep));
    assert_eq!(off.rules.enabled().len(), 13);
    assert_ne!(off.config_hash(), reference.config_hash());
    let wide = format!(
        "{}\n[rules.full_step]\nfrom_share = 2.0\n",
        reference_text()
    );
    let message = refused(&wide);
    assert!(message.contains("rules.full_step.from_share"), "{message}");
    let unknown = format!(
        "{}\n[rules.full_stepp]\nenabled = false\n",
        reference_text()
    );
    assert!(refused(&unknown).contains("full_stepp"));
}
