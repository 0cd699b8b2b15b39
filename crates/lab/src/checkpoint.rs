//! Checkpoints of a training run, so that `fall-guard-lab train` can be stopped
//! at any point and, rerun with the same arguments, resume from the last
//! completed epoch.
//!
//! A run's checkpoint directory (`<out>.ckpt/` by default, `train
//! --checkpoint-dir`) holds `args.json`, what the run was started with (its
//! arguments and the data set's manifest), and one directory per network
//! the run trains (`model/`, or `h15/`, `h30/` ... with `--per-horizon`).
//! After each epoch [`Checkpoint::save`] writes into a network's directory
//! the network after that epoch (`model-e<E>.bpk`, with its
//! standardisation), the best network so far (`best-e<B>.bpk`, written
//! when it changes), the four Adam states (`adam-e<E>-<encoder>.bpk`), then
//! `state.json` (the epoch, the history, the best epoch, the epochs since
//! it, whether training stopped): each file written as `NAME.partial` and
//! renamed. `state.json` names the files it goes with, so a run stopped
//! while an epoch's files are being written resumes from the epoch before;
//! files it does not name are removed. Floats are stored as their bits:
//! the resumed run continues from the very values.
//!
//! Resuming gives the model an uninterrupted run gives: the window sampler
//! replays its earlier epochs' draws (picks only), burn's generator is
//! reseeded at every epoch from the seed and the epoch number
//! ([`super::fit::epoch_seed`]), and parameter ids are fixed by position
//! ([`super::fit::stable_param_ids`]), so the optimizer states, keyed by
//! them, find their parameters again.

use std::path::{Path, PathBuf};

use burn::optim::ModuleOptimizer;
use burn::prelude::*;
use burn::tensor::Bytes;
use serde::{Deserialize, Serialize};

use crate::error::TrainError;
use fall_guard_runtime::model::file::{load_emp, partial_path, save_model};
use fall_guard_runtime::model::{Emp, EpochRecord, ModelMeta};

/// The encoders, each with its own Adam, in the order of the optimizers.
pub const ENCODERS: [&str; 4] = ["motion", "trajectory", "vision", "classifier"];

/// One epoch of the history, floats as bits.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
struct EpochBits {
    epoch: usize,
    train_loss: u64,
    val_loss: u64,
    val_accuracy: u64,
}

impl From<&EpochRecord> for EpochBits {
    fn from(r: &EpochRecord) -> Self {
        EpochBits {
            epoch: r.epoch,
            train_loss: r.train_loss.to_bits(),
            val_loss: r.val_loss.to_bits(),
            val_accuracy: r.val_accuracy.to_bits(),
        }
    }
}

impl From<EpochBits> for EpochRecord {
    fn from(b: EpochBits) -> Self {
        EpochRecord {
            epoch: b.epoch,
            train_loss: f64::from_bits(b.train_loss),
            val_loss: f64::from_bits(b.val_loss),
            val_accuracy: f64::from_bits(b.val_accuracy),
        }
    }
}

/// The standardisation statistics of a network, as bits.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
struct StatsBits {
    joint_mean: Vec<u32>,
    joint_std: Vec<u32>,
    plan_mean: Vec<u32>,
    plan_std: Vec<u32>,
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

fn floats(v: &[u32]) -> Vec<f32> {
    v.iter().map(|&x| f32::from_bits(x)).collect()
}

/// `state.json`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
struct StateFile {
    /// Epochs completed.
    epoch: usize,
    best_epoch: usize,
    since_best: usize,
    /// Training is over (early stop, or the last epoch ran): the best
    /// network is what is left to write.
    stopped: bool,
    history: Vec<EpochBits>,
    stats: StatsBits,
}

/// Where a training resumes.
pub struct Resumed {
    /// Epochs completed.
    pub epoch: usize,
    /// The network after that epoch, on the training device.
    pub model: Emp,
    /// The best network so far (inference, on the base device), its epoch
    /// and its validation loss.
    pub best: (usize, f64, Emp),
    /// Epochs since the best.
    pub since_best: usize,
    /// Whether training had stopped.
    pub stopped: bool,
    /// The history so far.
    pub history: Vec<EpochRecord>,
    /// The Adam states, in [`ENCODERS`] order, to load into the optimizers.
    pub optimizers: [Bytes; 4],
}

/// What [`Checkpoint::save`] writes after an epoch.
pub struct EpochState<'a> {
    pub epoch: usize,
    pub meta: &'a ModelMeta,
    pub model: &'a Emp,
    /// The best network, written when it is this epoch's.
    pub best: (usize, &'a Emp),
    pub since_best: usize,
    pub stopped: bool,
    /// In [`ENCODERS`] order.
    pub optimizers: [&'a ModuleOptimizer; 4],
}

/// One network's checkpoint directory.
#[derive(Debug, Clone)]
pub struct Checkpoint {
    dir: PathBuf,
}

fn data_err(what: String) -> TrainError {
    TrainError::Data(what)
}

fn io_err(path: &Path, e: impl std::fmt::Display) -> TrainError {
    data_err(format!("checkpoint {}: {e}", path.display()))
}

/// Writes `bytes` to `path` through `NAME.partial`, renamed once complete.
pub fn write_atomically(path: &Path, bytes: &[u8]) -> Result<(), TrainError> {
    let tmp = partial_path(path);
    let err = |p: &Path, e: std::io::Error| data_err(format!("writing {}: {e}", p.display()));
    std::fs::write(&tmp, bytes).map_err(|e| err(&tmp, e))?;
    std::fs::rename(&tmp, path).map_err(|e| err(path, e))
}

impl Checkpoint {
    /// The checkpoint in `dir` (created when first saved).
    pub fn new(dir: impl Into<PathBuf>) -> Checkpoint {
        Checkpoint { dir: dir.into() }
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    fn state_path(&self) -> PathBuf {
        self.dir.join("state.json")
    }

    fn model_path(&self, epoch: usize) -> PathBuf {
        self.dir.join(format!("model-e{epoch}.bpk"))
    }

    fn best_path(&self, epoch: usize) -> PathBuf {
        self.dir.join(format!("best-e{epoch}.bpk"))
    }

    fn adam_path(&self, epoch: usize, encoder: &str) -> PathBuf {
        self.dir.join(format!("adam-e{epoch}-{encoder}.bpk"))
    }

    /// Whether an epoch was saved here.
    pub fn exists(&self) -> bool {
        self.state_path().is_file()
    }

    fn read_state(&self) -> Result<Option<StateFile>, TrainError> {
        let path = self.state_path();
        match std::fs::read(&path) {
            Ok(bytes) => serde_json::from_slice(&bytes)
                .map(Some)
                .map_err(|e| io_err(&path, format!("not a checkpoint state: {e}"))),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
            Err(e) => Err(io_err(&path, e)),
        }
    }

    /// Reads the last saved epoch, if any: the networks on `device` (the
    /// training one, autodiff) and `base` (the best one), `meta` given the
    /// saved standardisation and history.
    pub fn load(
        &self,
        meta: &mut ModelMeta,
        device: &Device,
        base: &Device,
    ) -> Result<Option<Resumed>, TrainError> {
        let Some(state) = self.read_state()? else {
            return Ok(None);
        };
        let (saved, model) = load_emp(&self.model_path(state.epoch), device)?;
        if saved.config != meta.config || saved.ablation != meta.ablation {
            return Err(data_err(format!(
                "checkpoint {}: its network ({} {:?}) is not the one this run trains",
                self.dir.display(),
                saved.ablation,
                saved.config
            )));
        }
        let (_, best) = load_emp(&self.best_path(state.best_epoch), base)?;
        let read = |encoder: &str| {
            let path = self.adam_path(state.epoch, encoder);
            std::fs::read(&path)
                .map(Bytes::from_bytes_vec)
                .map_err(|err| io_err(&path, err))
        };
        let [m, t, v, c] = ENCODERS;
        let optimizers = [read(m)?, read(t)?, read(v)?, read(c)?];
        let history: Vec<EpochRecord> = state.history.iter().map(|&b| b.into()).collect();
        let best_loss = history
            .get(state.best_epoch.wrapping_sub(1))
            .map_or(f64::NAN, |h| h.val_loss);
        meta.joint_mean = floats(&state.stats.joint_mean);
        meta.joint_std = floats(&state.stats.joint_std);
        meta.plan_mean = floats(&state.stats.plan_mean);
        meta.plan_std = floats(&state.stats.plan_std);
        meta.history = history.clone();
        meta.best_epoch = state.best_epoch;
        self.remove_unnamed(&state);
        Ok(Some(Resumed {
            epoch: state.epoch,
            model,
            best: (state.best_epoch, best_loss, best),
            since_best: state.since_best,
            stopped: state.stopped,
            history,
            optimizers,
        }))
    }

    /// Saves an epoch: its files first, then `state.json`, which names them;
    /// then the files of other epochs go.
    pub fn save(&self, s: &EpochState<'_>) -> Result<(), TrainError> {
        std::fs::create_dir_all(&self.dir).map_err(|e| io_err(&self.dir, e))?;
        save_model(&self.model_path(s.epoch), s.meta, s.model)?;
        let best_path = self.best_path(s.best.0);
        if s.best.0 == s.epoch || !best_path.is_file() {
            save_model(&best_path, s.meta, s.best.1)?;
        }
        for (opt, encoder) in s.optimizers.iter().zip(ENCODERS) {
            let path = self.adam_path(s.epoch, encoder);
            let bytes = opt.into_bytes().map_err(|e| io_err(&path, e))?;
            write_atomically(&path, &bytes)?;
        }
        let state = StateFile {
            epoch: s.epoch,
            best_epoch: s.best.0,
            since_best: s.since_best,
            stopped: s.stopped,
            history: s.meta.history.iter().map(EpochBits::from).collect(),
            stats: StatsBits {
                joint_mean: bits(&s.meta.joint_mean),
                joint_std: bits(&s.meta.joint_std),
                plan_mean: bits(&s.meta.plan_mean),
                plan_std: bits(&s.meta.plan_std),
            },
        };
        let json = serde_json::to_vec_pretty(&state).map_err(|e| io_err(&self.dir, e))?;
        write_atomically(&self.state_path(), &json)?;
        self.remove_unnamed(&state);
        Ok(())
    }

    /// The files `state` goes with, itself included.
    fn named(&self, state: &StateFile) -> Vec<PathBuf> {
        let mut files = vec![
            self.state_path(),
            self.model_path(state.epoch),
            self.best_path(state.best_epoch),
        ];
        files.extend(ENCODERS.iter().map(|e| self.adam_path(state.epoch, e)));
        files
    }

    /// Removes the files of epochs `state` does not name, and half-written
    /// ones: what an epoch left that the last saved one replaces.
    fn remove_unnamed(&self, state: &StateFile) {
        self.remove_ours_except(&self.named(state));
    }

    fn remove_ours_except(&self, keep: &[PathBuf]) {
        let Ok(entries) = std::fs::read_dir(&self.dir) else {
            return;
        };
        for entry in entries.flatten() {
            let path = entry.path();
            let name = entry.file_name().to_string_lossy().into_owned();
            let ours = name.ends_with(".partial")
                || ["model-e", "best-e", "adam-e"]
                    .iter()
                    .any(|p| name.starts_with(p) && name.ends_with(".bpk"));
            if ours && !keep.contains(&path) {
                if let Err(e) = std::fs::remove_file(&path) {
                    tracing::warn!(path = %path.display(), error = %e, "cannot remove an old checkpoint file");
                }
            }
        }
    }

    /// Removes this checkpoint: `state.json` first (a run stopped half-way
    /// through finds no epoch and starts afresh), then the files of the
    /// epochs, then the directory if it is left empty.
    pub fn remove(&self) -> Result<(), TrainError> {
        match std::fs::remove_file(self.state_path()) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => return Err(io_err(&self.state_path(), e)),
        }
        self.remove_ours_except(&[]);
        let _ = std::fs::remove_dir(&self.dir);
        Ok(())
    }
}
