//! Training is deterministic for a seed on one machine, and a run stopped
//! part-way and resumed from its checkpoint trains the same model. In a
//! process of its own: burn's random generator is global to a process, and
//! other tests creating networks at the same time would draw from it.

use std::ops::Range;

use fall_guard_lab::{fit, EpochSource, FitOptions, LabeledWindow, TrainError, WindowSet};
use fall_guard_runtime::model::{save_model, Ablation, ModelConfig, ModelMeta};
#[path = "support/windows.rs"]
mod windows;
use windows::{small_config, RampEpisodes};

fn names(cfg: &ModelConfig) -> Vec<String> {
    (0..cfg.n_joints).map(|i| format!("j{i}")).collect()
}

#[test]
fn training_is_deterministic_for_a_seed() {
    let cfg = small_config();
    let run = |seed: u64| {
        let meta = ModelMeta::new(cfg.clone(), Ablation::MP, 30.0, names(&cfg));
        let mut source = RampEpisodes {
            cfg: cfg.clone(),
            per_epoch: 16,
            seed: 3,
        };
        let opts = FitOptions {
            seed,
            max_epochs: 2,
            progress: false,
            ..FitOptions::default()
        };
        fit(meta, &mut source, &opts).expect("fit").0.history
    };
    let first = run(7);
    assert_eq!(first, run(7), "same seed, same history");
    assert_ne!(first, run(8), "another seed, another history");
}

/// An epoch whose windows stop coming from `fail_from` on: the process
/// stopped part-way through it.
struct Stopped {
    inner: Box<dyn WindowSet>,
    fail_from: usize,
}

impl WindowSet for Stopped {
    fn len(&self) -> usize {
        self.inner.len()
    }
    fn build(&self, range: Range<usize>, frames: bool) -> Result<Vec<LabeledWindow>, TrainError> {
        if range.end > self.fail_from {
            return Err(TrainError::Data("stopped".into()));
        }
        self.inner.build(range, frames)
    }
}

/// The ramp task, stopped in the middle of epoch `stop_in`.
struct StopsIn {
    source: RampEpisodes,
    stop_in: usize,
}

impl EpochSource for StopsIn {
    fn train_epoch(&mut self, epoch: usize) -> Result<Box<dyn WindowSet>, TrainError> {
        let inner = self.source.train_epoch(epoch)?;
        if epoch == self.stop_in {
            return Ok(Box::new(Stopped {
                fail_from: inner.len() / 2,
                inner,
            }));
        }
        Ok(inner)
    }
    fn validation(&mut self) -> Result<Box<dyn WindowSet>, TrainError> {
        self.source.validation()
    }
}

/// Stopped during epoch 2 and run again with the same options, training
/// resumes after epoch 1 and ends with the model an uninterrupted run
/// ends with: the same file, byte for byte, and the same history.
#[test]
fn a_run_stopped_and_resumed_trains_the_uninterrupted_model() {
    let cfg = small_config();
    let dir = tempfile::tempdir().unwrap();
    let ckpt = dir.path().join("run.ckpt");
    let meta = ModelMeta::new(cfg.clone(), Ablation::MP, 30.0, names(&cfg));
    let source = || RampEpisodes {
        cfg: cfg.clone(),
        per_epoch: 32,
        seed: 3,
    };
    let opts = |checkpoint: Option<std::path::PathBuf>| FitOptions {
        seed: 11,
        max_epochs: 3,
        patience: 5,
        progress: false,
        checkpoint,
        ..FitOptions::default()
    };
    let written = |name: &str, meta: &ModelMeta, model| {
        let path = dir.path().join(name);
        save_model(&path, meta, model).unwrap();
        std::fs::read(path).unwrap()
    };

    let (meta_a, model_a) = fit(meta.clone(), &mut source(), &opts(None)).unwrap();
    assert_eq!(meta_a.history.len(), 3);
    let uninterrupted = written("a.bpk", &meta_a, &model_a);

    let mut stopping = StopsIn {
        source: source(),
        stop_in: 2,
    };
    let err = fit(meta.clone(), &mut stopping, &opts(Some(ckpt.clone()))).unwrap_err();
    assert!(err.to_string().contains("stopped"), "{err}");
    let files: Vec<String> = std::fs::read_dir(&ckpt)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert!(
        files.contains(&"model-e1.bpk".to_string()) && !files.iter().any(|f| f.contains("-e2")),
        "{files:?}"
    );

    let (meta_b, model_b) = fit(meta.clone(), &mut source(), &opts(Some(ckpt.clone()))).unwrap();
    assert_eq!(meta_b.history, meta_a.history);
    assert_eq!(meta_b.best_epoch, meta_a.best_epoch);
    let resumed = written("b.bpk", &meta_b, &model_b);
    assert!(
        resumed == uninterrupted,
        "the resumed run wrote another model"
    );

    // A finished run's checkpoint resumes to the end: the same model again,
    // without training (a source that gives no windows would fail).
    struct Nothing;
    impl EpochSource for Nothing {
        fn train_epoch(&mut self, _: usize) -> Result<Box<dyn WindowSet>, TrainError> {
            Err(TrainError::Data("asked for an epoch".into()))
        }
        fn validation(&mut self) -> Result<Box<dyn WindowSet>, TrainError> {
            Ok(Box::new(Vec::<LabeledWindow>::new()))
        }
    }
    let (meta_c, model_c) = fit(meta, &mut Nothing, &opts(Some(ckpt))).unwrap();
    assert!(written("c.bpk", &meta_c, &model_c) == uninterrupted);
}
