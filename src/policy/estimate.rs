//! A controller-side estimate of the relative pose, as a careful operator forms it: each executed
//! move is predicted, each new camera state is blended in, and the robot's systematic sideways
//! drift while pushing along the axis (its calibration error) is learned and allowed for.
//!
//! Position P: per lateral axis a four-state Kalman filter over the offset (mm) and how far the
//! robot really moves sideways per mm commanded along each axis of {M} (its calibration error
//! bends every move the same way); the axial component has a one-state filter. Orientation O: predicted, then blended
//! with a fixed gain. A large disagreement (the first frame, a move seen part-way) resets the
//! offsets to the measurement and keeps the learned drift.

use crate::geometry::Move;
use crate::geometry::pose::{self, Pose, pose_from_mm_deg};
use crate::sim::Observation;
use nalgebra::{Matrix2x3, Matrix4, RowVector3, Vector3, Vector4};

/// Filter settings; the defaults suit the reference camera (σ ≈ 0.024 mm and 0.013 deg per frame).
#[derive(Debug, Clone, Copy)]
pub struct TrackerTuning {
    /// σ of one measured P component (mm).
    pub measurement_sd_mm: f64,
    /// Weight of a new measured orientation.
    pub orientation_gain: f64,
    /// Relative error of an executed axial move (per mm moved).
    pub move_error_per_mm: f64,
    /// Prior σ of the sideways drift per mm commanded.
    pub drift_prior_sd: f64,
    /// Disagreements beyond these reset the estimate to the measurement.
    pub jump_mm: f64,
    pub jump_deg: f64,
}

impl Default for TrackerTuning {
    fn default() -> Self {
        TrackerTuning {
            measurement_sd_mm: 0.03,
            orientation_gain: 0.35,
            move_error_per_mm: 2e-3,
            drift_prior_sd: 0.002,
            jump_mm: 0.5,
            jump_deg: 0.3,
        }
    }
}

/// One lateral axis: state (offset mm, sideways drift per mm commanded along x, y, z of {M})
/// and its covariance.
#[derive(Debug, Clone, Copy)]
struct LateralFilter {
    state: Vector4<f64>,
    covariance: Matrix4<f64>,
}

#[derive(Debug, Clone)]
pub struct PoseTracker {
    tuning: TrackerTuning,
    m_f: Option<Pose>,
    lateral: [LateralFilter; 2],
    axial_variance: f64,
}

impl PoseTracker {
    pub fn new(tuning: TrackerTuning) -> Self {
        let mut tracker = PoseTracker {
            tuning,
            m_f: None,
            lateral: [LateralFilter {
                state: Vector4::zeros(),
                covariance: Matrix4::zeros(),
            }; 2],
            axial_variance: 0.0,
        };
        tracker.reset();
        tracker
    }

    pub fn reset(&mut self) {
        self.m_f = None;
        let drift_variance = self.tuning.drift_prior_sd.powi(2);
        for filter in &mut self.lateral {
            filter.state = Vector4::zeros();
            filter.covariance = Matrix4::from_diagonal(&Vector4::new(
                0.0,
                drift_variance,
                drift_variance,
                drift_variance,
            ));
        }
    }

    /// Takes in the move executed since the last call (`None` if it was vetoed or there was
    /// none) and the new observation.
    pub fn update(&mut self, executed: Option<&Move>, observation: &Observation) {
        let t = self.tuning;
        if let (Some(m_f), Some(step)) = (self.m_f.as_mut(), executed) {
            *m_f = step.as_pose().inverse() * *m_f;
            let commanded = step.translation_mm;
            let moved = commanded.norm();
            for (axis, filter) in self.lateral.iter_mut().enumerate() {
                // The true move carries drift · command on top of the command.
                let drift = Vector3::new(filter.state[1], filter.state[2], filter.state[3]);
                m_f.translation.vector[axis] -= drift.dot(&commanded);
                let mut f = Matrix4::identity();
                f[(0, 1)] = -commanded.x;
                f[(0, 2)] = -commanded.y;
                f[(0, 3)] = -commanded.z;
                filter.covariance = f * filter.covariance * f.transpose()
                    + Matrix4::from_diagonal(&Vector4::new(1e-8, 1e-12, 1e-12, 1e-12));
                filter.state[0] = m_f.translation.vector[axis];
            }
            self.axial_variance += (t.move_error_per_mm * moved).powi(2) + 1e-8;
        }
        if !observation.measurement_fresh {
            return;
        }
        let s = &observation.state;
        let measured = pose_from_mm_deg(
            Vector3::new(s[6], s[7], s[8]),
            Vector3::new(s[9], s[10], s[11]),
        );
        let r = t.measurement_sd_mm.powi(2);
        let Some(predicted) = self.m_f else {
            self.set_to(measured, r);
            return;
        };
        let gap_mm = (measured.translation.vector - predicted.translation.vector).norm();
        let gap_deg = measured.rotation.angle_to(&predicted.rotation).to_degrees();
        if gap_mm > t.jump_mm || gap_deg > t.jump_deg {
            self.set_to(measured, r);
            return;
        }
        let mut blended = pose::interpolate(&predicted, &measured, t.orientation_gain);
        for (axis, filter) in self.lateral.iter_mut().enumerate() {
            let innovation = measured.translation.vector[axis] - filter.state[0];
            let p = filter.covariance;
            let gain: Vector4<f64> = p.column(0) / (p[(0, 0)] + r);
            filter.state += gain * innovation;
            filter.covariance = (Matrix4::identity() - gain * Vector4::x().transpose()) * p;
            blended.translation.vector[axis] = filter.state[0];
        }
        let gain = self.axial_variance / (self.axial_variance + r);
        blended.translation.vector.z = predicted.translation.vector.z
            + gain * (measured.translation.vector.z - predicted.translation.vector.z);
        self.axial_variance *= 1.0 - gain;
        self.m_f = Some(blended);
    }

    /// Starts again from a measurement, keeping the learned drift.
    fn set_to(&mut self, measured: Pose, variance: f64) {
        for (axis, filter) in self.lateral.iter_mut().enumerate() {
            filter.state[0] = measured.translation.vector[axis];
            for k in 1..4 {
                filter.covariance[(0, k)] = 0.0;
                filter.covariance[(k, 0)] = 0.0;
            }
            filter.covariance[(0, 0)] = variance;
        }
        self.axial_variance = variance;
        self.m_f = Some(measured);
    }

    /// P (mm) and O (deg) of the estimate, as in the state vector.
    pub fn estimate(&self) -> Option<(Vector3<f64>, Vector3<f64>)> {
        self.m_f
            .map(|m_f| (m_f.translation.vector, pose::rotation_vector_deg(&m_f)))
    }

    /// σ of the lateral offset estimate (mm), the larger of the two axes.
    pub fn lateral_sd_mm(&self) -> f64 {
        self.lateral
            .iter()
            .map(|f| f.covariance[(0, 0)].sqrt())
            .fold(0.0, f64::max)
    }

    /// σ of the lateral offset (mm, the larger axis) after an axial move of `dz_mm`, from what is
    /// known now of the offset and of the drift.
    pub fn lateral_sd_after_mm(&self, dz_mm: f64) -> f64 {
        self.lateral
            .iter()
            .map(|f| {
                let p = &f.covariance;
                (p[(0, 0)] - 2.0 * dz_mm * p[(0, 3)] + dz_mm * dz_mm * p[(3, 3)])
                    .max(0.0)
                    .sqrt()
            })
            .fold(0.0, f64::max)
    }

    /// The learned sideways drift: row i is the extra move of {M} along x (i = 0) or y (i = 1)
    /// per mm commanded along x, y and z of {M}.
    pub fn drift(&self) -> Matrix2x3<f64> {
        let row = |f: &LateralFilter| RowVector3::new(f.state[1], f.state[2], f.state[3]);
        Matrix2x3::from_rows(&[row(&self.lateral[0]), row(&self.lateral[1])])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn observation(p: [f64; 3], o: [f64; 3]) -> Observation {
        let mut state = [0.0; 12];
        state[6..9].copy_from_slice(&p);
        state[9..12].copy_from_slice(&o);
        Observation {
            state,
            step: 0,
            measurement_fresh: true,
            last_veto: None,
        }
    }

    #[test]
    fn predicts_moves_and_averages_agreeing_measurements() {
        let mut tracker = PoseTracker::new(TrackerTuning::default());
        tracker.update(None, &observation([1.0, 0.0, -10.0], [0.0, 0.0, 0.0]));
        // Move 1 mm in x: predicted P_x = 0; a measurement of 0.1 pulls the estimate part-way.
        tracker.update(
            Some(&Move::translation(1.0, 0.0, 0.0)),
            &observation([0.1, 0.0, -10.0], [0.0, 0.0, 0.0]),
        );
        let (p, _) = tracker.estimate().unwrap();
        assert!(p.x > 0.0 && p.x < 0.1, "{p}");
        // A 3 mm surprise resets to the measurement.
        tracker.update(None, &observation([3.0, 0.0, -10.0], [0.0, 0.0, 0.0]));
        assert!((tracker.estimate().unwrap().0.x - 3.0).abs() < 1e-12);
    }

    #[test]
    fn learns_a_steady_sideways_drift() {
        // The robot drifts +0.002 mm in P_x per mm pushed in −z of {M} (Δz = −1 mm a step).
        let mut tracker = PoseTracker::new(TrackerTuning::default());
        let mut truth_x = 0.0;
        let mut truth_z = -80.0;
        tracker.update(None, &observation([truth_x, 0.0, truth_z], [0.0; 3]));
        for _ in 0..60 {
            let step = Move::translation(0.0, 0.0, -1.0);
            truth_x += 0.002;
            truth_z += 1.0;
            tracker.update(Some(&step), &observation([truth_x, 0.0, truth_z], [0.0; 3]));
        }
        // Each Δz = −1 mm moved {M} by an extra −0.002 mm in x (P_x grew): drift = 0.002.
        assert!(
            (tracker.drift()[(0, 2)] - 0.002).abs() < 2e-4,
            "{}",
            tracker.drift()
        );
        assert!((tracker.estimate().unwrap().0.x - truth_x).abs() < 1e-3);
    }
}
