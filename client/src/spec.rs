//! What callers pass to the client: a job specification (inputs as local paths or existing
//! upload ids / object keys, preset, dotted-key overrides, idempotency key, requirements and
//! the final render), a render request, list filters, and the results of submit and list.

use serde_json::{Map, Value};
use std::path::PathBuf;
use stylenerf_proto::v1 as pb;

/// One job input.
#[derive(Debug, Clone, PartialEq)]
pub enum Input {
    /// A local file or, for the dataset, a scene folder (packed into a tar archive) or a
    /// `.tar` file; uploaded by `Client::submit`.
    Path(PathBuf),
    /// An earlier upload of the same owner (`UploadReceipt.upload_id`).
    UploadId(String),
    /// An object the operator staged in the coordinator's store.
    ObjectKey(String),
}

impl Input {
    /// A local path (scene folder, `.tar` archive or style image).
    pub fn path(path: impl Into<PathBuf>) -> Self {
        Input::Path(path.into())
    }
}

impl From<PathBuf> for Input {
    fn from(path: PathBuf) -> Self {
        Input::Path(path)
    }
}

impl From<&std::path::Path> for Input {
    fn from(path: &std::path::Path) -> Self {
        Input::Path(path.to_path_buf())
    }
}

/// Everything needed to create a job.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct JobSpec {
    /// Display name (optional).
    pub name: String,
    /// The scene dataset (with camera poses).
    pub dataset: Option<Input>,
    /// Or plain photos instead: a folder of photos (packed into a tar archive), a `.tar` of
    /// one, or a video; the job then starts with the `poses` stage (COLMAP on a worker).
    pub photos: Option<Input>,
    /// One or more style images.
    pub styles: Vec<Input>,
    /// `tiny`, `quick`, `standard` or `paper`; `None` = the coordinator's default (`quick`).
    pub preset: Option<String>,
    /// Preset overrides, keyed `<stage>.<dotted setting path>` (`"nerf_pretrain.steps": 500`,
    /// `"nerf_pretrain.field.grid.levels": 12`; see docs/API.md, "Stage overrides").
    pub overrides: Map<String, Value>,
    /// Repeating a submission with the same key returns the first job (`created = false`).
    pub idempotency_key: Option<String>,
    /// CUDA, worker labels, memory per task.
    pub requirements: pb::Requirements,
    /// Camera path of the final render (default: the preset's).
    pub camera_path: Option<pb::CameraPath>,
    /// Style blend of the final render (empty = every style in turn).
    pub style_blend: Vec<pb::StyleWeight>,
    /// Where the coordinator POSTs the job's events (signed; see `Submission::webhook_secret`).
    pub webhook: Option<pb::Webhook>,
    /// The integrator's key-value pairs, kept with the job and filterable in `list`.
    pub metadata: std::collections::HashMap<String, String>,
    /// Scheduling priority, -100 to 100 (higher first; 0 by default).
    pub priority: i32,
    /// Epoch ms by which the job must have finished, or it fails (0 = none).
    pub deadline_at_ms: i64,
}

impl JobSpec {
    /// A job on `dataset` with `styles` and every other setting at its default.
    pub fn new<S: Into<Input>>(
        dataset: impl Into<Input>,
        styles: impl IntoIterator<Item = S>,
    ) -> Self {
        JobSpec {
            dataset: Some(dataset.into()),
            styles: styles.into_iter().map(Into::into).collect(),
            ..Default::default()
        }
    }
}

/// A further stylized render of a trained job.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct RenderSpec {
    pub camera_path: Option<pb::CameraPath>,
    /// Style indices (order of the job's styles) and weights; empty = every style in turn.
    pub style_blend: Vec<pb::StyleWeight>,
    /// Overrides for this render only (`render_stylized.<setting>` keys).
    pub overrides: Map<String, Value>,
}

/// Filters and paging of `Client::list`.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ListFilter {
    /// Only jobs in these states (empty = all).
    pub states: Vec<pb::JobState>,
    /// Only this owner's jobs (admin tokens only).
    pub owner: Option<String>,
    /// Page size (0 = the coordinator's default, 50; at most 500).
    pub page_size: u32,
    /// `JobPage::next_page_token` of the previous page.
    pub page_token: Option<String>,
    /// Include each job's stage tasks.
    pub include_tasks: bool,
    /// Only jobs whose metadata holds every one of these pairs.
    pub metadata: std::collections::HashMap<String, String>,
}

/// One page of jobs, newest first.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct JobPage {
    pub jobs: Vec<pb::Job>,
    /// `None` on the last page.
    pub next_page_token: Option<String>,
}

/// The outcome of `Client::submit`.
#[derive(Debug, Clone, PartialEq)]
pub struct Submission {
    pub job: pb::Job,
    /// False when the idempotency key matched an existing job.
    pub created: bool,
    /// Receipts of the inputs uploaded for this submission (dataset first, then styles).
    pub uploads: Vec<pb::UploadReceipt>,
    /// The secret that signs the job's webhook deliveries (empty without a webhook, or when an
    /// existing job was returned): keep it to verify them.
    pub webhook_secret: String,
}

/// Options of `Client::watch`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct WatchOptions {
    /// Only events after this sequence number (0 = the whole history).
    pub after_seq: u64,
    /// Leave out progress events.
    pub skip_progress: bool,
}

/// Serialises overrides as the `config_overrides_json` field (`""` when empty).
pub(crate) fn overrides_json(overrides: &Map<String, Value>) -> String {
    if overrides.is_empty() {
        String::new()
    } else {
        Value::Object(overrides.clone()).to_string()
    }
}
