//! The cell file: every physical parameter of one assembly cell (docs/design.md §4), in one TOML file.
//!
//! Loading refuses unknown keys, malformed values and physically impossible cells, with a message
//! that names the key. Frames (see `docs/twin.md`): {F} sits at the centre of the bore entrance,
//! z pointing out of the bore; {M} sits on the shaft axis at the shoulder, z pointing from the tip
//! back to the shoulder, so that {M} = {F} when the parts are docked.

use super::fixture_layout::{FixtureLayout, LayoutError};
pub use crate::policy::shield::RulesConfig;
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Why a cell file was refused.
#[derive(Debug, thiserror::Error)]
pub enum CellConfigError {
    #[error("cannot read cell file {path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
    #[error("cell file {path} is not a valid cell: {message}")]
    Parse { path: String, message: String },
    #[error("cell file {path}: `{key}` = {value}: {reason}")]
    Invalid {
        path: String,
        key: &'static str,
        value: String,
        reason: String,
    },
    /// A calibration file refused; its problem is in the message (not a `source`, which an
    /// error chain would print a second time).
    #[error("cell file {path}: `camera.fixture_layout` {layout}: {problem}")]
    Layout {
        path: String,
        layout: String,
        problem: LayoutError,
    },
}

/// A whole cell.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CellConfig {
    /// A short name, e.g. `phi170`.
    pub name: String,
    pub shaft: ShaftConfig,
    pub bore: BoreConfig,
    pub success: SuccessConfig,
    pub robot: RobotConfig,
    pub camera: CameraConfig,
    pub imperfections: ImperfectionConfig,
    pub episode: EpisodeConfig,
    pub steps: StepLimitConfig,
    pub reward: RewardConfig,
    /// The collision supervisor's settings; a cell file without the section gets no margin.
    #[serde(default)]
    pub supervisor: SupervisorConfig,
    /// The rules between a learned policy's proposal and the supervisor
    /// (docs/policy-rules.md); a cell file without the section runs every rule. Left out of the
    /// serialised config (and so of its hash) while it is today's default.
    #[serde(default, skip_serializing_if = "RulesConfig::is_default")]
    pub rules: RulesConfig,
}

/// The few numbers of a cell that a policy trained across cells reads beside the pose
/// (`policy::inputs`): they differ from cell to cell and change what a good move is.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize)]
pub struct CellShape {
    /// How far the shaft goes in: from the tip at the entrance to seated (mm).
    pub bore_depth_mm: f64,
    /// Radial clearance between shaft and bore (mm).
    pub radial_clearance_mm: f64,
    /// Angular pitch of the connecting holes (deg).
    pub hole_pitch_deg: f64,
    /// How far off the bore wall the supervisor keeps the shaft (mm).
    pub wall_margin_mm: f64,
}

impl CellShape {
    /// The radial room (mm) a centred shaft has before the supervisor's wall margin: 0.03 mm
    /// on the reference cell, 0.01 mm on a Φ100 bore with 0.03 mm clearance.
    pub fn clearance_beside_margin_mm(&self) -> f64 {
        self.radial_clearance_mm - self.wall_margin_mm
    }

    /// The tilt (deg) at which a shaft seated in the bore would touch the supervisor's wall
    /// margin: the radial clearance beside the margin over the bore's depth. 0.029° on the
    /// reference cell, 0.0057° on a Φ100 bore 100 mm deep with 0.03 mm clearance.
    pub fn clearance_tilt_deg(&self) -> f64 {
        (self.clearance_beside_margin_mm() / self.bore_depth_mm)
            .atan()
            .to_degrees()
    }
}

/// Segment I: the shaft the robot carries.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ShaftConfig {
    pub diameter_mm: f64,
    /// Length of the shaft from its tip to the shoulder of Segment I's body.
    pub engaged_length_mm: f64,
    /// Outer diameter of Segment I's body behind the shoulder.
    pub body_diameter_mm: f64,
    pub holes: u32,
    pub hole_diameter_mm: f64,
    /// Distance of the radial holes' centre line from the shaft tip.
    pub hole_offset_mm: f64,
}

/// Segment II: the bore on the fixture.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BoreConfig {
    pub diameter_mm: f64,
    pub depth_mm: f64,
    pub outer_diameter_mm: f64,
    /// Axial relief beyond the nominal depth: the seating faces touch at depth + relief, so the
    /// success band (depth ± tolerance) can be reached from both sides without contact.
    pub axial_relief_mm: f64,
    pub holes: u32,
    pub hole_diameter_mm: f64,
    /// Distance of the radial holes' centre line from the bore entrance.
    pub hole_offset_mm: f64,
}

/// When an assembly counts as done.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SuccessConfig {
    /// Allowed error of the insertion depth about `bore.depth_mm`.
    pub depth_tolerance_mm: f64,
    /// Allowed arc offset between matching holes, measured on the bore's hole circle.
    pub hole_arc_tolerance_mm: f64,
}

/// The 6-SPS parallel robot (Stewart platform) and how Segment I sits on it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RobotConfig {
    pub base_radius_mm: f64,
    pub platform_radius_mm: f64,
    /// Angular positions of the three base joint pairs' centres.
    pub base_pair_centres_deg: [f64; 3],
    /// Angular positions of the three platform joint pairs' centres.
    pub platform_pair_centres_deg: [f64; 3],
    /// Each joint of a pair sits this far either side of the pair's centre.
    pub pair_half_angle_deg: f64,
    /// Platform height above the base at home; the docked pose is the home pose.
    pub home_height_mm: f64,
    pub leg_min_mm: f64,
    pub leg_max_mm: f64,
    /// Height of Segment I's shoulder (frame {M}) above the platform.
    pub segment_mount_mm: f64,
    /// Cartesian speed limits of one move.
    pub speed_mm_s: f64,
    pub speed_deg_s: f64,
    /// Poses whose normalised Jacobian determinant falls below this are refused as near-singular.
    pub singularity_threshold: f64,
}

impl RobotConfig {
    /// Base joint centres `a_i` in the base frame {O}, mm.
    ///
    /// Base joint `2k` / `2k+1` sits at `base_pair_centres_deg[k] ∓ pair_half_angle_deg`. For the
    /// reference cell the base joints lie at -15, 15, 105, 135, 225, 255 deg.
    pub fn base_joints_mm(&self) -> [Vector3<f64>; 6] {
        let half = self.pair_half_angle_deg;
        std::array::from_fn(|i| {
            let centre = self.base_pair_centres_deg[i / 2];
            let sign = if i % 2 == 0 { -1.0 } else { 1.0 };
            on_circle(self.base_radius_mm, centre + sign * half)
        })
    }

    /// Platform joint centres `b_i` in the platform frame {P}, mm.
    ///
    /// Leg `2k+1` goes to the near joint of platform pair `k` (`platform_pair_centres_deg[k] -
    /// half`), leg `2k` to the near joint of the previous platform pair (`[k-1 mod 3] + half`).
    /// For the reference cell the platform joints lie at -45, 45, 75, 165, 195, 285 deg.
    pub fn platform_joints_mm(&self) -> [Vector3<f64>; 6] {
        let half = self.pair_half_angle_deg;
        std::array::from_fn(|i| {
            let k = i / 2;
            let angle = if i % 2 == 0 {
                self.platform_pair_centres_deg[(k + 2) % 3] + half
            } else {
                self.platform_pair_centres_deg[k] - half
            };
            on_circle(self.platform_radius_mm, angle)
        })
    }

    /// Leg lengths at the home pose ({P} `home_height_mm` above {O}, unrotated), mm: the
    /// inverse kinematics `L_i = |r + b_i - a_i|` with no rotation, which is all the cell file's
    /// check of the stroke needs (`kinematics::StewartGeometry` has the general case).
    pub fn home_leg_lengths_mm(&self) -> [f64; 6] {
        let r = Vector3::new(0.0, 0.0, self.home_height_mm);
        let (a, b) = (self.base_joints_mm(), self.platform_joints_mm());
        std::array::from_fn(|i| (r + b[i] - a[i]).norm())
    }
}

/// A point on a circle of `radius_mm` in the z = 0 plane at `angle_deg` from the x axis.
fn on_circle(radius_mm: f64, angle_deg: f64) -> Vector3<f64> {
    let (s, c) = angle_deg.to_radians().sin_cos();
    Vector3::new(radius_mm * c, radius_mm * s, 0.0)
}

/// The binocular camera and the coded points on the two fixtures.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraConfig {
    /// Camera position in the robot base frame {O}.
    pub position_mm: [f64; 3],
    /// The point the camera looks at, in {O}.
    pub target_mm: [f64; 3],
    pub min_range_m: f64,
    pub max_range_m: f64,
    /// Point noise σ per axis = `noise_base_mm` + `noise_per_m_mm` × range in metres.
    pub noise_base_mm: f64,
    pub noise_per_m_mm: f64,
    /// The generated ring of coded points on each fixture (when no `fixture_layout` is given):
    /// this many points, ids 0 to n − 1, evenly on the ring from 0.1 rad.
    pub points_per_fixture: u32,
    /// Radius of the ring of coded points on each fixture.
    pub fixture_radius_mm: f64,
    /// Coded points alternate ± this far along the fixture axis, so the ring is not flat.
    pub fixture_height_spread_mm: f64,
    /// A calibration file of both fixtures' coded points (CSV, `config::fixture_layout`),
    /// relative to the cell file; it replaces the generated ring.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fixture_layout: Option<String>,
    /// The coded points read from `fixture_layout` when the cell file was parsed.
    #[serde(default, skip_deserializing, skip_serializing_if = "Option::is_none")]
    pub calibrated_layout: Option<FixtureLayout>,
    /// Fixture {C1} sits this far behind Segment I's shoulder (+z of {M}); fixture {C2} this far
    /// inside Segment II from its entrance (−z of {F}).
    pub fixture_offset_mm: f64,
    pub rate_hz: f64,
    pub dropout_probability: f64,
    pub outlier_probability: f64,
    /// Size of a gross outlier error.
    pub outlier_magnitude_mm: f64,
    /// A point whose fit residual exceeds this many σ (and 0.05 mm) is rejected as an outlier.
    pub outlier_rejection_sigmas: f64,
    /// Time from a capture to the state reaching the controller.
    pub latency_s: f64,
}

/// Switches for each imperfection of the twin, and the robot's error sizes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImperfectionConfig {
    pub camera_noise: bool,
    pub dropped_points: bool,
    pub outliers: bool,
    pub latency: bool,
    pub calibration_error: bool,
    pub execution_error: bool,
    /// True joint centres lie within this distance of their nominal positions.
    pub calibration_error_mm: f64,
    /// Leg-length encoder and actuator resolution.
    pub leg_resolution_mm: f64,
    /// Random leg-length error of each move (σ).
    pub leg_error_sd_mm: f64,
}

/// Episode protocol: initial conditions and limits.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EpisodeConfig {
    pub max_steps: u32,
    pub max_consecutive_vetoes: u32,
    /// Magnitude of the initial offset from the mouth pose (tip centred on the entrance).
    pub initial_offset_mm: f64,
    /// Magnitude of the initial orientation error about a random axis.
    pub initial_orientation_deg: f64,
    /// The shaft starts at least this far clear of Segment II.
    pub initial_min_clearance_mm: f64,
    /// The shoulder may not move further than this from the docked pose.
    pub workspace_radius_mm: f64,
    /// Nor tilt more than this.
    pub workspace_tilt_deg: f64,
}

/// Largest move of one step (scaled by the step-size weight ω3).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StepLimitConfig {
    pub position_mm: f64,
    pub orientation_deg: f64,
}

/// The collision supervisor (docs/design.md §8).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SupervisorConfig {
    /// A move is allowed only if the probability of contact along it, under the estimate's
    /// distribution, is below this bound (docs/estimation.md).
    #[serde(default = "default_contact_risk_per_move")]
    pub contact_risk_per_move: f64,
    /// Steps the cell may hold in a row for more frames, because no move is sure enough, before
    /// the job ends as `uncertain`.
    #[serde(default = "default_max_uncertain_holds")]
    pub max_uncertain_holds: u32,
    /// An extra margin on the mean: a move may not bring the shaft nearer the bore wall than this
    /// (mm) by the estimate, nor close a gap already under it. 0: the probability bound alone.
    #[serde(default)]
    pub wall_margin_mm: f64,
}

fn default_contact_risk_per_move() -> f64 {
    1e-4
}

fn default_max_uncertain_holds() -> u32 {
    150
}

impl Default for SupervisorConfig {
    fn default() -> Self {
        SupervisorConfig {
            contact_risk_per_move: default_contact_risk_per_move(),
            max_uncertain_holds: default_max_uncertain_holds(),
            wall_margin_mm: 0.0,
        }
    }
}

/// The paper's reward (§3.3), Table 1 weights.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RewardConfig {
    pub success: f64,
    pub failure: f64,
    pub step_penalty: f64,
    pub error_penalty: f64,
    /// r_err applies once countP or countO exceeds this.
    pub error_count_limit: u32,
    pub lambda_global: f64,
    pub lambda_position: f64,
    pub lambda_orientation: f64,
    pub lambda_error: f64,
    pub gamma: f64,
}

impl CellConfig {
    /// Reads, parses and validates a cell file.
    pub fn load(path: &Path) -> Result<Self, CellConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| CellConfigError::Io {
            path: path.display().to_string(),
            source,
        })?;
        Self::parse(&text, &path.display().to_string())
    }

    /// Parses and validates cell TOML; `origin` names the source in messages, and a relative
    /// `camera.fixture_layout` is read from its folder.
    pub fn parse(text: &str, origin: &str) -> Result<Self, CellConfigError> {
        let mut config: CellConfig = toml::from_str(text).map_err(|e| CellConfigError::Parse {
            path: origin.to_string(),
            message: e.to_string(),
        })?;
        config.validate(origin)?;
        if let Some(file) = &config.camera.fixture_layout {
            let at = Path::new(origin)
                .parent()
                .unwrap_or(Path::new(""))
                .join(file);
            let text = std::fs::read_to_string(&at).map_err(|source| CellConfigError::Io {
                path: at.display().to_string(),
                source,
            })?;
            let layout =
                FixtureLayout::parse_csv(&text).map_err(|problem| CellConfigError::Layout {
                    path: origin.to_string(),
                    layout: at.display().to_string(),
                    problem,
                })?;
            config.camera.calibrated_layout = Some(layout);
        }
        Ok(config)
    }

    /// The reference cell shipped with the crate (cells/phi170.toml).
    pub fn reference() -> Self {
        Self::parse(include_str!("../../cells/phi170.toml"), "cells/phi170.toml")
            .expect("the bundled reference cell is valid")
    }

    /// Radial clearance between shaft and bore, mm.
    pub fn radial_clearance_mm(&self) -> f64 {
        (self.bore.diameter_mm - self.shaft.diameter_mm) / 2.0
    }

    /// Angular pitch of the connecting holes, deg.
    pub fn hole_pitch_deg(&self) -> f64 {
        360.0 / f64::from(self.bore.holes)
    }

    /// What a policy trained across cells needs to know of this one ([`CellShape`]).
    pub fn shape(&self) -> CellShape {
        CellShape {
            bore_depth_mm: self.shaft.engaged_length_mm,
            radial_clearance_mm: self.radial_clearance_mm(),
            hole_pitch_deg: self.hole_pitch_deg(),
            wall_margin_mm: self.supervisor.wall_margin_mm,
        }
    }

    /// Checks a cell made in code (a randomised training cell) as a file is checked on loading.
    pub fn check(&self, origin: &str) -> Result<(), CellConfigError> {
        self.validate(origin)
    }

    /// A stable hash of the whole configuration (FNV-1a over its canonical JSON), so stored
    /// results can say which cell they were measured on.
    pub fn config_hash(&self) -> String {
        let json = serde_json::to_string(self).expect("cell config serialises");
        let mut hash: u64 = 0xcbf2_9ce4_8422_2325;
        for byte in json.bytes() {
            hash ^= u64::from(byte);
            hash = hash.wrapping_mul(0x0000_0100_0000_01b3);
        }
        format!("{hash:016x}")
    }

    fn validate(&self, origin: &str) -> Result<(), CellConfigError> {
        let invalid = |key: &'static str, value: f64, reason: &str| CellConfigError::Invalid {
            path: origin.to_string(),
            key,
            value: value.to_string(),
            reason: reason.to_string(),
        };
        if let Some((key, value, range)) = self.rules.invalid() {
            return Err(invalid(key, value, &format!("must be {range}")));
        }
        let positive: [(&'static str, f64); 22] = [
            ("shaft.diameter_mm", self.shaft.diameter_mm),
            ("shaft.engaged_length_mm", self.shaft.engaged_length_mm),
            ("shaft.body_diameter_mm", self.shaft.body_diameter_mm),
            ("shaft.hole_diameter_mm", self.shaft.hole_diameter_mm),
            ("bore.diameter_mm", self.bore.diameter_mm),
            ("bore.depth_mm", self.bore.depth_mm),
            ("bore.outer_diameter_mm", self.bore.outer_diameter_mm),
            ("bore.hole_diameter_mm", self.bore.hole_diameter_mm),
            (
                "success.depth_tolerance_mm",
                self.success.depth_tolerance_mm,
            ),
            (
                "success.hole_arc_tolerance_mm",
                self.success.hole_arc_tolerance_mm,
            ),
            ("robot.base_radius_mm", self.robot.base_radius_mm),
            ("robot.platform_radius_mm", self.robot.platform_radius_mm),
            ("robot.home_height_mm", self.robot.home_height_mm),
            ("robot.leg_min_mm", self.robot.leg_min_mm),
            ("robot.speed_mm_s", self.robot.speed_mm_s),
            ("robot.speed_deg_s", self.robot.speed_deg_s),
            ("camera.fixture_radius_mm", self.camera.fixture_radius_mm),
            ("camera.rate_hz", self.camera.rate_hz),
            (
                "camera.outlier_rejection_sigmas",
                self.camera.outlier_rejection_sigmas,
            ),
            (
                "episode.workspace_radius_mm",
                self.episode.workspace_radius_mm,
            ),
            ("steps.position_mm", self.steps.position_mm),
            ("steps.orientation_deg", self.steps.orientation_deg),
        ];
        for (key, value) in positive {
            if !(value.is_finite() && value > 0.0) {
                return Err(invalid(
                    key,
                    value,
                    "must be a finite number greater than 0",
                ));
            }
        }
        let non_negative: [(&'static str, f64); 11] = [
            ("bore.axial_relief_mm", self.bore.axial_relief_mm),
            ("camera.noise_base_mm", self.camera.noise_base_mm),
            ("camera.noise_per_m_mm", self.camera.noise_per_m_mm),
            (
                "camera.outlier_magnitude_mm",
                self.camera.outlier_magnitude_mm,
            ),
            ("camera.latency_s", self.camera.latency_s),
            (
                "camera.fixture_height_spread_mm",
                self.camera.fixture_height_spread_mm,
            ),
            (
                "imperfections.calibration_error_mm",
                self.imperfections.calibration_error_mm,
            ),
            (
                "imperfections.leg_resolution_mm",
                self.imperfections.leg_resolution_mm,
            ),
            (
                "imperfections.leg_error_sd_mm",
                self.imperfections.leg_error_sd_mm,
            ),
            ("episode.initial_offset_mm", self.episode.initial_offset_mm),
            (
                "episode.initial_orientation_deg",
                self.episode.initial_orientation_deg,
            ),
        ];
        for (key, value) in non_negative {
            if !(value.is_finite() && value >= 0.0) {
                return Err(invalid(key, value, "must be a finite number, 0 or more"));
            }
        }
        for (key, value) in [
            (
                "camera.dropout_probability",
                self.camera.dropout_probability,
            ),
            (
                "camera.outlier_probability",
                self.camera.outlier_probability,
            ),
        ] {
            if !(0.0..1.0).contains(&value) {
                return Err(invalid(key, value, "must be a probability in [0, 1)"));
            }
        }
        if self.bore.diameter_mm <= self.shaft.diameter_mm {
            return Err(invalid(
                "bore.diameter_mm",
                self.bore.diameter_mm,
                &format!(
                    "clearance ≤ 0: the bore must be wider than the shaft ({} mm)",
                    self.shaft.diameter_mm
                ),
            ));
        }
        let risk = self.supervisor.contact_risk_per_move;
        if !(risk > 0.0 && risk < 0.5) {
            return Err(invalid(
                "supervisor.contact_risk_per_move",
                risk,
                "must be more than 0 and less than 0.5",
            ));
        }
        if self.supervisor.max_uncertain_holds == 0 {
            return Err(invalid(
                "supervisor.max_uncertain_holds",
                0.0,
                "must be at least 1",
            ));
        }
        let margin = self.supervisor.wall_margin_mm;
        if !(margin.is_finite() && margin >= 0.0 && margin < self.radial_clearance_mm()) {
            return Err(invalid(
                "supervisor.wall_margin_mm",
                margin,
                &format!(
                    "must be 0 or more and less than the radial clearance ({:.4} mm)",
                    self.radial_clearance_mm()
                ),
            ));
        }
        if self.bore.outer_diameter_mm <= self.bore.diameter_mm {
            return Err(invalid(
                "bore.outer_diameter_mm",
                self.bore.outer_diameter_mm,
                "must exceed bore.diameter_mm",
            ));
        }
        if self.shaft.body_diameter_mm <= self.shaft.diameter_mm {
            return Err(invalid(
                "shaft.body_diameter_mm",
                self.shaft.body_diameter_mm,
                "must exceed shaft.diameter_mm (the shoulder)",
            ));
        }
        if self.shaft.engaged_length_mm < self.bore.depth_mm {
            return Err(invalid(
                "shaft.engaged_length_mm",
                self.shaft.engaged_length_mm,
                "must be at least bore.depth_mm, or the shaft cannot reach the insertion depth",
            ));
        }
        if self.bore.holes == 0 || self.bore.holes != self.shaft.holes {
            return Err(invalid(
                "bore.holes",
                f64::from(self.bore.holes),
                &format!(
                    "must be at least 1 and equal shaft.holes ({})",
                    self.shaft.holes
                ),
            ));
        }
        if self.bore.hole_offset_mm >= self.bore.depth_mm {
            return Err(invalid(
                "bore.hole_offset_mm",
                self.bore.hole_offset_mm,
                "the holes must lie inside the bore depth",
            ));
        }
        if self.shaft.hole_offset_mm >= self.shaft.engaged_length_mm {
            return Err(invalid(
                "shaft.hole_offset_mm",
                self.shaft.hole_offset_mm,
                "the holes must lie on the shaft",
            ));
        }
        if self.success.depth_tolerance_mm > self.bore.axial_relief_mm {
            return Err(invalid(
                "success.depth_tolerance_mm",
                self.success.depth_tolerance_mm,
                "exceeds bore.axial_relief_mm: the far side of the success band would be in contact",
            ));
        }
        if self.robot.leg_max_mm <= self.robot.leg_min_mm {
            return Err(invalid(
                "robot.leg_max_mm",
                self.robot.leg_max_mm,
                "must exceed robot.leg_min_mm",
            ));
        }
        let home_legs = self.robot.home_leg_lengths_mm();
        for (leg, length) in home_legs.iter().enumerate() {
            if *length < self.robot.leg_min_mm || *length > self.robot.leg_max_mm {
                let key = if *length < self.robot.leg_min_mm {
                    "robot.leg_min_mm"
                } else {
                    "robot.leg_max_mm"
                };
                return Err(invalid(
                    key,
                    if *length < self.robot.leg_min_mm {
                        self.robot.leg_min_mm
                    } else {
                        self.robot.leg_max_mm
                    },
                    &format!(
                        "the stroke cannot reach the home pose: leg {} needs {length:.3} mm there",
                        leg + 1
                    ),
                ));
            }
        }
        if self.camera.points_per_fixture < 3 {
            return Err(invalid(
                "camera.points_per_fixture",
                f64::from(self.camera.points_per_fixture),
                "a frame needs at least three coded points",
            ));
        }
        if self.camera.min_range_m <= 0.0 || self.camera.max_range_m <= self.camera.min_range_m {
            return Err(invalid(
                "camera.max_range_m",
                self.camera.max_range_m,
                "the range must satisfy 0 < min_range_m < max_range_m",
            ));
        }
        let range_m = self
            .camera
            .position_mm
            .iter()
            .zip(&self.camera.target_mm)
            .map(|(a, b)| (a - b).powi(2))
            .sum::<f64>()
            .sqrt()
            / 1000.0;
        if !(self.camera.min_range_m..=self.camera.max_range_m).contains(&range_m) {
            return Err(invalid(
                "camera.position_mm",
                range_m,
                &format!(
                    "the camera is {range_m:.3} m from its target, outside its range [{}, {}] m",
                    self.camera.min_range_m, self.camera.max_range_m
                ),
            ));
        }
        if self.episode.max_steps == 0 {
            return Err(invalid("episode.max_steps", 0.0, "must be at least 1"));
        }
        if self.episode.max_consecutive_vetoes == 0 {
            return Err(invalid(
                "episode.max_consecutive_vetoes",
                0.0,
                "must be at least 1",
            ));
        }
        if !(self.reward.gamma > 0.0 && self.reward.gamma <= 1.0) {
            return Err(invalid(
                "reward.gamma",
                self.reward.gamma,
                "must lie in (0, 1]",
            ));
        }
        if !(self.episode.workspace_tilt_deg > 0.0 && self.episode.workspace_tilt_deg < 45.0) {
            return Err(invalid(
                "episode.workspace_tilt_deg",
                self.episode.workspace_tilt_deg,
                "must lie in (0, 45) deg",
            ));
        }
        Ok(())
    }
}
