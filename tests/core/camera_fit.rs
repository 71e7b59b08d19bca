//! The frame fit and the camera → state pipeline against theory, on the reference cell.
//!
//! Theory used (isotropic per-axis noise σᵢ on point i, n points, ordinary least squares):
//! - Translation: the model points' centroid is the fixture origin (the ring is symmetric, its
//!   heights alternate ±h), so the fitted origin is the measured centroid and its error per axis
//!   has variance Σσᵢ²/n²; E|δt|² = 3 Σσᵢ²/n².
//! - Rotation: linearising R(I + [δθ]×), with Σpᵢ = 0 rotation decouples from translation and
//!   δθ = J⁻¹ Σ pᵢ × eᵢ with J = Σ (|pᵢ|² I − pᵢpᵢᵀ) (the points' "inertia" tensor), so
//!   Cov(δθ) = J⁻¹ (Σ σᵢ² (|pᵢ|² I − pᵢpᵢᵀ)) J⁻¹ and E|δθ|² = tr Cov(δθ). For the ring (radius
//!   r, heights ±h, equal σ) this is σ²/n · (2/(r²/2 + h²) + 1/r²).
//! - State P, O: first-order propagation of the 36 point coordinates through the whole
//!   estimator (numerical Jacobian of the noise-free pipeline), Cov = J diag(σᵢ²) Jᵀ.

use assembly_cell::camera::{CameraFrame, SimCamera, StateEstimator};
use assembly_cell::config::cell::CellConfig;
use assembly_cell::geometry::fit::fit_frame;
use assembly_cell::geometry::pose::{pose_from_mm_deg, rotation_vector_deg};
use assembly_cell::geometry::{CellFrames, Pose};
use nalgebra::{Matrix3, Point3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal, UnitSphere};

fn gaussian3(rng: &mut impl Rng) -> Vector3<f64> {
    Vector3::new(
        rng.sample(StandardNormal),
        rng.sample(StandardNormal),
        rng.sample(StandardNormal),
    )
}

/// The reference cell's Segment II fixture {C2} in {W} at the docked pose, its model points
/// and each point's per-axis σ.
struct KnownFrame {
    truth: Pose,
    model: Vec<Point3<f64>>,
    sigma: Vec<f64>,
    reject_above_mm: f64,
}

fn known_frame() -> KnownFrame {
    let cell = CellConfig::reference();
    let frames = CellFrames::from_config(&cell);
    let home = Pose::translation(0.0, 0.0, cell.robot.home_height_mm);
    let (_, w_f) = frames.world_poses(&home);
    let truth = w_f * frames.f_c2;
    let camera = SimCamera::new(&cell, &frames, 1.0);
    let model = frames.c2_points_mm.clone();
    let sigma = model
        .iter()
        .map(|p| camera.sigma_at_mm(&(truth * p)))
        .collect();
    KnownFrame {
        truth,
        model,
        sigma,
        reject_above_mm: StateEstimator::new(&cell, &frames).rejection_threshold_mm(),
    }
}

fn errors(fit: &Pose, truth: &Pose) -> (f64, f64) {
    (
        (fit.translation.vector - truth.translation.vector).norm(),
        (truth.inverse() * fit).rotation.angle(),
    )
}

fn rms(values: &[f64]) -> f64 {
    (values.iter().map(|v| v * v).sum::<f64>() / values.len() as f64).sqrt()
}

/// Theoretical RMS of |δt| (mm) and |δθ| (rad) for the known frame.
fn theory(k: &KnownFrame) -> (f64, f64) {
    let n = k.model.len() as f64;
    let centroid = k.model.iter().map(|p| p.coords).sum::<Vector3<f64>>() / n;
    assert!(centroid.norm() < 1e-9, "the ring's centroid is its origin");
    let sum_var: f64 = k.sigma.iter().map(|s| s * s).sum();
    let t_rms = (3.0 * sum_var).sqrt() / n;
    let inertia = |p: &Point3<f64>| {
        Matrix3::identity() * p.coords.norm_squared() - p.coords * p.coords.transpose()
    };
    let j: Matrix3<f64> = k.model.iter().map(inertia).sum();
    let weighted: Matrix3<f64> = k
        .model
        .iter()
        .zip(&k.sigma)
        .map(|(p, s)| inertia(p) * (s * s))
        .sum();
    let j_inv = j.try_inverse().unwrap();
    let cov = j_inv * weighted * j_inv;
    (t_rms, cov.trace().sqrt())
}

#[test]
fn frame_fit_matches_theory_under_spec_noise() {
    let k = known_frame();
    assert_eq!(k.model.len(), 6);
    let mean_sigma = k.sigma.iter().sum::<f64>() / 6.0;
    // σ = 0.012 + 0.012 × ~2.2 m.
    assert!(
        (0.035..0.042).contains(&mean_sigma),
        "σ {mean_sigma} mm at the reference range"
    );
    let (t_theory, r_theory) = theory(&k);
    let mut rng = ChaCha8Rng::seed_from_u64(20240601);
    let mut t_err = Vec::new();
    let mut r_err = Vec::new();
    let mut measured = vec![Point3::origin(); 6];
    for _ in 0..2000 {
        for ((m, p), s) in measured.iter_mut().zip(&k.model).zip(&k.sigma) {
            *m = k.truth * p + gaussian3(&mut rng) * *s;
        }
        let fit = fit_frame(&k.model, &measured, k.reject_above_mm).unwrap();
        assert_eq!(fit.rejected, 0);
        let (dt, dr) = errors(&fit.pose, &k.truth);
        t_err.push(dt);
        r_err.push(dr);
    }
    let (t_rms, r_rms) = (rms(&t_err), rms(&r_err));
    println!(
        "σ ≈ {mean_sigma:.4} mm; origin RMS {t_rms:.5} mm (theory {t_theory:.5}); \
         rotation RMS {:.3e} deg (theory {:.3e})",
        r_rms.to_degrees(),
        r_theory.to_degrees()
    );
    assert!(
        (t_rms / t_theory - 1.0).abs() < 0.25,
        "{t_rms} vs {t_theory}"
    );
    assert!(
        (r_rms / r_theory - 1.0).abs() < 0.25,
        "{r_rms} vs {r_theory}"
    );
}

#[test]
fn planted_outlier_is_rejected() {
    let k = known_frame();
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let mut clean_err = Vec::new();
    let mut rejected_err = Vec::new();
    let mut unrejected_err = Vec::new();
    let mut measured = vec![Point3::origin(); 6];
    for trial in 0..500 {
        for ((m, p), s) in measured.iter_mut().zip(&k.model).zip(&k.sigma) {
            *m = k.truth * p + gaussian3(&mut rng) * *s;
        }
        let clean = fit_frame(&k.model, &measured, k.reject_above_mm).unwrap();
        clean_err.push(errors(&clean.pose, &k.truth).0);
        let bad = trial % 6;
        let [x, y, z]: [f64; 3] = UnitSphere.sample(&mut rng);
        measured[bad] += Vector3::new(x, y, z) * 2.0;
        let fit = fit_frame(&k.model, &measured, k.reject_above_mm).unwrap();
        assert_eq!((fit.used, fit.rejected), (5, 1), "trial {trial}");
        // Exactly the fit without the planted point.
        let keep: Vec<usize> = (0..6).filter(|&i| i != bad).collect();
        let model5: Vec<_> = keep.iter().map(|&i| k.model[i]).collect();
        let measured5: Vec<_> = keep.iter().map(|&i| measured[i]).collect();
        let five = fit_frame(&model5, &measured5, f64::INFINITY).unwrap();
        let (dt, dr) = errors(&fit.pose, &five.pose);
        assert!(dt < 1e-9 && dr < 1e-12);
        rejected_err.push(errors(&fit.pose, &k.truth).0);
        let naive = fit_frame(&k.model, &measured, f64::INFINITY).unwrap();
        unrejected_err.push(errors(&naive.pose, &k.truth).0);
    }
    let (clean, rejected, naive) = (rms(&clean_err), rms(&rejected_err), rms(&unrejected_err));
    println!("origin RMS: clean {clean:.5} mm, outlier rejected {rejected:.5}, kept {naive:.5}");
    // Five points instead of six: theory √(6/5) ≈ 1.10 plus a small lever-arm term.
    assert!(rejected / clean < 1.3, "{rejected} vs {clean}");
    assert!(naive > 5.0 * clean);
}

/// Setup for the pipeline tests: a cell, its frames, the true world poses at `f_m`.
fn pipeline(cell: &CellConfig, f_m: &Pose) -> (CellFrames, Pose, Pose) {
    let frames = CellFrames::from_config(cell);
    let (w_m, w_f) = frames.world_poses(&frames.platform_for(f_m));
    (frames, w_m, w_f)
}

fn expected_state(w_m: &Pose, f_m: &Pose, pitch: f64) -> [f64; 12] {
    let m_f = f_m.inverse();
    let a_r = rotation_vector_deg(w_m);
    let o = rotation_vector_deg(&m_f);
    let t = w_m.translation.vector;
    let p = m_f.translation.vector;
    [
        t.x,
        t.y,
        t.z,
        a_r.x,
        a_r.y,
        a_r.z,
        p.x,
        p.y,
        p.z,
        o.x,
        o.y,
        assembly_cell::camera::wrap_deg(o.z, pitch),
    ]
}

#[test]
fn pipeline_without_noise_is_exact() {
    let mut cell = CellConfig::reference();
    cell.imperfections.camera_noise = false;
    cell.imperfections.dropped_points = false;
    cell.imperfections.outliers = false;
    let pitch = cell.hole_pitch_deg();
    let relative_poses = [
        pose_from_mm_deg(Vector3::new(1.5, -2.0, 20.0), Vector3::new(0.3, -0.2, 10.0)),
        pose_from_mm_deg(
            Vector3::new(-30.0, 12.0, 55.0),
            Vector3::new(-1.0, 0.5, -40.0),
        ),
        Pose::identity(),
    ];
    for f_m in relative_poses {
        let (frames, w_m, w_f) = pipeline(&cell, &f_m);
        let camera = SimCamera::new(&cell, &frames, 1.0);
        let estimator = StateEstimator::new(&cell, &frames);
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let mut frame = CameraFrame::default();
        camera.capture_into(&w_m, &w_f, &mut rng, &mut frame);
        let m = estimator.estimate(&frame, 1.0).unwrap();
        let state = m.state(pitch);
        let want = expected_state(&w_m, &f_m, pitch);
        for (i, (g, w)) in state.iter().zip(want).enumerate() {
            assert!((g - w).abs() < 1e-9, "s[{i}] = {g}, expected {w}");
        }
    }
}

/// First-order covariance of P (mm) and O (deg) from the point noise: numerical Jacobian of
/// the noise-free pipeline with respect to each point coordinate.
fn linearised_sigma(
    camera: &SimCamera,
    estimator: &StateEstimator,
    w_m: &Pose,
    w_f: &Pose,
    pitch: f64,
) -> [f64; 6] {
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let base = camera.capture(w_m, w_f, &mut rng);
    assert_eq!(base.points.len(), 12, "noise-free capture for the Jacobian");
    let s0 = estimator.estimate(&base, 1.0).unwrap().state(pitch);
    let h = 1e-4;
    let mut var = [0.0; 6];
    for i in 0..base.points.len() {
        let sigma = camera.sigma_at_mm(&base.points[i].position_mm);
        for axis in 0..3 {
            let mut frame = base.clone();
            frame.points[i].position_mm[axis] += h;
            let s = estimator.estimate(&frame, 1.0).unwrap().state(pitch);
            for (k, v) in var.iter_mut().enumerate() {
                let d = (s[6 + k] - s0[6 + k]) / h;
                *v += d * d * sigma * sigma;
            }
        }
    }
    var.map(f64::sqrt)
}

#[test]
fn pipeline_with_noise_stays_within_five_sigma() {
    let reference = CellConfig::reference();
    let pitch = reference.hole_pitch_deg();
    let docked = Pose::identity();
    // The Jacobian comes from a noise-free twin of the same cell.
    let mut quiet = reference.clone();
    quiet.imperfections.camera_noise = false;
    quiet.imperfections.dropped_points = false;
    quiet.imperfections.outliers = false;
    let (frames, w_m, w_f) = pipeline(&reference, &docked);
    let quiet_camera = SimCamera::new(&quiet, &frames, 1.0);
    let estimator = StateEstimator::new(&reference, &frames);
    let sigma = linearised_sigma(&quiet_camera, &estimator, &w_m, &w_f, pitch);
    let truth = expected_state(&w_m, &docked, pitch);

    for (label, cell) in [
        ("noise only", {
            let mut c = quiet.clone();
            c.imperfections.camera_noise = true;
            c
        }),
        ("reference imperfections", reference.clone()),
    ] {
        let camera = SimCamera::new(&cell, &frames, 1.0);
        let mut rng = ChaCha8Rng::seed_from_u64(99);
        let mut frame = CameraFrame::default();
        let n = 10_000;
        let mut sum = [0.0; 6];
        let mut sum_sq = [0.0; 6];
        let mut rejected = 0;
        for i in 0..n {
            camera.capture_into(&w_m, &w_f, &mut rng, &mut frame);
            let m = estimator.estimate(&frame, 1.0).unwrap();
            rejected += m.fit_c1.rejected + m.fit_c2.rejected;
            let s = m.state(pitch);
            for k in 0..6 {
                let e = s[6 + k] - truth[6 + k];
                // 5σ per capture for the first 200 captures (chance of a miss ≈ 7e-4); over
                // all 10k captures (60k values) a 5σ value turns up with ≈ 3% chance, so 6σ.
                let bound = if i < 200 { 5.0 } else { 6.0 };
                assert!(
                    e.abs() < bound * sigma[k],
                    "{label}: capture {i}: state[{}] off by {e} (σ {})",
                    6 + k,
                    sigma[k]
                );
                sum[k] += e;
                sum_sq[k] += e * e;
            }
        }
        let std: Vec<f64> = (0..6)
            .map(|k| (sum_sq[k] / n as f64 - (sum[k] / n as f64).powi(2)).sqrt())
            .collect();
        println!(
            "{label}: std P = [{:.4}, {:.4}, {:.4}] mm, O = [{:.5}, {:.5}, {:.5}] deg \
             ({rejected} points dropped or rejected); linearised σ P = [{:.4}, {:.4}, {:.4}] mm, \
             O = [{:.5}, {:.5}, {:.5}] deg",
            std[0],
            std[1],
            std[2],
            std[3],
            std[4],
            std[5],
            sigma[0],
            sigma[1],
            sigma[2],
            sigma[3],
            sigma[4],
            sigma[5]
        );
        for k in 0..6 {
            assert!(
                (std[k] / sigma[k] - 1.0).abs() < 0.1,
                "{label}: std {} vs σ {}",
                std[k],
                sigma[k]
            );
        }
    }
}
