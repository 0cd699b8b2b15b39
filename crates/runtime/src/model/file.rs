//! The model file: one file with the weights and everything needed to use them.
//!
//! Layout: `b"FGEMP\0v1"` (8 bytes), JSON length (u64 LE), the [`ModelMeta`]
//! JSON, burnpack length (u64 LE), the burnpack bytes of the [`Emp`] weights.
//! A file whose calibration is beta calibration at some horizon starts with
//! `b"FGEMP\0v2"` instead, so that a reader that knows only Platt scaling
//! refuses it rather than publish probabilities it would compute wrongly.
//! Written by `fall-guard-lab train`, read by the daemon, `eval` and `bench`.

use std::path::{Path, PathBuf};

use burn::module::Module;
use burn::prelude::*;
use burn::store::ModuleRecord;
use burn::tensor::Bytes;
use serde::{Deserialize, Serialize};

use super::config::{Ablation, ModelConfig};
use super::emp::{Emp, EmpInference, EmpInput};
use super::ranges::Bounds;
use super::vision::lowpass_frames;

const MAGIC: &[u8; 8] = b"FGEMP\0v1";
/// The magic of a file that needs a reader of beta calibration.
const MAGIC_V2: &[u8; 8] = b"FGEMP\0v2";

/// Errors from loading, checking or running a model.
#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    /// The file could not be read or written.
    #[error("model file {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// The file ends before what its header announces.
    #[error("model file {path} is truncated: {what}")]
    Truncated {
        /// The file.
        path: PathBuf,
        /// What was being read.
        what: String,
    },
    /// The file does not start with the fall-guard model magic.
    #[error("{path} is not a fall-guard model file (bad magic; expected a file written by `fall-guard-lab train`)")]
    BadMagic {
        /// The file.
        path: PathBuf,
    },
    /// The metadata is unreadable or inconsistent.
    #[error("model file {path}: bad metadata: {message}")]
    BadMeta {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// The weights do not fit the network the metadata describes.
    #[error("model file {path}: bad weights: {message}")]
    Weights {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// The model was trained for other inputs than those offered.
    #[error("model does not match the inputs: {0}")]
    Incompatible(String),
    /// An input is malformed (wrong length, NaN, missing stream).
    #[error("bad model input: {0}")]
    Input(String),
}

/// One epoch of the training history.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EpochRecord {
    /// 1-based epoch.
    pub epoch: usize,
    /// Mean training loss (BCE per horizon).
    pub train_loss: f64,
    /// Validation loss.
    pub val_loss: f64,
    /// Validation accuracy, mean over horizons.
    pub val_accuracy: f64,
}

/// Everything the daemon needs besides the weights.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ModelMeta {
    /// Network sizes.
    pub config: ModelConfig,
    /// Which encoders are on.
    pub ablation: Ablation,
    /// Forecast horizons, ticks.
    pub horizons_ticks: Vec<usize>,
    /// Tick rate the model was trained at, Hz.
    pub rate_hz: f64,
    /// Window length `N`, ticks.
    pub n_ticks: usize,
    /// Joint names in model order.
    pub joint_names: Vec<String>,
    /// Frame side `S`, pixels.
    pub frame_size: u32,
    /// Per-joint mean of `joints`, radians (train split).
    pub joint_mean: Vec<f32>,
    /// Per-joint standard deviation of `joints`, radians (train split).
    pub joint_std: Vec<f32>,
    /// Per-joint mean of `plan`, radians (train split).
    pub plan_mean: Vec<f32>,
    /// Per-joint standard deviation of `plan`, radians (train split).
    pub plan_std: Vec<f32>,
    /// Training history, one entry per epoch.
    #[serde(default)]
    pub history: Vec<EpochRecord>,
    /// The epoch whose weights are stored (1-based; 0 = untrained).
    #[serde(default)]
    pub best_epoch: usize,
    /// Where the training data came from, e.g. `simulated`.
    pub trained_on: String,
    /// Training seed.
    #[serde(default)]
    pub seed: u64,
    /// Post-hoc calibration of the probabilities (`fall-guard-lab calibrate`);
    /// none: `sigmoid` of the network's logits as trained.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibration: Option<Calibration>,
    /// How the training windows were drawn (`deployment` or `paper`, see
    /// `train::sampler`); none: written before the option existed
    /// (deployment).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub protocol: Option<String>,
    /// The vision encoder's learning rate when it trained at another than
    /// its rate table's (`train --vision-lr`); none: the table's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub vision_lr: Option<f64>,
    /// The range of every input over the training split (written by
    /// `fall-guard-lab train`, added by `fall-guard-lab ranges`), which the
    /// out-of-range guard holds windows to ([`super::ranges`]); none: no
    /// bounds, nothing checked.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub input_ranges: Option<super::ranges::InputRanges>,
}

/// Post-hoc calibration, fitted on held-out windows after training, per
/// horizon of the network's logit `z_k`: Platt scaling, `p_k = sigmoid(a_k
/// z_k + b_k)`, or beta calibration, `p_k = sigmoid(a_k softplus(z_k) -
/// c_k softplus(-z_k) + b_k)`, which gives the two sides of the logit slopes
/// of their own (in the raw probability `q = sigmoid(z)`: `sigmoid(c_k ln q -
/// a_k ln(1 - q) + b_k)`, Kull et al.'s beta calibration; Platt is `c_k =
/// a_k`). Then a running maximum over the horizons, so that a longer horizon
/// never reads less likely than a shorter one (the network guarantees that
/// for its raw output; a per-horizon fit alone would not).
/// `fall-guard-lab calibrate` fits each horizon, shortest first, for the
/// probability so applied (above the shorter ones' maximum).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Calibration {
    /// Logit scale per horizon (`1 / temperature`), positive: `a_k`, of
    /// the positive side of the logit under beta calibration.
    pub scale: Vec<f32>,
    /// Logit offset per horizon: `b_k`.
    pub bias: Vec<f32>,
    /// Beta calibration's scale of the negative side per horizon, `c_k`,
    /// positive (equal to `scale` at a horizon calibrated by Platt
    /// scaling); none: Platt scaling at every horizon.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub neg_scale: Option<Vec<f32>>,
    /// What it was fitted on, e.g. `validation split of data/sim2000, 2000 windows`.
    pub fitted_on: String,
}

impl Calibration {
    /// The identity: `sigmoid(z)` per horizon.
    pub fn identity(horizons: usize) -> Self {
        Calibration {
            scale: vec![1.0; horizons],
            bias: vec![0.0; horizons],
            neg_scale: None,
            fitted_on: "identity".into(),
        }
    }

    /// The calibrated logit of horizon `k` (before the running maximum).
    pub fn logit(&self, k: usize, z: f32) -> f32 {
        let (a, b) = (self.scale[k], self.bias[k]);
        match &self.neg_scale {
            Some(c) => a * softplus(z) - c[k] * softplus(-z) + b,
            None => a * z + b,
        }
    }

    /// Calibrated probabilities of one window's `K` logits.
    pub fn apply(&self, logits: &[f32]) -> Vec<f32> {
        let mut floor = 0.0f32;
        logits
            .iter()
            .enumerate()
            .map(|(k, &z)| {
                floor = floor.max(sigmoid(self.logit(k, z)));
                floor
            })
            .collect()
    }

    /// Whether some horizon is calibrated by beta calibration (a scale of
    /// its own for the negative side), which a reader of Platt scaling
    /// alone would apply wrongly.
    pub fn is_beta(&self) -> bool {
        self.neg_scale
            .as_ref()
            .is_some_and(|c| c.iter().zip(&self.scale).any(|(c, a)| c != a))
    }

    fn validate(&self, horizons: usize) -> Result<(), String> {
        if self.scale.len() != horizons || self.bias.len() != horizons {
            return Err(format!(
                "calibration has {} scales and {} biases for {horizons} horizons",
                self.scale.len(),
                self.bias.len()
            ));
        }
        if self.scale.iter().any(|&a| !(a.is_finite() && a > 0.0)) {
            return Err("a calibration scale is not a positive number".into());
        }
        if self.bias.iter().any(|b| !b.is_finite()) {
            return Err("a calibration bias is not finite".into());
        }
        if let Some(c) = &self.neg_scale {
            if c.len() != horizons {
                return Err(format!(
                    "calibration has {} negative-side scales for {horizons} horizons",
                    c.len()
                ));
            }
            if c.iter().any(|&c| !(c.is_finite() && c > 0.0)) {
                return Err("a calibration negative-side scale is not a positive number".into());
            }
        }
        Ok(())
    }
}

/// `ln(1 + e^z)`, without overflow for large `z`.
pub fn softplus(z: f32) -> f32 {
    if z > 0.0 {
        z + (-z).exp().ln_1p()
    } else {
        z.exp().ln_1p()
    }
}

/// The logistic function, saturating cleanly for large `|z|`.
pub fn sigmoid(z: f32) -> f32 {
    if z >= 0.0 {
        1.0 / (1.0 + (-z).exp())
    } else {
        let e = z.exp();
        e / (1.0 + e)
    }
}

impl ModelMeta {
    /// Probabilities of one window's `K` logits: calibrated when the file
    /// carries a calibration, `sigmoid(z)` otherwise.
    pub fn probabilities_of(&self, logits: &[f32]) -> Vec<f32> {
        match &self.calibration {
            Some(c) => c.apply(logits),
            None => logits.iter().map(|&z| sigmoid(z)).collect(),
        }
    }

    /// The horizons in ms at the model's tick rate, rounded (15 ticks at
    /// 30 Hz: 500), as configs and topics name them.
    pub fn horizons_ms(&self) -> Vec<u32> {
        self.horizons_ticks
            .iter()
            .map(|&h| (h as f64 * 1000.0 / self.rate_hz).round() as u32)
            .collect()
    }

    /// Metadata for an untrained model with identity standardisation.
    pub fn new(
        config: ModelConfig,
        ablation: Ablation,
        rate_hz: f64,
        joint_names: Vec<String>,
    ) -> Self {
        let c = config.n_joints;
        ModelMeta {
            ablation,
            horizons_ticks: config.horizons_ticks.clone(),
            rate_hz,
            n_ticks: config.n_ticks,
            frame_size: config.frame_size as u32,
            joint_names,
            joint_mean: vec![0.0; c],
            joint_std: vec![1.0; c],
            plan_mean: vec![0.0; c],
            plan_std: vec![1.0; c],
            history: Vec::new(),
            best_epoch: 0,
            trained_on: "untrained".into(),
            seed: 0,
            calibration: None,
            protocol: None,
            vision_lr: None,
            input_ranges: None,
            config,
        }
    }

    /// Refuses inputs the model was not trained for, saying what differs.
    pub fn check_compatible_with(
        &self,
        joint_names: &[String],
        rate_hz: f64,
        n_ticks: usize,
        max_horizon_ticks: usize,
        frame_size: u32,
    ) -> Result<(), ModelError> {
        let mut diffs = Vec::new();
        if joint_names != self.joint_names.as_slice() {
            let first = self
                .joint_names
                .iter()
                .zip(joint_names)
                .position(|(a, b)| a != b)
                .unwrap_or(self.joint_names.len().min(joint_names.len()));
            diffs.push(format!(
                "joint list differs: model has {} joints, input {}; first difference at index {first}: model {:?}, input {:?}",
                self.joint_names.len(),
                joint_names.len(),
                self.joint_names.get(first),
                joint_names.get(first)
            ));
        }
        if (rate_hz - self.rate_hz).abs() > 1e-6 * self.rate_hz.max(1.0) {
            diffs.push(format!(
                "tick rate: model {} Hz, input {} Hz",
                self.rate_hz, rate_hz
            ));
        }
        if n_ticks != self.n_ticks {
            diffs.push(format!(
                "window length N: model {} ticks, input {}",
                self.n_ticks, n_ticks
            ));
        }
        let hk = self.config.max_horizon_ticks();
        if max_horizon_ticks < hk {
            diffs.push(format!(
                "plan reaches {max_horizon_ticks} ticks ahead, the model needs {hk}"
            ));
        }
        if self.ablation.uses_vision() && frame_size != self.frame_size {
            diffs.push(format!(
                "frame size: model {} px, input {} px",
                self.frame_size, frame_size
            ));
        }
        if diffs.is_empty() {
            Ok(())
        } else {
            Err(ModelError::Incompatible(diffs.join("; ")))
        }
    }

    fn validate(&self) -> Result<(), String> {
        self.config.validate()?;
        let c = self.config.n_joints;
        if self.joint_names.len() != c {
            return Err(format!(
                "{} joint names for {} joints",
                self.joint_names.len(),
                c
            ));
        }
        for (name, v) in [
            ("joint_mean", &self.joint_mean),
            ("joint_std", &self.joint_std),
            ("plan_mean", &self.plan_mean),
            ("plan_std", &self.plan_std),
        ] {
            if v.len() != c {
                return Err(format!("{name} has {} values for {c} joints", v.len()));
            }
            if v.iter().any(|x| !x.is_finite()) {
                return Err(format!("{name} is not finite"));
            }
        }
        if self
            .joint_std
            .iter()
            .chain(&self.plan_std)
            .any(|&s| s <= 0.0)
        {
            return Err("a standard deviation is not positive".into());
        }
        if self.n_ticks != self.config.n_ticks || self.horizons_ticks != self.config.horizons_ticks
        {
            return Err("n_ticks / horizons_ticks disagree with the config".into());
        }
        if self.rate_hz.is_nan() || self.rate_hz <= 0.0 {
            return Err(format!("rate_hz {} is not positive", self.rate_hz));
        }
        if let Some(c) = &self.calibration {
            c.validate(self.horizons_ticks.len())?;
        }
        Ok(())
    }
}

/// How the weights are stored in a model file. Loading accepts either: the
/// weights are cast to the network's f32 on load.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum WeightPrecision {
    /// f32, as trained.
    #[default]
    Full,
    /// IEEE half precision (f16): half the file size; what it costs in
    /// accuracy is measured in the model card.
    Half,
}

/// Casts every float parameter to one dtype.
struct CastParams(burn::tensor::DType);

impl burn::module::ModuleMapper for CastParams {
    fn map_float<const D: usize>(
        &mut self,
        param: burn::module::Param<Tensor<D>>,
    ) -> burn::module::Param<Tensor<D>> {
        let dtype = self.0;
        param.map(|t| t.cast(dtype))
    }
}

/// Writes `meta` and the weights of `model` to `path` (one file), in f32.
pub fn save_model(path: &Path, meta: &ModelMeta, model: &Emp) -> Result<(), ModelError> {
    save_model_as(path, meta, model, WeightPrecision::Full)
}

/// Writes `meta` and the weights of `model` to `path` at `precision`.
pub fn save_model_as(
    path: &Path,
    meta: &ModelMeta,
    model: &Emp,
    precision: WeightPrecision,
) -> Result<(), ModelError> {
    let io = |source| ModelError::Io {
        path: path.to_path_buf(),
        source,
    };
    let json = serde_json::to_vec(meta).map_err(|e| ModelError::BadMeta {
        path: path.to_path_buf(),
        message: e.to_string(),
    })?;
    let mut model = model.clone().valid();
    if precision == WeightPrecision::Half {
        model = model.map(&mut CastParams(burn::tensor::DType::F16));
    }
    let weights = model
        .into_record()
        .into_bytes()
        .map_err(|e| ModelError::Weights {
            path: path.to_path_buf(),
            message: e.to_string(),
        })?;
    let mut out = Vec::with_capacity(8 + 16 + json.len() + weights.len());
    let beta = meta.calibration.as_ref().is_some_and(Calibration::is_beta);
    out.extend_from_slice(if beta { MAGIC_V2 } else { MAGIC });
    out.extend_from_slice(&(json.len() as u64).to_le_bytes());
    out.extend_from_slice(&json);
    out.extend_from_slice(&(weights.len() as u64).to_le_bytes());
    out.extend_from_slice(&weights);
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(io)?;
    }
    // Write `NAME.partial` then rename, so a reader never sees half a file.
    let tmp = partial_path(path);
    std::fs::write(&tmp, &out).map_err(io)?;
    std::fs::rename(&tmp, path).map_err(io)?;
    Ok(())
}

/// Writes `meta` over the metadata of the model file `path` into `out`
/// (the same path or another), the weights section copied byte for byte:
/// for metadata added after training (`fall-guard-lab ranges`). `meta`
/// must describe the same network: same sizes and encoders, and a
/// calibration of the same form, since the file's version says which.
pub fn rewrite_meta(path: &Path, out: &Path, meta: &ModelMeta) -> Result<(), ModelError> {
    let (old, _) = load_emp(path, &super::cpu_device())?;
    if old.config != meta.config || old.ablation != meta.ablation {
        return Err(ModelError::BadMeta {
            path: path.to_path_buf(),
            message: "the new metadata describes another network".into(),
        });
    }
    let beta = |m: &ModelMeta| m.calibration.as_ref().is_some_and(Calibration::is_beta);
    if beta(&old) != beta(meta) {
        return Err(ModelError::BadMeta {
            path: path.to_path_buf(),
            message: "the new metadata changes the calibration's form".into(),
        });
    }
    let bytes = std::fs::read(path).map_err(|source| ModelError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    // load_emp checked the layout: magic, length, metadata, the rest.
    let json_len = u64::from_le_bytes(bytes[8..16].try_into().expect("8 bytes")) as usize;
    let rest = &bytes[16 + json_len..];
    let json = serde_json::to_vec(meta).map_err(|e| ModelError::BadMeta {
        path: out.to_path_buf(),
        message: e.to_string(),
    })?;
    let mut file = Vec::with_capacity(16 + json.len() + rest.len());
    file.extend_from_slice(&bytes[..8]);
    file.extend_from_slice(&(json.len() as u64).to_le_bytes());
    file.extend_from_slice(&json);
    file.extend_from_slice(rest);
    let io = |source| ModelError::Io {
        path: out.to_path_buf(),
        source,
    };
    let tmp = partial_path(out);
    std::fs::write(&tmp, &file).map_err(io)?;
    std::fs::rename(&tmp, out).map_err(io)?;
    Ok(())
}

/// `NAME.partial` next to `path` (`models/emp.h15.bpk` ->
/// `models/emp.h15.bpk.partial`): where a file is written before it is
/// renamed to `path`.
pub fn partial_path(path: &Path) -> PathBuf {
    let mut name = path.file_name().unwrap_or_default().to_os_string();
    name.push(".partial");
    path.with_file_name(name)
}

/// Reads a model file: metadata and the trainable network on `device`.
pub fn load_emp(path: &Path, device: &Device) -> Result<(ModelMeta, Emp), ModelError> {
    let bytes = std::fs::read(path).map_err(|source| ModelError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let p = || path.to_path_buf();
    if bytes.len() < MAGIC.len() {
        return Err(if MAGIC.starts_with(&bytes) && !bytes.is_empty() {
            ModelError::Truncated {
                path: p(),
                what: "magic".into(),
            }
        } else {
            ModelError::BadMagic { path: p() }
        });
    }
    let v1 = &bytes[..8] == MAGIC;
    if !v1 && &bytes[..8] != MAGIC_V2 {
        return Err(ModelError::BadMagic { path: p() });
    }
    let mut at = 8usize;
    let mut take = |n: usize, what: &str| -> Result<&[u8], ModelError> {
        if bytes.len() - at < n {
            return Err(ModelError::Truncated {
                path: p(),
                what: format!(
                    "{what}: needs {n} bytes at offset {at}, file has {}",
                    bytes.len()
                ),
            });
        }
        let s = &bytes[at..at + n];
        at += n;
        Ok(s)
    };
    let json_len =
        u64::from_le_bytes(take(8, "metadata length")?.try_into().expect("8 bytes")) as usize;
    let json = take(json_len, "metadata")?;
    let meta: ModelMeta = serde_json::from_slice(json).map_err(|e| ModelError::BadMeta {
        path: p(),
        message: e.to_string(),
    })?;
    meta.validate()
        .map_err(|message| ModelError::BadMeta { path: p(), message })?;
    if v1 && meta.calibration.as_ref().is_some_and(Calibration::is_beta) {
        return Err(ModelError::BadMeta {
            path: p(),
            message: "a version-1 file carries a beta calibration (version 2's)".into(),
        });
    }
    let w_len =
        u64::from_le_bytes(take(8, "weights length")?.try_into().expect("8 bytes")) as usize;
    let weights = take(w_len, "weights")?.to_vec();
    let record = ModuleRecord::from_bytes(Bytes::from_bytes_vec(weights))
        .map_err(|e| ModelError::Weights {
            path: p(),
            message: e.to_string(),
        })?
        .cast_to_module_dtype();
    let model = Emp::new(&meta.config, meta.ablation, device)
        .try_load_record(record)
        .map_err(|e| ModelError::Weights {
            path: p(),
            message: e.to_string(),
        })?;
    Ok((meta, model))
}

/// How the classifier's input projection, most of a network's weights
/// (7,260 x 1,024 for EMP lite), is held in memory for inference
/// (`[model].projection`, `bench --projection`, `eval --projection`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Deserialize, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ProjectionWeights {
    /// At the file's precision (f16 for the shipped files): the product is
    /// the one training evaluated.
    #[default]
    AsFile,
    /// Symmetric int8, one scale per input row: half the memory of f16 and
    /// half the bytes read per tick; forecasts move by the amounts the
    /// model card gives.
    Int8,
}

impl ProjectionWeights {
    /// As `[model].projection` spells it.
    pub fn name(self) -> &'static str {
        match self {
            ProjectionWeights::AsFile => "as_file",
            ProjectionWeights::Int8 => "int8",
        }
    }
}

/// As the command lines spell it (`--projection as-file|int8`); the
/// config's `as_file` is taken too.
impl std::str::FromStr for ProjectionWeights {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "as-file" | "as_file" => Ok(ProjectionWeights::AsFile),
            "int8" => Ok(ProjectionWeights::Int8),
            other => Err(format!(
                "unknown projection {other:?}: expected as-file or int8"
            )),
        }
    }
}

/// How the trajectory encoder's convolutions multiply for inference
/// (`[model].convolutions`, `bench --convolutions`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Deserialize, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Convolutions {
    /// f32 products, as training evaluated them.
    #[default]
    F32,
    /// Weights in int8 (one scale per output channel), each im2col row in
    /// 7 bits, integer sums: fewer instructions per tick on AVX2; forecasts
    /// move by the amounts the model card gives.
    Int8,
    /// [`Convolutions::Int8`] where the integer kernel is the faster one
    /// (x86-64 with AVX2), [`Convolutions::F32`] elsewhere: on aarch64 the
    /// f32 products run in NEON registers, and the integer ones in a
    /// portable loop that takes twice the instructions of a whole tick
    /// (`docs/performance.md`, "aarch64: instructions per tick").
    Auto,
}

impl Convolutions {
    /// As `[model].convolutions` spells it.
    pub fn name(self) -> &'static str {
        match self {
            Convolutions::F32 => "f32",
            Convolutions::Int8 => "int8",
            Convolutions::Auto => "auto",
        }
    }

    /// What `Auto` is on this CPU; the others as they are.
    pub fn resolved(self) -> Convolutions {
        match self {
            Convolutions::Auto if super::int8_gemm::has_simd_kernel() => Convolutions::Int8,
            Convolutions::Auto => Convolutions::F32,
            chosen => chosen,
        }
    }
}

/// As the command lines spell it (`--convolutions f32|int8|auto`).
impl std::str::FromStr for Convolutions {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "f32" => Ok(Convolutions::F32),
            "int8" => Ok(Convolutions::Int8),
            "auto" => Ok(Convolutions::Auto),
            other => Err(format!(
                "unknown convolutions {other:?}: expected f32, int8 or auto"
            )),
        }
    }
}

/// A model ready for inference: metadata, fused network, device.
#[derive(Debug, Clone)]
pub struct LoadedModel {
    /// What the file says about the model.
    pub meta: ModelMeta,
    /// The fused inference network.
    pub network: EmpInference,
    /// The device it runs on.
    pub device: Device,
    /// Where it was loaded from.
    pub path: PathBuf,
}

impl LoadedModel {
    /// Loads `path` for inference on the CPU device.
    pub fn load(path: impl AsRef<Path>) -> Result<Self, ModelError> {
        let path = path.as_ref();
        let device = super::cpu_device();
        let (meta, emp) = load_emp(path, &device)?;
        tracing::info!(file = %path.display(), ablation = %meta.ablation, config = %meta.config.name, "model loaded");
        Ok(Self::from_parts(meta, &emp, device, path.to_path_buf()))
    }

    /// The same model with its input projection held as `projection` says.
    pub fn with_projection(mut self, projection: ProjectionWeights) -> Self {
        if projection == ProjectionWeights::Int8 {
            self.network.quantize_projection();
        }
        self
    }

    /// The same model with its trajectory convolutions as `convolutions` says
    /// (`Auto` as [`Convolutions::resolved`] chooses on this CPU).
    pub fn with_convolutions(mut self, convolutions: Convolutions) -> Self {
        if convolutions.resolved() == Convolutions::Int8 {
            self.network.quantize_convolutions();
        }
        self
    }

    /// Wraps an in-memory network (tests, training).
    pub fn from_parts(meta: ModelMeta, emp: &Emp, device: Device, path: PathBuf) -> Self {
        LoadedModel {
            network: emp.to_inference(),
            meta,
            device,
            path,
        }
    }

    /// Whole-window forecast: `K` probabilities, non-decreasing in the horizon.
    ///
    /// `joints` `[N, C]` and `plan` `[N + h_K, C]` in radians, `frames`
    /// `[3, N, S, S]` in `[0, 1]` (row-major, as `window::Window` holds them).
    /// Inputs the ablation does not use are ignored (may be empty); the
    /// trajectory encoder reads what the model's
    /// [`super::TrajectoryInput`] cuts from `joints` and `plan`.
    pub fn forecast_arrays(
        &self,
        joints: &[f32],
        plan: &[f32],
        frames: &[f32],
    ) -> Result<Vec<f32>, ModelError> {
        let logits = self.logits_arrays(joints, plan, frames)?;
        Ok(self.meta.probabilities_of(&logits))
    }

    /// The network's raw logits `z_k` of one window (before `sigmoid` and
    /// calibration); what `fall-guard-lab calibrate` fits on.
    pub fn logits_arrays(
        &self,
        joints: &[f32],
        plan: &[f32],
        frames: &[f32],
    ) -> Result<Vec<f32>, ModelError> {
        let input = self.batch_input(&[joints], &[plan], &[frames])?;
        host_logits(self.network.forward(input))
    }

    /// Builds a standardised, low-passed batch from raw windows.
    pub fn batch_input(
        &self,
        joints: &[&[f32]],
        plan: &[&[f32]],
        frames: &[&[f32]],
    ) -> Result<EmpInput, ModelError> {
        build_input(&self.meta, joints, plan, frames, &self.device)
    }
}

/// The logits of a `[1, K]` batch, on the host.
pub fn host_logits(logits: Tensor<2>) -> Result<Vec<f32>, ModelError> {
    logits
        .into_data()
        .try_to_vec::<f32>()
        .map_err(|e| ModelError::Input(format!("model output is not f32: {e:?}")))
}

/// Standardises joints and plan per joint (each value held to its measured
/// range first, when the file has ranges, [`Bounds`]: a value inside it is
/// untouched), checks every value,
/// low-passes the frames, and stacks `B` windows into one network input.
pub fn build_input(
    meta: &ModelMeta,
    joints: &[&[f32]],
    plan: &[&[f32]],
    frames: &[&[f32]],
    device: &Device,
) -> Result<EmpInput, ModelError> {
    let cfg = &meta.config;
    let (n, c, l, s) = (cfg.n_ticks, cfg.n_joints, cfg.plan_len(), cfg.frame_size);
    let b = joints.len();
    let bounds = Bounds::of(meta);
    let mut excursions = Vec::new();
    let mut standardise =
        |name: &str, rows: usize, windows: &[&[f32]], mean: &[f32], std: &[f32]| {
            let is_plan = name == "plan";
            let mut out = Vec::with_capacity(b * rows * c);
            for (w, x) in windows.iter().enumerate() {
                if x.len() != rows * c {
                    return Err(ModelError::Input(format!(
                        "{name} of window {w} has {} values, expected {rows} ticks x {c} joints",
                        x.len()
                    )));
                }
                for (i, &v) in x.iter().enumerate() {
                    if !v.is_finite() {
                        return Err(ModelError::Input(format!(
                            "{name} of window {w} is not finite at tick {} joint {} ({v})",
                            i / c,
                            meta.joint_names
                                .get(i % c)
                                .map(String::as_str)
                                .unwrap_or("?")
                        )));
                    }
                    let v = match &bounds {
                        Some(b) => b.clip(is_plan, i % c, v, &mut excursions),
                        None => v,
                    };
                    out.push((v - mean[i % c]) / std[i % c]);
                }
            }
            Ok(Tensor::<3>::from_data(
                TensorData::new(out, [b, rows, c]),
                device,
            ))
        };
    let joints_t = standardise("joints", n, joints, &meta.joint_mean, &meta.joint_std)?;
    let plan_t = if meta.ablation.uses_plan() {
        if plan.len() != b {
            return Err(ModelError::Input(format!(
                "{} plans for {b} windows",
                plan.len()
            )));
        }
        let rows: Vec<&[f32]> = joints
            .iter()
            .zip(plan)
            .map(|(j, p)| cfg.trajectory_rows(j, p))
            .collect();
        Some(standardise(
            "plan",
            l,
            &rows,
            &meta.plan_mean,
            &meta.plan_std,
        )?)
    } else {
        None
    };
    let frames_t = if meta.ablation.uses_vision() {
        if frames.len() != b {
            return Err(ModelError::Input(format!(
                "{} frame stacks for {b} windows",
                frames.len()
            )));
        }
        let mut all = Vec::with_capacity(b * 3 * n * s * s);
        for (w, f) in frames.iter().enumerate() {
            if f.len() != 3 * n * s * s {
                return Err(ModelError::Input(format!(
                    "frames of window {w} have {} values, expected 3 x {n} x {s} x {s}",
                    f.len()
                )));
            }
            if let Some(i) = f.iter().position(|v| !v.is_finite()) {
                return Err(ModelError::Input(format!(
                    "frames of window {w} are not finite at tick {}",
                    (i / (s * s)) % n
                )));
            }
            all.extend_from_slice(f);
        }
        let raw = Tensor::<5>::from_data(TensorData::new(all, [b, 3, n, s, s]), device);
        Some(lowpass_frames(raw, cfg.lowpass_a))
    } else {
        None
    };
    Ok(EmpInput {
        joints: joints_t,
        plan: plan_t,
        frames: frames_t,
    })
}
