//! `stylenerf-worker`: a standalone worker process (the same as `stylenerf worker`).

use clap::Parser;
use stylenerf_worker::logging::{self, LogFormat};
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
    /// Log format.
    #[arg(long, env = "STYLENERF_LOG_FORMAT", value_enum, default_value_t = LogFormat::Pretty)]
    log_format: LogFormat,
}

fn main() -> anyhow::Result<()> {
    // Before any other thread exists: the allocator's arenas are chosen per thread.
    stylenerf_engine::keep_freed_memory();
    stylenerf_engine::one_arena_for_all_threads();
    let cli = Cli::parse();
    logging::init(&cli.log, cli.log_format);
    tokio::runtime::Runtime::new()?
        .block_on(stylenerf_worker::run_until_signal(cli.worker.into_config()))?;
    Ok(())
}
