//! Prometheus metrics: installs the process-wide `metrics` recorder once and serves its text
//! exposition at `/metrics` on a separate port.

use metrics_exporter_prometheus::{Matcher, PrometheusBuilder, PrometheusHandle};
use std::net::SocketAddr;
use std::sync::OnceLock;
use tokio::sync::watch;

static HANDLE: OnceLock<Option<PrometheusHandle>> = OnceLock::new();

/// The recorder's handle; `None` if the embedding program installed another recorder.
pub fn handle() -> Option<PrometheusHandle> {
    HANDLE
        .get_or_init(|| {
            let recorder = PrometheusBuilder::new()
                .set_buckets_for_metric(
                    Matcher::Full("stylenerf_task_duration_seconds".into()),
                    &[
                        0.01, 0.1, 1.0, 10.0, 60.0, 300.0, 900.0, 1800.0, 3600.0, 7200.0,
                    ],
                )
                .ok()?
                .set_buckets_for_metric(
                    Matcher::Full("stylenerf_write_group_size".into()),
                    &[1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0],
                )
                .ok()?
                .build_recorder();
            let handle = recorder.handle();
            metrics::set_global_recorder(recorder).ok()?;
            describe();
            Some(handle)
        })
        .clone()
}

fn describe() {
    metrics::describe_gauge!(
        "stylenerf_queue_depth",
        "Ready tasks waiting for a worker, per stage"
    );
    metrics::describe_gauge!("stylenerf_tasks_running", "Leased tasks, per stage");
    metrics::describe_gauge!("stylenerf_live_workers", "Workers heard from recently");
    metrics::describe_counter!("stylenerf_lease_expiries_total", "Leases that expired");
    metrics::describe_counter!("stylenerf_leases_total", "Tasks leased, per stage");
    metrics::describe_counter!("stylenerf_jobs_created_total", "Jobs created");
    metrics::describe_counter!(
        "stylenerf_tasks_finished_total",
        "Task attempts that ended, per stage and outcome"
    );
    metrics::describe_histogram!(
        "stylenerf_write_group_size",
        "Write RPCs committed together in one transaction by the group-commit writer"
    );
    metrics::describe_histogram!(
        "stylenerf_task_duration_seconds",
        metrics::Unit::Seconds,
        "Lease-to-completion time of succeeded tasks, per stage"
    );
}

/// Serves `/metrics` until `shutdown` turns true. Returns the bound address.
pub async fn serve(
    addr: SocketAddr,
    mut shutdown: watch::Receiver<bool>,
) -> anyhow::Result<(SocketAddr, tokio::task::JoinHandle<()>)> {
    let handle = handle();
    let listener = tokio::net::TcpListener::bind(addr).await?;
    let local = listener.local_addr()?;
    let app = axum::Router::new().route(
        "/metrics",
        axum::routing::get(move || {
            let handle = handle.clone();
            async move {
                match handle {
                    Some(h) => {
                        h.run_upkeep();
                        h.render()
                    }
                    None => "# another metrics recorder is installed in this process\n".into(),
                }
            }
        }),
    );
    let task = tokio::spawn(async move {
        let result = axum::serve(listener, app)
            .with_graceful_shutdown(async move {
                let _ = shutdown.wait_for(|stop| *stop).await;
            })
            .await;
        if let Err(e) = result {
            tracing::error!(error = %e, "metrics endpoint failed");
        }
    });
    Ok((local, task))
}
