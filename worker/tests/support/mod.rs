//! Test support: an embedded coordinator (real SQLite file, token auth, fast heartbeats) in a
//! temp dir, a generated 32×32 scene and a style image uploaded as a job, workers configured
//! for tests, and helpers to wait for worker events and job states.

#![allow(dead_code)]

use std::path::Path;
use std::time::{Duration, Instant};

use stylenerf_engine::scene::generate::{generate, GenerateOptions};
use stylenerf_server::proto::v1 as pb;
use stylenerf_server::proto::v1::artifact_service_client::ArtifactServiceClient;
use stylenerf_server::proto::v1::job_service_client::JobServiceClient;
use stylenerf_server::{
    AuthConfig, Coordinator, CoordinatorConfig, CoordinatorHandle, Role, TokenEntry,
};
use stylenerf_worker::connection::{Authed, Bearer};
use stylenerf_worker::{RunSummary, Worker, WorkerConfig, WorkerEvent, WorkerHandle};
use tokio::sync::broadcast;
use tokio::task::JoinHandle;

pub const CLIENT: &str = "client-token-0123456789";
pub const WORKER: &str = "worker-token-0123456789";
/// The tests look into the store as an operator: workers reach only the jobs they hold.
pub const ADMIN: &str = "admin-token-0123456789a";

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
    coordinator_on(dir, CoordinatorConfig::local(dir).listen).await
}

/// [`coordinator`] listening on `listen`.
pub async fn coordinator_on(dir: &Path, listen: std::net::SocketAddr) -> CoordinatorHandle {
    init_logs();
    let mut config = CoordinatorConfig::local(dir);
    config.listen = listen;
    let entry = |role, name: &str, token: &str| TokenEntry {
        role,
        name: name.into(),
        token: token.into(),
    };
    config.auth = AuthConfig::Tokens(vec![
        entry(Role::Client, "alice", CLIENT),
        entry(Role::Worker, "workers", WORKER),
        entry(Role::Admin, "operator", ADMIN),
    ]);
    config.heartbeat_interval = Duration::from_millis(200);
    config.lease_ttl = Duration::from_secs(10);
    config.reaper_interval = Duration::from_millis(100);
    config.max_lease_wait = Duration::from_secs(2);
    Coordinator::start(config)
        .await
        .expect("coordinator starts")
}

async fn channel(handle: &CoordinatorHandle) -> tonic::transport::Channel {
    tonic::transport::Channel::from_shared(handle.endpoint())
        .unwrap()
        .connect()
        .await
        .unwrap()
}

fn bearer(token: &str) -> Bearer {
    Bearer::new(Some(token)).unwrap()
}

pub async fn jobs(handle: &CoordinatorHandle) -> JobServiceClient<Authed> {
    JobServiceClient::with_interceptor(channel(handle).await, bearer(CLIENT))
}

pub async fn artifacts(handle: &CoordinatorHandle) -> ArtifactServiceClient<Authed> {
    ArtifactServiceClient::with_interceptor(channel(handle).await, bearer(ADMIN))
}

fn sha256(data: &[u8]) -> String {
    use sha2::Digest;
    hex::encode(sha2::Sha256::digest(data))
}

async fn upload(
    client: &mut JobServiceClient<Authed>,
    kind: pb::UploadKind,
    name: &str,
    data: Vec<u8>,
) -> String {
    let mut messages = vec![pb::UploadChunk {
        part: Some(pb::upload_chunk::Part::Header(pb::UploadHeader {
            kind: kind as i32,
            filename: name.into(),
            total_size: data.len() as u64,
            sha256: sha256(&data),
        })),
    }];
    for chunk in data.chunks(1 << 20) {
        messages.push(pb::UploadChunk {
            part: Some(pb::upload_chunk::Part::Data(chunk.to_vec())),
        });
    }
    client
        .upload(tokio_stream::iter(messages))
        .await
        .expect("upload accepted")
        .into_inner()
        .upload_id
}

/// A generated 32×32 scene with 8 views, as a tar archive with the scene in `scene/`.
fn scene_tar(dir: &Path) -> Vec<u8> {
    let scene = dir.join("scene");
    generate(
        &GenerateOptions {
            size: 32,
            views: 8,
            ..Default::default()
        },
        &scene,
    )
    .expect("scene generated");
    let mut builder = tar::Builder::new(Vec::new());
    builder.append_dir_all("scene", &scene).unwrap();
    builder.into_inner().unwrap()
}

fn style_png() -> Vec<u8> {
    let image = image::RgbImage::from_fn(48, 48, |x, y| {
        image::Rgb([(x * 5) as u8, (y * 5) as u8, ((x + y) * 3) as u8])
    });
    let mut out = std::io::Cursor::new(Vec::new());
    image.write_to(&mut out, image::ImageFormat::Png).unwrap();
    out.into_inner()
}

/// Uploads a generated scene and one style and creates a `tiny` job with `overrides`.
pub async fn submit(
    handle: &CoordinatorHandle,
    dir: &Path,
    overrides: serde_json::Value,
    memory_bytes: u64,
) -> String {
    let mut client = jobs(handle).await;
    let dataset = upload(
        &mut client,
        pb::UploadKind::DatasetArchive,
        "scene.tar",
        scene_tar(dir),
    )
    .await;
    let style = upload(
        &mut client,
        pb::UploadKind::StyleImage,
        "style.png",
        style_png(),
    )
    .await;
    let input = |id: String| pb::InputRef {
        source: Some(pb::input_ref::Source::UploadId(id)),
    };
    client
        .create_job(pb::CreateJobRequest {
            name: "test".into(),
            dataset: Some(input(dataset)),
            styles: vec![input(style)],
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
    jobs(handle)
        .await
        .get_job(pb::GetJobRequest { job_id: id.into() })
        .await
        .unwrap()
        .into_inner()
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

/// Polls `f` every 50 ms until it returns `Some`, within `timeout`.
pub async fn eventually<T, F: std::future::Future<Output = Option<T>>>(
    timeout: Duration,
    mut f: impl FnMut() -> F,
) -> T {
    let deadline = Instant::now() + timeout;
    loop {
        if let Some(t) = f().await {
            return t;
        }
        assert!(
            Instant::now() < deadline,
            "condition not met within {timeout:?}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

pub async fn list(handle: &CoordinatorHandle, prefix: &str) -> Vec<String> {
    artifacts(handle)
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
