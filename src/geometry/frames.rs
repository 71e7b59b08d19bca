//! The fixed frames of a cell (paper Fig. 2, Eq. 1), built once from the cell file.
//!
//! - {O}: robot base, at the centre of the base joint circle, z up.
//! - {P}: moving platform; at home it sits `home_height_mm` above {O}, unrotated.
//! - {M}: Segment I, on the shaft axis at the shoulder, z from the tip back to the shoulder; the
//!   shaft occupies z ∈ [-engaged_length, 0].
//! - {F}: Segment II, at the centre of the bore entrance, z out of the bore; the bore occupies
//!   z ∈ [-depth, 0]. {M} = {F} when docked, and the docked pose is the robot's home pose.
//! - {C1}, {C2}: the fixtures carrying the coded points, rigidly on Segment I and Segment II.
//! - {W}: the (left) camera, z along the line of sight.
//!
//! Naming: `a_b` is the pose of frame B in frame A (maps B coordinates to A coordinates).

use super::pose::{Pose, rotation_x_deg};
use crate::config::cell::CellConfig;
use crate::config::fixture_layout::LayoutPoint;
use nalgebra::{Isometry3, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};

/// Fixed transforms and coded-point layouts of one cell.
#[derive(Debug, Clone)]
pub struct CellFrames {
    /// Segment I on the platform: {M} in {P}.
    pub p_m: Pose,
    /// Segment II on its fixture: {F} in the robot base {O}.
    pub o_f: Pose,
    /// Fixture {C1} on Segment I: {C1} in {M}.
    pub m_c1: Pose,
    /// Fixture {C2} on Segment II: {C2} in {F}.
    pub f_c2: Pose,
    /// The camera: {W} in {O}.
    pub o_w: Pose,
    /// Coded points of fixture {C1}, in {C1} coordinates (mm).
    pub c1_points_mm: Vec<Point3<f64>>,
    /// Coded points of fixture {C2}, in {C2} coordinates (mm).
    pub c2_points_mm: Vec<Point3<f64>>,
    /// The ids a camera names {C1}'s coded points by, beside `c1_points_mm`.
    pub c1_labels: Vec<u16>,
    /// The ids of {C2}'s coded points, beside `c2_points_mm`.
    pub c2_labels: Vec<u16>,
    /// The calibration's σ per axis of each of {C1}'s coded points, mm (0: not given).
    pub c1_sigma_mm: Vec<f64>,
    /// The same for {C2}'s.
    pub c2_sigma_mm: Vec<f64>,
}

impl CellFrames {
    pub fn from_config(cell: &CellConfig) -> Self {
        let p_m = Translation3::new(0.0, 0.0, cell.robot.segment_mount_mm) * rotation_x_deg(180.0);
        let o_p_home = Isometry3::translation(0.0, 0.0, cell.robot.home_height_mm);
        let o_f = o_p_home * p_m;
        let m_c1 = Isometry3::translation(0.0, 0.0, cell.camera.fixture_offset_mm);
        let f_c2 = Isometry3::translation(0.0, 0.0, -cell.camera.fixture_offset_mm);
        let o_w = look_at(
            Vector3::from(cell.camera.position_mm),
            Vector3::from(cell.camera.target_mm),
        );
        let (c1, c2) = match &cell.camera.calibrated_layout {
            Some(layout) => (Layout::of(&layout.c1), Layout::of(&layout.c2)),
            None => {
                let ring = Layout::ring(
                    cell.camera.points_per_fixture as usize,
                    cell.camera.fixture_radius_mm,
                    cell.camera.fixture_height_spread_mm,
                );
                (ring.clone(), ring)
            }
        };
        CellFrames {
            p_m,
            o_f,
            m_c1,
            f_c2,
            o_w,
            c1_points_mm: c1.points_mm,
            c2_points_mm: c2.points_mm,
            c1_labels: c1.labels,
            c2_labels: c2.labels,
            c1_sigma_mm: c1.sigma_mm,
            c2_sigma_mm: c2.sigma_mm,
        }
    }

    /// The platform pose that puts Segment I at `f_m` ({M} in {F}).
    pub fn platform_for(&self, f_m: &Pose) -> Pose {
        self.o_f * f_m * self.p_m.inverse()
    }

    /// {M} in {F} for a platform pose {P} in {O}.
    pub fn segment_for(&self, o_p: &Pose) -> Pose {
        self.o_f.inverse() * o_p * self.p_m
    }

    /// {M} in {W} and {F} in {W} for a platform pose: what the camera sees.
    pub fn world_poses(&self, o_p: &Pose) -> (Pose, Pose) {
        let w_o = self.o_w.inverse();
        (w_o * o_p * self.p_m, w_o * self.o_f)
    }
}

/// The camera frame at `eye` looking at `target`, z along the line of sight, y roughly down.
fn look_at(eye: Vector3<f64>, target: Vector3<f64>) -> Pose {
    let z = (target - eye).normalize();
    let up = if z.cross(&Vector3::z()).norm() > 1e-6 {
        Vector3::z()
    } else {
        Vector3::x()
    };
    let x = z.cross(&up).normalize();
    let y = z.cross(&x);
    let rotation = Rotation3::from_basis_unchecked(&[x, y, z]);
    Isometry3::from_parts(
        Translation3::from(eye),
        UnitQuaternion::from_rotation_matrix(&rotation),
    )
}

/// One fixture's coded points: positions, labels and calibration σ side by side.
#[derive(Clone)]
struct Layout {
    points_mm: Vec<Point3<f64>>,
    labels: Vec<u16>,
    sigma_mm: Vec<f64>,
}

impl Layout {
    /// `count` coded points evenly on a ring, alternately `spread_mm` above and below its
    /// plane, labelled 0 to `count` − 1, with no calibration σ.
    fn ring(count: usize, radius_mm: f64, spread_mm: f64) -> Layout {
        let points_mm = (0..count)
            .map(|k| {
                let angle = std::f64::consts::TAU * k as f64 / count as f64 + 0.1;
                let z = if k % 2 == 0 { spread_mm } else { -spread_mm };
                Point3::new(radius_mm * angle.cos(), radius_mm * angle.sin(), z)
            })
            .collect();
        Layout {
            points_mm,
            labels: (0..count)
                .map(|k| u16::try_from(k).unwrap_or(u16::MAX))
                .collect(),
            sigma_mm: vec![0.0; count],
        }
    }

    /// A calibrated fixture's points, in the file's order.
    fn of(points: &[LayoutPoint]) -> Layout {
        Layout {
            points_mm: points.iter().map(|p| p.position_mm.into()).collect(),
            labels: points.iter().map(|p| p.label).collect(),
            sigma_mm: points.iter().map(|p| p.sigma_mm.unwrap_or(0.0)).collect(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn docked_pose_is_home_and_frames_round_trip() {
        let cell = CellConfig::reference();
        let frames = CellFrames::from_config(&cell);
        let home = Isometry3::translation(0.0, 0.0, cell.robot.home_height_mm);
        let f_m = frames.segment_for(&home);
        assert!(f_m.translation.vector.norm() < 1e-12);
        assert!(f_m.rotation.angle() < 1e-12);
        // The shaft tip (z_M = -60) is up in the world, towards Segment II.
        let tip_in_o = frames.o_f * f_m * Point3::new(0.0, 0.0, -60.0);
        assert!(tip_in_o.z > frames.o_f.translation.vector.z);
        let back = frames.platform_for(&f_m);
        assert!((back.translation.vector - home.translation.vector).norm() < 1e-9);
    }

    #[test]
    fn camera_looks_at_target() {
        let cell = CellConfig::reference();
        let frames = CellFrames::from_config(&cell);
        let target = Point3::from(Vector3::from(cell.camera.target_mm));
        let in_w = frames.o_w.inverse() * target;
        assert!(in_w.x.abs() < 1e-9 && in_w.y.abs() < 1e-9 && in_w.z > 0.0);
    }
}
