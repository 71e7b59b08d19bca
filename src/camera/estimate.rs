//! From a capture to the relative pose of the segments and the 12-dim state.

use super::sim::nominal_point_sigma_mm;
use super::uncertainty::{FixtureCovariance, fit_covariance, relative_covariance};
use super::{CameraError, CameraFrame, Fixture, PointNoise, wrap_deg};
use crate::config::cell::CellConfig;
use crate::geometry::fit::{FitError, FrameFit, MAX_FIT_POINTS, fit_frame};
use crate::geometry::pose::{is_finite, rotation_vector_deg};
use crate::geometry::{CellFrames, Pose};
use nalgebra::{Matrix6, Point3, Vector3};

/// Smallest outlier rejection threshold, mm.
const MIN_REJECTION_MM: f64 = 0.05;

/// The state estimator: fits {C1} and {C2} to a capture and applies Eq. 1.
#[derive(Debug, Clone)]
pub struct StateEstimator {
    c1_model: Vec<Point3<f64>>,
    c2_model: Vec<Point3<f64>>,
    /// {M} in {C1}.
    c1_m: Pose,
    /// {F} in {C2}.
    c2_f: Pose,
    /// Rejection threshold at the data sheet's noise, mm.
    reject_above_mm: f64,
    /// The data sheet's point noise.
    sheet: PointNoise,
}

/// One state estimate.
#[derive(Debug, Clone)]
pub struct Measurement {
    /// Segment I: {M} in {W}.
    pub w_m: Pose,
    /// Segment II: {F} in {W}.
    pub w_f: Pose,
    /// {F} in {M}.
    pub m_f: Pose,
    /// Fit of {C1} in {W}. `rejected` also counts points dropped for non-finite coordinates
    /// or unknown ids, so `used + rejected` is the number of {C1} points in the capture.
    pub fit_c1: FrameFit,
    /// Fit of {C2} in {W}, likewise.
    pub fit_c2: FrameFit,
    /// Covariance of the errors of `m_f` at the data sheet's noise (noise scale 1), ordered
    /// `(δP mm, δO rad)` in {M} (see `uncertainty::relative_covariance`).
    pub covariance: Matrix6<f64>,
    /// Both fits' residuals, each squared and divided by its point's data-sheet variance, summed.
    pub residual_squares: f64,
    /// Degrees of freedom of those residuals (`3n − 6` per fixture).
    pub residual_dof: usize,
    /// {C1}'s fit covariance at the data sheet's noise, about the centre of its points.
    pub c1: FixtureCovariance,
    /// {C2}'s fit (on the static Segment II) with its covariance at the data sheet's noise,
    /// about the centre of its points: a pose that must not move.
    pub c2: FixtureCovariance,
}

/// One fixture's fit with what its uncertainty needs.
struct FixtureFit {
    fit: FrameFit,
    covariance: FixtureCovariance,
    residual_squares: f64,
    residual_dof: usize,
}

impl StateEstimator {
    /// An estimator for `cell`. Outlier rejection threshold: the larger of
    /// `outlier_rejection_sigmas` × the nominal point σ (noise scale 1) and 0.05 mm.
    pub fn new(cell: &CellConfig, frames: &CellFrames) -> Self {
        let sigma = nominal_point_sigma_mm(cell, frames);
        StateEstimator {
            c1_model: frames.c1_points_mm.clone(),
            c2_model: frames.c2_points_mm.clone(),
            c1_m: frames.m_c1.inverse(),
            c2_f: frames.f_c2.inverse(),
            reject_above_mm: (cell.camera.outlier_rejection_sigmas * sigma).max(MIN_REJECTION_MM),
            sheet: PointNoise::of(&cell.camera),
        }
    }

    /// The residual above which a coded point is rejected at the data sheet's noise, mm.
    pub fn rejection_threshold_mm(&self) -> f64 {
        self.reject_above_mm
    }

    /// Estimates the segment poses from one capture. `noise_scale` is how noisy the camera is
    /// believed to be (× the data sheet): the outlier rejection threshold grows with it. Points
    /// with non-finite coordinates or unknown ids are dropped; a fixture with fewer than 3
    /// usable points, or whose points are collinear, is an error.
    pub fn estimate(
        &self,
        frame: &CameraFrame,
        noise_scale: f64,
    ) -> Result<Measurement, CameraError> {
        let reject_above_mm = self.reject_above_mm * noise_scale.max(1.0);
        let c1 = self.fit_fixture(frame, Fixture::C1, reject_above_mm)?;
        let c2 = self.fit_fixture(frame, Fixture::C2, reject_above_mm)?;
        let w_m = c1.fit.pose * self.c1_m;
        let w_f = c2.fit.pose * self.c2_f;
        let m_f = w_m.inverse() * w_f;
        if !(is_finite(&w_m) && is_finite(&w_f) && is_finite(&m_f)) {
            return Err(CameraError::NonFinite);
        }
        let covariance = relative_covariance(&w_m, &m_f, &c1.covariance, &c2.covariance);
        if covariance.iter().any(|v| !v.is_finite()) {
            return Err(CameraError::NonFinite);
        }
        Ok(Measurement {
            w_m,
            w_f,
            m_f,
            fit_c1: c1.fit,
            fit_c2: c2.fit,
            covariance,
            residual_squares: c1.residual_squares + c2.residual_squares,
            residual_dof: c1.residual_dof + c2.residual_dof,
            c1: c1.covariance,
            c2: c2.covariance,
        })
    }

    fn fit_fixture(
        &self,
        frame: &CameraFrame,
        fixture: Fixture,
        reject_above_mm: f64,
    ) -> Result<FixtureFit, CameraError> {
        let layout = match fixture {
            Fixture::C1 => &self.c1_model,
            Fixture::C2 => &self.c2_model,
        };
        let mut model = [Point3::origin(); MAX_FIT_POINTS];
        let mut measured = [Point3::origin(); MAX_FIT_POINTS];
        let mut usable = 0usize;
        let mut dropped = 0usize;
        for point in frame.points.iter().filter(|p| p.fixture == fixture) {
            let p = &point.position_mm;
            let Some(model_point) = layout.get(usize::from(point.id)) else {
                dropped += 1;
                continue;
            };
            if !(p.x.is_finite() && p.y.is_finite() && p.z.is_finite()) {
                dropped += 1;
                continue;
            }
            if usable == MAX_FIT_POINTS {
                return Err(CameraError::Fixture {
                    fixture,
                    source: FitError::TooManyPoints {
                        found: usable + 1,
                        max: MAX_FIT_POINTS,
                    },
                });
            }
            model[usable] = *model_point;
            measured[usable] = *p;
            usable += 1;
        }
        let mut fit = fit_frame(&model[..usable], &measured[..usable], reject_above_mm)
            .map_err(|source| CameraError::Fixture { fixture, source })?;
        // The fitted positions of the points used, their data-sheet σ and residuals.
        let mut fitted = [Point3::origin(); MAX_FIT_POINTS];
        let mut sigmas = [0.0; MAX_FIT_POINTS];
        let mut count = 0;
        let mut residual_squares = 0.0;
        for i in (0..usable).filter(|i| fit.inliers & (1u64 << i) != 0) {
            fitted[count] = fit.pose * model[i];
            sigmas[count] = self.sheet.at_mm(&fitted[count]);
            residual_squares +=
                (measured[i] - fitted[count]).norm_squared() / sigmas[count].powi(2);
            count += 1;
        }
        let centre = Point3::from(
            fitted[..count]
                .iter()
                .map(|p| p.coords)
                .sum::<Vector3<f64>>()
                / count as f64,
        );
        let covariance = fit_covariance(&fitted[..count], &sigmas[..count], &centre).ok_or(
            CameraError::Fixture {
                fixture,
                source: FitError::Degenerate,
            },
        )?;
        fit.rejected += dropped;
        Ok(FixtureFit {
            fit,
            covariance: FixtureCovariance { covariance, centre },
            residual_squares,
            residual_dof: 3 * count - 6,
        })
    }
}

impl Measurement {
    /// The 12-dim state `[A1..A6, Px, Py, Pz, Ox, Oy, Oz]` (docs/design.md §5): A = pose of {M} in
    /// {W} (translation mm, rotation vector deg); P = translation of {F} in {M} (mm); O =
    /// rotation vector of {F} in {M} (deg), its z component wrapped into
    /// `[-pitch/2, pitch/2)` with `hole_pitch_deg` = 360 / holes.
    pub fn state(&self, hole_pitch_deg: f64) -> [f64; 12] {
        state_vector(&self.w_m, &self.m_f, hole_pitch_deg)
    }
}

/// The 12-dim state of docs/design.md §5 from {M} in {W} (A: translation mm, rotation vector deg) and
/// {F} in {M} (P mm, O rotation vector deg with O_z wrapped into [-pitch/2, pitch/2)).
pub fn state_vector(w_m: &Pose, m_f: &Pose, hole_pitch_deg: f64) -> [f64; 12] {
    let a_t = w_m.translation.vector;
    let a_r = rotation_vector_deg(w_m);
    let p = m_f.translation.vector;
    let o = rotation_vector_deg(m_f);
    [
        a_t.x,
        a_t.y,
        a_t.z,
        a_r.x,
        a_r.y,
        a_r.z,
        p.x,
        p.y,
        p.z,
        o.x,
        o.y,
        wrap_deg(o.z, hole_pitch_deg),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{CodedPoint, SimCamera};
    use crate::geometry::pose::pose_from_mm_deg;
    use nalgebra::Vector3;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn dummy_fit(pose: Pose) -> FrameFit {
        FrameFit {
            pose,
            rms_residual_mm: 0.0,
            max_residual_mm: 0.0,
            used: 6,
            rejected: 0,
            inliers: 0b11_1111,
        }
    }

    #[test]
    fn state_of_a_hand_built_measurement() {
        let w_m = pose_from_mm_deg(
            Vector3::new(10.0, 20.0, 2000.0),
            Vector3::new(0.0, 0.0, 30.0),
        );
        let m_f = pose_from_mm_deg(Vector3::new(1.0, 2.0, 3.0), Vector3::new(0.0, 0.0, 50.0));
        let w_f = w_m * m_f;
        let m = Measurement {
            w_m,
            w_f,
            m_f,
            fit_c1: dummy_fit(w_m),
            fit_c2: dummy_fit(w_f),
            covariance: Matrix6::identity(),
            residual_squares: 0.0,
            residual_dof: 24,
            c1: FixtureCovariance {
                covariance: Matrix6::identity(),
                centre: Point3::origin(),
            },
            c2: FixtureCovariance {
                covariance: Matrix6::identity(),
                centre: Point3::origin(),
            },
        };
        let s = m.state(45.0);
        let expected = [
            10.0, 20.0, 2000.0, 0.0, 0.0, 30.0, 1.0, 2.0, 3.0, 0.0, 0.0, 5.0,
        ];
        for (got, want) in s.iter().zip(expected) {
            assert!((got - want).abs() < 1e-9, "{s:?}");
        }
        // A small tilt: x/y unwrapped, z wrapped.
        let m_f = pose_from_mm_deg(Vector3::zeros(), Vector3::new(0.5, -0.25, -47.0));
        let m = Measurement { m_f, ..m.clone() };
        let s = m.state(45.0);
        assert!((s[9] - 0.5).abs() < 1e-9 && (s[10] + 0.25).abs() < 1e-9);
        assert!((s[11] + 2.0).abs() < 1e-9);
    }

    fn setup() -> (CellConfig, CellFrames, Pose, Pose) {
        let mut cell = CellConfig::reference();
        cell.imperfections.camera_noise = false;
        cell.imperfections.dropped_points = false;
        cell.imperfections.outliers = false;
        let frames = CellFrames::from_config(&cell);
        let f_m = pose_from_mm_deg(Vector3::new(0.5, -1.0, 12.0), Vector3::new(0.2, 0.1, 7.0));
        let (w_m, w_f) = frames.world_poses(&frames.platform_for(&f_m));
        (cell, frames, w_m, w_f)
    }

    #[test]
    fn exact_capture_gives_exact_poses() {
        let (cell, frames, w_m, w_f) = setup();
        let camera = SimCamera::new(&cell, &frames, 1.0);
        let estimator = StateEstimator::new(&cell, &frames);
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let frame = camera.capture(&w_m, &w_f, &mut rng);
        assert_eq!(frame.points.len(), 12);
        let m = estimator.estimate(&frame, 1.0).unwrap();
        assert!((m.w_m.translation.vector - w_m.translation.vector).norm() < 1e-9);
        assert!((m.w_m.inverse() * w_m).rotation.angle() < 1e-12);
        assert!((m.w_f.inverse() * w_f).rotation.angle() < 1e-12);
        assert!(estimator.rejection_threshold_mm() > 0.2);
    }

    #[test]
    fn nan_point_is_dropped_and_counted() {
        let (cell, frames, w_m, w_f) = setup();
        let camera = SimCamera::new(&cell, &frames, 1.0);
        let estimator = StateEstimator::new(&cell, &frames);
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let mut frame = camera.capture(&w_m, &w_f, &mut rng);
        frame.points[1].position_mm.y = f64::NAN;
        frame.points[7].position_mm.z = f64::INFINITY;
        let m = estimator.estimate(&frame, 1.0).unwrap();
        assert_eq!((m.fit_c1.used, m.fit_c1.rejected), (5, 1));
        assert_eq!((m.fit_c2.used, m.fit_c2.rejected), (5, 1));
        assert!(m.state(45.0).iter().all(|v| v.is_finite()));
        assert!((m.w_m.translation.vector - w_m.translation.vector).norm() < 1e-9);

        // NaN everywhere on C1 but two points: an error, never a finite-looking state.
        let mut frame = camera.capture(&w_m, &w_f, &mut rng);
        for p in frame
            .points
            .iter_mut()
            .filter(|p| p.fixture == Fixture::C1)
            .skip(2)
        {
            p.position_mm.x = f64::NAN;
        }
        let err = estimator.estimate(&frame, 1.0).unwrap_err();
        assert_eq!(
            err,
            CameraError::Fixture {
                fixture: Fixture::C1,
                source: FitError::TooFewPoints {
                    found: 2,
                    needed: 3
                }
            }
        );
        assert_eq!(err.to_string(), "fixture C1: only 2 coded points, 3 needed");
    }

    #[test]
    fn unknown_ids_and_missing_fixture() {
        let (cell, frames, w_m, w_f) = setup();
        let camera = SimCamera::new(&cell, &frames, 1.0);
        let estimator = StateEstimator::new(&cell, &frames);
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mut frame = camera.capture(&w_m, &w_f, &mut rng);
        frame.points.push(CodedPoint {
            fixture: Fixture::C2,
            id: 999,
            position_mm: Point3::origin(),
        });
        let m = estimator.estimate(&frame, 1.0).unwrap();
        assert_eq!((m.fit_c2.used, m.fit_c2.rejected), (6, 1));
        frame.points.retain(|p| p.fixture == Fixture::C1);
        let err = estimator.estimate(&frame, 1.0).unwrap_err();
        assert!(
            err.to_string()
                .starts_with("fixture C2: only 0 coded points")
        );
    }
}
