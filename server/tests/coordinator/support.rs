//! Test support: coordinators on 127.0.0.1:0, token-bearing clients, generated datasets and
//! style images, uploads, and a fake worker that runs stages without the engine.

use sha2::{Digest, Sha256};
use std::path::Path;
use std::time::Duration;
use stylenerf_server::proto::v1 as pb;
use stylenerf_server::proto::v1::artifact_service_client::ArtifactServiceClient;
use stylenerf_server::proto::v1::job_service_client::JobServiceClient;
use stylenerf_server::proto::v1::worker_service_client::WorkerServiceClient;
use stylenerf_server::{
    AuthConfig, Coordinator, CoordinatorConfig, CoordinatorHandle, Role, TokenEntry,
};
use tonic::metadata::MetadataValue;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;
use tonic::{Request, Status};

pub const ALICE: &str = "client-alice-0123456789";
pub const BOB: &str = "client-bob-0123456789ab";
pub const WORKER: &str = "worker-token-0123456789";
/// A second worker principal (another pool, or an intruder with a worker token).
pub const OTHER_WORKER: &str = "worker-token-b-0123456789";
pub const ADMIN: &str = "admin-token-0123456789a";

fn tokens() -> AuthConfig {
    let entry = |role, name: &str, token: &str| TokenEntry {
        role,
        name: name.into(),
        token: token.into(),
    };
    AuthConfig::Tokens(vec![
        entry(Role::Client, "alice", ALICE),
        entry(Role::Client, "bob", BOB),
        entry(Role::Worker, "worker", WORKER),
        entry(Role::Worker, "other-worker", OTHER_WORKER),
        entry(Role::Admin, "root", ADMIN),
    ])
}

/// A test configuration under `dir`: token auth, fast reaper.
pub fn config(dir: &Path) -> CoordinatorConfig {
    let mut config = CoordinatorConfig::local(dir);
    config.auth = tokens();
    config.reaper_interval = Duration::from_millis(50);
    config.max_lease_wait = Duration::from_secs(5);
    config
}

pub async fn start(config: CoordinatorConfig) -> CoordinatorHandle {
    Coordinator::start(config)
        .await
        .expect("coordinator starts")
}

/// Adds `authorization: Bearer <token>` to every call.
#[derive(Clone)]
pub struct Bearer(Option<MetadataValue<tonic::metadata::Ascii>>);

impl tonic::service::Interceptor for Bearer {
    fn call(&mut self, mut request: Request<()>) -> Result<Request<()>, Status> {
        if let Some(value) = &self.0 {
            request
                .metadata_mut()
                .insert("authorization", value.clone());
        }
        Ok(request)
    }
}

pub type Authed = InterceptedService<Channel, Bearer>;

pub async fn channel(handle: &CoordinatorHandle) -> Channel {
    Channel::from_shared(handle.endpoint())
        .unwrap()
        .connect()
        .await
        .expect("connects")
}

pub fn bearer(token: Option<&str>) -> Bearer {
    Bearer(token.map(|t| format!("Bearer {t}").parse().unwrap()))
}

pub async fn jobs_client(
    handle: &CoordinatorHandle,
    token: Option<&str>,
) -> JobServiceClient<Authed> {
    JobServiceClient::with_interceptor(channel(handle).await, bearer(token))
}

pub async fn worker_client(
    handle: &CoordinatorHandle,
    token: Option<&str>,
) -> WorkerServiceClient<Authed> {
    WorkerServiceClient::with_interceptor(channel(handle).await, bearer(token))
}

pub async fn artifact_client(
    handle: &CoordinatorHandle,
    token: Option<&str>,
) -> ArtifactServiceClient<Authed> {
    ArtifactServiceClient::with_interceptor(channel(handle).await, bearer(token))
}

pub fn sha256(data: &[u8]) -> String {
    hex::encode(Sha256::digest(data))
}

pub fn png(width: u32, height: u32) -> Vec<u8> {
    let image = image::RgbImage::from_fn(width, height, |x, y| {
        image::Rgb([(x * 40) as u8, (y * 40) as u8, 128])
    });
    let mut out = std::io::Cursor::new(Vec::new());
    image.write_to(&mut out, image::ImageFormat::Png).unwrap();
    out.into_inner()
}

/// A tar archive with the given regular members.
pub fn tar_of(members: &[(&str, &[u8])]) -> Vec<u8> {
    let mut builder = tar::Builder::new(Vec::new());
    for (path, data) in members {
        let mut header = tar::Header::new_gnu();
        header.set_size(data.len() as u64);
        header.set_mode(0o644);
        header.set_cksum();
        builder.append_data(&mut header, path, *data).unwrap();
    }
    builder.into_inner().unwrap()
}

/// A small NeRF-synthetic scene: `transforms_train.json` and two images.
pub fn scene_tar() -> Vec<u8> {
    let transforms = br#"{"camera_angle_x": 0.69, "frames": [
        {"file_path": "./train/r_0", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]]},
        {"file_path": "./train/r_1", "transform_matrix": [[0,0,1,4],[0,1,0,0],[-1,0,0,0],[0,0,0,1]]}
    ]}"#;
    let image = png(4, 4);
    tar_of(&[
        ("lego/transforms_train.json", transforms),
        ("lego/train/r_0.png", &image),
        ("lego/train/r_1.png", &image),
    ])
}

/// Uploads `data` with an explicit header (for malformed-upload tests).
pub async fn upload_raw(
    client: &mut JobServiceClient<Authed>,
    header: pb::UploadHeader,
    data: &[u8],
) -> Result<pb::UploadReceipt, Status> {
    let mut messages = vec![pb::UploadChunk {
        part: Some(pb::upload_chunk::Part::Header(header)),
    }];
    for chunk in data.chunks(64 << 10) {
        messages.push(pb::UploadChunk {
            part: Some(pb::upload_chunk::Part::Data(chunk.to_vec())),
        });
    }
    client
        .upload(tokio_stream::iter(messages))
        .await
        .map(|r| r.into_inner())
}

pub async fn upload(
    client: &mut JobServiceClient<Authed>,
    kind: pb::UploadKind,
    filename: &str,
    data: &[u8],
) -> Result<pb::UploadReceipt, Status> {
    let header = pb::UploadHeader {
        kind: kind as i32,
        filename: filename.into(),
        total_size: data.len() as u64,
        sha256: sha256(data),
    };
    upload_raw(client, header, data).await
}

/// Uploads the test scene and two styles and returns a create request for them.
pub async fn job_request(client: &mut JobServiceClient<Authed>) -> pb::CreateJobRequest {
    let dataset = upload(
        client,
        pb::UploadKind::DatasetArchive,
        "lego.tar",
        &scene_tar(),
    )
    .await
    .expect("dataset upload");
    let mut styles = Vec::new();
    for size in [8, 12] {
        let receipt = upload(
            client,
            pb::UploadKind::StyleImage,
            "style.png",
            &png(size, size),
        )
        .await
        .expect("style upload");
        styles.push(pb::InputRef {
            source: Some(pb::input_ref::Source::UploadId(receipt.upload_id)),
        });
    }
    pb::CreateJobRequest {
        name: "lego".into(),
        dataset: Some(pb::InputRef {
            source: Some(pb::input_ref::Source::UploadId(dataset.upload_id)),
        }),
        styles,
        preset: "tiny".into(),
        ..Default::default()
    }
}

pub async fn create_job(client: &mut JobServiceClient<Authed>) -> pb::Job {
    let request = job_request(client).await;
    client
        .create_job(request)
        .await
        .expect("job created")
        .into_inner()
        .job
        .unwrap()
}

/// A fake worker: registered capabilities and clients.
pub struct FakeWorker {
    pub id: String,
    pub workers: WorkerServiceClient<Authed>,
    pub artifacts: ArtifactServiceClient<Authed>,
}

impl FakeWorker {
    pub async fn register(handle: &CoordinatorHandle, device: &str, memory_bytes: u64) -> Self {
        Self::register_as(handle, WORKER, device, memory_bytes).await
    }

    /// Registers with the given worker token.
    pub async fn register_as(
        handle: &CoordinatorHandle,
        token: &str,
        device: &str,
        memory_bytes: u64,
    ) -> Self {
        let mut workers = worker_client(handle, Some(token)).await;
        let id = workers
            .register_worker(pb::RegisterWorkerRequest {
                name: "fake".into(),
                capabilities: Some(pb::Capabilities {
                    device: device.into(),
                    memory_bytes,
                    labels: vec![],
                    max_tasks: 4,
                }),
                worker_id: String::new(),
            })
            .await
            .expect("registers")
            .into_inner()
            .worker_id;
        let artifacts = artifact_client(handle, Some(token)).await;
        FakeWorker {
            id,
            workers,
            artifacts,
        }
    }

    pub async fn lease(&mut self, wait_ms: u64) -> Option<pb::TaskAssignment> {
        self.workers
            .lease_task(pb::LeaseTaskRequest {
                worker_id: self.id.clone(),
                wait_ms,
                free_memory_bytes: 0,
            })
            .await
            .expect("lease call")
            .into_inner()
            .task
    }

    pub async fn heartbeat(
        &mut self,
        task: &pb::TaskAssignment,
        step: u64,
    ) -> Result<pb::HeartbeatResponse, Status> {
        self.workers
            .heartbeat(pb::HeartbeatRequest {
                worker_id: self.id.clone(),
                task_id: task.task_id,
                fencing_token: task.fencing_token,
                progress: Some(pb::Progress {
                    step,
                    total: 10,
                    loss: 0.5 / (step as f64 + 1.0),
                    metrics: [("psnr".to_string(), 20.0 + step as f64)].into(),
                    eta_seconds: (10 - step.min(10)) as f64,
                    message: "training".into(),
                }),
            })
            .await
            .map(|r| r.into_inner())
    }

    /// Stores one output object through the ArtifactService and completes the task with it.
    pub async fn complete(&mut self, task: &pb::TaskAssignment) -> Result<pb::Artifact, Status> {
        let data = format!("output of {} (task {})", task.output_prefix, task.task_id).into_bytes();
        let key = format!("{}result.bin", task.output_prefix);
        let messages = vec![
            pb::PutObjectChunk {
                part: Some(pb::put_object_chunk::Part::Header(pb::PutObjectHeader {
                    key: key.clone(),
                    size: data.len() as u64,
                    sha256: sha256(&data),
                })),
            },
            pb::PutObjectChunk {
                part: Some(pb::put_object_chunk::Part::Data(data)),
            },
        ];
        let artifact = self
            .artifacts
            .put_object(tokio_stream::iter(messages))
            .await?
            .into_inner();
        self.workers
            .complete_task(pb::CompleteTaskRequest {
                worker_id: self.id.clone(),
                task_id: task.task_id,
                fencing_token: task.fencing_token,
                outputs: vec![artifact.clone()],
                metrics: [("psnr".to_string(), 31.0)].into(),
            })
            .await?;
        Ok(artifact)
    }

    /// Leases, heartbeats and completes one task; returns its assignment.
    pub async fn run_one(&mut self) -> pb::TaskAssignment {
        let task = self.lease(5000).await.expect("a task is ready");
        let reply = self.heartbeat(&task, 5).await.expect("heartbeat");
        assert!(!reply.cancel);
        self.complete(&task).await.expect("completes");
        task
    }
}

pub async fn get_job(client: &mut JobServiceClient<Authed>, id: &str) -> pb::Job {
    client
        .get_job(pb::GetJobRequest { job_id: id.into() })
        .await
        .expect("get job")
        .into_inner()
}

/// The BadRequest field violations of a status.
pub fn bad_fields(status: &Status) -> Vec<String> {
    use tonic_types::StatusExt;
    status
        .get_details_bad_request()
        .map(|b| b.field_violations.into_iter().map(|v| v.field).collect())
        .unwrap_or_default()
}
