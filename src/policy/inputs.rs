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
//! - **cell-scaled** (format version 2): the cell-relative inputs with the tilt in the cell's
//!   own unit. Slot 3 holds the unit u (below), slots 9 and 10 hold O_x / u and O_y / u, and
//!   the orientation actor's x and y outputs are in the same unit: its move about x and y is
//!   multiplied by u ([`PolicyInputs::move_from_units`]).
//!
//! The tilt a cell takes is the tilt at which the seated shaft would touch the supervisor's
//! wall margin (`CellShape::clearance_tilt_deg`): 0.029° on the reference cell, 0.0057° on a
//! Φ100 bore 100 mm deep with 0.03 mm of clearance. The unit u is that tilt over the reference
//! cell's, at most 1: on the reference cell and on looser ones the inputs and moves are in
//! degrees, and on a deep, tight cell a tilt that matters there reads as large as one that
//! matters on the reference cell. With the tilt in degrees, an orientation actor learnt
//! across cells answered the 0.004° that a Φ100 bore 100 mm deep could not take with no move
//! at all, and held there until the step limit
//! (docs/experiments/2026-11-27-15ddca6-tilt-in-the-cells-unit.md). The hole pitch is not
//! needed: the roll error O_z is already the offset to the nearest hole.
//!
//! Slots 6–11 keep their places, and their units but for the cell-scaled tilt, so the training
//! code that reads P and O from them (the goal-centred normaliser, the insertion weighting of
//! behaviour cloning) works on all three, with the entrance at slot 8 = 0 instead of −depth;
//! the normaliser's tilt σ of 0.03 is then in the cell's unit.

use crate::config::cell::{CellConfig, CellShape};
use crate::sim::Observation;
use std::collections::BTreeMap;

/// The reference cell's clearance tilt (deg): (0.05 − 0.02) mm over 60 mm. A cell-scaled
/// policy measures a tighter cell's tilt in units of its clearance tilt over this one.
const REFERENCE_CLEARANCE_TILT_DEG: f64 = 0.028_647_887_369_217_37;

/// The slot of cell-scaled inputs that holds the tilt unit.
const TILT_UNIT_SLOT: usize = 3;

/// The smallest tilt unit: a cell whose clearance tilt is a twentieth of the reference cell's
/// or less (the clearance all but taken by the wall margin) reads its tilt at this unit.
const MIN_TILT_UNIT: f64 = 0.05;

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
    /// The cell-relative inputs with the tilt, and the orientation actor's tilting moves, in
    /// the cell's own unit (format version 2).
    CellScaled,
}

impl PolicyInputs {
    pub const ALL: [PolicyInputs; 3] = [
        PolicyInputs::Absolute,
        PolicyInputs::CellRelative,
        PolicyInputs::CellScaled,
    ];

    /// The name in a policy file's metadata and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            PolicyInputs::Absolute => "absolute",
            PolicyInputs::CellRelative => "cell-relative",
            PolicyInputs::CellScaled => "cell-scaled",
        }
    }

    /// Whether the policy reads the cell it is on (every input but the paper's state).
    pub fn reads_the_cell(self) -> bool {
        self != PolicyInputs::Absolute
    }

    pub fn parse(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|inputs| inputs.name() == name)
    }

    /// The policy file format version that carries these inputs.
    pub fn format_version(self) -> &'static str {
        match self {
            PolicyInputs::Absolute => "1",
            PolicyInputs::CellRelative | PolicyInputs::CellScaled => "2",
        }
    }

    /// Marks `metadata` (as `standard_metadata` writes it, version 1) for these inputs: a
    /// policy that reads the cell is a version 2 file that names its inputs; an absolute one
    /// stays a version 1 file, byte for byte as before.
    pub fn mark(self, metadata: &mut BTreeMap<String, String>) {
        if self.reads_the_cell() {
            metadata.insert("format_version".into(), self.format_version().into());
            metadata.insert(INPUTS_KEY.into(), self.name().into());
        }
    }

    /// The twelve numbers the network reads for `observation`.
    pub fn of(self, observation: &Observation) -> [f64; 12] {
        let s = &observation.state;
        match self {
            PolicyInputs::Absolute => *s,
            PolicyInputs::CellRelative => cell_relative(s, &observation.cell),
            PolicyInputs::CellScaled => {
                let mut inputs = cell_relative(s, &observation.cell);
                let unit = tilt_unit(&observation.cell);
                inputs[TILT_UNIT_SLOT] = unit;
                inputs[9] /= unit;
                inputs[10] /= unit;
                inputs
            }
        }
    }

    /// The unit (deg) of the orientation actor's tilt about x and y, read from `inputs` (as
    /// [`PolicyInputs::of`] makes them): 1 but for cell-scaled inputs.
    pub fn tilt_unit_deg(self, inputs: &[f64; 12]) -> f64 {
        match self {
            PolicyInputs::CellScaled => inputs[TILT_UNIT_SLOT],
            PolicyInputs::Absolute | PolicyInputs::CellRelative => 1.0,
        }
    }

    /// A move `[Δx, Δy, Δz, θx, θy, θz]` (mm, deg) in the network's units: θx, θy over the
    /// tilt unit of `inputs`.
    pub fn move_in_units(self, inputs: &[f64; 12], mut action: [f64; 6]) -> [f64; 6] {
        let unit = self.tilt_unit_deg(inputs);
        action[3] /= unit;
        action[4] /= unit;
        action
    }

    /// The move (mm, deg) that `action`, in the network's units, stands for on the cell of
    /// `inputs`: the inverse of [`PolicyInputs::move_in_units`].
    pub fn move_from_units(self, inputs: &[f64; 12], mut action: [f64; 6]) -> [f64; 6] {
        let unit = self.tilt_unit_deg(inputs);
        action[3] *= unit;
        action[4] *= unit;
        action
    }

    /// Slot 8's value with the tip at the bore's entrance on `cell`.
    pub fn entrance_input_mm(self, cell: &CellConfig) -> f64 {
        match self {
            PolicyInputs::Absolute => -cell.shaft.engaged_length_mm,
            PolicyInputs::CellRelative | PolicyInputs::CellScaled => 0.0,
        }
    }
}

/// The cell-relative inputs of the paper's state `s` on `cell` (the table above).
fn cell_relative(s: &[f64; 12], cell: &CellShape) -> [f64; 12] {
    let in_clearances =
        |mm: f64| (mm / cell.radial_clearance_mm).clamp(-MAX_CLEARANCES, MAX_CLEARANCES);
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

/// The unit (deg) of a cell-scaled policy's tilt on `cell`: its clearance tilt over the
/// reference cell's, at most 1.
fn tilt_unit(cell: &CellShape) -> f64 {
    (cell.clearance_tilt_deg() / REFERENCE_CLEARANCE_TILT_DEG).clamp(MIN_TILT_UNIT, 1.0)
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
    fn cell_scaled_inputs_read_the_tilt_in_the_cells_unit() {
        // By hand: the reference cell's clearance tilt is atan(0.03 / 60) = 0.028648°, its
        // unit 1; phi100-deep's is atan(0.01 / 100) = 0.0057296°, its unit 0.2; a looser cell
        // than the reference stays at 1.
        for (text, unit) in [
            (include_str!("../../cells/phi170.toml"), 1.0),
            (include_str!("../../cells/phi100-deep.toml"), 0.2),
            (include_str!("../../cells/phi250-shallow.toml"), 1.0),
        ] {
            let cell = CellConfig::parse(text, "cell").unwrap();
            let mut env = AssemblyEnv::new(&cell, EnvOptions::from_cell(&cell));
            let observation = env.reset(5).unwrap();
            let relative = PolicyInputs::CellRelative.of(&observation);
            let scaled = PolicyInputs::CellScaled.of(&observation);
            assert!(
                (scaled[3] - unit).abs() < 1e-4,
                "{}: {}",
                cell.name,
                scaled[3]
            );
            assert_eq!(PolicyInputs::CellScaled.tilt_unit_deg(&scaled), scaled[3]);
            assert_eq!(PolicyInputs::CellRelative.tilt_unit_deg(&relative), 1.0);
            for slot in [9, 10] {
                assert!((scaled[slot] * scaled[3] - relative[slot]).abs() < 1e-12);
            }
            let same = [0, 1, 2, 4, 5, 6, 7, 8, 11];
            assert!(same.iter().all(|&i| scaled[i] == relative[i]));
            // A move in the network's units and back: only the tilt about x and y changes.
            let action = [1.0, -2.0, 3.0, 0.004, -0.002, 0.01];
            let in_units = PolicyInputs::CellScaled.move_in_units(&scaled, action);
            assert!((in_units[3] - 0.004 / scaled[3]).abs() < 1e-12);
            assert_eq!((&in_units[..3], in_units[5]), (&action[..3], action[5]));
            let back = PolicyInputs::CellScaled.move_from_units(&scaled, in_units);
            assert!(back.iter().zip(action).all(|(a, b)| (a - b).abs() < 1e-15));
        }
        let reference = CellConfig::reference().shape().clearance_tilt_deg();
        assert!((reference - REFERENCE_CLEARANCE_TILT_DEG).abs() < 1e-12);
    }

    #[test]
    fn names_round_trip_and_only_files_that_read_the_cell_change_version() {
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
        PolicyInputs::CellScaled.mark(&mut v1);
        assert_eq!(v1["format_version"], "2");
        assert_eq!(v1[INPUTS_KEY], "cell-scaled");
    }
}
