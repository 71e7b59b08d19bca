//! The twin's robot: a 6-SPS platform whose true geometry differs from the nominal model the
//! controller uses (kinematic calibration error), and whose legs land a little off their command
//! (actuator resolution and a random error per move).
//!
//! The controller never sees the truth: it keeps a setpoint (the platform pose it has commanded,
//! in its nominal model) and commands the leg lengths the nominal model gives for it. Like any
//! position-controlled axis, each leg lands within its error of the commanded length; errors do
//! not accumulate from move to move, but the calibration error bends every move the same way.
//!
//! Robot faults ([`RobotFaults`], `sim::fault`) make it land short of its command or report its
//! legs late.

use super::fault::RobotFaults;
use crate::config::cell::CellConfig;
use crate::geometry::{CellFrames, Move, Pose};
use crate::kinematics::{KinematicsError, StewartGeometry};
use crate::robot::{Robot, RobotError};
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

/// The robot the service's twin and `celld twin-server` keep from episode to episode (its
/// calibration error is drawn from this seed), as a real cell keeps its robot.
pub const CELL_ROBOT_SEED: u64 = 1;

#[derive(Debug, Clone)]
pub struct TwinRobot {
    nominal: StewartGeometry,
    truth: StewartGeometry,
    calibration_error_mm: f64,
    /// Multiplies each drawn joint displacement (1: the cell file's calibration error).
    calibration_scale: f64,
    /// The robot is kept from episode to episode: its joint displacements are drawn from this
    /// seed, not from the episode's random stream.
    kept: Option<u64>,
    resolution_mm: f64,
    leg_error_sd_mm: f64,
    /// Segment I's frame {M} in the platform's {P}: turns a move in {M} into a platform pose.
    p_m: Pose,
    /// True platform pose in {O}.
    true_platform: Pose,
    /// The commanded platform pose, in the nominal model.
    setpoint: Pose,
    /// What the encoders report.
    encoders_mm: [f64; 6],
    /// The legs' true lengths.
    legs_mm: [f64; 6],
    /// The nominal leg lengths of the last move's command.
    commanded_mm: Option<[f64; 6]>,
    faults: RobotFaults,
}

impl TwinRobot {
    pub fn new(cell: &CellConfig) -> Self {
        let nominal = StewartGeometry::from_config(&cell.robot);
        let home = nominal.home_pose();
        let imperfect = &cell.imperfections;
        TwinRobot {
            truth: nominal.clone(),
            calibration_error_mm: if imperfect.calibration_error {
                imperfect.calibration_error_mm
            } else {
                0.0
            },
            resolution_mm: if imperfect.execution_error {
                imperfect.leg_resolution_mm
            } else {
                0.0
            },
            leg_error_sd_mm: if imperfect.execution_error {
                imperfect.leg_error_sd_mm
            } else {
                0.0
            },
            calibration_scale: 1.0,
            kept: None,
            encoders_mm: nominal.leg_lengths_mm(&home),
            legs_mm: nominal.leg_lengths_mm(&home),
            commanded_mm: None,
            faults: RobotFaults::default(),
            p_m: CellFrames::from_config(cell).p_m,
            nominal,
            true_platform: home,
            setpoint: home,
        }
    }

    /// Scales the calibration error: each joint displacement drawn at [`TwinRobot::reset`] is
    /// multiplied by `scale` (0: a perfectly calibrated robot). The draws are the same whatever
    /// the scale, so episodes under different scales share their other random numbers.
    pub fn with_calibration_scale(mut self, scale: f64) -> Self {
        self.calibration_scale = scale;
        self
    }

    /// Keeps one robot from episode to episode, its calibration error drawn from `seed` (a real
    /// cell's robot), instead of a new one each episode.
    pub fn with_kept_calibration(mut self, seed: u64) -> Self {
        self.kept = Some(seed);
        self
    }

    /// The faults the next moves suffer (none by default; [`TwinRobot::reset`] keeps them).
    pub fn set_faults(&mut self, faults: RobotFaults) {
        self.faults = faults;
    }

    pub fn faults(&self) -> &RobotFaults {
        &self.faults
    }

    /// Starts an episode with the platform truly at `true_platform`; draws a new calibration error
    /// (each joint centre displaced uniformly within a ball of the configured radius, times the
    /// calibration scale). A kept robot draws its own again from its seed; the episode's draws
    /// are still taken, so its other random numbers are the same either way.
    pub fn reset(
        &mut self,
        true_platform: Pose,
        rng: &mut impl Rng,
    ) -> Result<(), KinematicsError> {
        let scale = self.calibration_scale;
        let mut draw = || random_in_ball(rng, self.calibration_error_mm) * scale;
        let mut base: [Vector3<f64>; 6] = std::array::from_fn(|_| draw());
        let mut platform: [Vector3<f64>; 6] = std::array::from_fn(|_| draw());
        if let Some(seed) = self.kept {
            let mut kept = ChaCha8Rng::seed_from_u64(seed);
            let mut draw = || random_in_ball(&mut kept, self.calibration_error_mm) * scale;
            base = std::array::from_fn(|_| draw());
            platform = std::array::from_fn(|_| draw());
        }
        self.truth = self.nominal.with_joint_offsets(&base, &platform);
        self.true_platform = true_platform;
        let legs = self.truth.leg_lengths_mm(&true_platform);
        self.legs_mm = legs;
        self.commanded_mm = None;
        self.encoders_mm = legs.map(|l| quantize(l, self.resolution_mm));
        self.setpoint = self
            .nominal
            .forward(&self.encoders_mm, &true_platform)?
            .pose;
        Ok(())
    }

    /// Moves to the setpoint `target` whose nominal leg lengths are `command_mm`. The legs land at
    /// the command rounded to the actuator resolution plus a random error; the true pose follows
    /// from the true geometry (forward kinematics warm-started from the last true pose). With
    /// `robot_short` each leg goes only that fraction of the way from its length to the rounded
    /// command, before the random error.
    pub fn execute(
        &mut self,
        target: &Pose,
        command_mm: &[f64; 6],
        rng: &mut impl Rng,
    ) -> Result<(), KinematicsError> {
        let mut actual = [0.0; 6];
        for ((leg, command), before) in actual.iter_mut().zip(command_mm).zip(&self.legs_mm) {
            let noise: f64 = rng.sample(StandardNormal);
            let mut goal = quantize(*command, self.resolution_mm);
            if let Some(fraction) = self.faults.short_fraction {
                goal = before + fraction * (goal - before);
            }
            *leg = goal + self.leg_error_sd_mm * noise;
        }
        self.commanded_mm = Some(*command_mm);
        self.true_platform = self.truth.forward(&actual, &self.true_platform)?.pose;
        self.legs_mm = actual;
        self.encoders_mm = actual.map(|l| quantize(l, self.resolution_mm));
        self.setpoint = *target;
        Ok(())
    }

    /// `robot_lag`: until [`TwinRobot::catch_up`], the encoders report the legs of the platform
    /// at `platform` (a pose along the last move) instead of where the move ended.
    pub fn report_lagging_at(&mut self, platform: &Pose) {
        let legs = self.truth.leg_lengths_mm(platform);
        self.encoders_mm = legs.map(|l| quantize(l, self.resolution_mm));
    }

    /// The encoders report the legs where they are (the end of a lagging move).
    pub fn catch_up(&mut self) {
        self.encoders_mm = self.legs_mm.map(|l| quantize(l, self.resolution_mm));
    }

    /// The nominal leg lengths the last executed move commanded (none since the reset).
    pub fn commanded_mm(&self) -> Option<&[f64; 6]> {
        self.commanded_mm.as_ref()
    }

    /// The legs' true lengths (the twin's ground truth).
    pub fn true_legs_mm(&self) -> &[f64; 6] {
        &self.legs_mm
    }

    pub fn true_platform(&self) -> &Pose {
        &self.true_platform
    }

    pub fn setpoint(&self) -> &Pose {
        &self.setpoint
    }

    /// What the encoders report.
    pub fn encoders_mm(&self) -> &[f64; 6] {
        &self.encoders_mm
    }
}

/// The twin's robot as a [`Robot`], for as long as it borrows the episode's random stream. The
/// twin's camera draws from the same stream, so an episode replays exactly under its seed.
pub struct TwinDrive<'a, G> {
    pub robot: &'a mut TwinRobot,
    pub rng: &'a mut G,
}

impl<G: Rng> Robot for TwinDrive<'_, G> {
    fn setpoint(&self) -> Pose {
        self.robot.setpoint
    }

    fn encoders_mm(&self) -> [f64; 6] {
        self.robot.encoders_mm
    }

    /// Commands the nominal leg lengths of the platform pose that moves {M} by `step`.
    fn execute(&mut self, step: &Move) -> Result<(), RobotError> {
        let p_m = self.robot.p_m;
        let target = self.robot.setpoint * p_m * step.as_pose() * p_m.inverse();
        let legs = (self.robot.nominal)
            .inverse_checked(&target)
            .map_err(|e| RobotError::Fault(e.into()))?;
        (self.robot)
            .execute(&target, &legs, self.rng)
            .map_err(|e| RobotError::Fault(e.into()))
    }

    /// The twin moves only inside `execute`, so between moves it already holds.
    fn hold(&mut self) {}
}

fn quantize(value: f64, resolution: f64) -> f64 {
    if resolution > 0.0 {
        (value / resolution).round() * resolution
    } else {
        value
    }
}

/// A point uniformly distributed in a ball of `radius` (mm).
fn random_in_ball(rng: &mut impl Rng, radius: f64) -> Vector3<f64> {
    if radius == 0.0 {
        return Vector3::zeros();
    }
    let direction = Vector3::<f64>::from_fn(|_, _| rng.sample(StandardNormal)).normalize();
    direction * radius * rng.random::<f64>().cbrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Exact;
    use rand::SeedableRng;

    #[test]
    fn perfect_robot_goes_where_commanded() {
        let mut cell = CellConfig::reference();
        cell.imperfections.calibration_error = false;
        cell.imperfections.execution_error = false;
        let mut robot = TwinRobot::new(&cell);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let home = robot.nominal.home_pose();
        robot.reset(home, &mut rng).unwrap();
        let target = home * Pose::translation(3.0, -2.0, 1.0);
        let legs = robot.nominal.leg_lengths_mm(&target);
        robot.execute(&target, &legs, &mut rng).unwrap();
        let error = robot.true_platform().translation.vector - target.translation.vector;
        assert!(error.norm() < 1e-9, "error {error}");
        assert_eq!(robot.setpoint(), &target);
    }

    #[test]
    fn a_drive_command_lands_where_the_supervisor_predicts() {
        let mut cell = CellConfig::reference();
        cell.imperfections.calibration_error = false;
        cell.imperfections.execution_error = false;
        let mut robot = TwinRobot::new(&cell);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2);
        let home = robot.nominal.home_pose();
        robot.reset(home, &mut rng).unwrap();
        let step = Move {
            translation_mm: Vector3::new(1.0, -0.5, -2.0),
            rotation_deg: Vector3::new(0.3, 0.0, -0.4),
        };
        // Far from the bore: the supervisor only checks limits and reachability.
        let far = Pose::translation(0.0, 0.0, 400.0).inverse();
        let allowed = crate::collision::supervisor::Supervisor::new(&cell)
            .check(&home, Some(&Exact(far)), &step)
            .unwrap();
        let mut drive = TwinDrive {
            robot: &mut robot,
            rng: &mut rng,
        };
        drive.execute(&step).unwrap();
        assert_eq!(drive.setpoint(), allowed.target_platform);
        assert_eq!(drive.encoders_mm(), allowed.legs_mm);
        let error =
            robot.true_platform().translation.vector - allowed.target_platform.translation.vector;
        assert!(error.norm() < 1e-9, "error {error}");
    }

    #[test]
    fn calibration_error_moves_the_truth_off_the_setpoint() {
        let cell = CellConfig::reference();
        let mut robot = TwinRobot::new(&cell);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let home = robot.nominal.home_pose();
        robot.reset(home, &mut rng).unwrap();
        let target = home * Pose::translation(0.0, 0.0, -40.0);
        let legs = robot.nominal.leg_lengths_mm(&target);
        robot.execute(&target, &legs, &mut rng).unwrap();
        let truth_error =
            (robot.true_platform().translation.vector - target.translation.vector).norm();
        // Joints off by up to 0.5 mm: the true pose is off by a fraction of a millimetre or so.
        assert!(
            truth_error > 1e-3 && truth_error < 3.0,
            "truth error {truth_error}"
        );
    }

    /// The error (per mm commanded, rows x, y, z of the motion; columns the axis commanded) of
    /// 5 mm moves along x, y and z from 40 mm below home, for robots drawn from seeds 0..n at
    /// `scale` times the cell file's calibration error, without leg noise: its rms per entry.
    fn move_error_rms(scale: f64, robots: u64) -> [[f64; 3]; 3] {
        let cell = CellConfig::reference();
        let mut squares = [[0.0; 3]; 3];
        for seed in 0..robots {
            let mut robot = TwinRobot::new(&cell).with_calibration_scale(scale);
            robot.leg_error_sd_mm = 0.0;
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
            let start = robot.nominal.home_pose() * Pose::translation(0.0, 0.0, -40.0);
            for axis in 0..3 {
                robot.reset(start, &mut rng).unwrap();
                let before = robot.true_platform().translation.vector;
                let mut commanded = nalgebra::Vector3::zeros();
                commanded[axis] = 5.0;
                let target = Pose::from(commanded) * *robot.setpoint();
                let legs = robot.nominal.leg_lengths_mm(&target);
                robot.execute(&target, &legs, &mut rng).unwrap();
                let error = robot.true_platform().translation.vector - before - commanded;
                for (row, row_squares) in squares.iter_mut().enumerate() {
                    row_squares[axis] += (error[row] / 5.0).powi(2);
                }
            }
        }
        squares.map(|row| row.map(|sum| (sum / robots as f64).sqrt()))
    }

    #[test]
    fn a_calibration_error_bends_sideways_moves_along_the_axis_as_much_as_sideways() {
        // What the state filter models (docs/estimation.md §3, decision 0045): the axial error
        // of a sideways move is as large as the sideways error of a move along the axis, while
        // the axial error of a move along the axis is an order of magnitude smaller. Run with
        // `--nocapture` for the figures.
        for scale in [1.0, 3.0] {
            let rms = move_error_rms(scale, 1000);
            eprintln!("calibration ×{scale}: rms per mm {rms:.5?}");
            let sideways_of_axial = (rms[0][2] + rms[1][2]) / 2.0;
            for axial_of_sideways in [rms[2][0], rms[2][1]] {
                let ratio = axial_of_sideways / sideways_of_axial;
                assert!((0.8..1.25).contains(&ratio), "×{scale}: {rms:?}");
            }
            assert!(rms[2][2] < 0.2 * sideways_of_axial, "×{scale}: {rms:?}");
        }
    }

    /// A robot without execution error, at home, for the fault tests.
    fn robot_at_home(cell: &CellConfig, scale: f64) -> (TwinRobot, rand_chacha::ChaCha8Rng) {
        let mut robot = TwinRobot::new(cell).with_calibration_scale(scale);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let home = robot.nominal.home_pose();
        robot.reset(home, &mut rng).unwrap();
        (robot, rng)
    }

    #[test]
    fn calibration_scale_zero_takes_the_calibration_error_away() {
        let mut cell = CellConfig::reference();
        cell.imperfections.execution_error = false;
        assert!(cell.imperfections.calibration_error);
        let mut off = [0.0; 3];
        for (k, scale) in [0.0, 1.0, 3.0].into_iter().enumerate() {
            let (mut robot, mut rng) = robot_at_home(&cell, scale);
            let target = robot.nominal.home_pose() * Pose::translation(5.0, -3.0, -40.0);
            let legs = robot.nominal.leg_lengths_mm(&target);
            robot.execute(&target, &legs, &mut rng).unwrap();
            assert_eq!(robot.encoders_mm(), &legs);
            off[k] = (robot.true_platform().translation.vector - target.translation.vector).norm();
        }
        assert!(off[0] < 1e-9, "{off:?}");
        assert!(off[1] > 1e-3 && off[2] > 2.0 * off[1], "{off:?}");
    }

    #[test]
    fn a_short_robot_lands_at_its_fraction_of_each_legs_change() {
        let mut cell = CellConfig::reference();
        cell.imperfections.calibration_error = false;
        cell.imperfections.execution_error = false;
        let (mut robot, mut rng) = robot_at_home(&cell, 1.0);
        robot.set_faults(RobotFaults {
            short_fraction: Some(0.7),
            lag_fraction: None,
        });
        let mut target = robot.nominal.home_pose();
        for _ in 0..3 {
            let before = *robot.true_legs_mm();
            target *= Pose::translation(2.0, 1.0, -3.0);
            let legs = robot.nominal.leg_lengths_mm(&target);
            robot.execute(&target, &legs, &mut rng).unwrap();
            for leg in 0..6 {
                let expected = before[leg] + 0.7 * (legs[leg] - before[leg]);
                assert!((robot.true_legs_mm()[leg] - expected).abs() < 1e-12);
            }
            assert_eq!(robot.encoders_mm(), robot.true_legs_mm());
            assert_eq!(robot.commanded_mm(), Some(&legs));
            assert_eq!(robot.setpoint(), &target);
        }
    }

    #[test]
    fn lagging_encoders_read_the_pose_given_until_the_robot_catches_up() {
        let mut cell = CellConfig::reference();
        cell.imperfections.calibration_error = false;
        cell.imperfections.execution_error = false;
        let (mut robot, mut rng) = robot_at_home(&cell, 1.0);
        let home = robot.nominal.home_pose();
        let target = home * Pose::translation(4.0, 0.0, 0.0);
        let legs = robot.nominal.leg_lengths_mm(&target);
        robot.execute(&target, &legs, &mut rng).unwrap();
        let midway = crate::geometry::pose::interpolate(&home, robot.true_platform(), 0.5);
        robot.report_lagging_at(&midway);
        assert_eq!(robot.encoders_mm(), &robot.nominal.leg_lengths_mm(&midway));
        assert!((0..6).any(|leg| (robot.encoders_mm()[leg] - legs[leg]).abs() > 0.1));
        robot.catch_up();
        assert_eq!(robot.encoders_mm(), &legs);
    }
}
