//! Segment II's running mean and its shift watch (docs/estimation.md §1a and §5): the
//! fixture of a segment that does not move, averaged over the episode's frames and watched
//! for the camera being knocked. Each frame costs a bounded amount of work however long the
//! episode: the frames are kept in at most [`EXACT_FRAMES`] runs ([`Block`]s).

use crate::geometry::Pose;
use nalgebra::{Matrix6, Vector6};

/// Frames in [`StaticSegment`]'s recent window, compared as one with the frames before them.
const STATIC_WINDOW: usize = 8;
/// The recent window's mean is a shift when its Mahalanobis distance² from the earlier frames'
/// mean is beyond this: χ² with 6 degrees of freedom exceeds it with probability about 1e-7.
const STATIC_SHIFT_CHI2: f64 = 40.0;
/// A frame this many σ off in any component is gross.
const STATIC_GROSS_SIGMAS: f64 = 6.0;
/// Earlier frames the recent window is compared with, at the least. Against one frame alone, a
/// first frame that an outlier the fit let through pulled a few σ off reads as a shift (8 of
/// 48,000 episodes of the twin without any fault); three dilute it below the threshold, and
/// delay the test by two frames. One of three far off the others is left out (decision 0046).
const STATIC_EARLIER_FRAMES: f64 = 3.0;
/// The frames since some frame are suspected of a shift when their mean's Mahalanobis
/// distance² from the frames before it is beyond this (χ² with 6 degrees of freedom: about 4e-5
/// for one split by chance): the mean's error is then widened to the shift's (it does not end
/// the episode). Every frame tests every split, and a chance disagreement of the first few
/// frames with the rest lasts the episode: at 25 (3e-4) such holds ended dozens of episodes in
/// 128,000 at twice the data sheet's noise (docs/estimation.md §1a).
const STATIC_SUSPECT_CHI2: f64 = 30.0;
/// A frame disagrees with the other frames of its run, and is left out of the suspicion's
/// "before" frames, beyond this Mahalanobis distance² (χ² with 6 degrees of freedom: about
/// 3e-4 by chance).
const ODD_FRAME_CHI2: f64 = 25.0;
/// Runs the episode's frames are kept in, at the most. Up to this many frames each is a run of
/// its own, and the mean, the suspicion and the verdicts are those of every frame kept apart:
/// the cell's longest episode is 310 frames (`episode.max_steps` = 300 steps of a frame each,
/// and up to 10 captures to start). Beyond it, each new frame merges the two neighbouring runs
/// among the older frames that hold the fewest frames between them, so the runs stay about
/// equal, `n / EXACT_FRAMES` frames each after n frames: a split is tested only between runs,
/// and the odd-frame screen leaves out a run, not a frame. The recent window's frames, and the
/// running sums of all frames and of the frames before the window, stay exact.
const EXACT_FRAMES: usize = 512;
/// The odd-frame screen orders the runs by a fast measure (each run against the sum of all
/// less its own) and computes the exact one (the others summed in order, as the screen is
/// defined) only for runs within this relative margin of the most disagreeing or of
/// [`ODD_FRAME_CHI2`]. The two differ only by rounding (under 1e-13 of the value for runs of up
/// to 500 correlated frames, some 30 times as loose as the others), so the screen's choice is
/// the exact one's.
const SCREEN_MARGIN: f64 = 1e-6;

/// Segment II does not move, so the cell keeps one estimate of it for the whole episode: the
/// mean of its fixture's frames ({F} in {W}), whose error shrinks with every frame and grows
/// with none of the robot's moves. Each frame of Segment I is then compared with that mean
/// instead of with its own noisy view of Segment II (docs/estimation.md).
///
/// It is also a watch: Segment II's frame as the camera sees it must stay where the episode's
/// earlier frames put it. A shift beyond the fits' noise is the camera (or the fixture) knocked
/// out of calibration; the robot's moves cannot explain it. The mean of the last
/// [`STATIC_WINDOW`] frames is compared with the mean of the frames before them, all six
/// components at once, so a shift of a few σ of one frame is seen within a few frames even when
/// the camera is noisy.
#[derive(Debug, Clone, Default)]
pub(super) struct StaticSegment {
    /// The first frame's {F} in {W}: the others are small motions ε of it, in its own axes.
    reference: Option<Pose>,
    /// Every frame averaged in, oldest first, in at most [`EXACT_FRAMES`] runs: a frame each
    /// until there are more frames, the newest [`STATIC_WINDOW`] always (the recent window).
    blocks: Vec<Block>,
    /// Frames averaged in.
    taken: usize,
    /// Sum of all frames' ε, in order: the mean is this over the frames.
    motion_sum: Vector6<f64>,
    /// Sum of all frames' covariances at the data sheet's noise, as motions of {F} in its own
    /// axes (`FixtureCovariance::in_frame`): the mean's is this over frames².
    covariance_sum: Matrix6<f64>,
    /// The frames before the recent window, summed in order as they leave it.
    earlier: Block,
    /// The current mean of all frames, as a pose.
    pub(super) mean: Option<Pose>,
    /// The last frame was gross.
    gross: bool,
    /// Where a shift is suspected but not confirmed: the covariance the mean's error must be
    /// given instead of its own (camera noise applied; see [`StaticSegment::suspicion`]).
    pub(super) suspected: Option<Matrix6<f64>>,
}

/// A run of consecutive frames of Segment II averaged in: how many, the sum of their ε from the
/// first frame (mm, rad), and the sum of their covariances at the data sheet's noise. That is
/// all the tests between runs of frames need: frames differ in covariance (a fit that lost
/// points to dropouts or screening is looser), and each is weighed by its own.
#[derive(Debug, Clone, Copy, Default)]
struct Block {
    frames: usize,
    motion: Vector6<f64>,
    covariance: Matrix6<f64>,
}

impl Block {
    /// One frame, as a run of one summed from zero.
    fn frame(motion: &Vector6<f64>, covariance: &Matrix6<f64>) -> Block {
        let mut block = Block::default();
        block.add(&Block {
            frames: 1,
            motion: *motion,
            covariance: *covariance,
        });
        block
    }

    /// The runs `blocks` as one, summed in order from zero.
    fn of<'a>(blocks: impl IntoIterator<Item = &'a Block>) -> Block {
        blocks.into_iter().fold(Block::default(), |mut sum, block| {
            sum.add(block);
            sum
        })
    }

    fn add(&mut self, other: &Block) {
        self.frames += other.frames;
        self.motion += other.motion;
        self.covariance += other.covariance;
    }

    /// This run's frames less `part`'s (a run within it).
    fn less(&self, part: &Block) -> Block {
        Block {
            frames: self.frames - part.frames,
            motion: self.motion - part.motion,
            covariance: self.covariance - part.covariance,
        }
    }

    /// The run's mean and its covariance at the data sheet's noise (frames' errors independent:
    /// the sum of their covariances over n²).
    fn mean(&self) -> (Vector6<f64>, Matrix6<f64>) {
        let n = self.frames as f64;
        (self.motion / n, self.covariance / (n * n))
    }
}

/// What [`StaticSegment::take`] made of a frame of Segment II.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) enum StaticFrame {
    /// Averaged in: the mean moved by this (in {F}'s axes).
    Taken { shift: Pose },
    /// Left out: one gross frame (an outlier the fit let through).
    Gross,
    /// Segment II has moved in the camera's view: the camera was knocked.
    Shifted,
}

impl StaticSegment {
    /// Takes in one frame of Segment II's {F} in {W}, with its covariance at the data sheet's
    /// noise in {F}'s axes and the camera's variance factor.
    pub(super) fn take(
        &mut self,
        w_f: &Pose,
        covariance: &Matrix6<f64>,
        variance_factor: f64,
    ) -> StaticFrame {
        let (Some(reference), Some(mean)) = (self.reference, self.mean) else {
            return self.start_from(w_f, covariance);
        };
        let frame = small_motion(&(reference.inverse() * *w_f));
        let difference = small_motion(&(mean.inverse() * *w_f));
        // The frame's error and the mean's own.
        let spread = (covariance + self.mean_covariance()) * variance_factor;
        // One gross frame is left out; two in a row are a shift, unless the mean rests on one
        // frame: then that frame was the odd one, and the mean starts again from this one.
        if (0..6).any(|i| {
            let z = difference[i] / spread[(i, i)].sqrt();
            z.is_nan() || z.abs() > STATIC_GROSS_SIGMAS
        }) {
            let confirmed = self.gross;
            self.gross = true;
            if confirmed && self.frames() < 2.0 {
                return self.start_from(w_f, covariance);
            }
            return if confirmed {
                StaticFrame::Shifted
            } else {
                StaticFrame::Gross
            };
        }
        self.gross = false;
        self.push(&frame, covariance);
        self.covariance_sum += covariance;
        if self.shifted(variance_factor) {
            return StaticFrame::Shifted;
        }
        self.suspected = self.suspicion(variance_factor);
        let new_mean = reference * pose_of(&(self.motion_sum / self.frames()));
        self.mean = Some(new_mean);
        StaticFrame::Taken {
            shift: mean.inverse() * new_mean,
        }
    }

    /// Adds a frame's ε and covariance to the runs and the running sums (not to
    /// `covariance_sum`, which the first frame sets), merging two older runs if there are more
    /// than [`EXACT_FRAMES`].
    fn push(&mut self, motion: &Vector6<f64>, covariance: &Matrix6<f64>) {
        self.blocks.push(Block::frame(motion, covariance));
        self.taken += 1;
        self.motion_sum += motion;
        // The frame that has just left the recent window, a frame of its own: the window's
        // runs are never merged.
        if let Some(left) = self.blocks.len().checked_sub(STATIC_WINDOW + 1) {
            let left = self.blocks[left];
            self.earlier.add(&left);
        }
        if self.blocks.len() > EXACT_FRAMES {
            self.merge_older();
        }
    }

    /// Merges the two neighbouring runs before the recent window that hold the fewest frames
    /// between them (the oldest such pair), so the runs stay about equal in length.
    fn merge_older(&mut self) {
        let older = &self.blocks[..self.blocks.len() - STATIC_WINDOW];
        let Some((first, _)) = older
            .windows(2)
            .enumerate()
            .min_by_key(|(i, pair)| (pair[0].frames + pair[1].frames, *i))
        else {
            return;
        };
        let second = self.blocks.remove(first + 1);
        self.blocks[first].add(&second);
    }

    /// Whether the full recent window's mean is beyond [`STATIC_SHIFT_CHI2`] of the earlier
    /// frames' mean, for frames of their own covariances × `variance_factor`, with and without
    /// an earlier frame that disagrees with the others (as for the suspicion): among only
    /// three, one an outlier pulled off moves their mean by a third of its error. The screen
    /// runs only on a window that is beyond the limit with them all.
    fn shifted(&self, variance_factor: f64) -> bool {
        if self.taken < STATIC_WINDOW || (self.earlier.frames as f64) < STATIC_EARLIER_FRAMES {
            return false;
        }
        let (before, window) = self.blocks.split_at(self.blocks.len() - STATIC_WINDOW);
        let window = Block::of(window);
        chi2_between(&self.earlier, &window, variance_factor) > STATIC_SHIFT_CHI2 && {
            let true_view = without_odd_frame(before, &Block::of(before), variance_factor);
            chi2_between(&true_view, &window, variance_factor) > STATIC_SHIFT_CHI2
        }
    }

    /// The covariance the mean's error must be given when the frames since some earlier frame
    /// disagree with the frames before it beyond [`STATIC_SUSPECT_CHI2`] (the split that
    /// disagrees most), none otherwise. A camera knocked early in an episode leaves few frames
    /// of the true view, and the sliding window soon has only shifted frames on both sides; the
    /// mean then drifts towards the shifted view unseen. If the later frames are shifted, the
    /// truth is the earlier frames' mean: the error of the mean of all frames is then their gap
    /// `d` plus the earlier mean's own error, `d dᵀ + Σ_before`, the earlier mean's
    /// covariance. Splits are tested between runs ([`EXACT_FRAMES`]).
    fn suspicion(&self, variance_factor: f64) -> Option<Matrix6<f64>> {
        let n = self.taken;
        let sides = STATIC_EARLIER_FRAMES as usize;
        let total = &self.motion_sum;
        // Each split from running sums: the frames before it, and the rest.
        let mut before = Block::default();
        let mut worst = (0.0, 0);
        let all_but_last = self.blocks.len().saturating_sub(1);
        for (runs, block) in (1..).zip(&self.blocks[..all_but_last]) {
            before.add(block);
            let split = before.frames;
            if split < sides || n - split < sides {
                continue;
            }
            let (n_before, n_after) = (split as f64, (n - split) as f64);
            let gap = (total - before.motion) / n_after - before.motion / n_before;
            let spread = (before.covariance / (n_before * n_before)
                + (self.covariance_sum - before.covariance) / (n_after * n_after))
                * variance_factor;
            let chi2 = mahalanobis_squared(&gap, &spread);
            if chi2 > worst.0 {
                worst = (chi2, runs);
            }
        }
        let (worst, split) = worst;
        if worst <= STATIC_SUSPECT_CHI2 {
            return None;
        }
        let (before, after) = self.blocks.split_at(split);
        let before_all = Block::of(before);
        let true_view = without_odd_frame(before, &before_all, variance_factor);
        if chi2_between(&true_view, &Block::of(after), variance_factor) <= STATIC_SUSPECT_CHI2 {
            return None;
        }
        let (before_mean, before_covariance) = before_all.mean();
        let gap = total / n as f64 - before_mean;
        Some(gap * gap.transpose() + before_covariance * variance_factor)
    }

    /// The mean starts from this frame (the first, or after an odd first one).
    fn start_from(&mut self, w_f: &Pose, covariance: &Matrix6<f64>) -> StaticFrame {
        let shift = self
            .mean
            .map_or(Pose::identity(), |mean| mean.inverse() * *w_f);
        *self = StaticSegment {
            reference: Some(*w_f),
            mean: Some(*w_f),
            covariance_sum: *covariance,
            ..StaticSegment::default()
        };
        self.push(&Vector6::zeros(), covariance);
        StaticFrame::Taken { shift }
    }

    /// Frames averaged in.
    fn frames(&self) -> f64 {
        self.taken as f64
    }

    /// Covariance of the mean's error at the data sheet's noise, in {F}'s axes.
    fn mean_covariance(&self) -> Matrix6<f64> {
        self.covariance_sum / (self.frames() * self.frames()).max(1.0)
    }

    /// Covariance of the mean's error with the camera's variance factor applied; the suspected
    /// shift's while there is one (it holds more than the mean's own: fewer frames, and the gap).
    pub(super) fn cautious_mean_covariance(&self, variance_factor: f64) -> Matrix6<f64> {
        self.suspected
            .unwrap_or_else(|| self.mean_covariance() * variance_factor)
    }
}

/// The frames of the runs `blocks` (`all`: their sum) without the run that disagrees most with
/// the others, if it does beyond [`ODD_FRAME_CHI2`] and there are more than two: a frame an
/// outlier pulled off is not a shift of the frames since, and frames of a true view agree with
/// each other. Each run is judged against the others summed in order; the fast measure (the
/// sum of all less the run) picks out the runs that need it ([`SCREEN_MARGIN`]), so the screen
/// costs a pass or two over the runs rather than a pass per run.
fn without_odd_frame(blocks: &[Block], all: &Block, variance_factor: f64) -> Block {
    if blocks.len() <= 2 {
        return *all;
    }
    let others = |skip: usize| Block::of(blocks[..skip].iter().chain(&blocks[skip + 1..]));
    let exact = |i: usize| (chi2_between(&blocks[i], &others(i), variance_factor), i);
    let fast: Vec<f64> = blocks
        .iter()
        .map(|block| chi2_between(block, &all.less(block), variance_factor))
        .collect();
    let margin = |chi2: f64| SCREEN_MARGIN * (1.0 + chi2.abs());
    let most = fast.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let odd = if fast.iter().all(|chi2| chi2.is_finite()) {
        if most + margin(most) <= ODD_FRAME_CHI2 {
            return *all;
        }
        // Only a run that may disagree as much as the most disagreeing can be the one.
        let floor = most - margin(most);
        (0..blocks.len())
            .filter(|&i| fast[i] + margin(fast[i]) >= floor)
            .map(exact)
            .max_by(|a, b| a.0.total_cmp(&b.0))
    } else {
        (0..blocks.len())
            .map(exact)
            .max_by(|a, b| a.0.total_cmp(&b.0))
    };
    match odd {
        Some((disagreement, i)) if disagreement > ODD_FRAME_CHI2 => others(i),
        _ => *all,
    }
}

/// Mahalanobis distance² between the means of two runs of frames, each frame of its own
/// covariance × `variance_factor` (0 when the gap's covariance is singular).
fn chi2_between(before: &Block, after: &Block, variance_factor: f64) -> f64 {
    let ((before_mean, before_covariance), (after_mean, after_covariance)) =
        (before.mean(), after.mean());
    let spread = (before_covariance + after_covariance) * variance_factor;
    mahalanobis_squared(&(after_mean - before_mean), &spread)
}

/// `gapᵀ covariance⁻¹ gap` (0 when the covariance is singular).
fn mahalanobis_squared(gap: &Vector6<f64>, covariance: &Matrix6<f64>) -> f64 {
    covariance
        .try_inverse()
        .map_or(0.0, |inverse| (gap.transpose() * inverse * gap)[(0, 0)])
}

/// A pose near the identity as `(translation mm, rotation vector rad)`.
fn small_motion(pose: &Pose) -> Vector6<f64> {
    let (t, r) = (pose.translation.vector, pose.rotation.scaled_axis());
    Vector6::new(t.x, t.y, t.z, r.x, r.y, r.z)
}

/// The pose of a small motion `(translation mm, rotation vector rad)`.
fn pose_of(motion: &Vector6<f64>) -> Pose {
    Pose::from_parts(
        motion.fixed_rows::<3>(0).into_owned().into(),
        nalgebra::UnitQuaternion::from_scaled_axis(motion.fixed_rows::<3>(3).into_owned()),
    )
}

#[cfg(test)]
mod reference;
#[cfg(test)]
mod tests;
