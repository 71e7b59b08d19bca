//! DA-DMP: the paper's learning-from-demonstration baseline (§4, "Transferability", after its
//! ref. [add15]): a Cartesian dynamic movement primitive — 3-D position and quaternion
//! orientation — fitted to the expert's demonstrations, replayed from each new start.
//!
//! The demonstrated trajectory is the pose of {M} relative to {F} (`f_m = m_f⁻¹`, built from P and
//! O of each recorded state), with the docked pose (`f_m` = identity) appended when the expert
//! docked. Every demonstration is mapped to the same phase (time-normalised to [0, 1]), a forcing
//! term is fitted to each by locally weighted regression on Gaussian basis functions of the phase,
//! and the weights are averaged over the demonstrations ("demonstration-trajectory adaptation":
//! the primitive carries the expert's typical shape).
//!
//! In normalised time s = t / (τ·D), with D the expert's mean duration (mean demonstration length
//! × the camera period) and τ = 1 (the paper's setting: the replay takes the expert's mean number
//! of steps):
//!
//! - canonical system: x' = −α_x x;
//! - position (per axis): z' = α(β(g − y) − z) + f(x), y' = z;
//! - orientation (Ude et al. 2014, unit quaternion q, log map): η' = α(β·2 log(g ∗ q̄) − η) + f(x),
//!   q ← exp(½ η ds) ∗ q, so q stays a unit quaternion by construction;
//! - f(x) = x Σ ψ_i(x) w_i / Σ ψ_i(x), ψ_i(x) = exp(−h_i (x − c_i)²).
//!
//! The forcing term is *not* multiplied by the amplitude (g − y0) (Pastor et al. 2009 do not
//! scale it either): the starts are offsets in random directions, so per-axis amplitudes change
//! sign from one demonstration to the next and are often near zero, which makes amplitude-scaled
//! weights blow up or cancel. Unscaled, the averaged weights reproduce the mean demonstration (the
//! system is linear in the weights), and a new start y0 enters as the transformation system's own
//! transient from y0, which decays onto the mean demonstrated path. The gains are stiff (α = 100,
//! β = α/4, critically damped) so that the transient of a 50 mm start offset has died out well
//! before the demonstrated insertion begins; with the textbook α = 25 it has not, and the replay
//! steers the shaft into the entrance face (every episode ends in vetoes). 80 basis functions,
//! more than the ~47 samples of a demonstration (the regression is local), follow the expert's
//! step-like path to a fraction of a millimetre.
//!
//! As a controller: at the first fresh observation the primitive is rolled out from the observed
//! pose (one target pose per camera cycle); at each step it commands the move that takes {M} from
//! its observed pose to the next target, orientation and position in one 6-D move, each component
//! clamped to the step limits; after the last target it keeps commanding the docked pose.

use super::record::{DemoEpisode, record_expert};
use super::{Controller, Decision, clamp_components};
use crate::config::cell::CellConfig;
use crate::geometry::Move;
use crate::geometry::pose::{Pose, pose_from_mm_deg};
use crate::sim::{EnvOptions, Observation};
use nalgebra::{Quaternion, Translation3, UnitQuaternion, Vector3};

/// The name `celld eval --controller` knows the baseline by.
pub const NAME: &str = "da-dmp";

/// Expert demonstrations [`default_dmp`] records, and their seed.
pub const DEFAULT_DEMONSTRATIONS: usize = 20;
pub const DEFAULT_SEED: u64 = 0xD4D3;

/// Settings of the primitive.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DmpSettings {
    /// α of the transformation systems.
    pub alpha: f64,
    /// β of the transformation systems (α/4: critically damped).
    pub beta: f64,
    /// Decay of the canonical system: the phase is e^{−α_x} at the end of the movement.
    pub alpha_x: f64,
    /// Gaussian basis functions per dimension.
    pub basis: usize,
    /// Time scaling factor: 1 = the expert's mean duration.
    pub tau: f64,
    /// Integration sub-steps per camera cycle.
    pub substeps: usize,
}

impl Default for DmpSettings {
    fn default() -> Self {
        DmpSettings {
            alpha: 100.0,
            beta: 25.0,
            alpha_x: 4.0,
            basis: 80,
            tau: 1.0,
            substeps: 20,
        }
    }
}

impl DmpSettings {
    fn validate(&self) -> Result<(), DmpError> {
        let positive = |v: f64| v.is_finite() && v > 0.0;
        if !(positive(self.alpha) && positive(self.beta) && positive(self.alpha_x)) {
            return Err(DmpError::InvalidSettings(
                "alpha, beta and alpha_x must be positive numbers".into(),
            ));
        }
        if !positive(self.tau) {
            return Err(DmpError::InvalidSettings(
                "tau must be a positive number".into(),
            ));
        }
        if self.basis < 2 || self.substeps < 1 {
            return Err(DmpError::InvalidSettings(
                "at least 2 basis functions and 1 sub-step are needed".into(),
            ));
        }
        Ok(())
    }
}

/// Why a primitive could not be fitted.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DmpError {
    #[error("no demonstrations to fit the DMP to")]
    NoDemonstrations,
    #[error(
        "demonstration {index} has {steps} step(s); fitting a DMP needs at least 2 per demonstration"
    )]
    TooShort { index: usize, steps: usize },
    #[error("demonstration {index}, step {step}: the state holds a non-finite number")]
    NonFinite { index: usize, step: usize },
    #[error("invalid DMP settings: {0}")]
    InvalidSettings(String),
}

/// Width of the basis functions: h_i = WIDTH_FACTOR / (c_i − c_{i+1})², so neighbours cross at
/// e^{−WIDTH_FACTOR/4} of their peak.
const WIDTH_FACTOR: f64 = 2.0;

/// Gaussian basis functions in the phase, centred at equal intervals of (normalised) time.
#[derive(Debug, Clone, PartialEq)]
struct Basis {
    centres: Vec<f64>,
    widths: Vec<f64>,
}

impl Basis {
    fn new(n: usize, alpha_x: f64) -> Self {
        let centres: Vec<f64> = (0..n)
            .map(|i| (-alpha_x * i as f64 / (n - 1) as f64).exp())
            .collect();
        let widths = (0..n)
            .map(|i| {
                let d = if i + 1 < n {
                    centres[i] - centres[i + 1]
                } else {
                    centres[i - 1] - centres[i]
                };
                WIDTH_FACTOR / (d * d)
            })
            .collect();
        Basis { centres, widths }
    }

    /// ψ_i(x) for every basis function, into `out`.
    fn activations(&self, x: f64, out: &mut Vec<f64>) {
        out.clear();
        out.extend(self.centres.iter().zip(&self.widths).map(|(c, h)| {
            let d = x - c;
            (-h * d * d).exp()
        }));
    }

    /// f(x) = x Σ ψ_i w_i / Σ ψ_i, from the activations ψ at x.
    fn forcing(psi: &[f64], weights: &[f64], x: f64) -> f64 {
        let (num, den) = psi
            .iter()
            .zip(weights)
            .fold((0.0, 0.0), |(num, den), (psi, w)| {
                (num + psi * w, den + psi)
            });
        if den > 1e-300 { x * num / den } else { 0.0 }
    }

    /// Locally weighted regression, one weight per basis function and dimension: the targets
    /// `f[dim][j]` at phases `x[j]` fitted by x·w_i under the weights ψ_i(x),
    /// w_i = Σ_j ψ_i x_j f_j / Σ_j ψ_i x_j².
    fn regress(&self, x: &[f64], f: &[Vec<f64>; 6]) -> [Vec<f64>; 6] {
        let n = self.centres.len();
        let mut num: [Vec<f64>; 6] = std::array::from_fn(|_| vec![0.0; n]);
        let mut den = vec![0.0; n];
        let mut psi = Vec::with_capacity(n);
        for (j, &x) in x.iter().enumerate() {
            self.activations(x, &mut psi);
            for (i, psi) in psi.iter().enumerate() {
                den[i] += psi * x * x;
                for (num, f) in num.iter_mut().zip(f) {
                    num[i] += psi * x * f[j];
                }
            }
        }
        for num in &mut num {
            for (w, den) in num.iter_mut().zip(&den) {
                *w = if *den > 1e-12 { *w / den } else { 0.0 };
            }
        }
        num
    }
}

/// The DA-DMP baseline: the fitted primitive, and as a [`Controller`] the episode's plan.
#[derive(Debug, Clone)]
pub struct DaDmp {
    settings: DmpSettings,
    basis: Basis,
    /// Forcing-term weights: position x, y, z, then orientation x, y, z (log map).
    weights: [Vec<f64>; 6],
    mean_steps: f64,
    demonstrations: usize,
    limit_mm: f64,
    limit_deg: f64,
    // Episode state.
    plan: Option<Vec<Pose>>,
    start_step: u32,
}

/// The demonstrated trajectory of one recorded episode: the pose of {M} in {F} at each step, with
/// the docked pose appended when the episode succeeded.
pub fn demonstration_poses(episode: &DemoEpisode, index: usize) -> Result<Vec<Pose>, DmpError> {
    if episode.steps.len() < 2 {
        return Err(DmpError::TooShort {
            index,
            steps: episode.steps.len(),
        });
    }
    let mut poses = Vec::with_capacity(episode.steps.len() + 1);
    for (step, s) in episode.steps.iter().enumerate() {
        if !s.state.iter().all(|v| v.is_finite()) {
            return Err(DmpError::NonFinite { index, step });
        }
        poses.push(f_m_from_state(&s.state));
    }
    if episode.succeeded {
        poses.push(Pose::identity());
    }
    Ok(poses)
}

/// The pose of {M} in {F} from a 12-dim state (P = {F}'s origin in {M}, O its rotation vector).
fn f_m_from_state(state: &[f64; 12]) -> Pose {
    m_f_from_state(state).inverse()
}

fn m_f_from_state(state: &[f64; 12]) -> Pose {
    pose_from_mm_deg(
        Vector3::new(state[6], state[7], state[8]),
        Vector3::new(state[9], state[10], state[11]),
    )
}

/// The orientations of a trajectory as quaternions with continuous signs: each one in the
/// hemisphere of the one before, the first in the goal's (identity's) hemisphere.
pub fn continuous_quaternions(poses: &[Pose]) -> Vec<Quaternion<f64>> {
    let mut out: Vec<Quaternion<f64>> = Vec::with_capacity(poses.len());
    for pose in poses {
        let q = *pose.rotation.quaternion();
        let reference = out.last().copied().unwrap_or_else(Quaternion::identity);
        out.push(if q.dot(&reference) < 0.0 { -q } else { q });
    }
    out
}

/// The quaternion log map of a unit quaternion: half its rotation vector (rad). `q` and −q give
/// the long and the short way round; callers keep signs continuous.
fn quat_log(q: &Quaternion<f64>) -> Vector3<f64> {
    let v = q.imag();
    let n = v.norm();
    if n < 1e-15 {
        return Vector3::zeros();
    }
    v * (n.atan2(q.w) / n)
}

/// 2 log(a ∗ b̄) with the short way round: the rotation vector (rad) that takes b to a.
fn rotation_between(a: &Quaternion<f64>, b: &Quaternion<f64>) -> Vector3<f64> {
    let d = a * b.conjugate();
    let d = if d.w < 0.0 { -d } else { d };
    quat_log(&d) * 2.0
}

/// Central differences on a uniform grid of spacing `h` (one-sided at the ends).
fn gradient(values: &[Vector3<f64>], h: f64) -> Vec<Vector3<f64>> {
    let n = values.len();
    (0..n)
        .map(|j| {
            let (a, b) = (j.saturating_sub(1), (j + 1).min(n - 1));
            (values[b] - values[a]) / (h * (b - a) as f64)
        })
        .collect()
}

/// Forcing targets of one demonstration on the normalised phase: (phases, [6 dims of f]).
fn forcing_targets(poses: &[Pose], settings: &DmpSettings) -> (Vec<f64>, [Vec<f64>; 6]) {
    let n = poses.len();
    let h = 1.0 / (n - 1) as f64;
    let (alpha, beta) = (settings.alpha, settings.beta);
    let phases: Vec<f64> = (0..n)
        .map(|j| (-settings.alpha_x * j as f64 * h).exp())
        .collect();
    // Position: the goal is the origin of {F}.
    let y: Vec<Vector3<f64>> = poses.iter().map(|p| p.translation.vector).collect();
    let yd = gradient(&y, h);
    let ydd = gradient(&yd, h);
    // Orientation: angular velocity (in {F}) from the log map of neighbouring quaternions.
    let q = continuous_quaternions(poses);
    let omega: Vec<Vector3<f64>> = (0..n)
        .map(|j| {
            let (a, b) = (j.saturating_sub(1), (j + 1).min(n - 1));
            rotation_between(&q[b], &q[a]) / (h * (b - a) as f64)
        })
        .collect();
    let omega_d = gradient(&omega, h);
    let goal = Quaternion::identity();
    let mut targets: [Vec<f64>; 6] = Default::default();
    for j in 0..n {
        let fp = ydd[j] - (-y[j] * beta - yd[j]) * alpha;
        let to_goal = rotation_between(&goal, &q[j]);
        let fo = omega_d[j] - (to_goal * beta - omega[j]) * alpha;
        for k in 0..3 {
            targets[k].push(fp[k]);
            targets[k + 3].push(fo[k]);
        }
    }
    (phases, targets)
}

impl DaDmp {
    /// Fits the primitive to recorded expert episodes with the default settings (see the module
    /// documentation); the step limits come from `cell`.
    pub fn fit(demos: &[DemoEpisode], cell: &CellConfig) -> Result<DaDmp, DmpError> {
        Self::fit_with(demos, cell, DmpSettings::default())
    }

    /// [`DaDmp::fit`] with explicit settings.
    pub fn fit_with(
        demos: &[DemoEpisode],
        cell: &CellConfig,
        settings: DmpSettings,
    ) -> Result<DaDmp, DmpError> {
        if demos.is_empty() {
            return Err(DmpError::NoDemonstrations);
        }
        let trajectories = demos
            .iter()
            .enumerate()
            .map(|(index, episode)| demonstration_poses(episode, index))
            .collect::<Result<Vec<_>, _>>()?;
        // The duration is the expert's mean number of steps (moves), whether or not the docked
        // pose was appended.
        let mean_steps =
            demos.iter().map(|e| e.steps.len() as f64).sum::<f64>() / demos.len() as f64;
        Self::from_trajectories(&trajectories, mean_steps, cell, settings)
    }

    /// Fits the primitive to pose trajectories of {M} in {F} (one pose per camera cycle, the
    /// docked pose as the goal), replayed over `mean_steps` camera cycles at τ = 1.
    pub fn from_trajectories(
        trajectories: &[Vec<Pose>],
        mean_steps: f64,
        cell: &CellConfig,
        settings: DmpSettings,
    ) -> Result<DaDmp, DmpError> {
        settings.validate()?;
        if trajectories.is_empty() {
            return Err(DmpError::NoDemonstrations);
        }
        for (index, poses) in trajectories.iter().enumerate() {
            if poses.len() < 2 {
                return Err(DmpError::TooShort {
                    index,
                    steps: poses.len(),
                });
            }
            if let Some(step) = poses
                .iter()
                .position(|p| !crate::geometry::pose::is_finite(p))
            {
                return Err(DmpError::NonFinite { index, step });
            }
        }
        if !(mean_steps.is_finite() && mean_steps >= 1.0) {
            return Err(DmpError::InvalidSettings(format!(
                "the mean demonstration length must be at least one step, not {mean_steps}"
            )));
        }
        let basis = Basis::new(settings.basis, settings.alpha_x);
        let mut weights: [Vec<f64>; 6] = std::array::from_fn(|_| vec![0.0; settings.basis]);
        for poses in trajectories {
            let (phases, targets) = forcing_targets(poses, &settings);
            let fitted = basis.regress(&phases, &targets);
            for (sum, w) in weights.iter_mut().zip(&fitted) {
                for (sum, w) in sum.iter_mut().zip(w) {
                    *sum += w / trajectories.len() as f64;
                }
            }
        }
        Ok(DaDmp {
            settings,
            basis,
            weights,
            mean_steps,
            demonstrations: trajectories.len(),
            limit_mm: cell.steps.position_mm,
            limit_deg: cell.steps.orientation_deg,
            plan: None,
            start_step: 0,
        })
    }

    pub fn settings(&self) -> &DmpSettings {
        &self.settings
    }

    /// The forcing-term weights: position x, y, z, then orientation x, y, z.
    pub fn weights(&self) -> &[Vec<f64>; 6] {
        &self.weights
    }

    /// The expert's mean number of steps per demonstration.
    pub fn mean_demo_steps(&self) -> f64 {
        self.mean_steps
    }

    /// How many demonstrations the primitive was fitted to.
    pub fn demonstrations(&self) -> usize {
        self.demonstrations
    }

    /// Camera cycles the replay takes: τ × the expert's mean number of steps.
    pub fn rollout_steps(&self) -> usize {
        (self.settings.tau * self.mean_steps).round().max(1.0) as usize
    }

    /// Rolls the primitive out from `start` (a pose of {M} in {F}) at rest: the target pose of
    /// {M} in {F} at each camera cycle, `start` first, `rollout_steps() + 1` poses in all.
    pub fn rollout(&self, start: &Pose) -> Vec<Pose> {
        let steps = self.rollout_steps();
        let substeps = self.settings.substeps;
        let ds = 1.0 / (self.settings.tau * self.mean_steps * substeps as f64);
        let (alpha, beta) = (self.settings.alpha, self.settings.beta);
        let goal = Quaternion::identity();
        let mut y = start.translation.vector;
        let mut z = Vector3::zeros();
        let mut q = *start.rotation.quaternion();
        if q.w < 0.0 {
            q = -q;
        }
        let mut eta = Vector3::zeros();
        let mut s = 0.0;
        let mut psi = Vec::with_capacity(self.settings.basis);
        let mut plan = Vec::with_capacity(steps + 1);
        plan.push(*start);
        for _ in 0..steps {
            for _ in 0..substeps {
                let x = (-self.settings.alpha_x * s).exp();
                self.basis.activations(x, &mut psi);
                let f = |dim: usize| Basis::forcing(&psi, &self.weights[dim], x);
                let fp = Vector3::new(f(0), f(1), f(2));
                let fo = Vector3::new(f(3), f(4), f(5));
                // Semi-implicit Euler: velocities first, then positions with the new velocities.
                z += ((-y * beta - z) * alpha + fp) * ds;
                y += z * ds;
                eta += ((rotation_between(&goal, &q) * beta - eta) * alpha + fo) * ds;
                q = UnitQuaternion::from_scaled_axis(eta * ds).into_inner() * q;
                q = q.normalize();
                s += ds;
            }
            let rotation = UnitQuaternion::from_quaternion(q);
            let pose = Pose::from_parts(Translation3::from(y), rotation);
            if !crate::geometry::pose::is_finite(&pose) {
                break;
            }
            plan.push(pose);
        }
        plan
    }

    /// The move of {M} (in {M}) from `m_f` (the observed pose of {F} in {M}) towards `target`
    /// (a pose of {M} in {F}), every component clamped to the step limits.
    fn move_towards(&self, m_f: &Pose, target: &Pose) -> Move {
        // new {M} = old {M} · A, so A = f_m⁻¹ · target = m_f · target.
        let a = m_f * target;
        Move {
            translation_mm: clamp_components(a.translation.vector, self.limit_mm),
            rotation_deg: clamp_components(
                a.rotation.scaled_axis().map(f64::to_degrees),
                self.limit_deg,
            ),
        }
    }
}

impl Controller for DaDmp {
    fn name(&self) -> &str {
        NAME
    }

    fn reset(&mut self, _seed: u64) {
        self.plan = None;
        self.start_step = 0;
    }

    fn act(&mut self, observation: &Observation) -> Decision {
        let state = &observation.state;
        if !observation.measurement_fresh || !state[6..].iter().all(|v| v.is_finite()) {
            return Decision::hold();
        }
        let m_f = m_f_from_state(state);
        if self.plan.is_none() {
            self.start_step = observation.step;
            self.plan = Some(self.rollout(&m_f.inverse()));
        }
        let plan = self.plan.as_deref().unwrap_or_default();
        let next = observation.step.saturating_sub(self.start_step) as usize + 1;
        let target = plan.get(next).copied().unwrap_or_else(Pose::identity);
        let action = self.move_towards(&m_f, &target);
        if action.is_finite() {
            Decision::plain(action)
        } else {
            Decision::hold()
        }
    }
}

/// The DA-DMP `celld eval --controller da-dmp` uses: fitted to [`DEFAULT_DEMONSTRATIONS`] expert
/// episodes recorded in `cell`'s twin with [`DEFAULT_SEED`] (the successful ones, when any).
pub fn try_default_dmp(cell: &CellConfig) -> Result<DaDmp, DmpError> {
    let demos = record_expert(
        cell,
        EnvOptions::from_cell(cell),
        DEFAULT_DEMONSTRATIONS,
        DEFAULT_SEED,
    );
    let usable: Vec<DemoEpisode> = demos
        .iter()
        .filter(|e| e.succeeded && e.steps.len() >= 2)
        .cloned()
        .collect();
    if usable.is_empty() {
        DaDmp::fit(&demos, cell)
    } else {
        DaDmp::fit(&usable, cell)
    }
}

/// [`try_default_dmp`], for the built-in controller table.
///
/// # Panics
/// When the expert cannot produce a single usable demonstration in `cell` (every episode failed
/// to start or ended within a step): there is then nothing to learn from.
pub fn default_dmp(cell: &CellConfig) -> DaDmp {
    try_default_dmp(cell).unwrap_or_else(|e| panic!("fitting the default DA-DMP: {e}"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{FusionTuning, StateFilter};
    use crate::policy::Actor;
    use crate::policy::record::DemoStep;

    /// Minimum-jerk profile from 0 to 1 over u ∈ [0, 1] (clamped outside).
    fn mj(u: f64) -> f64 {
        let u = u.clamp(0.0, 1.0);
        u * u * u * (10.0 - 15.0 * u + 6.0 * u * u)
    }

    /// A demonstration shaped like the expert's: lateral first, down to the entrance, a pause,
    /// then the insertion; the orientation corrected early. `steps` camera cycles.
    fn synthetic(steps: usize, start: Vector3<f64>, rotation_deg: Vector3<f64>) -> Vec<Pose> {
        (0..=steps)
            .map(|j| {
                let s = j as f64 / steps as f64;
                let lateral = 1.0 - mj(s / 0.4);
                let z = if s < 0.5 {
                    60.0 + (start.z - 60.0) * (1.0 - mj(s / 0.3))
                } else {
                    60.0 * (1.0 - mj((s - 0.5) / 0.5))
                };
                let t = Vector3::new(start.x * lateral, start.y * lateral, z);
                pose_from_mm_deg(t, rotation_deg * (1.0 - mj(s / 0.3)))
            })
            .collect()
    }

    fn demo() -> Vec<Pose> {
        synthetic(
            50,
            Vector3::new(30.0, -20.0, 80.0),
            Vector3::new(0.8, -0.5, 0.3),
        )
    }

    fn fit(trajectories: &[Vec<Pose>], mean_steps: f64) -> DaDmp {
        DaDmp::from_trajectories(
            trajectories,
            mean_steps,
            &CellConfig::reference(),
            DmpSettings::default(),
        )
        .unwrap()
    }

    fn max_position_error(a: &[Pose], b: &[Pose]) -> f64 {
        a.iter()
            .zip(b)
            .map(|(a, b)| (a.translation.vector - b.translation.vector).norm())
            .fold(0.0, f64::max)
    }

    #[test]
    fn a_fitted_dmp_reproduces_its_demonstration() {
        let demo = demo();
        let dmp = fit(std::slice::from_ref(&demo), 50.0);
        assert_eq!(dmp.rollout_steps(), 50);
        let plan = dmp.rollout(&demo[0]);
        assert_eq!(plan.len(), demo.len());
        assert_eq!(plan[0], demo[0], "same start");
        let error = max_position_error(&plan, &demo);
        assert!(
            error < 0.25,
            "largest deviation {error} mm on an 80 mm movement"
        );
        let end = plan.last().unwrap();
        assert!(end.translation.vector.norm() < 0.05, "same goal: {end}");
        assert!(end.rotation.angle().to_degrees() < 1e-3);
        for (p, d) in plan.iter().zip(&demo) {
            let angle = (p.rotation.inverse() * d.rotation).angle().to_degrees();
            assert!(angle < 0.01, "orientation off by {angle} deg");
        }
    }

    #[test]
    fn a_new_start_still_reaches_the_goal_with_the_demonstrated_shape() {
        let demo = demo();
        let dmp = fit(std::slice::from_ref(&demo), 50.0);
        let start = pose_from_mm_deg(Vector3::new(45.0, -35.0, 100.0), Vector3::zeros());
        let plan = dmp.rollout(&start);
        assert_eq!(plan[0], start);
        let end = plan.last().unwrap();
        assert!(
            end.translation.vector.norm() < 0.05,
            "reaches the goal: {end}"
        );
        // Monotone where the demonstration is (a start further out on the same side): wherever
        // the demonstration moves along an axis, the replay moves the same way.
        for (w, d) in plan.windows(2).zip(demo.windows(2)) {
            let step = w[1].translation.vector - w[0].translation.vector;
            let demo_step = d[1].translation.vector - d[0].translation.vector;
            for k in 0..3 {
                if demo_step[k].abs() > 0.1 {
                    assert!(
                        step[k] * demo_step[k].signum() > 0.0,
                        "{step} against {demo_step}"
                    );
                }
            }
        }
        // The start's offset dies out early; from then on the demonstrated path, including the
        // pause at the entrance before the insertion.
        let error = max_position_error(&plan[15..], &demo[15..]);
        assert!(error < 0.3, "deviation {error} mm after the transient");
        assert!(
            plan[16..=25]
                .iter()
                .all(|p| (p.translation.vector.z - 60.0).abs() < 0.3)
        );
    }

    #[test]
    fn the_orientation_stays_a_unit_quaternion() {
        let demo = demo();
        let dmp = fit(std::slice::from_ref(&demo), 50.0);
        // Far outside the demonstrated range: 40 degrees about a skew axis.
        let axis = Vector3::new(1.0, -2.0, 0.5).normalize();
        let start = pose_from_mm_deg(Vector3::new(10.0, 5.0, 70.0), axis * 40.0);
        let plan = dmp.rollout(&start);
        let quaternions = continuous_quaternions(&plan);
        for (pose, q) in plan.iter().zip(&quaternions) {
            assert!((pose.rotation.quaternion().norm() - 1.0).abs() < 1e-12);
            assert!((q.norm() - 1.0).abs() < 1e-12);
        }
        assert!(quaternions.windows(2).all(|w| w[0].dot(&w[1]) > 0.0));
        let end = plan.last().unwrap().rotation.angle().to_degrees();
        assert!(end < 0.01, "ends {end} deg from the goal");
    }

    #[test]
    fn quaternion_signs_are_made_continuous() {
        let poses: Vec<Pose> = (0..5)
            .map(|i| pose_from_mm_deg(Vector3::zeros(), Vector3::new(0.0, 0.0, 10.0 * i as f64)))
            .collect();
        let mut flipped = poses.clone();
        for p in flipped.iter_mut().skip(1).step_by(2) {
            // The same rotation, the other sign.
            p.rotation = UnitQuaternion::new_unchecked(-p.rotation.into_inner());
        }
        let q = continuous_quaternions(&flipped);
        assert!(q.iter().all(|q| q.w > 0.0));
        let log = rotation_between(&q[3], &q[2]);
        assert!((log.z.to_degrees() - 10.0).abs() < 1e-9);
    }

    #[test]
    fn weights_averaged_over_time_scaled_copies_match_the_single_demonstration() {
        let start = Vector3::new(30.0, -20.0, 80.0);
        let rotation = Vector3::new(0.8, -0.5, 0.3);
        let single = fit(&[synthetic(50, start, rotation)], 50.0);
        let copies = fit(
            &[
                synthetic(40, start, rotation),
                synthetic(60, start, rotation),
            ],
            50.0,
        );
        assert_eq!(copies.mean_demo_steps(), 50.0);
        for (a, b) in single.weights().iter().zip(copies.weights()) {
            let norm = |v: &mut dyn Iterator<Item = f64>| v.map(|x| x * x).sum::<f64>().sqrt();
            let relative =
                norm(&mut a.iter().zip(b).map(|(a, b)| a - b)) / norm(&mut a.iter().copied());
            assert!(
                relative < 0.05,
                "weights differ by {relative} (relative RMS)"
            );
        }
        // And the replays agree.
        let error = max_position_error(
            &single.rollout(&start_pose()),
            &copies.rollout(&start_pose()),
        );
        assert!(error < 0.3, "replays differ by {error} mm");
    }

    fn start_pose() -> Pose {
        pose_from_mm_deg(
            Vector3::new(30.0, -20.0, 80.0),
            Vector3::new(0.8, -0.5, 0.3),
        )
    }

    fn step(state: [f64; 12]) -> DemoStep {
        DemoStep {
            episode: 0,
            step: 0,
            state,
            action: [0.0; 6],
            actor: Actor::Position,
            scale: 0.0,
        }
    }

    fn state(p: Vector3<f64>, o: Vector3<f64>) -> [f64; 12] {
        let mut s = [0.0; 12];
        s[6..9].copy_from_slice(p.as_slice());
        s[9..].copy_from_slice(o.as_slice());
        s
    }

    #[test]
    fn bad_demonstrations_are_refused_with_a_reason() {
        let cell = CellConfig::reference();
        let error = DaDmp::fit(&[], &cell).unwrap_err();
        assert_eq!(error, DmpError::NoDemonstrations);
        assert!(error.to_string().contains("no demonstrations"));

        let good = DemoEpisode {
            steps: vec![step(state(Vector3::new(0.0, 0.0, -70.0), Vector3::zeros())); 3],
            succeeded: true,
        };
        let short = DemoEpisode {
            steps: vec![step([0.0; 12])],
            succeeded: true,
        };
        let error = DaDmp::fit(&[good.clone(), short], &cell).unwrap_err();
        assert_eq!(error, DmpError::TooShort { index: 1, steps: 1 });
        assert!(
            error.to_string().contains("demonstration 1 has 1 step"),
            "{error}"
        );

        let mut bad = good.clone();
        bad.steps[2].state[10] = f64::NAN;
        let error = DaDmp::fit(&[good.clone(), bad], &cell).unwrap_err();
        assert_eq!(error, DmpError::NonFinite { index: 1, step: 2 });
        assert!(error.to_string().contains("non-finite"), "{error}");

        let settings = DmpSettings {
            basis: 1,
            ..DmpSettings::default()
        };
        assert!(matches!(
            DaDmp::fit_with(std::slice::from_ref(&good), &cell, settings),
            Err(DmpError::InvalidSettings(_))
        ));
        assert!(DaDmp::fit(&[good], &cell).is_ok());
    }

    #[test]
    fn demonstrations_become_poses_of_m_in_f_ending_docked() {
        let p = Vector3::new(1.0, -2.0, -70.0);
        let o = Vector3::new(0.0, 0.5, 0.2);
        let episode = DemoEpisode {
            steps: vec![step(state(p, o)), step(state(p * 0.5, o * 0.5))],
            succeeded: true,
        };
        let poses = demonstration_poses(&episode, 0).unwrap();
        assert_eq!(poses.len(), 3);
        // f_m · (F's origin in M) = origin: {M} sits where P says {F} is not.
        let back = poses[0] * nalgebra::Point3::from(p);
        assert!(back.coords.norm() < 1e-12);
        assert_eq!(poses[2], Pose::identity());
        let episode = DemoEpisode {
            succeeded: false,
            ..episode
        };
        assert_eq!(demonstration_poses(&episode, 0).unwrap().len(), 2);
    }

    fn observation(state: [f64; 12], step: u32, fresh: bool) -> Observation {
        Observation {
            state,
            raw_state: state,
            estimate: StateFilter::new(FusionTuning::default()),
            step,
            measurement_fresh: fresh,
            last_veto: None,
            cell: CellConfig::reference().shape(),
        }
    }

    #[test]
    fn the_controller_tracks_its_plan_within_the_step_limits_and_holds_when_blind() {
        let cell = CellConfig::reference();
        let mut dmp = fit(&[demo()], 50.0);
        dmp.reset(1);
        let start = state(
            Vector3::new(20.0, -30.0, -90.0),
            Vector3::new(0.3, 0.9, -0.2),
        );
        assert_eq!(dmp.act(&observation(start, 0, false)), Decision::hold());
        let first = dmp.act(&observation(start, 0, true)).action;
        assert!(first.is_finite());
        let (mm, deg) = first.max_components();
        assert!(mm <= cell.steps.position_mm && deg <= cell.steps.orientation_deg);
        // Stale measurements or broken numbers: hold, never NaN.
        assert_eq!(dmp.act(&observation(start, 1, false)), Decision::hold());
        let mut broken = start;
        broken[7] = f64::NAN;
        assert_eq!(dmp.act(&observation(broken, 1, true)), Decision::hold());
        // Past the plan's end: straight for the docked pose, clamped.
        let near = state(Vector3::new(0.01, -0.02, 3.0), Vector3::new(0.0, 0.0, 0.01));
        let late = dmp.act(&observation(near, 400, true)).action;
        assert!((late.translation_mm - Vector3::new(0.01, -0.02, 3.0)).norm() < 1e-9);
        assert!((late.rotation_deg.z - 0.01).abs() < 1e-9);
        // A reset forgets the plan: the next first observation is a new start.
        dmp.reset(2);
        let again = dmp.act(&observation(near, 0, true));
        let mut fresh = fit(&[demo()], 50.0);
        assert_eq!(again, fresh.act(&observation(near, 0, true)));
    }
}
