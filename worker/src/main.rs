//! `stylenerf-worker`: a standalone worker process (the same as `stylenerf worker`).

use clap::Parser;
use stylenerf_worker::WorkerArgs;

/// Leases StylizedNeRF stage tasks from a coordinator and runs them.
#[derive(Debug, Parser)]
#[command(name = "stylenerf-worker", version, about)]
struct Cli {
    #[command(flatten)]
    worker: WorkerArgs,
    /// Log filter (tracing `EnvFilter` syntax), e.g. `info` or `stylenerf_worker=debug`.
    #[arg(long, env = "STYLENERF_LOG", default_value = "info")]
    log: String,
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    stylenerf_engine::malloc::keep_freed_memory();
    let cli = Cli::parse();
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_new(&cli.log)
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .init();
    stylenerf_worker::run_until_signal(cli.worker.into_config()).await?;
    Ok(())
}
