//! Why a kinematic computation was refused.

/// A refused inverse or forward kinematics computation. Every message carries its numbers.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum KinematicsError {
    /// A leg would leave its stroke. `leg` is the 0-based leg index; the message names it 1-based.
    #[error(
        "leg {} out of stroke: {length_mm:.3} mm not in [{min_mm:.3}, {max_mm:.3}] mm",
        leg + 1
    )]
    LegOutOfStroke {
        leg: usize,
        length_mm: f64,
        min_mm: f64,
        max_mm: f64,
    },
    /// The pose is too close to a singularity: conditioning (dimensionless, 0..1) below threshold.
    #[error("near-singular pose: conditioning {conditioning:.5} below threshold {threshold:.5}")]
    NearSingular { conditioning: f64, threshold: f64 },
    /// Forward kinematics gave up; `residual_mm` is the largest leg-length residual at the end.
    #[error(
        "forward kinematics did not converge in {iterations} iterations: largest leg residual {residual_mm:.3e} mm"
    )]
    NoConvergence { iterations: u32, residual_mm: f64 },
    /// An input (pose or leg lengths) held a NaN or infinity.
    #[error("non-finite {what}")]
    NonFinite { what: &'static str },
}

impl KinematicsError {
    /// A short snake_case code for logs and APIs.
    pub fn code(&self) -> &'static str {
        match self {
            KinematicsError::LegOutOfStroke { .. } => "leg_out_of_stroke",
            KinematicsError::NearSingular { .. } => "near_singular",
            KinematicsError::NoConvergence { .. } => "no_convergence",
            KinematicsError::NonFinite { .. } => "non_finite",
        }
    }
}
