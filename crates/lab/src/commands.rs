//! The `train` and `eval` subcommands: argument structs and their run
//! functions. Windows come from the data plane (`dataset`, `sampler`,
//! `window`): the same code the daemon uses to build its windows.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use crate::error::{refused, CommandResult, Doing};
use rand::rngs::StdRng;
use rand::seq::SliceRandom;
use rand::SeedableRng;

use super::checkpoint::{write_atomically, Checkpoint};
use super::device::TrainDevice;
use super::eval::{predict, report, EvalReport, Predictions};
use super::fit::{
    fit, for_each_batch, EncoderRates, EpochSource, FitOptions, LabeledWindow, WindowSet,
    WindowTruth,
};
use super::logreg::LogRegModel;
use super::plots;
use crate::dataset::{data_name, Dataset, Split};
use crate::error::TrainError;
use crate::sampler::{labels_at, Protocol, SamplerConfig, SamplerError, WindowSampler};
use fall_guard_runtime::model::{
    save_model, Ablation, Convolutions, LoadedModel, ModelConfig, ModelMeta, ProjectionWeights,
    StreamingForecaster, TrajectoryInput,
};
use fall_guard_runtime::window::{EpisodeTicks, Streams, WindowSpec};

/// Windows built at a time by `eval` and `calibrate` (each 2.9 MB as `f32`
/// for N = 60 at 64 x 64): what bounds their memory, whatever the split.
pub const EVAL_BATCH: usize = 16;

/// Arguments of `fall-guard-lab train`.
#[derive(Debug, Clone)]
pub struct TrainOptions {
    /// Data set directory (recordings + manifest.json).
    pub data: PathBuf,
    /// P, MP, EP, EMP, or logreg (the logistic-regression baseline).
    pub ablation: String,
    /// Network configuration: lite or paper.
    pub config: String,
    /// Seed of initialisation, dropout and window sampling.
    pub seed: u64,
    /// Output model file.
    pub out: PathBuf,
    /// At most this many epochs.
    pub epochs: usize,
    /// Early-stopping patience on validation loss, epochs.
    pub patience: usize,
    /// Windows per step.
    pub batch: usize,
    /// Learning-rate table: sim (SimP column) or robot (RP column).
    pub rates: String,
    /// The vision encoder's learning rate in place of the table's.
    pub vision_lr: Option<f64>,
    /// Every learning rate multiplied by this (after `vision_lr`): 1 to
    /// train, less to fine-tune a trained network without undoing it.
    pub lr_scale: f64,
    /// Window length N, ticks.
    pub n_ticks: usize,
    /// Horizons, ticks, comma-separated.
    pub horizons: Vec<usize>,
    /// Tick rate, Hz.
    pub rate_hz: f64,
    /// Frame side, pixels.
    pub frame_size: u32,
    /// Joint names in model order, comma-separated (default: the Poppy Humanoid's 25).
    pub joint_names: Option<Vec<String>>,
    /// What the data is, stored in the model file.
    pub trained_on: String,
    /// How training and validation windows are drawn: `deployment` (one set
    /// for all horizons, balanced at the middle one) or `paper` (one set per
    /// horizon, balanced at it, windows ending at or before its stop line).
    pub protocol: Protocol,
    /// Train one network per horizon P (each with that one horizon, its plan
    /// reaching P ticks ahead), written next to --out as `NAME.h<P>.EXT`.
    pub per_horizon: bool,
    /// What the trajectory encoder reads: `planned` (past and future plan),
    /// `historical-only` (past N plan ticks), `real-position` (the measured
    /// joints). Stored in the model file.
    pub trajectory: TrajectoryInput,
    /// Where the network trains: cpu, cuda, cuda:N (feature `cuda`) or wgpu
    /// (feature `wgpu`). The model file is the same whichever trains it.
    pub device: TrainDevice,
    /// Where the checkpoints of the run go (default `<out>.ckpt`, next to
    /// the output): one per epoch; a rerun with the same arguments resumes
    /// from the last.
    pub checkpoint_dir: Option<PathBuf>,
    /// No progress bar.
    pub quiet: bool,
    /// Fine-tune this model file: start from its weights, keep its network
    /// sizes, trajectory input and standardisation (`--config`, `--n-ticks`,
    /// `--horizons` and `--trajectory` are taken from it).
    pub init: Option<PathBuf>,
}

/// Arguments of `fall-guard-lab eval`.
#[derive(Debug, Clone)]
pub struct EvalOptions {
    /// Model file (network or logreg baseline).
    pub model: PathBuf,
    /// More model files of other seeds: metrics become mean ± std.
    pub seeds: Vec<PathBuf>,
    /// Data set directory.
    pub data: Option<PathBuf>,
    /// Split to evaluate.
    pub split: String,
    /// Output directory (metrics.json, metrics.md, PNG plots).
    pub out: Option<PathBuf>,
    /// Seed of the test-window sampler.
    pub sample_seed: u64,
    /// Windows drawn per episode (each an independent draw; under the paper
    /// protocol, per episode and horizon).
    pub draws: usize,
    /// The protocol of the plots and of the report's top-level `horizons`;
    /// the report has a section for each protocol either way.
    pub protocol: Protocol,
    /// Offline per-tick forecast of one recording (with --per-tick-out).
    pub recording: Option<PathBuf>,
    /// JSON lines: one forecast per tick of --recording.
    pub per_tick_out: Option<PathBuf>,
    /// How each network's classifier input projection is held.
    pub projection: ProjectionWeights,
    /// How each network's trajectory convolutions multiply.
    pub convolutions: Convolutions,
}

impl EvalOptions {
    /// The offline per-tick forecast of one recording by one model file, the
    /// rest at the command's defaults: `fall-guard-lab eval --model MODEL
    /// --recording RECORDING --per-tick-out OUT --projection PROJECTION`.
    pub fn per_tick(
        model: PathBuf,
        recording: PathBuf,
        out: PathBuf,
        projection: ProjectionWeights,
    ) -> EvalOptions {
        EvalOptions {
            model,
            seeds: Vec::new(),
            data: None,
            split: "test".into(),
            out: None,
            sample_seed: 12345,
            draws: 1,
            protocol: Protocol::Deployment,
            recording: Some(recording),
            per_tick_out: Some(out),
            projection,
            convolutions: Convolutions::F32,
        }
    }

    /// The same, the trajectory convolutions as `convolutions` says
    /// (`--convolutions`).
    pub fn with_convolutions(mut self, convolutions: Convolutions) -> EvalOptions {
        self.convolutions = convolutions;
        self
    }
}

/// The streams a model reads: its ablation's, and the plan only when its
/// trajectory input is cut from the plan (`None`: the logistic baseline,
/// joints + plan).
pub fn needs_of(ablation: Option<Ablation>, trajectory: TrajectoryInput) -> Streams {
    match ablation {
        Some(a) => Streams {
            joints: true,
            plan: a.uses_plan() && trajectory.reads_plan(),
            camera: a.uses_vision(),
        },
        // logreg: joints + plan
        None => Streams {
            joints: true,
            plan: true,
            camera: false,
        },
    }
}

/// The streams `meta`'s network reads.
pub fn needs_of_model(meta: &ModelMeta) -> Streams {
    needs_of(Some(meta.ablation), meta.config.trajectory)
}

/// The episodes of one split, read once (windows of both protocols are cut
/// from them).
pub fn load_split_episodes(
    dataset: &Dataset,
    split: Split,
    spec: &WindowSpec,
    needs: Streams,
) -> Result<Arc<Vec<EpisodeTicks>>, TrainError> {
    let episodes = dataset.load_split(split, spec, needs).map_err(|e| {
        TrainError::Data(format!("{} split of {}: {e}", split, dataset.dir.display()))
    })?;
    Ok(Arc::new(episodes))
}

/// The sampler seed of the paper protocol's window set of horizon `h`
/// ticks: it depends on the horizon's length, not on its position in the
/// model's list, so a one-horizon model (`train --per-horizon`) is scored
/// on the very windows the all-horizon model is scored on at that horizon.
fn paper_seed(seed: u64, horizon_ticks: usize) -> u64 {
    seed ^ (horizon_ticks as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15)
}

/// One drawn window of a split: its episode, where it ends, its labels,
/// the horizon it is scored at.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SplitPick {
    /// Index of the episode in its split.
    pub episode: usize,
    pub end_tick: i64,
    /// Every horizon's truth: fallen at `end_tick + h`.
    pub labels: Vec<bool>,
    /// See [`LabeledWindow::scored_horizon`].
    pub scored_horizon: Option<usize>,
}

/// Windows drawn from a split ([`SplitWindows::epoch`]): the picks, their
/// arrays built a batch at a time from the split's episodes ([`WindowSet`]).
#[derive(Clone)]
pub struct SplitEpoch {
    episodes: Arc<Vec<EpisodeTicks>>,
    spec: WindowSpec,
    needs: Streams,
    picks: Vec<SplitPick>,
}

impl SplitEpoch {
    /// The windows, in order.
    pub fn picks(&self) -> &[SplitPick] {
        &self.picks
    }

    /// Appends the windows of another draw of the same split.
    pub fn extend(&mut self, other: SplitEpoch) {
        debug_assert!(Arc::ptr_eq(&self.episodes, &other.episodes));
        self.picks.extend(other.picks);
    }

    fn window(&self, pick: &SplitPick, needs: Streams) -> Result<LabeledWindow, TrainError> {
        let ep = &self.episodes[pick.episode];
        let w = ep
            .window_ending_at(pick.end_tick, &self.spec, needs)
            .map_err(|e| {
                TrainError::Data(format!(
                    "{} at tick {}: {e}",
                    ep.path.display(),
                    pick.end_tick
                ))
            })?;
        Ok(LabeledWindow {
            joints: w.joints,
            plan: w.plan,
            frames: w.frames,
            labels: labels_f32(&pick.labels),
            episode: pick.episode,
            scored_horizon: pick.scored_horizon,
        })
    }
}

fn labels_f32(labels: &[bool]) -> Vec<f32> {
    labels.iter().map(|&b| f32::from(u8::from(b))).collect()
}

impl WindowSet for SplitEpoch {
    fn len(&self) -> usize {
        self.picks.len()
    }

    fn build(
        &self,
        range: std::ops::Range<usize>,
        frames: bool,
    ) -> Result<Vec<LabeledWindow>, TrainError> {
        let needs = Streams {
            camera: self.needs.camera && frames,
            ..self.needs
        };
        let picks = self.picks.get(range.clone()).ok_or_else(|| {
            TrainError::Data(format!("windows {range:?} of {}", self.picks.len()))
        })?;
        picks.iter().map(|p| self.window(p, needs)).collect()
    }

    fn truths(&self) -> Result<Vec<WindowTruth>, TrainError> {
        Ok(self
            .picks
            .iter()
            .map(|p| WindowTruth {
                labels: labels_f32(&p.labels),
                episode: p.episode,
                scored_horizon: p.scored_horizon,
            })
            .collect())
    }
}

/// Labelled windows of a split under one [`Protocol`]: per epoch, one
/// window per usable episode (deployment), or one per usable episode and
/// horizon (paper: each horizon's own balanced set, its windows marked with
/// [`LabeledWindow::scored_horizon`], the union shuffled).
pub struct SplitWindows {
    episodes: Arc<Vec<EpisodeTicks>>,
    /// One sampler per window set, with the horizon index it is scored at
    /// (`None`: all horizons).
    sets: Vec<(Option<usize>, WindowSampler)>,
    horizons: Vec<usize>,
    spec: WindowSpec,
    needs: Streams,
    rng: StdRng,
}

impl SplitWindows {
    /// Loads `split` of `dataset` for `spec` and draws windows under `protocol`.
    pub fn load(
        dataset: &Dataset,
        split: Split,
        spec: &WindowSpec,
        needs: Streams,
        horizons: &[usize],
        seed: u64,
        protocol: Protocol,
    ) -> Result<Self, TrainError> {
        let episodes = load_split_episodes(dataset, split, spec, needs)?;
        Self::new(episodes, spec, needs, horizons, seed, protocol).map_err(|e| {
            TrainError::Data(format!("{} split of {}: {e}", split, dataset.dir.display()))
        })
    }

    /// Windows of episodes already read.
    pub fn new(
        episodes: Arc<Vec<EpisodeTicks>>,
        spec: &WindowSpec,
        needs: Streams,
        horizons: &[usize],
        seed: u64,
        protocol: Protocol,
    ) -> Result<Self, SamplerError> {
        let sets = match protocol {
            Protocol::Deployment => {
                let mut cfg = SamplerConfig::new(spec.n_ticks, horizons.to_vec());
                cfg.needs = needs;
                vec![(None, WindowSampler::new(&episodes, cfg, seed)?)]
            }
            Protocol::Paper => horizons
                .iter()
                .enumerate()
                .map(|(k, &h)| {
                    let mut cfg = SamplerConfig::paper(spec.n_ticks, h);
                    cfg.needs = needs;
                    Ok((
                        Some(k),
                        WindowSampler::new(&episodes, cfg, paper_seed(seed, h))?,
                    ))
                })
                .collect::<Result<_, SamplerError>>()?,
        };
        Ok(SplitWindows {
            episodes,
            sets,
            horizons: horizons.to_vec(),
            spec: spec.clone(),
            needs,
            rng: StdRng::seed_from_u64(seed ^ 0x5E75),
        })
    }

    /// The next epoch of windows: which they are, not yet their arrays.
    pub fn epoch(&mut self) -> SplitEpoch {
        let mut picks = Vec::new();
        for (scored, sampler) in &mut self.sets {
            for pick in sampler.epoch() {
                // Every horizon's truth (the paper's picks carry only the
                // scored one's).
                let labels = match scored {
                    None => pick.labels,
                    Some(_) => labels_at(
                        self.episodes[pick.episode].fall_onset_tick,
                        pick.end_tick,
                        &self.horizons,
                    ),
                };
                picks.push(SplitPick {
                    episode: pick.episode,
                    end_tick: pick.end_tick,
                    labels,
                    scored_horizon: *scored,
                });
            }
        }
        if self.sets.len() > 1 {
            picks.shuffle(&mut self.rng);
        }
        SplitEpoch {
            episodes: self.episodes.clone(),
            spec: self.spec.clone(),
            needs: self.needs,
            picks,
        }
    }
}

/// Training windows: epoch `e` is the sampler's `e`-th draw, whichever
/// epoch is asked for first (a resumed run replays the draws of the epochs
/// it skips: picks only, no window is built).
struct DatasetSource {
    train: SplitWindows,
    drawn: usize,
    validation: SplitEpoch,
}

impl EpochSource for DatasetSource {
    fn train_epoch(&mut self, epoch: usize) -> Result<Box<dyn WindowSet>, TrainError> {
        if epoch <= self.drawn {
            return Err(TrainError::Data(format!(
                "training epoch {epoch} asked for after epoch {}: the sampler only draws forward",
                self.drawn
            )));
        }
        while self.drawn + 1 < epoch {
            self.train.epoch();
            self.drawn += 1;
        }
        self.drawn += 1;
        Ok(Box::new(self.train.epoch()))
    }
    fn validation(&mut self) -> Result<Box<dyn WindowSet>, TrainError> {
        Ok(Box::new(self.validation.clone()))
    }
}

fn default_joint_names() -> Vec<String> {
    fall_guard_runtime::robot::JointTable::poppy_humanoid().names()
}

/// Where `train --per-horizon` writes the network of horizon `h` ticks:
/// `models/emp.bpk` -> `models/emp.h15.bpk`.
pub fn per_horizon_path(out: &Path, horizon_ticks: usize) -> PathBuf {
    let stem = out
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    let name = match out.extension() {
        Some(ext) => format!("{stem}.h{horizon_ticks}.{}", ext.to_string_lossy()),
        None => format!("{stem}.h{horizon_ticks}"),
    };
    out.with_file_name(name)
}

/// Runs `fall-guard-lab train`: one model for all horizons, or with
/// `--per-horizon` one per horizon.
pub fn run_train(args: &TrainOptions) -> CommandResult<()> {
    if args.device != TrainDevice::Cpu && args.ablation.eq_ignore_ascii_case("logreg") {
        return Err(refused(format!(
            "--device {}: the logistic baseline trains on the CPU only",
            args.device
        )));
    }
    if let Some(lr) = args.vision_lr {
        if !(lr.is_finite() && lr > 0.0) {
            return Err(refused(format!(
                "--vision-lr {lr}: a learning rate is a positive number"
            )));
        }
        let without_vision = args.ablation.eq_ignore_ascii_case("logreg")
            || args
                .ablation
                .parse::<Ablation>()
                .is_ok_and(|a| !a.uses_vision());
        if without_vision {
            return Err(refused(format!(
                "--vision-lr: {} has no vision encoder",
                args.ablation
            )));
        }
    }
    // Refuse a device not compiled in before reading any data.
    args.device.device()?;
    let dataset =
        Dataset::open(&args.data).doing(|| format!("opening data set {}", args.data.display()))?;
    let joint_names = args.joint_names.clone().unwrap_or_else(default_joint_names);
    let logreg = args.ablation.eq_ignore_ascii_case("logreg");
    let ablation: Option<Ablation> = if logreg {
        None
    } else {
        Some(args.ablation.parse().map_err(refused)?)
    };
    if logreg && args.trajectory != TrajectoryInput::Planned {
        return Err(refused(format!(
            "--trajectory {}: the logistic baseline reads the planned window only",
            args.trajectory
        )));
    }
    let mut cfg = ModelConfig::named(
        &args.config,
        args.n_ticks,
        joint_names.len(),
        args.horizons.clone(),
        args.frame_size as usize,
    )
    .map_err(refused)?;
    cfg.trajectory = args.trajectory;
    let mut init_meta = None;
    if let Some(init) = &args.init {
        let (im, _) = fall_guard_runtime::model::file::load_emp(
            init,
            &fall_guard_runtime::model::cpu_device(),
        )
        .doing(|| format!("reading {}", init.display()))?;
        if Some(im.ablation) != ablation {
            return Err(refused(format!(
                "--init {}: holds {}, not {}",
                init.display(),
                im.ablation,
                args.ablation
            )));
        }
        if im.joint_names != joint_names || (im.rate_hz - args.rate_hz).abs() > 1e-9 {
            return Err(refused(format!(
                "--init {}: trained for other joints or another tick rate",
                init.display()
            )));
        }
        if args.per_horizon {
            return Err(refused(
                "--init with --per-horizon: fine-tune one network at a time",
            ));
        }
        cfg = im.config.clone();
        init_meta = Some(im);
    }
    cfg.validate().map_err(refused)?;
    let spec = WindowSpec {
        n_ticks: cfg.n_ticks,
        max_horizon_ticks: cfg.max_horizon_ticks(),
        rate_hz: args.rate_hz,
        joint_names: joint_names.clone(),
        frame_size: args.frame_size,
    };
    let needs = needs_of(ablation, cfg.trajectory);
    let runs: Vec<(String, Vec<usize>, PathBuf)> = if args.per_horizon {
        cfg.horizons_ticks
            .iter()
            .map(|&h| (format!("h{h}"), vec![h], per_horizon_path(&args.out, h)))
            .collect()
    } else {
        vec![(
            "model".to_string(),
            cfg.horizons_ticks.clone(),
            args.out.clone(),
        )]
    };
    // The logistic baseline trains in one go: nothing to checkpoint.
    let run = match ablation {
        Some(_) => {
            let names: Vec<String> = runs.iter().map(|r| r.0.clone()).collect();
            Some(RunCheckpoint::open(args, &dataset, names)?)
        }
        None => None,
    };
    // Read once; every per-horizon network cuts its windows from them.
    let train_eps = load_split_episodes(&dataset, Split::Train, &spec, needs)?;
    let val_eps = load_split_episodes(&dataset, Split::Validation, &spec, needs)?;
    // The input ranges every network of this run is written with (the
    // daemon's out-of-range guard): those of the training split.
    let input_ranges = match ablation {
        Some(a) => {
            let probe = ModelMeta::new(cfg.clone(), a, args.rate_hz, joint_names.clone());
            let set = data_name(&dataset.dir);
            Some(crate::ranges::measure(&train_eps, &probe, &set, "train")?.0)
        }
        None => None,
    };
    for (name, horizons, out) in runs {
        let net = run.as_ref().map(|r| r.network(&name));
        if let Some(net) = &net {
            if net.is_done() && out.is_file() {
                tracing::info!(
                    "{} already written by this run (checkpoint {}): skipped",
                    out.display(),
                    net.checkpoint.dir().display()
                );
                continue;
            }
        }
        let mut cfg = cfg.clone();
        cfg.horizons_ticks = horizons;
        let spec = WindowSpec {
            max_horizon_ticks: cfg.max_horizon_ticks(),
            ..spec.clone()
        };
        let data = |e: SamplerError, split: Split| {
            TrainError::Data(format!("{split} split of {}: {e}", dataset.dir.display()))
        };
        let train = SplitWindows::new(
            train_eps.clone(),
            &spec,
            needs,
            &cfg.horizons_ticks,
            args.seed,
            args.protocol,
        )
        .map_err(|e| data(e, Split::Train))?;
        let validation = SplitWindows::new(
            val_eps.clone(),
            &spec,
            needs,
            &cfg.horizons_ticks,
            args.seed ^ 0x5EED,
            args.protocol,
        )
        .map_err(|e| data(e, Split::Validation))?
        .epoch();
        train_one(
            args,
            ablation,
            cfg,
            &joint_names,
            train,
            validation,
            &out,
            net.as_ref(),
            &NetworkStart {
                input_ranges: input_ranges.clone(),
                init: init_meta.clone(),
            },
        )?;
        if let Some(net) = &net {
            net.finish()?;
        }
    }
    if let Some(run) = run {
        run.remove()?;
    }
    Ok(())
}

/// Where `train` checkpoints when `--checkpoint-dir` is not given:
/// `models/emp.bpk` -> `models/emp.bpk.ckpt`.
pub fn default_checkpoint_dir(out: &Path) -> PathBuf {
    let mut name = out.file_name().unwrap_or_default().to_os_string();
    name.push(".ckpt");
    out.with_file_name(name)
}

/// The checkpoint directory of one `train` run: `args.json` (the
/// arguments and the data set's manifest it was started with) and one
/// [`Checkpoint`] per network, with a `NAME.done` marker once that
/// network's model file is written.
struct RunCheckpoint {
    dir: PathBuf,
    networks: Vec<String>,
}

/// One network of a [`RunCheckpoint`].
struct NetworkCheckpoint {
    checkpoint: Checkpoint,
    done: PathBuf,
}

impl NetworkCheckpoint {
    fn is_done(&self) -> bool {
        self.done.is_file()
    }

    /// Its model file is written: marks it done and removes its epochs.
    fn finish(&self) -> CommandResult<()> {
        write_atomically(&self.done, b"")?;
        self.checkpoint.remove()?;
        Ok(())
    }
}

/// What a run is checked against when it resumes: every argument that
/// changes what it trains, and the data set's manifest.
pub(crate) fn run_arguments(args: &TrainOptions, dataset: &Dataset) -> serde_json::Value {
    let mut arguments = serde_json::json!({
        "data": args.data,
        "manifest": {
            "train": dataset.manifest.train,
            "validation": dataset.manifest.validation,
            "test": dataset.manifest.test,
        },
        "ablation": args.ablation,
        "config": args.config,
        "seed": args.seed,
        "out": args.out,
        "epochs": args.epochs,
        "patience": args.patience,
        "batch": args.batch,
        "rates": args.rates,
        "n_ticks": args.n_ticks,
        "horizons": args.horizons,
        "rate_hz": args.rate_hz,
        "frame_size": args.frame_size,
        "joint_names": args.joint_names,
        "trained_on": args.trained_on,
        "protocol": args.protocol.name(),
        "per_horizon": args.per_horizon,
        "trajectory": args.trajectory.to_string(),
        "device": args.device.to_string(),
    });
    // Only when given, so that runs started without it still resume.
    if let Some(lr) = args.vision_lr {
        arguments["vision_lr"] = lr.into();
    }
    if args.lr_scale != 1.0 {
        arguments["lr_scale"] = args.lr_scale.into();
    }
    arguments
}

impl RunCheckpoint {
    /// The run's checkpoint: resumed when `args.json` holds these
    /// arguments, refused when it holds others, started otherwise.
    fn open(
        args: &TrainOptions,
        dataset: &Dataset,
        networks: Vec<String>,
    ) -> CommandResult<RunCheckpoint> {
        let dir = args
            .checkpoint_dir
            .clone()
            .unwrap_or_else(|| default_checkpoint_dir(&args.out));
        let path = dir.join("args.json");
        let want = run_arguments(args, dataset);
        match std::fs::read(&path) {
            Ok(bytes) => {
                let have: serde_json::Value = serde_json::from_slice(&bytes)
                    .doing(|| format!("reading {}", path.display()))?;
                if have != want {
                    let differ: Vec<&str> = want
                        .as_object()
                        .into_iter()
                        .flatten()
                        .filter(|&(k, v)| have.get(k.as_str()) != Some(v))
                        .map(|(k, _)| k.as_str())
                        .collect();
                    return Err(refused(format!(
                        "{} holds the checkpoint of a run with other arguments (they differ in: {}): rerun with that run's arguments to resume it, remove the directory to start afresh, or give another --checkpoint-dir",
                        dir.display(),
                        differ.join(", ")
                    )));
                }
                tracing::info!("resuming the run checkpointed in {}", dir.display());
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                std::fs::create_dir_all(&dir).doing(|| format!("creating {}", dir.display()))?;
                write_atomically(&path, &serde_json::to_vec_pretty(&want)?)?;
            }
            Err(e) => return Err(e).doing(|| format!("reading {}", path.display())),
        }
        Ok(RunCheckpoint { dir, networks })
    }

    fn network(&self, name: &str) -> NetworkCheckpoint {
        NetworkCheckpoint {
            checkpoint: Checkpoint::new(self.dir.join(name)),
            done: self.dir.join(format!("{name}.done")),
        }
    }

    /// The run is over: its files go, then the directory if left empty.
    fn remove(self) -> CommandResult<()> {
        for name in &self.networks {
            Checkpoint::new(self.dir.join(name)).remove()?;
            let _ = std::fs::remove_file(self.dir.join(format!("{name}.done")));
        }
        std::fs::remove_file(self.dir.join("args.json"))
            .doing(|| format!("removing {}", self.dir.display()))?;
        let _ = std::fs::remove_dir(&self.dir);
        Ok(())
    }
}

/// What every network of one `train` run starts from besides its config.
struct NetworkStart {
    /// The training split's input ranges (the daemon's out-of-range guard).
    input_ranges: Option<fall_guard_runtime::model::ranges::InputRanges>,
    /// `--init`: that file's metadata, whose standardisation its weights
    /// were trained on.
    init: Option<ModelMeta>,
}

/// Trains and writes one model of `cfg`'s horizons (a network checkpointed
/// in `checkpoint` every epoch).
#[allow(clippy::too_many_arguments)]
fn train_one(
    args: &TrainOptions,
    ablation: Option<Ablation>,
    cfg: ModelConfig,
    joint_names: &[String],
    mut train: SplitWindows,
    validation: SplitEpoch,
    out: &Path,
    checkpoint: Option<&NetworkCheckpoint>,
    start: &NetworkStart,
) -> CommandResult<()> {
    if let Some(parent) = out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).doing(|| format!("creating {}", parent.display()))?;
    }
    match ablation {
        None => {
            // Joints and plan only: the whole epoch fits in memory.
            let epoch = train.epoch();
            let windows = epoch.build(0..epoch.len(), false)?;
            let mut m = LogRegModel::fit(
                &windows,
                cfg.horizons_ticks.clone(),
                args.rate_hz,
                cfg.n_ticks,
                joint_names.to_vec(),
            )?;
            m.trained_on = args.trained_on.clone();
            m.save(out)?;
            tracing::info!("logistic-regression baseline written to {}", out.display());
        }
        Some(ablation) => {
            let mut meta = ModelMeta::new(cfg, ablation, args.rate_hz, joint_names.to_vec());
            meta.trained_on = args.trained_on.clone();
            if let Some(im) = &start.init {
                // The weights were trained on this standardisation.
                meta.joint_mean.clone_from(&im.joint_mean);
                meta.joint_std.clone_from(&im.joint_std);
                meta.plan_mean.clone_from(&im.plan_mean);
                meta.plan_std.clone_from(&im.plan_std);
            }
            meta.protocol = Some(args.protocol.name().into());
            let mut rates = match args.rates.as_str() {
                "sim" => EncoderRates::sim(),
                "robot" => EncoderRates::robot(),
                other => return Err(refused(format!("unknown --rates {other:?}: sim or robot"))),
            };
            if let Some(lr) = args.vision_lr {
                rates.vision.lr = lr;
                meta.vision_lr = Some(lr);
            }
            if !(args.lr_scale > 0.0 && args.lr_scale.is_finite()) {
                return Err(refused(format!(
                    "--lr-scale {}: a positive factor",
                    args.lr_scale
                )));
            }
            rates = rates.scaled(args.lr_scale);
            let opts = FitOptions {
                seed: args.seed,
                max_epochs: args.epochs,
                patience: args.patience,
                batch_size: args.batch,
                rates,
                progress: !args.quiet,
                device: args.device,
                checkpoint: checkpoint.map(|c| c.checkpoint.dir().to_path_buf()),
                init: args.init.clone(),
            };
            let mut source = DatasetSource {
                train,
                drawn: 0,
                validation,
            };
            let (mut meta, model) = fit(meta, &mut source, &opts)?;
            meta.input_ranges.clone_from(&start.input_ranges);
            save_model(out, &meta, &model)?;
            tracing::info!(
                "{} model ({} trajectory, {} protocol, horizons {:?} ticks) written to {} (best epoch {}, val loss {:.4})",
                ablation,
                meta.config.trajectory,
                args.protocol,
                meta.horizons_ticks,
                out.display(),
                meta.best_epoch,
                meta.history
                    .get(meta.best_epoch.saturating_sub(1))
                    .map(|h| h.val_loss)
                    .unwrap_or(f64::NAN)
            );
        }
    }
    Ok(())
}

enum AnyModel {
    Network(Box<LoadedModel>),
    LogReg(Box<LogRegModel>, PathBuf),
}

fn load_any(
    path: &Path,
    projection: ProjectionWeights,
    convolutions: Convolutions,
) -> CommandResult<AnyModel> {
    if let Some(m) = LogRegModel::load(path)? {
        return Ok(AnyModel::LogReg(Box::new(m), path.to_path_buf()));
    }
    Ok(AnyModel::Network(Box::new(
        LoadedModel::load(path)?
            .with_projection(projection)
            .with_convolutions(convolutions),
    )))
}

/// Runs `fall-guard-lab eval`: the per-tick forecasts of `--recording`
/// (written to `--per-tick-out`), and the report of the split (written to
/// `--out`, and returned for the binary to print) when a data set is given.
pub fn run_eval(args: &EvalOptions) -> CommandResult<Option<EvalReport>> {
    if let Some(rec) = &args.recording {
        let out = args
            .per_tick_out
            .as_ref()
            .ok_or_else(|| refused("--recording needs --per-tick-out FILE"))?;
        let model = LoadedModel::load(&args.model)?
            .with_projection(args.projection)
            .with_convolutions(args.convolutions);
        let n = per_tick_forecast(&model, rec, out)?;
        tracing::info!("{n} per-tick forecasts written to {}", out.display());
        if args.data.is_none() {
            return Ok(None);
        }
    }
    let data = args
        .data
        .as_ref()
        .ok_or_else(|| refused("--data DIR is needed to evaluate on a split"))?;
    let out_dir = args
        .out
        .as_ref()
        .ok_or_else(|| refused("--out DIR is needed to evaluate on a split"))?;
    let split: Split = args.split.parse().map_err(refused)?;
    let dataset = Dataset::open(data).doing(|| format!("opening data set {}", data.display()))?;
    let mut paths = vec![args.model.clone()];
    paths.extend(args.seeds.iter().cloned());
    let models: Vec<AnyModel> = paths
        .iter()
        .map(|p| load_any(p, args.projection, args.convolutions))
        .collect::<CommandResult<_>>()?;
    // Windows come from the first model's description; the others must agree.
    let (spec, needs, horizons, rate_hz, ablation_name, history) = match &models[0] {
        AnyModel::Network(m) => (
            m.meta.window_spec(),
            needs_of_model(&m.meta),
            m.meta.horizons_ticks.clone(),
            m.meta.rate_hz,
            m.meta.ablation.to_string(),
            m.meta.history.clone(),
        ),
        AnyModel::LogReg(m, _) => (
            WindowSpec {
                n_ticks: m.n_ticks,
                max_horizon_ticks: *m.horizons_ticks.last().unwrap_or(&0),
                rate_hz: m.rate_hz,
                joint_names: m.joint_names.clone(),
                frame_size: 64,
            },
            needs_of(None, TrajectoryInput::Planned),
            m.horizons_ticks.clone(),
            m.rate_hz,
            "logreg".to_string(),
            Vec::new(),
        ),
    };
    for m in &models[1..] {
        if let AnyModel::Network(m) = m {
            if m.meta.horizons_ticks != horizons {
                return Err(refused(format!(
                    "{} forecasts horizons {:?} ticks, the first model {:?}: --seeds must be the same model trained with other seeds (evaluate a per-horizon network on its own)",
                    m.path.display(),
                    m.meta.horizons_ticks,
                    horizons
                )));
            }
            m.meta.check_compatible_with(
                &spec.joint_names,
                spec.rate_hz,
                spec.n_ticks,
                spec.max_horizon_ticks,
                spec.frame_size,
            )?;
        }
    }
    let episodes = load_split_episodes(&dataset, split, &spec, needs)?;
    let mut order = vec![args.protocol];
    order.extend(Protocol::ALL.into_iter().filter(|&p| p != args.protocol));
    let mut sections = Vec::new();
    let mut primary: Option<(Vec<WindowTruth>, Vec<Predictions>)> = None;
    for protocol in order {
        let mut split_windows = SplitWindows::new(
            episodes.clone(),
            &spec,
            needs,
            &horizons,
            args.sample_seed,
            protocol,
        )
        .map_err(|e| {
            refused(format!(
                "{} split of {} under the {protocol} protocol: {e}",
                split.name(),
                data.display()
            ))
        })?;
        let mut windows = split_windows.epoch();
        for _ in 1..args.draws.max(1) {
            windows.extend(split_windows.epoch());
        }
        // Built and forecast a batch at a time: only the probabilities stay.
        let mut preds: Vec<Predictions> = models
            .iter()
            .map(|m| Predictions {
                model: match m {
                    AnyModel::Network(m) => data_name(&m.path),
                    AnyModel::LogReg(_, p) => data_name(p),
                },
                probabilities: Vec::with_capacity(windows.len()),
            })
            .collect();
        for_each_batch(&windows, EVAL_BATCH, true, |batch| {
            for (m, p) in models.iter().zip(&mut preds) {
                match m {
                    AnyModel::Network(m) => {
                        p.probabilities.extend(predict(m, batch)?.probabilities)
                    }
                    AnyModel::LogReg(m, _) => {
                        for w in batch {
                            p.probabilities.push(m.predict(w)?);
                        }
                    }
                }
            }
            Ok(())
        })?;
        let truths = windows.truths()?;
        sections.push(report(
            &preds,
            &truths,
            &horizons,
            rate_hz,
            protocol,
            args.sample_seed,
        ));
        if primary.is_none() {
            primary = Some((truths, preds));
        }
    }
    let rep = EvalReport::new(
        paths.iter().map(|p| data_name(p)).collect(),
        &ablation_name,
        split.name(),
        sections,
    );
    rep.write(out_dir)
        .doing(|| format!("writing to {}", out_dir.display()))?;
    let (windows, preds) = primary.expect("at least one protocol");
    // Plots of the first model, primary protocol, each horizon on the
    // windows that score it.
    let scored = |k: usize| windows.iter().enumerate().filter(move |(_, w)| w.scores(k));
    let labels: Vec<Vec<bool>> = (0..horizons.len())
        .map(|k| scored(k).map(|(_, w)| w.labels[k] > 0.5).collect())
        .collect();
    let probs: Vec<Vec<f32>> = (0..horizons.len())
        .map(|k| {
            scored(k)
                .map(|(i, _)| preds[0].probabilities[i][k])
                .collect()
        })
        .collect();
    let series: Vec<plots::HorizonSeries<'_>> = horizons
        .iter()
        .enumerate()
        .map(|(k, h)| {
            (
                format!("{:.0} ms", *h as f64 * 1000.0 / rate_hz),
                probs[k].as_slice(),
                labels[k].as_slice(),
            )
        })
        .collect();
    plots::roc_plot(&out_dir.join("roc.png"), &series)?;
    plots::reliability_plot(&out_dir.join("reliability.png"), &series)?;
    if !history.is_empty() {
        plots::training_plot(&out_dir.join("training.png"), &history)?;
    }
    Ok(Some(rep))
}

/// One forecast per tick of an episode, replayed tick by tick through the
/// streaming forecaster as the daemon does, once the window is full:
/// `(tick, stamp_ns, probabilities)`.
pub fn forecast_ticks(
    model: &LoadedModel,
    episode: &EpisodeTicks,
) -> CommandResult<Vec<(i64, i64, Vec<f32>)>> {
    Ok(forecast_ticks_judged(model, episode)?
        .into_iter()
        .map(|t| (t.tick, t.stamp_ns, t.probabilities))
        .collect())
}

/// One tick's forecast and the out-of-range guard's judgement of its window.
#[derive(Debug, Clone, PartialEq)]
pub struct JudgedForecast {
    pub tick: i64,
    pub stamp_ns: i64,
    pub probabilities: Vec<f32>,
    /// The window holds an input outside the network's training range.
    pub out_of_range: bool,
}

/// [`forecast_ticks`] with the guard's judgement of each window.
pub fn forecast_ticks_judged(
    model: &LoadedModel,
    episode: &EpisodeTicks,
) -> CommandResult<Vec<JudgedForecast>> {
    let needs = needs_of_model(&model.meta);
    let mut stream = StreamingForecaster::new(model);
    let mut out = Vec::with_capacity(episode.ticks.len());
    for tick in &episode.ticks {
        if !needs.present_in(tick) {
            continue;
        }
        let at = || format!("{}: tick {}", episode.path.display(), tick.tick);
        stream.push(tick).doing(at)?;
        if stream.is_full() {
            out.push(JudgedForecast {
                tick: tick.tick,
                stamp_ns: tick.stamp_ns,
                probabilities: stream.forecast().doing(at)?,
                out_of_range: !stream.excursions().is_empty(),
            });
        }
    }
    Ok(out)
}

/// Replays a recording through [`forecast_ticks`] and writes one JSON line
/// per tick once the window is full: `{"tick", "stamp_ns", "probabilities"}`.
/// Returns the number of lines.
pub fn per_tick_forecast(
    model: &LoadedModel,
    recording: &Path,
    out: &Path,
) -> CommandResult<usize> {
    use std::io::Write;
    let spec = model.meta.window_spec();
    let needs = needs_of_model(&model.meta);
    let episode = crate::dataset::load_episode(recording, &spec, needs)
        .doing(|| format!("reading {}", recording.display()))?;
    let forecasts = forecast_ticks(model, &episode)?;
    let file = std::fs::File::create(out).doing(|| format!("creating {}", out.display()))?;
    let mut w = std::io::BufWriter::new(file);
    for (tick, stamp_ns, p) in &forecasts {
        serde_json::to_writer(
            &mut w,
            &serde_json::json!({"tick": tick, "stamp_ns": stamp_ns, "probabilities": p}),
        )?;
        w.write_all(b"\n")?;
    }
    w.flush()?;
    Ok(forecasts.len())
}

/// `fall-guard-lab half`: the same model file with its weights in half precision.
#[derive(Debug)]
pub struct HalfOptions {
    /// Model file to convert (f32 or already half).
    pub model: PathBuf,
    /// Output model file.
    pub out: PathBuf,
}

/// Rewrites a model file with f16 weights (metadata unchanged), then loads
/// it back to check it reads.
pub fn run_half(args: &HalfOptions) -> CommandResult<()> {
    let device = fall_guard_runtime::model::cpu_device();
    let (meta, emp) = fall_guard_runtime::model::file::load_emp(&args.model, &device)
        .doing(|| format!("reading {}", args.model.display()))?;
    fall_guard_runtime::model::save_model_as(
        &args.out,
        &meta,
        &emp,
        fall_guard_runtime::model::WeightPrecision::Half,
    )
    .doing(|| format!("writing {}", args.out.display()))?;
    LoadedModel::load(&args.out).doing(|| format!("reading back {}", args.out.display()))?;
    let size = |p: &Path| std::fs::metadata(p).map(|m| m.len()).unwrap_or(0);
    tracing::info!(
        "{} ({} bytes) -> {} ({} bytes, f16 weights)",
        args.model.display(),
        size(&args.model),
        args.out.display(),
        size(&args.out)
    );
    Ok(())
}
