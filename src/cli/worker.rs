//! `stylenerf worker`: leases stage tasks from a coordinator and runs them until Ctrl-C or
//! SIGTERM, then checkpoints the running tasks, uploads the checkpoints and releases their
//! leases (see `docs/OPERATIONS.md`). With `--metrics-listen` it serves Prometheus metrics and
//! `/healthz` for probes, as the coordinator does.

use stylenerf_worker::WorkerArgs;

/// Options of `stylenerf worker`.
#[derive(Debug, clap::Args)]
pub struct WorkerCommand {
    #[command(flatten)]
    pub args: WorkerArgs,
    /// Prometheus metrics (`/metrics`) and liveness (`/healthz`) listen address, or `off`
    #[arg(long, env = "STYLENERF_WORKER_METRICS_LISTEN", default_value = "off")]
    pub metrics_listen: String,
}

pub fn run(command: WorkerCommand) -> anyhow::Result<()> {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    let metrics_listen: Option<std::net::SocketAddr> = match command.metrics_listen.as_str() {
        "off" => None,
        addr => Some(addr.parse().map_err(|e| {
            anyhow::anyhow!("--metrics-listen {addr:?}: {e} (expected host:port or `off`)")
        })?),
    };
    runtime.block_on(async {
        let (stop, stop_rx) = tokio::sync::watch::channel(false);
        let endpoint = match metrics_listen {
            Some(addr) => {
                let (addr, task) = stylenerf_server::metrics_http::serve(addr, stop_rx).await?;
                tracing::info!(metrics = %format!("http://{addr}/metrics"), "worker metrics");
                Some(task)
            }
            None => None,
        };
        let result = stylenerf_worker::run_until_signal(command.args.into_config()).await;
        let _ = stop.send(true);
        if let Some(task) = endpoint {
            let _ = task.await;
        }
        result.map(|_| ())
    })
}
