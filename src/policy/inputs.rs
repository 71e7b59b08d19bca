//! What a learned policy's network reads: twelve numbers made from an observation.
//!
//! A policy file says which twelve (`__metadata__["inputs"]`, docs/design.md §6):
//!
//! - **absolute** (format version 1): the paper's state `[A1..A6, Px, Py, Pz, Ox, Oy, Oz]`.
//!   A1..A6 is where the robot carries {M} in the world, and P_z is measured from the seated
//!   pose, so a policy learnt on one cell reads another robot, camera placement or bore depth
//!   as states it has never seen.
//! - **cell-relative** (format version 2): the same pose relative to the goal, with the depth
//!   measured from the bore's entrance, beside the numbers of the cell that change what a good
//!   move is:
//!
//! | slot | cell-relative input |
//! |---|---|
//! | 0 | P_z: how far the shaft is from seated (mm, negative above) |
//! | 1 | the bore's depth (mm) |
//! | 2 | the radial clearance (mm) |
//! | 3 | the hole pitch (deg) |
//! | 4, 5 | P_x, P_y in radial clearances, within ±10 |
//! | 6, 7 | P_x, P_y (mm) |
//! | 8 | the tip's depth below the entrance, P_z + depth (mm, negative above) |
//! | 9, 10, 11 | O_x, O_y, O_z (deg) |
//!
//! In the bore what matters is how much of the clearance the shaft uses, a few hundredths of a
//! millimetre on one cell and a tenth on another: slots 4 and 5 say it in the cell's own unit.
//! The estimate's σ is not an input: as one, it stood in for the demonstrator's count of holds
//! and the sideways moves followed it instead of the pose
//! (docs/experiments/2026-11-25-5277d5a-cell-relative-inputs-and-randomised-cells.md).
//!
//! Slots 6–11 keep their places and units, so the training code that reads P and O from them
//! (the goal-centred normaliser, the insertion weighting of behaviour cloning) works on both,
//! with the entrance at slot 8 = 0 instead of −depth.

use crate::config::cell::CellConfig;
use crate::sim::Observation;
use std::collections::BTreeMap;

/// Slots 4 and 5 (the sideways error in clearances) stop here: beyond it the shaft is
/// plainly outside the bore, and slots 6 and 7 say where.
const MAX_CLEARANCES: f64 = 10.0;

/// The `__metadata__` key that names a policy's inputs.
pub const INPUTS_KEY: &str = "inputs";

/// Which twelve numbers a policy reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum PolicyInputs {
    /// The paper's state (format version 1).
    #[default]
    Absolute,
    /// The pose relative to the goal and the entrance, with the cell's shape (format
    /// version 2).
    CellRelative,
}

impl PolicyInputs {
    pub const ALL: [PolicyInputs; 2] = [PolicyInputs::Absolute, PolicyInputs::CellRelative];

    /// The name in a policy file's metadata and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            PolicyInputs::Absolute => "absolute",
            PolicyInputs::CellRelative => "cell-relative",
        }
    }

    pub fn parse(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|inputs| inputs.name() == name)
    }

    /// The policy file format version that carries these inputs.
    pub fn format_version(self) -> &'static str {
        match self {
            PolicyInputs::Absolute => "1",
            PolicyInputs::CellRelative => "2",
        }
    }

    /// Marks `metadata` (as `standard_metadata` writes it, version 1) for these inputs: a
    /// cell-relative policy is a version 2 file that names its inputs; an absolute one stays
    /// a version 1 file, byte for byte as before.
    pub fn mark(self, metadata: &mut BTreeMap<String, String>) {
        if self == PolicyInputs::CellRelative {
            metadata.insert("format_version".into(), self.format_version().into());
            metadata.insert(INPUTS_KEY.into(), self.name().into());
        }
    }

    /// The twelve numbers the network reads for `observation`.
    pub fn of(self, observation: &Observation) -> [f64; 12] {
        let s = &observation.state;
        match self {
            PolicyInputs::Absolute => *s,
            PolicyInputs::CellRelative => {
                let cell = &observation.cell;
                let in_clearances = |mm: f64| {
                    (mm / cell.radial_clearance_mm).clamp(-MAX_CLEARANCES, MAX_CLEARANCES)
                };
                [
                    s[8],
                    cell.bore_depth_mm,
                    cell.radial_clearance_mm,
                    cell.hole_pitch_deg,
                    in_clearances(s[6]),
                    in_clearances(s[7]),
                    s[6],
                    s[7],
                    s[8] + cell.bore_depth_mm,
                    s[9],
                    s[10],
                    s[11],
                ]
            }
        }
    }

    /// Slot 8's value with the tip at the bore's entrance on `cell`.
    pub fn entrance_input_mm(self, cell: &CellConfig) -> f64 {
        match self {
            PolicyInputs::Absolute => -cell.shaft.engaged_length_mm,
            PolicyInputs::CellRelative => 0.0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::{AssemblyEnv, EnvOptions};

    #[test]
    fn cell_relative_inputs_put_the_entrance_at_zero_on_every_cell() {
        for text in [
            include_str!("../../cells/phi170.toml"),
            include_str!("../../cells/phi100-deep.toml"),
        ] {
            let cell = CellConfig::parse(text, "cell").unwrap();
            let mut env = AssemblyEnv::new(&cell, EnvOptions::from_cell(&cell));
            let observation = env.reset(3).unwrap();
            let absolute = PolicyInputs::Absolute.of(&observation);
            let relative = PolicyInputs::CellRelative.of(&observation);
            assert_eq!(absolute, observation.state);
            let depth = cell.shaft.engaged_length_mm;
            // The tip's depth below the entrance and the distance from seated differ by the
            // bore's depth, and each is at its reference where the cell says.
            assert_eq!(relative[0], absolute[8]);
            assert!((relative[8] - relative[0] - depth).abs() < 1e-9);
            assert_eq!(
                absolute[8] - PolicyInputs::Absolute.entrance_input_mm(&cell),
                relative[8] - PolicyInputs::CellRelative.entrance_input_mm(&cell)
            );
            assert_eq!(&relative[6..8], &absolute[6..8]);
            assert_eq!(&relative[9..], &absolute[9..]);
            assert_eq!(relative[1], depth);
            assert!((relative[2] - cell.radial_clearance_mm()).abs() < 1e-12);
            assert!((relative[3] - 360.0 / f64::from(cell.bore.holes)).abs() < 1e-12);
            let clearance = cell.radial_clearance_mm();
            for (slot, p) in [(4, absolute[6]), (5, absolute[7])] {
                let expected = (p / clearance).clamp(-10.0, 10.0);
                assert!((relative[slot] - expected).abs() < 1e-9);
            }
        }
    }

    #[test]
    fn names_round_trip_and_only_cell_relative_files_change_version() {
        for inputs in PolicyInputs::ALL {
            assert_eq!(PolicyInputs::parse(inputs.name()), Some(inputs));
        }
        assert_eq!(PolicyInputs::parse("relative"), None);
        let mut v1 = BTreeMap::from([("format_version".to_string(), "1".to_string())]);
        let before = v1.clone();
        PolicyInputs::Absolute.mark(&mut v1);
        assert_eq!(v1, before);
        PolicyInputs::CellRelative.mark(&mut v1);
        assert_eq!(v1["format_version"], "2");
        assert_eq!(v1[INPUTS_KEY], "cell-relative");
    }
}
