//! The digital twin's binocular camera and the state estimate (paper Eq. 1, docs/design.md §5).
//!
//! [`SimCamera`] turns the true poses of Segment I ({M}) and Segment II ({F}) in the camera
//! frame {W} into one capture of decoded coded points, with the cell's noise, dropped points and
//! gross outliers. [`StateEstimator`] fits the fixture frames {C1}, {C2} to a capture, applies
//! Eq. 1 (`w_m = w_c1 · c1_m`, `w_f = w_c2 · c2_f`) and forms the 12-dim state.

pub mod drift;
mod estimate;
pub mod fusion;
pub mod ingest;
mod sim;
pub mod uncertainty;

pub use drift::DriftKnowledge;
pub use estimate::{Measurement, StateEstimator, state_vector};
pub use fusion::{Fusion, FusionTuning, StateFilter};
pub use sim::{SimCamera, nominal_point_sigma_mm};

use crate::geometry::fit::FitError;
use nalgebra::Point3;

/// The camera's data-sheet noise: per-axis σ = `noise_base_mm` + `noise_per_m_mm` × the range
/// from the camera in metres. The twin's camera draws its noise from it (times its noise
/// scale); the estimator weighs the points and normalises their residuals by it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PointNoise {
    base_mm: f64,
    per_m_mm: f64,
}

impl PointNoise {
    pub fn of(camera: &crate::config::cell::CameraConfig) -> Self {
        PointNoise {
            base_mm: camera.noise_base_mm,
            per_m_mm: camera.noise_per_m_mm,
        }
    }

    /// σ per axis (mm) of a point `range_m` metres from the camera.
    pub fn at_range_mm(&self, range_m: f64) -> f64 {
        self.base_mm + self.per_m_mm * range_m
    }

    /// σ per axis (mm) of a point at `position` in the camera frame {W}.
    pub fn at_mm(&self, position: &Point3<f64>) -> f64 {
        self.at_range_mm(position.coords.norm() / 1000.0)
    }
}

/// The fixture a coded point sits on: {C1} on Segment I, {C2} on Segment II.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Fixture {
    C1,
    C2,
}

impl std::fmt::Display for Fixture {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Fixture::C1 => "C1",
            Fixture::C2 => "C2",
        })
    }
}

/// One decoded coded point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CodedPoint {
    pub fixture: Fixture,
    /// Index of the point in its fixture's layout (`CellFrames::c1_points_mm` / `c2_points_mm`;
    /// a camera names it by its label, `CellFrames::c1_labels` / `c2_labels`).
    pub id: u16,
    /// Measured position in the camera frame {W}, mm.
    pub position_mm: Point3<f64>,
}

/// One capture: the coded points the camera decoded (dropped points absent). Reuse its buffer
/// between captures ([`SimCamera::capture_into`] clears it).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CameraFrame {
    pub points: Vec<CodedPoint>,
    /// The capture's number within its episode: 1 for the episode's first capture, +1 per
    /// capture (0 when nobody numbered it). A frame delivered late or twice keeps its number.
    pub sequence: u64,
    /// Whether the points were measured or rebuilt from a tracker's fit.
    pub kind: FrameKind,
}

/// What a frame's points are: it decides what the frame may teach of the camera's noise.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub enum FrameKind {
    /// The coded points as the camera measured them, each with its own noise: their fit's
    /// residuals show how noisy the camera is.
    #[default]
    Measured,
    /// Each fixture's coded points rebuilt at their layout from the frame a tracker fitted to
    /// them (OpenIGTLink TRANSFORM): exact by construction, so their residuals say nothing of
    /// the noise. The fit is as uncertain as the tracker made it: the data-sheet noise of the
    /// points it fitted times `variance_factor` (1: as noisy as the data sheet says).
    Fitted { variance_factor: f64 },
}

/// Why a capture gave no state.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CameraError {
    /// The frame of one fixture could not be fitted.
    #[error("fixture {fixture}: {}", describe_fit_error(source))]
    Fixture { fixture: Fixture, source: FitError },
    /// The estimate came out non-finite.
    #[error("the camera estimate is not finite")]
    NonFinite,
    /// The frame disagrees with the fused estimate; held back until a second frame confirms it.
    #[error(
        "the frame is {sigmas:.1} σ from the fused estimate: held back until the next frame confirms it"
    )]
    HeldBack { sigmas: f64 },
    /// Segment II, which does not move, is seen somewhere else: the camera or its fixture has
    /// been knocked out of calibration.
    #[error("Segment II's fixture is seen where it was not: the camera is out of calibration")]
    Shifted,
}

fn describe_fit_error(error: &FitError) -> String {
    match error {
        FitError::TooFewPoints { found, needed } => {
            format!("only {found} coded points, {needed} needed")
        }
        FitError::Degenerate => "the coded points are collinear, no frame".to_string(),
        FitError::NonFinite => "non-finite coded point coordinates".to_string(),
        FitError::TooManyPoints { found, max } => {
            format!("{found} coded points, at most {max} supported")
        }
        other => other.to_string(),
    }
}

/// Wraps `angle` into `[-period/2, period/2)` (any unit, e.g. deg). A non-finite angle or a
/// period that is not a finite positive number gives NaN.
pub fn wrap_deg(angle: f64, period: f64) -> f64 {
    if !(angle.is_finite() && period.is_finite() && period > 0.0) {
        return f64::NAN;
    }
    let half = period / 2.0;
    let mut wrapped = angle - period * ((angle + half) / period).floor();
    // Rounding can land exactly on the open end, or a hair outside.
    if wrapped >= half {
        wrapped -= period;
    } else if wrapped < -half {
        wrapped += period;
    }
    wrapped
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wrap_deg_cases() {
        let close = |a: f64, b: f64| (a - b).abs() < 1e-12;
        assert!(close(wrap_deg(50.0, 45.0), 5.0));
        assert!(close(wrap_deg(-50.0, 45.0), -5.0));
        assert!(close(wrap_deg(22.5, 45.0), -22.5));
        assert!(close(wrap_deg(-22.5, 45.0), -22.5));
        assert!(close(wrap_deg(22.499, 45.0), 22.499));
        assert!(close(wrap_deg(0.0, 45.0), 0.0));
        assert!(close(wrap_deg(360.0, 45.0), 0.0));
        assert!(close(wrap_deg(-720.0 + 3.0, 30.0), 3.0));
        assert!(close(wrap_deg(179.0, 360.0), 179.0));
        assert!(close(wrap_deg(181.0, 360.0), -179.0));
        assert!(close(wrap_deg(1e6 + 0.25, 1.0), 0.25));
        assert!(wrap_deg(f64::NAN, 45.0).is_nan());
        assert!(wrap_deg(f64::INFINITY, 45.0).is_nan());
        assert!(wrap_deg(10.0, 0.0).is_nan());
        assert!(wrap_deg(10.0, -45.0).is_nan());
        for k in -2000..2000 {
            let w = wrap_deg(k as f64 * 0.37, 45.0);
            assert!((-22.5..22.5).contains(&w));
        }
    }

    #[test]
    fn camera_error_message_names_fixture() {
        let e = CameraError::Fixture {
            fixture: Fixture::C1,
            source: FitError::TooFewPoints {
                found: 2,
                needed: 3,
            },
        };
        assert_eq!(e.to_string(), "fixture C1: only 2 coded points, 3 needed");
    }
}
