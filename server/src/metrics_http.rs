//! Prometheus metrics: installs the process-wide `metrics` recorder once and serves its text
//! exposition at `/metrics` on a separate port, with the process's own metrics (CPU, memory,
//! threads, file descriptors) and `stylenerf_build_info`, and `/healthz` for HTTP probes. The
//! coordinator serves it; so does `stylenerf worker --metrics-listen`.

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
                    Matcher::Full("stylenerf_job_duration_seconds".into()),
                    &[
                        1.0, 10.0, 60.0, 300.0, 900.0, 1800.0, 3600.0, 7200.0, 14400.0, 43200.0,
                        86400.0,
                    ],
                )
                .ok()?
                .set_buckets_for_metric(
                    Matcher::Full("stylenerf_queue_wait_seconds".into()),
                    &[
                        0.01, 0.1, 1.0, 10.0, 60.0, 300.0, 900.0, 3600.0, 14400.0, 86400.0,
                    ],
                )
                .ok()?
                .set_buckets_for_metric(
                    Matcher::Full("stylenerf_rpc_duration_seconds".into()),
                    &[
                        0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5,
                        5.0, 10.0, 30.0,
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
            metrics_process::Collector::default().describe();
            metrics::gauge!(
                "stylenerf_build_info",
                "version" => env!("CARGO_PKG_VERSION"),
                "cloud_storage" => if cfg!(feature = "cloud") { "yes" } else { "no" },
            )
            .set(1.0);
            Some(handle)
        })
        .clone()
}

fn describe() {
    metrics::describe_gauge!(
        "stylenerf_build_info",
        "Always 1; the labels say which build of stylenerf this process is"
    );
    metrics::describe_gauge!(
        "stylenerf_queue_depth",
        "Ready tasks waiting for a worker, per stage, device class (`cpu`: any worker; \
         `cuda`: CUDA workers) and the worker labels the job requires (sorted, comma-joined)"
    );
    metrics::describe_gauge!(
        "stylenerf_tasks_running",
        "Leased tasks, per stage, device class and required labels"
    );
    metrics::describe_histogram!(
        "stylenerf_queue_wait_seconds",
        metrics::Unit::Seconds,
        "Time from a task becoming ready to its lease, per stage and device class"
    );
    metrics::describe_histogram!(
        "stylenerf_job_duration_seconds",
        metrics::Unit::Seconds,
        "Submission-to-end time of finished jobs, per outcome"
    );
    metrics::describe_histogram!(
        "stylenerf_rpc_duration_seconds",
        metrics::Unit::Seconds,
        "gRPC calls by method and status code: time to the response headers"
    );
    metrics::describe_gauge!("stylenerf_live_workers", "Workers heard from recently");
    metrics::describe_counter!("stylenerf_lease_expiries_total", "Leases that expired");
    metrics::describe_counter!("stylenerf_leases_total", "Tasks leased, per stage");
    metrics::describe_counter!("stylenerf_jobs_created_total", "Jobs created");
    metrics::describe_counter!(
        "stylenerf_jobs_deleted_total",
        "Jobs deleted (DeleteJob or retention)"
    );
    metrics::describe_counter!(
        "stylenerf_tasks_finished_total",
        "Task attempts that ended, per stage and outcome"
    );
    metrics::describe_gauge!(
        "stylenerf_worker_tasks_running",
        "Worker: tasks this worker is running"
    );
    metrics::describe_gauge!(
        "stylenerf_worker_draining",
        "Worker: 1 once a shutdown has begun (checkpointing and releasing its tasks)"
    );
    metrics::describe_counter!(
        "stylenerf_worker_tasks_total",
        "Worker: tasks this worker ended, per stage and outcome"
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
    shutdown: watch::Receiver<bool>,
) -> anyhow::Result<(SocketAddr, tokio::task::JoinHandle<()>)> {
    let handle = handle();
    let process = std::sync::Arc::new(metrics_process::Collector::default());
    let listener = tokio::net::TcpListener::bind(addr).await?;
    let local = listener.local_addr()?;
    let app = axum::Router::new()
        .route(
            "/metrics",
            axum::routing::get(move || {
                let handle = handle.clone();
                let process = process.clone();
                async move {
                    match handle {
                        Some(h) => {
                            process.collect();
                            h.run_upkeep();
                            h.render()
                        }
                        None => "# another metrics recorder is installed in this process\n".into(),
                    }
                }
            }),
        )
        // Liveness: the process answers. (The coordinator's readiness is its gRPC health.)
        .route("/healthz", axum::routing::get(|| async { "ok\n" }));
    Ok((
        local,
        spawn_router(listener, app, shutdown, "metrics endpoint"),
    ))
}

/// Serves `app` on `listener` until `shutdown` turns true (the coordinator's HTTP endpoints).
pub(crate) fn spawn_router(
    listener: tokio::net::TcpListener,
    app: axum::Router,
    mut shutdown: watch::Receiver<bool>,
    what: &'static str,
) -> tokio::task::JoinHandle<()> {
    tokio::spawn(async move {
        let result = axum::serve(listener, app)
            .with_graceful_shutdown(async move {
                let _ = shutdown.wait_for(|stop| *stop).await;
            })
            .await;
        if let Err(e) = result {
            tracing::error!(error = %e, "{what} failed");
        }
    })
}
