//! State fusion: the cell's estimate of {F} in {M} from the camera's frames and the robot's own
//! commanded moves. One frame alone is noisy (σ ≈ 0.023 mm per axis of P against a 0.05 mm
//! radial clearance); the cell predicts each commanded move, blends each new frame in, and learns
//! how the robot really moves sideways per mm commanded (its calibration error bends every move
//! the same way). The state vector, the supervisor and every controller use this estimate.
//!
//! Position P: per lateral axis a four-state Kalman filter over the offset (mm) and the sideways
//! drift per mm commanded along x, y and z of {M}; the axial component has a one-state filter.
//! Orientation O: predicted, then blended with a fixed gain. A frame that disagrees with the
//! estimate by more than the jump thresholds is held back, not blended: one gross frame (an
//! outlier the point fit let through) must not throw away what the filter has learned. Only a
//! second frame that agrees with the held one, or the first frame of an episode, resets the
//! estimate to the measurement (keeping the learned drift).

use crate::geometry::Move;
use crate::geometry::pose::{self, Pose};
use nalgebra::{Matrix2x3, Matrix4, RowVector3, Vector3, Vector4};

/// Filter settings; the defaults suit the reference camera (σ ≈ 0.024 mm and 0.013 deg per frame).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FusionTuning {
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

impl Default for FusionTuning {
    fn default() -> Self {
        FusionTuning {
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
#[derive(Debug, Clone, Copy, PartialEq)]
struct LateralFilter {
    state: Vector4<f64>,
    covariance: Matrix4<f64>,
}

/// The fused estimate. `Copy`, so an observation can carry a snapshot of it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StateFilter {
    tuning: FusionTuning,
    m_f: Option<Pose>,
    lateral: [LateralFilter; 2],
    axial_variance: f64,
    /// The last frame that disagreed with the estimate, carried along by the moves since.
    held_back: Option<Pose>,
}

/// What [`StateFilter::update`] made of a frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Fusion {
    /// Blended into the estimate.
    Blended,
    /// The estimate starts again from this frame: the first of an episode, or one that confirms
    /// a held-back jump.
    Reset,
    /// Held back: it disagrees with the estimate by this much, and no earlier frame confirms it.
    HeldBack { gap_mm: f64, gap_deg: f64 },
}

impl StateFilter {
    pub fn new(tuning: FusionTuning) -> Self {
        let mut tracker = StateFilter {
            tuning,
            m_f: None,
            lateral: [LateralFilter {
                state: Vector4::zeros(),
                covariance: Matrix4::zeros(),
            }; 2],
            axial_variance: 0.0,
            held_back: None,
        };
        tracker.reset();
        tracker
    }

    pub fn reset(&mut self) {
        self.m_f = None;
        self.held_back = None;
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

    /// Predicts an executed move (commanded, in {M}).
    pub fn predict(&mut self, executed: &Move) {
        let t = self.tuning;
        let Some(m_f) = self.m_f.as_mut() else {
            return;
        };
        *m_f = executed.as_pose().inverse() * *m_f;
        if let Some(held) = self.held_back.as_mut() {
            *held = executed.as_pose().inverse() * *held;
        }
        let commanded = executed.translation_mm;
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
        self.axial_variance += (t.move_error_per_mm * commanded.norm()).powi(2) + 1e-8;
    }

    /// Takes in a new measurement of {F} in {M}: blends it in, starts again from it, or holds
    /// it back (see the module's comment).
    pub fn update(&mut self, measured: &Pose) -> Fusion {
        let t = self.tuning;
        let r = t.measurement_sd_mm.powi(2);
        let Some(predicted) = self.m_f else {
            self.set_to(*measured, r);
            return Fusion::Reset;
        };
        let (gap_mm, gap_deg) = gap(&predicted, measured);
        if gap_mm > t.jump_mm || gap_deg > t.jump_deg {
            let confirmed = self.held_back.is_some_and(|held| {
                let (mm, deg) = gap(&held, measured);
                mm <= t.jump_mm && deg <= t.jump_deg
            });
            if confirmed {
                self.set_to(*measured, r);
                return Fusion::Reset;
            }
            self.held_back = Some(*measured);
            return Fusion::HeldBack { gap_mm, gap_deg };
        }
        self.held_back = None;
        let mut blended = pose::interpolate(&predicted, measured, t.orientation_gain);
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
        Fusion::Blended
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
        self.held_back = None;
    }

    /// The estimate of {F} in {M}, once there is one.
    pub fn m_f(&self) -> Option<Pose> {
        self.m_f
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

/// How far apart two estimates of {F} in {M} are (mm, deg).
fn gap(a: &Pose, b: &Pose) -> (f64, f64) {
    (
        (b.translation.vector - a.translation.vector).norm(),
        b.rotation.angle_to(&a.rotation).to_degrees(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::pose::pose_from_mm_deg;

    fn measured(p: [f64; 3]) -> Pose {
        pose_from_mm_deg(Vector3::from(p), Vector3::zeros())
    }

    #[test]
    fn predicts_moves_and_averages_agreeing_measurements() {
        let mut filter = StateFilter::new(FusionTuning::default());
        filter.update(&measured([1.0, 0.0, -10.0]));
        // Move 1 mm in x: predicted P_x = 0; a measurement of 0.1 pulls the estimate part-way.
        filter.predict(&Move::translation(1.0, 0.0, 0.0));
        filter.update(&measured([0.1, 0.0, -10.0]));
        let p = filter.m_f().unwrap().translation.vector;
        assert!(p.x > 0.0 && p.x < 0.1, "{p}");
        // A 3 mm surprise is held back; a second frame that agrees with it resets to it.
        let before = filter.m_f();
        assert!(matches!(
            filter.update(&measured([3.0, 0.0, -10.0])),
            Fusion::HeldBack { gap_mm, .. } if (gap_mm - 2.9).abs() < 0.1
        ));
        assert_eq!(filter.m_f(), before);
        assert_eq!(filter.update(&measured([3.01, 0.0, -10.0])), Fusion::Reset);
        assert!((filter.m_f().unwrap().translation.vector.x - 3.01).abs() < 1e-12);
    }

    #[test]
    fn one_gross_frame_leaves_the_estimate_and_its_certainty_alone() {
        // Twenty agreeing frames make the estimate sure; one frame 1 mm and 0.5 deg off between
        // them is held back each time, and the estimate goes on as if it had not come.
        let steady = measured([0.02, -0.01, -30.0]);
        let gross = pose_from_mm_deg(Vector3::new(1.0, -0.01, -30.0), Vector3::new(0.5, 0.0, 0.0));
        let mut clean = StateFilter::new(FusionTuning::default());
        let mut disturbed = StateFilter::new(FusionTuning::default());
        for i in 0..20 {
            clean.update(&steady);
            disturbed.update(&steady);
            if i % 5 == 4 {
                let verdict = disturbed.update(&gross);
                assert!(matches!(verdict, Fusion::HeldBack { gap_deg, .. } if gap_deg > 0.49));
            }
        }
        assert_eq!(disturbed.m_f(), clean.m_f());
        assert_eq!(disturbed.lateral_sd_mm(), clean.lateral_sd_mm());
        assert!(clean.lateral_sd_mm() < 0.01, "{}", clean.lateral_sd_mm());
    }

    #[test]
    fn a_held_back_frame_is_carried_along_by_the_moves_until_confirmed() {
        // The part really is 2 mm further in x than estimated: the first frame is held back, the
        // robot then moves 1 mm in x, and the next frame (1 mm from the first one as seen
        // before the move, but where the first one says it should be now) confirms it.
        let mut filter = StateFilter::new(FusionTuning::default());
        filter.update(&measured([0.0, 0.0, -10.0]));
        assert!(matches!(
            filter.update(&measured([2.0, 0.0, -10.0])),
            Fusion::HeldBack { .. }
        ));
        filter.predict(&Move::translation(1.0, 0.0, 0.0));
        assert_eq!(filter.update(&measured([1.0, 0.0, -10.0])), Fusion::Reset);
        assert!((filter.m_f().unwrap().translation.vector.x - 1.0).abs() < 1e-12);
    }

    #[test]
    fn learns_a_steady_sideways_drift() {
        // Each Δz = −1 mm moves {M} an extra −0.002 mm in x, so P_x grows by 0.002.
        let mut filter = StateFilter::new(FusionTuning::default());
        let (mut truth_x, mut truth_z) = (0.0, -80.0);
        filter.update(&measured([truth_x, 0.0, truth_z]));
        for _ in 0..60 {
            filter.predict(&Move::translation(0.0, 0.0, -1.0));
            truth_x += 0.002;
            truth_z += 1.0;
            filter.update(&measured([truth_x, 0.0, truth_z]));
        }
        assert!(
            (filter.drift()[(0, 2)] - 0.002).abs() < 2e-4,
            "{}",
            filter.drift()
        );
        assert!((filter.m_f().unwrap().translation.vector.x - truth_x).abs() < 1e-3);
        assert!(filter.lateral_sd_mm() < 0.01);
        // Uncertainty grows with the length of the next axial move.
        assert!(filter.lateral_sd_after_mm(-5.0) > filter.lateral_sd_after_mm(-1.0));
    }
}
