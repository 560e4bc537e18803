//! `Client`: the job API of a coordinator as plain async methods — upload inputs, submit,
//! inspect, list, watch, wait, cancel, list and download artifacts, and request new renders.
//! Cheap to clone (clones share one HTTP/2 connection); every error is a [`ClientError`].

use crate::download::{download_file, relative_key, DownloadOptions, DownloadedFile};
use crate::error::{ClientError, Result};
use crate::spec::{
    overrides_json, Input, JobPage, JobSpec, ListFilter, RenderSpec, Submission, WatchOptions,
};
use crate::transport::{connect_channel, AuthedChannel, Bearer, ConnectOptions};
use crate::upload::{append_stream, prepare_dataset, prepare_file, prepare_photos, PreparedUpload};
use crate::watch::backoff;
use crate::watch::EventStream;
use futures::StreamExt;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use stylenerf_proto::v1 as pb;
use stylenerf_proto::v1::job_service_client::JobServiceClient;
use tonic::transport::Channel;
use tonic::Streaming;

/// Largest message accepted from the coordinator (job listings with many artifacts).
const MAX_MESSAGE_BYTES: usize = 16 << 20;

/// Failed attempts in a row before an upload gives up.
pub const MAX_UPLOAD_RESUMES: u32 = 8;

/// Whether an upload step that failed this way may be resumed from the committed size: a
/// lost connection or a broken stream, another call on the session, or an offset that the
/// coordinator had moved past.
fn may_resume(error: &ClientError) -> bool {
    use tonic::Code;
    error.is_retryable()
        || matches!(
            error,
            ClientError::FailedPrecondition { .. }
                | ClientError::Status {
                    code: Code::Unknown | Code::Cancelled | Code::Internal,
                    ..
                }
        )
}

/// A connection to a coordinator's `JobService`, authenticated with one token.
#[derive(Clone)]
pub struct Client {
    jobs: JobServiceClient<AuthedChannel>,
    endpoint: Arc<str>,
}

impl std::fmt::Debug for Client {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Client")
            .field("endpoint", &self.endpoint)
            .finish_non_exhaustive()
    }
}

impl Client {
    /// Connects to `endpoint` (`http://host:port`, `https://host:port` or `host:port`) with a
    /// bearer token (`None` for a coordinator without authentication). Fails at once with
    /// [`ClientError::Unreachable`] when nothing answers.
    pub async fn connect(endpoint: &str, token: Option<&str>) -> Result<Self> {
        Self::connect_with(&ConnectOptions::new(endpoint, token.map(str::to_string))).await
    }

    /// Connects with full options (TLS CA, server name, connect timeout).
    pub async fn connect_with(options: &ConnectOptions) -> Result<Self> {
        let bearer = Bearer::new(options.token.as_deref())?;
        let (channel, endpoint) = connect_channel(options).await?;
        Ok(Self::from_channel(channel, bearer, endpoint))
    }

    /// Wraps an existing channel (e.g. shared with other services); `endpoint` is only used
    /// in error messages.
    pub fn from_channel(channel: Channel, bearer: Bearer, endpoint: impl Into<String>) -> Self {
        let jobs = JobServiceClient::with_interceptor(channel, bearer)
            .max_decoding_message_size(MAX_MESSAGE_BYTES)
            .max_encoding_message_size(MAX_MESSAGE_BYTES);
        Client {
            jobs,
            endpoint: endpoint.into().into(),
        }
    }

    /// The coordinator's URL.
    pub fn endpoint(&self) -> &str {
        &self.endpoint
    }

    /// The generated tonic client, for calls this type does not wrap.
    pub fn raw(&self) -> JobServiceClient<AuthedChannel> {
        self.jobs.clone()
    }

    fn status(&self) -> impl Fn(tonic::Status) -> ClientError + '_ {
        move |status| ClientError::from_status(status, &self.endpoint)
    }

    /// Sends a prepared file as a resumable upload: a session, appends from the size the
    /// coordinator has committed (again after a broken stream, up to [`MAX_UPLOAD_RESUMES`]
    /// times in a row), then the finish with the SHA-256 (repeated safely if its answer is
    /// lost).
    async fn send_upload(
        &self,
        upload: &PreparedUpload,
        kind: pb::UploadKind,
    ) -> Result<pb::UploadReceipt> {
        let session = self
            .jobs
            .clone()
            .start_upload(pb::StartUploadRequest {
                kind: kind as i32,
                filename: upload.filename.clone(),
                total_size: upload.size,
            })
            .await
            .map_err(self.status())?
            .into_inner();
        let id = session.session_id;
        let mut committed = session.committed_size;
        let mut failures = 0;
        loop {
            let step = async {
                if committed < upload.size {
                    committed = self.append(upload, &id, committed).await?;
                }
                if committed < upload.size {
                    return Err(ClientError::Unreachable {
                        endpoint: self.endpoint.to_string(),
                        reason: format!(
                            "the upload stream ended after {committed} of {} bytes",
                            upload.size
                        ),
                    });
                }
                self.jobs
                    .clone()
                    .finish_upload(pb::FinishUploadRequest {
                        session_id: id.clone(),
                        sha256: upload.sha256.clone(),
                        total_size: upload.size,
                    })
                    .await
                    .map(tonic::Response::into_inner)
                    .map_err(self.status())
            };
            let cause = match step.await {
                Ok(receipt) => return Ok(receipt),
                Err(e) if may_resume(&e) && failures < MAX_UPLOAD_RESUMES => e,
                Err(e) => return Err(e),
            };
            failures += 1;
            tracing::warn!(session = %id, error = %cause, attempt = failures, "upload interrupted; resuming");
            tokio::time::sleep(backoff(failures)).await;
            // Where the coordinator stands now (it commits what arrived before the break).
            if let Ok(now) = self
                .jobs
                .clone()
                .get_upload_session(pb::GetUploadSessionRequest {
                    session_id: id.clone(),
                })
                .await
            {
                committed = now.into_inner().committed_size;
            }
        }
    }

    /// One `AppendUpload` stream from `offset`; returns the committed size.
    async fn append(&self, upload: &PreparedUpload, id: &str, offset: u64) -> Result<u64> {
        let io_error = Arc::new(Mutex::new(None));
        let messages = append_stream(upload, id, offset, io_error.clone()).await?;
        let result = self.jobs.clone().append_upload(messages).await;
        if let Some(e) = io_error.lock().expect("not poisoned").take() {
            return Err(ClientError::io(&upload.path, e));
        }
        Ok(result.map_err(self.status())?.into_inner().committed_size)
    }

    /// Uploads a scene: a folder (packed into a tar archive with the members relative to it;
    /// it must hold `transforms.json`, `transforms_train.json` or `poses_bounds.npy` at its root
    /// or one level down) or an existing `.tar` file. Returns the receipt whose `upload_id`
    /// goes into a job.
    pub async fn upload_dataset(&self, path: impl AsRef<Path>) -> Result<pb::UploadReceipt> {
        let path = path.as_ref().to_path_buf();
        let prepared = blocking(move || prepare_dataset(&path)).await?;
        self.send_upload(&prepared, pb::UploadKind::DatasetArchive)
            .await
    }

    /// Uploads a scene without camera poses: a folder of photos (packed into a tar archive;
    /// PNG or JPEG, at least 3 in one folder), a `.tar` of one, or a video (MP4, MOV, MKV,
    /// WebM, AVI, MTS). A job on it starts with the `poses` stage. Returns the receipt.
    pub async fn upload_photos(&self, path: impl AsRef<Path>) -> Result<pb::UploadReceipt> {
        let path = path.as_ref().to_path_buf();
        let prepared = blocking(move || prepare_photos(&path)).await?;
        self.send_upload(&prepared, pb::UploadKind::Photos).await
    }

    /// Uploads one style image (PNG, JPEG, GIF or WebP).
    pub async fn upload_style(&self, path: impl AsRef<Path>) -> Result<pb::UploadReceipt> {
        let path = path.as_ref().to_path_buf();
        let prepared = blocking(move || prepare_file(&path)).await?;
        self.send_upload(&prepared, pb::UploadKind::StyleImage)
            .await
    }

    /// The reference to an input, uploading local paths first.
    async fn input_ref(
        &self,
        input: &Input,
        kind: pb::UploadKind,
        uploads: &mut Vec<pb::UploadReceipt>,
    ) -> Result<pb::InputRef> {
        use pb::input_ref::Source;
        let source = match input {
            Input::UploadId(id) => Source::UploadId(id.clone()),
            Input::ObjectKey(key) => Source::ObjectKey(key.clone()),
            Input::Path(path) => {
                let receipt = match kind {
                    pb::UploadKind::DatasetArchive => self.upload_dataset(path).await?,
                    pb::UploadKind::Photos => self.upload_photos(path).await?,
                    _ => self.upload_style(path).await?,
                };
                let id = receipt.upload_id.clone();
                uploads.push(receipt);
                Source::UploadId(id)
            }
        };
        Ok(pb::InputRef {
            source: Some(source),
        })
    }

    /// Uploads the spec's local inputs and creates the job.
    pub async fn submit(&self, spec: &JobSpec) -> Result<Submission> {
        let (dataset, kind) = match (&spec.dataset, &spec.photos) {
            (Some(dataset), None) => (dataset, pb::UploadKind::DatasetArchive),
            (None, Some(photos)) => (photos, pb::UploadKind::Photos),
            (Some(_), Some(_)) => {
                return Err(ClientError::InvalidInput(
                    "a job starts from a dataset or from photos, not both".into(),
                ))
            }
            (None, None) => {
                return Err(ClientError::InvalidInput(
                    "a job needs a dataset (a scene folder or .tar) or photos (a folder of \
                     photos or a video)"
                        .into(),
                ))
            }
        };
        if spec.styles.is_empty() {
            return Err(ClientError::InvalidInput(
                "a job needs at least one style image".into(),
            ));
        }
        let mut uploads = Vec::new();
        let dataset = self.input_ref(dataset, kind, &mut uploads).await?;
        let mut styles = Vec::with_capacity(spec.styles.len());
        for style in &spec.styles {
            styles.push(
                self.input_ref(style, pb::UploadKind::StyleImage, &mut uploads)
                    .await?,
            );
        }
        let request = pb::CreateJobRequest {
            name: spec.name.clone(),
            dataset: Some(dataset),
            styles,
            preset: spec.preset.clone().unwrap_or_default(),
            config_overrides_json: overrides_json(&spec.overrides),
            idempotency_key: spec.idempotency_key.clone().unwrap_or_default(),
            requirements: Some(spec.requirements.clone()),
            camera_path: spec.camera_path.clone(),
            style_blend: spec.style_blend.clone(),
            webhook: spec.webhook.clone(),
            metadata: spec.metadata.clone(),
            priority: spec.priority,
            deadline_at_ms: spec.deadline_at_ms,
        };
        let response = self.create_job(request).await?;
        let job = response
            .job
            .ok_or_else(|| ClientError::Protocol("CreateJob answered without a job".into()))?;
        Ok(Submission {
            job,
            created: response.created,
            uploads,
            webhook_secret: response.webhook_secret,
        })
    }

    /// `CreateJob` as it is, for callers that build the request themselves.
    pub async fn create_job(&self, request: pb::CreateJobRequest) -> Result<pb::CreateJobResponse> {
        Ok(self
            .jobs
            .clone()
            .create_job(request)
            .await
            .map_err(self.status())?
            .into_inner())
    }

    /// One job with its stage tasks.
    pub async fn get(&self, job_id: &str) -> Result<pb::Job> {
        Ok(self
            .jobs
            .clone()
            .get_job(pb::GetJobRequest {
                job_id: job_id.to_string(),
            })
            .await
            .map_err(self.status())?
            .into_inner())
    }

    /// One page of jobs, newest first.
    pub async fn list(&self, filter: &ListFilter) -> Result<JobPage> {
        let response = self
            .jobs
            .clone()
            .list_jobs(pb::ListJobsRequest {
                states: filter.states.iter().map(|s| *s as i32).collect(),
                owner: filter.owner.clone().unwrap_or_default(),
                page_size: filter.page_size,
                page_token: filter.page_token.clone().unwrap_or_default(),
                include_tasks: filter.include_tasks,
                metadata: filter.metadata.clone(),
            })
            .await
            .map_err(self.status())?
            .into_inner();
        Ok(JobPage {
            jobs: response.jobs,
            next_page_token: Some(response.next_page_token).filter(|t| !t.is_empty()),
        })
    }

    /// Every job matching the filter, following the pages (at most `limit` jobs).
    pub async fn list_all(&self, filter: &ListFilter, limit: usize) -> Result<Vec<pb::Job>> {
        let mut filter = filter.clone();
        let mut jobs = Vec::new();
        loop {
            let page = self.list(&filter).await?;
            jobs.extend(page.jobs);
            match page.next_page_token {
                Some(token) if jobs.len() < limit => filter.page_token = Some(token),
                _ => break,
            }
        }
        jobs.truncate(limit);
        Ok(jobs)
    }

    /// The raw `WatchJob` stream (no reconnection).
    pub(crate) async fn open_watch(
        &self,
        job_id: &str,
        after_seq: u64,
        skip_progress: bool,
    ) -> Result<Streaming<pb::Event>> {
        Ok(self
            .jobs
            .clone()
            .watch_job(pb::WatchJobRequest {
                job_id: job_id.to_string(),
                after_seq,
                skip_progress,
            })
            .await
            .map_err(self.status())?
            .into_inner())
    }

    /// The job's events after `options.after_seq`, then live ones; the stream ends when the job
    /// is terminal. Reconnects on its own after a dropped connection.
    pub async fn watch(&self, job_id: &str, options: WatchOptions) -> Result<EventStream> {
        crate::watch::watch(self.clone(), job_id.to_string(), options).await
    }

    /// Every event of all the caller's jobs after `options.after_seq`, then live, until the
    /// stream is dropped (`WatchJobs`). Resume after a disconnect with the last `seq` seen.
    pub async fn watch_all(&self, options: WatchOptions) -> Result<tonic::Streaming<pb::Event>> {
        Ok(self
            .jobs
            .clone()
            .watch_jobs(pb::WatchJobsRequest {
                after_seq: options.after_seq,
                skip_progress: options.skip_progress,
                owner: String::new(),
            })
            .await
            .map_err(self.status())?
            .into_inner())
    }

    /// Waits until the job is terminal and returns it (state changes only, no progress).
    pub async fn wait(&self, job_id: &str) -> Result<pb::Job> {
        let mut events = self
            .watch(
                job_id,
                WatchOptions {
                    after_seq: 0,
                    skip_progress: true,
                },
            )
            .await?;
        while let Some(event) = events.next().await {
            event?;
        }
        self.get(job_id).await
    }

    /// Cancels the job (a no-op on a terminal job) and returns it.
    pub async fn cancel(&self, job_id: &str, reason: &str) -> Result<pb::Job> {
        Ok(self
            .jobs
            .clone()
            .cancel_job(pb::CancelJobRequest {
                job_id: job_id.to_string(),
                reason: reason.to_string(),
            })
            .await
            .map_err(self.status())?
            .into_inner())
    }

    /// Deletes a finished job: its objects in the store, then its records. A running job must
    /// be cancelled first ([`ClientError`](crate::ClientError) with FAILED_PRECONDITION).
    pub async fn delete(&self, job_id: &str) -> Result<pb::DeleteJobResponse> {
        Ok(self
            .jobs
            .clone()
            .delete_job(pb::DeleteJobRequest {
                job_id: job_id.to_string(),
            })
            .await
            .map_err(self.status())?
            .into_inner())
    }

    /// A signed URL any HTTP client can GET the object from without a token, valid for
    /// `ttl_seconds` (0: the coordinator's default, an hour): presigned by the object store
    /// where it signs (S3, GCS, Azure), else by a coordinator started with `--http-listen`.
    pub async fn artifact_url(
        &self,
        job_id: &str,
        key: &str,
        ttl_seconds: u32,
    ) -> Result<pb::ArtifactUrl> {
        Ok(self
            .jobs
            .clone()
            .get_artifact_url(pb::GetArtifactUrlRequest {
                job_id: job_id.to_string(),
                key: key.to_string(),
                ttl_seconds,
            })
            .await
            .map_err(self.status())?
            .into_inner())
    }

    /// The deliveries of the job's webhook events, oldest first.
    pub async fn webhook_deliveries(&self, job_id: &str) -> Result<Vec<pb::WebhookDelivery>> {
        Ok(self
            .jobs
            .clone()
            .list_webhook_deliveries(pb::ListWebhookDeliveriesRequest {
                job_id: job_id.to_string(),
            })
            .await
            .map_err(self.status())?
            .into_inner()
            .deliveries)
    }

    /// Objects stored under `jobs/<job_id>/<prefix>`.
    pub async fn artifacts(&self, job_id: &str, prefix: &str) -> Result<Vec<pb::Artifact>> {
        Ok(self
            .jobs
            .clone()
            .list_artifacts(pb::ListArtifactsRequest {
                job_id: job_id.to_string(),
                prefix: prefix.to_string(),
            })
            .await
            .map_err(self.status())?
            .into_inner()
            .artifacts)
    }

    /// Downloads the job's outputs (not its inputs or checkpoints) into `dest_dir`, keeping
    /// their paths below `jobs/<job>/` (`dest_dir/render_stylized/frames/0000.png`).
    pub async fn download(
        &self,
        job_id: &str,
        dest_dir: impl AsRef<Path>,
    ) -> Result<Vec<DownloadedFile>> {
        self.download_with(job_id, dest_dir, &DownloadOptions::default())
            .await
    }

    /// Downloads the selected artifacts into `dest_dir`; each file is written atomically.
    pub async fn download_with(
        &self,
        job_id: &str,
        dest_dir: impl AsRef<Path>,
        options: &DownloadOptions,
    ) -> Result<Vec<DownloadedFile>> {
        let dest_dir = dest_dir.as_ref();
        let mut out = Vec::new();
        for artifact in self.artifacts(job_id, &options.prefix).await? {
            let relative = relative_key(job_id, &artifact.key)?;
            if options.wants(relative) {
                let dest: PathBuf = dest_dir.join(relative);
                out.push(self.download_artifact(job_id, &artifact, &dest).await?);
            }
        }
        Ok(out)
    }

    /// Downloads one artifact (as listed by [`Client::artifacts`]) to `dest`, atomically.
    pub async fn download_artifact(
        &self,
        job_id: &str,
        artifact: &pb::Artifact,
        dest: &Path,
    ) -> Result<DownloadedFile> {
        download_file(
            &mut self.jobs.clone(),
            &self.endpoint,
            job_id,
            artifact,
            dest,
        )
        .await
    }

    /// Adds a `render_stylized` task (new camera path and/or style blend) to a job whose
    /// `mutual_learning` stage succeeded.
    pub async fn render(&self, job_id: &str, spec: &RenderSpec) -> Result<pb::Task> {
        Ok(self
            .jobs
            .clone()
            .render_job(pb::RenderJobRequest {
                job_id: job_id.to_string(),
                camera_path: spec.camera_path.clone(),
                style_blend: spec.style_blend.clone(),
                config_overrides_json: overrides_json(&spec.overrides),
            })
            .await
            .map_err(self.status())?
            .into_inner())
    }
}

/// Runs blocking file work (hashing, packing) off the async runtime.
async fn blocking<T: Send + 'static>(
    work: impl FnOnce() -> Result<T> + Send + 'static,
) -> Result<T> {
    tokio::task::spawn_blocking(work)
        .await
        .map_err(|e| ClientError::InvalidInput(format!("preparing the upload failed: {e}")))?
}
