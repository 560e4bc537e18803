//! Test support of the real worker: a coordinator from `stylenerf-testkit` with fast
//! heartbeats, a generated 32×32 scene and a style image uploaded as a job, workers configured
//! for tests, and helpers to wait for worker events and look at jobs and the store.

#![allow(dead_code, unused_imports)]

use std::path::Path;
use std::time::{Duration, Instant};

use stylenerf_server::proto::v1 as pb;
use stylenerf_server::proto::v1::job_service_client::JobServiceClient;
use stylenerf_server::CoordinatorHandle;
pub use stylenerf_testkit::eventually;
use stylenerf_testkit::{
    artifact_client, config, jobs_client, png, start, tar_dir, tiny_scene, upload, uploaded,
    Authed, ADMIN, ALICE, WORKER,
};
use stylenerf_worker::{RunSummary, Worker, WorkerConfig, WorkerEvent, WorkerHandle};
use tokio::sync::broadcast;
use tokio::task::JoinHandle;

pub fn init_logs() {
    let _ = tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_env("STYLENERF_LOG")
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn")),
        )
        .with_test_writer()
        .try_init();
}

/// A coordinator under `dir` with heartbeats every 200 ms.
pub async fn coordinator(dir: &Path) -> CoordinatorHandle {
    coordinator_on(dir, config(dir).listen).await
}

/// [`coordinator`] listening on `listen`.
pub async fn coordinator_on(dir: &Path, listen: std::net::SocketAddr) -> CoordinatorHandle {
    init_logs();
    let mut config = config(dir);
    config.listen = listen;
    config.heartbeat_interval = Duration::from_millis(200);
    config.lease_ttl = Duration::from_secs(10);
    config.reaper_interval = Duration::from_millis(100);
    config.max_lease_wait = Duration::from_secs(2);
    start(config).await
}

/// A client with the token of [`ALICE`].
pub async fn jobs(handle: &CoordinatorHandle) -> JobServiceClient<Authed> {
    jobs_client(handle, Some(ALICE)).await
}

/// A generated 32×32 scene with 8 views, as a tar archive with the scene in `scene/`.
fn scene_tar(dir: &Path) -> Vec<u8> {
    let scene = dir.join("scene");
    tiny_scene(&scene);
    tar_dir("scene", &scene)
}

/// Uploads a generated scene and one style and creates a `tiny` job with `overrides`.
pub async fn submit(
    handle: &CoordinatorHandle,
    dir: &Path,
    overrides: serde_json::Value,
    memory_bytes: u64,
) -> String {
    let mut client = jobs(handle).await;
    let upload = |kind, name: &'static str, data: Vec<u8>| {
        let mut client = client.clone();
        async move {
            upload(&mut client, kind, name, &data)
                .await
                .expect("upload accepted")
        }
    };
    let dataset = upload(pb::UploadKind::DatasetArchive, "scene.tar", scene_tar(dir)).await;
    let style = upload(pb::UploadKind::StyleImage, "style.png", png(48, 48)).await;
    client
        .create_job(pb::CreateJobRequest {
            name: "test".into(),
            dataset: Some(uploaded(&dataset)),
            styles: vec![uploaded(&style)],
            preset: "tiny".into(),
            config_overrides_json: overrides.to_string(),
            requirements: Some(pb::Requirements {
                memory_bytes,
                ..Default::default()
            }),
            ..Default::default()
        })
        .await
        .expect("job created")
        .into_inner()
        .job
        .unwrap()
        .id
}

pub async fn get_job(handle: &CoordinatorHandle, id: &str) -> pb::Job {
    stylenerf_testkit::get_job(&mut jobs(handle).await, id).await
}

/// A test worker: checkpoints every 10 steps, scratch under `dir`.
pub fn worker_config(handle: &CoordinatorHandle, dir: &Path) -> WorkerConfig {
    worker_config_for(&handle.endpoint(), dir)
}

/// [`worker_config`] for a coordinator at `endpoint` (which may not be up yet).
pub fn worker_config_for(endpoint: &str, dir: &Path) -> WorkerConfig {
    let mut c = WorkerConfig::new(endpoint);
    c.token = Some(WORKER.into());
    c.name = "test-worker".into();
    c.checkpoint_every_steps = 10;
    c.checkpoint_every = None;
    c.checkpoint_upload_every = Duration::from_millis(100);
    c.lease_wait = Duration::from_secs(1);
    c.scratch_dir = Some(dir.join("scratch"));
    c
}

/// A running worker: its handle, events and the task running it.
pub struct Running {
    pub handle: WorkerHandle,
    pub events: broadcast::Receiver<WorkerEvent>,
    pub task: JoinHandle<anyhow::Result<RunSummary>>,
}

pub async fn spawn_worker(config: WorkerConfig) -> Running {
    let worker = Worker::register(config).await.expect("worker registers");
    let handle = worker.handle();
    let events = handle.subscribe();
    let task = tokio::spawn(worker.run());
    Running {
        handle,
        events,
        task,
    }
}

impl Running {
    /// The next event matching `f`, within `timeout`.
    pub async fn wait_for<T>(
        &mut self,
        timeout: Duration,
        mut f: impl FnMut(&WorkerEvent) -> Option<T>,
    ) -> T {
        let deadline = Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match tokio::time::timeout(left, self.events.recv()).await {
                Ok(Ok(event)) => {
                    if let Some(t) = f(&event) {
                        return t;
                    }
                }
                Ok(Err(e)) => panic!("worker events: {e}"),
                Err(_) => panic!("no matching worker event within {timeout:?}"),
            }
        }
    }

    /// Shuts the worker down and returns what it did.
    pub async fn stop(self) -> RunSummary {
        self.handle.shutdown();
        tokio::time::timeout(Duration::from_secs(60), self.task)
            .await
            .expect("worker stops within a minute")
            .unwrap()
            .unwrap()
    }
}

/// The keys under `prefix` in the store, seen as the operator.
pub async fn list(handle: &CoordinatorHandle, prefix: &str) -> Vec<String> {
    artifact_client(handle, Some(ADMIN))
        .await
        .list_objects(pb::ListObjectsRequest {
            prefix: prefix.into(),
        })
        .await
        .unwrap()
        .into_inner()
        .objects
        .into_iter()
        .map(|o| o.key)
        .collect()
}
