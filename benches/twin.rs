//! Speed of the twin's parts (docs/design.md §9). Run: `cargo bench --bench twin`.

use assembly_cell::camera::{CameraFrame, SimCamera, StateEstimator};
use assembly_cell::collision::clearance::{PartGeometry, clearance};
use assembly_cell::config::cell::CellConfig;
use assembly_cell::geometry::CellFrames;
use assembly_cell::geometry::fit::fit_frame;
use assembly_cell::geometry::pose::pose_from_mm_deg;
use assembly_cell::kinematics::StewartGeometry;
use assembly_cell::policy::{self, eval};
use assembly_cell::sim::{AssemblyEnv, EnvOptions};
use criterion::{Criterion, criterion_group, criterion_main};
use nalgebra::{Point3, Vector3};
use rand::SeedableRng;
use std::hint::black_box;

fn kinematics(c: &mut Criterion) {
    let cell = CellConfig::reference();
    let robot = StewartGeometry::from_config(&cell.robot);
    let home = robot.home_pose();
    let target =
        home * pose_from_mm_deg(Vector3::new(3.0, -2.0, -4.0), Vector3::new(0.4, -0.3, 0.5));
    let legs = robot.leg_lengths_mm(&target);
    c.bench_function("ik", |b| {
        b.iter(|| robot.leg_lengths_mm(black_box(&target)))
    });
    // Warm start: from the pose one step (≈5 mm, 1 deg) away, as in the control loop.
    let previous =
        home * pose_from_mm_deg(Vector3::new(0.0, 0.0, -1.0), Vector3::new(0.0, 0.0, -0.5));
    c.bench_function("fk_warm", |b| {
        b.iter(|| robot.forward(black_box(&legs), &previous).unwrap())
    });
    let far = home
        * pose_from_mm_deg(
            Vector3::new(80.0, -60.0, -120.0),
            Vector3::new(4.0, -3.0, 2.0),
        );
    let far_legs = robot.leg_lengths_mm(&far);
    c.bench_function("fk_cold_from_home", |b| {
        b.iter(|| robot.forward(black_box(&far_legs), &home).unwrap())
    });
    let warm = robot.forward(&legs, &previous).unwrap();
    let cold = robot.forward(&far_legs, &home).unwrap();
    eprintln!(
        "fk iterations: warm {} (residual {:.1e} mm), cold {} (residual {:.1e} mm)",
        warm.iterations, warm.residual_mm, cold.iterations, cold.residual_mm
    );
}

fn collision(c: &mut Criterion) {
    let cell = CellConfig::reference();
    let parts = PartGeometry::from_config(&cell);
    let inserted = pose_from_mm_deg(
        Vector3::new(0.02, -0.01, 30.0),
        Vector3::new(0.02, 0.01, 0.3),
    );
    let shaft = parts.shaft_obb(&inserted);
    let bore = parts.bore_obb();
    c.bench_function("obb_sat", |b| {
        b.iter(|| black_box(&shaft).intersects(black_box(&bore)))
    });
    c.bench_function("clearance_inserted", |b| {
        b.iter(|| clearance(black_box(&parts), black_box(&inserted)))
    });
}

fn camera(c: &mut Criterion) {
    let cell = CellConfig::reference();
    let frames = CellFrames::from_config(&cell);
    let truth = pose_from_mm_deg(
        Vector3::new(100.0, 20.0, 2000.0),
        Vector3::new(10.0, -5.0, 30.0),
    );
    let model = frames.c1_points_mm.clone();
    let measured: Vec<Point3<f64>> = model
        .iter()
        .enumerate()
        .map(|(i, p)| truth * p + Vector3::new(0.01, -0.02, 0.015) * (i as f64 - 2.5))
        .collect();
    c.bench_function("frame_fit_6_points", |b| {
        b.iter(|| fit_frame(black_box(&model), black_box(&measured), 0.3).unwrap())
    });
    let camera = SimCamera::new(&cell, &frames, 1.0);
    let estimator = StateEstimator::new(&cell, &frames);
    let (w_m, w_f) = frames.world_poses(&frames.platform_for(&nalgebra::Isometry3::identity()));
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
    let mut frame = CameraFrame::default();
    c.bench_function("capture_and_estimate", |b| {
        b.iter(|| {
            camera.capture_into(&w_m, &w_f, &mut rng, &mut frame);
            estimator.estimate(&frame, 1.0)
        })
    });
}

fn environment(c: &mut Criterion) {
    let cell = CellConfig::reference();
    let mut env = AssemblyEnv::new(&cell, EnvOptions::from_cell(&cell));
    let mut expert = policy::builtin("expert", &cell).unwrap();
    let mut seed = 0;
    let mut observation = env.reset(seed).unwrap();
    // One step of a whole expert episode mix (far, near, in the bore), resetting when done.
    c.bench_function("env_step_expert_mix", |b| {
        b.iter(|| {
            let decision = expert.act(&observation);
            let result = env.step(&decision.action).unwrap();
            observation = if result.done {
                seed += 1;
                expert.reset(seed);
                env.reset(seed).unwrap()
            } else {
                result.observation
            };
        })
    });
    let mut group = c.benchmark_group("eval");
    group.sample_size(10);
    group.bench_function("expert_1000_episodes", |b| {
        b.iter(|| {
            let make = || policy::builtin("expert", &cell).unwrap();
            eval::evaluate(&cell, EnvOptions::from_cell(&cell), 1000, 7, &make, &|_| {})
        })
    });
    group.finish();
}

criterion_group!(benches, kinematics, collision, camera, environment);
criterion_main!(benches);
