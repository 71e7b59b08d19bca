//! The chance constraint's arithmetic (docs/estimation.md): how many σ of the estimate's
//! errors the supervisor's envelope must span for a given bound on the probability of contact,
//! and the probability a given clearance leaves.
//!
//! The envelope is exceeded only if one of four Gaussian errors exceeds k of its σ: the
//! sideways displacement at either end of the part of the shaft inside the bore (two 2-D
//! vectors), the tilt (a 2-D vector) or the axial position (1-D). A 2-D Gaussian vector whose
//! covariance's largest eigenvalue is at most σ² exceeds kσ in length with probability at
//! most `exp(−k²/2)`; a 1-D one exceeds it in size with probability `erfc(k/√2)`. By the union
//! bound, the probability of contact is at most `3·exp(−k²/2) + erfc(k/√2)`.

use super::clearance::{Clearance, Growth};

/// σ of how far any point of Segment I may be from where the mean estimate puts it (mm).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Spread {
    pub sideways_mm: f64,
    pub axial_mm: f64,
    /// Along the axis, for the shoulder's outer rim.
    pub seat_mm: f64,
}

impl Spread {
    /// The envelope of `sigmas` σ.
    pub fn scaled(&self, sigmas: f64) -> Growth {
        Growth {
            sideways_mm: self.sideways_mm * sigmas,
            axial_mm: self.axial_mm * sigmas,
            seat_mm: self.seat_mm * sigmas,
        }
    }
}

/// The bound on the probability that an envelope of `sigmas` σ is exceeded.
pub fn risk_at(sigmas: f64) -> f64 {
    if sigmas.is_nan() || sigmas <= 0.0 {
        return 1.0;
    }
    (3.0 * (-sigmas * sigmas / 2.0).exp() + erfc(sigmas / std::f64::consts::SQRT_2)).min(1.0)
}

/// The smallest number of σ whose envelope is exceeded with probability at most `bound`.
pub fn sigmas_for(bound: f64) -> f64 {
    let (mut lo, mut hi) = (0.0, 40.0);
    for _ in 0..100 {
        let mid = 0.5 * (lo + hi);
        if risk_at(mid) > bound {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    hi
}

/// The estimated probability of contact along a move whose clearance by the mean estimate is
/// `along`, for a spread `spread`: the bound for the envelope that just closes the smaller gap
/// (in σ of its direction). 0 when the parts cannot touch.
pub fn contact_risk(along: &Clearance, spread: &Spread) -> f64 {
    let ratio = |gap: f64, sd: f64| {
        if gap.is_infinite() {
            f64::INFINITY
        } else if sd > 0.0 {
            gap / sd
        } else if gap > 0.0 {
            f64::INFINITY
        } else {
            0.0
        }
    };
    let sigmas = ratio(along.wall_mm, spread.sideways_mm).min(ratio(along.seat_mm, spread.seat_mm));
    if sigmas.is_infinite() {
        0.0
    } else {
        risk_at(sigmas)
    }
}

/// The complementary error function (Numerical Recipes' Chebyshev fit, relative error below
/// 1.2e-7 everywhere).
pub fn erfc(x: f64) -> f64 {
    let z = x.abs();
    let t = 1.0 / (1.0 + 0.5 * z);
    let poly = -z * z - 1.265_512_23
        + t * (1.000_023_68
            + t * (0.374_091_96
                + t * (0.096_784_18
                    + t * (-0.186_288_06
                        + t * (0.278_868_07
                            + t * (-1.135_203_98
                                + t * (1.488_515_87 + t * (-0.822_152_23 + t * 0.170_872_77))))))));
    let r = t * poly.exp();
    if x >= 0.0 { r } else { 2.0 - r }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn erfc_matches_published_values() {
        // Abramowitz & Stegun, Table 7.1.
        for (x, want) in [
            (0.0, 1.0),
            (0.5, 0.479_500_122),
            (1.0, 0.157_299_207),
            (2.0, 4.677_734_98e-3),
            (3.0, 2.209_049_70e-5),
            (-1.0, 1.842_700_793),
        ] {
            assert!(
                ((erfc(x) - want) / want).abs() < 2e-7,
                "erfc({x}) = {}",
                erfc(x)
            );
        }
    }

    #[test]
    fn the_envelope_for_a_bound_is_exceeded_that_rarely() {
        for bound in [1e-2, 1e-4, 1e-6] {
            let k = sigmas_for(bound);
            assert!((risk_at(k) - bound).abs() < bound * 1e-6, "{bound}: {k}");
            assert!(risk_at(k * 0.99) > bound);
        }
        // 1e-4 per move needs about 4.6 σ.
        assert!(
            (sigmas_for(1e-4) - 4.57).abs() < 0.02,
            "{}",
            sigmas_for(1e-4)
        );
        // A 2-D isotropic Gaussian exceeds kσ with probability exp(−k²/2) exactly: the bound
        // is three of those plus the 1-D tail.
        assert!((risk_at(3.0) - (3.0 * (-4.5f64).exp() + erfc(3.0 / 2f64.sqrt()))).abs() < 1e-15);
    }

    #[test]
    fn the_risk_falls_with_the_clearance() {
        let spread = Spread {
            sideways_mm: 0.01,
            axial_mm: 0.01,
            seat_mm: 0.01,
        };
        let at = |wall_mm| {
            contact_risk(
                &Clearance {
                    wall_mm,
                    seat_mm: f64::INFINITY,
                },
                &spread,
            )
        };
        assert_eq!(at(f64::INFINITY), 0.0);
        assert_eq!(at(0.0), 1.0);
        assert!(at(0.02) > at(0.03) && at(0.03) > at(0.045));
        assert!((at(0.0457) - 1e-4).abs() < 2e-5, "{}", at(0.0457));
    }
}
