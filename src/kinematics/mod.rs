//! Kinematics of the 6-SPS parallel robot (Stewart platform) that carries Segment I.
//!
//! Frames: the base frame {O} sits at the centre of the base joint circle, z up; the platform
//! frame {P} sits at the centre of the platform joint circle. A platform pose is {P} in {O}
//! ([`Pose`], mm). Leg `i` joins base joint `a_i` (in {O}) to platform joint `b_i` (in {P}); its
//! length is `L_i = |r + R b_i - a_i|` (paper Eq. 2).
//!
//! - Inverse kinematics is closed form ([`StewartGeometry::leg_lengths_mm`],
//!   [`StewartGeometry::inverse_checked`]).
//! - Forward kinematics is Newton-Raphson (paper Eqs. 3-6, [`StewartGeometry::forward`]).
//! - [`StewartGeometry::conditioning`] measures the distance from a singularity.
//!
//! Everything here is allocation-free and uses nalgebra fixed-size types.

mod error;

pub use error::KinematicsError;

use crate::config::cell::RobotConfig;
use crate::geometry::pose::{Pose, is_finite};
use nalgebra::{Isometry3, Matrix3, Matrix6, Translation3, UnitQuaternion, Vector3, Vector6};

/// Forward kinematics gives up after this many Newton steps.
pub const FK_MAX_ITERATIONS: u32 = 20;
/// Forward kinematics stops once a Newton step is below this (mm for the translation part, rad
/// for the rotation part) ...
pub const FK_STEP_TOLERANCE: f64 = 1e-12;
/// ... and the largest leg-length residual `| |q_i| - L_i |` is at most this (mm).
pub const FK_RESIDUAL_TOLERANCE_MM: f64 = 1e-9;

/// The geometry of one 6-SPS robot: joint centres, stroke and singularity threshold.
#[derive(Debug, Clone, PartialEq)]
pub struct StewartGeometry {
    /// Base joint centres `a_i` in the base frame {O}, mm.
    pub base_joints_mm: [Vector3<f64>; 6],
    /// Platform joint centres `b_i` in the platform frame {P}, mm.
    pub platform_joints_mm: [Vector3<f64>; 6],
    /// Shortest leg length, mm.
    pub leg_min_mm: f64,
    /// Longest leg length, mm.
    pub leg_max_mm: f64,
    /// Height of {P} above {O} at home, mm.
    pub home_height_mm: f64,
    /// Poses whose [`conditioning`](StewartGeometry::conditioning) is below this are refused.
    pub singularity_threshold: f64,
}

/// The result of forward kinematics.
#[derive(Debug, Clone, PartialEq)]
pub struct FkSolution {
    /// The platform pose {P} in {O}.
    pub pose: Pose,
    /// Newton steps taken before the one that met the tolerances (0 when the start pose already
    /// solved the legs).
    pub iterations: u32,
    /// Largest leg-length residual `| |q_i| - L_i |` at the last evaluation, mm.
    pub residual_mm: f64,
}

impl StewartGeometry {
    /// The nominal robot of a cell file: its joint centres as the cell file places them
    /// ([`RobotConfig::base_joints_mm`], [`RobotConfig::platform_joints_mm`]).
    pub fn from_config(robot: &RobotConfig) -> Self {
        StewartGeometry {
            base_joints_mm: robot.base_joints_mm(),
            platform_joints_mm: robot.platform_joints_mm(),
            leg_min_mm: robot.leg_min_mm,
            leg_max_mm: robot.leg_max_mm,
            home_height_mm: robot.home_height_mm,
            singularity_threshold: robot.singularity_threshold,
        }
    }

    /// The home pose: {P} `home_height_mm` above {O}, unrotated.
    pub fn home_pose(&self) -> Pose {
        Isometry3::translation(0.0, 0.0, self.home_height_mm)
    }

    /// Leg lengths at the home pose, mm.
    pub fn home_leg_lengths_mm(&self) -> [f64; 6] {
        self.leg_lengths_mm(&self.home_pose())
    }

    /// Inverse kinematics (paper Eq. 2): `q_i = r + R b_i - a_i`, `L_i = |q_i|`, mm. No checks.
    pub fn leg_lengths_mm(&self, platform: &Pose) -> [f64; 6] {
        let r = platform.translation.vector;
        let rm: Matrix3<f64> = platform.rotation.to_rotation_matrix().into_inner();
        std::array::from_fn(|i| {
            (r + rm * self.platform_joints_mm[i] - self.base_joints_mm[i]).norm()
        })
    }

    /// Inverse kinematics with checks: a non-finite pose is [`KinematicsError::NonFinite`], a leg
    /// outside `[leg_min_mm, leg_max_mm]` is [`KinematicsError::LegOutOfStroke`] (the first such
    /// leg), a pose with [`conditioning`](Self::conditioning) below `singularity_threshold` is
    /// [`KinematicsError::NearSingular`]. Returns the leg lengths, mm.
    pub fn inverse_checked(&self, platform: &Pose) -> Result<[f64; 6], KinematicsError> {
        if !is_finite(platform) {
            return Err(KinematicsError::NonFinite {
                what: "platform pose",
            });
        }
        let legs = self.leg_lengths_mm(platform);
        if let Some((leg, &length_mm)) = legs
            .iter()
            .enumerate()
            .find(|(_, l)| !(self.leg_min_mm..=self.leg_max_mm).contains(*l))
        {
            return Err(KinematicsError::LegOutOfStroke {
                leg,
                length_mm,
                min_mm: self.leg_min_mm,
                max_mm: self.leg_max_mm,
            });
        }
        let conditioning = self.conditioning(platform);
        if conditioning < self.singularity_threshold {
            return Err(KinematicsError::NearSingular {
                conditioning,
                threshold: self.singularity_threshold,
            });
        }
        Ok(legs)
    }

    /// The inverse Jacobian at a pose: row `i` is `[u_iᵀ, (R b_i × u_i)ᵀ]` with `u_i` the unit
    /// vector of leg `i`, so that `dL = J [v; ω]` for a platform velocity `v` (mm/s, of the
    /// platform origin) and angular velocity `ω` (rad/s), both in {O}. Units: columns 0-2
    /// dimensionless, columns 3-5 mm.
    pub fn inverse_jacobian(&self, platform: &Pose) -> Matrix6<f64> {
        let r = platform.translation.vector;
        let rm: Matrix3<f64> = platform.rotation.to_rotation_matrix().into_inner();
        let mut j = Matrix6::zeros();
        for i in 0..6 {
            let rb = rm * self.platform_joints_mm[i];
            let q = r + rb - self.base_joints_mm[i];
            let u = q / q.norm();
            let m = rb.cross(&u);
            j.fixed_view_mut::<1, 3>(i, 0).copy_from(&u.transpose());
            j.fixed_view_mut::<1, 3>(i, 3).copy_from(&m.transpose());
        }
        j
    }

    /// Dimensionless conditioning of the inverse Jacobian at a pose: `|det J| / Π_i |row_i|`
    /// (Hadamard ratio) after dividing the angular columns by the platform radius (the mean
    /// distance of the platform joints from the platform origin), so that all entries are
    /// dimensionless. 1 = rows mutually orthogonal (perfectly conditioned), 0 = singular.
    pub fn conditioning(&self, platform: &Pose) -> f64 {
        let j = self.inverse_jacobian(platform);
        self.hadamard_ratio(&j, j.determinant())
    }

    /// The characteristic length (mm) that makes the angular Jacobian columns dimensionless.
    fn platform_scale_mm(&self) -> f64 {
        let sum: f64 = self.platform_joints_mm.iter().map(|b| b.xy().norm()).sum();
        sum / 6.0
    }

    /// `|det J_s| / Π |row_i(J_s)|` for `J_s` = `j` with columns 3-5 divided by the platform
    /// scale; `det_j` is `det j` (so callers holding an LU need not recompute it).
    fn hadamard_ratio(&self, j: &Matrix6<f64>, det_j: f64) -> f64 {
        let s = self.platform_scale_mm();
        if s.is_nan() || s <= 0.0 {
            return 0.0;
        }
        let mut row_product = 1.0;
        for i in 0..6 {
            let lin = j.fixed_view::<1, 3>(i, 0).norm_squared();
            let ang = j.fixed_view::<1, 3>(i, 3).norm_squared() / (s * s);
            row_product *= (lin + ang).sqrt();
        }
        let ratio = det_j.abs() / (s * s * s) / row_product;
        if ratio.is_finite() { ratio } else { 0.0 }
    }

    /// Forward kinematics by Newton-Raphson (paper Eqs. 3-6), starting from `start`.
    ///
    /// Unknowns: the platform translation `r` (mm) and a rotation increment `dθ` (rad) applied on
    /// the left, `R ← Exp(dθ) R`, i.e. a rotation vector in {O} about the platform origin. This
    /// local parametrisation has an analytic Jacobian (the inverse Jacobian
    /// [`inverse_jacobian`](Self::inverse_jacobian)) and no Euler-angle singularities. The
    /// residuals are `f_i = |q_i| - L_i`, which have the same roots as the paper's
    /// `|q_i|² - L_i²` for positive legs but are uniformly scaled in mm.
    ///
    /// Stops when the Newton step is below [`FK_STEP_TOLERANCE`] (mm and rad) and the largest
    /// residual is at most [`FK_RESIDUAL_TOLERANCE_MM`]. Safety net for the f64 rounding floor
    /// (~1e-13 mm at 1 m): with the residual within tolerance, a step ≤ 1e-9 that is no longer
    /// shrinking (≥ half the previous step) also counts as converged; over the reference
    /// workspace it never fires. The final step is applied but not counted. Errors: non-finite legs or start pose →
    /// [`KinematicsError::NonFinite`]; an iterate whose conditioning is below
    /// `singularity_threshold` → [`KinematicsError::NearSingular`]; more than
    /// [`FK_MAX_ITERATIONS`] steps → [`KinematicsError::NoConvergence`].
    pub fn forward(&self, legs_mm: &[f64; 6], start: &Pose) -> Result<FkSolution, KinematicsError> {
        if !legs_mm.iter().all(|l| l.is_finite()) {
            return Err(KinematicsError::NonFinite {
                what: "leg lengths",
            });
        }
        if !is_finite(start) {
            return Err(KinematicsError::NonFinite { what: "start pose" });
        }
        let mut r = start.translation.vector;
        let mut rotation = UnitQuaternion::new_normalize(start.rotation.into_inner());
        let mut previous_step = f64::INFINITY;
        let mut k = 0;
        loop {
            let rm: Matrix3<f64> = rotation.to_rotation_matrix().into_inner();
            let mut j = Matrix6::zeros();
            let mut f = Vector6::zeros();
            let mut residual: f64 = 0.0;
            for i in 0..6 {
                let rb = rm * self.platform_joints_mm[i];
                let q = r + rb - self.base_joints_mm[i];
                let len = q.norm();
                let u = q / len;
                let m = rb.cross(&u);
                j.fixed_view_mut::<1, 3>(i, 0).copy_from(&u.transpose());
                j.fixed_view_mut::<1, 3>(i, 3).copy_from(&m.transpose());
                f[i] = len - legs_mm[i];
                residual = residual.max(f[i].abs());
            }
            if !residual.is_finite() {
                return Err(KinematicsError::NoConvergence {
                    iterations: k,
                    residual_mm: residual,
                });
            }
            let lu = j.lu();
            let conditioning = self.hadamard_ratio(&j, lu.determinant());
            if conditioning < self.singularity_threshold {
                return Err(KinematicsError::NearSingular {
                    conditioning,
                    threshold: self.singularity_threshold,
                });
            }
            let Some(step) = lu.solve(&(-f)) else {
                return Err(KinematicsError::NearSingular {
                    conditioning: 0.0,
                    threshold: self.singularity_threshold,
                });
            };
            let dr = step.fixed_rows::<3>(0).into_owned();
            let dtheta = step.fixed_rows::<3>(3).into_owned();
            let step_size = dr.norm().max(dtheta.norm());
            let small = step_size <= FK_STEP_TOLERANCE
                || (step_size <= 1e3 * FK_STEP_TOLERANCE && step_size >= 0.5 * previous_step);
            let converged = residual <= FK_RESIDUAL_TOLERANCE_MM && small;
            r += dr;
            rotation = UnitQuaternion::new_normalize(
                UnitQuaternion::from_scaled_axis(dtheta).into_inner() * rotation.into_inner(),
            );
            if converged {
                return Ok(FkSolution {
                    pose: Isometry3::from_parts(Translation3::from(r), rotation),
                    iterations: k,
                    residual_mm: residual,
                });
            }
            if k >= FK_MAX_ITERATIONS {
                return Err(KinematicsError::NoConvergence {
                    iterations: k,
                    residual_mm: residual,
                });
            }
            previous_step = step_size;
            k += 1;
        }
    }

    /// The same robot with every joint centre moved: base offsets in {O}, platform offsets in
    /// {P}, mm. This is the "true" robot of a cell with kinematic calibration error.
    pub fn with_joint_offsets(
        &self,
        base_offsets_mm: &[Vector3<f64>; 6],
        platform_offsets_mm: &[Vector3<f64>; 6],
    ) -> Self {
        StewartGeometry {
            base_joints_mm: std::array::from_fn(|i| self.base_joints_mm[i] + base_offsets_mm[i]),
            platform_joints_mm: std::array::from_fn(|i| {
                self.platform_joints_mm[i] + platform_offsets_mm[i]
            }),
            ..self.clone()
        }
    }
}

#[cfg(test)]
mod tests;
