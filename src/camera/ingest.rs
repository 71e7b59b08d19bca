//! Camera ingestion's pure core: from captures and executed moves to the state the controller
//! sees, one [`Shot`] in and one [`Estimate`] out. The twin's environment calls it inline; the
//! service runs it on a thread of its own (`cell::ingestion`).

use super::drift::DriftKnowledge;
use super::uncertainty::{NoiseScale, relative_covariance_of};
use super::{
    CameraError, CameraFrame, FrameKind, Fusion, FusionTuning, StateEstimator, StateFilter,
    state_vector,
};
use crate::config::cell::CellConfig;
use crate::geometry::{CellFrames, Move, Pose};
use nalgebra::Matrix6;
use static_segment::{StaticFrame, StaticSegment};

mod static_segment;

/// What ingestion is given after each move: the capture and what the robot did before it.
#[derive(Debug, Clone, Default)]
pub struct Shot {
    /// The first capture of an episode: forget the last one first.
    pub new_episode: bool,
    /// With `new_episode`: the robot hit something or faulted since the last episode, so what
    /// the cell remembers of its drift is forgotten too.
    pub forget_robot: bool,
    /// The move the robot executed since the last capture (none: vetoed, or still).
    pub executed: Option<Move>,
    /// The part of the commanded move still to come after the exposure, in {M} (none when the
    /// robot had stopped).
    pub remaining: Option<Pose>,
    pub frame: CameraFrame,
}

/// A camera fault ingestion noticed (docs/estimation.md, faults).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Detected {
    /// A coded point has been missing from [`OCCLUSION_FRAMES`] frames in a row; the fits go on
    /// without it (their covariance grows accordingly).
    Occlusion,
    /// The camera has sent the same frame [`FROZEN_FRAMES`] times in a row.
    FrozenCamera,
    /// A frame older than one already taken in; it is dropped.
    OutOfOrder,
    /// The measured pose jumped, confirmed by a second frame, where the robot's moves say it
    /// cannot have: the camera or a fixture has been knocked out of calibration.
    CameraShift,
    /// Segment II's frames since some frame disagree with the frames before it, short of a
    /// confirmed shift: its estimate's covariance is widened, so the cell holds.
    ShiftSuspected,
    /// The robot's moves disagree with the drift the cell remembered of it: it has changed
    /// since (replaced, re-mounted, knocked). The memory is dropped and the episode goes on
    /// from what its own frames say.
    RobotChanged,
}

impl Detected {
    pub fn code(&self) -> &'static str {
        match self {
            Detected::Occlusion => "occlusion",
            Detected::FrozenCamera => "frozen_camera",
            Detected::OutOfOrder => "out_of_order",
            Detected::CameraShift => "camera_shift",
            Detected::ShiftSuspected => "camera_shift_suspected",
            Detected::RobotChanged => "robot_changed",
        }
    }
}

/// Beyond this Mahalanobis distance² (x and y) between the sideways estimates of the filter
/// that remembers the robot's drift and the one that does not, the remembered drift is taken to
/// be wrong. χ² with 2 degrees of freedom passes 12 with probability 2.5e-3, but the distance is
/// measured cautiously (`StateFilter::sideways_disagreement_with`) and a false alarm costs only
/// the episode's speed: the cell goes on without the memory. 20 let a silently replaced robot
/// into the wall four times as often (docs/estimation.md §3a).
const ROBOT_CHANGED_CHI2: f64 = 12.0;

/// Frames in a row a coded point may be missing before it is reported occluded (a dropped
/// point, 2% a frame in the reference camera, is missing 8 frames in a row once in 4e13).
pub const OCCLUSION_FRAMES: u32 = 8;
/// Identical frames in a row that make the camera frozen.
pub const FROZEN_FRAMES: u32 = 3;
/// Largest coded-point id tracked for occlusion, per fixture.
const TRACKED_POINTS: usize = 16;

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
    /// A camera fault noticed at this capture.
    pub detected: Option<Detected>,
}

/// What ingestion remembers of the frames to notice faults.
#[derive(Debug, Clone, Default)]
struct FrameWatch {
    /// The last frame taken in.
    last: Option<CameraFrame>,
    repeats: u32,
    /// Frames in a row each coded point of {C1} and {C2} has been missing.
    missing: [[u32; TRACKED_POINTS]; 2],
    /// The coded points seen in this episode: only one of them can go missing. Counting ids a
    /// fixture does not have named `occlusion` at the eighth frame of every episode.
    seen_before: [[bool; TRACKED_POINTS]; 2],
}

impl FrameWatch {
    /// Screens a frame before it is used: `Err` for a frame that must not be used, with the
    /// fault it shows once it is one; `Ok` with anything noticed about a usable one.
    fn screen(&mut self, frame: &CameraFrame) -> Result<Option<Detected>, Option<Detected>> {
        if self
            .last
            .as_ref()
            .is_some_and(|last| frame.sequence < last.sequence)
        {
            return Err(Some(Detected::OutOfOrder));
        }
        if self.last.as_ref() == Some(frame) && !frame.points.is_empty() {
            self.repeats += 1;
            return Err((self.repeats + 1 >= FROZEN_FRAMES).then_some(Detected::FrozenCamera));
        }
        self.repeats = 0;
        match &mut self.last {
            Some(last) => last.clone_from(frame),
            none => *none = Some(frame.clone()),
        }
        let mut seen = [[false; TRACKED_POINTS]; 2];
        for point in &frame.points {
            if let Some(slot) = seen[fixture_index(point.fixture)].get_mut(usize::from(point.id)) {
                *slot = true;
            }
        }
        let mut occluded = false;
        for ((missing, seen_before), seen) in
            self.missing.iter_mut().zip(&mut self.seen_before).zip(seen)
        {
            for ((count, before), seen) in missing.iter_mut().zip(seen_before).zip(seen) {
                *before |= seen;
                *count = if seen || !*before { 0 } else { *count + 1 };
                occluded |= *count == OCCLUSION_FRAMES;
            }
        }
        Ok(occluded.then_some(Detected::Occlusion))
    }
}

/// The noisiest camera the cell is specified for, × its data sheet's point noise.
const NOISIEST_SPECIFIED_CAMERA: f64 = 4.0;

fn fixture_index(fixture: super::Fixture) -> usize {
    match fixture {
        super::Fixture::C1 => 0,
        super::Fixture::C2 => 1,
    }
}

/// Fits each capture, carries it forward by the part of the move still to come, fuses it into
/// the state filter and forms the 12-dim state (docs/design.md §5).
#[derive(Debug, Clone)]
pub struct Ingest {
    estimator: StateEstimator,
    filter: StateFilter,
    /// How noisy the camera really is, learned from each frame's fit residuals.
    noise: NoiseScale,
    watch: FrameWatch,
    segment_two: StaticSegment,
    hole_pitch_deg: f64,
    state: [f64; 12],
    raw_state: [f64; 12],
    estimated_m_f: Option<Pose>,
    /// The cell keeps its robot: each episode starts from the drift the last ones learned.
    remember_drift: bool,
    /// What the episodes so far learned of the robot's drift (with `remember_drift`).
    drift_memory: Option<DriftKnowledge>,
    /// No camera fault was confirmed in this episode, so what it learned may be kept.
    episode_trusted: bool,
    /// While an episode runs from the remembered drift: the same filter started from a prior
    /// for a robot never seen, as wide as the remembered drift calls for
    /// (`FusionTuning::checking_a_memory`), fed the same frames, so that a remembered drift
    /// that has become wrong shows as the two disagreeing.
    unremembering: Option<StateFilter>,
    /// The remembered drift was found wrong at this frame (named once, at the frame).
    robot_changed: bool,
}

impl Ingest {
    pub fn new(cell: &CellConfig, frames: &CellFrames) -> Self {
        Ingest {
            estimator: StateEstimator::new(cell, frames),
            filter: StateFilter::new(FusionTuning::default()),
            noise: NoiseScale::default(),
            watch: FrameWatch::default(),
            segment_two: StaticSegment::default(),
            hole_pitch_deg: cell.hole_pitch_deg(),
            state: [0.0; 12],
            raw_state: [0.0; 12],
            estimated_m_f: None,
            remember_drift: false,
            drift_memory: None,
            episode_trusted: true,
            unremembering: None,
            robot_changed: false,
        }
    }

    /// For a cell that keeps its robot: each episode starts from the drift the episodes before
    /// it learned (`camera::drift`), not from the prior for a robot never seen. An episode in
    /// which a camera shift or a frozen camera was confirmed teaches it nothing.
    pub fn remembering_drift(mut self) -> Self {
        self.remember_drift = true;
        self
    }

    /// What the finished episodes taught of the robot's drift (none before the first, or when
    /// the drift is not remembered).
    pub fn drift_memory(&self) -> Option<&DriftKnowledge> {
        self.drift_memory.as_ref()
    }

    /// What would be remembered if the episode ended now: the memory updated with what this
    /// episode's frames alone said of the drift (`DriftKnowledge::updated_with`); the memory as
    /// it was if the episode cannot teach anything.
    fn learned_drift(&self) -> Option<DriftKnowledge> {
        if !self.remember_drift {
            return None;
        }
        // The filter that started from a prior (its own) for an unseen robot.
        let alone = self.unremembering.as_ref().unwrap_or(&self.filter);
        if !self.episode_trusted || alone.m_f().is_none() {
            return self.drift_memory;
        }
        let episode = alone.drift_knowledge(1);
        if !episode.is_usable() {
            return self.drift_memory;
        }
        Some(match self.drift_memory {
            Some(memory) => {
                memory
                    .carried(self.filter.tuning().drift_change_sd)
                    .updated_with(&episode, alone.tuning().drift_prior_sd)
                    .knowledge
            }
            None => episode,
        })
    }

    /// Takes in one shot: forgets the last episode if this one is new, predicts the executed
    /// move, then ingests the capture.
    pub fn take(&mut self, shot: &Shot) -> Estimate {
        if shot.new_episode {
            self.drift_memory = if shot.forget_robot {
                None
            } else {
                self.learned_drift()
            };
            self.reset();
        }
        if let Some(step) = &shot.executed {
            self.predict(step);
        }
        let (fresh, detected) = match self.watch.screen(&shot.frame) {
            Err(fault) => {
                self.estimated_m_f = None;
                (false, fault)
            }
            Ok(noticed) => match self.ingest(&shot.frame, shot.remaining.as_ref()) {
                Ok(shifted) => {
                    let suspected = self.segment_two.suspected.map(|_| Detected::ShiftSuspected);
                    (true, shifted.or(noticed).or(suspected))
                }
                Err(CameraError::Shifted) => (false, Some(Detected::CameraShift)),
                Err(_) => (false, noticed),
            },
        };
        if matches!(
            detected,
            Some(Detected::CameraShift | Detected::FrozenCamera)
        ) {
            self.episode_trusted = false;
        }
        let changed = std::mem::take(&mut self.robot_changed).then_some(Detected::RobotChanged);
        let detected = detected.or(changed);
        Estimate {
            state: self.state,
            raw_state: self.raw_state,
            m_f: self.estimated_m_f,
            filter: self.filter,
            fresh,
            detected,
        }
    }

    /// Forgets everything but the robot's drift, when remembered: a new episode starts blind.
    fn reset(&mut self) {
        self.filter.reset();
        self.unremembering = None;
        // Only a remembering ingest has a memory (`learned_drift`).
        if let Some(memory) = self.drift_memory {
            let tuning = *self.filter.tuning();
            let check = tuning.checking_a_memory(&memory);
            self.unremembering = Some(StateFilter::new(check));
            self.filter
                .reset_from(&memory.carried(tuning.drift_change_sd));
        }
        self.episode_trusted = true;
        self.robot_changed = false;
        self.noise = NoiseScale::default();
        self.pass_noise_scale();
        self.watch = FrameWatch::default();
        self.segment_two = StaticSegment::default();
        self.state = [0.0; 12];
        self.raw_state = [0.0; 12];
        self.estimated_m_f = None;
    }

    /// The robot executed `step`: the filter carries its estimate along.
    fn predict(&mut self, step: &Move) {
        for filter in self.filters() {
            filter.predict(step);
        }
    }

    /// Feeds the frame the filter just took (`fusion`) to the filter that does not remember the
    /// drift, if the episode runs from a remembered one, and compares the two. The remembered
    /// drift is wrong if the filter that remembers it is far sideways from the one that does
    /// not, or sees a jump that the other explains: the memory is forgotten, and the episode
    /// goes on with the other filter's drift and its answer to the frame, from the estimate it
    /// had, its covariance widened by the gap (`StateFilter::give_way_to`). Either filter may
    /// be the one that erred, so the estimate does not jump to the other's: a jump the
    /// supervisor believed could centre the shaft into the wall.
    fn check_remembered_drift(
        &mut self,
        fusion: Fusion,
        m_f: &Pose,
        covariance: &Matrix6<f64>,
    ) -> Fusion {
        let Some(mut unremembering) = self.unremembering else {
            return fusion;
        };
        let fresh = unremembering.update(m_f, covariance);
        let wrong = self
            .filter
            .sideways_disagreement_with(&unremembering)
            .is_some_and(|d| d > ROBOT_CHANGED_CHI2)
            || (matches!(fusion, Fusion::Jumped { .. })
                && matches!(fresh, Fusion::Blended | Fusion::Reset));
        if !wrong {
            self.unremembering = Some(unremembering);
            return fusion;
        }
        self.filter.give_way_to(&unremembering);
        self.unremembering = None;
        self.drift_memory = None;
        self.robot_changed = true;
        fresh
    }

    /// Gives every filter the camera's noise as now learned.
    fn pass_noise_scale(&mut self) {
        self.pass_scale(self.noise.scale());
    }

    /// Gives every filter this noise scale (× the data sheet's point noise).
    fn pass_scale(&mut self, scale: f64) {
        for filter in self.filters() {
            filter.set_noise_scale(scale);
        }
    }

    /// The state filter and, while the episode runs from a remembered drift, the one that does
    /// not remember it.
    fn filters(&mut self) -> impl Iterator<Item = &mut StateFilter> {
        std::iter::once(&mut self.filter).chain(self.unremembering.as_mut())
    }

    /// Takes in one capture. `remaining` is the part of the commanded move still to come after
    /// the exposure, in {M} (none when the robot had stopped). On success the fused estimate
    /// and the state move on; on failure (no fit, or a frame the filter holds back) the state
    /// stays as it was and the estimate is stale (the supervisor then vetoes every move). A jump
    /// the moves do not explain is answered as a camera shift.
    fn ingest(
        &mut self,
        frame: &CameraFrame,
        remaining: Option<&Pose>,
    ) -> Result<Option<Detected>, CameraError> {
        // Until frames have shown how noisy the camera is, the first is fitted for the noise it
        // shows itself (up to the noisiest camera the cell is specified for): at the data
        // sheet's threshold a camera four times as noisy loses one or two good points of six in
        // most fits, and the episode's view of Segment II starts from it. Once seen, the fits are
        // also screened against that noise, taken cautiously high so that a noise still being
        // learned does not read as a point gone astray. A tracker's fitted frame is exact by
        // construction: nothing to reject, nothing to screen.
        let (noise_scale, known_variance_factor) = if let FrameKind::Fitted { .. } = frame.kind {
            (1.0, None)
        } else if self.noise.has_seen_frames() {
            let factor = self.noise.cautious_variance_factor();
            (self.noise.scale(), Some(factor))
        } else {
            let seen = self
                .estimator
                .noise_scale_of(frame, NOISIEST_SPECIFIED_CAMERA);
            (seen, None)
        };
        let mut measurement = self
            .estimator
            .estimate_screened(frame, noise_scale, known_variance_factor)
            .inspect_err(|_| self.estimated_m_f = None)?;
        if let Some(remaining) = remaining {
            measurement.w_m *= remaining;
            measurement.m_f = remaining.inverse() * measurement.m_f;
        }
        // Residuals show the camera's noise only where the points were measured; a tracker's
        // fit is as uncertain as the tracker says.
        let variance_factor = match frame.kind {
            FrameKind::Measured => {
                self.noise
                    .add(measurement.residual_squares, measurement.residual_dof);
                self.pass_noise_scale();
                self.noise.cautious_variance_factor()
            }
            FrameKind::Fitted { variance_factor } => {
                // A factor that is no variance's is taken as the data sheet's.
                let factor = if variance_factor.is_finite() && variance_factor > 0.0 {
                    variance_factor
                } else {
                    1.0
                };
                self.pass_scale(factor.sqrt());
                factor
            }
        };
        // Segment II from the episode's mean, not from this frame alone; this frame's view of
        // it goes into the mean unless it is gross.
        let c2 = measurement.c2.in_frame(&measurement.w_f);
        match self
            .segment_two
            .take(&measurement.w_f, &c2, variance_factor)
        {
            StaticFrame::Shifted => {
                self.estimated_m_f = None;
                return Err(CameraError::Shifted);
            }
            StaticFrame::Taken { shift } => {
                let covariance = self.segment_two.cautious_mean_covariance(variance_factor);
                for filter in self.filters() {
                    filter.move_segment_two(&shift, &covariance);
                }
            }
            StaticFrame::Gross => {}
        }
        let w_f = self.segment_two.mean.unwrap_or(measurement.w_f);
        let m_f = measurement.w_m.inverse() * w_f;
        let covariance =
            relative_covariance_of(&measurement.w_m, &m_f, &measurement.c1) * variance_factor;
        let fusion = self.filter.update(&m_f, &covariance);
        let fusion = self.check_remembered_drift(fusion, &m_f, &covariance);
        let shifted = match fusion {
            Fusion::HeldBack { sigmas } => {
                self.estimated_m_f = None;
                return Err(CameraError::HeldBack { sigmas });
            }
            Fusion::Jumped { .. } => Some(Detected::CameraShift),
            Fusion::Blended | Fusion::Reset => None,
        };
        self.raw_state = measurement.state(self.hole_pitch_deg);
        let fused = self.filter.m_f().unwrap_or(m_f);
        self.state = state_vector(&measurement.w_m, &fused, self.hole_pitch_deg);
        self.estimated_m_f = Some(fused);
        Ok(shifted)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Frames numbered from 1 with the coded points `ids` of each fixture, the points themselves
    /// anywhere (the watch reads which points are there, not where).
    fn frames_with(ids: impl Fn(u64) -> Vec<u16>, count: u64) -> Vec<CameraFrame> {
        (1..=count)
            .map(|sequence| CameraFrame {
                points: [crate::camera::Fixture::C1, crate::camera::Fixture::C2]
                    .into_iter()
                    .flat_map(|fixture| {
                        ids(sequence)
                            .into_iter()
                            .map(move |id| crate::camera::CodedPoint {
                                fixture,
                                id,
                                position_mm: nalgebra::Point3::new(
                                    f64::from(id),
                                    sequence as f64,
                                    0.0,
                                ),
                            })
                    })
                    .collect(),
                sequence,
                kind: crate::camera::FrameKind::Measured,
            })
            .collect()
    }

    #[test]
    fn only_a_point_seen_and_then_lost_is_an_occlusion() {
        let noticed = |frames: &[CameraFrame]| {
            let mut watch = FrameWatch::default();
            frames
                .iter()
                .position(|frame| watch.screen(frame) == Ok(Some(Detected::Occlusion)))
        };
        // Six points a fixture, ids 0–5, in every frame: the ids it does not have are not
        // missing.
        assert_eq!(noticed(&frames_with(|_| (0..6).collect(), 40)), None);
        // Point 3 seen in the first 10 frames, then lost: named at its eighth frame missing.
        let lost = frames_with(|k| (0..6).filter(|&id| id != 3 || k <= 10).collect(), 40);
        assert_eq!(noticed(&lost), Some(10 + OCCLUSION_FRAMES as usize - 1));
        // Lost for seven frames and back: a dropped point or two, not an occlusion.
        let back = frames_with(
            |k| {
                (0..6)
                    .filter(|&id| id != 3 || !(11..18).contains(&k))
                    .collect()
            },
            40,
        );
        assert_eq!(noticed(&back), None);
    }
}
