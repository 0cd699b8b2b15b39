//! The `fall-guard` command line: parses arguments and calls the library.

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "fall-guard",
    version,
    about = "Forecasts falls of a walking Poppy Humanoid (EMP)"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Train a model (or the logistic baseline) on a data set.
    Train(fall_guard::train::cli::TrainArgs),
    /// Evaluate model files on a split; or forecast one recording per tick.
    Eval(fall_guard::train::cli::EvalArgs),
    /// Per-tick latency and training throughput of the network.
    Bench(fall_guard::train::bench::BenchArgs),
}

fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::from_default_env())
        .with_writer(std::io::stderr)
        .init();
    match Cli::parse().command {
        Command::Train(args) => fall_guard::train::cli::run_train(&args)?,
        Command::Eval(args) => fall_guard::train::cli::run_eval(&args)?,
        Command::Bench(args) => {
            fall_guard::train::bench::run_bench(&args)?;
        }
    }
    Ok(())
}
