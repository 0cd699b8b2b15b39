//! The daemon's TOML configuration, read and validated once at start.
//!
//! A file enters through [`Config::load`] (or [`Config::parse`] for the
//! embedded default, `config/replay.toml`); every key is known
//! (`deny_unknown_fields`), every value is checked, and an error names the
//! file and the key: `config/replay.toml: [model].horizon_ms: expected one of
//! the model's horizons 500, 1000, 1500, 2000, got 700`. Checks that need the
//! loaded model (horizons, joints) run in [`Config::check_against_model`],
//! with the same error shape. Relative paths are relative to the config
//! file's directory (to the working directory for the embedded default).

pub use crate::ros::TopicsConfig;
pub mod sources;

pub use sources::{BusConfig, CameraConfig, DynamixelConfig, Pacing, PixelFormat};
use std::fmt;
use std::path::{Path, PathBuf};

use serde::Deserialize;
use thiserror::Error;

pub use crate::outputs::latch::LatchThresholds;
use crate::outputs::latch::{LatchError, Thresholds};

/// The default replay configuration, compiled into the binary.
pub const EMBEDDED_REPLAY_CONFIG: &str = include_str!("../../../config/replay.toml");
/// The name the embedded default reports in errors.
pub const EMBEDDED_REPLAY_NAME: &str = "config/replay.toml (embedded)";

#[derive(Debug, Error)]
pub enum ConfigError {
    #[error("{file}: cannot read the config: {source}")]
    Read {
        file: String,
        #[source]
        source: std::io::Error,
    },
    /// Not TOML, or a key/value of the wrong shape.
    #[error("{file}{at}: {key}: {message}", at = .line.map(|l| format!(":{l}")).unwrap_or_default())]
    Syntax {
        file: String,
        line: Option<usize>,
        key: String,
        message: String,
    },
    /// A well-formed value that is not acceptable.
    #[error("{file}: {key}: {message}")]
    Value {
        file: String,
        key: String,
        message: String,
    },
}

impl ConfigError {
    /// The key the error is about (`[model].horizon_ms`), for tests and logs.
    pub fn key(&self) -> Option<&str> {
        match self {
            ConfigError::Read { .. } => None,
            ConfigError::Syntax { key, .. } | ConfigError::Value { key, .. } => Some(key),
        }
    }
}

/// The whole file.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Config {
    pub robot: RobotConfig,
    pub model: ModelConfig,
    pub streams: StreamsConfig,
    /// The servo buses when `[streams].joints = "dynamixel"`; the section's
    /// keys belong to the servo source (`sources/dynamixel.rs`).
    #[serde(default)]
    pub dynamixel: Option<DynamixelConfig>,
    #[serde(default)]
    pub camera: Option<CameraConfig>,
    #[serde(default)]
    pub replay: Option<ReplayConfig>,
    #[serde(default)]
    pub ros: RosConfig,
    #[serde(default)]
    pub output: OutputConfig,
    /// Where the file came from (for error messages); not a key.
    #[serde(skip)]
    pub origin: String,
    /// Directory relative paths are resolved against; not a key.
    #[serde(skip)]
    pub base_dir: PathBuf,
}

/// `[robot]`
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct RobotConfig {
    /// Name of this robot: the `hardware_id` of every diagnostic status.
    pub name: String,
    /// Joint table: only `"poppy_humanoid"` is built in.
    #[serde(default = "default_joint_table")]
    pub joints: String,
    /// The tick rate, Hz: the grid every stream is resampled onto. The
    /// networks are trained at it (checked when they load) and `record`
    /// writes it as the recording's `rate_hz`, without loading a network.
    #[serde(default = "default_tick_rate_hz")]
    pub tick_rate_hz: f64,
}

fn default_joint_table() -> String {
    "poppy_humanoid".to_string()
}

fn default_tick_rate_hz() -> f64 {
    30.0
}

/// `[model]`: the network files and the safety latch on its output.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ModelConfig {
    /// Directory of the model files (relative to the config file).
    #[serde(default = "default_model_dir")]
    pub dir: PathBuf,
    /// The full network; required.
    pub emp: PathBuf,
    /// Fallbacks used when a stream is lost (camera lost: MP, plan lost: EP,
    /// both: P). Optional: without one, that loss leaves forecasts invalid.
    #[serde(default)]
    pub mp: Option<PathBuf>,
    #[serde(default)]
    pub ep: Option<PathBuf>,
    #[serde(default)]
    pub p: Option<PathBuf>,
    /// When the fallbacks are loaded: `"at_start"` (default: every network
    /// in memory, a switch costs one whole-window forward) or
    /// `"when_needed"` (each fallback is loaded and checked at start, then
    /// released, and loaded again the first time it is needed, then kept:
    /// less memory until the first switch, which also pays the load).
    #[serde(default)]
    pub fallbacks: FallbackLoading,
    /// How each network's classifier input projection is held in memory:
    /// `"int8"` (default: half the memory of f16 and less read per tick;
    /// forecasts within 0.0011 of the file's, model card) or `"as_file"`
    /// (f16 for the shipped files: the product training evaluated).
    #[serde(default = "default_projection")]
    pub projection: crate::model::ProjectionWeights,
    /// How the trajectory encoder's convolutions multiply: `"auto"`
    /// (default: `"int8"` on x86-64 with AVX2, `"f32"` elsewhere), `"int8"`
    /// (integer products, fewer instructions per tick on AVX2; forecasts
    /// within 0.004 of f32's on the bundled recordings, model card) or
    /// `"f32"` (the products training evaluated).
    #[serde(default = "default_convolutions")]
    pub convolutions: crate::model::Convolutions,
    /// Horizon watched by the safety latch (`/fall_guard/fall_imminent`), ms;
    /// must be one of the model's horizons.
    pub horizon_ms: u32,
    /// Latch turns on when the probability at `horizon_ms` reaches this.
    pub trigger: f32,
    /// Latch turns off only when it drops below this (< `trigger`).
    pub release: f32,
    /// ... and has stayed below it this long, ms (0: at the first tick
    /// below). A longer hold delays a release, never an assertion, so a
    /// network whose output swings does not make the signal chatter.
    #[serde(default)]
    pub release_hold_ms: u32,
    /// `[model.thresholds]`: a (trigger, release) pair of one network,
    /// chosen for it on validation, used while it makes the forecasts;
    /// a network without one uses `trigger` and `release`.
    #[serde(default)]
    pub thresholds: NetworkThresholds,
    /// What a forecast does when its window holds an input outside the
    /// range the network was trained on: `"hold"` (default: not valid,
    /// NaN, `fall_imminent` asserted) or `"forecast"` (published as
    /// usual, inputs held to their bounds, the excursion on
    /// `/diagnostics`). `docs/daemon.md`, "Inputs outside the training range".
    #[serde(default)]
    pub out_of_range: OutOfRange,
}

/// `[model].out_of_range`.
#[derive(Debug, Clone, Copy, Default, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum OutOfRange {
    /// The forecast is not valid while an input is out: the safety signal
    /// holds.
    #[default]
    Hold,
    /// The forecast is published from the inputs held to their bounds.
    Forecast,
}

impl OutOfRange {
    pub fn as_str(self) -> &'static str {
        match self {
            OutOfRange::Hold => "hold",
            OutOfRange::Forecast => "forecast",
        }
    }
}

/// `[model.thresholds]`: `emp = [trigger, release]`, and so on.
#[derive(Debug, Clone, Default, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct NetworkThresholds {
    #[serde(default)]
    pub emp: Option<[f32; 2]>,
    #[serde(default)]
    pub mp: Option<[f32; 2]>,
    #[serde(default)]
    pub ep: Option<[f32; 2]>,
    #[serde(default)]
    pub p: Option<[f32; 2]>,
}

impl NetworkThresholds {
    /// The pairs given, with their network and config key.
    pub fn pairs(&self) -> Vec<(crate::model::Ablation, &'static str, [f32; 2])> {
        use crate::model::Ablation;
        [
            (Ablation::EMP, "[model.thresholds].emp", self.emp),
            (Ablation::MP, "[model.thresholds].mp", self.mp),
            (Ablation::EP, "[model.thresholds].ep", self.ep),
            (Ablation::P, "[model.thresholds].p", self.p),
        ]
        .into_iter()
        .filter_map(|(a, key, pair)| pair.map(|p| (a, key, p)))
        .collect()
    }
}

/// `[model].fallbacks`: when the fallback networks are in memory.
#[derive(Debug, Clone, Copy, Default, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum FallbackLoading {
    /// All networks loaded at start and kept.
    #[default]
    AtStart,
    /// Checked at start, released, loaded at their first use, then kept.
    WhenNeeded,
}

fn default_projection() -> crate::model::ProjectionWeights {
    crate::model::ProjectionWeights::Int8
}

fn default_convolutions() -> crate::model::Convolutions {
    crate::model::Convolutions::Auto
}

fn default_model_dir() -> PathBuf {
    PathBuf::from("models")
}

/// Where the joint angles come from.
#[derive(Debug, Clone, Copy, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum JointsSource {
    /// The daemon owns the servo buses (`[dynamixel]`).
    Dynamixel,
    /// Another driver owns them; read `/joint_states`.
    Ros,
}

/// Where head-camera frames come from.
#[derive(Debug, Clone, Copy, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum CameraSource {
    /// Open the camera directly (`[camera]`, cargo feature `camera-v4l`).
    V4l2,
    /// `/head_camera/image_raw/compressed`.
    Ros,
    /// No camera: the daemon runs MP (or P).
    None,
}

/// Where the planned trajectory comes from.
#[derive(Debug, Clone, Copy, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum PlanSource {
    /// `/planned_trajectory`.
    Ros,
    /// No planner: the daemon runs EP (or P).
    None,
}

/// `[streams]`: the source of each stream for `run`/`record`, and when a
/// stream counts as stale (not valid, and lost for model choice). `replay`
/// ignores the sources (everything comes from the recording) but keeps the
/// staleness limits.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct StreamsConfig {
    pub joints: JointsSource,
    pub camera: CameraSource,
    pub plan: PlanSource,
    /// A stream whose latest sample is older than this at a tick is stale.
    ///
    /// For the joints, the age of the oldest joint's value, from the time
    /// its bus was asked for it (each bus's sync read, or the retry that
    /// got it). 150 ms in the shipped configs: a motor whose reply is lost
    /// in L read cycles in a row is, just before its next value reaches
    /// the tick, (L + 1) cycles plus the rest of that value's cycle (at
    /// most one more) plus the hand-over to the tick old; at the 23 ms a
    /// cycle measured on a noisy bus (retries included) that is at most
    /// 92 ms for two lost cycles and 115 ms for three, and 150 ms leaves
    /// 35 ms for a late thread (`docs/daemon.md`, "Validity").
    pub joints_stale_ms: u32,
    pub camera_stale_ms: u32,
    pub plan_stale_ms: u32,
    /// The longest gap of the joints that is bridged, in ticks: a run of at
    /// most this many ticks whose joints were all read but some older than
    /// `joints_stale_ms` (their last values held) makes those ticks' own
    /// forecasts not valid, but not the ones after: the forecast is valid
    /// again on the first fresh tick, while the window holds at most this
    /// many such ticks. A longer gap (or a joint not read) is waited out
    /// until it has left the window. 0 bridges nothing; default 3 (100 ms
    /// at 30 Hz: a bridged tick holds no value older than the bound plus
    /// 100 ms); at most 30, and below half the networks' window.
    #[serde(default = "default_joints_max_held_ticks")]
    pub joints_max_held_ticks: u32,
    /// The input boundary (`streams/input.rs`) rejects a sample stamped
    /// more than this after the tick clock (live: the system clock).
    #[serde(default = "default_max_future_ms")]
    pub max_future_ms: u32,
    /// ... or more than this before it.
    #[serde(default = "default_max_past_ms")]
    pub max_past_ms: u32,
    /// A planned position more than this beyond its joint's limits
    /// (`robot.rs`) is rejected (`out_of_limits`).
    #[serde(default = "default_plan_limit_margin_deg")]
    pub plan_limit_margin_deg: f64,
    /// A compressed camera image larger than this is rejected before it is
    /// decoded (`too_large`).
    #[serde(default = "default_max_image_bytes")]
    pub max_image_bytes: usize,
}

fn default_plan_limit_margin_deg() -> f64 {
    5.0
}

fn default_max_image_bytes() -> usize {
    2_000_000
}

fn default_joints_max_held_ticks() -> u32 {
    3
}

fn default_max_future_ms() -> u32 {
    250
}

fn default_max_past_ms() -> u32 {
    10_000
}

impl StreamsConfig {
    /// The boundary's limits for a model of the joints `joint_names` (their
    /// limits from `table`; a joint the table lacks is not range-checked)
    /// and S x S frames.
    pub fn input_limits(
        &self,
        joint_names: &[String],
        table: &crate::robot::JointTable,
        frame_size: u32,
    ) -> crate::streams::input::InputLimits {
        let range = table.ranges_rad(joint_names, self.plan_limit_margin_deg);
        crate::streams::input::InputLimits {
            max_future_ns: i64::from(self.max_future_ms) * 1_000_000,
            max_past_ns: i64::from(self.max_past_ms) * 1_000_000,
            n_joints: joint_names.len(),
            frame_size,
            plan_range_rad: Some(range.into()),
            max_image_bytes: self.max_image_bytes,
        }
    }
}

/// `[replay]`: defaults of `fall-guard replay` (the command line wins).
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ReplayConfig {
    /// The MCAP recording to replay (relative to the config file).
    pub recording: PathBuf,
    /// Recorded time runs this many times faster than real time.
    #[serde(default = "one_f64")]
    pub speed: f64,
    /// Run as fast as inference allows (ignores `speed`).
    #[serde(default)]
    pub max_speed: bool,
}

fn one_f64() -> f64 {
    1.0
}

/// `[ros]`: the ROS 2 node (inputs from ROS and every output).
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct RosConfig {
    /// Publish outputs on ROS 2 (inputs from ROS need it too).
    #[serde(default = "yes")]
    pub enabled: bool,
    #[serde(default = "default_node_name")]
    pub node_name: String,
    /// Prefix of every topic, e.g. `/poppy` (the launch file sets it).
    #[serde(default = "default_namespace")]
    pub namespace: String,
    /// DDS domain; absent: `ROS_DOMAIN_ID`, else 0.
    #[serde(default)]
    pub domain_id: Option<u16>,
    /// Only talk on 127.0.0.1; absent: `ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`.
    #[serde(default)]
    pub localhost_only: Option<bool>,
    /// The SROS2 enclave used when `ROS_SECURITY_ENABLE=true`
    /// (`ROS_SECURITY_ENCLAVE_OVERRIDE` wins over it).
    #[serde(default = "default_enclave")]
    pub enclave: String,
    #[serde(default)]
    pub topics: TopicsConfig,
}

impl Default for RosConfig {
    fn default() -> Self {
        RosConfig {
            enabled: true,
            node_name: default_node_name(),
            namespace: default_namespace(),
            domain_id: None,
            localhost_only: None,
            enclave: default_enclave(),
            topics: TopicsConfig::default(),
        }
    }
}

fn yes() -> bool {
    true
}

fn default_node_name() -> String {
    "fall_guard".to_string()
}
fn default_namespace() -> String {
    "/".to_string()
}
fn default_enclave() -> String {
    crate::ros::security::DEFAULT_ENCLAVE.to_string()
}

/// `[output]`
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct OutputConfig {
    /// Print one line per forecast on stdout.
    pub print_forecasts: bool,
    /// Period of `/diagnostics`.
    pub diagnostics_period_ms: u32,
}

impl Default for OutputConfig {
    fn default() -> Self {
        OutputConfig {
            print_forecasts: false,
            diagnostics_period_ms: 1000,
        }
    }
}

/// The horizons and joints of the loaded model, as far as the config cares.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelFacts {
    pub horizons_ms: Vec<u32>,
    pub joint_names: Vec<String>,
    pub rate_hz: f64,
    /// `N`, the ticks of the window.
    pub n_ticks: usize,
}

/// `a.b[1].c` -> `[a].b[1].c`; a top-level key stays bare.
fn format_key(path: &str) -> String {
    if path.is_empty() || path == "." {
        return "(top level)".to_string();
    }
    match path.split_once('.') {
        Some((table, rest)) => format!("[{table}].{rest}"),
        None => format!("[{path}]"),
    }
}

impl Config {
    /// Read and validate a config file.
    pub fn load(path: &Path) -> Result<Config, ConfigError> {
        let file = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
            file: file.clone(),
            source,
        })?;
        let base = path.parent().map(Path::to_path_buf).unwrap_or_default();
        Config::parse(&text, &file, &base)
    }

    /// The embedded `config/replay.toml`, relative to the working directory.
    pub fn embedded_replay() -> Result<Config, ConfigError> {
        Config::parse(EMBEDDED_REPLAY_CONFIG, EMBEDDED_REPLAY_NAME, Path::new(""))
    }

    /// Parse and validate `text`; `origin` names it in errors, `base_dir`
    /// resolves relative paths.
    pub fn parse(text: &str, origin: &str, base_dir: &Path) -> Result<Config, ConfigError> {
        let syntax = |line: Option<usize>, key: String, message: String| ConfigError::Syntax {
            file: origin.to_string(),
            line,
            key,
            message,
        };
        let line_of = |span: Option<std::ops::Range<usize>>| {
            span.map(|s| text[..s.start.min(text.len())].matches('\n').count() + 1)
        };
        let deserializer = toml::Deserializer::parse(text).map_err(|e| {
            syntax(
                line_of(e.span()),
                "(syntax)".into(),
                e.message().trim().to_string(),
            )
        })?;
        let mut config: Config = serde_path_to_error::deserialize(deserializer).map_err(|e| {
            let path = e.path().to_string();
            let inner = e.inner();
            let message = inner.message().trim().to_string();
            // An unknown key is reported at its table: name the key itself.
            let field = message
                .strip_prefix("unknown field `")
                .and_then(|m| m.split_once('`'))
                .map(|(field, _)| field);
            let key = match field {
                Some(field) if path == "." || path.is_empty() => field.to_string(),
                // The path may stop at the table or already name the key.
                Some(field) if !path.ends_with(field) => format!("{}.{field}", format_key(&path)),
                _ => format_key(&path),
            };
            syntax(line_of(inner.span()), key, message)
        })?;
        config.origin = origin.to_string();
        config.base_dir = base_dir.to_path_buf();
        config.validate()?;
        Ok(config)
    }

    fn value_error(&self, key: &str, message: impl fmt::Display) -> ConfigError {
        ConfigError::Value {
            file: self.origin.clone(),
            key: key.to_string(),
            message: message.to_string(),
        }
    }

    /// Checks that need nothing but the file.
    /// The safety latch's pairs, each made by [`Thresholds::new`] (the one
    /// check of a pair); a bad one is named by its key. Checked when the
    /// config is loaded, so that a loaded config's pairs are good.
    pub fn latch_thresholds(&self) -> Result<LatchThresholds, ConfigError> {
        let m = &self.model;
        let default = Thresholds::new(m.trigger, m.release).map_err(|e| match e {
            LatchError::OutOfRange { which, value } => self.value_error(
                &format!("[model].{which}"),
                format!("expected a probability in [0, 1], got {value}"),
            ),
            LatchError::NotBelow { trigger, release } => self.value_error(
                "[model].release",
                format!("expected below [model].trigger = {trigger} (hysteresis), got {release}"),
            ),
        })?;
        let per_network = m
            .thresholds
            .pairs()
            .into_iter()
            .map(|(network, key, [trigger, release])| {
                Thresholds::new(trigger, release)
                    .map(|t| (network, t))
                    .map_err(|e| {
                        self.value_error(
                            key,
                            format!("expected [trigger, release]: {e}, got [{trigger}, {release}]"),
                        )
                    })
            })
            .collect::<Result<_, _>>()?;
        Ok(LatchThresholds {
            default,
            per_network,
        })
    }

    fn validate(&self) -> Result<(), ConfigError> {
        if self.robot.name.trim().is_empty() {
            return Err(self.value_error("[robot].name", "must not be empty"));
        }
        if self.robot.joints != "poppy_humanoid" {
            return Err(self.value_error(
                "[robot].joints",
                format!(
                    "expected one of the built-in joint tables \"poppy_humanoid\", got {:?}",
                    self.robot.joints
                ),
            ));
        }
        if let Err(e) = crate::clock::TickGrid::new(self.robot.tick_rate_hz) {
            return Err(self.value_error("[robot].tick_rate_hz", e.to_string()));
        }
        self.latch_thresholds()?;
        let s = &self.streams;
        for (key, ms) in [
            ("[streams].joints_stale_ms", s.joints_stale_ms),
            ("[streams].camera_stale_ms", s.camera_stale_ms),
            ("[streams].plan_stale_ms", s.plan_stale_ms),
            ("[streams].max_future_ms", s.max_future_ms),
            ("[streams].max_past_ms", s.max_past_ms),
        ] {
            if ms == 0 || ms > 60_000 {
                return Err(self.value_error(key, format!("expected 1 to 60000 ms, got {ms}")));
            }
        }
        if s.joints_max_held_ticks > 30 {
            return Err(self.value_error(
                "[streams].joints_max_held_ticks",
                format!("expected 0 to 30 ticks, got {}", s.joints_max_held_ticks),
            ));
        }
        if !(0.0..=180.0).contains(&s.plan_limit_margin_deg) {
            return Err(self.value_error(
                "[streams].plan_limit_margin_deg",
                format!("expected 0 to 180 degrees, got {}", s.plan_limit_margin_deg),
            ));
        }
        if s.max_image_bytes < 1024 {
            return Err(self.value_error(
                "[streams].max_image_bytes",
                format!("expected at least 1024 bytes, got {}", s.max_image_bytes),
            ));
        }
        if s.joints == JointsSource::Dynamixel {
            match &self.dynamixel {
                None => {
                    return Err(self.value_error(
                        "[dynamixel]",
                        "missing: [streams].joints = \"dynamixel\" needs the servo buses",
                    ))
                }
                Some(d) if d.buses.is_empty() => {
                    return Err(self.value_error("[dynamixel].buses", "needs at least one bus"))
                }
                Some(d) if !(0.0..=1.0).contains(&d.warn_missed_share) => {
                    return Err(self.value_error(
                        "[dynamixel].warn_missed_share",
                        format!(
                            "expected a share of the read cycles in 0..1, got {}",
                            d.warn_missed_share
                        ),
                    ))
                }
                Some(_) => {}
            }
        }
        if s.camera == CameraSource::V4l2 {
            let Some(c) = &self.camera else {
                return Err(self.value_error(
                    "[camera]",
                    "missing: [streams].camera = \"v4l2\" needs the camera device",
                ));
            };
            for (key, v) in [
                ("[camera].width", c.width),
                ("[camera].height", c.height),
                ("[camera].fps", c.fps),
            ] {
                if v == 0 {
                    return Err(self.value_error(key, "must be positive"));
                }
            }
            if c.format == PixelFormat::Yuyv && c.width % 2 != 0 {
                return Err(self.value_error(
                    "[camera].width",
                    format!("YUYV needs an even width, got {}", c.width),
                ));
            }
        }
        if !self.ros.namespace.starts_with('/') {
            return Err(self.value_error(
                "[ros].namespace",
                format!(
                    "expected an absolute namespace like \"/poppy\", got {:?}",
                    self.ros.namespace
                ),
            ));
        }
        if let Err(why) = crate::ros::security::check_enclave_name(&self.ros.enclave) {
            return Err(self.value_error(
                "[ros].enclave",
                format!("{why}, got {:?}", self.ros.enclave),
            ));
        }
        if let Some(r) = &self.replay {
            if !(r.speed.is_finite() && r.speed > 0.0) {
                return Err(self.value_error(
                    "[replay].speed",
                    format!("expected a positive factor, got {}", r.speed),
                ));
            }
        }
        if self.output.diagnostics_period_ms < 10 {
            return Err(self.value_error(
                "[output].diagnostics_period_ms",
                format!(
                    "expected at least 10, got {}",
                    self.output.diagnostics_period_ms
                ),
            ));
        }
        Ok(())
    }

    /// Checks against the loaded model: the latch horizon must be one of
    /// the model's, the model's joints must be the robot's, and a bridged
    /// gap of the joints must be shorter than half its window.
    pub fn check_against_model(
        &self,
        facts: &ModelFacts,
        robot_joints: &[String],
    ) -> Result<(), ConfigError> {
        self.latch_horizon_index(&facts.horizons_ms)?;
        let held = self.streams.joints_max_held_ticks as usize;
        if 2 * held >= facts.n_ticks {
            return Err(self.value_error(
                "[streams].joints_max_held_ticks",
                format!(
                    "{held} ticks, not below half the model's window of {} ticks",
                    facts.n_ticks
                ),
            ));
        }
        if (facts.rate_hz - self.robot.tick_rate_hz).abs() > 1e-9 {
            return Err(self.value_error(
                "[robot].tick_rate_hz",
                format!(
                    "the model ticks at {} Hz, the config at {} Hz",
                    facts.rate_hz, self.robot.tick_rate_hz
                ),
            ));
        }
        if facts.joint_names != robot_joints {
            let first_difference = facts
                .joint_names
                .iter()
                .zip(robot_joints)
                .position(|(a, b)| a != b)
                .unwrap_or(facts.joint_names.len().min(robot_joints.len()));
            return Err(self.value_error(
                "[model].emp",
                format!(
                    "the model's {} joints do not match the robot {:?}'s {} joints (first difference at index {}: model {:?}, robot {:?})",
                    facts.joint_names.len(),
                    self.robot.joints,
                    robot_joints.len(),
                    first_difference,
                    facts.joint_names.get(first_difference),
                    robot_joints.get(first_difference),
                ),
            ));
        }
        Ok(())
    }

    /// Override `[ros].namespace` (from the command line named `origin`).
    pub fn set_namespace(&mut self, namespace: &str, origin: &str) -> Result<(), ConfigError> {
        if !namespace.starts_with('/') {
            return Err(ConfigError::Value {
                file: origin.to_string(),
                key: "[ros].namespace".to_string(),
                message: format!(
                    "expected an absolute namespace like \"/poppy\", got {namespace:?}"
                ),
            });
        }
        self.ros.namespace = namespace.to_string();
        Ok(())
    }

    /// The index of `[model].horizon_ms` among the model's horizons (the
    /// horizon the safety latch watches).
    pub fn latch_horizon_index(&self, horizons_ms: &[u32]) -> Result<usize, ConfigError> {
        horizons_ms
            .iter()
            .position(|&h| h == self.model.horizon_ms)
            .ok_or_else(|| {
                let list: Vec<String> = horizons_ms.iter().map(u32::to_string).collect();
                self.value_error(
                    "[model].horizon_ms",
                    format!(
                        "expected one of the model's horizons {}, got {}",
                        list.join(", "),
                        self.model.horizon_ms
                    ),
                )
            })
    }

    /// Checks of `run` and `record`, which read the live sources of
    /// `[streams]` (`replay` takes every stream from the recording): a
    /// stream read from ROS 2 needs `[ros].enabled`.
    pub fn check_live_sources(&self) -> Result<(), ConfigError> {
        let s = &self.streams;
        let from_ros = s.joints == JointsSource::Ros
            || s.camera == CameraSource::Ros
            || s.plan == PlanSource::Ros;
        if from_ros && !self.ros.enabled {
            return Err(self.value_error("[streams]", "reads from ROS 2 but [ros].enabled = false"));
        }
        Ok(())
    }

    /// The recording to replay: `arg` (`--recording`), else
    /// `[replay].recording`.
    pub fn replay_recording(&self, arg: Option<&Path>) -> Result<PathBuf, ConfigError> {
        match (arg, &self.replay) {
            (Some(p), _) => Ok(p.to_path_buf()),
            (None, Some(r)) => Ok(self.resolve(&r.recording)),
            (None, None) => Err(self.value_error(
                "[replay].recording",
                "no recording: pass --recording PATH or set [replay].recording",
            )),
        }
    }

    /// How fast a replay runs: `--max-speed` (`max_speed`), else `--speed`
    /// (`speed`), else `[replay]` (`max_speed`, then `speed`), else real
    /// time. `--speed` must be a positive factor (`[replay].speed` is
    /// checked at load).
    pub fn replay_pacing(
        &self,
        speed: Option<f64>,
        max_speed: bool,
    ) -> Result<Pacing, ConfigError> {
        let defaults = self.replay.as_ref();
        if max_speed || defaults.is_some_and(|r| r.max_speed) && speed.is_none() {
            return Ok(Pacing::MaxSpeed);
        }
        let speed = speed.or(defaults.map(|r| r.speed)).unwrap_or(1.0);
        if !(speed.is_finite() && speed > 0.0) {
            return Err(ConfigError::Value {
                file: "--speed".to_string(),
                key: "[replay].speed".to_string(),
                message: format!("expected a positive factor, got {speed}"),
            });
        }
        Ok(Pacing::Speed(speed))
    }

    /// A path from the config, resolved against the config's directory.
    pub fn resolve(&self, path: &Path) -> PathBuf {
        if path.is_absolute() {
            path.to_path_buf()
        } else {
            self.base_dir.join(path)
        }
    }

    /// A model file (`[model].dir` joined with the name), resolved.
    pub fn model_path(&self, file: &Path) -> PathBuf {
        self.resolve(&self.model.dir.join(file))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<Config, ConfigError> {
        Config::parse(text, "test.toml", Path::new("/cfg"))
    }

    #[test]
    fn embedded_replay_config_is_valid() {
        let config = Config::embedded_replay().expect("embedded config parses");
        assert!(config.replay.is_some());
        assert_eq!(config.origin, EMBEDDED_REPLAY_NAME);
    }

    /// `[model].convolutions`: auto when absent, `"f32"` and `"int8"`
    /// taken, anything else refused naming the choices.
    #[test]
    fn convolutions_default_to_auto_and_parse() {
        use crate::model::Convolutions;
        // The embedded config without its `convolutions` line.
        let text: String = EMBEDDED_REPLAY_CONFIG
            .lines()
            .filter(|l| !l.starts_with("convolutions"))
            .map(|l| format!("{l}\n"))
            .collect();
        assert_eq!(
            parse(&text).expect("parses").model.convolutions,
            Convolutions::Auto
        );
        let with = |v: &str| {
            text.replacen(
                "horizon_ms = ",
                &format!("convolutions = \"{v}\"\nhorizon_ms = "),
                1,
            )
        };
        assert_eq!(
            parse(&with("f32")).expect("f32").model.convolutions,
            Convolutions::F32
        );
        assert_eq!(
            parse(&with("int8")).expect("int8").model.convolutions,
            Convolutions::Int8
        );
        let e = parse(&with("f16")).expect_err("f16 refused").to_string();
        assert!(e.contains("f16"), "{e}");
    }

    #[test]
    fn plan_limits_are_the_joint_ranges_widened_by_the_margin() {
        let config = Config::embedded_replay().expect("embedded config parses");
        let table = crate::robot::JointTable::poppy_humanoid();
        let names = vec!["l_elbow_y".to_string(), "r_knee_y".into(), "unknown".into()];
        let limits = config.streams.input_limits(&names, &table, 64);
        let range = limits.plan_range_rad.expect("plan ranges");
        let deg = |(lo, hi): (f64, f64)| (lo.to_degrees(), hi.to_degrees());
        let margin = config.streams.plan_limit_margin_deg;
        // Direct: pypot's limits as they are.
        let (lo, hi) = deg(range[0]);
        assert!((lo - (-148.0 - margin)).abs() < 1e-9 && (hi - (1.0 + margin)).abs() < 1e-9);
        // Indirect: pypot's [-134, 3.5] is the joint range [-3.5, 134].
        let (lo, hi) = deg(range[1]);
        assert!((lo - (-3.5 - margin)).abs() < 1e-9 && (hi - (134.0 + margin)).abs() < 1e-9);
        // A joint the table lacks is not range-checked.
        assert_eq!(range[2], (f64::NEG_INFINITY, f64::INFINITY));
        assert_eq!(limits.max_image_bytes, config.streams.max_image_bytes);
    }

    #[test]
    fn shipped_robot_config_is_valid() {
        let path = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../.."))
            .join("config/poppy_humanoid.toml");
        let config = Config::load(&path).expect("robot config parses");
        assert_eq!(config.streams.joints, JointsSource::Dynamixel);
        assert_eq!(config.dynamixel.expect("buses").buses.len(), 2);
    }

    #[test]
    fn the_missed_read_share_of_a_failing_motor_is_checked() {
        let path = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../.."))
            .join("config/poppy_humanoid.toml");
        let text = std::fs::read_to_string(path).expect("robot config");
        let config = parse(&text).expect("robot config parses");
        assert_eq!(config.dynamixel.expect("buses").warn_missed_share, 0.2);
        for bad in ["1.5", "-0.1", "nan"] {
            let text = with_line(
                &text,
                "warn_missed_share",
                &format!("warn_missed_share = {bad}"),
            );
            let err = parse(&text).expect_err(bad);
            assert_eq!(
                err.key(),
                Some("[dynamixel].warn_missed_share"),
                "{bad}: {err}"
            );
        }
        // Left out: the default.
        let text = with_line(&text, "warn_missed_share", "");
        assert_eq!(
            parse(&text)
                .expect("default")
                .dynamixel
                .expect("buses")
                .warn_missed_share,
            0.2
        );
    }

    #[test]
    fn unknown_key_is_named_with_its_table_and_line() {
        let text = EMBEDDED_REPLAY_CONFIG.replacen("[model]\n", "[model]\nhorizn = 3\n", 1);
        let err = parse(&text).expect_err("unknown key");
        assert_eq!(err.key(), Some("[model].horizn"));
        let shown = err.to_string();
        assert!(shown.starts_with("test.toml:"), "{shown}");
        assert!(shown.contains("unknown field `horizn`"), "{shown}");
    }

    /// `text` with the line that sets `key` replaced by `line` (whatever
    /// value the shipped config has).
    fn with_line(text: &str, key: &str, line: &str) -> String {
        let mut found = false;
        let out: Vec<&str> = text
            .lines()
            .map(|l| {
                let k = l.split('=').next().unwrap_or("").trim();
                if k == key && !found {
                    found = true;
                    line
                } else {
                    l
                }
            })
            .collect();
        assert!(found, "no `{key} =` line in the config");
        out.join("\n")
    }

    #[test]
    fn per_network_thresholds_are_read_and_checked() {
        // The shipped config's own pairs, then others in their place.
        let shipped = parse(EMBEDDED_REPLAY_CONFIG).expect("valid");
        assert!(!shipped.model.thresholds.pairs().is_empty());
        let base = EMBEDDED_REPLAY_CONFIG
            .split("# -- per-network thresholds")
            .next()
            .expect("text");
        let text = format!("{base}\n[model.thresholds]\nemp = [0.7, 0.4]\np = [0.55, 0.2]\n");
        let config = parse(&text).expect("valid");
        let pairs = config.model.thresholds.pairs();
        assert_eq!(
            pairs,
            [
                (
                    crate::model::Ablation::EMP,
                    "[model.thresholds].emp",
                    [0.7, 0.4]
                ),
                (
                    crate::model::Ablation::P,
                    "[model.thresholds].p",
                    [0.55, 0.2]
                ),
            ]
        );
        // A network's own pair, else `[model].trigger` / `release`.
        let latch = config.latch_thresholds().expect("pairs");
        let p = latch.of(crate::model::Ablation::P);
        assert_eq!((p.trigger(), p.release()), (0.55, 0.2));
        assert_eq!(latch.of(crate::model::Ablation::MP), latch.default);
        let bad = format!("{base}\n[model.thresholds]\nmp = [0.3, 0.5]\n");
        let err = parse(&bad).expect_err("release above trigger");
        assert_eq!(err.key(), Some("[model.thresholds].mp"), "{err}");
        let unknown = format!("{base}\n[model.thresholds]\nemq = [0.7, 0.4]\n");
        let err = parse(&unknown).expect_err("unknown network");
        assert!(err.to_string().contains("emq"), "{err}");
    }

    #[test]
    fn wrong_type_names_the_key() {
        let text = with_line(EMBEDDED_REPLAY_CONFIG, "trigger", "trigger = \"high\"");
        let err = parse(&text).expect_err("wrong type");
        assert_eq!(err.key(), Some("[model].trigger"), "{err}");
    }

    #[test]
    fn bad_enum_value_names_the_key() {
        let text = EMBEDDED_REPLAY_CONFIG.replace("camera = \"none\"", "camera = \"usb\"");
        let err = parse(&text).expect_err("bad source");
        assert_eq!(err.key(), Some("[streams].camera"), "{err}");
        assert!(err.to_string().contains("v4l2"), "{err}");
    }

    #[test]
    fn hysteresis_must_be_ordered() {
        let text = with_line(EMBEDDED_REPLAY_CONFIG, "release", "release = 0.99");
        let err = parse(&text).expect_err("release above trigger");
        assert_eq!(err.key(), Some("[model].release"));
    }

    #[test]
    fn missing_section_is_named() {
        let text = EMBEDDED_REPLAY_CONFIG.replace("[streams]", "[streamz]");
        let err = parse(&text).expect_err("missing streams");
        assert!(err.to_string().contains("streams"), "{err}");
    }

    #[test]
    fn horizon_must_be_one_of_the_models() {
        let config = Config::embedded_replay().expect("parses");
        let mut config = config;
        config.model.horizon_ms = 700;
        let facts = ModelFacts {
            horizons_ms: vec![500, 1000, 1500, 2000],
            joint_names: vec!["a".into()],
            rate_hz: 30.0,
            n_ticks: 60,
        };
        let err = config
            .check_against_model(&facts, &["a".to_string()])
            .expect_err("700 is not a horizon");
        assert_eq!(
            err.to_string(),
            "config/replay.toml (embedded): [model].horizon_ms: expected one of the model's horizons 500, 1000, 1500, 2000, got 700"
        );
        config.model.horizon_ms = 1000;
        let err = config
            .check_against_model(&facts, &["b".to_string()])
            .expect_err("joint mismatch");
        assert!(
            err.to_string().contains("first difference at index 0"),
            "{err}"
        );
        let facts = ModelFacts {
            rate_hz: 50.0,
            ..facts
        };
        let err = config
            .check_against_model(&facts, &["a".to_string()])
            .expect_err("rate mismatch");
        assert_eq!(err.key(), Some("[robot].tick_rate_hz"), "{err}");
        // A bridged gap of the joints below half the window.
        let facts = ModelFacts {
            rate_hz: 30.0,
            n_ticks: 6,
            ..facts
        };
        config.streams.joints_max_held_ticks = 2;
        config
            .check_against_model(&facts, &["a".to_string()])
            .expect("2 of 6 ticks");
        config.streams.joints_max_held_ticks = 3;
        let err = config
            .check_against_model(&facts, &["a".to_string()])
            .expect_err("3 of 6 ticks");
        assert_eq!(err.key(), Some("[streams].joints_max_held_ticks"), "{err}");
    }

    #[test]
    fn live_sources_from_ros_need_ros_enabled() {
        let mut config = parse(EMBEDDED_REPLAY_CONFIG).expect("parses");
        config.check_live_sources().expect("ros enabled");
        config.ros.enabled = false;
        let err = config.check_live_sources().expect_err("ros off");
        assert_eq!(err.key(), Some("[streams]"), "{err}");
        assert!(err.to_string().contains("[ros].enabled = false"), "{err}");
        config.streams.joints = JointsSource::Dynamixel;
        config.streams.plan = PlanSource::None;
        config.check_live_sources().expect("nothing from ROS 2");
    }

    #[test]
    fn replay_recording_and_pacing_come_from_the_arguments_then_the_config() {
        use crate::config::Pacing;
        let mut config = parse(EMBEDDED_REPLAY_CONFIG).expect("parses");
        assert_eq!(
            config.replay_recording(Some(Path::new("x.mcap"))).ok(),
            Some(PathBuf::from("x.mcap"))
        );
        assert_eq!(
            config.replay_recording(None).ok(),
            Some(PathBuf::from("/cfg/tests/fixtures/episode_00007.mcap"))
        );
        assert_eq!(
            config.replay_pacing(None, false).ok(),
            Some(Pacing::Speed(1.0))
        );
        assert_eq!(
            config.replay_pacing(Some(4.0), false).ok(),
            Some(Pacing::Speed(4.0))
        );
        assert_eq!(
            config.replay_pacing(Some(4.0), true).ok(),
            Some(Pacing::MaxSpeed)
        );
        for bad in [0.0, -1.0, f64::NAN] {
            let err = config
                .replay_pacing(Some(bad), false)
                .expect_err("bad speed");
            assert!(err.to_string().starts_with("--speed: "), "{err}");
        }
        if let Some(r) = config.replay.as_mut() {
            r.max_speed = true;
        }
        assert_eq!(
            config.replay_pacing(None, false).ok(),
            Some(Pacing::MaxSpeed)
        );
        assert_eq!(
            config.replay_pacing(Some(2.0), false).ok(),
            Some(Pacing::Speed(2.0))
        );
        config.replay = None;
        let err = config.replay_recording(None).expect_err("no recording");
        assert_eq!(err.key(), Some("[replay].recording"), "{err}");
        assert_eq!(
            config.replay_pacing(None, false).ok(),
            Some(Pacing::Speed(1.0))
        );
    }

    #[test]
    fn relative_paths_resolve_against_the_config_dir() {
        let config = parse(EMBEDDED_REPLAY_CONFIG).expect("parses");
        assert_eq!(
            config.model_path(Path::new("emp.bpk")),
            Path::new("/cfg/models/emp.bpk")
        );
    }
}
