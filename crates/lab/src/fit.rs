//! The training loop: Adam with per-encoder learning rate and weight decay,
//! batch 4, early stopping on validation loss, the best epoch kept.
//!
//! In: labelled windows from an [`EpochSource`] (one i.i.d. window per episode
//! per epoch, drawn by the data plane's sampler): each epoch a [`WindowSet`],
//! which says which windows it holds and builds their arrays a batch at a
//! time, so memory does not grow with the number of windows. Out: the
//! trained [`Emp`] and its [`ModelMeta`] (standardisation statistics,
//! history), ready for [`fall_guard_runtime::model::save_model`].
//!
//! With [`FitOptions::checkpoint`], every epoch is checkpointed and a rerun
//! resumes from the last one ([`super::checkpoint`]); burn's generator is
//! reseeded at each epoch ([`epoch_seed`]) so that a resumed run trains as
//! an uninterrupted one.

use std::ops::Range;
use std::path::PathBuf;

use burn::module::{Module, ModuleMapper, Param, ParamId};
use burn::optim::{GradientsParams, ModuleOptimizer};
use burn::prelude::*;

use super::adam::FusedAdam;
use super::checkpoint::{Checkpoint, EpochState};
use super::device::TrainDevice;
use crate::error::TrainError;
use fall_guard_runtime::model::file::{build_input, load_emp};
use fall_guard_runtime::model::{cpu_device, Ablation, Emp, EpochRecord, ModelConfig, ModelMeta};

/// One training sample: a window and its labels.
#[derive(Debug, Clone)]
pub struct LabeledWindow {
    /// `[N, C]` radians.
    pub joints: Vec<f32>,
    /// `[N + h_K, C]` radians.
    pub plan: Vec<f32>,
    /// `[3, N, S, S]` in `[0, 1]` (may be empty for ablations without vision).
    pub frames: Vec<f32>,
    /// `K` labels: 1 if fallen at `t + h_k`.
    pub labels: Vec<f32>,
    /// The episode it was cut from (index in its split): the unit the
    /// bootstrap of `eval` resamples.
    pub episode: usize,
    /// `Some(k)`: drawn for horizon `k` alone (the paper protocol: balanced
    /// at `h_k`, stop line at `h_k`), so only label `k` is trained on and
    /// scored; `None`: every horizon (the deployment protocol).
    pub scored_horizon: Option<usize>,
}

impl LabeledWindow {
    /// Whether label `k` of this window is trained on and scored.
    pub fn scores(&self, k: usize) -> bool {
        self.scored_horizon.is_none_or(|s| s == k)
    }

    /// What it is scored against, without its arrays.
    pub fn truth(&self) -> WindowTruth {
        WindowTruth {
            labels: self.labels.clone(),
            episode: self.episode,
            scored_horizon: self.scored_horizon,
        }
    }
}

/// A window's labels, episode and scored horizon: what metrics need of it
/// once it has been forecast (see [`LabeledWindow`]).
#[derive(Debug, Clone, PartialEq)]
pub struct WindowTruth {
    /// `K` labels: 1 if fallen at `t + h_k`.
    pub labels: Vec<f32>,
    /// The episode it was cut from (index in its split).
    pub episode: usize,
    /// See [`LabeledWindow::scored_horizon`].
    pub scored_horizon: Option<usize>,
}

impl WindowTruth {
    /// Whether label `k` of this window is scored.
    pub fn scores(&self, k: usize) -> bool {
        self.scored_horizon.is_none_or(|s| s == k)
    }
}

/// Labelled windows in a fixed order whose arrays are built when asked for,
/// a few at a time: an epoch of a data set holds which windows it has (a
/// few bytes each), not their frames (2.9 MB each as `f32` for N = 60 at
/// 64 x 64).
pub trait WindowSet {
    /// How many windows.
    fn len(&self) -> usize;

    /// Whether there is none.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Windows `range`, in order. With `frames` false their frames are left
    /// empty (for statistics of the joints and the plan).
    fn build(&self, range: Range<usize>, frames: bool) -> Result<Vec<LabeledWindow>, TrainError>;

    /// Every window's truth, in order.
    fn truths(&self) -> Result<Vec<WindowTruth>, TrainError> {
        let mut out = Vec::with_capacity(self.len());
        for start in (0..self.len()).step_by(256) {
            let batch = self.build(start..(start + 256).min(self.len()), false)?;
            out.extend(batch.iter().map(LabeledWindow::truth));
        }
        Ok(out)
    }
}

/// Windows already built (synthetic data, tests).
impl WindowSet for Vec<LabeledWindow> {
    fn len(&self) -> usize {
        self.as_slice().len()
    }

    fn build(&self, range: Range<usize>, frames: bool) -> Result<Vec<LabeledWindow>, TrainError> {
        let part = self.get(range.clone()).ok_or_else(|| {
            TrainError::Data(format!(
                "windows {range:?} of a set of {}",
                self.as_slice().len()
            ))
        })?;
        Ok(part
            .iter()
            .map(|w| LabeledWindow {
                frames: if frames { w.frames.clone() } else { Vec::new() },
                ..w.clone_without_frames()
            })
            .collect())
    }
}

impl LabeledWindow {
    fn clone_without_frames(&self) -> LabeledWindow {
        LabeledWindow {
            joints: self.joints.clone(),
            plan: self.plan.clone(),
            frames: Vec::new(),
            labels: self.labels.clone(),
            episode: self.episode,
            scored_horizon: self.scored_horizon,
        }
    }
}

/// Calls `f` on consecutive batches of at most `batch` windows of `set`.
pub fn for_each_batch(
    set: &dyn WindowSet,
    batch: usize,
    frames: bool,
    mut f: impl FnMut(&[LabeledWindow]) -> Result<(), TrainError>,
) -> Result<(), TrainError> {
    let (n, b) = (set.len(), batch.max(1));
    for start in (0..n).step_by(b) {
        f(&set.build(start..(start + b).min(n), frames)?)?;
    }
    Ok(())
}

/// Where the windows come from.
pub trait EpochSource {
    /// The training windows of epoch `epoch` (1-based), in training order:
    /// the same for an epoch whichever epoch is asked for first (a resumed
    /// run starts at a later one).
    fn train_epoch(&mut self, epoch: usize) -> Result<Box<dyn WindowSet>, TrainError>;
    /// The validation windows (the same every epoch).
    fn validation(&mut self) -> Result<Box<dyn WindowSet>, TrainError>;
}

/// Learning rate and weight decay of one encoder.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Rate {
    /// Learning rate.
    pub lr: f64,
    /// L2 weight decay.
    pub weight_decay: f32,
}

/// Per-encoder rates (the paper's appendix table).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct EncoderRates {
    /// Motion encoder.
    pub motion: Rate,
    /// Trajectory encoder.
    pub trajectory: Rate,
    /// Vision encoder.
    pub vision: Rate,
    /// Classifier.
    pub classifier: Rate,
}

impl EncoderRates {
    /// Every learning rate multiplied by `factor` (weight decays kept).
    pub fn scaled(self, factor: f64) -> Self {
        let s = |r: Rate| Rate {
            lr: r.lr * factor,
            ..r
        };
        EncoderRates {
            motion: s(self.motion),
            trajectory: s(self.trajectory),
            vision: s(self.vision),
            classifier: s(self.classifier),
        }
    }

    /// SimP column (simulation, 30 Hz).
    pub fn sim() -> Self {
        EncoderRates {
            motion: Rate {
                lr: 1e-4,
                weight_decay: 1e-5,
            },
            trajectory: Rate {
                lr: 1e-3,
                weight_decay: 1e-4,
            },
            vision: Rate {
                lr: 1e-6,
                weight_decay: 1e-6,
            },
            classifier: Rate {
                lr: 1e-3,
                weight_decay: 1e-4,
            },
        }
    }

    /// RP column (real robot, ~10 Hz).
    pub fn robot() -> Self {
        EncoderRates {
            motion: Rate {
                lr: 5e-4,
                weight_decay: 1e-4,
            },
            trajectory: Rate {
                lr: 1e-4,
                weight_decay: 1e-4,
            },
            vision: Rate {
                lr: 1e-5,
                weight_decay: 5e-4,
            },
            classifier: Rate {
                lr: 1e-4,
                weight_decay: 1e-4,
            },
        }
    }
}

/// Training options.
#[derive(Debug, Clone)]
pub struct FitOptions {
    /// Seed of initialisation and dropout.
    pub seed: u64,
    /// At most this many epochs.
    pub max_epochs: usize,
    /// Stop after this many epochs without a better validation loss.
    pub patience: usize,
    /// Windows per step.
    pub batch_size: usize,
    /// Per-encoder rates.
    pub rates: EncoderRates,
    /// Log the training's progress at info level (a line at every tenth of
    /// an epoch and one per epoch); otherwise at debug level.
    pub progress: bool,
    /// Where the steps run (CPU unless a GPU backend is compiled in and asked for).
    pub device: TrainDevice,
    /// Checkpoint every epoch in this directory and resume from it when it
    /// holds one ([`super::checkpoint`]); the caller removes it once the
    /// model is written.
    pub checkpoint: Option<PathBuf>,
    /// Start from this model file's weights (fine-tuning) instead of a
    /// fresh initialisation; `meta` then carries that file's
    /// standardisation, kept as it is (the weights were trained on it).
    pub init: Option<PathBuf>,
}

impl Default for FitOptions {
    fn default() -> Self {
        FitOptions {
            seed: 1,
            max_epochs: 10,
            patience: 3,
            batch_size: 4,
            rates: EncoderRates::sim(),
            progress: true,
            device: TrainDevice::Cpu,
            checkpoint: None,
            init: None,
        }
    }
}

/// Keeps freed memory in the process heap for the rest of the process.
///
/// A training step allocates and frees buffers of tens of MB (im2col,
/// activations, gradients). glibc serves the large ones with `mmap` and
/// gives them back at `free`, or trims the heap, so every step page-faults
/// them in again (zeroed by the kernel): 10-15% of a step's time here.
/// Training processes set this once; the daemon does not (it returns its
/// load-time heap with `malloc_trim`).
pub fn keep_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        static ONCE: std::sync::Once = std::sync::Once::new();
        ONCE.call_once(|| {
            // SAFETY: mallopt only changes glibc's allocation thresholds; it
            // is called once, before the buffers it concerns are allocated.
            unsafe {
                libc::mallopt(libc::M_MMAP_MAX, 0);
                libc::mallopt(libc::M_TRIM_THRESHOLD, i32::MAX);
            }
        });
    }
}

/// Per-joint sums of one input over windows, in window order.
struct Moments {
    sum: Vec<f64>,
    sq: Vec<f64>,
    count: usize,
}

impl Moments {
    fn new(c: usize) -> Moments {
        Moments {
            sum: vec![0.0; c],
            sq: vec![0.0; c],
            count: 0,
        }
    }

    fn add(&mut self, values: &[f32]) {
        for row in values.chunks_exact(self.sum.len()) {
            for (j, &v) in row.iter().enumerate() {
                self.sum[j] += v as f64;
                self.sq[j] += (v as f64) * (v as f64);
            }
            self.count += 1;
        }
    }

    fn mean_std(&self) -> (Vec<f32>, Vec<f32>) {
        let n = self.count.max(1) as f64;
        let mean: Vec<f32> = self.sum.iter().map(|s| (s / n) as f32).collect();
        let std: Vec<f32> = self
            .sq
            .iter()
            .zip(&self.sum)
            .map(|(q, s)| ((q / n - (s / n).powi(2)).max(0.0).sqrt() as f32).max(1e-3))
            .collect();
        (mean, std)
    }
}

/// Per-joint mean and standard deviation of `joints` and `plan` over
/// `windows` (built a batch at a time, without their frames).
pub fn standardisation(meta: &mut ModelMeta, windows: &dyn WindowSet) -> Result<(), TrainError> {
    let c = meta.config.n_joints;
    let cfg = meta.config.clone();
    let (mut joints, mut plan) = (Moments::new(c), Moments::new(c));
    for_each_batch(windows, 256, false, |batch| {
        for w in batch {
            joints.add(&w.joints);
            // The trajectory encoder's input as the model reads it (the
            // planned window, its past part only, or the measured joints).
            plan.add(cfg.trajectory_rows(&w.joints, &w.plan));
        }
        Ok(())
    })?;
    (meta.joint_mean, meta.joint_std) = joints.mean_std();
    (meta.plan_mean, meta.plan_std) = plan.mean_std();
    Ok(())
}

/// Numerically stable binary cross-entropy with logits, mean over batch and horizons.
pub fn bce_with_logits(logits: Tensor<2>, labels: Tensor<2>) -> Tensor<1> {
    let pos = logits.clone().clamp_min(0.0);
    let log_term = logits.clone().abs().neg().exp().log1p();
    (pos - logits * labels + log_term).mean()
}

/// Binary cross-entropy with logits over the scored labels only (`mask` 1
/// for a scored label, 0 otherwise): their mean.
pub fn masked_bce_with_logits(logits: Tensor<2>, labels: Tensor<2>, mask: Tensor<2>) -> Tensor<1> {
    let pos = logits.clone().clamp_min(0.0);
    let log_term = logits.clone().abs().neg().exp().log1p();
    let scored = mask.clone().sum().clamp_min(1.0);
    ((pos - logits * labels + log_term) * mask).sum() / scored
}

/// The batch's loss: plain BCE when every label is scored (deployment
/// protocol), masked BCE when windows were drawn for one horizon each.
fn batch_loss(
    logits: Tensor<2>,
    batch: &[LabeledWindow],
    k: usize,
    device: &Device,
) -> Result<Tensor<1>, TrainError> {
    let labels = labels_tensor(batch, k, device)?;
    if batch.iter().all(|w| w.scored_horizon.is_none()) {
        return Ok(bce_with_logits(logits, labels));
    }
    let mask: Vec<f32> = batch
        .iter()
        .flat_map(|w| (0..k).map(move |h| f32::from(u8::from(w.scores(h)))))
        .collect();
    let mask = Tensor::<2>::from_data(TensorData::new(mask, [batch.len(), k]), device);
    Ok(masked_bce_with_logits(logits, labels, mask))
}

fn labels_tensor(
    windows: &[LabeledWindow],
    k: usize,
    device: &Device,
) -> Result<Tensor<2>, TrainError> {
    let mut v = Vec::with_capacity(windows.len() * k);
    for w in windows {
        if w.labels.len() != k {
            return Err(TrainError::Data(format!(
                "a window has {} labels, the model has {k} horizons",
                w.labels.len()
            )));
        }
        if w.scored_horizon.is_some_and(|s| s >= k) {
            return Err(TrainError::Data(format!(
                "a window is scored at horizon index {:?}, the model has {k} horizons",
                w.scored_horizon
            )));
        }
        v.extend_from_slice(&w.labels);
    }
    Ok(Tensor::<2>::from_data(
        TensorData::new(v, [windows.len(), k]),
        device,
    ))
}

fn input_for(
    meta: &ModelMeta,
    batch: &[LabeledWindow],
    device: &Device,
) -> Result<fall_guard_runtime::model::EmpInput, TrainError> {
    let joints: Vec<&[f32]> = batch.iter().map(|w| w.joints.as_slice()).collect();
    let plan: Vec<&[f32]> = batch.iter().map(|w| w.plan.as_slice()).collect();
    let frames: Vec<&[f32]> = batch.iter().map(|w| w.frames.as_slice()).collect();
    Ok(build_input(meta, &joints, &plan, &frames, device)?)
}

/// Validation loss and mean accuracy of `model` (evaluated without autodiff,
/// on `device`, where the model's weights are).
pub fn evaluate_loss(
    model: &Emp,
    meta: &ModelMeta,
    windows: &dyn WindowSet,
    batch_size: usize,
    device: &Device,
) -> Result<(f64, f64), TrainError> {
    let device = device.clone().without_autodiff();
    let model = model.valid();
    let k = meta.config.k();
    let (mut loss_sum, mut correct, mut count) = (0.0f64, 0usize, 0usize);
    for_each_batch(windows, batch_size, true, |batch| {
        let logits = model.forward(input_for(meta, batch, &device)?);
        let loss: f32 = batch_loss(logits.clone(), batch, k, &device)?.into_scalar();
        loss_sum += loss as f64 * batch.len() as f64;
        let z: Vec<f32> = logits
            .into_data()
            .try_to_vec::<f32>()
            .map_err(|e| TrainError::Data(format!("{e:?}")))?;
        for (w, row) in batch.iter().zip(z.chunks(k)) {
            for (h, (y, zv)) in w.labels.iter().zip(row).enumerate() {
                if w.scores(h) {
                    correct += usize::from((*zv > 0.0) == (*y > 0.5));
                    count += 1;
                }
            }
        }
        Ok(())
    })?;
    let n = windows.len().max(1) as f64;
    Ok((loss_sum / n, correct as f64 / count.max(1) as f64))
}

/// The seed of burn's generator for epoch `epoch` of a run seeded `seed`:
/// each epoch's dropout depends on these two only, so a run resumed at an
/// epoch draws what an uninterrupted one draws there.
pub fn epoch_seed(seed: u64, epoch: usize) -> u64 {
    // splitmix64 of the pair
    let mut z = seed ^ (epoch as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Gives every parameter of `model` an id fixed by its position (burn draws
/// them at random). The optimizer states are keyed by these ids, and the
/// model file stores them: with fixed ids a checkpoint's states find their
/// parameters again, and two runs with the same seed write the same bytes.
pub fn stable_param_ids(model: Emp) -> Emp {
    struct Renumber(u64);
    impl ModuleMapper for Renumber {
        fn map_float<const D: usize>(&mut self, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
            let (_, tensor, mapper) = param.consume();
            self.0 += 1;
            Param::from_mapped_value(ParamId::from(self.0), tensor, mapper)
        }
    }
    model.map(&mut Renumber(0xFA11_0000_0000))
}

/// An epoch's progress in the log (the library draws nothing): a line at
/// every tenth of its steps, with the mean loss so far and the time left at
/// the pace so far; at debug level when progress was not asked for.
struct EpochProgress {
    epoch: usize,
    max_epochs: usize,
    steps: usize,
    started: std::time::Instant,
    next_tenth: usize,
    shown: bool,
}

impl EpochProgress {
    fn new(epoch: usize, max_epochs: usize, steps: usize, shown: bool) -> EpochProgress {
        EpochProgress {
            epoch,
            max_epochs,
            steps,
            started: std::time::Instant::now(),
            next_tenth: 1,
            shown,
        }
    }

    fn step(&mut self, done: usize, mean_loss: f64) {
        if self.steps == 0 || done * 10 < self.next_tenth * self.steps {
            return;
        }
        self.next_tenth = done * 10 / self.steps + 1;
        let elapsed = self.started.elapsed().as_secs_f64();
        let left = elapsed / done as f64 * (self.steps - done) as f64;
        let line = format!(
            "epoch {}/{}: {done}/{} steps, loss {mean_loss:.4}, {:.0} s left in the epoch",
            self.epoch, self.max_epochs, self.steps, left
        );
        if self.shown {
            tracing::info!("{line}");
        } else {
            tracing::debug!("{line}");
        }
    }
}

/// Trains `meta.ablation` on `source`. `meta` carries the config and input
/// description; its standardisation is computed from the first training epoch.
///
/// burn's random generator (initialisation, dropout) is global to the
/// process, so one training at a time holds it: two `fit` calls in one process
/// run one after the other, each deterministic for its seed.
pub fn fit(
    mut meta: ModelMeta,
    source: &mut dyn EpochSource,
    opts: &FitOptions,
) -> Result<(ModelMeta, Emp), TrainError> {
    static RNG_OWNER: std::sync::Mutex<()> = std::sync::Mutex::new(());
    let _rng = RNG_OWNER
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    keep_freed_memory();
    let base = opts.device.device()?;
    let device = base.clone().autodiff();
    device.seed(opts.seed);
    let cfg: ModelConfig = meta.config.clone();
    let ablation: Ablation = meta.ablation;
    let k = cfg.k();
    let mut model = stable_param_ids(Emp::new(&cfg, ablation, &device));
    let adam = |r: Rate| -> ModuleOptimizer { FusedAdam::new(Some(r.weight_decay)).init() };
    let r = opts.rates;
    let (mut opt_m, mut opt_t, mut opt_v, mut opt_c) = (
        adam(r.motion),
        adam(r.trajectory),
        adam(r.vision),
        adam(r.classifier),
    );
    meta.seed = opts.seed;
    meta.history.clear();

    let checkpoint = opts.checkpoint.as_ref().map(Checkpoint::new);
    let resumed = match &checkpoint {
        Some(c) => c.load(&mut meta, &device, &base)?,
        None => None,
    };
    let validation = source.validation()?;
    let mut first_epoch = None;
    let mut best: Option<(f64, Emp)> = None;
    let mut since_best = 0usize;
    let mut start = 1;
    let mut stopped = false;
    match resumed {
        Some(r) => {
            model = r.model;
            let load = |opt: ModuleOptimizer, bytes: burn::tensor::Bytes| {
                opt.from_bytes(bytes)
                    .map_err(|e| TrainError::Data(format!("checkpoint optimizer state: {e}")))
            };
            let [m, t, v, c] = r.optimizers;
            (opt_m, opt_t, opt_v, opt_c) = (
                load(opt_m, m)?,
                load(opt_t, t)?,
                load(opt_v, v)?,
                load(opt_c, c)?,
            );
            let (best_epoch, best_loss, best_model) = r.best;
            best = Some((best_loss, best_model));
            meta.best_epoch = best_epoch;
            meta.history = r.history;
            since_best = r.since_best;
            start = r.epoch + 1;
            stopped = r.stopped;
            if opts.progress {
                tracing::info!(
                    "resuming from the checkpoint in {} after epoch {}",
                    opts.checkpoint.as_ref().expect("resumed").display(),
                    r.epoch
                );
            }
        }
        None => {
            let first = source.train_epoch(1)?;
            if first.is_empty() {
                return Err(TrainError::Data(
                    "the training split gave no windows".into(),
                ));
            }
            match &opts.init {
                Some(path) => {
                    let (_, start) = load_emp(path, &device)?;
                    model = stable_param_ids(start);
                }
                None => standardisation(&mut meta, first.as_ref())?,
            }
            first_epoch = Some(first);
        }
    }
    for epoch in start..=opts.max_epochs {
        if stopped {
            break;
        }
        let windows = match first_epoch.take() {
            Some(w) => w,
            None => source.train_epoch(epoch)?,
        };
        device.seed(epoch_seed(opts.seed, epoch));
        let b = opts.batch_size.max(1);
        let n = windows.len();
        let steps = n.div_ceil(b);
        let mut progress = EpochProgress::new(epoch, opts.max_epochs, steps, opts.progress);
        let mut loss_sum = 0.0f64;
        for step in 0..steps {
            let batch = windows.build(step * b..((step + 1) * b).min(n), true)?;
            let input = input_for(&meta, &batch, &device)?;
            let loss = batch_loss(model.forward(input), &batch, k, &device)?;
            let len = batch.len();
            drop(batch);
            let loss_value: f32 = loss.clone().into_scalar();
            loss_sum += loss_value as f64 * len as f64;
            let mut grads = loss.backward();
            let g_m = GradientsParams::from_module(&mut grads, &model.motion);
            let g_c = GradientsParams::from_module(&mut grads, &model.classifier);
            let g_t = model
                .plan
                .as_ref()
                .map(|p| GradientsParams::from_module(&mut grads, p));
            let g_v = model
                .vision
                .as_ref()
                .map(|v| GradientsParams::from_module(&mut grads, v));
            let Emp {
                motion,
                plan,
                vision,
                classifier,
            } = model;
            model = Emp {
                motion: opt_m.step(r.motion.lr, motion, g_m),
                plan: plan
                    .zip(g_t)
                    .map(|(p, g)| opt_t.step(r.trajectory.lr, p, g)),
                vision: vision.zip(g_v).map(|(v, g)| opt_v.step(r.vision.lr, v, g)),
                classifier: opt_c.step(r.classifier.lr, classifier, g_c),
            };
            progress.step(step + 1, loss_sum / ((step + 1) * b).min(n) as f64);
        }
        drop(windows);
        let train_loss = loss_sum / n.max(1) as f64;
        let (val_loss, val_accuracy) =
            evaluate_loss(&model, &meta, validation.as_ref(), 16, &base)?;
        meta.history.push(EpochRecord {
            epoch,
            train_loss,
            val_loss,
            val_accuracy,
        });
        if opts.progress {
            tracing::info!(
                "epoch {epoch}: train loss {train_loss:.4}, val loss {val_loss:.4}, val acc {val_accuracy:.3}"
            );
        }
        tracing::debug!(epoch, train_loss, val_loss, val_accuracy, "epoch done");
        if best.as_ref().is_none_or(|(b, _)| val_loss < *b) {
            best = Some((val_loss, model.valid()));
            meta.best_epoch = epoch;
            since_best = 0;
        } else {
            since_best += 1;
            if since_best >= opts.patience {
                tracing::info!(
                    "early stop: no better validation loss for {} epochs",
                    opts.patience
                );
                stopped = true;
            }
        }
        if let Some(c) = &checkpoint {
            let (_, best_model) = best.as_ref().expect("set above");
            c.save(&EpochState {
                epoch,
                meta: &meta,
                model: &model,
                best: (meta.best_epoch, best_model),
                since_best,
                stopped: stopped || epoch == opts.max_epochs,
                optimizers: [&opt_m, &opt_t, &opt_v, &opt_c],
            })?;
        }
    }
    let (_, best_model) =
        best.ok_or_else(|| TrainError::Data("no epoch ran (max_epochs = 0)".into()))?;
    // Callers evaluate and save on the CPU.
    let best_model = if opts.device == TrainDevice::Cpu {
        best_model
    } else {
        best_model.to_device(&cpu_device())
    };
    Ok((meta, best_model))
}
