//! What the cell knows of its robot's sideways drift, kept from one episode to the next.
//!
//! A robot's kinematic calibration error bends every move it makes near the bore the same way;
//! the state filter learns that as a sideways drift per mm commanded (`StateFilter`). The
//! error belongs to the robot, not to the episode: a cell that keeps its robot keeps what it
//! learned. The next episode starts from the last one's drift and covariance, widened by how
//! much the drift may differ from one episode to the next (`FusionTuning::drift_change_sd`).
//! What an episode adds is what its own frames said, so the memory never feeds on itself, and
//! an episode that disagrees with it starts it again (`DriftKnowledge::updated_with`). Camera
//! ingestion also checks the memory frame by frame against a filter that does not have it
//! (`camera::ingest`, docs/estimation.md §3a).

use nalgebra::{Matrix6, Vector6};
use serde::{Deserialize, Serialize};

/// Beyond this Mahalanobis distance² (six components) between what an episode alone said of
/// the drift and what was remembered, the robot has changed (χ² with 6 degrees of freedom:
/// about 4e-5 by chance).
pub const ROBOT_CHANGED_DRIFT_CHI2: f64 = 30.0;

/// What [`DriftKnowledge::updated_with`] made of an episode.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Updated {
    pub knowledge: DriftKnowledge,
    /// The episode disagreed with the memory: only the episode's knowledge is kept.
    pub changed: bool,
}

/// The learned drift and its uncertainty, as the filter held them at the end of an episode.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DriftKnowledge {
    /// The extra move of {M} along x (first three) and y (last three) per mm commanded along
    /// x, y and z of {M}.
    pub per_mm: [f64; 6],
    /// Covariance of the errors of `per_mm`, row by row.
    pub covariance: [[f64; 6]; 6],
    /// Episodes it was learned over.
    pub episodes: u32,
}

impl DriftKnowledge {
    /// The covariance is kept symmetric: its two halves, which rounding may have parted, are
    /// averaged.
    pub fn new(per_mm: &Vector6<f64>, covariance: &Matrix6<f64>, episodes: u32) -> Self {
        let covariance = (covariance + covariance.transpose()) * 0.5;
        DriftKnowledge {
            per_mm: (*per_mm).into(),
            covariance: std::array::from_fn(|i| std::array::from_fn(|j| covariance[(i, j)])),
            episodes,
        }
    }

    pub fn per_mm_vector(&self) -> Vector6<f64> {
        Vector6::from(self.per_mm)
    }

    pub fn covariance_matrix(&self) -> Matrix6<f64> {
        Matrix6::from_fn(|i, j| self.covariance[i][j])
    }

    /// The drift's rms over its six components (per mm).
    pub fn rms_per_mm(&self) -> f64 {
        (self.per_mm_vector().norm_squared() / 6.0).sqrt()
    }

    /// σ of each component of `per_mm`.
    pub fn sd_per_mm(&self) -> [f64; 6] {
        std::array::from_fn(|i| self.covariance[i][i].max(0.0).sqrt())
    }

    /// The prior for the next episode: each component may have changed by `change_sd` per mm.
    pub fn carried(&self, change_sd: f64) -> Self {
        let mut next = *self;
        for (i, row) in next.covariance.iter_mut().enumerate() {
            row[i] += change_sd * change_sd;
        }
        next
    }

    /// Adds what one episode taught to what was known before it (`self`, carried to the
    /// episode). `episode` is the drift as a filter that started the episode from the prior for
    /// an unseen robot (mean 0, σ `prior_sd` per component) ended it: its information less the
    /// prior's is what the episode's own moves and frames said, independent of what was known
    /// before, so the memory never feeds on itself. If the episode disagrees with the memory
    /// beyond [`ROBOT_CHANGED_DRIFT_CHI2`], the robot has changed and the episode's knowledge
    /// alone is kept (`changed` is then true).
    pub fn updated_with(&self, episode: &DriftKnowledge, prior_sd: f64) -> Updated {
        let restart = || Updated {
            knowledge: DriftKnowledge {
                episodes: 1,
                ..*episode
            },
            changed: true,
        };
        let (known, seen) = (self.covariance_matrix(), episode.covariance_matrix());
        let gap = episode.per_mm_vector() - self.per_mm_vector();
        let Some(apart) = (known + seen).cholesky().map(|c| c.inverse()) else {
            return restart();
        };
        if (gap.transpose() * apart * gap)[(0, 0)] > ROBOT_CHANGED_DRIFT_CHI2 {
            return restart();
        }
        let (Some(known_inverse), Some(seen_inverse)) = (
            known.cholesky().map(|c| c.inverse()),
            seen.cholesky().map(|c| c.inverse()),
        ) else {
            return restart();
        };
        let prior_information = Matrix6::from_diagonal_element(prior_sd.powi(-2));
        let information = known_inverse + seen_inverse - prior_information;
        let Some(covariance) = information.cholesky().map(|c| c.inverse()) else {
            return restart();
        };
        let mean = covariance
            * (known_inverse * self.per_mm_vector() + seen_inverse * episode.per_mm_vector());
        Updated {
            knowledge: DriftKnowledge::new(&mean, &covariance, self.episodes + 1),
            changed: false,
        }
    }

    /// Usable as a prior: finite, with a covariance that is symmetric and positive definite.
    pub fn is_usable(&self) -> bool {
        let c = self.covariance_matrix();
        self.per_mm.iter().all(|v| v.is_finite())
            && c.iter().all(|v| v.is_finite())
            && (c - c.transpose()).abs().max() <= 1e-9 * c.abs().max()
            && c.cholesky().is_some()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn knowledge() -> DriftKnowledge {
        let mut c = Matrix6::from_diagonal_element(1e-8);
        c[(0, 1)] = 2e-9;
        c[(1, 0)] = 2e-9;
        DriftKnowledge::new(&Vector6::new(1e-3, -2e-4, 5e-4, 0.0, 3e-4, -1e-3), &c, 3)
    }

    #[test]
    fn round_trips_through_its_matrices_and_json() {
        let k = knowledge();
        let again = DriftKnowledge::new(&k.per_mm_vector(), &k.covariance_matrix(), k.episodes);
        assert_eq!(again, k);
        let json = serde_json::to_string(&k).unwrap();
        assert_eq!(serde_json::from_str::<DriftKnowledge>(&json).unwrap(), k);
    }

    #[test]
    fn carrying_adds_the_change_to_each_variance_only() {
        let k = knowledge();
        let next = k.carried(1e-4);
        // 1e-8 + (1e-4)² = 2e-8 on the diagonal: σ √2 times larger.
        for i in 0..6 {
            assert!((next.covariance[i][i] - 2e-8).abs() < 1e-20);
            assert!((next.sd_per_mm()[i] - 2f64.sqrt() * 1e-4).abs() < 1e-12);
        }
        assert_eq!(next.covariance[0][1], 2e-9);
        assert_eq!(next.per_mm, k.per_mm);
        assert_eq!(next.episodes, k.episodes);
    }

    /// Diagonal knowledge: each component `mean`, σ `sd`.
    fn isotropic(mean: f64, sd: f64, episodes: u32) -> DriftKnowledge {
        DriftKnowledge::new(
            &Vector6::repeat(mean),
            &Matrix6::from_diagonal_element(sd * sd),
            episodes,
        )
    }

    #[test]
    fn an_episode_adds_its_own_information_only() {
        // Remembered: 1e-3 ± 2e-4. The episode alone measured 1.3e-3 ± 3e-4, seen through a
        // filter that started from 0 ± 2e-3: its posterior is that measurement fused with the
        // prior, information 1/(3e-4)² + 1/(2e-3)².
        let (prior, measured, measured_sd): (f64, f64, f64) = (2e-3, 1.3e-3, 3e-4);
        let information = measured_sd.powi(-2) + prior.powi(-2);
        let episode = isotropic(
            measured / measured_sd.powi(2) / information,
            information.sqrt().recip(),
            1,
        );
        let memory = isotropic(1e-3, 2e-4, 4);
        let updated = memory.updated_with(&episode, prior);
        assert!(!updated.changed);
        // By hand: the two measurements weighted by their information.
        let (w1, w2) = (2e-4f64.powi(-2), measured_sd.powi(-2));
        let mean = (1e-3 * w1 + measured * w2) / (w1 + w2);
        let sd = (w1 + w2).sqrt().recip();
        let k = updated.knowledge;
        for i in 0..6 {
            assert!(
                (k.per_mm[i] - mean).abs() < 1e-12,
                "{} against {mean}",
                k.per_mm[i]
            );
            assert!((k.sd_per_mm()[i] - sd).abs() < 1e-12);
        }
        assert_eq!(k.episodes, 5);
    }

    #[test]
    fn an_episode_far_from_the_memory_starts_it_again() {
        let memory = isotropic(1e-3, 5e-5, 20);
        let episode = isotropic(-1e-3, 3e-4, 1);
        let updated = memory.updated_with(&episode, 2e-3);
        assert!(updated.changed);
        assert_eq!(
            updated.knowledge,
            DriftKnowledge {
                episodes: 1,
                ..episode
            }
        );
    }

    #[test]
    fn a_broken_covariance_is_not_usable() {
        assert!(knowledge().is_usable());
        let mut negative = knowledge();
        negative.covariance[2][2] = -1e-8;
        assert!(!negative.is_usable());
        let mut lopsided = knowledge();
        lopsided.covariance[0][1] = 5e-9;
        assert!(!lopsided.is_usable());
        let mut nan = knowledge();
        nan.per_mm[4] = f64::NAN;
        assert!(!nan.is_usable());
    }
}
