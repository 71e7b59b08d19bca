//! The research diagnostics' shared code: reading their positional arguments, the
//! controllers they name, the zones they count steps in, and two controllers' failures paired
//! episode by episode ([`paired`]). The programs are in `src/programs/`, run by name through
//! the one binary, `src/main.rs` (README.md lists them).

pub mod paired;

/// The command line as the program named by the first argument sees it: its own arguments
/// after the binary's path, as if it were a binary of its own.
pub fn args() -> impl Iterator<Item = String> {
    let mut all = std::env::args();
    let binary = all.next();
    all.next(); // the program's name
    binary.into_iter().chain(all)
}

/// Positional argument `index` (1 is the first) of the program, or `default` when it is not
/// given; an error naming it when it is given but does not parse.
pub fn arg<T: std::str::FromStr>(index: usize, default: T) -> anyhow::Result<T> {
    match args().nth(index) {
        None => Ok(default),
        Some(text) => text.parse().map_err(|_| {
            anyhow::anyhow!(
                "argument {index}, {text:?}, is not a {}",
                std::any::type_name::<T>()
            )
        }),
    }
}

/// Comma-separated evaluation seeds, each a seed or an inclusive range: `10,11,12` or
/// `10-12`.
pub fn seeds(text: &str) -> anyhow::Result<Vec<u64>> {
    let seed = |s: &str| {
        s.trim()
            .parse::<u64>()
            .map_err(|_| anyhow::anyhow!("seed {s:?} is not a whole number"))
    };
    let mut seeds = Vec::new();
    for part in text.split(',') {
        match part.split_once('-') {
            Some((first, last)) => seeds.extend(seed(first)?..=seed(last)?),
            None => seeds.push(seed(part)?),
        }
    }
    Ok(seeds)
}

/// A built-in controller by name, or a policy file (`.safetensors`).
pub fn controller_factory(
    name: &str,
    cell: &assembly_cell::config::cell::CellConfig,
) -> anyhow::Result<assembly_cell::policy::ControllerFactory> {
    use assembly_cell::policy::{self, Controller};
    if name.ends_with(".safetensors") {
        let learned = policy::learned::LearnedPolicy::from_path(name)?;
        Ok(Box::new(move || {
            Box::new(learned.clone()) as Box<dyn Controller>
        }))
    } else {
        Ok(policy::builtin_factory(name, cell)?)
    }
}

/// Where the tip is by the estimate, as the diagnostics count steps: `far` more than 5 mm above
/// the bore's entrance, `entrance` within 5 mm of it, `bore` more than 0.2 mm in.
pub fn zone(observation: &assembly_cell::sim::Observation) -> &'static str {
    match observation.insertion_mm() {
        inserted_mm if inserted_mm > 0.2 => "bore",
        inserted_mm if inserted_mm > -5.0 => "entrance",
        _ => "far",
    }
}
