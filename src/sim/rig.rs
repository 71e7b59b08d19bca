//! The twin's robot and camera as hardware: a platform moved to absolute poses and a camera
//! that captures on request, with no supervisor and no judge. `celld twin-server` puts it
//! behind a GCS controller and an OpenIGTLink camera.
//!
//! An episode draws from its seed exactly as [`AssemblyEnv`](super::AssemblyEnv) does: the
//! initial pose, the robot's calibration error, then per move the legs' errors and per capture
//! the camera's noise, from one stream. A client that moves and captures in the twin's order
//! therefore sees the twin's episode.

use super::env::InitialConditions;
use super::robot::TwinRobot;
use crate::camera::{CameraFrame, SimCamera};
use crate::collision::clearance::PartGeometry;
use crate::config::cell::CellConfig;
use crate::geometry::{CellFrames, Pose};
use crate::kinematics::{KinematicsError, StewartGeometry};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// The twin's platform and camera, driven from outside.
pub struct TwinRig {
    cell: CellConfig,
    frames: CellFrames,
    parts: PartGeometry,
    nominal: StewartGeometry,
    robot: TwinRobot,
    camera: SimCamera,
    rng: ChaCha8Rng,
    captures: u64,
    frame: CameraFrame,
}

impl TwinRig {
    /// The twin of `cell`, its platform at home until [`TwinRig::begin_episode`].
    pub fn new(cell: &CellConfig) -> Self {
        let frames = CellFrames::from_config(cell);
        TwinRig {
            camera: SimCamera::new(cell, &frames, 1.0),
            parts: PartGeometry::from_config(cell),
            nominal: StewartGeometry::from_config(&cell.robot),
            robot: TwinRobot::new(cell),
            rng: ChaCha8Rng::seed_from_u64(0),
            captures: 0,
            frame: CameraFrame::default(),
            cell: cell.clone(),
            frames,
        }
    }

    /// Keeps one robot from episode to episode, its calibration error drawn from `seed`, as
    /// [`EnvOptions::kept_robots`](super::EnvOptions) does.
    pub fn with_kept_robot(mut self, seed: u64) -> Self {
        self.robot = self.robot.with_kept_calibration(seed);
        self
    }

    /// Draws an episode from `seed`: Segment I at the initial offset and orientation error
    /// from the mouth pose, the robot's calibration error; the captures count from 1 again.
    pub fn begin_episode(
        &mut self,
        seed: u64,
        initial: InitialConditions,
    ) -> Result<(), KinematicsError> {
        self.rng = ChaCha8Rng::seed_from_u64(seed);
        self.captures = 0;
        let f_m = self.sample_initial(initial);
        self.robot
            .reset(self.frames.platform_for(&f_m), &mut self.rng)
    }

    /// The commanded platform pose in {O} (after an episode starts: where the nominal model
    /// puts the legs' readings), as the controller reports it.
    pub fn setpoint(&self) -> Pose {
        *self.robot.setpoint()
    }

    /// The true pose of {M} in {F} (the twin's ground truth).
    pub fn true_f_m(&self) -> Pose {
        self.frames.segment_for(self.robot.true_platform())
    }

    /// Moves the platform to `target` in {O}: the legs get the nominal lengths of the pose
    /// and land with the twin's execution error.
    pub fn move_to(&mut self, target: &Pose) -> Result<(), KinematicsError> {
        let legs = self.nominal.inverse_checked(target)?;
        self.robot.execute(target, &legs, &mut self.rng)
    }

    /// Whether the nominal model reaches `target`.
    pub fn reaches(&self, target: &Pose) -> bool {
        self.nominal.inverse_checked(target).is_ok()
    }

    /// One capture of the scene as it is now; its sequence number counts the episode's
    /// captures from 1.
    pub fn capture(&mut self) -> &CameraFrame {
        let (w_m, w_f) = self.frames.world_poses(self.robot.true_platform());
        self.camera
            .capture_into(&w_m, &w_f, &mut self.rng, &mut self.frame);
        self.captures += 1;
        self.frame.sequence = self.captures;
        &self.frame
    }

    pub fn cell(&self) -> &CellConfig {
        &self.cell
    }

    /// The cell's frames and its fixtures' coded-point layouts.
    pub fn frames(&self) -> &CellFrames {
        &self.frames
    }

    /// The initial pose of {M} in {F}, drawn as `AssemblyEnv` draws it (the test below holds
    /// the two together).
    fn sample_initial(&mut self, initial: InitialConditions) -> Pose {
        super::env::sample_initial(
            &mut self.rng,
            &self.parts,
            self.cell.episode.initial_min_clearance_mm,
            initial,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::{AssemblyEnv, EnvOptions};

    #[test]
    fn an_episode_starts_and_is_seen_as_the_twin_environment_starts_it() {
        let cell = CellConfig::reference();
        let initial = InitialConditions::from_cell(&cell);
        for seed in [1, 7, 42] {
            let mut env = AssemblyEnv::new(&cell, EnvOptions::from_cell(&cell));
            env.begin_episode(seed, initial).unwrap();
            let mut rig = TwinRig::new(&cell);
            rig.begin_episode(seed, initial).unwrap();
            assert_eq!(rig.true_f_m(), env.true_f_m(), "seed {seed}");
            assert_eq!(
                rig.capture().clone(),
                env.capture_still(true).frame,
                "seed {seed}"
            );
        }
    }
}
