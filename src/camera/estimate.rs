//! From a capture to the relative pose of the segments and the 12-dim state.

use super::sim::nominal_point_sigma_mm;
use super::uncertainty::{FixtureCovariance, fit_covariance, relative_covariance};
use super::{CameraError, CameraFrame, Fixture, PointNoise, wrap_deg};
use crate::config::cell::CellConfig;
use crate::geometry::fit::{
    FitError, FrameFit, MAX_FIT_POINTS, MIN_FIT_POINTS, fit_frame, refit_without,
};
use crate::geometry::pose::{is_finite, rotation_vector_deg};
use crate::geometry::{CellFrames, Pose};
use nalgebra::{Matrix6, Point3, Vector3};

/// Smallest outlier rejection threshold, mm.
const MIN_REJECTION_MM: f64 = 0.05;

/// The median residual of a point over its σ that a rigid fit of six points leaves: the median
/// of a χ with 3 degrees of freedom (1.538), shrunk by the fit's 6 of 18 degrees of freedom
/// (× √(12/18)).
const SHEET_MEDIAN_RESIDUAL: f64 = 1.256;

/// A fit's residuals, each over its point's σ, squared and summed, are beyond what the camera's
/// noise gives by chance when over the χ² quantile of this upper tail (1e-4): one point is then
/// left out (`StateEstimator::without_the_unexplained_point`).
const RESIDUALS_TAIL_SIGMAS: f64 = 3.719;

/// The state estimator: fits {C1} and {C2} to a capture and applies Eq. 1.
#[derive(Debug, Clone)]
pub struct StateEstimator {
    c1_model: Vec<Point3<f64>>,
    c2_model: Vec<Point3<f64>>,
    /// Each model point's calibration σ per axis, mm (0: not given).
    c1_calibration_mm: Vec<f64>,
    c2_calibration_mm: Vec<f64>,
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
            c1_calibration_mm: frames.c1_sigma_mm.clone(),
            c2_calibration_mm: frames.c2_sigma_mm.clone(),
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

    /// How noisy the camera looks in this one capture (× the data sheet, from 1 up to
    /// `up_to`): each fixture fitted with the threshold of a camera `up_to` times the data
    /// sheet's, the median of its points' residuals over their data-sheet σ against the median
    /// the data sheet's noise leaves; the quieter fixture's. A median, and the quieter fixture,
    /// so that a point gone astray, and the fit it bent, do not make the camera look noisy. For
    /// the first frame of an episode, before any has shown the camera's noise: at the data
    /// sheet's threshold a camera four times as noisy loses one or two good points of six in
    /// most fits.
    pub fn noise_scale_of(&self, frame: &CameraFrame, up_to: f64) -> f64 {
        let up_to = up_to.max(1.0);
        let reject_above_mm = self.reject_above_mm * up_to;
        let median_of = |fixture: Fixture| -> Option<f64> {
            let points = self.fixture_points(frame, fixture).ok()?;
            let (model, measured) = (points.model(), points.measured());
            let fit = fit_frame(model, measured, reject_above_mm).ok()?;
            let mut ratios: Vec<f64> = model
                .iter()
                .zip(measured)
                .zip(points.calibration())
                .map(|((m, q), calibration)| {
                    let fitted = fit.pose * m;
                    (q - fitted).norm() / self.point_sigma_mm(&fitted, *calibration)
                })
                .collect();
            ratios.sort_by(f64::total_cmp);
            Some(ratios[ratios.len() / 2])
        };
        [median_of(Fixture::C1), median_of(Fixture::C2)]
            .into_iter()
            .flatten()
            .min_by(f64::total_cmp)
            .map_or(1.0, |median| {
                (median / SHEET_MEDIAN_RESIDUAL).clamp(1.0, up_to)
            })
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
        self.estimate_screened(frame, noise_scale, None)
    }

    /// [`estimate`](Self::estimate), and when the camera's variance factor is known
    /// (`known_variance_factor`, × the data sheet's), each fixture's residuals are screened as
    /// a whole against it: a point that bent the fit towards itself is left out even when its
    /// own residual is under the threshold (`without_the_unexplained_point`).
    pub fn estimate_screened(
        &self,
        frame: &CameraFrame,
        noise_scale: f64,
        known_variance_factor: Option<f64>,
    ) -> Result<Measurement, CameraError> {
        let c1 = self.fit_fixture(frame, Fixture::C1, noise_scale, known_variance_factor)?;
        let c2 = self.fit_fixture(frame, Fixture::C2, noise_scale, known_variance_factor)?;
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

    /// Fits one fixture: the points whose residual is beyond the rejection threshold (scaled by
    /// `noise_scale`, at least the data sheet's) are left out one by one, then, with a
    /// `known_variance_factor`, while the residuals as a whole are beyond that noise, the point
    /// without which the fit explains the others best.
    fn fit_fixture(
        &self,
        frame: &CameraFrame,
        fixture: Fixture,
        noise_scale: f64,
        known_variance_factor: Option<f64>,
    ) -> Result<FixtureFit, CameraError> {
        let reject_above_mm = self.reject_above_mm * noise_scale.max(1.0);
        let points = self.fixture_points(frame, fixture)?;
        let (model, measured) = (points.model(), points.measured());
        let calibration = points.calibration();
        let mut fit = fit_frame(model, measured, reject_above_mm)
            .map_err(|source| CameraError::Fixture { fixture, source })?;
        if let Some(variance_factor) = known_variance_factor {
            while let Some(better) = self.without_the_unexplained_point(
                model,
                measured,
                calibration,
                reject_above_mm,
                variance_factor,
                &fit,
            ) {
                fit = better;
            }
        }
        // The fitted positions of the points used and their data-sheet σ (with their
        // calibration's, where the layout gives one).
        let mut fitted = [Point3::origin(); MAX_FIT_POINTS];
        let mut sigmas = [0.0; MAX_FIT_POINTS];
        let mut count = 0;
        for i in (0..model.len()).filter(|i| fit.inliers & (1u64 << i) != 0) {
            fitted[count] = fit.pose * model[i];
            sigmas[count] = self.point_sigma_mm(&fitted[count], calibration[i]);
            count += 1;
        }
        let residual_squares = self.residual_squares(model, measured, calibration, &fit);
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
        fit.rejected += points.dropped;
        Ok(FixtureFit {
            fit,
            covariance: FixtureCovariance { covariance, centre },
            residual_squares,
            residual_dof: 3 * count - 6,
        })
    }

    /// The points of `fixture` in `frame` a fit can use, beside their model points: those with
    /// a known id and finite coordinates (the others are counted as dropped).
    fn fixture_points(
        &self,
        frame: &CameraFrame,
        fixture: Fixture,
    ) -> Result<FixturePoints, CameraError> {
        let (layout, calibration) = match fixture {
            Fixture::C1 => (&self.c1_model, &self.c1_calibration_mm),
            Fixture::C2 => (&self.c2_model, &self.c2_calibration_mm),
        };
        let mut points = FixturePoints {
            model: [Point3::origin(); MAX_FIT_POINTS],
            measured: [Point3::origin(); MAX_FIT_POINTS],
            calibration: [0.0; MAX_FIT_POINTS],
            usable: 0,
            dropped: 0,
        };
        for point in frame.points.iter().filter(|p| p.fixture == fixture) {
            let p = &point.position_mm;
            let Some(model_point) = layout.get(usize::from(point.id)) else {
                points.dropped += 1;
                continue;
            };
            if !(p.x.is_finite() && p.y.is_finite() && p.z.is_finite()) {
                points.dropped += 1;
                continue;
            }
            if points.usable == MAX_FIT_POINTS {
                return Err(CameraError::Fixture {
                    fixture,
                    source: FitError::TooManyPoints {
                        found: points.usable + 1,
                        max: MAX_FIT_POINTS,
                    },
                });
            }
            points.model[points.usable] = *model_point;
            points.calibration[points.usable] = calibration
                .get(usize::from(point.id))
                .copied()
                .unwrap_or(0.0);
            points.measured[points.usable] = *p;
            points.usable += 1;
        }
        Ok(points)
    }

    /// The residuals of the points `fit` used, each over its point's σ
    /// ([`point_sigma_mm`](Self::point_sigma_mm)), squared and summed.
    fn residual_squares(
        &self,
        model: &[Point3<f64>],
        measured: &[Point3<f64>],
        calibration: &[f64],
        fit: &FrameFit,
    ) -> f64 {
        (0..model.len())
            .filter(|i| fit.inliers & (1u64 << i) != 0)
            .map(|i| {
                let fitted = fit.pose * model[i];
                (measured[i] - fitted).norm_squared()
                    / self.point_sigma_mm(&fitted, calibration[i]).powi(2)
            })
            .sum()
    }

    /// A coded point's σ per axis at `fitted` (mm): the data sheet's, and with a calibration
    /// σ (`calibration_mm` > 0) the two added in quadrature. The fit itself is unweighted; the
    /// calibration's σ enters the fit's covariance and the residuals' scale.
    fn point_sigma_mm(&self, fitted: &Point3<f64>, calibration_mm: f64) -> f64 {
        let sheet = self.sheet.at_mm(fitted);
        if calibration_mm > 0.0 {
            sheet.hypot(calibration_mm)
        } else {
            sheet
        }
    }

    /// When `fit`'s residuals are beyond what a camera of `variance_factor` × the data sheet's
    /// variance (at least the data sheet's) gives by chance, the fit without the point that
    /// leaves the others best explained. A gross error on one of six points bends the fit
    /// towards it, and at four times the data sheet's noise the per-point threshold grows with
    /// the noise while the error does not: the point then hides under the threshold and pulls
    /// the fixture's frame several σ off. At least four points are kept.
    fn without_the_unexplained_point(
        &self,
        model: &[Point3<f64>],
        measured: &[Point3<f64>],
        calibration: &[f64],
        reject_above_mm: f64,
        variance_factor: f64,
        fit: &FrameFit,
    ) -> Option<FrameFit> {
        if fit.used <= MIN_FIT_POINTS + 1 {
            return None;
        }
        let dof = (3 * fit.used - 6) as f64;
        let chance = chi2_upper_quantile(dof, RESIDUALS_TAIL_SIGMAS) * variance_factor.max(1.0);
        if self.residual_squares(model, measured, calibration, fit) <= chance {
            return None;
        }
        (0..model.len())
            .filter(|i| fit.inliers & (1u64 << i) != 0)
            .filter_map(|i| refit_without(model, measured, reject_above_mm, fit, i).ok())
            .map(|without| {
                let squares = self.residual_squares(model, measured, calibration, &without);
                (squares, without)
            })
            .min_by(|a, b| a.0.total_cmp(&b.0))
            .map(|(_, without)| without)
    }
}

/// A fixture's usable points in a capture ([`StateEstimator::fixture_points`]).
struct FixturePoints {
    model: [Point3<f64>; MAX_FIT_POINTS],
    measured: [Point3<f64>; MAX_FIT_POINTS],
    /// Each point's calibration σ, mm (0: not given).
    calibration: [f64; MAX_FIT_POINTS],
    usable: usize,
    /// Points left out for an unknown id or non-finite coordinates.
    dropped: usize,
}

impl FixturePoints {
    fn model(&self) -> &[Point3<f64>] {
        &self.model[..self.usable]
    }

    fn measured(&self) -> &[Point3<f64>] {
        &self.measured[..self.usable]
    }

    fn calibration(&self) -> &[f64] {
        &self.calibration[..self.usable]
    }
}

/// The χ² value with `dof` degrees of freedom exceeded with the probability of a normal
/// variable exceeding `sigmas` (Wilson and Hilferty's cube-root approximation).
fn chi2_upper_quantile(dof: f64, sigmas: f64) -> f64 {
    let spread = 2.0 / (9.0 * dof);
    dof * (1.0 - spread + sigmas * spread.sqrt()).powi(3)
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
    fn a_point_the_fit_bent_towards_is_left_out_when_the_residuals_are_beyond_the_noise() {
        // An exact capture but for 0.6 mm on one of C2's points: under the per-point threshold
        // of a camera four times the data sheet's (6 σ of ~0.036 mm × 4), so rejection keeps
        // it and the fit bends towards it. Screened against the data sheet's noise (the
        // residuals' χ² with 12 degrees of freedom is then hundreds of times its 1e-4 quantile),
        // the fit without it is the exact one again.
        let (cell, frames, w_m, w_f) = setup();
        let camera = SimCamera::new(&cell, &frames, 1.0);
        let estimator = StateEstimator::new(&cell, &frames);
        let mut frame = camera.capture(&w_m, &w_f, &mut ChaCha8Rng::seed_from_u64(1));
        let astray = frame
            .points
            .iter_mut()
            .find(|p| p.fixture == Fixture::C2)
            .expect("a point of C2");
        astray.position_mm +=
            Vector3::new(0.0, 0.6, 0.0) / 2f64.sqrt() + Vector3::new(0.0, 0.0, 0.3);
        let error_mm = |m: &Measurement| (m.w_f.translation.vector - w_f.translation.vector).norm();
        let kept = estimator.estimate(&frame, 4.0).unwrap();
        assert_eq!(kept.fit_c2.used, 6);
        assert!(error_mm(&kept) > 0.01, "bent by {} mm", error_mm(&kept));
        let screened = estimator.estimate_screened(&frame, 4.0, Some(1.0)).unwrap();
        assert_eq!((screened.fit_c2.used, screened.fit_c2.rejected), (5, 1));
        assert!(error_mm(&screened) < 1e-9, "{} mm", error_mm(&screened));
        // C1's exact fit is left as it is.
        assert_eq!(screened.fit_c1.used, 6);
        // A camera as noisy as that point says is not screened: 16 times the variance.
        let noisy = estimator
            .estimate_screened(&frame, 4.0, Some(16.0))
            .unwrap();
        assert_eq!(noisy.fit_c2.used, 6);
    }

    #[test]
    fn a_first_frame_shows_how_noisy_the_camera_is_and_one_point_astray_does_not() {
        // A camera four times as noisy as its data sheet: at the data sheet's threshold most
        // frames lose good points; read from the frame itself the noise is three to four
        // times the sheet's, and at that threshold nearly every frame keeps all twelve.
        let (mut cell, frames, w_m, w_f) = setup();
        cell.imperfections.camera_noise = true;
        let noisy = SimCamera::new(&cell, &frames, 4.0);
        let estimator = StateEstimator::new(&cell, &frames);
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let used = |m: &Measurement| m.fit_c1.used + m.fit_c2.used;
        let (mut losing_at_sheet, mut losing_as_seen, mut scales) = (0, 0, Vec::new());
        for _ in 0..200 {
            let frame = noisy.capture(&w_m, &w_f, &mut rng);
            let seen = estimator.noise_scale_of(&frame, 4.0);
            scales.push(seen);
            losing_at_sheet += usize::from(used(&estimator.estimate(&frame, 1.0).unwrap()) < 12);
            losing_as_seen += usize::from(used(&estimator.estimate(&frame, seen).unwrap()) < 12);
        }
        scales.sort_by(f64::total_cmp);
        assert!((3.0..=4.0).contains(&scales[100]), "median {}", scales[100]);
        assert!(
            losing_at_sheet > 150,
            "{losing_at_sheet} of 200 at the sheet's threshold"
        );
        assert!(losing_as_seen < 10, "{losing_as_seen} of 200 as seen");
        // At the data sheet's noise, a point of C2 2 mm astray bends that fixture's fit, but C1
        // shows the camera as it is (a median of six, so within about half the sheet's), and at
        // that threshold the point is left out.
        let quiet = SimCamera::new(&cell, &frames, 1.0);
        for _ in 0..50 {
            let mut frame = quiet.capture(&w_m, &w_f, &mut rng);
            assert_eq!(frame.points[7].fixture, Fixture::C2);
            frame.points[7].position_mm += Vector3::new(2.0, 0.0, 0.0);
            let seen = estimator.noise_scale_of(&frame, 4.0);
            assert!(seen < 2.0, "{seen}");
            assert_eq!(estimator.estimate(&frame, seen).unwrap().fit_c2.rejected, 1);
        }
    }

    #[test]
    fn a_first_frame_reads_its_noise_from_the_points_a_fit_can_use() {
        // A point with a non-finite coordinate or an unknown id is left out of the noise read,
        // as the fit leaves it out: the read is the one without that point.
        let (mut cell, frames, w_m, w_f) = setup();
        cell.imperfections.camera_noise = true;
        let camera = SimCamera::new(&cell, &frames, 2.0);
        let estimator = StateEstimator::new(&cell, &frames);
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for _ in 0..20 {
            let frame = camera.capture(&w_m, &w_f, &mut rng);
            let mut without = frame.clone();
            without.points.remove(7);
            let expected = estimator.noise_scale_of(&without, 4.0);
            let mut broken = frame.clone();
            broken.points[7].position_mm.z = f64::NAN;
            assert_eq!(estimator.noise_scale_of(&broken, 4.0), expected);
            let mut unknown = frame;
            unknown.points[7].id = 200;
            assert_eq!(estimator.noise_scale_of(&unknown, 4.0), expected);
        }
    }

    #[test]
    fn the_residual_screens_quantile_is_the_chi2_tail_of_1e_4() {
        // For an even number k of degrees of freedom the χ² upper tail is exact:
        // e^(−x/2) Σ_{i<k/2} (x/2)^i / i!. The cube-root approximation's quantile for the
        // normal tail of 3.719 σ (1e-4) leaves a tail within a quarter of 1e-4.
        let tail = |k: usize, x: f64| {
            let mut term = 1.0;
            let mut sum = 0.0;
            for i in 0..k / 2 {
                if i > 0 {
                    term *= x / 2.0 / i as f64;
                }
                sum += term;
            }
            (-x / 2.0).exp() * sum
        };
        for k in [6, 12, 18, 36] {
            let p = tail(k, chi2_upper_quantile(k as f64, RESIDUALS_TAIL_SIGMAS));
            assert!((p - 1e-4).abs() < 2.5e-5, "{k} degrees of freedom: {p}");
        }
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
