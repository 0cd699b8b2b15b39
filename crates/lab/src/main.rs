//! The lab's binary, `fall-guard-lab`: training, evaluation, calibration,
//! the latch's warnings and the training benchmark, on a workstation. It
//! parses arguments (`cli.rs`, the only place that knows clap for these
//! commands), dispatches to the lab library and prints what it returns.
//! The robot's binary (`fall-guard`) does not link any of it.

mod cli;

use anyhow::Result;
use clap::Parser;

use cli::{Cli, Command};
use fall_guard_lab::{bench, calibrate, commands, warning};

/// Logs when `RUST_LOG` is unset: what a command is doing, at info.
const DEFAULT_LOG_FILTER: &str = "info";

fn main() -> Result<()> {
    let cli = Cli::parse();
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(DEFAULT_LOG_FILTER));
    // Logs go to stderr: stdout carries the tables.
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .init();
    match cli.command {
        Command::Train(args) => commands::run_train(&args.into())?,
        Command::Eval(args) => {
            if let Some(report) = commands::run_eval(&args.into())? {
                print!("{}", report.markdown());
            }
        }
        Command::Warnings(args) => print!("{}", warning::run_warnings(&args.into())?.table()),
        Command::Half(args) => commands::run_half(&args.into())?,
        Command::Finetune(args) => {
            print!(
                "{}",
                fall_guard_lab::finetune::run_finetune(&args.into())?.markdown()
            )
        }
        Command::Ranges(args) => {
            println!("{}", fall_guard_lab::ranges::run_ranges(&args.into())?)
        }
        Command::Calibrate(args) => print!("{}", calibrate::run_calibrate(&args.into())?.table()),
        Command::Bench(args) => {
            let report = bench::run_train_bench(&args.into())?;
            eprintln!(
                "training (EMP, batch 4, {}): {:.1} samples/s",
                report.train_device, report.train_samples_per_s
            );
        }
    }
    Ok(())
}
