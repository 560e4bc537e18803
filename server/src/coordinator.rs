//! The embeddable coordinator: `Coordinator::start` opens the database and store, serves the
//! gRPC services (with health and reflection), the metrics endpoint and the lease reaper, and
//! returns a `CoordinatorHandle` to learn the bound address and shut everything down.

use crate::api::artifact_api::ArtifactApi;
use crate::api::job_api::JobApi;
use crate::api::worker_api::WorkerApi;
use crate::auth::Authenticator;
use crate::config::CoordinatorConfig;
use crate::db::Db;
use crate::scheduler;
use crate::state::Shared;
use crate::storage::Storage;
use crate::writer::Writer;
use std::net::SocketAddr;
use std::sync::atomic::AtomicI64;
use std::sync::Arc;
use std::time::Duration;
use stylenerf_proto::v1::artifact_service_server::ArtifactServiceServer;
use stylenerf_proto::v1::job_service_server::JobServiceServer;
use stylenerf_proto::v1::worker_service_server::WorkerServiceServer;
use tokio::sync::{broadcast, watch, Notify, Semaphore};
use tokio::task::JoinHandle;
use tonic::server::NamedService;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::server::TcpIncoming;
use tonic::transport::{Identity, Server, ServerTlsConfig};

/// Largest gRPC message accepted (upload chunks are at most 1 MiB; manifests can be long).
const MAX_MESSAGE_BYTES: usize = 16 << 20;

/// Entry point for running a coordinator in-process.
pub struct Coordinator;

/// A running coordinator.
pub struct CoordinatorHandle {
    /// Turned NOT_SERVING when the shutdown starts.
    health: tonic_health::server::HealthReporter,
    local_addr: SocketAddr,
    metrics_addr: Option<SocketAddr>,
    tls: bool,
    shared: Arc<Shared>,
    stop: watch::Sender<bool>,
    server: JoinHandle<Result<(), tonic::transport::Error>>,
    background: Vec<JoinHandle<()>>,
}

impl Coordinator {
    /// Starts a coordinator: applies migrations, binds the listeners and spawns the services
    /// on the current Tokio runtime.
    pub async fn start(config: CoordinatorConfig) -> anyhow::Result<CoordinatorHandle> {
        if let Some(dir) = &config.spool_dir {
            // Found out now rather than at the first upload.
            tempfile::NamedTempFile::new_in(dir).map_err(|e| {
                anyhow::anyhow!(
                    "spool directory {}: {e} (it must be a writable folder)",
                    dir.display()
                )
            })?;
        }
        let storage = Storage::open(&config.storage_url)?;
        storage.check_access().await?;
        anyhow::ensure!(
            config.artifact_urls != crate::config::ArtifactUrls::Store || storage.can_sign(),
            "--artifact-urls store: the store {} signs no URLs (a local folder); use auto or \
             coordinator with --http-listen",
            config.storage_url
        );
        if config.restore_from_backup {
            match crate::backup::restore(&storage, &config.database).await? {
                Some(key) => tracing::warn!(%key, database = %config.database.display(),
                    "database restored from the newest backup"),
                None => tracing::info!(
                    "restore from backup: database present or no backup; \
                    starting from the file"
                ),
            }
        }
        let db = Db::open(&config.database).await?;
        let (stop, stop_rx) = watch::channel(false);
        let (events, _) = broadcast::channel(4096);
        let writer = Writer::spawn(db.write.clone(), events.clone());
        // The download endpoint is bound first: its address is the default public URL.
        let downloads = match config.http_listen {
            Some(addr) => {
                let listener = tokio::net::TcpListener::bind(addr)
                    .await
                    .map_err(|e| anyhow::anyhow!("--http-listen {addr}: {e}"))?;
                let signer = match &config.url_signing_key {
                    Some(key) => crate::http_download::UrlSigner::new(key)?,
                    None => crate::http_download::UrlSigner::random()?,
                };
                let public_url = config
                    .public_url
                    .clone()
                    .unwrap_or_else(|| format!("http://{}", listener.local_addr().unwrap_or(addr)))
                    .trim_end_matches('/')
                    .to_string();
                Some((
                    listener,
                    crate::http_download::Downloads { signer, public_url },
                ))
            }
            None => None,
        };
        let shared = Arc::new(Shared {
            db,
            writer,
            storage,
            config: config.clone(),
            events,
            ready: Notify::new(),
            shutdown: stop_rx.clone(),
            next_expiry_check: AtomicI64::new(0),
            validations: Semaphore::new(crate::inputs::CONCURRENT_VALIDATIONS),
            worker_owners: Default::default(),
            queue_series: Default::default(),
            busy_upload_sessions: Default::default(),
            downloads: downloads.as_ref().map(|(_, d)| d.clone()),
        });

        let auth = Authenticator::new(&config.auth);
        let interceptor = move |request| auth.intercept(request);
        let jobs = JobServiceServer::new(JobApi {
            shared: shared.clone(),
        })
        .max_decoding_message_size(MAX_MESSAGE_BYTES);
        let workers = WorkerServiceServer::new(WorkerApi {
            shared: shared.clone(),
        })
        .max_decoding_message_size(MAX_MESSAGE_BYTES);
        let artifacts = ArtifactServiceServer::new(ArtifactApi {
            shared: shared.clone(),
        })
        .max_decoding_message_size(MAX_MESSAGE_BYTES);

        let (health, health_service) = tonic_health::server::health_reporter();
        health.set_serving::<JobServiceServer<JobApi>>().await;
        health.set_serving::<WorkerServiceServer<WorkerApi>>().await;
        health
            .set_serving::<ArtifactServiceServer<ArtifactApi>>()
            .await;
        // Reflection in both versions clients use (grpcurl 1.8 and Python's client still ask
        // v1alpha), with the google.rpc error details our statuses carry.
        let reflection = || {
            tonic_reflection::server::Builder::configure()
                .register_encoded_file_descriptor_set(stylenerf_proto::FILE_DESCRIPTOR_SET)
                .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
                .register_encoded_file_descriptor_set(tonic_types::pb::FILE_DESCRIPTOR_SET)
        };
        let reflection_v1alpha = reflection().build_v1alpha()?;
        let reflection = reflection().build_v1()?;

        let mut server = Server::builder().tcp_nodelay(true);
        if let Some(tls) = &config.tls {
            let cert = std::fs::read(&tls.cert)
                .map_err(|e| anyhow::anyhow!("reading {}: {e}", tls.cert.display()))?;
            let key = std::fs::read(&tls.key)
                .map_err(|e| anyhow::anyhow!("reading {}: {e}", tls.key.display()))?;
            server = server
                .tls_config(ServerTlsConfig::new().identity(Identity::from_pem(cert, key)))?;
        }
        let rpc_metrics = crate::rpc_metrics::RpcMetricsLayer::new(&[
            stylenerf_proto::FILE_DESCRIPTOR_SET,
            tonic_health::pb::FILE_DESCRIPTOR_SET,
            tonic_reflection::pb::v1::FILE_DESCRIPTOR_SET,
            tonic_reflection::pb::v1alpha::FILE_DESCRIPTOR_SET,
        ])?;
        let router = server
            .layer(rpc_metrics)
            .add_service(health_service)
            .add_service(reflection)
            .add_service(reflection_v1alpha)
            .add_service(InterceptedService::new(jobs, interceptor.clone()))
            .add_service(InterceptedService::new(workers, interceptor.clone()))
            .add_service(InterceptedService::new(artifacts, interceptor));

        let listener = tokio::net::TcpListener::bind(config.listen).await?;
        let local_addr = listener.local_addr()?;
        let incoming = TcpIncoming::from(listener).with_nodelay(Some(true));
        let mut server_stop = stop_rx.clone();
        let server = tokio::spawn(router.serve_with_incoming_shutdown(incoming, async move {
            let _ = server_stop.wait_for(|stop| *stop).await;
        }));

        let mut background = vec![
            tokio::spawn(reaper(shared.clone())),
            tokio::spawn(crate::webhooks::run(shared.clone())),
            tokio::spawn(crate::upload_sessions::run(shared.clone())),
        ];
        if let Some((listener, endpoint)) = downloads {
            tracing::info!(public_url = %endpoint.public_url, "HTTP downloads");
            background.push(crate::http_download::serve(
                listener,
                shared.clone(),
                endpoint.signer,
                stop_rx.clone(),
            ));
        }
        if let Some(keep) = config.retention {
            background.push(tokio::spawn(crate::retention::run(
                shared.clone(),
                keep,
                config.retention_sweep_interval,
            )));
        }
        if let Some(interval) = config.backup_interval {
            background.push(tokio::spawn(crate::backup::run(shared.clone(), interval)));
        }
        let metrics_addr = match config.metrics_listen {
            Some(addr) => {
                let (addr, task) = crate::metrics_http::serve(addr, stop_rx.clone()).await?;
                background.push(task);
                Some(addr)
            }
            None => {
                crate::metrics_http::handle();
                None
            }
        };
        let metrics = metrics_addr.map_or("off".to_string(), |a| format!("http://{a}/metrics"));
        tracing::info!(
            %local_addr,
            %metrics,
            database = %config.database.display(),
            storage = %shared.storage.url(),
            backend = %shared.storage.backend(),
            "coordinator listening"
        );
        Ok(CoordinatorHandle {
            health,
            local_addr,
            metrics_addr,
            tls: config.tls.is_some(),
            shared,
            stop,
            server,
            background,
        })
    }
}

/// Requeues expired leases and refreshes the gauges every `reaper_interval`.
async fn reaper(shared: Arc<Shared>) {
    shared
        .every(shared.config.reaper_interval, || async {
            if let Err(e) = scheduler::reap(&shared).await {
                tracing::warn!(error = %e, "reaping expired leases failed");
            }
            if let Err(e) = scheduler::refresh_gauges(&shared).await {
                tracing::warn!(error = %e, "refreshing gauges failed");
            }
        })
        .await
}

impl CoordinatorHandle {
    /// The bound gRPC address (useful with port 0).
    pub fn local_addr(&self) -> SocketAddr {
        self.local_addr
    }

    /// The URL clients and workers connect to, e.g. `http://127.0.0.1:50051`.
    pub fn endpoint(&self) -> String {
        let scheme = if self.tls { "https" } else { "http" };
        format!("{scheme}://{}", self.local_addr)
    }

    /// The bound metrics address, if the endpoint is enabled.
    pub fn metrics_addr(&self) -> Option<SocketAddr> {
        self.metrics_addr
    }

    /// The object store URL handed to workers.
    pub fn storage_url(&self) -> &str {
        self.shared.storage.url()
    }

    /// Reports NOT_SERVING on every health service and serves on for `drain_grace`; then stops
    /// accepting calls, ends long-polls and watch streams, waits up to five seconds for calls
    /// in flight, and closes the database.
    pub async fn shutdown(self) -> anyhow::Result<()> {
        for service in [
            "",
            JobServiceServer::<JobApi>::NAME,
            WorkerServiceServer::<WorkerApi>::NAME,
            ArtifactServiceServer::<ArtifactApi>::NAME,
        ] {
            self.health
                .set_service_status(service, tonic_health::ServingStatus::NotServing)
                .await;
        }
        let grace = self.shared.config.drain_grace;
        if !grace.is_zero() {
            tracing::info!(?grace, "draining: health reports NOT_SERVING");
            tokio::time::sleep(grace).await;
        }
        let _ = self.stop.send(true);
        let mut server = self.server;
        match tokio::time::timeout(Duration::from_secs(5), &mut server).await {
            Ok(joined) => joined??,
            Err(_) => {
                tracing::warn!("calls still in flight after 5 s; aborting them");
                server.abort();
            }
        }
        for task in self.background {
            let _ = tokio::time::timeout(Duration::from_secs(5), task).await;
        }
        // Nothing is written any more: the last snapshot loses nothing.
        if self.shared.config.backup_interval.is_some() {
            match crate::backup::snapshot(&self.shared).await {
                Ok(key) => tracing::info!(%key, "database backed up at shutdown"),
                Err(e) => tracing::error!(error = %e, "backing up the database at shutdown failed"),
            }
        }
        self.shared.db.close().await;
        tracing::info!("coordinator stopped");
        Ok(())
    }
}
