//! The fixtures' coded points from a calibration file (a photogrammetry report's export): each
//! point's id, its coordinates in its fixture's frame and, if the report gives it, their σ.
//!
//! The file is CSV (docs/integration.md, "Fixture layouts"): a header line naming the columns
//! `fixture,id,x_mm,y_mm,z_mm` and optionally `sigma_mm`, then one line per point. `fixture` is
//! `C1` (on Segment I) or `C2` (on Segment II); `id` the number the camera names the point by
//! (0 to 65535); coordinates in mm in the fixture's frame {C1} or {C2}; `sigma_mm` the
//! calibration's σ per axis, mm (empty: not given). Blank lines and lines starting with `#`
//! are skipped; spaces around a value are ignored.

use crate::geometry::fit::{FitError, MAX_FIT_POINTS, MIN_FIT_POINTS, fit_frame};
use nalgebra::Point3;
use serde::Serialize;

/// One coded point of a calibrated fixture.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LayoutPoint {
    /// The id the camera names the point by.
    pub label: u16,
    /// Its coordinates in its fixture's frame, mm.
    pub position_mm: [f64; 3],
    /// The calibration's σ per axis, mm, when the report gives one.
    pub sigma_mm: Option<f64>,
}

/// Both fixtures' coded points, in the file's order.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FixtureLayout {
    pub c1: Vec<LayoutPoint>,
    pub c2: Vec<LayoutPoint>,
}

/// Why a calibration file was refused: the line, and the point, at fault.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LayoutError {
    #[error("no header line (`fixture,id,x_mm,y_mm,z_mm[,sigma_mm]`)")]
    NoHeader,
    #[error(
        "line {line}: the header is `{found}`, not `fixture,id,x_mm,y_mm,z_mm` with `sigma_mm` optional"
    )]
    Header { line: usize, found: String },
    #[error("line {line}: {found} values, {expected} expected (one per header column)")]
    Columns {
        line: usize,
        found: usize,
        expected: usize,
    },
    #[error("line {line}: `{column}` is `{value}`: {reason}")]
    Value {
        line: usize,
        column: &'static str,
        value: String,
        reason: &'static str,
    },
    #[error("line {line}: point {fixture} {label}: `{column}` is {value}, not a finite number")]
    NonFinite {
        line: usize,
        fixture: &'static str,
        label: u16,
        column: &'static str,
        value: f64,
    },
    #[error("line {line}: point {fixture} {label}: `sigma_mm` is {sigma}, must be 0 or more")]
    NegativeSigma {
        line: usize,
        fixture: &'static str,
        label: u16,
        sigma: f64,
    },
    #[error("line {line}: point {fixture} {label} again (first on line {first_line})")]
    Duplicate {
        line: usize,
        fixture: &'static str,
        label: u16,
        first_line: usize,
    },
    #[error("fixture {fixture}: {found} coded points, at least {needed} needed for a fit")]
    TooFew {
        fixture: &'static str,
        found: usize,
        needed: usize,
    },
    #[error("fixture {fixture}: {found} coded points, at most {max} supported")]
    TooMany {
        fixture: &'static str,
        found: usize,
        max: usize,
    },
    #[error("fixture {fixture}: its coded points are collinear, no frame can be fitted to them")]
    Collinear { fixture: &'static str },
}

const COLUMNS: [&str; 6] = ["fixture", "id", "x_mm", "y_mm", "z_mm", "sigma_mm"];

impl FixtureLayout {
    /// Parses and checks a calibration file's text.
    pub fn parse_csv(text: &str) -> Result<FixtureLayout, LayoutError> {
        let mut lines = text
            .lines()
            .enumerate()
            .map(|(k, line)| (k + 1, line.trim()))
            .filter(|(_, line)| !line.is_empty() && !line.starts_with('#'));
        let (line, header) = lines.next().ok_or(LayoutError::NoHeader)?;
        let names: Vec<&str> = header.split(',').map(str::trim).collect();
        let expected = names.len();
        if !(expected == 5 || expected == 6) || names[..] != COLUMNS[..expected] {
            return Err(LayoutError::Header {
                line,
                found: header.to_string(),
            });
        }
        let mut layout = FixtureLayout {
            c1: Vec::new(),
            c2: Vec::new(),
        };
        // (fixture, label) → the line it was first given on.
        let mut seen = std::collections::HashMap::new();
        for (line, text) in lines {
            let values: Vec<&str> = text.split(',').map(str::trim).collect();
            if values.len() != expected {
                return Err(LayoutError::Columns {
                    line,
                    found: values.len(),
                    expected,
                });
            }
            let value = |column: usize, reason| LayoutError::Value {
                line,
                column: COLUMNS[column],
                value: values[column].to_string(),
                reason,
            };
            let fixture = match values[0] {
                "C1" => "C1",
                "C2" => "C2",
                _ => return Err(value(0, "a fixture is C1 or C2")),
            };
            let label: u16 = values[1]
                .parse()
                .map_err(|_| value(1, "an id is a whole number from 0 to 65535"))?;
            let mut numbers = [0.0; 4];
            for (k, number) in numbers.iter_mut().enumerate().take(expected - 2) {
                let column = k + 2;
                if column == 5 && values[column].is_empty() {
                    *number = f64::NAN;
                    continue;
                }
                *number = values[column]
                    .parse()
                    .map_err(|_| value(column, "not a number"))?;
                if !number.is_finite() {
                    return Err(LayoutError::NonFinite {
                        line,
                        fixture,
                        label,
                        column: COLUMNS[column],
                        value: *number,
                    });
                }
            }
            let sigma_mm = (expected == 6 && !values[5].is_empty()).then_some(numbers[3]);
            if let Some(sigma) = sigma_mm.filter(|s| *s < 0.0) {
                return Err(LayoutError::NegativeSigma {
                    line,
                    fixture,
                    label,
                    sigma,
                });
            }
            if let Some(first_line) = seen.insert((fixture, label), line) {
                return Err(LayoutError::Duplicate {
                    line,
                    fixture,
                    label,
                    first_line,
                });
            }
            let point = LayoutPoint {
                label,
                position_mm: [numbers[0], numbers[1], numbers[2]],
                sigma_mm,
            };
            match fixture {
                "C1" => layout.c1.push(point),
                _ => layout.c2.push(point),
            }
        }
        for (fixture, points) in [("C1", &layout.c1), ("C2", &layout.c2)] {
            check_fixture(fixture, points)?;
        }
        Ok(layout)
    }
}

/// A fixture's points define its frame: enough of them, not too many for a fit, not collinear.
fn check_fixture(fixture: &'static str, points: &[LayoutPoint]) -> Result<(), LayoutError> {
    if points.len() < MIN_FIT_POINTS {
        return Err(LayoutError::TooFew {
            fixture,
            found: points.len(),
            needed: MIN_FIT_POINTS,
        });
    }
    if points.len() > MAX_FIT_POINTS {
        return Err(LayoutError::TooMany {
            fixture,
            found: points.len(),
            max: MAX_FIT_POINTS,
        });
    }
    let model: Vec<Point3<f64>> = points.iter().map(|p| p.position_mm.into()).collect();
    match fit_frame(&model, &model, f64::INFINITY) {
        Err(FitError::Degenerate) => Err(LayoutError::Collinear { fixture }),
        _ => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const HEADER: &str = "fixture,id,x_mm,y_mm,z_mm,sigma_mm\n";

    fn points(fixture: &str, labels: &[u16]) -> String {
        labels
            .iter()
            .map(|&k| {
                let angle = f64::from(k);
                format!(
                    "{fixture},{k},{},{},{},\n",
                    100.0 * angle.cos(),
                    100.0 * angle.sin(),
                    if k % 2 == 0 { 5.0 } else { -5.0 }
                )
            })
            .collect()
    }

    #[test]
    fn a_calibration_file_reads_with_and_without_sigma() {
        let text = "# a photogrammetry report\n\
                    fixture, id, x_mm, y_mm, z_mm, sigma_mm\n\
                    C1, 101, 1.5, -2.0, 3.25, 0.004\n\
                    C1, 102, 10, 0, 0,\n\
                    \n\
                    C1, 103, 0, 10, 0, 0\n\
                    C2, 7, 0, 0, 0, 0.01\n\
                    C2, 8, 20, 0, 1, 0.01\n\
                    C2, 9, 0, 20, -1, 0.01\n";
        let layout = FixtureLayout::parse_csv(text).unwrap();
        assert_eq!(
            layout.c1[0],
            LayoutPoint {
                label: 101,
                position_mm: [1.5, -2.0, 3.25],
                sigma_mm: Some(0.004)
            }
        );
        assert_eq!(layout.c1[1].sigma_mm, None);
        assert_eq!(layout.c1[2].sigma_mm, Some(0.0));
        let labels: Vec<u16> = layout.c2.iter().map(|p| p.label).collect();
        assert_eq!(labels, [7, 8, 9]);
        let without = "fixture,id,x_mm,y_mm,z_mm\n".to_string()
            + &points("C1", &[0, 1, 2]).replace(",\n", "\n")
            + &points("C2", &[4, 5, 6]).replace(",\n", "\n");
        let layout = FixtureLayout::parse_csv(&without).unwrap();
        assert!(layout.c1.iter().all(|p| p.sigma_mm.is_none()));
    }

    #[test]
    fn each_fault_is_named_with_its_line_and_point() {
        let good = HEADER.to_string() + &points("C1", &[0, 1, 2]) + &points("C2", &[0, 1, 2]);
        assert!(FixtureLayout::parse_csv(&good).is_ok());
        let with = |extra: &str| FixtureLayout::parse_csv(&(good.clone() + extra)).unwrap_err();
        // The good file's points are on lines 2 to 7.
        assert_eq!(
            with("C2,1,5,5,5,\n"),
            LayoutError::Duplicate {
                line: 8,
                fixture: "C2",
                label: 1,
                first_line: 6
            }
        );
        assert!(matches!(
            with("C1,9,5,NaN,5,\n"),
            LayoutError::NonFinite {
                line: 8,
                fixture: "C1",
                label: 9,
                column: "y_mm",
                value
            } if value.is_nan()
        ));
        let message = with("C1,9,5,inf,5,\n").to_string();
        assert_eq!(
            message,
            "line 8: point C1 9: `y_mm` is inf, not a finite number"
        );
        assert_eq!(
            with("C1,9,5,5,5,-0.01\n").to_string(),
            "line 8: point C1 9: `sigma_mm` is -0.01, must be 0 or more"
        );
        assert_eq!(
            with("C3,9,5,5,5,\n").to_string(),
            "line 8: `fixture` is `C3`: a fixture is C1 or C2"
        );
        assert_eq!(
            with("C1,x,5,5,5,\n").to_string(),
            "line 8: `id` is `x`: an id is a whole number from 0 to 65535"
        );
        assert_eq!(
            with("C1,9,5,5\n").to_string(),
            "line 8: 4 values, 6 expected (one per header column)"
        );
        let few = HEADER.to_string() + &points("C1", &[0, 1, 2]) + &points("C2", &[0, 1]);
        assert_eq!(
            FixtureLayout::parse_csv(&few).unwrap_err().to_string(),
            "fixture C2: 2 coded points, at least 3 needed for a fit"
        );
        let in_line = HEADER.to_string()
            + &points("C1", &[0, 1, 2])
            + "C2,0,0,0,0,\nC2,1,1,1,1,\nC2,2,2,2,2,\n";
        assert_eq!(
            FixtureLayout::parse_csv(&in_line).unwrap_err(),
            LayoutError::Collinear { fixture: "C2" }
        );
        let many: Vec<u16> = (0..65).collect();
        let crowded = HEADER.to_string() + &points("C1", &many) + &points("C2", &[0, 1, 2]);
        assert_eq!(
            FixtureLayout::parse_csv(&crowded).unwrap_err(),
            LayoutError::TooMany {
                fixture: "C1",
                found: 65,
                max: 64
            }
        );
        assert_eq!(
            FixtureLayout::parse_csv("# only a comment\n"),
            Err(LayoutError::NoHeader)
        );
        assert!(matches!(
            FixtureLayout::parse_csv("id,x,y,z\n"),
            Err(LayoutError::Header { line: 1, .. })
        ));
    }
}
