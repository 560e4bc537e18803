//! `stylenerf coordinator`: runs the coordinator (gRPC job and worker APIs, SQLite, artifact
//! store, metrics) until Ctrl-C or SIGTERM, then shuts it down gracefully.

use stylenerf_server::{Coordinator, CoordinatorArgs};

/// Options of `stylenerf coordinator` (see `docs/OPERATIONS.md`).
#[derive(Debug, clap::Args)]
pub struct CoordinatorCommand {
    #[command(flatten)]
    pub args: CoordinatorArgs,
}

pub fn run(command: CoordinatorCommand) -> anyhow::Result<()> {
    let config = super::common::with_engine_checks(command.args.into_config()?);
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    runtime.block_on(async move {
        // Start-up and shutdown are logged by the coordinator itself (in the log format asked
        // for: with `--log-format json`, stderr holds JSON lines only).
        let coordinator = Coordinator::start(config).await?;
        shutdown_signal().await;
        tracing::info!("signal received: shutting down");
        coordinator.shutdown().await
    })
}

/// Resolves on Ctrl-C or (on Unix) SIGTERM (also used by `demo` and `up`).
pub(crate) async fn shutdown_signal() {
    #[cfg(unix)]
    {
        let mut term =
            match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
                Ok(term) => term,
                Err(_) => {
                    let _ = tokio::signal::ctrl_c().await;
                    return;
                }
            };
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
