//! The simulated binocular camera.

use super::{CameraFrame, CodedPoint, Fixture, FrameKind, PointNoise};
use crate::config::cell::CellConfig;
use crate::geometry::{CellFrames, Pose};
use nalgebra::{Point3, Vector3};
use rand::Rng;
use rand_distr::{Distribution, StandardNormal, UnitSphere};

/// The twin's camera: coded-point layouts on Segment I and II, and its error model.
///
/// Per capture and per coded point, in this order: dropped with `dropout_probability` (if
/// `imperfections.dropped_points`); Gaussian noise per axis with σ = (`noise_base_mm` +
/// `noise_per_m_mm` × range in m) × `noise_scale` (if `imperfections.camera_noise`); with
/// `outlier_probability` a gross error of `outlier_magnitude_mm` in a uniformly random
/// direction (if `imperfections.outliers`). Range is the point's distance from the camera
/// origin (the origin of {W}). A switch that is off draws no random numbers.
#[derive(Debug, Clone)]
pub struct SimCamera {
    /// {C1}'s coded points in {M} coordinates, mm.
    c1_in_m: Vec<Point3<f64>>,
    /// {C2}'s coded points in {F} coordinates, mm.
    c2_in_f: Vec<Point3<f64>>,
    noise: bool,
    sheet: PointNoise,
    noise_scale: f64,
    /// 0 when dropped points are switched off.
    dropout_probability: f64,
    /// 0 when outliers are switched off.
    outlier_probability: f64,
    outlier_magnitude_mm: f64,
    nominal_sigma_mm: f64,
}

impl SimCamera {
    /// A camera for `cell`. `noise_scale` multiplies the point noise σ (CLI `--noise-scale`);
    /// the switches come from `cell.imperfections` (`camera_noise`, `dropped_points`,
    /// `outliers`).
    pub fn new(cell: &CellConfig, frames: &CellFrames, noise_scale: f64) -> Self {
        let camera = &cell.camera;
        let switches = &cell.imperfections;
        SimCamera {
            c1_in_m: frames
                .c1_points_mm
                .iter()
                .map(|p| frames.m_c1 * p)
                .collect(),
            c2_in_f: frames
                .c2_points_mm
                .iter()
                .map(|p| frames.f_c2 * p)
                .collect(),
            noise: switches.camera_noise,
            sheet: PointNoise::of(camera),
            noise_scale,
            dropout_probability: if switches.dropped_points {
                camera.dropout_probability
            } else {
                0.0
            },
            outlier_probability: if switches.outliers {
                camera.outlier_probability
            } else {
                0.0
            },
            outlier_magnitude_mm: camera.outlier_magnitude_mm,
            nominal_sigma_mm: nominal_point_sigma_mm(cell, frames) * noise_scale,
        }
    }

    /// Simulates one capture of Segment I at `w_m` ({M} in {W}) and Segment II at `w_f`
    /// ({F} in {W}) into `frame` (cleared first; its buffer is reused).
    pub fn capture_into(
        &self,
        w_m: &Pose,
        w_f: &Pose,
        rng: &mut impl Rng,
        frame: &mut CameraFrame,
    ) {
        frame.points.clear();
        frame.kind = FrameKind::Measured;
        for (fixture, pose, points) in [
            (Fixture::C1, w_m, &self.c1_in_m),
            (Fixture::C2, w_f, &self.c2_in_f),
        ] {
            for (k, local) in points.iter().enumerate() {
                if self.dropout_probability > 0.0 && rng.random::<f64>() < self.dropout_probability
                {
                    continue;
                }
                let mut position = pose * local;
                if self.noise {
                    let sigma = self.sigma_at_mm(&position);
                    let n = Vector3::new(
                        rng.sample::<f64, _>(StandardNormal),
                        rng.sample::<f64, _>(StandardNormal),
                        rng.sample::<f64, _>(StandardNormal),
                    );
                    position += n * sigma;
                }
                if self.outlier_probability > 0.0 && rng.random::<f64>() < self.outlier_probability
                {
                    let [x, y, z]: [f64; 3] = UnitSphere.sample(rng);
                    position += Vector3::new(x, y, z) * self.outlier_magnitude_mm;
                }
                frame.points.push(CodedPoint {
                    fixture,
                    id: u16::try_from(k).unwrap_or(u16::MAX),
                    position_mm: position,
                });
            }
        }
    }

    /// [`capture_into`](Self::capture_into) into a new frame.
    pub fn capture(&self, w_m: &Pose, w_f: &Pose, rng: &mut impl Rng) -> CameraFrame {
        let mut frame = CameraFrame {
            points: Vec::with_capacity(self.c1_in_m.len() + self.c2_in_f.len()),
            sequence: 0,
            kind: FrameKind::Measured,
        };
        self.capture_into(w_m, w_f, rng, &mut frame);
        frame
    }

    /// Per-axis noise σ (mm) of a point at `position` in {W}, `noise_scale` included, whether
    /// or not camera noise is switched on.
    pub fn sigma_at_mm(&self, position: &Point3<f64>) -> f64 {
        self.sheet.at_mm(position) * self.noise_scale
    }

    /// The expected per-axis σ (mm) of a coded point at the docked pose (mean over both
    /// fixtures' points), `noise_scale` included, whether or not camera noise is switched on:
    /// the scale for rejection thresholds.
    pub fn nominal_sigma_mm(&self) -> f64 {
        self.nominal_sigma_mm
    }

    /// The multiplier on the point noise σ.
    pub fn noise_scale(&self) -> f64 {
        self.noise_scale
    }
}

/// Mean per-axis point σ (mm) over both fixtures' coded points at the docked (home) pose, from
/// the cell's noise model with noise scale 1.
pub fn nominal_point_sigma_mm(cell: &CellConfig, frames: &CellFrames) -> f64 {
    let home = Pose::translation(0.0, 0.0, cell.robot.home_height_mm);
    let (w_m, w_f) = frames.world_poses(&home);
    let c1 = frames.c1_points_mm.iter().map(|p| w_m * frames.m_c1 * p);
    let c2 = frames.c2_points_mm.iter().map(|p| w_f * frames.f_c2 * p);
    let (sum, count) = c1.chain(c2).fold((0.0, 0usize), |(s, n), p| {
        (s + p.coords.norm() / 1000.0, n + 1)
    });
    let mean_range_m = if count > 0 { sum / count as f64 } else { 0.0 };
    PointNoise::of(&cell.camera).at_range_mm(mean_range_m)
}
