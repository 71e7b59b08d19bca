//! Two controllers' failures on the same episodes, paired (McNemar's exact test).
//!
//! Evaluated on the same seeds, two controllers meet the same cells, robots and camera frames
//! episode by episode. Most of a good controller's rare failures are then the cell's, not
//! its own: the same episode ends the same way whoever drives (a false `camera_shift`, an
//! estimate that stays too unsure to move). Only the episodes one controller fails and the
//! other does not tell them apart, and under "neither is better" each such episode is
//! equally likely to be either's: the sign test on those counts is exact, and is the most a
//! run of episodes can say about which fails less.

use assembly_cell::policy::eval::EpisodeReport;

/// How two controllers' failures fall on the episodes they both ran.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct PairedFailures {
    /// Episodes paired.
    pub episodes: usize,
    /// Episodes both failed.
    pub both: usize,
    /// Episodes only the reference failed.
    pub reference_only: usize,
    /// Episodes only the candidate failed.
    pub candidate_only: usize,
}

/// The two runs do not cover the same episodes, so they cannot be paired.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("cannot pair {reference} episodes of the reference with {candidate} of the candidate")]
pub struct NotPaired {
    pub reference: usize,
    pub candidate: usize,
}

/// Two evaluations of the same episodes (the same cell, options, count and seed), episode by
/// episode in index order, whatever order they finished in.
pub fn paired_episodes<'a>(
    reference: &'a [EpisodeReport],
    candidate: &'a [EpisodeReport],
) -> Result<Vec<(&'a EpisodeReport, &'a EpisodeReport)>, NotPaired> {
    let not_paired = NotPaired {
        reference: reference.len(),
        candidate: candidate.len(),
    };
    if reference.len() != candidate.len() {
        return Err(not_paired);
    }
    let by_index = |reports: &'a [EpisodeReport]| {
        let mut sorted: Vec<&EpisodeReport> = reports.iter().collect();
        sorted.sort_by_key(|r| r.index);
        sorted
    };
    let pairs: Vec<_> = by_index(reference)
        .into_iter()
        .zip(by_index(candidate))
        .collect();
    if pairs
        .iter()
        .any(|(r, c)| (r.index, r.seed) != (c.index, c.seed))
    {
        return Err(not_paired);
    }
    Ok(pairs)
}

impl PairedFailures {
    /// Pairs two evaluations of the same episodes by episode index.
    pub fn of(
        reference: &[EpisodeReport],
        candidate: &[EpisodeReport],
    ) -> Result<PairedFailures, NotPaired> {
        let mut paired = PairedFailures::default();
        for (r, c) in paired_episodes(reference, candidate)? {
            paired.count(r, c);
        }
        Ok(paired)
    }

    /// Counts one more episode, as the reference and the candidate ended it.
    pub fn count(&mut self, reference: &EpisodeReport, candidate: &EpisodeReport) {
        self.episodes += 1;
        match (reference.succeeded(), candidate.succeeded()) {
            (false, false) => self.both += 1,
            (false, true) => self.reference_only += 1,
            (true, false) => self.candidate_only += 1,
            (true, true) => {}
        }
    }

    /// Two-sided p-value of McNemar's exact test: how likely counts of episodes failed by one
    /// side alone at least this uneven are if neither controller fails more than the other.
    pub fn p_value(&self) -> f64 {
        sign_test_p(self.reference_only, self.candidate_only)
    }

    /// The most episodes the candidate could fail on its own, beside the reference's own
    /// failures here, and still be ahead with a two-sided p-value below `alpha`; `None` when
    /// even none would not be enough.
    pub fn own_failures_for_a_lead(&self, alpha: f64) -> Option<usize> {
        (0..=self.reference_only)
            .take_while(|&own| sign_test_p(self.reference_only, own) < alpha)
            .last()
    }
}

/// Two-sided exact sign test: with `a + b` discordant episodes, each equally likely to fall
/// either way, twice the chance of a split at least as uneven as `a` against `b` (at most 1).
pub fn sign_test_p(a: usize, b: usize) -> f64 {
    let n = a + b;
    let fewer = a.min(b);
    // ln C(n, k), built up term by term, keeps 2^-n from underflowing for large n.
    let mut ln_choose = 0.0_f64;
    let mut tail = 0.0_f64;
    let ln_half_to_n = -(n as f64) * std::f64::consts::LN_2;
    for k in 0..=fewer {
        if k > 0 {
            ln_choose += ((n - k + 1) as f64).ln() - (k as f64).ln();
        }
        tail += (ln_choose + ln_half_to_n).exp();
    }
    (2.0 * tail).min(1.0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use assembly_cell::sim::PoseErrors;
    use proptest::prelude::*;

    fn report(index: usize, outcome: &str) -> EpisodeReport {
        EpisodeReport {
            index,
            seed: 1000 + index as u64,
            outcome: outcome.to_string(),
            steps: 30,
            reward: 0.0,
            vetoes: 0,
            final_errors: PoseErrors::default(),
            rules: Default::default(),
        }
    }

    /// By hand: 12 discordant episodes split 10 to 2 have P(X ≤ 2) = (1 + 12 + 66) / 4096,
    /// so p = 158 / 4096; 5 to 0 gives 2 / 32; an even split and no split give 1.
    #[test]
    fn the_sign_test_matches_hand_computed_binomial_tails() {
        assert!((sign_test_p(10, 2) - 158.0 / 4096.0).abs() < 1e-12);
        assert!((sign_test_p(2, 10) - 158.0 / 4096.0).abs() < 1e-12);
        assert!((sign_test_p(5, 0) - 2.0 / 32.0).abs() < 1e-12);
        assert_eq!(sign_test_p(13, 13), 1.0);
        assert_eq!(sign_test_p(0, 0), 1.0);
    }

    proptest! {
        /// Against the binomial tail summed from factorials (exact in f64 for n ≤ 60).
        #[test]
        fn the_sign_test_matches_the_tail_from_factorials(a in 0usize..30, b in 0usize..30) {
            let n = a + b;
            let choose = |k: usize| -> f64 {
                (0..k).fold(1.0, |c, i| c * (n - i) as f64 / (i + 1) as f64)
            };
            let tail: f64 = (0..=a.min(b)).map(choose).sum::<f64>() / 2f64.powi(n as i32);
            let expected = (2.0 * tail).min(1.0);
            prop_assert!((sign_test_p(a, b) - expected).abs() < 1e-9 * expected.max(1e-300));
        }
    }

    #[test]
    fn episodes_are_paired_by_index_whatever_order_they_finished_in() {
        let reference = vec![
            report(0, "success"),
            report(1, "uncertain"),
            report(2, "contact"),
            report(3, "success"),
            report(4, "step_limit"),
        ];
        let mut candidate = vec![
            report(0, "contact"),
            report(1, "uncertain"),
            report(2, "success"),
            report(3, "success"),
            report(4, "uncertain"),
        ];
        candidate.reverse();
        let paired = PairedFailures::of(&reference, &candidate).unwrap();
        assert_eq!(
            paired,
            PairedFailures {
                episodes: 5,
                both: 2,
                reference_only: 1,
                candidate_only: 1,
            }
        );
        let mut twice = paired;
        for (r, c) in paired_episodes(&reference, &candidate).unwrap() {
            twice.count(r, c);
        }
        assert_eq!(twice.both, 4);
        assert_eq!(twice.episodes, 10);
    }

    #[test]
    fn runs_of_different_episodes_are_not_paired() {
        let reference = vec![report(0, "success"), report(1, "success")];
        assert_eq!(
            PairedFailures::of(&reference, &reference[..1]),
            Err(NotPaired {
                reference: 2,
                candidate: 1
            })
        );
        let mut other_seed = reference.clone();
        other_seed[1].seed += 1;
        assert!(PairedFailures::of(&reference, &other_seed).is_err());
    }

    /// With 10 episodes failed by the reference alone, a candidate needs at most 2 of its own
    /// for p < 0.05 (p = 158/4096 ≈ 0.039; with 3, 0.092); with 5, none is enough (0.0625).
    #[test]
    fn the_own_failures_a_lead_allows() {
        let with = |reference_only| PairedFailures {
            episodes: 512_000,
            both: 15,
            reference_only,
            candidate_only: 0,
        };
        assert_eq!(with(10).own_failures_for_a_lead(0.05), Some(2));
        assert!(sign_test_p(10, 3) >= 0.05);
        assert_eq!(with(5).own_failures_for_a_lead(0.05), None);
        assert_eq!(with(6).own_failures_for_a_lead(0.05), Some(0));
    }
}
