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
