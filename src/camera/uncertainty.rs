//! How uncertain one capture's estimate is (docs/estimation.md).
//!
//! - [`fit_covariance`]: the covariance of a least-squares rigid fit of a fixture's frame to its
//!   coded points, from each point's noise σ (first order: the fit is linear in small errors).
//! - [`relative_covariance`]: carries the two fixtures' fit covariances through Eq. 1 to the
//!   errors of {F} in {M} (position mm, rotation rad); [`relative_covariance_of`] one fixture's
//!   part, and [`segment_two_in_m`] the part of Segment II's pose estimate, whose fixture does
//!   not move.
//! - [`NoiseScale`]: how noisy the camera really is, as a multiple of its data sheet, learned
//!   from the fit residuals (six points per fixture over-determine each frame).

use crate::geometry::Pose;
use nalgebra::{Matrix3, Matrix6, Point3, Vector3};

/// The cross-product matrix `[v]×` (`[v]× u = v × u`).
fn cross(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// A 6×6 matrix from four 3×3 blocks.
fn blocks(a: Matrix3<f64>, b: Matrix3<f64>, c: Matrix3<f64>, d: Matrix3<f64>) -> Matrix6<f64> {
    let mut m = Matrix6::zeros();
    m.fixed_view_mut::<3, 3>(0, 0).copy_from(&a);
    m.fixed_view_mut::<3, 3>(0, 3).copy_from(&b);
    m.fixed_view_mut::<3, 3>(3, 0).copy_from(&c);
    m.fixed_view_mut::<3, 3>(3, 3).copy_from(&d);
    m
}

/// Covariance of an unweighted least-squares rigid fit to `points` (the fitted positions, mm),
/// each measured with isotropic per-axis noise σ `sigmas_mm[i]`. The errors are a small motion
/// about `centre`, `p ↦ p + δθ × (p − centre) + δt`, ordered `(δt mm, δθ rad)`. `None` for fewer
/// than three points or collinear ones.
pub fn fit_covariance(
    points: &[Point3<f64>],
    sigmas_mm: &[f64],
    centre: &Point3<f64>,
) -> Option<Matrix6<f64>> {
    if points.len() < 3 || points.len() != sigmas_mm.len() {
        return None;
    }
    // Jacobian of a point's position in the motion: J = [I, −[q]×], q = p − centre.
    let mut information = Matrix6::zeros();
    let mut noise = Matrix6::zeros();
    for (p, sigma) in points.iter().zip(sigmas_mm) {
        let q = cross(&(p - centre));
        let jtj = blocks(Matrix3::identity(), -q, q, -(q * q));
        information += jtj;
        noise += jtj * (sigma * sigma);
    }
    let inverse = information.try_inverse()?;
    let covariance = inverse * noise * inverse;
    covariance
        .iter()
        .all(|v| v.is_finite())
        .then(|| (covariance + covariance.transpose()) * 0.5)
}

/// One fixture's fit: its covariance about `centre` (see [`fit_covariance`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FixtureCovariance {
    pub covariance: Matrix6<f64>,
    pub centre: Point3<f64>,
}

impl FixtureCovariance {
    /// The same covariance for the fit's small motion written about `point` instead of the
    /// centre: `δt_point = δt + (centre − point) × δθ`, the rotation unchanged.
    pub fn about(&self, point: &Point3<f64>) -> Matrix6<f64> {
        let moved = blocks(
            Matrix3::identity(),
            cross(&(self.centre - point)),
            Matrix3::zeros(),
            Matrix3::identity(),
        );
        moved * self.covariance * moved.transpose()
    }

    /// The covariance of the same errors as a small motion ε of `frame` (a pose in {W} rigidly
    /// attached to the fixture) written in that frame's own axes, on the right:
    /// `frame_true ≈ frame · exp(ε)`, ordered `(ε_t mm, ε_θ rad)`. A motion (δt at the frame's
    /// origin, δθ) in {W} is `ε = (Rᵀ δt, Rᵀ δθ)`. In these axes Segment II's error does not
    /// depend on where Segment I is: it moves {F} in {M} by `(R_mf ε_t, R_mf ε_θ)`.
    pub fn in_frame(&self, frame: &Pose) -> Matrix6<f64> {
        let rt = frame.rotation.to_rotation_matrix().matrix().transpose();
        let to_frame = blocks(rt, Matrix3::zeros(), Matrix3::zeros(), rt);
        let covariance =
            to_frame * self.about(&Point3::from(frame.translation.vector)) * to_frame.transpose();
        (covariance + covariance.transpose()) * 0.5
    }
}

/// How an error ε of Segment II's {F}, written in {F}'s axes (see
/// [`FixtureCovariance::in_frame`]), moves {F} in {M}: `(δP, δO) = (R ε_t, R ε_θ)` with R the
/// rotation of `m_f`. Returns the covariance of `(δP mm, δO rad)` for ε of covariance
/// `in_f`.
pub fn segment_two_in_m(m_f: &Pose, in_f: &Matrix6<f64>) -> Matrix6<f64> {
    let r = *m_f.rotation.to_rotation_matrix().matrix();
    let rotate = blocks(r, Matrix3::zeros(), Matrix3::zeros(), r);
    let covariance = rotate * in_f * rotate.transpose();
    (covariance + covariance.transpose()) * 0.5
}

/// Covariance of the errors of {F} in {M}, ordered `(δP mm, δO rad)` in {M}, with the rotation
/// error on the left (`m_f_true ≈ exp(δO) · m_f` for the rotation, `P_true = P + δP`), given the
/// estimates `w_m` ({M} in {W}) and `m_f`, and the fits of {C1} (on Segment I) and {C2} (on
/// Segment II). The two fits' errors are independent.
///
/// A small motion ξ of {C1}'s fit about the origin of {W} moves `w_m` to `exp(ξ₁)·w_m`, and
/// likewise `w_f`; then `m_f = w_m⁻¹·w_f` moves by `exp(ξ₂ − ξ₁)` written in {M}: rotation
/// `R_mᵀ δθ`, translation `R_mᵀ (δt + δθ × t_m)`, and P moves by that translation plus the rotation
/// acting on P itself.
pub fn relative_covariance(
    w_m: &Pose,
    m_f: &Pose,
    c1: &FixtureCovariance,
    c2: &FixtureCovariance,
) -> Matrix6<f64> {
    relative_covariance_of(w_m, m_f, c1) + relative_covariance_of(w_m, m_f, c2)
}

/// The part of [`relative_covariance`] that one fixture's fit contributes.
pub fn relative_covariance_of(w_m: &Pose, m_f: &Pose, fixture: &FixtureCovariance) -> Matrix6<f64> {
    let rt = w_m.rotation.to_rotation_matrix().matrix().transpose();
    let in_m = blocks(
        rt,
        -rt * cross(&w_m.translation.vector),
        Matrix3::zeros(),
        rt,
    );
    let on_p = blocks(
        Matrix3::identity(),
        -cross(&m_f.translation.vector),
        Matrix3::zeros(),
        Matrix3::identity(),
    );
    let to_relative = on_p * in_m;
    let world = fixture.about(&Point3::origin());
    let covariance = to_relative * world * to_relative.transpose();
    (covariance + covariance.transpose()) * 0.5
}

/// Weight of the data sheet's noise in [`NoiseScale`], in degrees of freedom: enough to steady
/// the first frame, little enough that a few frames override it.
const PRIOR_DOF: f64 = 6.0;
/// Each frame keeps this share of what the earlier ones said, so the estimate follows a camera
/// whose noise changes (about the last 50 frames count).
const FORGETTING: f64 = 0.98;

/// The camera's point noise as a multiple of its data sheet, learned from fit residuals.
///
/// A rigid fit of n points leaves `3n − 6` degrees of freedom in its residuals; with per-axis
/// noise σᵢ = s · σ_sheet(range), `Σ |rᵢ|² / σ_sheet,ᵢ²` has expectation `s² (3n − 6)`. The
/// estimate of s² is the ratio of the (exponentially forgotten) sums, starting from s = 1 with
/// the weight of [`PRIOR_DOF`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NoiseScale {
    weighted_squares: f64,
    dof: f64,
}

impl Default for NoiseScale {
    fn default() -> Self {
        NoiseScale {
            weighted_squares: PRIOR_DOF,
            dof: PRIOR_DOF,
        }
    }
}

impl NoiseScale {
    /// Takes in one fit's normalised residual sum of squares and its degrees of freedom.
    pub fn add(&mut self, normalised_squares: f64, dof: usize) {
        if dof == 0 || !normalised_squares.is_finite() || normalised_squares < 0.0 {
            return;
        }
        self.weighted_squares = FORGETTING * self.weighted_squares + normalised_squares;
        self.dof = FORGETTING * self.dof + dof as f64;
    }

    /// The estimate of s (1 = the data sheet).
    pub fn scale(&self) -> f64 {
        self.variance_factor().sqrt()
    }

    /// The estimate of s².
    pub fn variance_factor(&self) -> f64 {
        self.weighted_squares / self.dof
    }

    /// Whether any frame has been taken in since the data sheet's prior: until then the
    /// estimate is the data sheet's, whatever the camera really is.
    pub fn has_seen_frames(&self) -> bool {
        self.dof > PRIOR_DOF
    }

    /// s² raised by two standard errors of its estimate (`√(2/ν)` relative for ν degrees of
    /// freedom): the factor covariances use, so that a camera seen for a few frames only is not
    /// trusted as if it were known.
    pub fn cautious_variance_factor(&self) -> f64 {
        self.variance_factor() * (1.0 + 2.0 * (2.0 / self.dof).sqrt())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::fit::fit_frame;
    use crate::geometry::pose::pose_from_mm_deg;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;
    use rand_distr::{Distribution, StandardNormal};

    fn sample_covariance(samples: &[[f64; 6]]) -> Matrix6<f64> {
        let n = samples.len() as f64;
        let mean: [f64; 6] = std::array::from_fn(|i| samples.iter().map(|s| s[i]).sum::<f64>() / n);
        Matrix6::from_fn(|i, j| {
            samples
                .iter()
                .map(|s| (s[i] - mean[i]) * (s[j] - mean[j]))
                .sum::<f64>()
                / (n - 1.0)
        })
    }

    /// Each diagonal element of `predicted` within `tolerance` (relative) of `sampled`.
    fn assert_variances_match(predicted: &Matrix6<f64>, sampled: &Matrix6<f64>, tolerance: f64) {
        for i in 0..6 {
            let (p, s) = (predicted[(i, i)], sampled[(i, i)]);
            assert!(
                (p / s - 1.0).abs() < tolerance,
                "axis {i}: predicted {p:.3e}, Monte Carlo {s:.3e}"
            );
        }
    }

    /// Six coded points like a fixture's, 2 m from the camera.
    fn fixture(centre: Vector3<f64>) -> Vec<Point3<f64>> {
        (0..6)
            .map(|k| {
                let a = k as f64 * std::f64::consts::TAU / 6.0;
                Point3::from(
                    centre + Vector3::new(140.0 * a.cos(), 140.0 * a.sin(), 5.0 * (-1f64).powi(k)),
                )
            })
            .collect()
    }

    #[test]
    fn fit_covariance_matches_monte_carlo() {
        let model = fixture(Vector3::zeros());
        let truth = pose_from_mm_deg(
            Vector3::new(10.0, -2000.0, 300.0),
            Vector3::new(5.0, -20.0, 40.0),
        );
        let points: Vec<Point3<f64>> = model.iter().map(|p| truth * p).collect();
        let sigmas: Vec<f64> = (0..6).map(|k| 0.03 + 0.005 * k as f64).collect();
        let centre = Point3::from(points.iter().map(|p| p.coords).sum::<Vector3<f64>>() / 6.0);
        let predicted = fit_covariance(&points, &sigmas, &centre).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let samples: Vec<[f64; 6]> = (0..20_000)
            .map(|_| {
                let noisy: Vec<Point3<f64>> = points
                    .iter()
                    .zip(&sigmas)
                    .map(|(p, s)| p + Vector3::from_fn(|_, _| StandardNormal.sample(&mut rng)) * *s)
                    .collect();
                let fit = fit_frame(&model, &noisy, f64::INFINITY).unwrap();
                // The fit's error as a motion about the centre.
                let error = fit.pose * truth.inverse();
                let theta = error.rotation.scaled_axis();
                let dt =
                    error.translation.vector + (error.rotation * centre.coords - centre.coords);
                [dt.x, dt.y, dt.z, theta.x, theta.y, theta.z]
            })
            .collect();
        assert_variances_match(&predicted, &sample_covariance(&samples), 0.05);
    }

    #[test]
    fn relative_covariance_matches_monte_carlo() {
        // {M} and {F} about 2 m from the camera, 120 mm apart, each seen through a fixture.
        let w_m = pose_from_mm_deg(
            Vector3::new(0.0, -2100.0, 60.0),
            Vector3::new(1.0, 0.5, 30.0),
        );
        let m_f = pose_from_mm_deg(
            Vector3::new(0.02, -0.01, -30.0),
            Vector3::new(0.1, -0.2, 3.0),
        );
        let w_f = w_m * m_f;
        let m_c1 = pose_from_mm_deg(Vector3::new(0.0, 0.0, 30.0), Vector3::zeros());
        let f_c2 = pose_from_mm_deg(Vector3::new(0.0, 0.0, -90.0), Vector3::zeros());
        let model = fixture(Vector3::zeros());
        let sigma = 0.04;
        let fit_of = |w_c: Pose| {
            let points: Vec<Point3<f64>> = model.iter().map(|p| w_c * p).collect();
            let centre = Point3::from(points.iter().map(|p| p.coords).sum::<Vector3<f64>>() / 6.0);
            let covariance = fit_covariance(&points, &[sigma; 6], &centre).unwrap();
            (points, FixtureCovariance { covariance, centre })
        };
        let (points_1, c1) = fit_of(w_m * m_c1);
        let (points_2, c2) = fit_of(w_f * f_c2);
        let predicted = relative_covariance(&w_m, &m_f, &c1, &c2);
        let mut rng = ChaCha8Rng::seed_from_u64(12);
        let mut noisy_fit = |points: &[Point3<f64>]| {
            let noisy: Vec<Point3<f64>> = points
                .iter()
                .map(|p| p + Vector3::from_fn(|_, _| StandardNormal.sample(&mut rng)) * sigma)
                .collect();
            fit_frame(&model, &noisy, f64::INFINITY).unwrap().pose
        };
        let samples: Vec<[f64; 6]> = (0..20_000)
            .map(|_| {
                let est_w_m = noisy_fit(&points_1) * m_c1.inverse();
                let est_w_f = noisy_fit(&points_2) * f_c2.inverse();
                let est = est_w_m.inverse() * est_w_f;
                let dp = est.translation.vector - m_f.translation.vector;
                let dtheta = (est.rotation * m_f.rotation.inverse()).scaled_axis();
                [dp.x, dp.y, dp.z, dtheta.x, dtheta.y, dtheta.z]
            })
            .collect();
        assert_variances_match(&predicted, &sample_covariance(&samples), 0.05);
    }

    #[test]
    fn segment_twos_part_written_in_f_is_the_same_as_through_eq_1() {
        // Two derivations of how {C2}'s fit error moves {F} in {M}: about the origin of {W}
        // through Eq. 1, and as a motion of {F} in its own axes. They must agree entry by entry,
        // wherever Segment I is.
        let model = fixture(Vector3::zeros());
        let w_f = pose_from_mm_deg(
            Vector3::new(40.0, -2050.0, 90.0),
            Vector3::new(-2.0, 1.0, 75.0),
        );
        let f_c2 = pose_from_mm_deg(Vector3::new(0.0, 0.0, -90.0), Vector3::new(0.0, 0.0, 10.0));
        let points: Vec<Point3<f64>> = model.iter().map(|p| w_f * f_c2 * p).collect();
        let centre = Point3::from(points.iter().map(|p| p.coords).sum::<Vector3<f64>>() / 6.0);
        let sigmas = [0.03, 0.04, 0.05, 0.03, 0.04, 0.05];
        let c2 = FixtureCovariance {
            covariance: fit_covariance(&points, &sigmas, &centre).unwrap(),
            centre,
        };
        let in_f = c2.in_frame(&w_f);
        for (p, o) in [
            ([0.0, 0.0, -30.0], [0.1, -0.2, 3.0]),
            ([25.0, -40.0, -80.0], [1.0, 0.5, -20.0]),
        ] {
            let m_f = pose_from_mm_deg(Vector3::from(p), Vector3::from(o));
            let w_m = w_f * m_f.inverse();
            let through_eq_1 = relative_covariance_of(&w_m, &m_f, &c2);
            let in_m = segment_two_in_m(&m_f, &in_f);
            let scale = through_eq_1.amax();
            assert!(
                (through_eq_1 - in_m).amax() < 1e-9 * scale,
                "{through_eq_1} against {in_m}"
            );
        }
    }

    #[test]
    fn noise_scale_learns_the_true_scale_from_residuals() {
        let model = fixture(Vector3::zeros());
        let truth = pose_from_mm_deg(
            Vector3::new(0.0, -2000.0, 0.0),
            Vector3::new(0.0, 0.0, 10.0),
        );
        let sheet_sigma = 0.03;
        for true_scale in [0.25, 1.0, 4.0, 8.0] {
            let mut rng = ChaCha8Rng::seed_from_u64(13);
            let mut estimate = NoiseScale::default();
            for _ in 0..200 {
                let noisy: Vec<Point3<f64>> = model
                    .iter()
                    .map(|p| {
                        truth * p
                            + Vector3::from_fn(|_, _| StandardNormal.sample(&mut rng))
                                * (sheet_sigma * true_scale)
                    })
                    .collect();
                let fit = fit_frame(&model, &noisy, f64::INFINITY).unwrap();
                let squares: f64 = model
                    .iter()
                    .zip(&noisy)
                    .map(|(m, q)| (fit.pose * m - q).norm_squared() / sheet_sigma.powi(2))
                    .sum();
                estimate.add(squares, 3 * 6 - 6);
            }
            let ratio = estimate.scale() / true_scale;
            assert!(
                (ratio - 1.0).abs() < 0.1,
                "scale {true_scale}: estimated {}",
                estimate.scale()
            );
            assert!(estimate.cautious_variance_factor() > estimate.variance_factor());
        }
    }
}
