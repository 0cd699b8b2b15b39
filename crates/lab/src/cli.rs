//! The lab binary's command line: clap's parsing structs, each turned into
//! the lab library's plain options struct (`commands::TrainOptions`, ...)
//! by `From`. The library has no clap derive: its enums (`Protocol`,
//! `TrajectoryInput`, the calibration's form) get their command-line twins
//! here; `Ablation`, `ProjectionWeights`, `Split` and `TrainDevice` parse by
//! `FromStr`.

use std::path::PathBuf;

use clap::{Args, Parser, Subcommand, ValueEnum};

use fall_guard_lab::bench::TrainBenchOptions;
use fall_guard_lab::calibrate::{CalibrateOptions, CalibrationForm, FormChoice};
use fall_guard_lab::commands::{EvalOptions, HalfOptions, TrainOptions};
use fall_guard_lab::dataset::Split;
use fall_guard_lab::device::TrainDevice;
use fall_guard_lab::sampler::Protocol;
use fall_guard_lab::warning::WarningsOptions;
use fall_guard_runtime::model::{Convolutions, ProjectionWeights, TrajectoryInput};

#[derive(Debug, Parser)]
#[command(
    name = "fall-guard-lab",
    version,
    about = "Trains, evaluates and calibrates fall-guard's networks on data sets of recordings (a workstation's tool, not the robot's)"
)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// Train a model (or the logistic baseline) on a data set.
    Train(TrainArgs),
    /// Evaluate model files on a split; or forecast one recording per tick.
    Eval(EvalArgs),
    /// Warning lead time and false alarms of the safety latch on a split; choose its thresholds.
    Warnings(WarningsArgs),
    /// Calibrate a model's probabilities on held-out windows (Platt scaling or beta calibration per horizon, shortest first).
    Calibrate(CalibrateArgs),
    /// Rewrite a model file with its weights in half precision (f16).
    Half(HalfArgs),
    /// Measure the input ranges a network was trained on (its training split) and write them into its model file, for the daemon's out-of-range guard.
    Ranges(RangesArgs),
    /// Fine-tune a shipped network on the owner's labelled recordings mixed with the simulated set, calibrate, choose its thresholds again, and write a card comparing it with the shipped one.
    Finetune(FinetuneArgs),
    /// Training throughput of the network (EMP, batch 4) on the CPU or a GPU.
    Bench(BenchArgs),
}

/// `--protocol` (`train`, `eval`, `calibrate`): `sampler::Protocol`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ProtocolArg {
    /// One window set for all horizons, balanced at the middle horizon, no
    /// fallen tick in a window (as the daemon sees an episode).
    Deployment,
    /// The paper's: one window set per horizon `P`, balanced at `P`, windows
    /// ending at or before the stop line `onset - P`.
    Paper,
}

impl From<ProtocolArg> for Protocol {
    fn from(p: ProtocolArg) -> Self {
        match p {
            ProtocolArg::Deployment => Protocol::Deployment,
            ProtocolArg::Paper => Protocol::Paper,
        }
    }
}

/// `calibrate --form`: `calibrate::FormChoice`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum FormArg {
    /// Per horizon, the form with the lower cross-validated loss on the
    /// fitting windows (5 folds by episode).
    Auto,
    /// Platt scaling, `sigmoid(a z + b)`, at every horizon.
    Platt,
    /// Beta calibration, `sigmoid(a softplus(z) - c softplus(-z) + b)`, at
    /// every horizon.
    Beta,
}

impl From<FormArg> for FormChoice {
    fn from(f: FormArg) -> Self {
        match f {
            FormArg::Auto => FormChoice::Auto,
            FormArg::Platt => FormChoice::Fixed(CalibrationForm::Platt),
            FormArg::Beta => FormChoice::Fixed(CalibrationForm::Beta),
        }
    }
}

/// `train --trajectory`: `model::TrajectoryInput`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum TrajectoryArg {
    /// The planned joint angles of ticks `t-N+1 ..= t+h_K`: the past and
    /// the known future of the plan (EMP as published).
    Planned,
    /// The planned joint angles of ticks `t-N+1 ..= t`, nothing from the future.
    HistoricalOnly,
    /// The measured joint angles of ticks `t-N+1 ..= t` in place of the plan.
    RealPosition,
}

impl From<TrajectoryArg> for TrajectoryInput {
    fn from(t: TrajectoryArg) -> Self {
        match t {
            TrajectoryArg::Planned => TrajectoryInput::Planned,
            TrajectoryArg::HistoricalOnly => TrajectoryInput::HistoricalOnly,
            TrajectoryArg::RealPosition => TrajectoryInput::RealPosition,
        }
    }
}

/// Arguments of `fall-guard-lab train`.
#[derive(Debug, Clone, Args)]
pub struct TrainArgs {
    /// Data set directory (recordings + manifest.json).
    #[arg(long)]
    pub data: PathBuf,
    /// P, MP, EP, EMP, or logreg (the logistic-regression baseline).
    #[arg(long, default_value = "EMP")]
    pub ablation: String,
    /// Network configuration: lite or paper.
    #[arg(long, default_value = "lite")]
    pub config: String,
    /// Seed of initialisation, dropout and window sampling.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Output model file.
    #[arg(long)]
    pub out: PathBuf,
    /// At most this many epochs.
    #[arg(long, default_value_t = 10)]
    pub epochs: usize,
    /// Early-stopping patience on validation loss, epochs.
    #[arg(long, default_value_t = 3)]
    pub patience: usize,
    /// Windows per step.
    #[arg(long, default_value_t = 4)]
    pub batch: usize,
    /// Learning-rate table: sim (SimP column) or robot (RP column).
    #[arg(long, default_value = "sim")]
    pub rates: String,
    /// The vision encoder's learning rate (EP, EMP), in place of the
    /// table's (the sim table's 1e-6 barely moves the encoder in 10 epochs).
    #[arg(long)]
    pub vision_lr: Option<f64>,
    /// Every learning rate multiplied by this (after --vision-lr); below 1
    /// to fine-tune (`--init`) without undoing what the network learnt.
    #[arg(long, default_value_t = 1.0)]
    pub lr_scale: f64,
    /// Window length N, ticks.
    #[arg(long, default_value_t = 60)]
    pub n_ticks: usize,
    /// Horizons, ticks, comma-separated.
    #[arg(long, default_value = "15,30,45,60", value_delimiter = ',')]
    pub horizons: Vec<usize>,
    /// Tick rate, Hz.
    #[arg(long, default_value_t = 30.0)]
    pub rate_hz: f64,
    /// Frame side, pixels.
    #[arg(long, default_value_t = 64)]
    pub frame_size: u32,
    /// Joint names in model order, comma-separated (default: the Poppy Humanoid's 25).
    #[arg(long, value_delimiter = ',')]
    pub joint_names: Option<Vec<String>>,
    /// What the data is, stored in the model file.
    #[arg(long, default_value = "simulated")]
    pub trained_on: String,
    /// How training and validation windows are drawn: `deployment` (one set
    /// for all horizons, balanced at the middle one) or `paper` (one set per
    /// horizon, balanced at it, windows ending at or before its stop line).
    #[arg(long, value_enum, default_value_t = ProtocolArg::Deployment)]
    pub protocol: ProtocolArg,
    /// Train one network per horizon P (each with that one horizon, its plan
    /// reaching P ticks ahead), written next to --out as `NAME.h<P>.EXT`.
    #[arg(long)]
    pub per_horizon: bool,
    /// What the trajectory encoder reads: `planned` (past and future plan),
    /// `historical-only` (past N plan ticks), `real-position` (the measured
    /// joints). Stored in the model file.
    #[arg(long, value_enum, default_value_t = TrajectoryArg::Planned)]
    pub trajectory: TrajectoryArg,
    /// Where the network trains: cpu, cuda, cuda:N (feature `cuda`) or wgpu
    /// (feature `wgpu`). The model file is the same whichever trains it.
    #[arg(long, default_value = "cpu")]
    pub device: TrainDevice,
    /// Where the run's checkpoints go (default: next to --out, `OUT.ckpt`).
    /// One per epoch; stopped and rerun with the same arguments, training
    /// resumes from the last; removed once the model is written.
    #[arg(long)]
    pub checkpoint_dir: Option<PathBuf>,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
    /// Fine-tune this model file: start from its weights, keep its sizes,
    /// trajectory input and standardisation.
    #[arg(long)]
    pub init: Option<PathBuf>,
}

impl From<TrainArgs> for TrainOptions {
    fn from(a: TrainArgs) -> Self {
        TrainOptions {
            data: a.data,
            ablation: a.ablation,
            config: a.config,
            seed: a.seed,
            out: a.out,
            epochs: a.epochs,
            patience: a.patience,
            batch: a.batch,
            rates: a.rates,
            vision_lr: a.vision_lr,
            lr_scale: a.lr_scale,
            n_ticks: a.n_ticks,
            horizons: a.horizons,
            rate_hz: a.rate_hz,
            frame_size: a.frame_size,
            joint_names: a.joint_names,
            trained_on: a.trained_on,
            protocol: a.protocol.into(),
            per_horizon: a.per_horizon,
            trajectory: a.trajectory.into(),
            device: a.device,
            checkpoint_dir: a.checkpoint_dir,
            quiet: a.quiet,
            init: a.init,
        }
    }
}

/// Arguments of `fall-guard-lab eval`.
#[derive(Debug, Clone, Args)]
pub struct EvalArgs {
    /// Model file (network or logreg baseline).
    #[arg(long)]
    pub model: PathBuf,
    /// More model files of other seeds: metrics become mean ± std.
    #[arg(long, num_args = 1..)]
    pub seeds: Vec<PathBuf>,
    /// Data set directory.
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// Split to evaluate.
    #[arg(long, default_value = "test")]
    pub split: String,
    /// Output directory (metrics.json, metrics.md, PNG plots).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Seed of the test-window sampler.
    #[arg(long, default_value_t = 12345)]
    pub sample_seed: u64,
    /// Windows drawn per episode (each an independent draw; under the paper
    /// protocol, per episode and horizon).
    #[arg(long, default_value_t = 1)]
    pub draws: usize,
    /// The protocol of the plots and of the report's top-level `horizons`;
    /// the report has a section for each protocol either way.
    #[arg(long, value_enum, default_value_t = ProtocolArg::Deployment)]
    pub protocol: ProtocolArg,
    /// Offline per-tick forecast of one recording (with --per-tick-out).
    #[arg(long)]
    pub recording: Option<PathBuf>,
    /// JSON lines: one forecast per tick of --recording.
    #[arg(long)]
    pub per_tick_out: Option<PathBuf>,
    /// How each network's classifier input projection is held: `as-file`
    /// (as the file stores it) or `int8` (`[model].projection`).
    #[arg(long, default_value = "as-file")]
    pub projection: ProjectionWeights,
    /// How each network's trajectory convolutions multiply: `f32` (as
    /// training evaluated them), `int8` or `auto` (`[model].convolutions`).
    #[arg(long, default_value = "f32")]
    pub convolutions: Convolutions,
}

impl From<EvalArgs> for EvalOptions {
    fn from(a: EvalArgs) -> Self {
        EvalOptions {
            model: a.model,
            seeds: a.seeds,
            data: a.data,
            split: a.split,
            out: a.out,
            sample_seed: a.sample_seed,
            draws: a.draws,
            protocol: a.protocol.into(),
            recording: a.recording,
            per_tick_out: a.per_tick_out,
            projection: a.projection,
            convolutions: a.convolutions,
        }
    }
}

/// `fall-guard-lab half`: the same model file with its weights in half precision.
#[derive(Debug, Args)]
pub struct HalfArgs {
    /// Model file to convert (f32 or already half).
    #[arg(long)]
    pub model: PathBuf,
    /// Output model file.
    #[arg(long)]
    pub out: PathBuf,
}

impl From<HalfArgs> for HalfOptions {
    fn from(a: HalfArgs) -> Self {
        HalfOptions {
            model: a.model,
            out: a.out,
        }
    }
}

/// Arguments of `fall-guard-lab finetune`.
#[derive(Debug, Clone, Args)]
pub struct FinetuneArgs {
    /// The network to fine-tune (e.g. models/mp.bpk).
    #[arg(long)]
    pub model: PathBuf,
    /// The owner's recordings (`fall-guard record`), each labelled (`fall-guard label --no-fall` or `--fall-at S`).
    #[arg(long = "recording", required = true)]
    pub recordings: Vec<PathBuf>,
    /// The simulated data set the network was trained on (its splits are mixed in).
    #[arg(long)]
    pub data: PathBuf,
    /// Output directory: the mixed data set, the network, card.md and card.json.
    #[arg(long)]
    pub out: PathBuf,
    /// Share of each walk held back (its end) to measure on.
    #[arg(long, default_value_t = 0.4)]
    pub holdout: f64,
    /// How many times each owner part is listed in the training split.
    #[arg(long, default_value_t = 50)]
    pub owner_copies: usize,
    /// Training epochs at most.
    #[arg(long, default_value_t = 3)]
    pub epochs: usize,
    /// The shipped network's learning rates (the sim table) multiplied by
    /// this: small, so that the fine-tune adds the owner's walking to what
    /// the network learnt instead of training it anew.
    #[arg(long, default_value_t = 0.1)]
    pub lr_scale: f64,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// The latch's horizon, ms, as `[model].horizon_ms`.
    #[arg(long, default_value_t = 2000)]
    pub horizon_ms: u32,
    /// As `[model].release_hold_ms`.
    #[arg(long, default_value_t = 1000)]
    pub release_hold_ms: u32,
    /// The daemon config whose `[model.thresholds]` holds the shipped
    /// network's pair (default: the embedded one, the shipped pairs).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// The shipped network's pair, in place of the config's (with --release).
    #[arg(long, requires = "release")]
    pub trigger: Option<f32>,
    #[arg(long, requires = "trigger")]
    pub release: Option<f32>,
    /// The data set whose validation split the new pair is chosen on: the
    /// retrain's choice set (`$FALL_GUARD_DATA/choice`: validation falls and
    /// walking), as the shipped pair was chosen. Default: the validation
    /// split of the set made from --data, whose non-falling episodes
    /// include the hard ones the robot rode out, so the pair chosen rises.
    #[arg(long)]
    pub choice: Option<PathBuf>,
    /// Budgets of the new pair's choice on the validation walks.
    #[arg(long, default_value_t = 0.1)]
    pub max_false_alarms_per_min: f64,
    #[arg(long, default_value_t = 0.01)]
    pub max_held_share: f64,
    /// Where the network trains (see `train --device`).
    #[arg(long, default_value = "cpu")]
    pub device: TrainDevice,
}

impl From<FinetuneArgs> for fall_guard_lab::finetune::FinetuneOptions {
    fn from(a: FinetuneArgs) -> Self {
        fall_guard_lab::finetune::FinetuneOptions {
            model: a.model,
            recordings: a.recordings,
            data: a.data,
            out: a.out,
            holdout: a.holdout,
            owner_copies: a.owner_copies,
            epochs: a.epochs,
            lr_scale: a.lr_scale,
            seed: a.seed,
            horizon_ms: a.horizon_ms,
            release_hold_ms: a.release_hold_ms,
            pair: a.trigger.zip(a.release),
            config: a.config,
            choice: a.choice,
            max_false_alarms_per_min: a.max_false_alarms_per_min,
            max_held_share: a.max_held_share,
            device: a.device,
        }
    }
}

/// Arguments of `fall-guard-lab ranges`.
#[derive(Debug, Clone, Args)]
pub struct RangesArgs {
    /// Model file (written in place unless `--out` is given; the weights are copied byte for byte).
    #[arg(long)]
    pub model: PathBuf,
    /// Data set directory the network was trained on.
    #[arg(long)]
    pub data: PathBuf,
    /// Split to measure: the one the network was trained on.
    #[arg(long, default_value = "train")]
    pub split: Split,
    /// Output model file.
    #[arg(long)]
    pub out: Option<PathBuf>,
}

impl From<RangesArgs> for fall_guard_lab::ranges::RangesOptions {
    fn from(a: RangesArgs) -> Self {
        fall_guard_lab::ranges::RangesOptions {
            model: a.model,
            data: a.data,
            split: a.split,
            out: a.out,
        }
    }
}

/// Arguments of `fall-guard-lab bench`.
#[derive(Debug, Clone, Args)]
pub struct BenchArgs {
    /// Training steps measured (batch 4, EMP), after one unmeasured step.
    #[arg(long, default_value_t = 10)]
    pub train_steps: usize,
    /// Device of the training: cpu, cuda, cuda:N or wgpu (see `train --device`).
    #[arg(long, default_value = "cpu")]
    pub device: TrainDevice,
    /// Network configuration (N=60, C=25, 64 px): lite or paper.
    #[arg(long, default_value = "lite")]
    pub config: String,
    /// Write the results here as JSON.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

impl From<BenchArgs> for TrainBenchOptions {
    fn from(a: BenchArgs) -> Self {
        TrainBenchOptions {
            train_steps: a.train_steps,
            device: a.device,
            config: a.config,
            json: a.json,
        }
    }
}

/// Arguments of `fall-guard-lab calibrate`.
#[derive(Debug, Clone, Args)]
pub struct CalibrateArgs {
    /// Model file to calibrate (a network; any calibration it has is replaced).
    #[arg(long)]
    pub model: PathBuf,
    /// Data set directory.
    #[arg(long)]
    pub data: PathBuf,
    /// Split to fit on: never the one the model is judged on.
    #[arg(long, default_value = "validation")]
    pub split: String,
    /// Windows drawn per episode (each an independent draw).
    #[arg(long, default_value_t = 10)]
    pub draws: usize,
    /// Seed of the window sampler.
    #[arg(long, default_value_t = 12345)]
    pub sample_seed: u64,
    /// How the fitting windows are drawn: `deployment` or `paper` (each
    /// horizon fitted on its own balanced set); see `train --protocol`.
    #[arg(long, value_enum, default_value_t = ProtocolArg::Deployment)]
    pub protocol: ProtocolArg,
    /// Output model file (may be the input).
    #[arg(long)]
    pub out: PathBuf,
    /// Store the weights in half precision (f16).
    #[arg(long)]
    pub half: bool,
    /// The map's form at each horizon: `auto` chooses between Platt scaling
    /// and beta calibration by cross-validation on the fitting windows.
    #[arg(long, value_enum, default_value_t = FormArg::Auto)]
    pub form: FormArg,
}

impl From<CalibrateArgs> for CalibrateOptions {
    fn from(a: CalibrateArgs) -> Self {
        CalibrateOptions {
            model: a.model,
            data: a.data,
            split: a.split,
            draws: a.draws,
            sample_seed: a.sample_seed,
            protocol: a.protocol.into(),
            out: a.out,
            half: a.half,
            form: a.form.into(),
        }
    }
}

/// `fall-guard-lab warnings`.
#[derive(Debug, Args)]
pub struct WarningsArgs {
    /// Model file (EMP, MP, EP or P).
    #[arg(long)]
    pub model: PathBuf,
    /// Data set directory (recordings + manifest.json).
    #[arg(long)]
    pub data: PathBuf,
    /// Split to replay: choose thresholds on `validation`, report on `test`.
    #[arg(long, default_value = "validation")]
    pub split: Split,
    /// Horizon the latch watches, ms (one of the model's horizons).
    #[arg(long, default_value_t = 1000)]
    pub horizon_ms: u32,
    /// Latch on at or above this probability.
    #[arg(long, default_value_t = 0.7)]
    pub trigger: f32,
    /// Latch off below this probability...
    #[arg(long, default_value_t = 0.4)]
    pub release: f32,
    /// ... for this long, ms, as `[model].release_hold_ms` (0: at once).
    #[arg(long, default_value_t = 0)]
    pub release_hold_ms: u32,
    /// Search the thresholds on this split instead (trigger 0.30..0.95 by
    /// 0.05, then 0.97, 0.98, 0.99 and 0.995; release = trigger - 0.3, at
    /// least 0.05): the lowest trigger whose
    /// false-alarm rate is within --max-false-alarms-per-min and whose time
    /// held within --max-held-share.
    #[arg(long)]
    pub choose: bool,
    /// False-alarm budget for --choose, per minute of non-falling walking.
    #[arg(long, default_value_t = 0.5)]
    pub max_false_alarms_per_min: f64,
    /// Time-held budget for --choose: the share of non-falling time with
    /// `fall_imminent` asserted once the window is full.
    #[arg(long, default_value_t = 0.01)]
    pub max_held_share: f64,
    /// What a window with an input outside the network's training range
    /// does, as the daemon's `[model].out_of_range`: hold (not valid, the
    /// latch asserted) or forecast.
    #[arg(long, value_enum, default_value_t = OutOfRangeArg::Hold)]
    pub out_of_range: OutOfRangeArg,
    /// JSON report.
    #[arg(long)]
    pub out: Option<PathBuf>,
}

/// `warnings --out-of-range`: `[model].out_of_range`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum OutOfRangeArg {
    Hold,
    Forecast,
}

impl From<WarningsArgs> for WarningsOptions {
    fn from(a: WarningsArgs) -> Self {
        WarningsOptions {
            model: a.model,
            data: a.data,
            split: a.split,
            horizon_ms: a.horizon_ms,
            trigger: a.trigger,
            release: a.release,
            release_hold_ms: a.release_hold_ms,
            choose: a.choose,
            max_false_alarms_per_min: a.max_false_alarms_per_min,
            max_held_share: a.max_held_share,
            hold_out_of_range: a.out_of_range == OutOfRangeArg::Hold,
            out: a.out,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_command_line_is_consistent() {
        use clap::CommandFactory;
        Cli::command().debug_assert();
    }

    #[test]
    fn eval_parses_its_projection() {
        let eval = |extra: &[&str]| {
            let mut all = vec!["fall-guard-lab", "eval", "--model", "m.bpk"];
            all.extend_from_slice(extra);
            match Cli::try_parse_from(all).expect("parses").command {
                Command::Eval(a) => EvalOptions::from(a),
                _ => panic!("not eval"),
            }
        };
        assert_eq!(eval(&[]).projection, ProjectionWeights::AsFile);
        assert_eq!(eval(&[]).convolutions, Convolutions::F32);
        assert_eq!(
            eval(&["--convolutions", "int8"]).convolutions,
            Convolutions::Int8
        );
        assert_eq!(
            eval(&["--projection", "int8"]).projection,
            ProjectionWeights::Int8
        );
        assert!(
            Cli::try_parse_from(["fall-guard-lab", "replay"]).is_err(),
            "the daemon is the robot binary's"
        );
    }

    #[test]
    fn train_and_bench_take_a_device_flag() {
        let train = |extra: &[&str]| {
            let mut all = vec!["fall-guard-lab", "train", "--data", "d", "--out", "o.bpk"];
            all.extend_from_slice(extra);
            Cli::try_parse_from(all).map(|c| match c.command {
                Command::Train(a) => TrainOptions::from(a),
                _ => panic!("not train"),
            })
        };
        let t = train(&[]).unwrap();
        assert_eq!(t.device, TrainDevice::Cpu, "the CPU by default");
        assert_eq!(t.protocol, Protocol::Deployment);
        assert_eq!(t.trajectory, TrajectoryInput::Planned);
        let t = train(&["--device", "cuda:1"]).unwrap();
        assert_eq!(t.device, TrainDevice::Cuda(1));
        let t = train(&["--protocol", "paper", "--trajectory", "historical-only"]).unwrap();
        assert_eq!(
            (t.protocol, t.trajectory),
            (Protocol::Paper, TrajectoryInput::HistoricalOnly)
        );
        let e = train(&["--device", "tpu"])
            .expect_err("unknown device refused")
            .to_string();
        assert!(e.contains("cuda:N"), "{e}");
        let cli = Cli::try_parse_from(["fall-guard-lab", "bench", "--device", "wgpu"]).unwrap();
        let Command::Bench(b) = cli.command else {
            panic!("not bench");
        };
        let b = TrainBenchOptions::from(b);
        assert_eq!(b.train_steps, 10);
        assert_eq!(b.device, TrainDevice::Wgpu);
    }

    #[test]
    fn training_on_a_backend_not_compiled_in_fails_before_reading_data() {
        for (device, built) in [
            ("cuda", cfg!(feature = "cuda")),
            ("wgpu", cfg!(feature = "wgpu")),
        ] {
            if built {
                continue;
            }
            let cli = Cli::try_parse_from([
                "fall-guard-lab",
                "train",
                "--data",
                "/nonexistent/data",
                "--out",
                "/nonexistent/o.bpk",
                "--device",
                device,
            ])
            .unwrap();
            let Command::Train(args) = cli.command else {
                panic!("not train");
            };
            let args = TrainOptions::from(args);
            assert_ne!(args.device, TrainDevice::Cpu);
            let e = format!(
                "{:#}",
                fall_guard_lab::commands::run_train(&args).expect_err("not compiled in")
            );
            assert!(
                e.contains(&format!("--features {device}")) && !e.contains("/nonexistent"),
                "{e}"
            );
        }
    }
}
