//! Inverse then forward kinematics round trip over the workspace of the reference cell.

use assembly_cell::config::cell::CellConfig;
use assembly_cell::geometry::pose::Pose;
use assembly_cell::kinematics::StewartGeometry;
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use proptest::prelude::*;
use proptest::test_runner::FileFailurePersistence;
use std::sync::OnceLock;

fn geometry() -> &'static StewartGeometry {
    static G: OnceLock<StewartGeometry> = OnceLock::new();
    G.get_or_init(|| StewartGeometry::from_config(&CellConfig::reference().robot))
}

/// Rotation between two poses, rad; accurate for tiny angles (unlike `acos`-based angles).
fn rotation_error_rad(a: &Pose, b: &Pose) -> f64 {
    let rel = a.rotation.inverse() * b.rotation;
    2.0 * rel.imag().norm().atan2(rel.w.abs())
}

fn translation_error_mm(a: &Pose, b: &Pose) -> f64 {
    (a.translation.vector - b.translation.vector).norm()
}

/// A unit vector from three numbers in [-1, 1] (rejecting near-zero ones).
fn axis(raw: [f64; 3]) -> Option<Vector3<f64>> {
    let v = Vector3::from(raw);
    let n = v.norm();
    (n > 0.1).then(|| v / n)
}

fn pose(translation_mm: Vector3<f64>, axis: Vector3<f64>, angle_rad: f64) -> Pose {
    Isometry3::from_parts(
        Translation3::from(translation_mm),
        UnitQuaternion::from_scaled_axis(axis * angle_rad),
    )
}

proptest! {
    // Poses with a leg out of stroke are rejected (a few percent); allow plenty of rejects.
    #![proptest_config(ProptestConfig {
        max_global_rejects: 100_000,
        failure_persistence: Some(Box::new(FileFailurePersistence::WithSource(
            "proptest-regressions"
        ))),
        ..ProptestConfig::with_cases(10_000)
    })]

    /// Workspace: ±150 mm laterally, -150..+100 mm in height about home, up to 8 deg tilt about
    /// a random axis. FK from home (cold) and from a nearby pose (warm, ≤ 5 mm / 1 deg off) must
    /// both recover the pose to 1e-9 mm / 1e-9 rad; the warm start within 5 iterations.
    #[test]
    fn ik_then_fk_round_trip(
        x in -150.0..150.0f64,
        y in -150.0..150.0f64,
        dz in -150.0..100.0f64,
        raw_axis in prop::array::uniform3(-1.0..1.0f64),
        angle_deg in 0.0..8.0f64,
        raw_warm_axis in prop::array::uniform3(-1.0..1.0f64),
        warm_dir in prop::array::uniform3(-1.0..1.0f64),
        warm_mm in 0.0..5.0f64,
        warm_deg in 0.0..1.0f64,
    ) {
        let g = geometry();
        let axis_v = axis(raw_axis);
        let warm_axis = axis(raw_warm_axis);
        let warm_dir = axis(warm_dir);
        prop_assume!(axis_v.is_some() && warm_axis.is_some() && warm_dir.is_some());
        let target = pose(
            Vector3::new(x, y, g.home_height_mm + dz),
            axis_v.unwrap(),
            angle_deg.to_radians(),
        );
        let legs = g.inverse_checked(&target);
        prop_assume!(legs.is_ok());
        let legs = legs.unwrap();

        let cold = g.forward(&legs, &g.home_pose());
        prop_assert!(cold.is_ok(), "cold FK failed: {:?}", cold);
        let cold = cold.unwrap();
        prop_assert!(cold.residual_mm <= 1e-9, "residual {}", cold.residual_mm);
        let te = translation_error_mm(&cold.pose, &target);
        let re = rotation_error_rad(&cold.pose, &target);
        prop_assert!(te <= 1e-9, "cold translation error {te} mm ({} it)", cold.iterations);
        prop_assert!(re <= 1e-9, "cold rotation error {re} rad ({} it)", cold.iterations);

        let start = Isometry3::from_parts(
            Translation3::from(target.translation.vector + warm_dir.unwrap() * warm_mm),
            UnitQuaternion::from_scaled_axis(warm_axis.unwrap() * warm_deg.to_radians())
                * target.rotation,
        );
        let warm = g.forward(&legs, &start);
        prop_assert!(warm.is_ok(), "warm FK failed: {:?}", warm);
        let warm = warm.unwrap();
        prop_assert!(warm.iterations <= 5, "warm FK took {} iterations", warm.iterations);
        let te = translation_error_mm(&warm.pose, &target);
        let re = rotation_error_rad(&warm.pose, &target);
        prop_assert!(te <= 1e-9, "warm translation error {te} mm");
        prop_assert!(re <= 1e-9, "warm rotation error {re} rad");
    }
}

/// Conditioning stays above the refusal threshold at the edges of the workspace.
#[test]
fn workspace_edges_are_not_near_singular() {
    let g = geometry();
    let h = g.home_height_mm;
    let mut poses = vec![g.home_pose()];
    for t in [
        Vector3::new(200.0, 0.0, h),
        Vector3::new(-200.0, 0.0, h),
        Vector3::new(0.0, 200.0, h),
        Vector3::new(0.0, -200.0, h),
        Vector3::new(0.0, 0.0, h + 200.0),
        Vector3::new(0.0, 0.0, h - 150.0),
    ] {
        for a in [Vector3::x(), Vector3::y(), Vector3::z()] {
            for deg in [-10.0, 0.0, 10.0f64] {
                poses.push(pose(t, a, deg.to_radians()));
            }
        }
    }
    for p in &poses {
        let c = g.conditioning(p);
        assert!(c > g.singularity_threshold, "{p:?}: conditioning {c}");
    }
}

/// Diagnostics: conditioning over the workspace and FK / IK timing. Run with
/// `cargo test --release --test kinematics_roundtrip -- --ignored --nocapture`.
#[test]
#[ignore]
fn diagnostics() {
    use std::time::Instant;
    let g = geometry();
    let h = g.home_height_mm;
    println!("home conditioning {:.4}", g.conditioning(&g.home_pose()));
    for (name, t) in [
        ("x+200", Vector3::new(200.0, 0.0, h)),
        ("x-200", Vector3::new(-200.0, 0.0, h)),
        ("y+200", Vector3::new(0.0, 200.0, h)),
        ("y-200", Vector3::new(0.0, -200.0, h)),
        ("z+200", Vector3::new(0.0, 0.0, h + 200.0)),
        ("z-200", Vector3::new(0.0, 0.0, h - 200.0)),
    ] {
        let c0 = g.conditioning(&pose(t, Vector3::x(), 0.0));
        let tilts: Vec<String> = [
            ("rx+10", Vector3::x(), 10.0),
            ("rx-10", Vector3::x(), -10.0),
            ("ry+10", Vector3::y(), 10.0),
            ("ry-10", Vector3::y(), -10.0),
            ("rz+10", Vector3::z(), 10.0),
            ("rz-10", Vector3::z(), -10.0),
        ]
        .iter()
        .map(|(n, a, d)| {
            format!(
                "{n} {:.4}",
                g.conditioning(&pose(t, *a, f64::to_radians(*d)))
            )
        })
        .collect();
        let legs = g.inverse_checked(&pose(t, Vector3::x(), 0.0));
        println!(
            "{name}: {c0:.4} | {} | ik {:?}",
            tilts.join(", "),
            legs.err().map(|e| e.code())
        );
    }
    for (name, a) in [
        ("rx", Vector3::x()),
        ("ry", Vector3::y()),
        ("rz", Vector3::z()),
    ] {
        for d in [-10.0, 10.0f64] {
            println!(
                "home {name}{d:+}: {:.4}",
                g.conditioning(&pose(Vector3::new(0.0, 0.0, h), a, d.to_radians()))
            );
        }
    }
    // Random sweep: minimum conditioning over the box ±200 mm, ±200 mm height, tilt ≤ 10 deg,
    // over poses whose legs are in stroke.
    let mut seed = 0x1234_5678_9abc_def0_u64;
    let mut rnd = move || {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        (seed >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
    };
    let (mut cmin, mut in_stroke, mut worst) = (f64::INFINITY, 0, g.home_pose());
    let (mut fk_failures, mut fk_worst_te, mut fk_worst_re) = (0, 0.0f64, 0.0f64);
    for _ in 0..200_000 {
        let t = Vector3::new(200.0 * rnd(), 200.0 * rnd(), h + 200.0 * rnd());
        let Some(a) = axis([rnd(), rnd(), rnd()]) else {
            continue;
        };
        let p = pose(t, a, 10f64.to_radians() * (rnd() + 1.0) / 2.0);
        let legs = g.leg_lengths_mm(&p);
        if legs
            .iter()
            .all(|l| (g.leg_min_mm..=g.leg_max_mm).contains(l))
        {
            in_stroke += 1;
            let c = g.conditioning(&p);
            match g.forward(&legs, &g.home_pose()) {
                Ok(s) => {
                    fk_worst_te = fk_worst_te.max(translation_error_mm(&s.pose, &p));
                    fk_worst_re = fk_worst_re.max(rotation_error_rad(&s.pose, &p));
                }
                Err(e) => {
                    fk_failures += 1;
                    println!("cold FK failed at {p:?}: {e}");
                }
            }
            if c < cmin {
                cmin = c;
                worst = p;
            }
        }
    }
    println!("random sweep: {in_stroke} in-stroke poses, min conditioning {cmin:.4} at {worst:?}");
    println!(
        "random sweep cold FK: {fk_failures} failures, worst errors {fk_worst_te:.2e} mm, {fk_worst_re:.2e} rad"
    );

    // Fraction of the round-trip test's pose box that is out of stroke (rejected there).
    let mut out = 0;
    for _ in 0..100_000 {
        let t = Vector3::new(150.0 * rnd(), 150.0 * rnd(), h - 25.0 + 125.0 * rnd());
        let Some(a) = axis([rnd(), rnd(), rnd()]) else {
            continue;
        };
        let p = pose(t, a, 8f64.to_radians() * (rnd() + 1.0) / 2.0);
        out += usize::from(g.inverse_checked(&p).is_err());
    }
    println!("round-trip box: {out} of 100000 poses refused by inverse_checked");

    // FK statistics and timing.
    let mut cold_its = [0u32; 21];
    let mut warm_its = [0u32; 21];
    let mut times = Vec::new();
    let mut cases = Vec::new();
    while cases.len() < 20_000 {
        let t = Vector3::new(150.0 * rnd(), 150.0 * rnd(), h - 25.0 + 125.0 * rnd());
        let Some(a) = axis([rnd(), rnd(), rnd()]) else {
            continue;
        };
        let p = pose(t, a, 8f64.to_radians() * (rnd() + 1.0) / 2.0);
        let Ok(legs) = g.inverse_checked(&p) else {
            continue;
        };
        let Some(da) = axis([rnd(), rnd(), rnd()]) else {
            continue;
        };
        let Some(dt) = axis([rnd(), rnd(), rnd()]) else {
            continue;
        };
        let start = Isometry3::from_parts(
            Translation3::from(p.translation.vector + dt * 5.0 * (rnd() + 1.0) / 2.0),
            UnitQuaternion::from_scaled_axis(da * 1f64.to_radians() * (rnd() + 1.0) / 2.0)
                * p.rotation,
        );
        cases.push((p, legs, start));
    }
    for (_, legs, start) in &cases {
        cold_its[g.forward(legs, &g.home_pose()).unwrap().iterations as usize] += 1;
        warm_its[g.forward(legs, start).unwrap().iterations as usize] += 1;
    }
    println!("cold iterations histogram {cold_its:?}");
    println!("warm iterations histogram {warm_its:?}");
    for (_, legs, start) in &cases {
        let t0 = Instant::now();
        let s = std::hint::black_box(g.forward(std::hint::black_box(legs), start));
        times.push(t0.elapsed().as_nanos() as f64);
        assert!(s.is_ok());
    }
    times.sort_by(f64::total_cmp);
    println!(
        "warm FK: median {:.2} µs, p99 {:.2} µs",
        times[times.len() / 2] / 1e3,
        times[times.len() * 99 / 100] / 1e3
    );
    let t0 = Instant::now();
    let mut acc = 0.0;
    for (p, _, _) in &cases {
        acc += g.leg_lengths_mm(std::hint::black_box(p))[0];
    }
    let ik = t0.elapsed().as_nanos() as f64 / cases.len() as f64;
    std::hint::black_box(acc);
    println!("IK: {ik:.1} ns per pose");
}
