//! The robot's binary, `fall-guard`: parses arguments (`cli.rs`, the only
//! place that knows clap for the daemon's subcommands), dispatches to the
//! runtime (`fall_guard_runtime`) and prints what it returns. It depends on
//! the runtime only: training is the lab's binary (`fall-guard-lab`).

mod cli;

use anyhow::Result;
use clap::Parser;

use cli::{Cli, Command};
use fall_guard_runtime::daemon;
use fall_guard_runtime::model::bench;

/// Logs when `RUST_LOG` is unset: fall-guard at info; DDS (rustdds,
/// ros2-client) only from warnings up, less two sources that say nothing an
/// operator can act on (set `RUST_LOG` to see them again):
/// - `rustdds::rtps::writer`: with `ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`
///   every sample to a discovered reader whose locators are all off
///   loopback logs `No locators` (about 30 lines per second with one rclpy
///   peer); delivery to the readers that can be reached goes on;
/// - `rustdds::network::udp_listener`: leaving the DDS multicast group on a
///   loopback-only participant at shutdown fails (`AddrNotAvailable`) and
///   logs an ERROR although nothing was lost;
/// - `rustdds::network::udp_sender`: every datagram over 1,500 bytes logs
///   `Message size = N` as a WARN, although UDP carries it; with DDS
///   Security on, discovery messages (which carry the security tokens) are
///   all that large, and each one logged.
const DEFAULT_LOG_FILTER: &str =
    "info,rustdds=warn,ros2_client=warn,rustdds::rtps::writer=error,rustdds::network::udp_listener=off,rustdds::network::udp_sender=error";

fn init_logging() {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(DEFAULT_LOG_FILTER));
    // Logs go to stderr: stdout carries the forecasts of `replay`.
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        // No colour codes into journald or a pipe.
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .init();
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    init_logging();
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    match cli.command {
        Command::Run(args) => {
            runtime.block_on(daemon::run(args.into()))?;
        }
        Command::Replay(args) => {
            let report = runtime.block_on(daemon::replay(args.into()))?;
            if report.interrupted {
                anyhow::bail!("replay of {} interrupted", report.recording.display());
            }
        }
        Command::Record(args) => {
            let summary = runtime.block_on(daemon::record(args.into()))?;
            eprintln!(
                "recorded {} joint states, {} frames, {} plans over {:.1} s",
                summary.counts.joints,
                summary.counts.camera,
                summary.counts.plan,
                summary.duration_ns as f64 / 1e9
            );
        }
        Command::Label(args) => match daemon::label(&args.clone().into())? {
            Some(onset_ns) => eprintln!(
                "{}: fall onset at log time {onset_ns} ns",
                args.recording.display()
            ),
            None => eprintln!("{}: labelled as not falling", args.recording.display()),
        },
        Command::BenchDaemon(args) => {
            let report = runtime.block_on(daemon::bench::run(args.into()))?;
            println!("{}", report.json());
        }
        Command::Bench(args) => {
            let options = bench::BenchOptions::from(args);
            eprintln!(
                "input projection held {}, convolutions in {}",
                options.projection.name(),
                options.convolutions.resolved().name()
            );
            let report = bench::run_bench(&options)?;
            for ablation in &report.ablations {
                eprintln!("{}", ablation.summary());
            }
        }
    }
    Ok(())
}
