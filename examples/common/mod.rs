//! What the measuring examples share: reading their positional arguments, and the zones they
//! count steps in.

// Each example uses what it needs of this module.
#![allow(dead_code)]

/// Positional argument `index` (1 is the first), or `default` when it is not given; an error
/// naming it when it is given but does not parse.
pub fn arg<T: std::str::FromStr>(index: usize, default: T) -> anyhow::Result<T> {
    match std::env::args().nth(index) {
        None => Ok(default),
        Some(text) => text.parse().map_err(|_| {
            anyhow::anyhow!(
                "argument {index}, {text:?}, is not a {}",
                std::any::type_name::<T>()
            )
        }),
    }
}

/// Comma-separated evaluation seeds, such as `10,11,12`.
pub fn seeds(text: &str) -> anyhow::Result<Vec<u64>> {
    text.split(',')
        .map(|s| {
            s.trim()
                .parse()
                .map_err(|_| anyhow::anyhow!("seed {s:?} is not a whole number"))
        })
        .collect()
}

/// Where the tip is by the estimate, as the examples count steps: `far` more than 5 mm above
/// the bore's entrance, `entrance` within 5 mm of it, `bore` more than 0.2 mm in.
pub fn zone(observation: &assembly_cell::sim::Observation) -> &'static str {
    match observation.insertion_mm() {
        inserted_mm if inserted_mm > 0.2 => "bore",
        inserted_mm if inserted_mm > -5.0 => "entrance",
        _ => "far",
    }
}
