//! Reference checks of the collision module: the OBB test against parry3d-f64's cuboid test, the
//! exact clearance against brute-force sampling of the shaft's surface, and the swept clearance
//! against densely interpolated poses.

use assembly_cell::collision::clearance::{Clearance, PartGeometry, clearance, clearance_along};
use assembly_cell::collision::obb::Obb;
use assembly_cell::config::cell::CellConfig;
use assembly_cell::geometry::pose::{Pose, interpolate};
use nalgebra::{Point3, Translation3, UnitQuaternion, Vector3};
use parry3d_f64::glamx::{DQuat, DVec3};
use parry3d_f64::math::Pose as ParryPose;
use parry3d_f64::query;
use parry3d_f64::shape::Cuboid;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::f64::consts::TAU;
use std::time::Instant;

fn random_rotation(rng: &mut ChaCha8Rng) -> UnitQuaternion<f64> {
    // Shoemake: uniform over SO(3).
    let (u1, u2, u3): (f64, f64, f64) = (rng.random(), rng.random(), rng.random());
    let (a, b) = ((1.0 - u1).sqrt(), u1.sqrt());
    UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
        b * (TAU * u3).cos(),
        a * (TAU * u2).sin(),
        a * (TAU * u2).cos(),
        b * (TAU * u3).sin(),
    ))
}

fn random_unit(rng: &mut ChaCha8Rng) -> Vector3<f64> {
    random_rotation(rng) * Vector3::z()
}

fn parry_pose(centre: &Vector3<f64>, rot: &UnitQuaternion<f64>) -> ParryPose {
    ParryPose::from_parts(
        DVec3::new(centre.x, centre.y, centre.z),
        DQuat::from_xyzw(rot.i, rot.j, rot.k, rot.w),
    )
}

#[test]
fn obb_agrees_with_parry_cuboids() {
    let mut rng = ChaCha8Rng::seed_from_u64(0x0bb);
    let pairs = 100_000;
    let (mut intersecting, mut near_touching, mut disagreements) = (0usize, 0usize, 0usize);
    let mut obb_ns = 0u128;
    for _ in 0..pairs {
        let ea = Vector3::from_fn(|_, _| rng.random_range(1.0..300.0));
        let eb = Vector3::from_fn(|_, _| rng.random_range(1.0..300.0));
        let (ra, rb) = (random_rotation(&mut rng), random_rotation(&mut rng));
        let ca = Vector3::from_fn(|_, _| rng.random_range(-500.0..500.0));
        // Centre distance up to the sum of the half diagonals: about half the pairs intersect.
        let reach = 0.5 * (ea.norm() + eb.norm());
        let cb = ca + random_unit(&mut rng) * rng.random_range(0.0..1.15 * reach);
        let a = Obb::new(&Pose::from_parts(Translation3::from(ca), ra), ea);
        let b = Obb::new(&Pose::from_parts(Translation3::from(cb), rb), eb);
        let start = Instant::now();
        let ours = a.intersects(&b);
        obb_ns += start.elapsed().as_nanos();
        let (pa, pb) = (parry_pose(&ca, &ra), parry_pose(&cb, &rb));
        let (sa, sb) = (
            Cuboid::new(DVec3::new(ea.x, ea.y, ea.z) * 0.5),
            Cuboid::new(DVec3::new(eb.x, eb.y, eb.z) * 0.5),
        );
        let theirs = query::intersection_test(&pa, &sa, &pb, &sb)
            .expect("cuboid pair is supported")
            .intersecting;
        intersecting += usize::from(theirs);
        if ours != theirs {
            // Only pairs within 1e-9 mm of touching may disagree.
            let depth = query::contact(&pa, &sa, &pb, &sb, 1.0)
                .expect("cuboid pair is supported")
                .map_or(f64::INFINITY, |c| c.dist);
            if depth.abs() < 1e-9 {
                near_touching += 1;
            } else {
                disagreements += 1;
                eprintln!("disagreement: ours {ours}, parry {theirs}, contact dist {depth}");
            }
        }
    }
    println!(
        "OBB vs parry: {pairs} pairs, {intersecting} intersecting, {disagreements} disagreements, \
         {near_touching} within 1e-9 mm of touching; OBB test ≈ {:.0} ns per pair (incl. timer)",
        obb_ns as f64 / pairs as f64
    );
    assert_eq!(disagreements, 0);
    assert!(
        intersecting > pairs * 3 / 10 && intersecting < pairs * 7 / 10,
        "{intersecting}"
    );
}

/// A pose of {M} in {F}: insertion depth `depth` (tip at z_F = −depth when upright), lateral
/// offset of the tip centre, tilt about a random horizontal axis, random spin about the shaft.
fn pose_near_bore(
    rng: &mut ChaCha8Rng,
    max_offset: f64,
    depth: (f64, f64),
    max_tilt_deg: f64,
    shaft_length: f64,
) -> Pose {
    let spin = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), rng.random_range(0.0..TAU));
    let dir = rng.random_range(0.0..TAU);
    let tilt_axis = nalgebra::Unit::new_normalize(Vector3::new(dir.cos(), dir.sin(), 0.0));
    let tilt = UnitQuaternion::from_axis_angle(
        &tilt_axis,
        rng.random_range(0.0..max_tilt_deg).to_radians(),
    );
    let rot = tilt * spin;
    let off_dir = rng.random_range(0.0..TAU);
    let off = rng.random_range(0.0..max_offset);
    let tip = Vector3::new(
        off * off_dir.cos(),
        off * off_dir.sin(),
        -rng.random_range(depth.0..depth.1),
    );
    let origin = tip + rot * Vector3::new(0.0, 0.0, shaft_length);
    Pose::from_parts(Translation3::from(origin), rot)
}

/// What dense sampling of the surfaces sees: the largest r over sampled shaft points inside the
/// wall's slab (−∞ if none), and whether a sampled point lies in Segment II's solid: in the wall
/// (the closed slab, r more than 1e-9 mm beyond the bore), below the bottom, or a point of the
/// shoulder face below the seating face.
struct Brute {
    max_r_in_slab: f64,
    contact: bool,
}

fn brute_force(g: &PartGeometry, pose: &Pose, n_phi: usize) -> Brute {
    let h = g.bore_depth_mm + g.axial_relief_mm;
    let (rs, len) = (g.shaft_radius_mm, g.shaft_length_mm);
    let eps = 1e-9;
    let mut out = Brute {
        max_r_in_slab: f64::NEG_INFINITY,
        contact: false,
    };
    let shaft_point = |p: Point3<f64>, out: &mut Brute| {
        let r = p.x.hypot(p.y);
        if p.z <= eps && p.z >= -h - eps {
            out.max_r_in_slab = out.max_r_in_slab.max(r);
            if r > g.bore_radius_mm + eps {
                out.contact = true;
            }
        }
        if p.z < -h - eps {
            out.contact = true;
        }
    };
    let a = pose.rotation * Vector3::z();
    let rows = 31;
    for k in 0..n_phi {
        let phi = TAU * k as f64 / n_phi as f64;
        let (s, c) = phi.sin_cos();
        // The generator line at angle φ: a grid along it, plus where it meets the slab's faces.
        for row in 0..rows {
            let z_m = -len * row as f64 / (rows - 1) as f64;
            shaft_point(pose * Point3::new(rs * c, rs * s, z_m), &mut out);
        }
        let foot = pose * Point3::new(rs * c, rs * s, 0.0);
        if a.z.abs() > 1e-12 {
            for plane in [0.0, -h] {
                let z_m = ((plane - foot.z) / a.z).clamp(-len, 0.0);
                shaft_point(pose * Point3::new(rs * c, rs * s, z_m), &mut out);
            }
        }
        // The tip face.
        for ring in 1..8 {
            let rho = rs * ring as f64 / 8.0;
            shaft_point(pose * Point3::new(rho * c, rho * s, -len), &mut out);
        }
        // The shoulder face: its outer rim and a ring inside it.
        for rho in [g.body_radius_mm, 0.5 * (g.body_radius_mm + rs)] {
            let p = pose * Point3::new(rho * c, rho * s, 0.0);
            if p.z < -g.axial_relief_mm - eps {
                out.contact = true;
            }
        }
    }
    // The two rims of the shaft, eight times denser.
    for k in 0..8 * n_phi {
        let phi = TAU * k as f64 / (8 * n_phi) as f64;
        let (s, c) = phi.sin_cos();
        for z_m in [-len, 0.0] {
            shaft_point(pose * Point3::new(rs * c, rs * s, z_m), &mut out);
        }
    }
    out
}

#[derive(Default)]
struct Tally {
    poses: usize,
    brute_contacts: usize,
    exact_contacts: usize,
    exact_only: usize,
    exact_only_deepest: f64,
    worst_gap: f64,
}

#[test]
fn clearance_agrees_with_brute_force_sampling() {
    let phi170 = PartGeometry::from_config(&CellConfig::reference());
    let phi200 = PartGeometry::from_config(
        &CellConfig::load(std::path::Path::new("cells/phi200.toml")).expect("phi200 cell"),
    );
    let mut rng = ChaCha8Rng::seed_from_u64(0xc1ea);
    // (name, part geometry, count, lateral offset, tip depth range, tilt)
    let groups = [
        ("near the bore", phi170, 8_000, 0.2, (-5.0, 62.0), 0.3),
        ("wider", phi170, 2_000, 5.0, (-5.0, 62.0), 10.0),
        ("large", phi170, 500, 150.0, (-20.0, 62.0), 40.0),
        (
            "phi200 near the bore",
            phi200,
            1_000,
            0.3,
            (-5.0, 62.0),
            0.3,
        ),
    ];
    let n_phi = 1440;
    for (name, g, count, offset, depth, tilt) in groups {
        let mut t = Tally::default();
        for i in 0..count {
            let pose = pose_near_bore(&mut rng, offset, depth, tilt, g.shaft_length_mm);
            let exact = clearance(&g, &pose);
            let brute = brute_force(&g, &pose, n_phi);
            t.poses += 1;
            // Sampled points are real points of the shaft: the exact maximum is never smaller.
            if brute.max_r_in_slab.is_finite() {
                let brute_wall = g.bore_radius_mm - brute.max_r_in_slab;
                assert!(
                    exact.wall_mm <= brute_wall + 1e-9,
                    "{name} {i}: exact {exact:?} above sampled wall gap {brute_wall}, {pose:?}"
                );
                t.worst_gap = t.worst_gap.max(brute_wall - exact.wall_mm);
            }
            if brute.contact {
                t.brute_contacts += 1;
                assert!(
                    !exact.is_clear(),
                    "{name} {i}: false clear {exact:?}, {pose:?}"
                );
            }
            if !exact.is_clear() {
                t.exact_contacts += 1;
                if !brute.contact {
                    t.exact_only += 1;
                    t.exact_only_deepest = t.exact_only_deepest.max(-exact.min_mm());
                }
            }
        }
        println!(
            "clearance vs brute force, {name}: {} poses, {} contacts sampled, {} exact contacts, \
             {} exact-only contacts (deepest {:.2e} mm), largest sampled-minus-exact wall gap \
             {:.2e} mm",
            t.poses,
            t.brute_contacts,
            t.exact_contacts,
            t.exact_only,
            t.exact_only_deepest,
            t.worst_gap
        );
        if name.ends_with("near the bore") {
            // Grazing contacts finer than the sampling grid are all the brute force can miss.
            assert!(t.exact_only_deepest < 1e-3, "{}", t.exact_only_deepest);
            assert!(t.worst_gap < 1e-3, "{}", t.worst_gap);
            assert!(t.brute_contacts > t.poses / 10 && t.exact_contacts < t.poses * 9 / 10);
        }
    }
}

#[test]
fn clearance_along_never_misses_a_sampled_contact() {
    let cell = CellConfig::reference();
    let g = PartGeometry::from_config(&cell);
    let mut rng = ChaCha8Rng::seed_from_u64(0x5ee9);
    let moves = 2_000;
    let fractions = 1_000;
    let (mut dense_contacts, mut along_contacts, mut along_only) = (0, 0, 0);
    for i in 0..moves {
        let from = if i % 2 == 0 {
            pose_near_bore(&mut rng, 0.1, (-3.0, 61.0), 0.2, g.shaft_length_mm)
        } else {
            pose_near_bore(&mut rng, 3.0, (-8.0, 20.0), 1.5, g.shaft_length_mm)
        };
        let (max_mm, max_deg): (f64, f64) = match i % 4 {
            0 | 1 => (0.1, 0.03),
            2 => (1.0, 0.2),
            _ => (5.0, 1.0),
        };
        let step = Pose::from_parts(
            Translation3::from(random_unit(&mut rng) * rng.random_range(0.0..max_mm)),
            UnitQuaternion::from_axis_angle(
                &nalgebra::Unit::new_normalize(random_unit(&mut rng)),
                rng.random_range(0.0..max_deg).to_radians(),
            ),
        );
        let to = step * from;
        let dense = (1..=fractions)
            .map(|k| clearance(&g, &interpolate(&from, &to, k as f64 / fractions as f64)))
            .fold(
                Clearance {
                    wall_mm: f64::INFINITY,
                    seat_mm: f64::INFINITY,
                },
                |acc, c| Clearance {
                    wall_mm: acc.wall_mm.min(c.wall_mm),
                    seat_mm: acc.seat_mm.min(c.seat_mm),
                },
            );
        let along = clearance_along(&g, &from, &to);
        if !dense.is_clear() {
            dense_contacts += 1;
            assert!(
                !along.is_clear(),
                "move {i}: missed contact, dense {dense:?}, along {along:?}"
            );
        }
        if !along.is_clear() {
            along_contacts += 1;
            along_only += usize::from(dense.is_clear());
        }
        // The sweep samples the end pose, so it is never more optimistic there.
        assert!(along.min_mm() <= clearance(&g, &to).min_mm());
    }
    println!(
        "clearance_along: {moves} moves, {dense_contacts} with a contact at 1000 fractions, \
         {along_contacts} reported, {along_only} reported only by the sweep"
    );
    assert!(dense_contacts > moves / 10 && dense_contacts < moves * 9 / 10);
}

#[test]
fn clearance_speed_report() {
    // Rough timings for the report; no assertion on time (tests run in parallel).
    let g = PartGeometry::from_config(&CellConfig::reference());
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let poses: Vec<Pose> = (0..10_000)
        .map(|_| pose_near_bore(&mut rng, 0.2, (-5.0, 62.0), 0.3, g.shaft_length_mm))
        .collect();
    let start = Instant::now();
    let mut sink = 0.0;
    for _ in 0..20 {
        for p in &poses {
            sink += clearance(&g, p).min_mm();
        }
    }
    let per = start.elapsed().as_nanos() as f64 / (20.0 * poses.len() as f64);
    let bore = g.bore_obb();
    let boxes: Vec<Obb> = poses.iter().map(|p| g.shaft_obb(p)).collect();
    let start = Instant::now();
    let mut hits = 0usize;
    for _ in 0..20 {
        for b in &boxes {
            hits += usize::from(b.separating_axis(&bore).is_none());
        }
    }
    let per_obb = start.elapsed().as_nanos() as f64 / (20.0 * boxes.len() as f64);
    // Fine insertion steps inside or just above the bore that stay clear.
    let mut moves = Vec::new();
    while moves.len() < 5_000 {
        let from = pose_near_bore(&mut rng, 0.03, (-3.0, 59.0), 0.01, g.shaft_length_mm);
        let lateral = Vector3::new(
            rng.random_range(-0.005..0.005),
            rng.random_range(-0.005..0.005),
            0.0,
        );
        let step = Pose::from_parts(
            Translation3::from(lateral + Vector3::new(0.0, 0.0, rng.random_range(-0.5..0.5))),
            UnitQuaternion::from_scaled_axis(random_unit(&mut rng) * 0.003f64.to_radians()),
        );
        let to = step * from;
        if clearance(&g, &from).is_clear() && clearance(&g, &to).is_clear() {
            moves.push((from, to));
        }
    }
    let mut worst = 0u128;
    let start = Instant::now();
    for (a, b) in &moves {
        let t = Instant::now();
        sink += clearance_along(&g, a, b).min_mm();
        worst = worst.max(t.elapsed().as_nanos());
    }
    let per_along = start.elapsed().as_nanos() as f64 / moves.len() as f64;
    println!(
        "OBB test ≈ {per_obb:.0} ns ({hits} overlaps); clearance ≈ {per:.0} ns per call; clearance_along on fine clear insertion steps ≈ \
         {per_along:.0} ns mean, {worst} ns worst ({sink:.1})"
    );
}
