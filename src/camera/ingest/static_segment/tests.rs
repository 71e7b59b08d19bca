//! The watch's behaviour: shifts noticed, still segments left alone, the mean's error as
//! claimed; and beyond [`EXACT_FRAMES`] frames, the same with the runs bounded.

use super::*;
use crate::geometry::pose::pose_from_mm_deg;
use nalgebra::Vector3;
use rand::SeedableRng;
use rand_distr::{Distribution, StandardNormal};
use std::ops::Range;

/// {C2}'s fit 2 m from the camera with σ 0.01 mm and 1e-4 rad, seen with noise, shifted by
/// `shift` at the frames in `shifted`, and grossly off at the frames in `gross`.
fn watch(shift: &Pose, shifted: Range<usize>, gross: &[usize], frames: usize) -> Option<usize> {
    watch_seeded(shift, shifted, gross, frames, 4)
}

/// No frame shifted.
const NEVER: Range<usize> = 0..0;

/// σ 0.01 mm and 1e-4 rad per component: the frames of [`seen_with_noise`].
fn frame_covariance() -> Matrix6<f64> {
    Matrix6::from_diagonal(&Vector6::new(1e-4, 1e-4, 1e-4, 1e-8, 1e-8, 1e-8))
}

/// `truth` seen with errors about the fixture's own origin, as [`frame_covariance`] says.
fn seen_with_noise(truth: &Pose, rng: &mut rand_chacha::ChaCha8Rng) -> Pose {
    let n: [f64; 6] = std::array::from_fn(|_| StandardNormal.sample(rng));
    let mut seen = *truth;
    seen.translation.vector += Vector3::new(n[0], n[1], n[2]) * 0.01;
    seen.rotation =
        nalgebra::UnitQuaternion::from_scaled_axis(Vector3::new(n[3], n[4], n[5]) * 1e-4)
            * seen.rotation;
    seen
}

fn watch_seeded(
    shift: &Pose,
    shifted: Range<usize>,
    gross: &[usize],
    frames: usize,
    seed: u64,
) -> Option<usize> {
    let truth = pose_from_mm_deg(Vector3::new(0.0, -2000.0, 100.0), Vector3::zeros());
    let covariance = frame_covariance();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let mut still = StaticSegment::default();
    for k in 0..frames {
        let mut seen = seen_with_noise(&truth, &mut rng);
        if shifted.contains(&k) {
            seen = shift * seen;
        }
        if gross.contains(&k) {
            seen.translation.vector.x += 0.5;
        }
        if still.take(&seen, &covariance, 1.0) == StaticFrame::Shifted {
            return Some(k);
        }
    }
    None
}

#[test]
fn a_shift_of_segment_twos_fixture_is_noticed_and_single_gross_frames_are_not() {
    let still = Pose::identity();
    assert_eq!(watch(&still, NEVER, &[], 400), None);
    // One gross frame now and then, or two at the very start (the first frame was the odd
    // one): no shift.
    assert_eq!(watch(&still, NEVER, &[30, 90, 200], 400), None);
    assert_eq!(watch(&still, NEVER, &[0], 100), None);
    // 0.2 mm: twenty σ of a frame, noticed at the second shifted frame.
    let knocked = pose_from_mm_deg(Vector3::new(0.2, 0.0, 0.0), Vector3::zeros());
    assert_eq!(watch(&knocked, 50..usize::MAX, &[], 100), Some(51));
    // 0.05 mm, five σ: noticed within a few frames by the trend.
    let nudged = pose_from_mm_deg(Vector3::new(0.0, 0.05, 0.0), Vector3::zeros());
    let seen = watch(&nudged, 50..usize::MAX, &[], 100).expect("a 5 σ shift is noticed");
    assert!((50..56).contains(&seen), "{seen}");
    // 2 σ of a frame in two directions, as a 0.2 mm shift is for a camera four times as
    // noisy as its data sheet: noticed within the recent window.
    let faint = pose_from_mm_deg(Vector3::new(0.02, -0.02, 0.0), Vector3::zeros());
    let seen = watch(&faint, 50..usize::MAX, &[], 100).expect("a 2 σ shift is noticed");
    assert!((50..59).contains(&seen), "{seen}");
    // A first frame pulled 4 σ off in three components by an outlier the fit let through
    // is no shift either: the window is compared with three earlier frames at the least.
    let pulled = pose_from_mm_deg(Vector3::new(0.04, 0.04, -0.04), Vector3::zeros());
    for seed in 0..20 {
        assert_eq!(
            watch_seeded(&pulled, 0..1, &[], 60, seed),
            None,
            "seed {seed}"
        );
    }
    // One of the first three frames pulled 5.5 σ off in every component (Mahalanobis
    // distance² about 180 from the others, as outliers the fit let through left frames of
    // the twin at twice the data sheet's noise) is within the gross test, and a third of it
    // in the earlier frames' mean once read as a shift at the first window (χ² 50–90).
    let outlier = pose_from_mm_deg(
        Vector3::new(0.055, 0.055, -0.055),
        Vector3::new(5.5e-4, -5.5e-4, 5.5e-4).map(f64::to_degrees),
    );
    let truth = pose_from_mm_deg(Vector3::new(0.0, -2000.0, 100.0), Vector3::zeros());
    let covariance = frame_covariance();
    for seed in 0..20 {
        for odd in 0..3 {
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
            let mut still = StaticSegment::default();
            for k in 0..60 {
                let mut seen = seen_with_noise(&truth, &mut rng);
                if k == odd {
                    // About the fixture's own origin, as the frame's errors are.
                    seen *= outlier;
                }
                let verdict = still.take(&seen, &covariance, 1.0);
                assert_ne!(verdict, StaticFrame::Shifted, "seed {seed}, outlier {odd}");
            }
        }
    }
    // No false alarm in a long still run with gross frames now and then, on other seeds.
    for seed in 10..20 {
        assert_eq!(
            watch_seeded(&still, NEVER, &[77, 150, 151 + seed as usize], 300, seed),
            None
        );
    }
}

/// Mahalanobis distance² of the mean's real error (the truth is `truth`) under `covariance`.
fn mean_error_chi2(still: &StaticSegment, truth: &Pose, covariance: &Matrix6<f64>) -> f64 {
    let error = small_motion(&(truth.inverse() * still.mean.expect("a mean")));
    let inverse = covariance.try_inverse().expect("a covariance");
    (error.transpose() * inverse * error)[(0, 0)]
}

#[test]
fn a_shift_after_few_true_frames_widens_the_means_covariance_over_its_error() {
    // Four true frames, then a shift of 2.5 σ of a frame in two directions, as a 0.2 mm
    // knock is early in an episode with a camera four times as noisy as its data sheet. The
    // window soon has shifted frames on both sides and the mean drifts to the shifted view.
    // A run hides the shift when, before it is noticed, the mean's real error is beyond
    // χ² = 40 (about 1e-7 by chance) of the covariance the estimate carries. The window
    // notices under half the runs; the mean's own covariance hides nearly all the others,
    // the widened one under half as many (191 and 80 of 200 at commit time; 43 when a
    // suspicion needed only χ² = 25, a threshold that held the cell for chance
    // disagreements of its first frames far more often: docs/estimation.md §1a).
    let truth = pose_from_mm_deg(Vector3::new(0.0, -2000.0, 100.0), Vector3::zeros());
    let covariance = frame_covariance();
    let shift = pose_from_mm_deg(Vector3::new(0.025, -0.025, 0.0), Vector3::zeros());
    let (mut hidden_cautious, mut hidden_own, mut noticed) = (0, 0, 0);
    for seed in 0..200 {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut still = StaticSegment::default();
        let (mut hid_cautious, mut hid_own) = (false, false);
        for k in 0..80 {
            let mut seen = seen_with_noise(&truth, &mut rng);
            if k >= 4 {
                seen = shift * seen;
            }
            if still.take(&seen, &covariance, 1.0) == StaticFrame::Shifted {
                noticed += 1;
                break;
            }
            let cautious = still.cautious_mean_covariance(1.0);
            hid_cautious |= mean_error_chi2(&still, &truth, &cautious) > 40.0;
            hid_own |= mean_error_chi2(&still, &truth, &still.mean_covariance()) > 40.0;
        }
        hidden_cautious += usize::from(hid_cautious);
        hidden_own += usize::from(hid_own);
    }
    assert!(
        noticed < 100,
        "the window alone notices {noticed} of 200 runs"
    );
    assert!(
        hidden_own > 150,
        "the mean's own covariance hides {hidden_own} of 200"
    );
    assert!(
        hidden_cautious * 2 < hidden_own,
        "widened {hidden_cautious} against {hidden_own}"
    );
}

#[test]
fn a_still_segment_is_seldom_suspected_of_a_shift() {
    // Without any shift, the mean's covariance is widened for a suspected shift in under
    // 1 % of frames (the cost of the watch: a few more frames of holding now and then).
    let truth = pose_from_mm_deg(Vector3::new(0.0, -2000.0, 100.0), Vector3::zeros());
    let covariance = frame_covariance();
    let (mut suspected, mut frames) = (0, 0);
    for seed in 0..100 {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1000 + seed);
        let mut still = StaticSegment::default();
        for _ in 0..150 {
            let seen = seen_with_noise(&truth, &mut rng);
            assert_ne!(still.take(&seen, &covariance, 1.0), StaticFrame::Shifted);
            suspected += usize::from(still.suspected.is_some());
            frames += 1;
        }
    }
    assert!(suspected * 100 < frames, "{suspected} of {frames} frames");
    // A first frame pulled 4 σ off in three components by an outlier disagrees with the
    // frames after it, but also with the true frames beside it: once those are there, it is
    // suspected no more often than a still segment.
    let pulled = pose_from_mm_deg(Vector3::new(0.04, 0.04, -0.04), Vector3::zeros());
    let (mut suspected, mut frames) = (0, 0);
    for seed in 0..20 {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut still = StaticSegment::default();
        for k in 0..60 {
            let mut seen = seen_with_noise(&truth, &mut rng);
            if k == 0 {
                seen = pulled * seen;
            }
            still.take(&seen, &covariance, 1.0);
            if k >= 6 {
                suspected += usize::from(still.suspected.is_some());
                frames += 1;
            }
        }
    }
    assert!(
        suspected * 100 < frames,
        "pulled: {suspected} of {frames} frames"
    );
}

#[test]
fn a_loose_frame_is_judged_by_its_own_covariance() {
    // Every tenth frame is a loose fit (points lost to dropouts or screening): twenty times
    // the σ sideways, its error drawn from that. Judged by a tight frame's covariance, one
    // such frame in the recent window reads as a shift of Segment II; judged by its own it
    // is no shift, and suspected no more often than a still segment (under 1 % of frames).
    let truth = pose_from_mm_deg(Vector3::new(0.0, -2000.0, 100.0), Vector3::zeros());
    let tight = frame_covariance();
    let mut loose = tight;
    loose[(0, 0)] *= 400.0;
    loose[(1, 1)] *= 400.0;
    let (mut suspected, mut frames) = (0, 0);
    for seed in 0..50 {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2000 + seed);
        let mut still = StaticSegment::default();
        for k in 0..150 {
            let mut seen = seen_with_noise(&truth, &mut rng);
            let covariance = if k % 10 == 5 {
                let extra: [f64; 2] = std::array::from_fn(|_| StandardNormal.sample(&mut rng));
                // σ 0.2 mm in all: the tight frame's 0.01 mm and the rest.
                let more = (400.0f64 - 1.0).sqrt() * 0.01;
                seen.translation.vector += Vector3::new(extra[0], extra[1], 0.0) * more;
                loose
            } else {
                tight
            };
            let verdict = still.take(&seen, &covariance, 1.0);
            assert_ne!(verdict, StaticFrame::Shifted, "seed {seed}, frame {k}");
            suspected += usize::from(still.suspected.is_some());
            frames += 1;
        }
    }
    assert!(suspected * 100 < frames, "{suspected} of {frames} frames");
}

#[test]
fn segment_twos_mean_has_the_error_its_covariance_claims() {
    // Frames of a still Segment II with errors of a known covariance in {F}'s axes: over
    // many runs the mean's error after n frames has the variance `mean_covariance` claims
    // (a frame's over n), per component.
    let truth = pose_from_mm_deg(
        Vector3::new(30.0, -2000.0, 100.0),
        Vector3::new(2.0, -1.0, 60.0),
    );
    let sd = [0.02, 0.01, 0.03, 2e-4, 1e-4, 3e-4];
    let covariance = Matrix6::from_diagonal(&Vector6::from_fn(|i, _| sd[i] * sd[i]));
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
    let (runs, frames) = (2000, 25);
    let mut squares = [0.0; 6];
    let mut claimed = [0.0; 6];
    for _ in 0..runs {
        let mut still = StaticSegment::default();
        for _ in 0..frames {
            let n: [f64; 6] = std::array::from_fn(|i| {
                let z: f64 = StandardNormal.sample(&mut rng);
                z * sd[i]
            });
            let error = Pose::from_parts(
                Vector3::new(n[0], n[1], n[2]).into(),
                nalgebra::UnitQuaternion::from_scaled_axis(Vector3::new(n[3], n[4], n[5])),
            );
            let verdict = still.take(&(truth * error), &covariance, 1.0);
            assert!(matches!(verdict, StaticFrame::Taken { .. }), "{verdict:?}");
        }
        let off = truth.inverse() * still.mean.unwrap();
        let (dt, dr) = (off.translation.vector, off.rotation.scaled_axis());
        let error = [dt.x, dt.y, dt.z, dr.x, dr.y, dr.z];
        let mean_covariance = still.mean_covariance();
        for i in 0..6 {
            squares[i] += error[i] * error[i];
            claimed[i] += mean_covariance[(i, i)];
        }
    }
    for i in 0..6 {
        let ratio = squares[i] / claimed[i];
        // 2000 runs resolve the ratio to about ±6 % (two standard errors).
        assert!((0.9..1.1).contains(&ratio), "component {i}: {ratio:.3}");
    }
}

#[test]
fn beyond_the_exact_frames_a_knock_is_still_noticed_within_a_few_frames() {
    // The same knocks as above, after 2000 still frames: the recent window and the frames
    // before it are summed exactly however long the episode. Each is noticed within the
    // window (a 5 σ shift at its fourth to seventh frame, as with every frame kept).
    let at = 2000;
    for seed in 0..3 {
        let knocked = pose_from_mm_deg(Vector3::new(0.2, 0.0, 0.0), Vector3::zeros());
        let seen = watch_seeded(&knocked, at..usize::MAX, &[], at + 50, seed);
        assert_eq!(seen, Some(at + 1), "seed {seed}");
        let nudged = pose_from_mm_deg(Vector3::new(0.0, 0.05, 0.0), Vector3::zeros());
        let seen = watch_seeded(&nudged, at..usize::MAX, &[], at + 50, seed)
            .expect("a 5 σ shift is noticed");
        assert!(
            (at..at + STATIC_WINDOW).contains(&seen),
            "seed {seed}: {seen}"
        );
        let faint = pose_from_mm_deg(Vector3::new(0.02, -0.02, 0.0), Vector3::zeros());
        let seen = watch_seeded(&faint, at..usize::MAX, &[], at + 50, seed)
            .expect("a 2 σ shift is noticed");
        assert!((at..at + 9).contains(&seen), "seed {seed}: {seen}");
    }
}

#[test]
fn beyond_the_exact_frames_a_still_segment_is_seldom_suspected() {
    // As for a short episode: over 3000 still frames with gross ones now and then, never a
    // shift, and the mean widened for a suspected one in under 1 % of the frames beyond
    // [`EXACT_FRAMES`].
    let truth = pose_from_mm_deg(Vector3::new(0.0, -2000.0, 100.0), Vector3::zeros());
    let covariance = frame_covariance();
    let (mut suspected, mut frames) = (0, 0);
    for seed in 0..4 {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3000 + seed);
        let mut still = StaticSegment::default();
        for k in 0..3000 {
            let mut seen = seen_with_noise(&truth, &mut rng);
            if k % 397 == 200 {
                seen.translation.vector.x += 0.5;
            }
            let verdict = still.take(&seen, &covariance, 1.0);
            assert_ne!(verdict, StaticFrame::Shifted, "seed {seed}, frame {k}");
            if k >= EXACT_FRAMES {
                suspected += usize::from(still.suspected.is_some());
                frames += 1;
            }
        }
    }
    assert!(suspected * 100 < frames, "{suspected} of {frames} frames");
}

#[test]
fn the_runs_stay_bounded_and_hold_every_frame_once() {
    // 6000 frames, loose and gross ones among them: never more than [`EXACT_FRAMES`] runs,
    // the recent window's frames each a run of its own, every taken frame in exactly one run
    // (each run's sums are its frames' sums), the runs about equal in length, and the mean
    // the mean of every frame summed in order.
    let truth = pose_from_mm_deg(Vector3::new(0.0, -2000.0, 100.0), Vector3::zeros());
    let tight = frame_covariance();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
    let mut still = StaticSegment::default();
    let mut frames: Vec<(Vector6<f64>, Matrix6<f64>)> = Vec::new();
    for k in 0..6000 {
        let mut seen = seen_with_noise(&truth, &mut rng);
        if k % 211 == 100 {
            seen.translation.vector.y -= 0.5;
        }
        let covariance = if k % 7 == 3 { tight * 9.0 } else { tight };
        let verdict = still.take(&seen, &covariance, 1.0);
        assert_ne!(verdict, StaticFrame::Shifted, "frame {k}");
        if verdict != StaticFrame::Gross {
            let reference = still.reference.expect("a first frame");
            frames.push((small_motion(&(reference.inverse() * seen)), covariance));
        }
        assert!(still.blocks.len() <= EXACT_FRAMES, "frame {k}");
        assert_eq!(still.taken, frames.len(), "frame {k}");
        let held: usize = still.blocks.iter().map(|block| block.frames).sum();
        assert_eq!(held, still.taken, "frame {k}");
        if still.taken >= STATIC_WINDOW {
            let window = &still.blocks[still.blocks.len() - STATIC_WINDOW..];
            assert!(window.iter().all(|block| block.frames == 1), "frame {k}");
            assert_eq!(
                still.earlier.frames,
                still.taken - STATIC_WINDOW,
                "frame {k}"
            );
        }
    }
    assert_eq!(still.blocks.len(), EXACT_FRAMES);
    let mut first = 0;
    for block in &still.blocks {
        let run = &frames[first..first + block.frames];
        let motion: Vector6<f64> = run.iter().map(|(motion, _)| motion).sum();
        let covariance: Matrix6<f64> = run.iter().map(|(_, covariance)| covariance).sum();
        assert!((block.motion - motion).norm() <= 1e-12 * (1.0 + motion.norm()));
        assert!((block.covariance - covariance).norm() <= 1e-12 * covariance.norm());
        first += block.frames;
    }
    let older = &still.blocks[..EXACT_FRAMES - STATIC_WINDOW];
    let longest = older.iter().map(|block| block.frames).max().unwrap();
    let shortest = older.iter().map(|block| block.frames).min().unwrap();
    assert!(
        longest <= 2 * shortest + 1,
        "runs of {shortest} to {longest} frames"
    );
    let sum: Vector6<f64> = frames.iter().map(|(motion, _)| motion).sum();
    let mean = still.reference.unwrap() * pose_of(&(sum / frames.len() as f64));
    assert_eq!(still.mean, Some(mean));
}
