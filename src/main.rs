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
    /// Per-tick latency and training throughput of the network.
    Bench(fall_guard::train::bench::BenchArgs),
}

fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::from_default_env())
        .with_writer(std::io::stderr)
        .init();
    match Cli::parse().command {
        Command::Bench(args) => {
            fall_guard::train::bench::run_bench(&args)?;
        }
    }
    Ok(())
}
