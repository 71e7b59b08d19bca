//! GCS 2.0 text protocol, pure: commands as the controller reads them, answers as it writes
//! them, and the platform pose as its six axes.
//!
//! A command is one line: the mnemonic, then its arguments separated by spaces, ended by LF
//! (`MOV X 1.5 Y -2`). A query's mnemonic ends in `?`. An answer is one or more lines; every
//! line but the last ends in `" \n"` (a space before the LF), the last in `"\n"`. Axis
//! answers read `X=1.5`. The hexapod's axes are X, Y, Z (mm) and U, V, W (deg, rotations about
//! X, Y and Z); the pivot point's coordinates are R, S, T (mm).

use crate::geometry::Pose;
use nalgebra::{Translation3, UnitQuaternion};

/// The hexapod's six motion axes, in the order of a pose array: X Y Z in mm, U V W in deg.
pub const AXES: [&str; 6] = ["X", "Y", "Z", "U", "V", "W"];

/// The pivot point's coordinates, mm.
pub const PIVOT_AXES: [&str; 3] = ["R", "S", "T"];

/// The platform pose as X Y Z (mm) and U V W (deg). The rotation is `Rz(W)·Ry(V)·Rx(U)`:
/// U about X first, then V about Y, then W about Z, all about the fixed axes.
pub fn pose_to_axes(pose: &Pose) -> [f64; 6] {
    let t = pose.translation.vector;
    let (u, v, w) = pose.rotation.euler_angles();
    [
        t.x,
        t.y,
        t.z,
        u.to_degrees(),
        v.to_degrees(),
        w.to_degrees(),
    ]
}

/// The pose of axis values X Y Z (mm) U V W (deg) (the inverse of [`pose_to_axes`]).
pub fn axes_to_pose(axes: &[f64; 6]) -> Pose {
    Pose::from_parts(
        Translation3::new(axes[0], axes[1], axes[2]),
        UnitQuaternion::from_euler_angles(
            axes[3].to_radians(),
            axes[4].to_radians(),
            axes[5].to_radians(),
        ),
    )
}

/// `name` with its axis–value pairs, as one command line: `MOV X 1.5 Y -2\n`. Values are
/// written in Rust's shortest form that reads back to the same `f64`.
pub fn command_with_values(name: &str, axes: &[&str], values: &[f64]) -> String {
    let mut line = String::from(name);
    for (axis, value) in axes.iter().zip(values) {
        line.push(' ');
        line.push_str(axis);
        line.push(' ');
        line.push_str(&value.to_string());
    }
    line.push('\n');
    line
}

/// Whether `buffer` holds a whole answer: it ends in LF without a space before it (or is one
/// control character, the answer to a single-character command).
pub fn answer_complete(buffer: &[u8]) -> bool {
    match buffer {
        [] => false,
        [only] => *only < 32,
        [.., before, last] => *last == b'\n' && *before != b' ',
    }
}

/// An answer of several lines, as the controller writes it: `" \n"` after each line but the
/// last, `"\n"` after the last.
pub fn answer_lines<S: AsRef<str>>(lines: &[S]) -> String {
    let mut answer = String::new();
    for (k, line) in lines.iter().enumerate() {
        answer.push_str(line.as_ref());
        answer.push_str(if k + 1 == lines.len() { "\n" } else { " \n" });
    }
    answer
}

/// Why an answer could not be read.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum AnswerError {
    #[error("no value for axis {axis}")]
    MissingAxis { axis: &'static str },
    #[error("`{text}` is not a number")]
    NotANumber { text: String },
    #[error("the line `{line}` is not `AXIS=VALUE`")]
    Malformed { line: String },
}

/// The `AXIS=VALUE` pairs of an answer, in the order given.
pub fn axis_pairs(answer: &str) -> Result<Vec<(&str, &str)>, AnswerError> {
    answer
        .lines()
        .map(str::trim)
        .filter(|line| !line.is_empty())
        .map(|line| {
            line.split_once('=')
                .map(|(axis, value)| (axis.trim(), value.trim()))
                .ok_or_else(|| AnswerError::Malformed { line: line.into() })
        })
        .collect()
}

/// The values an answer gives the `axes` (in their order), other axes ignored.
pub fn axis_values<const N: usize>(
    answer: &str,
    axes: &[&'static str; N],
) -> Result<[f64; N], AnswerError> {
    let pairs = axis_pairs(answer)?;
    let mut values = [0.0; N];
    for (value, axis) in values.iter_mut().zip(axes) {
        let (_, text) = pairs
            .iter()
            .find(|(name, _)| name == axis)
            .ok_or(AnswerError::MissingAxis { axis })?;
        *value = parse_number(text)?;
    }
    Ok(values)
}

/// The flags (`1`/`0`) an answer gives the six motion axes (`ONT?`, `SVO?`, `FRF?`).
pub fn axis_flags(answer: &str) -> Result<[bool; 6], AnswerError> {
    Ok(axis_values(answer, &AXES)?.map(|v| v != 0.0))
}

/// A number as the controller writes it.
pub fn parse_number(text: &str) -> Result<f64, AnswerError> {
    text.trim()
        .parse::<f64>()
        .ok()
        .filter(|v| v.is_finite())
        .ok_or_else(|| AnswerError::NotANumber { text: text.into() })
}

/// One command as the controller reads it: the mnemonic (upper case) and its arguments.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Request<'a> {
    pub mnemonic: String,
    pub args: Vec<&'a str>,
}

impl<'a> Request<'a> {
    /// A command line without its LF; `None` for an empty line.
    pub fn parse(line: &'a str) -> Option<Request<'a>> {
        let mut words = line.split_whitespace();
        let mnemonic = words.next()?.to_ascii_uppercase();
        Some(Request {
            mnemonic,
            args: words.collect(),
        })
    }

    /// The arguments as axis–value pairs (`X 1.5 Y 2`); `None` when they are not.
    pub fn pairs(&self) -> Option<Vec<(&'a str, &'a str)>> {
        if self.args.is_empty() || !self.args.len().is_multiple_of(2) {
            return None;
        }
        Some(self.args.chunks(2).map(|p| (p[0], p[1])).collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    #[test]
    fn a_pose_survives_the_axes_and_back() {
        let pose = crate::geometry::pose::pose_from_mm_deg(
            Vector3::new(1.25, -3.5, 412.0),
            Vector3::new(0.7, -1.1, 12.0),
        );
        let back = axes_to_pose(&pose_to_axes(&pose));
        assert!((back.translation.vector - pose.translation.vector).norm() < 1e-12);
        assert!(back.rotation.angle_to(&pose.rotation) < 1e-12);
        let axes = pose_to_axes(&Pose::translation(1.0, 2.0, 3.0));
        assert_eq!(axes, [1.0, 2.0, 3.0, 0.0, 0.0, 0.0]);
        // U alone is a rotation about X.
        let u = axes_to_pose(&[0.0, 0.0, 0.0, 90.0, 0.0, 0.0]);
        let y = u.rotation * Vector3::y();
        assert!((y - Vector3::z()).norm() < 1e-12, "{y}");
    }

    #[test]
    fn commands_and_answers_are_written_as_the_controller_expects() {
        assert_eq!(
            command_with_values("MOV", &["X", "W"], &[1.5, -0.1]),
            "MOV X 1.5 W -0.1\n"
        );
        assert_eq!(answer_lines(&["X=1", "Y=0"]), "X=1 \nY=0\n");
        assert!(answer_complete(b"X=1 \nY=0\n"));
        assert!(!answer_complete(b"X=1 \n"));
        assert!(!answer_complete(b"X=1"));
        assert!(answer_complete(&[0xB1, b'\n']));
        assert!(answer_complete(b"\x06"));
        assert!(!answer_complete(b""));
    }

    #[test]
    fn axis_answers_are_read_and_bad_ones_named() {
        let answer = "X=1.5 \nY=-2 \nZ=400 \nU=0 \nV=0.25 \nW=1e-3\n";
        assert_eq!(
            axis_values(answer, &AXES),
            Ok([1.5, -2.0, 400.0, 0.0, 0.25, 1e-3])
        );
        assert_eq!(
            axis_flags("X=1 \nY=1 \nZ=1 \nU=1 \nV=0 \nW=1\n"),
            Ok([true, true, true, true, false, true])
        );
        assert_eq!(
            axis_values("X=1\n", &AXES),
            Err(AnswerError::MissingAxis { axis: "Y" })
        );
        assert_eq!(
            axis_values("X=abc\n", &["X"]),
            Err(AnswerError::NotANumber { text: "abc".into() })
        );
        assert_eq!(
            axis_values("X=nan\n", &["X"]),
            Err(AnswerError::NotANumber { text: "nan".into() })
        );
        assert_eq!(
            axis_pairs("garbage\n"),
            Err(AnswerError::Malformed {
                line: "garbage".into()
            })
        );
    }

    #[test]
    fn requests_split_into_mnemonic_and_pairs() {
        let request = Request::parse("mov X 1 Y 2").unwrap();
        assert_eq!(request.mnemonic, "MOV");
        assert_eq!(request.pairs(), Some(vec![("X", "1"), ("Y", "2")]));
        assert_eq!(Request::parse("MOV X").unwrap().pairs(), None);
        assert_eq!(Request::parse("   "), None);
    }
}
