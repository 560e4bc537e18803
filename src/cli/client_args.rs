//! The client commands' arguments: what `submit`, `status`, `watch`, `list`, `cancel`,
//! `fetch`, `render` and `events` take on the command line, and the parsers of their values
//! (blends, overrides, pairs, states).

use anyhow::Context;
use clap::{Args, Subcommand, ValueEnum};
use serde_json::Value;
use std::path::PathBuf;
use stylenerf_client::{names, pb, Client, ConnectOptions, Input, DEFAULT_ENDPOINT};
use stylenerf_plan::settings::{addressed, parse_override};
use stylenerf_plan::Stage;

/// How results are printed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum OutputFormat {
    Text,
    Json,
}

/// Where the coordinator is and how to print results (shared by every client command).
#[derive(Debug, Clone, Args)]
pub struct ConnectionArgs {
    /// Coordinator URL: http://host:port, https://host:port or host:port.
    #[arg(long, env = "STYLENERF_ENDPOINT", default_value = DEFAULT_ENDPOINT)]
    pub endpoint: String,
    /// Bearer token of a `client` (or `admin`) role; not needed with --insecure-no-auth.
    #[arg(long, env = "STYLENERF_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    /// CA certificate (PEM) that signed the coordinator's TLS certificate [default: the
    /// system CA bundle].
    #[arg(long, env = "STYLENERF_CA_CERT")]
    pub ca_cert: Option<PathBuf>,
    /// Output format: text for people, json (proto JSON field names) for scripts.
    #[arg(short = 'o', long, value_enum, default_value_t = OutputFormat::Text)]
    pub output: OutputFormat,
}

impl ConnectionArgs {
    pub(crate) async fn connect(&self) -> anyhow::Result<Client> {
        let mut options = ConnectOptions::new(self.endpoint.clone(), self.token.clone());
        options.ca_certificate = self.ca_cert.clone();
        Ok(Client::connect_with(&options).await?)
    }

    pub(crate) fn json(&self) -> bool {
        self.output == OutputFormat::Json
    }
}

/// The client commands (flattened into the top-level command list).
#[derive(Debug, Subcommand)]
pub enum ClientCommand {
    /// Upload a scene folder and style images and create a job; prints the job id.
    Submit(Box<SubmitArgs>),
    /// Show a job and its stages.
    Status(JobArgs),
    /// Follow a job with a progress bar per stage until it ends (exit status 1 when it fails
    /// or is cancelled).
    Watch(JobArgs),
    /// List your jobs, newest first.
    List(ListArgs),
    /// Cancel a job.
    Cancel(CancelArgs),
    /// Delete a finished job: its inputs, outputs and checkpoints in the store, then its record
    /// (cancel a running job first).
    Delete(JobArgs),
    /// Print a signed URL from which a browser or any HTTP client can download one of a job's
    /// objects without a token, until it expires (the coordinator needs --http-listen).
    Url(UrlArgs),
    /// The deliveries of a job's webhook: state, attempts, last HTTP status and error.
    Webhooks(JobArgs),
    /// Download a job's outputs into a folder.
    Fetch(FetchArgs),
    /// Render a trained job again with another camera path or style blend.
    Render(RenderArgs),
    /// Print a job's event log, following it until the job ends.
    Events(EventsArgs),
}

#[derive(Debug, Args)]
pub struct SubmitArgs {
    /// Scene: a folder with transforms.json / transforms_train.json / poses_bounds.npy and its
    /// images, a .tar of one, `upload:<id>` or `object:<key>`.
    #[arg(
        long,
        value_name = "DIR",
        required_unless_present = "photos",
        conflicts_with = "photos"
    )]
    pub data: Option<String>,
    /// Or a scene without camera poses: a folder of photos, a .tar of one, a video, or
    /// `upload:<id>`; the job starts with the poses stage (COLMAP, on a worker that has it).
    #[arg(long, value_name = "DIR|VIDEO")]
    pub photos: Option<String>,
    /// Style image (repeat for several styles); also `upload:<id>` or `object:<key>`.
    #[arg(long = "style", value_name = "IMAGE", required = true)]
    pub styles: Vec<String>,
    /// Training preset: tiny, quick, standard or paper [default: the coordinator's, quick].
    #[arg(long)]
    pub preset: Option<String>,
    /// Override a setting of one stage: `--set nerf_pretrain.steps=500
    /// --set decoder_pretrain.style_weight=2` (`<stage>.<setting path>=<JSON or text>`).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub overrides: Vec<String>,
    /// Display name of the job.
    #[arg(long, default_value = "")]
    pub name: String,
    /// Makes retries safe: the same key returns the job created first.
    #[arg(long)]
    pub idempotency_key: Option<String>,
    /// Run only on CUDA workers.
    #[arg(long)]
    pub require_cuda: bool,
    /// Worker label every task needs (repeatable), e.g. `zone=eu`.
    #[arg(long = "label")]
    pub labels: Vec<String>,
    /// Memory each task needs, in MiB [default: the coordinator's per-stage estimate].
    #[arg(long)]
    pub memory_mib: Option<u64>,
    #[command(flatten)]
    pub render: RenderOptions,
    /// Scheduling priority, -100 to 100: higher-priority jobs' tasks are leased first.
    #[arg(long, default_value_t = 0, allow_negative_numbers = true)]
    pub priority: i32,
    /// Fail the job if it has not finished this many seconds from now.
    #[arg(long = "deadline", value_name = "SECONDS")]
    pub deadline_secs: Option<f64>,
    /// Metadata pair kept with the job (repeatable): `--meta customer=42 --meta order=A-17`.
    #[arg(long = "meta", value_name = "KEY=VALUE")]
    pub metadata: Vec<String>,
    /// POST the job's events to this http(s) URL, signed (Standard Webhooks); the secret is
    /// printed once.
    #[arg(long, value_name = "URL")]
    pub webhook: Option<String>,
    /// Events the webhook gets (repeatable): job_created, job_state, task_state,
    /// task_progress [default: job_state].
    #[arg(long = "webhook-event", value_name = "KIND", value_parser = parse_event_kind)]
    pub webhook_events: Vec<pb::EventKind>,
    /// Follow the job until it ends (like `stylenerf watch`).
    #[arg(long)]
    pub wait: bool,
    #[command(flatten)]
    pub connection: ConnectionArgs,
}

/// Camera path and style blend of a stylized render.
#[derive(Debug, Clone, Args)]
pub struct RenderOptions {
    /// Style blend of the final render: `INDEX:WEIGHT,...` over the job's styles in the order
    /// given at submission (`0:0.3,1:0.7`), or one index [default: every style in turn].
    #[arg(long, value_name = "BLEND")]
    pub blend: Option<String>,
    /// Frames to render [default: the preset's].
    #[arg(long)]
    pub frames: Option<u32>,
    /// Camera path kind: orbit, spiral, interpolate or train [default: the preset's].
    #[arg(long = "camera-path", value_name = "KIND")]
    pub camera_path: Option<String>,
    /// Frames per second of the animation [default: the preset's].
    #[arg(long)]
    pub fps: Option<f64>,
}

impl RenderOptions {
    pub(crate) fn camera_path(&self) -> Option<pb::CameraPath> {
        (self.frames.is_some() || self.camera_path.is_some() || self.fps.is_some()).then(|| {
            pb::CameraPath {
                kind: self.camera_path.clone().unwrap_or_default(),
                num_frames: self.frames.unwrap_or(0),
                fps: self.fps.unwrap_or(0.0),
                params_json: String::new(),
            }
        })
    }

    pub(crate) fn style_blend(&self) -> anyhow::Result<Vec<pb::StyleWeight>> {
        self.blend.as_deref().map_or(Ok(Vec::new()), parse_blend)
    }
}

#[derive(Debug, Args)]
pub struct JobArgs {
    /// Job id (`j-...`).
    pub job: String,
    #[command(flatten)]
    pub connection: ConnectionArgs,
}

#[derive(Debug, Args)]
pub struct ListArgs {
    /// Only jobs in these states (repeatable): queued, running, succeeded, failed, cancelled.
    #[arg(long = "state", value_parser = parse_state)]
    pub states: Vec<pb::JobState>,
    /// Only this owner's jobs (admin tokens).
    #[arg(long)]
    pub owner: Option<String>,
    /// Show at most this many jobs.
    #[arg(long, default_value_t = 50)]
    pub limit: usize,
    /// Only jobs with this metadata pair (repeatable): `--meta customer=42`.
    #[arg(long = "meta", value_name = "KEY=VALUE")]
    pub metadata: Vec<String>,
    #[command(flatten)]
    pub connection: ConnectionArgs,
}

#[derive(Debug, Args)]
pub struct CancelArgs {
    /// Job id.
    pub job: String,
    /// Why (kept in the job's error and events).
    #[arg(long, default_value = "cancelled from the command line")]
    pub reason: String,
    #[command(flatten)]
    pub connection: ConnectionArgs,
}

#[derive(Debug, Args)]
pub struct FetchArgs {
    /// Job id.
    pub job: String,
    /// Destination folder [default: ./<job id>].
    #[arg(long = "out", value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Only artifacts under this prefix of the job, e.g. `render_stylized/`.
    #[arg(long, default_value = "")]
    pub prefix: String,
    /// Also download the inputs (dataset archive, style images).
    #[arg(long)]
    pub inputs: bool,
    /// Also download training checkpoints.
    #[arg(long)]
    pub checkpoints: bool,
    #[command(flatten)]
    pub connection: ConnectionArgs,
}

#[derive(Debug, Args)]
pub struct UrlArgs {
    /// Job id.
    pub job: String,
    /// Object key, as `stylenerf fetch` or `ListArtifacts` name it, e.g.
    /// `jobs/<job>/render_stylized/style-0/animation.gif`; a key without the `jobs/<job>/`
    /// prefix is taken relative to the job.
    pub key: String,
    /// Seconds the URL works (at most 7 days) [default: the coordinator's, an hour].
    #[arg(long, default_value_t = 0)]
    pub ttl: u32,
    #[command(flatten)]
    pub connection: ConnectionArgs,
}

#[derive(Debug, Args)]
pub struct RenderArgs {
    /// Job id.
    pub job: String,
    /// Style blend `INDEX:WEIGHT,...` (`0:0.3,1:0.7`) or one style index [default: every
    /// style in turn].
    #[arg(long = "style", value_name = "BLEND")]
    pub blend: Option<String>,
    /// Frames to render [default: the preset's].
    #[arg(long)]
    pub frames: Option<u32>,
    /// Camera path kind: orbit, spiral, interpolate or train [default: the preset's].
    #[arg(long = "camera-path", value_name = "KIND")]
    pub camera_path: Option<String>,
    /// Frames per second [default: the preset's].
    #[arg(long)]
    pub fps: Option<f64>,
    /// Override a setting for this render only: `--set render_stylized.<setting>=<value>`.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub overrides: Vec<String>,
    /// Follow the job until the render ends.
    #[arg(long)]
    pub wait: bool,
    #[command(flatten)]
    pub connection: ConnectionArgs,
}

#[derive(Debug, Args)]
pub struct EventsArgs {
    /// Job id.
    pub job: String,
    /// Only events after this sequence number.
    #[arg(long, default_value_t = 0)]
    pub after: u64,
    /// Leave out progress events.
    #[arg(long)]
    pub no_progress: bool,
    #[command(flatten)]
    pub connection: ConnectionArgs,
}

/// `KEY=VALUE` pairs of an option.
pub(crate) fn parse_pairs(
    option: &str,
    list: &[String],
) -> anyhow::Result<std::collections::HashMap<String, String>> {
    list.iter()
        .map(|pair| {
            pair.split_once('=')
                .map(|(k, v)| (k.to_string(), v.to_string()))
                .ok_or_else(|| anyhow::anyhow!("{option} {pair:?}: expected KEY=VALUE"))
        })
        .collect()
}

pub(crate) fn parse_event_kind(text: &str) -> Result<pb::EventKind, String> {
    pb::EventKind::from_str_name(&format!("EVENT_KIND_{}", text.to_ascii_uppercase()))
        .filter(|k| *k != pb::EventKind::Unspecified)
        .ok_or_else(|| {
            format!("{text:?}: expected job_created, job_state, task_state or task_progress")
        })
}

pub(crate) fn parse_state(text: &str) -> Result<pb::JobState, String> {
    names::parse_job_state(text).ok_or_else(|| {
        format!("unknown job state {text:?} (queued, running, succeeded, failed, cancelled)")
    })
}

/// `0:0.3,1:0.7` (or a single index) as style weights.
pub fn parse_blend(text: &str) -> anyhow::Result<Vec<pb::StyleWeight>> {
    text.split(',')
        .map(str::trim)
        .filter(|part| !part.is_empty())
        .map(|part| {
            let (index, weight) = part.split_once(':').unwrap_or((part, "1"));
            let style_index = index.trim().parse().with_context(|| {
                format!("style blend {part:?}: {index:?} is not a style index (0, 1, ...)")
            })?;
            let weight = weight
                .trim()
                .parse()
                .with_context(|| format!("style blend {part:?}: {weight:?} is not a number"))?;
            Ok(pb::StyleWeight {
                style_index,
                weight,
            })
        })
        .collect()
}

/// `--set <stage>.<path>=value` arguments as the overrides map. Workers address overrides by
/// stage (docs/API.md, "Stage overrides"), so a key without a stage prefix is refused here
/// instead of failing the job's first task.
pub fn parse_overrides(list: &[String]) -> anyhow::Result<serde_json::Map<String, Value>> {
    list.iter()
        .map(|text| {
            let (key, value) = parse_override(text)?;
            anyhow::ensure!(
                addressed(&key).is_ok(),
                "--set {text}: prefix the setting with its stage, one of {} (e.g. \
                 nerf_pretrain.steps=500)",
                Stage::names().join(", ")
            );
            Ok((key, value))
        })
        .collect()
}

/// `upload:<id>` and `object:<key>` reference stored inputs; anything else is a local path.
pub(crate) fn parse_input(text: &str) -> Input {
    if let Some(id) = text.strip_prefix("upload:") {
        Input::UploadId(id.to_string())
    } else if let Some(key) = text.strip_prefix("object:") {
        Input::ObjectKey(key.to_string())
    } else {
        Input::path(text)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn blends_and_overrides_parse() {
        let blend = parse_blend("0:0.3, 1:0.7").unwrap();
        assert_eq!((blend[1].style_index, blend[1].weight), (1, 0.7));
        assert_eq!(parse_blend("2").unwrap()[0].weight, 1.0);
        assert!(parse_blend("a:1").is_err());
        let overrides = parse_overrides(&[
            "nerf_pretrain.steps=500".into(),
            "render_stylized.mode=fast".into(),
        ])
        .unwrap();
        assert_eq!(overrides["nerf_pretrain.steps"], 500);
        assert_eq!(overrides["render_stylized.mode"], "fast");
        let err = parse_overrides(&["steps=500".into()])
            .unwrap_err()
            .to_string();
        assert!(err.contains("prefix the setting with its stage"), "{err}");
    }
}
