//! The research diagnostics, one binary: `cargo run --release -p cell-research -- NAME ARGS`
//! runs program NAME (`src/programs/NAME.rs`, whose doc comment says what it measures and
//! what its arguments are). One binary rather than one a program: each links the whole cell
//! library, and building a dozen of them was most of this crate's build.

mod programs {
    pub mod after_an_uncertain_refusal;
    pub mod camera_goals;
    pub mod certainty_gate;
    pub mod drawn_cell_failures;
    pub mod failure_trace;
    pub mod paired_failures;
    pub mod robot_changed;
    pub mod shift_watch;
    pub mod still_frames;
    pub mod teacher_in_the_zone;
    pub mod what_the_network_decides;
    pub mod where_the_steps_go;
}

/// A program's entry point.
type Program = fn() -> anyhow::Result<()>;

/// Each program's name and its entry point.
const PROGRAMS: &[(&str, Program)] = &[
    (
        "after_an_uncertain_refusal",
        programs::after_an_uncertain_refusal::main,
    ),
    ("camera_goals", programs::camera_goals::main),
    ("certainty_gate", programs::certainty_gate::main),
    ("drawn_cell_failures", programs::drawn_cell_failures::main),
    ("failure_trace", programs::failure_trace::main),
    ("paired_failures", programs::paired_failures::main),
    ("robot_changed", programs::robot_changed::main),
    ("shift_watch", programs::shift_watch::main),
    ("still_frames", || {
        programs::still_frames::main();
        Ok(())
    }),
    ("teacher_in_the_zone", programs::teacher_in_the_zone::main),
    (
        "what_the_network_decides",
        programs::what_the_network_decides::main,
    ),
    ("where_the_steps_go", programs::where_the_steps_go::main),
];

fn main() -> anyhow::Result<()> {
    let name = std::env::args().nth(1).unwrap_or_default();
    match PROGRAMS.iter().find(|(program, _)| *program == name) {
        Some((_, run)) => run(),
        None => {
            let names: Vec<&str> = PROGRAMS.iter().map(|(program, _)| *program).collect();
            anyhow::bail!(
                "no program {name:?}; run one of: {} (README.md says what each measures)",
                names.join(", ")
            )
        }
    }
}
