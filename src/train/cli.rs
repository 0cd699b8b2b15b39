//! The `train` and `eval` subcommands: argument structs and their run
//! functions. Windows come from the data plane (`dataset`, `sampler`,
//! `window`): the same code the daemon uses to build its windows.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{bail, Context};
use rand::rngs::StdRng;
use rand::seq::SliceRandom;
use rand::SeedableRng;

use super::device::TrainDevice;
use super::eval::{predict, report, EvalReport, Predictions};
use super::fit::{fit, EncoderRates, EpochSource, FitOptions, LabeledWindow, TrainError};
use super::logreg::LogRegModel;
use super::plots;
use crate::model::{
    save_model, Ablation, LoadedModel, ModelConfig, ModelMeta, ProjectionWeights,
    StreamingForecaster, TrajectoryInput,
};
use crate::train::dataset::{Dataset, Split};
use crate::train::sampler::{labels_at, Protocol, SamplerConfig, SamplerError, WindowSampler};
use crate::window::{EpisodeTicks, Streams, WindowSpec};

/// Arguments of `fall-guard train`.
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
    /// No progress bar.
    pub quiet: bool,
}

/// Arguments of `fall-guard eval`.
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

    /// The next epoch of windows.
    pub fn epoch(&mut self) -> Result<Vec<LabeledWindow>, TrainError> {
        let mut out = Vec::new();
        for (scored, sampler) in &mut self.sets {
            for pick in sampler.epoch() {
                let ep = &self.episodes[pick.episode];
                let w = ep
                    .window_ending_at(pick.end_tick, &self.spec, self.needs)
                    .map_err(|e| {
                        TrainError::Data(format!(
                            "{} at tick {}: {e}",
                            ep.path.display(),
                            pick.end_tick
                        ))
                    })?;
                // Every horizon's truth (the paper's picks carry only the
                // scored one's).
                let labels = match scored {
                    None => pick.labels,
                    Some(_) => labels_at(ep.fall_onset_tick, pick.end_tick, &self.horizons),
                };
                out.push(LabeledWindow {
                    joints: w.joints,
                    plan: w.plan,
                    frames: w.frames,
                    labels: labels.iter().map(|&b| f32::from(u8::from(b))).collect(),
                    episode: pick.episode,
                    scored_horizon: *scored,
                });
            }
        }
        if self.sets.len() > 1 {
            out.shuffle(&mut self.rng);
        }
        Ok(out)
    }
}

struct DatasetSource {
    train: SplitWindows,
    validation: Vec<LabeledWindow>,
}

impl EpochSource for DatasetSource {
    fn train_epoch(&mut self, _epoch: usize) -> Result<Vec<LabeledWindow>, TrainError> {
        self.train.epoch()
    }
    fn validation(&mut self) -> Result<Vec<LabeledWindow>, TrainError> {
        Ok(self.validation.clone())
    }
}

fn default_joint_names() -> Vec<String> {
    crate::robot::JointTable::poppy_humanoid().names()
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

/// Runs `fall-guard train`: one model for all horizons, or with
/// `--per-horizon` one per horizon.
pub fn run_train(args: &TrainOptions) -> anyhow::Result<()> {
    if args.device != TrainDevice::Cpu && args.ablation.eq_ignore_ascii_case("logreg") {
        bail!(
            "--device {}: the logistic baseline trains on the CPU only",
            args.device
        );
    }
    // Refuse a device not compiled in before reading any data.
    args.device.device()?;
    let dataset = Dataset::open(&args.data)
        .with_context(|| format!("opening data set {}", args.data.display()))?;
    let joint_names = args.joint_names.clone().unwrap_or_else(default_joint_names);
    let logreg = args.ablation.eq_ignore_ascii_case("logreg");
    let ablation: Option<Ablation> = if logreg {
        None
    } else {
        Some(args.ablation.parse().map_err(anyhow::Error::msg)?)
    };
    if logreg && args.trajectory != TrajectoryInput::Planned {
        bail!(
            "--trajectory {}: the logistic baseline reads the planned window only",
            args.trajectory
        );
    }
    let mut cfg = ModelConfig::named(
        &args.config,
        args.n_ticks,
        joint_names.len(),
        args.horizons.clone(),
        args.frame_size as usize,
    )
    .map_err(anyhow::Error::msg)?;
    cfg.trajectory = args.trajectory;
    cfg.validate().map_err(anyhow::Error::msg)?;
    let spec = WindowSpec {
        n_ticks: cfg.n_ticks,
        max_horizon_ticks: cfg.max_horizon_ticks(),
        rate_hz: args.rate_hz,
        joint_names: joint_names.clone(),
        frame_size: args.frame_size,
    };
    let needs = needs_of(ablation, cfg.trajectory);
    // Read once; every per-horizon network cuts its windows from them.
    let train_eps = load_split_episodes(&dataset, Split::Train, &spec, needs)?;
    let val_eps = load_split_episodes(&dataset, Split::Validation, &spec, needs)?;
    let runs: Vec<(Vec<usize>, PathBuf)> = if args.per_horizon {
        cfg.horizons_ticks
            .iter()
            .map(|&h| (vec![h], per_horizon_path(&args.out, h)))
            .collect()
    } else {
        vec![(cfg.horizons_ticks.clone(), args.out.clone())]
    };
    for (horizons, out) in runs {
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
        .epoch()?;
        train_one(args, ablation, cfg, &joint_names, train, validation, &out)?;
    }
    Ok(())
}

/// Trains and writes one model of `cfg`'s horizons.
fn train_one(
    args: &TrainOptions,
    ablation: Option<Ablation>,
    cfg: ModelConfig,
    joint_names: &[String],
    mut train: SplitWindows,
    validation: Vec<LabeledWindow>,
    out: &Path,
) -> anyhow::Result<()> {
    if let Some(parent) = out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent)
            .with_context(|| format!("creating {}", parent.display()))?;
    }
    match ablation {
        None => {
            let windows = train.epoch()?;
            let mut m = LogRegModel::fit(
                &windows,
                cfg.horizons_ticks.clone(),
                args.rate_hz,
                cfg.n_ticks,
                joint_names.to_vec(),
            )?;
            m.trained_on = args.trained_on.clone();
            m.save(out)?;
            eprintln!("logistic-regression baseline written to {}", out.display());
        }
        Some(ablation) => {
            let mut meta = ModelMeta::new(cfg, ablation, args.rate_hz, joint_names.to_vec());
            meta.trained_on = args.trained_on.clone();
            meta.protocol = Some(args.protocol.name().into());
            let rates = match args.rates.as_str() {
                "sim" => EncoderRates::sim(),
                "robot" => EncoderRates::robot(),
                other => bail!("unknown --rates {other:?}: sim or robot"),
            };
            let opts = FitOptions {
                seed: args.seed,
                max_epochs: args.epochs,
                patience: args.patience,
                batch_size: args.batch,
                rates,
                progress: !args.quiet,
                device: args.device,
            };
            let mut source = DatasetSource { train, validation };
            let (meta, model) = fit(meta, &mut source, &opts)?;
            save_model(out, &meta, &model)?;
            eprintln!(
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

fn load_any(path: &Path, projection: ProjectionWeights) -> anyhow::Result<AnyModel> {
    if let Some(m) = LogRegModel::load(path)? {
        return Ok(AnyModel::LogReg(Box::new(m), path.to_path_buf()));
    }
    Ok(AnyModel::Network(Box::new(
        LoadedModel::load(path)?.with_projection(projection),
    )))
}

/// Runs `fall-guard eval`.
pub fn run_eval(args: &EvalOptions) -> anyhow::Result<()> {
    if let Some(rec) = &args.recording {
        let out = args
            .per_tick_out
            .as_ref()
            .context("--recording needs --per-tick-out FILE")?;
        let model = LoadedModel::load(&args.model)?.with_projection(args.projection);
        let n = per_tick_forecast(&model, rec, out)?;
        eprintln!("{n} per-tick forecasts written to {}", out.display());
        if args.data.is_none() {
            return Ok(());
        }
    }
    let data = args
        .data
        .as_ref()
        .context("--data DIR is needed to evaluate on a split")?;
    let out_dir = args
        .out
        .as_ref()
        .context("--out DIR is needed to evaluate on a split")?;
    let split: Split = args.split.parse().map_err(anyhow::Error::msg)?;
    let dataset =
        Dataset::open(data).with_context(|| format!("opening data set {}", data.display()))?;
    let mut paths = vec![args.model.clone()];
    paths.extend(args.seeds.iter().cloned());
    let models: Vec<AnyModel> = paths
        .iter()
        .map(|p| load_any(p, args.projection))
        .collect::<anyhow::Result<_>>()?;
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
                bail!(
                    "{} forecasts horizons {:?} ticks, the first model {:?}: --seeds must be the same model trained with other seeds (evaluate a per-horizon network on its own)",
                    m.path.display(),
                    m.meta.horizons_ticks,
                    horizons
                );
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
    let mut primary: Option<(Vec<LabeledWindow>, Vec<Predictions>)> = None;
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
            anyhow::anyhow!(
                "{} split of {} under the {protocol} protocol: {e}",
                split.name(),
                data.display()
            )
        })?;
        let mut windows = Vec::new();
        for _ in 0..args.draws.max(1) {
            windows.extend(split_windows.epoch()?);
        }
        let preds: Vec<Predictions> = models
            .iter()
            .map(|m| match m {
                AnyModel::Network(m) => predict(m, &windows),
                AnyModel::LogReg(m, p) => Ok(Predictions {
                    model: p.display().to_string(),
                    probabilities: windows
                        .iter()
                        .map(|w| m.predict(w))
                        .collect::<Result<_, _>>()?,
                }),
            })
            .collect::<Result<_, TrainError>>()?;
        sections.push(report(
            &preds,
            &windows,
            &horizons,
            rate_hz,
            protocol,
            args.sample_seed,
        ));
        if primary.is_none() {
            primary = Some((windows, preds));
        }
    }
    let rep = EvalReport::new(
        paths.iter().map(|p| p.display().to_string()).collect(),
        &ablation_name,
        split.name(),
        sections,
    );
    rep.write(out_dir)
        .with_context(|| format!("writing to {}", out_dir.display()))?;
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
    print!("{}", rep.markdown());
    Ok(())
}

/// One forecast per tick of an episode, replayed tick by tick through the
/// streaming forecaster as the daemon does, once the window is full:
/// `(tick, stamp_ns, probabilities)`.
pub fn forecast_ticks(
    model: &LoadedModel,
    episode: &EpisodeTicks,
) -> anyhow::Result<Vec<(i64, i64, Vec<f32>)>> {
    let needs = needs_of_model(&model.meta);
    let mut stream = StreamingForecaster::new(model);
    let mut out = Vec::with_capacity(episode.ticks.len());
    for tick in &episode.ticks {
        if !needs.present_in(tick) {
            continue;
        }
        let at = || format!("{}: tick {}", episode.path.display(), tick.tick);
        stream.push(tick).with_context(at)?;
        if stream.is_full() {
            out.push((
                tick.tick,
                tick.stamp_ns,
                stream.forecast().with_context(at)?,
            ));
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
) -> anyhow::Result<usize> {
    use std::io::Write;
    let spec = model.meta.window_spec();
    let needs = needs_of_model(&model.meta);
    let episode = crate::train::dataset::load_episode(recording, &spec, needs)
        .with_context(|| format!("reading {}", recording.display()))?;
    let forecasts = forecast_ticks(model, &episode)?;
    let file = std::fs::File::create(out).with_context(|| format!("creating {}", out.display()))?;
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

/// `fall-guard half`: the same model file with its weights in half precision.
#[derive(Debug)]
pub struct HalfOptions {
    /// Model file to convert (f32 or already half).
    pub model: PathBuf,
    /// Output model file.
    pub out: PathBuf,
}

/// Rewrites a model file with f16 weights (metadata unchanged), then loads
/// it back to check it reads.
pub fn run_half(args: &HalfOptions) -> anyhow::Result<()> {
    let device = crate::model::cpu_device();
    let (meta, emp) = crate::model::file::load_emp(&args.model, &device)
        .with_context(|| format!("reading {}", args.model.display()))?;
    crate::model::save_model_as(&args.out, &meta, &emp, crate::model::WeightPrecision::Half)
        .with_context(|| format!("writing {}", args.out.display()))?;
    LoadedModel::load(&args.out).with_context(|| format!("reading back {}", args.out.display()))?;
    let size = |p: &Path| std::fs::metadata(p).map(|m| m.len()).unwrap_or(0);
    eprintln!(
        "{} ({} bytes) -> {} ({} bytes, f16 weights)",
        args.model.display(),
        size(&args.model),
        args.out.display(),
        size(&args.out)
    );
    Ok(())
}
