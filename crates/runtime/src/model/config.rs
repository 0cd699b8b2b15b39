//! Network configuration: the shapes and sizes of one EMP model.
//!
//! A [`ModelConfig`] is built by name (`lite`, `paper`) from the task's window
//! spec and saved in the model file, so that a file always says how it was built.

use serde::{Deserialize, Serialize};
use std::fmt;
use std::str::FromStr;

/// Which encoders are switched on (the paper's names). All four are the same
/// code; the daemon falls back to a smaller one when a sensor stream is lost.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Ablation {
    /// Proprioception only.
    P,
    /// Motion plan + proprioception.
    MP,
    /// Egocentric vision + proprioception.
    EP,
    /// All three.
    EMP,
}

impl Ablation {
    /// All ablations, smallest first.
    pub const ALL: [Ablation; 4] = [Ablation::P, Ablation::MP, Ablation::EP, Ablation::EMP];

    /// Whether the trajectory (plan) encoder is on.
    pub fn uses_plan(self) -> bool {
        matches!(self, Ablation::MP | Ablation::EMP)
    }

    /// Whether the vision encoder is on.
    pub fn uses_vision(self) -> bool {
        matches!(self, Ablation::EP | Ablation::EMP)
    }
}

impl fmt::Display for Ablation {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let s = match self {
            Ablation::P => "P",
            Ablation::MP => "MP",
            Ablation::EP => "EP",
            Ablation::EMP => "EMP",
        };
        f.write_str(s)
    }
}

impl FromStr for Ablation {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.to_ascii_uppercase().as_str() {
            "P" => Ok(Ablation::P),
            "MP" => Ok(Ablation::MP),
            "EP" => Ok(Ablation::EP),
            "EMP" => Ok(Ablation::EMP),
            other => Err(format!(
                "unknown ablation {other:?}: expected P, MP, EP or EMP"
            )),
        }
    }
}

/// What the trajectory encoder (M) reads: the paper's input ablations
/// (section "Ablation Studies", table "Input data ablations"). Stored in the
/// model file (in its [`ModelConfig`]), so that training, `eval` and the
/// streaming forecaster build the same input; files written before this
/// option existed read as [`TrajectoryInput::Planned`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum TrajectoryInput {
    /// The planned joint angles of ticks `t-N+1 ..= t+h_K` (`N + h_K` rows):
    /// the past and the known future of the plan (EMP as published).
    #[default]
    Planned,
    /// "Historical only": the planned joint angles of ticks `t-N+1 ..= t`
    /// (`N` rows), nothing from the future.
    HistoricalOnly,
    /// "Real position": the measured joint angles of ticks `t-N+1 ..= t`
    /// (`N` rows, a copy of the motion encoder's input) in place of the plan.
    RealPosition,
}

impl TrajectoryInput {
    /// The name on the command line and in the model file.
    pub fn name(self) -> &'static str {
        match self {
            TrajectoryInput::Planned => "planned",
            TrajectoryInput::HistoricalOnly => "historical-only",
            TrajectoryInput::RealPosition => "real-position",
        }
    }

    /// Whether the input is cut from the planned trajectory (the plan
    /// stream is needed).
    pub fn reads_plan(self) -> bool {
        !matches!(self, TrajectoryInput::RealPosition)
    }
}

impl fmt::Display for TrajectoryInput {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Sizes of every part of the network (see `docs/network.md`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ModelConfig {
    /// `lite` or `paper`.
    pub name: String,
    /// Window length `N`, ticks.
    pub n_ticks: usize,
    /// Number of joints `C`.
    pub n_joints: usize,
    /// Forecast horizons `H`, ticks, increasing.
    pub horizons_ticks: Vec<usize>,
    /// Input frame side `S`, pixels.
    pub frame_size: usize,
    /// Low-pass cut-off `a`: frequencies `|f| < a` kept, frames decimated to `2a`.
    pub lowpass_a: usize,
    /// Motion encoder: number of temporal blocks.
    pub num_temporal: usize,
    /// Trajectory encoder: embedding width `d_t`.
    pub plan_d: usize,
    /// Trajectory encoder: Inception hidden width.
    pub inc_dim: usize,
    /// Trajectory encoder: Inception kernels `1, 3, 5, ...`.
    pub num_kernels: usize,
    /// Trajectory encoder: periods per block.
    pub top_k: usize,
    /// Trajectory encoder: number of TimesNet blocks.
    pub num_times: usize,
    /// Vision encoder: output channels of each Inception3d layer.
    pub vision_channels: Vec<usize>,
    /// Vision encoder: whether each layer's max-pool also halves time.
    pub vision_time_pool: Vec<bool>,
    /// Classifier hidden width.
    pub d_model: usize,
    /// Classifier dropout (training only).
    pub dropout: f64,
    /// What the trajectory encoder reads.
    #[serde(default)]
    pub trajectory: TrajectoryInput,
}

impl ModelConfig {
    /// The onboard default (`inc_dim = 64`, `num_kernels = 3`).
    pub fn lite(
        n_ticks: usize,
        n_joints: usize,
        horizons_ticks: Vec<usize>,
        frame_size: usize,
    ) -> Self {
        ModelConfig {
            name: "lite".into(),
            n_ticks,
            n_joints,
            horizons_ticks,
            frame_size,
            lowpass_a: (frame_size / 4).max(1),
            num_temporal: 6,
            plan_d: 32,
            inc_dim: 64,
            num_kernels: 3,
            top_k: 3,
            num_times: 2,
            vision_channels: vec![8, 16, 32, 32],
            vision_time_pool: vec![false, false, true, true],
            d_model: 1024,
            dropout: 0.1,
            trajectory: TrajectoryInput::Planned,
        }
    }

    /// This config with TimesNet's defaults (`inc_dim = 256`,
    /// `num_kernels = 6`): the `paper` config of the same shapes.
    pub fn paper(self) -> Self {
        ModelConfig {
            name: "paper".into(),
            inc_dim: 256,
            num_kernels: 6,
            ..self
        }
    }

    /// By name: `lite` or `paper`.
    pub fn named(
        name: &str,
        n_ticks: usize,
        n_joints: usize,
        horizons_ticks: Vec<usize>,
        frame_size: usize,
    ) -> Result<Self, String> {
        let lite = Self::lite(n_ticks, n_joints, horizons_ticks, frame_size);
        match name {
            "lite" => Ok(lite),
            "paper" => Ok(lite.paper()),
            other => Err(format!(
                "unknown model config {other:?}: expected lite or paper"
            )),
        }
    }

    /// Number of horizons `K`.
    pub fn k(&self) -> usize {
        self.horizons_ticks.len()
    }

    /// Longest horizon `h_K`, ticks.
    pub fn max_horizon_ticks(&self) -> usize {
        self.horizons_ticks.last().copied().unwrap_or(0)
    }

    /// Rows of the trajectory encoder's input: `L = N + h_K` for the
    /// planned trajectory, `N` for the historical-only and real-position
    /// ablations.
    pub fn plan_len(&self) -> usize {
        match self.trajectory {
            TrajectoryInput::Planned => self.n_ticks + self.max_horizon_ticks(),
            TrajectoryInput::HistoricalOnly | TrajectoryInput::RealPosition => self.n_ticks,
        }
    }

    /// The trajectory encoder's input, `[plan_len(), C]`, cut from a window's
    /// measured `joints` `[N, C]` and planned `plan` `[N + h_K, C]` (as
    /// `window::Window` holds them): the whole plan, its first `N` rows (ticks
    /// up to `t`), or the joints. The one place the ablations are made;
    /// training, `eval` and the streaming forecaster all go through it. A
    /// slice too short is returned whole, for the caller's length check.
    pub fn trajectory_rows<'a>(&self, joints: &'a [f32], plan: &'a [f32]) -> &'a [f32] {
        match self.trajectory {
            TrajectoryInput::Planned => plan,
            TrajectoryInput::HistoricalOnly => {
                &plan[..(self.n_ticks * self.n_joints).min(plan.len())]
            }
            TrajectoryInput::RealPosition => joints,
        }
    }

    /// Side of the low-passed frame, `2a`.
    pub fn lowpassed_size(&self) -> usize {
        2 * self.lowpass_a
    }

    /// Vision output shape `[channels, time, h, w]` after all layers.
    pub fn vision_out_shape(&self) -> [usize; 4] {
        let mut t = self.n_ticks;
        let mut hw = self.lowpassed_size();
        for &tp in &self.vision_time_pool {
            hw /= 2;
            if tp {
                t /= 2;
            }
        }
        [*self.vision_channels.last().unwrap_or(&3), t, hw, hw]
    }

    /// Checks that the sizes make a network.
    pub fn validate(&self) -> Result<(), String> {
        if self.n_ticks < 2 || self.n_joints == 0 || self.horizons_ticks.is_empty() {
            return Err("n_ticks >= 2, n_joints >= 1 and at least one horizon are needed".into());
        }
        if self.horizons_ticks.windows(2).any(|w| w[0] >= w[1]) || self.horizons_ticks[0] == 0 {
            return Err(format!(
                "horizons must be positive and increasing: {:?}",
                self.horizons_ticks
            ));
        }
        if self.vision_channels.len() != self.vision_time_pool.len()
            || self.vision_channels.is_empty()
        {
            return Err(
                "vision_channels and vision_time_pool must have the same, non-zero length".into(),
            );
        }
        if 2 * self.lowpass_a > self.frame_size {
            return Err(format!(
                "low-pass a = {} needs frames of at least {} px",
                self.lowpass_a,
                2 * self.lowpass_a
            ));
        }
        let [_, t, hw, _] = self.vision_out_shape();
        if t == 0 || hw == 0 {
            return Err(
                "the vision encoder pools the window away: more ticks or larger frames needed"
                    .into(),
            );
        }
        if self.num_kernels == 0 || self.top_k == 0 {
            return Err("num_kernels and top_k must be positive".into());
        }
        Ok(())
    }
}
