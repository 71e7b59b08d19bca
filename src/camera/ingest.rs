//! Camera ingestion's pure core: from captures and executed moves to the state the controller
//! sees, one [`Shot`] in and one [`Estimate`] out. The twin's environment calls it inline; the
//! service runs it on a thread of its own (`cell::ingestion`).

use super::uncertainty::NoiseScale;
use super::{
    CameraError, CameraFrame, Fusion, FusionTuning, StateEstimator, StateFilter, state_vector,
};
use crate::config::cell::CellConfig;
use crate::geometry::{CellFrames, Move, Pose};

/// What ingestion is given after each move: the capture and what the robot did before it.
#[derive(Debug, Clone, Default)]
pub struct Shot {
    /// The first capture of an episode: forget the last one first.
    pub new_episode: bool,
    /// The move the robot executed since the last capture (none: vetoed, or still).
    pub executed: Option<Move>,
    /// The part of the commanded move still to come after the exposure, in {M} (none when the
    /// robot had stopped).
    pub remaining: Option<Pose>,
    pub frame: CameraFrame,
}

/// What ingestion makes of a shot: the state the controller and the supervisor work from.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Estimate {
    /// The fused 12-dim state (A from the last frame; P and O from the filter). Kept from the
    /// last usable frame when this one was not.
    pub state: [f64; 12],
    /// The state from the last usable frame alone.
    pub raw_state: [f64; 12],
    /// The fused estimate of {F} in {M}; none when this capture could not be used.
    pub m_f: Option<Pose>,
    /// A snapshot of the state filter.
    pub filter: StateFilter,
    /// Whether this capture was usable.
    pub fresh: bool,
}

/// Fits each capture, carries it forward by the part of the move still to come, fuses it into
/// the state filter and forms the 12-dim state (docs/design.md §5).
#[derive(Debug, Clone)]
pub struct Ingest {
    estimator: StateEstimator,
    filter: StateFilter,
    /// How noisy the camera really is, learned from each frame's fit residuals.
    noise: NoiseScale,
    hole_pitch_deg: f64,
    state: [f64; 12],
    raw_state: [f64; 12],
    estimated_m_f: Option<Pose>,
}

impl Ingest {
    pub fn new(cell: &CellConfig, frames: &CellFrames) -> Self {
        Ingest {
            estimator: StateEstimator::new(cell, frames),
            filter: StateFilter::new(FusionTuning::default()),
            noise: NoiseScale::default(),
            hole_pitch_deg: cell.hole_pitch_deg(),
            state: [0.0; 12],
            raw_state: [0.0; 12],
            estimated_m_f: None,
        }
    }

    /// Takes in one shot: forgets the last episode if this one is new, predicts the executed
    /// move, then ingests the capture.
    pub fn take(&mut self, shot: &Shot) -> Estimate {
        if shot.new_episode {
            self.reset();
        }
        if let Some(step) = &shot.executed {
            self.predict(step);
        }
        let fresh = self.ingest(&shot.frame, shot.remaining.as_ref()).is_ok();
        Estimate {
            state: self.state,
            raw_state: self.raw_state,
            m_f: self.estimated_m_f,
            filter: self.filter,
            fresh,
        }
    }

    /// Forgets everything: a new episode starts blind.
    fn reset(&mut self) {
        self.filter.reset();
        self.noise = NoiseScale::default();
        self.filter.set_noise_scale(self.noise.scale());
        self.state = [0.0; 12];
        self.raw_state = [0.0; 12];
        self.estimated_m_f = None;
    }

    /// The robot executed `step`: the filter carries its estimate along.
    fn predict(&mut self, step: &Move) {
        self.filter.predict(step);
    }

    /// Takes in one capture. `remaining` is the part of the commanded move still to come after
    /// the exposure, in {M} (none when the robot had stopped). On success the fused estimate
    /// and the state move on; on failure (no fit, or a frame the filter holds back) the state
    /// stays as it was and the estimate is stale (the supervisor then vetoes every move).
    fn ingest(&mut self, frame: &CameraFrame, remaining: Option<&Pose>) -> Result<(), CameraError> {
        let mut measurement = match self.estimator.estimate(frame, self.noise.scale()) {
            Ok(measurement) => measurement,
            Err(error) => {
                self.estimated_m_f = None;
                return Err(error);
            }
        };
        if let Some(remaining) = remaining {
            measurement.w_m *= remaining;
            measurement.m_f = remaining.inverse() * measurement.m_f;
        }
        self.noise
            .add(measurement.residual_squares, measurement.residual_dof);
        self.filter.set_noise_scale(self.noise.scale());
        let covariance = measurement.covariance * self.noise.cautious_variance_factor();
        if let Fusion::HeldBack { sigmas } = self.filter.update(&measurement.m_f, &covariance) {
            self.estimated_m_f = None;
            return Err(CameraError::HeldBack { sigmas });
        }
        self.raw_state = measurement.state(self.hole_pitch_deg);
        let fused = self.filter.m_f().unwrap_or(measurement.m_f);
        self.state = state_vector(&measurement.w_m, &fused, self.hole_pitch_deg);
        self.estimated_m_f = Some(fused);
        Ok(())
    }
}
