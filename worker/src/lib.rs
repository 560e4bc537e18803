//! The StylizedNeRF worker: registers with the coordinator, leases stage tasks, runs them with
//! the engine on a blocking thread, streams progress in heartbeats, checkpoints to the object
//! store and resumes from there, and uploads its outputs (with `manifest.json` last) before
//! completing each task.
//!
//! Embedding:
//!
//! ```no_run
//! # async fn demo() -> anyhow::Result<()> {
//! use stylenerf_worker::{Worker, WorkerConfig};
//! let mut config = WorkerConfig::new("http://127.0.0.1:50051");
//! config.token = Some("worker-token".into());
//! let worker = Worker::register(config).await?;
//! let handle = worker.handle(); // handle.shutdown(), handle.subscribe()
//! let summary = worker.run().await?;
//! # Ok(()) }
//! ```

pub mod archive;
pub mod config;
pub mod connection;
pub mod context;
pub mod error;
pub mod events;
pub mod logging;
pub mod progress;
pub mod retry;
pub mod scratch;
pub mod stages;
pub mod store;
pub mod task;
pub mod task_config;
pub mod worker;

pub use config::{WorkerArgs, WorkerConfig};
pub use error::TaskError;
pub use events::{TaskResult, WorkerEvent};
pub use task::MANIFEST;
pub use worker::{RunSummary, Worker, WorkerHandle};

/// Runs a worker until SIGINT/SIGTERM (a second signal exits at once); what `stylenerf worker`
/// and `stylenerf-worker` do.
pub async fn run_until_signal(config: WorkerConfig) -> anyhow::Result<RunSummary> {
    let worker = Worker::register(config).await?;
    let handle = worker.handle();
    tokio::spawn(async move {
        wait_for_signal().await;
        tracing::info!(
            "signal received: checkpointing and releasing running tasks (again to exit now)"
        );
        handle.shutdown();
        wait_for_signal().await;
        tracing::warn!("second signal: exiting without releasing the leases");
        std::process::exit(130);
    });
    let summary = worker.run().await?;
    tracing::info!(
        completed = summary.completed,
        failed = summary.failed,
        cancelled = summary.cancelled,
        released = summary.released,
        "worker stopped"
    );
    Ok(summary)
}

async fn wait_for_signal() {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{signal, SignalKind};
        let mut term = signal(SignalKind::terminate()).expect("SIGTERM handler");
        tokio::select! {
            _ = tokio::signal::ctrl_c() => {}
            _ = term.recv() => {}
        }
    }
    #[cfg(not(unix))]
    {
        let _ = tokio::signal::ctrl_c().await;
    }
}
