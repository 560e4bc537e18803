//! A worker without the engine: it registers, leases, reports progress and completes each task
//! with one stored object, [`fake_output`], through the same APIs a real worker calls.

use stylenerf_proto::v1 as pb;
use stylenerf_proto::v1::artifact_service_client::ArtifactServiceClient;
use stylenerf_proto::v1::worker_service_client::WorkerServiceClient;
use stylenerf_server::CoordinatorHandle;
use tonic::Status;

use crate::clients::{artifact_client, worker_client, Authed};
use crate::coordinator::WORKER;
use crate::inputs::sha256;

/// What the fake worker stores as `<output prefix>result.bin` for `task` (about 50 KB).
pub fn fake_output(task: &pb::TaskAssignment) -> Vec<u8> {
    format!("output of {} (task {})\n", task.output_prefix, task.task_id)
        .repeat(1000)
        .into_bytes()
}

/// A registered fake worker and its clients.
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
        Self::register_with(handle, token, device, memory_bytes, &[]).await
    }

    /// Registers with the given worker token, advertising `tools` (`colmap`, `ffmpeg`).
    pub async fn register_with(
        handle: &CoordinatorHandle,
        token: &str,
        device: &str,
        memory_bytes: u64,
        tools: &[&str],
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
                    tools: tools.iter().map(|t| t.to_string()).collect(),
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

    /// Reports step `step` of 10, with a loss, a `psnr` of `20 + step` and an ETA.
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

    /// Stores [`fake_output`] through the ArtifactService and completes the task with it.
    pub async fn complete(&mut self, task: &pb::TaskAssignment) -> Result<pb::Artifact, Status> {
        let data = fake_output(task);
        let messages = vec![
            pb::PutObjectChunk {
                part: Some(pb::put_object_chunk::Part::Header(pb::PutObjectHeader {
                    key: format!("{}result.bin", task.output_prefix),
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

    /// Leases, heartbeats (step 5) and completes one task; returns its assignment.
    pub async fn run_one(&mut self) -> pb::TaskAssignment {
        let task = self.lease(5000).await.expect("a task is ready");
        let reply = self.heartbeat(&task, 5).await.expect("heartbeat");
        assert!(!reply.cancel);
        self.complete(&task).await.expect("completes");
        task
    }
}
