use super::*;
use crate::config::cell::CellConfig;
use crate::geometry::pose::pose_from_mm_deg;

fn reference() -> StewartGeometry {
    StewartGeometry::from_config(&CellConfig::reference().robot)
}

/// Rotation between two poses, rad; accurate for tiny angles (unlike `acos`-based angles).
fn rotation_error_rad(a: &Pose, b: &Pose) -> f64 {
    let rel = a.rotation.inverse() * b.rotation;
    2.0 * rel.imag().norm().atan2(rel.w.abs())
}

fn angle_deg(v: &Vector3<f64>) -> f64 {
    v.y.atan2(v.x).to_degrees().rem_euclid(360.0)
}

#[test]
fn joint_layout_of_the_reference_cell() {
    let g = reference();
    let base = [345.0, 15.0, 105.0, 135.0, 225.0, 255.0];
    let platform = [315.0, 45.0, 75.0, 165.0, 195.0, 285.0];
    for i in 0..6 {
        assert!(
            (angle_deg(&g.base_joints_mm[i]) - base[i]).abs() < 1e-9,
            "base {i}"
        );
        assert!(
            (angle_deg(&g.platform_joints_mm[i]) - platform[i]).abs() < 1e-9,
            "platform {i}"
        );
        assert!((g.base_joints_mm[i].norm() - 500.0).abs() < 1e-9);
        assert!((g.platform_joints_mm[i].norm() - 300.0).abs() < 1e-9);
        assert_eq!(g.base_joints_mm[i].z, 0.0);
        assert_eq!(g.platform_joints_mm[i].z, 0.0);
    }
}

#[test]
fn the_cell_files_stroke_check_sees_the_home_legs_of_the_kinematics() {
    let robot = CellConfig::reference().robot;
    assert_eq!(
        robot.home_leg_lengths_mm(),
        StewartGeometry::from_config(&robot).home_leg_lengths_mm()
    );
}

#[test]
fn home_leg_length_matches_hand_computation() {
    // Every leg spans 30 deg between base (r = 500) and platform (r = 300) joint:
    // d² = 500² + 300² - 2·500·300·cos 30° = 340000 - 150000·√3, L = sqrt(800² + d²).
    let d2 = 500.0_f64.powi(2) + 300.0_f64.powi(2) - 2.0 * 500.0 * 300.0 * 30f64.to_radians().cos();
    let hand = (800.0_f64.powi(2) + d2).sqrt();
    assert!((hand - 848.641_490_185_737).abs() < 1e-9);
    let g = reference();
    for (i, l) in g.home_leg_lengths_mm().iter().enumerate() {
        assert!((l - hand).abs() < 1e-9, "leg {i}: {l} vs {hand}");
    }
    assert_eq!(
        g.home_pose().translation.vector,
        Vector3::new(0.0, 0.0, 800.0)
    );
    assert_eq!(g.home_pose().rotation, UnitQuaternion::identity());
}

#[test]
fn pure_lift_lengthens_every_leg_by_the_formula() {
    let g = reference();
    let d2 = 340000.0 - 150000.0 * 3f64.sqrt();
    let lift = Isometry3::translation(0.0, 0.0, 900.0);
    for l in g.leg_lengths_mm(&lift) {
        assert!((l - (900.0_f64.powi(2) + d2).sqrt()).abs() < 1e-9);
    }
}

#[test]
fn stroke_error_carries_the_numbers() {
    let g = reference();
    // Raise the platform until the legs (all equal) exceed 1050 mm.
    let high = Isometry3::translation(0.0, 0.0, 1020.0);
    let err = g.inverse_checked(&high).unwrap_err();
    let expected_len = g.leg_lengths_mm(&high)[0];
    assert!(expected_len > 1050.0);
    match &err {
        KinematicsError::LegOutOfStroke {
            leg,
            length_mm,
            min_mm,
            max_mm,
        } => {
            assert_eq!(*leg, 0);
            assert_eq!(*length_mm, expected_len);
            assert_eq!((*min_mm, *max_mm), (650.0, 1050.0));
        }
        other => panic!("unexpected {other:?}"),
    }
    let msg = err.to_string();
    assert_eq!(
        msg,
        format!("leg 1 out of stroke: {expected_len:.3} mm not in [650.000, 1050.000] mm")
    );
    assert_eq!(err.code(), "leg_out_of_stroke");

    // A sideways shift stretches one particular leg first; the message names it 1-based.
    let side = Isometry3::translation(-420.0, 0.0, 800.0);
    let legs = g.leg_lengths_mm(&side);
    let first = legs
        .iter()
        .position(|l| !(650.0..=1050.0).contains(l))
        .unwrap();
    match g.inverse_checked(&side).unwrap_err() {
        KinematicsError::LegOutOfStroke { leg, length_mm, .. } => {
            assert_eq!(leg, first);
            assert_eq!(length_mm, legs[first]);
        }
        other => panic!("unexpected {other:?}"),
    }
}

#[test]
fn other_errors_have_codes_and_numbers() {
    let e = KinematicsError::NearSingular {
        conditioning: 0.0123,
        threshold: 0.02,
    };
    assert_eq!(e.code(), "near_singular");
    assert!(e.to_string().contains("0.01230") && e.to_string().contains("0.02000"));
    let e = KinematicsError::NoConvergence {
        iterations: 20,
        residual_mm: 1.5e-3,
    };
    assert_eq!(e.code(), "no_convergence");
    assert!(e.to_string().contains("20") && e.to_string().contains("1.500e-3"));
    let e = KinematicsError::NonFinite { what: "start pose" };
    assert_eq!(e.code(), "non_finite");
    assert_eq!(e.to_string(), "non-finite start pose");
}

#[test]
fn inverse_checked_accepts_home_and_rejects_non_finite() {
    let g = reference();
    assert_eq!(
        g.inverse_checked(&g.home_pose()).unwrap(),
        g.home_leg_lengths_mm()
    );
    let bad = Isometry3::translation(f64::NAN, 0.0, 800.0);
    assert_eq!(
        g.inverse_checked(&bad).unwrap_err(),
        KinematicsError::NonFinite {
            what: "platform pose"
        }
    );
}

#[test]
fn inverse_checked_refuses_near_singular_poses() {
    let mut g = reference();
    let c = g.conditioning(&g.home_pose());
    g.singularity_threshold = c + 0.01;
    match g.inverse_checked(&g.home_pose()).unwrap_err() {
        KinematicsError::NearSingular {
            conditioning,
            threshold,
        } => {
            assert_eq!(conditioning, c);
            assert_eq!(threshold, c + 0.01);
        }
        other => panic!("unexpected {other:?}"),
    }
}

#[test]
fn fk_of_home_legs_from_home_returns_home() {
    let g = reference();
    let home = g.home_pose();
    let sol = g.forward(&g.home_leg_lengths_mm(), &home).unwrap();
    assert!(sol.iterations <= 1, "{} iterations", sol.iterations);
    assert!(sol.residual_mm <= 1e-9);
    assert!((sol.pose.translation.vector - home.translation.vector).norm() < 1e-9);
    assert!(rotation_error_rad(&sol.pose, &home) < 1e-12);
}

#[test]
fn fk_recovers_a_tilted_shifted_pose() {
    let g = reference();
    let target = pose_from_mm_deg(
        Vector3::new(40.0, -25.0, 760.0),
        Vector3::new(3.0, -2.0, 5.0),
    );
    let legs = g.inverse_checked(&target).unwrap();
    let sol = g.forward(&legs, &g.home_pose()).unwrap();
    assert!((sol.pose.translation.vector - target.translation.vector).norm() < 1e-9);
    assert!(rotation_error_rad(&sol.pose, &target) < 1e-9);
    assert!(sol.iterations <= 8);
    // Warm start within a few mm / 1 deg.
    let near = pose_from_mm_deg(
        Vector3::new(43.0, -22.0, 763.0),
        Vector3::new(3.5, -2.5, 5.5),
    );
    let warm = g.forward(&legs, &near).unwrap();
    assert!(warm.iterations <= 5, "{} iterations", warm.iterations);
    assert!((warm.pose.translation.vector - target.translation.vector).norm() < 1e-9);
    assert!(rotation_error_rad(&warm.pose, &target) < 1e-9);
}

#[test]
fn fk_refuses_non_finite_input_and_reports_no_convergence() {
    let g = reference();
    let home = g.home_pose();
    let mut legs = g.home_leg_lengths_mm();
    legs[2] = f64::INFINITY;
    assert_eq!(
        g.forward(&legs, &home).unwrap_err(),
        KinematicsError::NonFinite {
            what: "leg lengths"
        }
    );
    let bad = Isometry3::translation(0.0, f64::NAN, 800.0);
    assert_eq!(
        g.forward(&g.home_leg_lengths_mm(), &bad).unwrap_err(),
        KinematicsError::NonFinite { what: "start pose" }
    );
    // Impossible legs (one far too long for the others) cannot be solved.
    let mut legs = g.home_leg_lengths_mm();
    legs[0] = 5000.0;
    let err = g.forward(&legs, &home).unwrap_err();
    assert!(
        matches!(
            err,
            KinematicsError::NoConvergence { .. } | KinematicsError::NearSingular { .. }
        ),
        "{err:?}"
    );
}

#[test]
fn joint_offsets_change_the_leg_lengths() {
    let g = reference();
    let mut base = [Vector3::zeros(); 6];
    let mut platform = [Vector3::zeros(); 6];
    base[1] = Vector3::new(0.3, -0.2, 0.1);
    platform[4] = Vector3::new(0.0, 0.0, 0.5);
    let t = g.with_joint_offsets(&base, &platform);
    assert_eq!(t.base_joints_mm[1], g.base_joints_mm[1] + base[1]);
    assert_eq!(
        t.platform_joints_mm[4],
        g.platform_joints_mm[4] + platform[4]
    );
    let nominal = g.home_leg_lengths_mm();
    let true_legs = t.home_leg_lengths_mm();
    for i in 0..6 {
        if i == 1 || i == 4 {
            assert!((true_legs[i] - nominal[i]).abs() > 1e-3, "leg {i}");
        } else {
            assert_eq!(true_legs[i], nominal[i]);
        }
    }
    // Platform z offset of 0.5 mm on leg 4 at home: the leg grows by about 0.5 · cos(tilt).
    let cos_tilt = 800.0 / nominal[4];
    assert!((true_legs[4] - nominal[4] - 0.5 * cos_tilt).abs() < 1e-3);
    // The true robot's FK of its own legs returns home.
    let sol = t.forward(&true_legs, &g.home_pose()).unwrap();
    assert!((sol.pose.translation.vector - g.home_pose().translation.vector).norm() < 1e-9);
}

#[test]
fn conditioning_is_sane_over_the_workspace() {
    let g = reference();
    let home = g.conditioning(&g.home_pose());
    assert!(home > 0.0 && home <= 1.0, "{home}");
    for (t, r) in [
        (Vector3::new(200.0, 0.0, 800.0), Vector3::zeros()),
        (Vector3::new(0.0, -200.0, 800.0), Vector3::zeros()),
        (Vector3::new(0.0, 0.0, 650.0), Vector3::new(10.0, 0.0, 0.0)),
        (Vector3::new(0.0, 0.0, 900.0), Vector3::new(0.0, -10.0, 0.0)),
        (Vector3::new(0.0, 0.0, 800.0), Vector3::new(0.0, 0.0, 10.0)),
    ] {
        let c = g.conditioning(&pose_from_mm_deg(t, r));
        assert!(c > g.singularity_threshold && c <= 1.0, "{t:?} {r:?}: {c}");
    }
    // A platform rotated 90 deg about z puts the legs in the classic singular configuration
    // region: conditioning collapses.
    let twisted = pose_from_mm_deg(Vector3::new(0.0, 0.0, 800.0), Vector3::new(0.0, 0.0, 90.0));
    assert!(g.conditioning(&twisted) < 0.5 * home);
}

#[test]
fn inverse_jacobian_matches_finite_differences() {
    let g = reference();
    let p = pose_from_mm_deg(
        Vector3::new(20.0, 10.0, 780.0),
        Vector3::new(2.0, 1.0, -3.0),
    );
    let j = g.inverse_jacobian(&p);
    let l0 = g.leg_lengths_mm(&p);
    let h = 1e-6;
    for c in 0..6 {
        let mut d = Vector6::zeros();
        d[c] = h;
        let dr = Vector3::new(d[0], d[1], d[2]);
        let dtheta = Vector3::new(d[3], d[4], d[5]);
        let q = Isometry3::from_parts(
            Translation3::from(p.translation.vector + dr),
            UnitQuaternion::from_scaled_axis(dtheta) * p.rotation,
        );
        let l1 = g.leg_lengths_mm(&q);
        for i in 0..6 {
            let fd = (l1[i] - l0[i]) / h;
            assert!(
                (fd - j[(i, c)]).abs() < 1e-3,
                "J[{i},{c}] {} vs {fd}",
                j[(i, c)]
            );
        }
    }
}
