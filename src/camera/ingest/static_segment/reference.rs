//! The reference [`StaticSegment`] is checked against: the watch with every frame kept apart.

use super::*;
use crate::geometry::pose::pose_from_mm_deg;
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

/// The watch as it was first written: every frame kept apart and every sum taken afresh, each
/// frame's work growing with the episode. [`StaticSegment`] must give exactly its results for
/// episodes of up to [`EXACT_FRAMES`] frames.
#[derive(Debug, Clone, Default)]
struct AllFrames {
    /// The first frame's {F} in {W}: the others are small motions ε of it, in its own axes.
    reference: Option<Pose>,
    /// Every frame averaged in, oldest first: the last [`STATIC_WINDOW`] are the recent
    /// window, the others the earlier frames.
    taken: Vec<SegmentTwoFrame>,
    /// Sum of all frames' covariances at the data sheet's noise, as motions of {F} in its own
    /// axes (`FixtureCovariance::in_frame`): the mean's is this over frames².
    covariance_sum: Matrix6<f64>,
    /// The current mean of all frames, as a pose.
    mean: Option<Pose>,
    /// The last frame was gross.
    gross: bool,
    /// Where a shift is suspected but not confirmed: the covariance the mean's error must be
    /// given instead of its own (camera noise applied; see [`AllFrames::suspicion`]).
    suspected: Option<Matrix6<f64>>,
}

/// One frame of Segment II averaged in: its ε from the first frame, and its covariance at the
/// data sheet's noise. Frames differ in covariance (a fit that lost points to dropouts or
/// screening is looser), so the tests between runs of frames weigh each by its own.
#[derive(Debug, Clone, Copy)]
struct SegmentTwoFrame {
    motion: Vector6<f64>,
    covariance: Matrix6<f64>,
}

impl AllFrames {
    /// Takes in one frame of Segment II's {F} in {W}, with its covariance at the data sheet's
    /// noise in {F}'s axes and the camera's variance factor.
    fn take(&mut self, w_f: &Pose, covariance: &Matrix6<f64>, variance_factor: f64) -> StaticFrame {
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
        self.taken.push(SegmentTwoFrame {
            motion: frame,
            covariance: *covariance,
        });
        self.covariance_sum += covariance;
        if self.shifted(variance_factor) {
            return StaticFrame::Shifted;
        }
        let sum = self.taken.iter().map(|f| f.motion).sum::<Vector6<f64>>();
        self.suspected = self.suspicion(&sum, variance_factor);
        let new_mean = reference * pose_of(&(sum / self.frames()));
        self.mean = Some(new_mean);
        StaticFrame::Taken {
            shift: mean.inverse() * new_mean,
        }
    }

    /// Whether the full recent window's mean is beyond [`STATIC_SHIFT_CHI2`] of the earlier
    /// frames' mean, for frames of their own covariances × `variance_factor`, with and without
    /// an earlier frame that disagrees with the others (as for the suspicion): among only
    /// three, one an outlier pulled off moves their mean by a third of its error. The screen
    /// costs a pass over the earlier frames per frame left out, so it runs only on a window
    /// that is beyond the limit with them all.
    fn shifted(&self, variance_factor: f64) -> bool {
        let earlier = self.taken.len().saturating_sub(STATIC_WINDOW);
        if self.taken.len() < STATIC_WINDOW || (earlier as f64) < STATIC_EARLIER_FRAMES {
            return false;
        }
        let (before, window) = self.taken.split_at(earlier);
        chi2_between(before, window, variance_factor) > STATIC_SHIFT_CHI2 && {
            let true_view = without_odd_frame(before, variance_factor);
            chi2_between(&true_view, window, variance_factor) > STATIC_SHIFT_CHI2
        }
    }

    /// The covariance the mean's error must be given when the frames since some earlier frame
    /// disagree with the frames before it beyond [`STATIC_SUSPECT_CHI2`] (the split that
    /// disagrees most), none otherwise. A camera knocked early in an episode leaves few frames
    /// of the true view, and the sliding window soon has only shifted frames on both sides; the
    /// mean then drifts towards the shifted view unseen. If the later frames are shifted, the
    /// truth is the earlier frames' mean: the error of the mean of all frames is then their gap
    /// `d` plus the earlier mean's own error, `d dᵀ + Σ_before`, the earlier mean's
    /// covariance. `total` is the sum of every frame's ε.
    fn suspicion(&self, total: &Vector6<f64>, variance_factor: f64) -> Option<Matrix6<f64>> {
        let n = self.taken.len();
        let sides = STATIC_EARLIER_FRAMES as usize;
        // Each split from running sums: the frames before it, and the rest.
        let mut before_sum = Vector6::zeros();
        let mut before_covariance = Matrix6::zeros();
        let mut worst = (0.0, 0);
        for split in 1..n {
            before_sum += self.taken[split - 1].motion;
            before_covariance += self.taken[split - 1].covariance;
            if split < sides || n - split < sides {
                continue;
            }
            let (n_before, n_after) = (split as f64, (n - split) as f64);
            let gap = (total - before_sum) / n_after - before_sum / n_before;
            let spread = (before_covariance / (n_before * n_before)
                + (self.covariance_sum - before_covariance) / (n_after * n_after))
                * variance_factor;
            let chi2 = mahalanobis_squared(&gap, &spread);
            if chi2 > worst.0 {
                worst = (chi2, split);
            }
        }
        let (worst, split) = worst;
        if worst <= STATIC_SUSPECT_CHI2 {
            return None;
        }
        let (before, after) = self.taken.split_at(split);
        let true_view = without_odd_frame(before, variance_factor);
        if chi2_between(&true_view, after, variance_factor) <= STATIC_SUSPECT_CHI2 {
            return None;
        }
        let (before_mean, before_covariance) = mean_of(before);
        let gap = total / n as f64 - before_mean;
        Some(gap * gap.transpose() + before_covariance * variance_factor)
    }

    /// The mean starts from this frame (the first, or after an odd first one).
    fn start_from(&mut self, w_f: &Pose, covariance: &Matrix6<f64>) -> StaticFrame {
        let shift = self
            .mean
            .map_or(Pose::identity(), |mean| mean.inverse() * *w_f);
        *self = AllFrames {
            reference: Some(*w_f),
            mean: Some(*w_f),
            taken: vec![SegmentTwoFrame {
                motion: Vector6::zeros(),
                covariance: *covariance,
            }],
            covariance_sum: *covariance,
            ..AllFrames::default()
        };
        StaticFrame::Taken { shift }
    }

    /// Frames averaged in.
    fn frames(&self) -> f64 {
        self.taken.len() as f64
    }

    /// Covariance of the mean's error at the data sheet's noise, in {F}'s axes.
    fn mean_covariance(&self) -> Matrix6<f64> {
        self.covariance_sum / (self.frames() * self.frames()).max(1.0)
    }

    /// Covariance of the mean's error with the camera's variance factor applied; the suspected
    /// shift's while there is one (it holds more than the mean's own: fewer frames, and the gap).
    fn cautious_mean_covariance(&self, variance_factor: f64) -> Matrix6<f64> {
        self.suspected
            .unwrap_or_else(|| self.mean_covariance() * variance_factor)
    }
}

/// `before` without one frame that disagrees with the others beyond [`ODD_FRAME_CHI2`]
/// (the one that disagrees most): a frame an outlier pulled off is not a shift of the frames
/// since, and frames of a true view agree with each other.
fn without_odd_frame(before: &[SegmentTwoFrame], variance_factor: f64) -> Vec<SegmentTwoFrame> {
    let without = |skip: usize| -> Vec<SegmentTwoFrame> {
        let mut rest = before.to_vec();
        rest.remove(skip);
        rest
    };
    let odd = (0..before.len())
        .map(|i| {
            let disagreement = chi2_between(&before[i..=i], &without(i), variance_factor);
            (disagreement, i)
        })
        .max_by(|a, b| a.0.total_cmp(&b.0));
    match odd {
        Some((disagreement, i)) if before.len() > 2 && disagreement > ODD_FRAME_CHI2 => without(i),
        _ => before.to_vec(),
    }
}

/// Mahalanobis distance² between the means of two runs of frames, each frame of its own
/// covariance × `variance_factor` (0 when the gap's covariance is singular).
fn chi2_between(
    before: &[SegmentTwoFrame],
    after: &[SegmentTwoFrame],
    variance_factor: f64,
) -> f64 {
    let ((before_mean, before_covariance), (after_mean, after_covariance)) =
        (mean_of(before), mean_of(after));
    let spread = (before_covariance + after_covariance) * variance_factor;
    mahalanobis_squared(&(after_mean - before_mean), &spread)
}

/// The mean of a run of frames and its covariance at the data sheet's noise (frames' errors
/// independent: the sum of their covariances over n²).
fn mean_of(frames: &[SegmentTwoFrame]) -> (Vector6<f64>, Matrix6<f64>) {
    let n = frames.len() as f64;
    let sum = frames.iter().map(|f| f.motion).sum::<Vector6<f64>>();
    let covariance = frames.iter().map(|f| f.covariance).sum::<Matrix6<f64>>();
    (sum / n, covariance / (n * n))
}

/// σ 0.01 mm and 1e-4 rad per component, `loose` times that, mixed by a random matrix: a frame's
/// error is `a z` for z standard normal, its covariance `a aᵀ`, correlated as real fits are.
fn random_factor(rng: &mut ChaCha8Rng, loose: f64) -> Matrix6<f64> {
    let sd = Vector6::new(0.01, 0.01, 0.01, 1e-4, 1e-4, 1e-4) * loose;
    let mix = Matrix6::from_fn(|_, _| {
        let z: f64 = StandardNormal.sample(&mut *rng);
        0.3 * z
    });
    Matrix6::from_diagonal(&sd) * (Matrix6::identity() + mix)
}

fn bits<'a>(values: impl IntoIterator<Item = &'a f64>) -> Vec<u64> {
    values.into_iter().map(|x| x.to_bits()).collect()
}

fn pose_bits(pose: &Pose) -> Vec<u64> {
    bits(
        pose.translation
            .vector
            .iter()
            .chain(pose.rotation.coords.iter()),
    )
}

fn verdict_bits(verdict: &StaticFrame) -> (u8, Vec<u64>) {
    match verdict {
        StaticFrame::Taken { shift } => (0, pose_bits(shift)),
        StaticFrame::Gross => (1, vec![]),
        StaticFrame::Shifted => (2, vec![]),
    }
}

/// What the two watches made of one sequence: frames suspected, gross and shifted.
#[derive(Debug, Default)]
struct Seen {
    suspected: usize,
    gross: usize,
    shifted: usize,
}

/// Feeds both watches one random episode of `frames` frames from `seed` and checks, frame by
/// frame, that their verdicts, means, suspicions and covariances are the same to the bit.
fn same_as_every_frame_kept(seed: u64, frames: usize) -> Seen {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let truth = pose_from_mm_deg(
        Vector3::new(30.0, -2000.0, 100.0),
        Vector3::new(2.0, -1.0, 60.0),
    );
    // A knock early (2.5 σ of a frame in two directions: suspected, seldom seen by the
    // window), one of the first three frames pulled off 5.5 σ in every component (screened
    // out), gross frames now and then, a knock late (5 σ: seen by the window).
    let early = rng.random_bool(0.5).then(|| rng.random_range(3..30));
    let pulled = rng.random_bool(0.5).then(|| rng.random_range(0..3));
    let late = rng
        .random_bool(0.4)
        .then(|| rng.random_range(frames / 2..frames));
    let early_shift = pose_from_mm_deg(Vector3::new(0.025, -0.025, 0.0), Vector3::zeros());
    let late_shift = pose_from_mm_deg(Vector3::new(0.0, 0.05, 0.0), Vector3::zeros());
    let outlier = pose_from_mm_deg(
        Vector3::new(0.055, 0.055, -0.055),
        Vector3::new(5.5e-4, -5.5e-4, 5.5e-4).map(f64::to_degrees),
    );
    let (mut blocks, mut every) = (StaticSegment::default(), AllFrames::default());
    let mut seen = Seen::default();
    for k in 0..frames {
        let loose = if rng.random_bool(0.1) {
            rng.random_range(2.0..20.0)
        } else {
            1.0
        };
        let a = random_factor(&mut rng, loose);
        let z = Vector6::<f64>::from_fn(|_, _| StandardNormal.sample(&mut rng));
        let mut w_f = truth * pose_of(&(a * z));
        if pulled == Some(k) {
            w_f *= outlier;
        }
        if early.is_some_and(|at| k >= at) {
            w_f = early_shift * w_f;
        }
        if late.is_some_and(|at| k >= at) {
            w_f = late_shift * w_f;
        }
        if k == 0 && seed.is_multiple_of(5) || rng.random_bool(0.02) {
            w_f.translation.vector.x += 0.5;
        }
        let covariance = a * a.transpose();
        let variance_factor = rng.random_range(0.8..1.6);
        let verdict = blocks.take(&w_f, &covariance, variance_factor);
        let expected = every.take(&w_f, &covariance, variance_factor);
        let at = format!("seed {seed}, frame {k}");
        assert_eq!(verdict_bits(&verdict), verdict_bits(&expected), "{at}");
        assert_eq!(
            blocks.mean.as_ref().map(pose_bits),
            every.mean.as_ref().map(pose_bits),
            "{at}"
        );
        assert_eq!(
            blocks.suspected.as_ref().map(|m| bits(m.iter())),
            every.suspected.as_ref().map(|m| bits(m.iter())),
            "{at}"
        );
        assert_eq!(
            bits(blocks.cautious_mean_covariance(variance_factor).iter()),
            bits(every.cautious_mean_covariance(variance_factor).iter()),
            "{at}"
        );
        seen.suspected += usize::from(every.suspected.is_some());
        seen.gross += usize::from(expected == StaticFrame::Gross);
        seen.shifted += usize::from(expected == StaticFrame::Shifted);
    }
    assert_eq!(blocks.taken, every.taken.len(), "seed {seed}");
    seen
}

#[test]
fn up_to_the_exact_frames_the_runs_give_every_frames_results_to_the_bit() {
    let mut seen = Seen::default();
    for seed in 0..16 {
        let frames = if seed % 4 == 0 {
            EXACT_FRAMES
        } else {
            ChaCha8Rng::seed_from_u64(100 + seed).random_range(20..EXACT_FRAMES)
        };
        let episode = same_as_every_frame_kept(seed, frames);
        seen.suspected += episode.suspected;
        seen.gross += episode.gross;
        seen.shifted += episode.shifted;
    }
    // The episodes reach every branch: suspicions, gross frames, shifts seen.
    assert!(
        seen.suspected > 0 && seen.gross > 0 && seen.shifted > 0,
        "{seen:?}"
    );
}

#[test]
fn the_odd_frame_screen_leaves_out_the_frame_every_frame_kept_would() {
    // Runs of single frames, one or two of them (the same frame twice: a tie) pulled off by
    // 0–8 σ in every component: the screen's choice, and the sum it leaves, are the
    // reference's to the bit.
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let (mut left_out, mut kept) = (0, 0);
    for case in 0..400 {
        let count = rng.random_range(3..60);
        let mut frames: Vec<SegmentTwoFrame> = (0..count)
            .map(|_| {
                let a = random_factor(&mut rng, 1.0);
                let z = Vector6::<f64>::from_fn(|_, _| StandardNormal.sample(&mut rng));
                SegmentTwoFrame {
                    motion: a * z,
                    covariance: a * a.transpose(),
                }
            })
            .collect();
        let odd = rng.random_range(0..count);
        let sigmas = rng.random_range(0.0..8.0);
        frames[odd].motion += Vector6::new(0.01, 0.01, -0.01, 1e-4, -1e-4, 1e-4) * sigmas;
        if case % 3 == 0 {
            let twin = rng.random_range(0..count);
            frames[twin] = frames[odd];
        }
        let variance_factor = rng.random_range(0.8..1.6);
        let blocks: Vec<Block> = frames
            .iter()
            .map(|f| Block::frame(&f.motion, &f.covariance))
            .collect();
        let screened = super::without_odd_frame(&blocks, &Block::of(&blocks), variance_factor);
        let expected = without_odd_frame(&frames, variance_factor);
        let (mean, covariance) = mean_of(&expected);
        assert_eq!(screened.frames, expected.len(), "case {case}");
        let (screened_mean, screened_covariance) = screened.mean();
        assert_eq!(bits(screened_mean.iter()), bits(mean.iter()), "case {case}");
        assert_eq!(
            bits(screened_covariance.iter()),
            bits(covariance.iter()),
            "case {case}"
        );
        if expected.len() < count {
            left_out += 1;
        } else {
            kept += 1;
        }
    }
    assert!(
        left_out > 50 && kept > 50,
        "{left_out} left out, {kept} kept"
    );
}

#[test]
fn beyond_the_exact_frames_a_knock_is_noticed_when_every_frame_kept_notices_it() {
    // After 2000 still frames, a shift of 5 σ of a frame, and one of 2 σ in two directions:
    // the recent window and the frames before it are summed as every frame kept sums them, so
    // the shift is noticed at the same frame.
    let truth = pose_from_mm_deg(Vector3::new(0.0, -2000.0, 100.0), Vector3::zeros());
    let sd = Vector6::new(0.01, 0.01, 0.01, 1e-4, 1e-4, 1e-4);
    let covariance = Matrix6::from_diagonal(&sd.component_mul(&sd));
    let shifts = [
        pose_from_mm_deg(Vector3::new(0.0, 0.05, 0.0), Vector3::zeros()),
        pose_from_mm_deg(Vector3::new(0.02, -0.02, 0.0), Vector3::zeros()),
    ];
    let at = 2000;
    for (seed, shift) in shifts.iter().enumerate() {
        let mut rng = ChaCha8Rng::seed_from_u64(seed as u64);
        let (mut blocks, mut every) = (StaticSegment::default(), AllFrames::default());
        let noticed = (0..at + 50).find(|&k| {
            let z = Vector6::<f64>::from_fn(|_, _| StandardNormal.sample(&mut rng));
            let mut seen = truth * pose_of(&sd.component_mul(&z));
            if k >= at {
                seen = shift * seen;
            }
            let verdicts = (
                blocks.take(&seen, &covariance, 1.0),
                every.take(&seen, &covariance, 1.0),
            );
            assert_eq!(
                verdicts.0 == StaticFrame::Shifted,
                verdicts.1 == StaticFrame::Shifted
            );
            verdicts.0 == StaticFrame::Shifted
        });
        let noticed = noticed.expect("the shift is noticed");
        assert!((at..at + STATIC_WINDOW).contains(&noticed), "{noticed}");
    }
}
