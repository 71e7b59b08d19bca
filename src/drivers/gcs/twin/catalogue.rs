//! What the twin's controller says about itself: its command list (`HLP?`), its parameter
//! table (`HPA?`, `SPA?`), its status register (`#4`). Clients such as PIPython learn from
//! `HLP?` which commands they may send, so every command listed here is answered and every
//! query not listed is refused with error 2.

use super::super::protocol::answer_lines;

/// The commands the twin answers, with PI's names for them: `HLP?`'s lines.
pub const COMMANDS: [(&str, &str); 40] = [
    ("#4", "Request Status Register"),
    ("#5", "Request Motion Status"),
    ("#7", "Request Controller Ready Status"),
    ("#24", "Stop All Axes"),
    ("*IDN?", "Get Device Identification"),
    ("CCL", "Set Command Level"),
    ("CCL?", "Get Command Level"),
    ("CST?", "Get Assignment Of Stages To Axes"),
    ("CSV?", "Get Current Syntax Version"),
    ("ERR?", "Get Error Number"),
    ("FRF", "Fast Reference Move To Reference Switch"),
    ("FRF?", "Get Referencing Result"),
    ("HLP?", "Get List Of Available Commands"),
    ("HLT", "Halt Motion Smoothly"),
    ("HPA?", "Get List Of Available Parameters"),
    ("KEN", "Enable Coordinate System"),
    ("KEN?", "Get Enabled Coordinate Systems"),
    ("KSD", "Define KSD Coordinate System"),
    ("MOV", "Set Target Position"),
    ("MOV?", "Get Target Position"),
    ("MVR", "Set Target Relative To Current Target"),
    ("ONT?", "Get On Target State"),
    ("POS?", "Get Real Position"),
    ("RON", "Set Reference Mode"),
    ("RON?", "Get Reference Mode"),
    ("SAI?", "Get List Of Current Axis Identifiers"),
    ("SPA", "Set Volatile Memory Parameters"),
    ("SPA?", "Get Volatile Memory Parameters"),
    ("SPI", "Set Pivot Point"),
    ("SPI?", "Get Pivot Point"),
    ("SSN?", "Get Device Serial Number"),
    ("STP", "Stop All Axes"),
    ("SVO", "Set Servo Mode"),
    ("SVO?", "Get Servo Mode"),
    ("TMN?", "Get Minimum Commandable Position"),
    ("TMX?", "Get Maximum Commandable Position"),
    ("VER?", "Get Versions Of Firmware And Drivers"),
    ("VLS", "Set System Velocity"),
    ("VLS?", "Get System Velocity"),
    ("VMO?", "Virtual Move"),
];

/// `HLP?`'s answer: a heading line, one line per command, a closing line (PIPython drops the
/// first and the last). The twin's own `EPISODE` is listed too.
pub fn help() -> String {
    let mut lines = vec!["The following commands are valid:".to_string()];
    lines.extend(COMMANDS.iter().map(|(name, what)| format!("{name} {what}")));
    lines.push(format!(
        "{} Draw A New Episode Of The Twin (SEED OFFSET_MM ORIENTATION_DEG)",
        super::EPISODE
    ));
    lines.push("end of help".into());
    answer_lines(&lines)
}

/// A parameter of each axis, as `HPA?` lists it and `SPA?` reads it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Parameter {
    /// 0x15: the axis's highest position (`TMX?`).
    MaxTravelPositive,
    /// 0x30: the axis's lowest position (`TMN?`).
    MaxTravelNegative,
    /// 0x3C: the stage's name (`CST?`).
    StageName,
}

impl Parameter {
    /// In the order `HPA?` and `SPA?` write them.
    pub const ALL: [Parameter; 3] = [
        Parameter::MaxTravelPositive,
        Parameter::MaxTravelNegative,
        Parameter::StageName,
    ];

    /// PI's parameter id.
    pub fn id(self) -> u32 {
        match self {
            Parameter::MaxTravelPositive => 0x15,
            Parameter::MaxTravelNegative => 0x30,
            Parameter::StageName => 0x3C,
        }
    }

    /// A parameter id as a command writes it: hex (`0x15`) or decimal (`21`).
    pub fn parse(text: &str) -> Option<Parameter> {
        let id = match text.get(..2) {
            Some("0x" | "0X") => u32::from_str_radix(&text[2..], 16).ok()?,
            _ => text.parse().ok()?,
        };
        Parameter::ALL.into_iter().find(|p| p.id() == id)
    }

    fn describe(self) -> (&'static str, &'static str) {
        match self {
            Parameter::MaxTravelPositive => {
                ("FLOAT", "Maximum Travel In Positive Direction (Phys. Unit)")
            }
            Parameter::MaxTravelNegative => {
                ("FLOAT", "Maximum Travel In Negative Direction (Phys. Unit)")
            }
            Parameter::StageName => ("CHAR", "Stage Name"),
        }
    }
}

/// `HPA?`'s answer: `ID=` then, tab-separated, the command level that may write it, how many
/// items have it (the six axes), its type, its group and its name.
pub fn parameter_help() -> String {
    let mut lines = vec!["The following parameters are valid:".to_string()];
    lines.extend(Parameter::ALL.iter().map(|p| {
        let (kind, name) = p.describe();
        format!("0x{:X}=\t1\t6\t{kind}\ttwin\t{name}", p.id())
    }));
    lines.push("end of help".into());
    answer_lines(&lines)
}

/// `#4`'s bits, as PI's controllers lay out their status register. Bit 14 (referencing) stays
/// 0: the twin references at once; bits 0 to 2 (limit and reference switches) too: it has none.
pub mod status {
    pub const ERROR: u32 = 1 << 8;
    pub const SERVO_ON: u32 = 1 << 12;
    pub const IN_MOTION: u32 = 1 << 13;
    pub const ON_TARGET: u32 = 1 << 15;
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_help_is_a_gcs_answer_pipython_can_split() {
        let help = help();
        let lines: Vec<&str> = help.lines().collect();
        assert_eq!(lines.len(), COMMANDS.len() + 3);
        assert!(lines[..lines.len() - 1].iter().all(|l| l.ends_with(' ')));
        assert!(help.ends_with("end of help\n"));
        // Each line between the first and the last starts with a command and no '='.
        for line in &lines[1..lines.len() - 1] {
            assert!(!line.contains('='), "{line}");
            assert!(!line.starts_with(' '), "{line}");
        }
        assert!(lines.contains(&"HLP? Get List Of Available Commands "));
    }

    #[test]
    fn parameters_are_found_by_their_ids_in_hex_or_decimal() {
        assert_eq!(Parameter::parse("0x15"), Some(Parameter::MaxTravelPositive));
        assert_eq!(Parameter::parse("0X3c"), Some(Parameter::StageName));
        assert_eq!(Parameter::parse("48"), Some(Parameter::MaxTravelNegative));
        assert_eq!(Parameter::parse("0x16"), None);
        assert_eq!(Parameter::parse("x"), None);
        let table = parameter_help();
        assert!(table.contains("\n0x30=\t1\t6\tFLOAT\t"), "{table}");
        // PIPython reads the type as the fourth whitespace-separated word.
        let line = table.lines().nth(1).unwrap();
        assert_eq!(line.split_whitespace().nth(3), Some("FLOAT"));
    }
}
