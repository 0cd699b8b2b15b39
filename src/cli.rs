//! The robot binary's command line: clap's parsing structs, each turned
//! into the runtime's plain options struct (`daemon::RunOptions`,
//! `model::bench::BenchOptions`, ...) by `From`. The runtime has no clap;
//! `Ablation`, `ProjectionWeights` and `Convolutions` parse by `FromStr`. Training and
//! evaluation are the lab's binary (`fall-guard-lab`), not this one.

use std::path::PathBuf;

use clap::{Args, Parser, Subcommand};

use fall_guard_runtime::daemon::bench::BenchDaemonOptions;
use fall_guard_runtime::daemon::{LabelOptions, RecordOptions, ReplayOptions, RunOptions};
use fall_guard_runtime::model::bench::BenchOptions;
use fall_guard_runtime::model::{Ablation, Convolutions, ProjectionWeights};

#[derive(Debug, Parser)]
#[command(
    name = "fall-guard",
    version,
    about = "Forecasts falls of a walking Poppy Humanoid and publishes them on ROS 2"
)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// Run the onboard daemon (servos, camera and plan in; forecasts out on ROS 2).
    Run(RunArgs),
    /// Replay an MCAP recording through the daemon with recorded time.
    Replay(ReplayArgs),
    /// Record the live streams as an MCAP recording.
    Record(RecordArgs),
    /// Mark the fall onset of a recording (in place).
    Label(LabelArgs),
    /// Benchmark the daemon: sensor-to-publish latency and memory while replaying at maximum speed.
    BenchDaemon(BenchDaemonArgs),
    /// Per-tick latency of each network's streaming forecast.
    Bench(BenchArgs),
}

/// `fall-guard run`: the onboard daemon.
#[derive(Debug, Clone, Args)]
pub struct RunArgs {
    /// The config file (see config/poppy_humanoid.toml).
    #[arg(long, default_value = "/etc/fall-guard/poppy_humanoid.toml")]
    pub config: PathBuf,
    /// ROS namespace for every relative topic (overrides `[ros].namespace`).
    #[arg(long)]
    pub namespace: Option<String>,
}

impl From<RunArgs> for RunOptions {
    fn from(a: RunArgs) -> Self {
        RunOptions {
            config: a.config,
            namespace: a.namespace,
        }
    }
}

/// `fall-guard replay`: the daemon on a recording, with recorded time.
#[derive(Debug, Clone, Args)]
pub struct ReplayArgs {
    /// Config file; without it, the embedded config/replay.toml.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// MCAP recording; without it, `[replay].recording` of the config.
    #[arg(long)]
    pub recording: Option<PathBuf>,
    /// Recorded time runs this many times faster than real time.
    #[arg(long, conflicts_with = "max_speed")]
    pub speed: Option<f64>,
    /// As fast as inference allows (every tick forecast, none skipped).
    #[arg(long)]
    pub max_speed: bool,
    /// Do not print one line per forecast on stdout.
    #[arg(long)]
    pub quiet: bool,
    /// Also write the recording with the daemon's outputs merged in
    /// (`/fall_guard/forecast`, `/fall_guard/fall_imminent`, `/diagnostics`
    /// at recorded time), e.g. to open in Foxglove with
    /// `docs/foxglove/fall-guard.json`.
    #[arg(long)]
    pub out: Option<PathBuf>,
}

impl From<ReplayArgs> for ReplayOptions {
    fn from(a: ReplayArgs) -> Self {
        ReplayOptions {
            config: a.config,
            recording: a.recording,
            speed: a.speed,
            max_speed: a.max_speed,
            quiet: a.quiet,
            out: a.out,
        }
    }
}

/// `fall-guard record`: record the live streams as an MCAP recording.
#[derive(Debug, Clone, Args)]
pub struct RecordArgs {
    #[arg(long)]
    pub config: PathBuf,
    /// Output file (.mcap).
    #[arg(long)]
    pub out: PathBuf,
    /// Stop after this many seconds (default: until Ctrl-C / SIGTERM).
    #[arg(long)]
    pub duration_s: Option<f64>,
}

impl From<RecordArgs> for RecordOptions {
    fn from(a: RecordArgs) -> Self {
        RecordOptions {
            config: a.config,
            out: a.out,
            duration_s: a.duration_s,
        }
    }
}

/// `fall-guard label`: mark the fall onset of a recording, in place.
#[derive(Debug, Clone, Args)]
pub struct LabelArgs {
    /// The recording to label.
    pub recording: PathBuf,
    /// Seconds after the recording's first message when the fall starts.
    #[arg(long, required_unless_present = "no_fall", conflicts_with = "no_fall")]
    pub fall_at: Option<f64>,
    /// The episode does not fall.
    #[arg(long)]
    pub no_fall: bool,
}

impl From<LabelArgs> for LabelOptions {
    fn from(a: LabelArgs) -> Self {
        LabelOptions {
            recording: a.recording,
            fall_at: a.fall_at,
            no_fall: a.no_fall,
        }
    }
}

/// `fall-guard bench-daemon`.
#[derive(Debug, Clone, Args)]
pub struct BenchDaemonArgs {
    /// Config file; without it, the embedded config/replay.toml.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Recording to loop; without it, `[replay].recording`.
    #[arg(long)]
    pub recording: Option<PathBuf>,
    /// Wall time to run, seconds.
    #[arg(long, default_value_t = 120.0)]
    pub duration_s: f64,
    /// Also write the report as JSON here.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Replay at this many times real time instead of maximum speed: the
    /// sensor-to-publish latency as on the robot (at maximum speed a sample
    /// also waits for the previous tick's inference).
    #[arg(long)]
    pub speed: Option<f64>,
}

impl From<BenchDaemonArgs> for BenchDaemonOptions {
    fn from(a: BenchDaemonArgs) -> Self {
        BenchDaemonOptions {
            config: a.config,
            recording: a.recording,
            duration_s: a.duration_s,
            json: a.json,
            speed: a.speed,
        }
    }
}

/// Arguments of `fall-guard bench`.
#[derive(Debug, Clone, Args)]
pub struct BenchArgs {
    /// Model file whose configuration is benchmarked (every ablation of it;
    /// the file's own ablation with its weights, held at the file's
    /// precision); without one, the reference `lite` configuration (N=60,
    /// C=25, 64 px) with freshly initialised f32 weights.
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Configuration when no model is given: lite or paper.
    #[arg(long, default_value = "lite")]
    pub config: String,
    /// Write the results here as JSON.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Ticks measured per ablation (after the window is full).
    #[arg(long, default_value_t = 300)]
    pub ticks: usize,
    /// Measure only these ablations (repeatable); all four when absent.
    #[arg(long = "ablation")]
    pub ablations: Vec<Ablation>,
    /// How the classifier's input projection is held: `int8`, as the
    /// daemon holds it by default (`[model].projection`), or `as-file`.
    #[arg(long, default_value = "int8")]
    pub projection: ProjectionWeights,
    /// How the trajectory encoder's convolutions multiply: `auto`, as the
    /// daemon runs them by default (`[model].convolutions`: `int8` on x86-64
    /// with AVX2, `f32` elsewhere), `int8` or `f32`.
    #[arg(long, default_value = "auto")]
    pub convolutions: Convolutions,
}

impl From<BenchArgs> for BenchOptions {
    fn from(a: BenchArgs) -> Self {
        BenchOptions {
            model: a.model,
            config: a.config,
            json: a.json,
            ticks: a.ticks,
            ablations: a.ablations,
            projection: a.projection,
            convolutions: a.convolutions,
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
    fn daemon_commands_parse_into_the_library_options() {
        let cli = Cli::try_parse_from(["fall-guard", "replay", "--max-speed", "--quiet"])
            .expect("parses");
        let Command::Replay(args) = cli.command else {
            panic!("not replay");
        };
        let o = ReplayOptions::from(args);
        assert!(o.max_speed && o.quiet && o.config.is_none() && o.speed.is_none());
        assert!(
            Cli::try_parse_from(["fall-guard", "replay", "--max-speed", "--speed", "2"]).is_err(),
            "--speed conflicts with --max-speed"
        );
        let cli = Cli::try_parse_from(["fall-guard", "run"]).expect("parses");
        let Command::Run(args) = cli.command else {
            panic!("not run");
        };
        assert_eq!(
            RunOptions::from(args).config,
            PathBuf::from("/etc/fall-guard/poppy_humanoid.toml")
        );
        assert!(Cli::try_parse_from(["fall-guard", "label", "r.mcap"]).is_err());
        let cli = Cli::try_parse_from(["fall-guard", "bench-daemon"]).expect("parses");
        let Command::BenchDaemon(args) = cli.command else {
            panic!("not bench-daemon");
        };
        assert_eq!(BenchDaemonOptions::from(args).duration_s, 120.0);
    }

    #[test]
    fn bench_parses_its_projection_and_ablations() {
        let cli = Cli::try_parse_from([
            "fall-guard",
            "bench",
            "--ablation",
            "EMP",
            "--projection",
            "as-file",
        ])
        .expect("parses");
        let Command::Bench(args) = cli.command else {
            panic!("not bench");
        };
        let b = BenchOptions::from(args);
        assert_eq!(b.ablations, vec![Ablation::EMP]);
        assert_eq!(b.projection, ProjectionWeights::AsFile);
        let cli = Cli::try_parse_from(["fall-guard", "bench"]).expect("parses");
        let Command::Bench(args) = cli.command else {
            panic!("not bench");
        };
        assert_eq!(BenchOptions::from(args).projection, ProjectionWeights::Int8);
        assert!(Cli::try_parse_from(["fall-guard", "bench", "--projection", "f8"]).is_err());
        assert!(
            Cli::try_parse_from(["fall-guard", "train", "--data", "d", "--out", "o"]).is_err(),
            "training is the lab's binary"
        );
    }
}
