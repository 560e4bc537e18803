//! The client commands: `submit`, `status`, `watch`, `list`, `cancel`, `fetch`, `render` and
//! `events`, talking to a coordinator through `stylenerf-client`. Each takes `--endpoint` /
//! `--token` (or `STYLENERF_ENDPOINT` / `STYLENERF_TOKEN`) and `--output text|json`: text for
//! people, one JSON document (or one per line for event streams) for scripts.

use super::client_view::{StageTimes, WatchView};
use super::terminal_safe::TerminalSafe;
use anyhow::Context;
use clap::{Args, Subcommand, ValueEnum};
use futures::StreamExt;
use serde_json::{json, Value};
use std::io::Write;
use std::path::PathBuf;
use stylenerf_client::{
    json as to_json, names, pb, Client, ConnectOptions, DownloadOptions, Input, JobSpec,
    ListFilter, RenderSpec, WatchOptions, DEFAULT_ENDPOINT,
};
use stylenerf_plan::settings::parse_override;

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
    async fn connect(&self) -> anyhow::Result<Client> {
        let mut options = ConnectOptions::new(self.endpoint.clone(), self.token.clone());
        options.ca_certificate = self.ca_cert.clone();
        Ok(Client::connect_with(&options).await?)
    }

    fn json(&self) -> bool {
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
    #[arg(long, value_name = "DIR")]
    pub data: String,
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
    fn camera_path(&self) -> Option<pb::CameraPath> {
        (self.frames.is_some() || self.camera_path.is_some() || self.fps.is_some()).then(|| {
            pb::CameraPath {
                kind: self.camera_path.clone().unwrap_or_default(),
                num_frames: self.frames.unwrap_or(0),
                fps: self.fps.unwrap_or(0.0),
                params_json: String::new(),
            }
        })
    }

    fn style_blend(&self) -> anyhow::Result<Vec<pb::StyleWeight>> {
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
fn parse_pairs(
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

fn parse_event_kind(text: &str) -> Result<pb::EventKind, String> {
    pb::EventKind::from_str_name(&format!("EVENT_KIND_{}", text.to_ascii_uppercase()))
        .filter(|k| *k != pb::EventKind::Unspecified)
        .ok_or_else(|| {
            format!("{text:?}: expected job_created, job_state, task_state or task_progress")
        })
}

fn parse_state(text: &str) -> Result<pb::JobState, String> {
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
    let stages: Vec<String> = (1..=5).map(names::stage).collect();
    list.iter()
        .map(|text| {
            let (key, value) = parse_override(text)?;
            let stage = key.split('.').next().unwrap_or_default();
            anyhow::ensure!(
                key.contains('.') && stages.iter().any(|s| s == stage),
                "--set {text}: prefix the setting with its stage, one of {} (e.g. \
                 nerf_pretrain.steps=500)",
                stages.join(", ")
            );
            Ok((key, value))
        })
        .collect()
}

/// `upload:<id>` and `object:<key>` reference stored inputs; anything else is a local path.
fn parse_input(text: &str) -> Input {
    if let Some(id) = text.strip_prefix("upload:") {
        Input::UploadId(id.to_string())
    } else if let Some(key) = text.strip_prefix("object:") {
        Input::ObjectKey(key.to_string())
    } else {
        Input::path(text)
    }
}

pub fn run(command: ClientCommand) -> anyhow::Result<()> {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    let mut stdout = TerminalSafe::new(std::io::stdout().lock());
    runtime.block_on(execute(command, &mut stdout))
}

/// Runs one client command, writing its result to `out` (progress goes to stderr).
pub async fn execute(command: ClientCommand, out: &mut dyn Write) -> anyhow::Result<()> {
    match command {
        ClientCommand::Submit(args) => submit(*args, out).await,
        ClientCommand::Status(args) => {
            let client = args.connection.connect().await?;
            let job = client.get(&args.job).await?;
            if args.connection.json() {
                print_json(out, &to_json::message(&job))
            } else {
                print_job(out, &job)
            }
        }
        ClientCommand::Watch(args) => {
            let client = args.connection.connect().await?;
            follow(&client, &args.job, args.connection.json(), out).await
        }
        ClientCommand::List(args) => list(args, out).await,
        ClientCommand::Cancel(args) => {
            let client = args.connection.connect().await?;
            let job = client.cancel(&args.job, &args.reason).await?;
            if args.connection.json() {
                print_json(out, &to_json::message(&job))
            } else {
                writeln!(out, "{}: {}", job.id, names::job_state(job.state))?;
                Ok(())
            }
        }
        ClientCommand::Delete(args) => {
            let client = args.connection.connect().await?;
            let deleted = client.delete(&args.job).await?;
            if args.connection.json() {
                print_json(out, &to_json::message(&deleted))
            } else {
                writeln!(
                    out,
                    "{}: deleted ({} objects, {})",
                    args.job,
                    deleted.deleted_objects,
                    human_bytes(deleted.deleted_bytes)
                )?;
                Ok(())
            }
        }
        ClientCommand::Url(args) => {
            let client = args.connection.connect().await?;
            let prefix = format!("jobs/{}/", args.job);
            let key = if args.key.starts_with(&prefix) {
                args.key.clone()
            } else {
                format!("{prefix}{}", args.key)
            };
            let url = client.artifact_url(&args.job, &key, args.ttl).await?;
            if args.connection.json() {
                print_json(out, &to_json::message(&url))
            } else {
                writeln!(out, "{}", url.url)?;
                Ok(())
            }
        }
        ClientCommand::Webhooks(args) => {
            let client = args.connection.connect().await?;
            let deliveries = client.webhook_deliveries(&args.job).await?;
            if args.connection.json() {
                let all: Vec<Value> = deliveries.iter().map(to_json::message).collect();
                return print_json(out, &Value::Array(all));
            }
            for d in &deliveries {
                let status = match d.last_status {
                    0 => String::new(),
                    s => format!(" HTTP {s}"),
                };
                let error = if d.last_error.is_empty() || d.state == "delivered" {
                    String::new()
                } else {
                    format!(": {}", d.last_error)
                };
                writeln!(
                    out,
                    "#{} event {} {} {} after {} attempt(s){status}{error}",
                    d.id,
                    d.event_seq,
                    names::event_kind(d.kind),
                    d.state,
                    d.attempts
                )?;
            }
            Ok(())
        }
        ClientCommand::Fetch(args) => fetch(args, out).await,
        ClientCommand::Render(args) => render(args, out).await,
        ClientCommand::Events(args) => events(args, out).await,
    }
}

fn print_json(out: &mut dyn Write, value: &Value) -> anyhow::Result<()> {
    serde_json::to_writer_pretty(&mut *out, value)?;
    writeln!(out)?;
    Ok(())
}

async fn submit(args: SubmitArgs, out: &mut dyn Write) -> anyhow::Result<()> {
    let json = args.connection.json();
    let spec = JobSpec {
        name: args.name.clone(),
        dataset: Some(parse_input(&args.data)),
        styles: args.styles.iter().map(|s| parse_input(s)).collect(),
        preset: args.preset.clone(),
        overrides: parse_overrides(&args.overrides)?,
        idempotency_key: args.idempotency_key.clone(),
        requirements: pb::Requirements {
            require_cuda: args.require_cuda,
            labels: args.labels.clone(),
            memory_bytes: args.memory_mib.map_or(0, |mib| mib << 20),
        },
        camera_path: args.render.camera_path(),
        style_blend: args.render.style_blend()?,
        metadata: parse_pairs("--meta", &args.metadata)?,
        priority: args.priority,
        deadline_at_ms: args
            .deadline_secs
            .map_or(0, |secs| now_ms() + (secs * 1000.0) as i64),
        webhook: args.webhook.as_ref().map(|url| pb::Webhook {
            url: url.clone(),
            events: args.webhook_events.iter().map(|k| *k as i32).collect(),
        }),
    };
    let client = args.connection.connect().await?;
    let submission = client.submit(&spec).await?;
    let job_id = submission.job.id.clone();
    if json {
        let mut job = submission.job.clone();
        if args.wait {
            job = client.wait(&job_id).await?;
        }
        print_json(
            out,
            &json!({
                "job": to_json::message(&job),
                "created": submission.created,
                "uploads": submission.uploads.iter().map(to_json::message).collect::<Vec<_>>(),
                "webhook_secret": submission.webhook_secret,
            }),
        )?;
        return terminal_outcome(&job, args.wait);
    }
    for receipt in &submission.uploads {
        eprintln!("uploaded {} ({})", receipt.upload_id, receipt.summary);
    }
    if !submission.created {
        eprintln!("an existing job has this idempotency key");
    }
    if !submission.webhook_secret.is_empty() {
        eprintln!(
            "webhook secret (verifies the deliveries; shown once): {}",
            submission.webhook_secret
        );
    }
    writeln!(out, "{job_id}")?;
    out.flush()?;
    if args.wait {
        follow(&client, &job_id, false, &mut std::io::sink()).await?;
    }
    Ok(())
}

/// With `--wait`: an error (exit status 1) unless the job succeeded.
fn terminal_outcome(job: &pb::Job, waited: bool) -> anyhow::Result<()> {
    if !waited || job.state == pb::JobState::Succeeded as i32 {
        return Ok(());
    }
    let reason = if job.error.is_empty() {
        String::new()
    } else {
        format!(": {}", job.error)
    };
    anyhow::bail!("job {} {}{reason}", job.id, names::job_state(job.state))
}

/// Follows the job until it is terminal: progress bars (text) or one event per line (JSON).
/// Also used by `stylenerf demo`.
pub(crate) async fn follow(
    client: &Client,
    job_id: &str,
    json: bool,
    out: &mut dyn Write,
) -> anyhow::Result<()> {
    let job = client.get(job_id).await?;
    let mut events = client.watch(job_id, WatchOptions::default()).await?;
    let mut view = if json {
        None
    } else {
        let times = StageTimes::of_last_similar(client, &job).await;
        Some(WatchView::new(&job, times))
    };
    while let Some(event) = events.next().await {
        let event = event?;
        match &mut view {
            Some(view) => view.apply(&event),
            None => {
                serde_json::to_writer(&mut *out, &to_json::message(&event))?;
                writeln!(out)?;
                out.flush()?;
            }
        }
    }
    let job = client.get(job_id).await?;
    if let Some(view) = view {
        view.finish(&job);
    }
    terminal_outcome(&job, true)
}

async fn list(args: ListArgs, out: &mut dyn Write) -> anyhow::Result<()> {
    let client = args.connection.connect().await?;
    let filter = ListFilter {
        states: args.states.clone(),
        owner: args.owner.clone(),
        page_size: args.limit.clamp(1, 500) as u32,
        metadata: parse_pairs("--meta", &args.metadata)?,
        ..Default::default()
    };
    let jobs = client.list_all(&filter, args.limit).await?;
    if args.connection.json() {
        return print_json(
            out,
            &Value::Array(jobs.iter().map(to_json::message).collect()),
        );
    }
    if jobs.is_empty() {
        writeln!(out, "no jobs")?;
        return Ok(());
    }
    writeln!(
        out,
        "{:<36}  {:<10}  {:<8}  {:<10}  NAME",
        "JOB", "STATE", "PRESET", "CREATED"
    )?;
    for job in &jobs {
        writeln!(
            out,
            "{:<36}  {:<10}  {:<8}  {:<10}  {}",
            job.id,
            names::job_state(job.state),
            job.preset,
            ago(job.created_at_ms),
            job.name
        )?;
    }
    Ok(())
}

async fn fetch(args: FetchArgs, out: &mut dyn Write) -> anyhow::Result<()> {
    let client = args.connection.connect().await?;
    let dest = args.out.clone().unwrap_or_else(|| PathBuf::from(&args.job));
    let options = DownloadOptions {
        prefix: args.prefix.clone(),
        include_inputs: args.inputs,
        include_checkpoints: args.checkpoints,
    };
    let files = client.download_with(&args.job, &dest, &options).await?;
    if args.connection.json() {
        return print_json(
            out,
            &json!({
                "job_id": args.job,
                "dir": dest,
                "files": files.iter().map(to_json::downloaded).collect::<Vec<_>>(),
            }),
        );
    }
    let mut bytes = 0;
    for file in &files {
        let verb = if file.skipped { "up to date" } else { "wrote" };
        writeln!(
            out,
            "{verb:>10}  {}  ({})",
            file.path.display(),
            human_bytes(file.size)
        )?;
        bytes += file.size;
    }
    writeln!(
        out,
        "{} files, {} in {}",
        files.len(),
        human_bytes(bytes),
        dest.display()
    )?;
    Ok(())
}

async fn render(args: RenderArgs, out: &mut dyn Write) -> anyhow::Result<()> {
    let options = RenderOptions {
        blend: args.blend.clone(),
        frames: args.frames,
        camera_path: args.camera_path.clone(),
        fps: args.fps,
    };
    let spec = RenderSpec {
        camera_path: options.camera_path(),
        style_blend: options.style_blend()?,
        overrides: parse_overrides(&args.overrides)?,
    };
    let client = args.connection.connect().await?;
    let task = client.render(&args.job, &spec).await?;
    if args.connection.json() {
        let mut value = json!({"task": to_json::message(&task)});
        if args.wait {
            let job = client.wait(&args.job).await?;
            value["job"] = to_json::message(&job);
            print_json(out, &value)?;
            return terminal_outcome(&job, true);
        }
        return print_json(out, &value);
    }
    writeln!(
        out,
        "render task {} of {} writes to {}",
        task.id, task.job_id, task.output_prefix
    )?;
    out.flush()?;
    if args.wait {
        follow(&client, &args.job, false, &mut std::io::sink()).await?;
    }
    Ok(())
}

async fn events(args: EventsArgs, out: &mut dyn Write) -> anyhow::Result<()> {
    let client = args.connection.connect().await?;
    let options = WatchOptions {
        after_seq: args.after,
        skip_progress: args.no_progress,
    };
    let mut events = client.watch(&args.job, options).await?;
    while let Some(event) = events.next().await {
        let event = event?;
        if args.connection.json() {
            serde_json::to_writer(&mut *out, &to_json::message(&event))?;
            writeln!(out)?;
        } else {
            writeln!(out, "{}", describe_event(&event))?;
        }
        out.flush()?;
    }
    Ok(())
}

/// One line per event: `#12 14:03:21 nerf_pretrain leased (attempt 1)`.
fn describe_event(event: &pb::Event) -> String {
    let kind = pb::EventKind::try_from(event.kind).unwrap_or_default();
    let what = match kind {
        pb::EventKind::JobCreated => "job created".to_string(),
        pb::EventKind::JobState => format!("job {}", names::job_state(event.job_state)),
        pb::EventKind::TaskState => format!(
            "{} {} (attempt {})",
            names::stage(event.stage),
            names::task_state(event.task_state),
            event.attempt
        ),
        pb::EventKind::TaskProgress => format!(
            "{} {}",
            names::stage(event.stage),
            event
                .progress
                .as_ref()
                .map(describe_progress)
                .unwrap_or_default()
        ),
        pb::EventKind::Unspecified => names::event_kind(event.kind),
    };
    let message = if event.message.is_empty() {
        String::new()
    } else {
        format!(": {}", event.message)
    };
    format!("#{} {} {what}{message}", event.seq, clock(event.at_ms))
}

/// `value` with four significant digits (`24.31`, `0.003000`, `1235`), in scientific notation
/// when it is tiny (`5.00e-5`): a learning rate must not show as `0.00`.
fn significant(value: f64) -> String {
    if value == 0.0 || !value.is_finite() {
        return value.to_string();
    }
    let magnitude = value.abs().log10().floor() as i32;
    if magnitude < -3 {
        return format!("{value:.2e}");
    }
    let decimals = (3 - magnitude).clamp(0, 6) as usize;
    format!("{value:.decimals$}")
}

/// The metrics a person reads, in this order; the others a stage reports (`rays`,
/// `samples_per_ray`, `occupied`, `resumed_from`, …) are for benchmarks and `-o json`.
const SHOWN_METRICS: [&str; 4] = ["psnr", "style", "content", "lr"];

/// `120/800 ETA 1m20s loss 0.01230 psnr 24.31 lr 0.005000`: step and the stage's ETA first
/// (what a narrow terminal keeps), then the loss and the curated metrics with four significant
/// digits, then the worker's message.
pub fn describe_progress(p: &pb::Progress) -> String {
    let mut parts = Vec::new();
    if p.total > 0 {
        parts.push(format!("{}/{}", p.step, p.total));
    } else if p.step > 0 {
        parts.push(format!("step {}", p.step));
    }
    if p.eta_seconds > 0.0 && p.total > 0 && p.step < p.total {
        parts.push(format!("ETA {}", duration(p.eta_seconds)));
    }
    if p.loss != 0.0 {
        parts.push(format!("loss {}", significant(p.loss)));
    }
    for name in SHOWN_METRICS {
        if let Some(value) = p.metrics.get(name) {
            parts.push(format!("{name} {}", significant(*value)));
        }
    }
    if !p.message.is_empty() {
        parts.push(p.message.clone());
    }
    parts.join(" ")
}

fn print_job(out: &mut dyn Write, job: &pb::Job) -> anyhow::Result<()> {
    let name = if job.name.is_empty() {
        String::new()
    } else {
        format!(" ({})", job.name)
    };
    writeln!(out, "job {}{name}: {}", job.id, names::job_state(job.state))?;
    writeln!(
        out,
        "  preset {}, owner {}, created {}",
        job.preset,
        job.owner,
        ago(job.created_at_ms)
    )?;
    if !job.error.is_empty() {
        writeln!(out, "  error: {}", job.error)?;
    }
    for task in &job.tasks {
        let mut detail = match pb::TaskState::try_from(task.state).unwrap_or_default() {
            pb::TaskState::Leased => task
                .progress
                .as_ref()
                .map(describe_progress)
                .unwrap_or_default(),
            pb::TaskState::Succeeded if task.finished_at_ms > 0 && task.started_at_ms > 0 => {
                format!(
                    "in {}",
                    duration((task.finished_at_ms - task.started_at_ms) as f64 / 1000.0)
                )
            }
            _ => String::new(),
        };
        if !task.error.is_empty() {
            detail = format!("{detail} error: {}", task.error);
        }
        writeln!(
            out,
            "  {:<16} {:<10} attempt {}/{}  {}",
            names::stage(task.stage),
            names::task_state(task.state),
            task.attempt,
            task.max_attempts,
            detail.trim()
        )?;
    }
    Ok(())
}

pub fn now_ms() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as i64)
}

/// `3m ago`.
fn ago(at_ms: i64) -> String {
    if at_ms <= 0 {
        return "-".into();
    }
    format!(
        "{} ago",
        duration(((now_ms() - at_ms).max(0) as f64) / 1000.0)
    )
}

/// `14:03:21` (UTC) of an epoch-ms time.
fn clock(at_ms: i64) -> String {
    let secs = at_ms.div_euclid(1000).rem_euclid(86_400);
    format!("{:02}:{:02}:{:02}", secs / 3600, secs / 60 % 60, secs % 60)
}

/// `45s`, `12m03s`, `2h05m`.
pub fn duration(seconds: f64) -> String {
    let s = seconds.max(0.0).round() as u64;
    match s {
        0..=59 => format!("{s}s"),
        60..=3599 => format!("{}m{:02}s", s / 60, s % 60),
        _ => format!("{}h{:02}m", s / 3600, s / 60 % 60),
    }
}

fn human_bytes(bytes: u64) -> String {
    const UNITS: [&str; 4] = ["B", "KiB", "MiB", "GiB"];
    let mut value = bytes as f64;
    let mut unit = 0;
    while value >= 1024.0 && unit + 1 < UNITS.len() {
        value /= 1024.0;
        unit += 1;
    }
    if unit == 0 {
        format!("{bytes} B")
    } else {
        format!("{value:.1} {}", UNITS[unit])
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cli::{Cli, Command};
    use clap::Parser;
    use stylenerf_engine::scene::generate::{generate, GenerateOptions};

    /// Parses a command line and runs the client command it names, returning its stdout.
    async fn run_line(args: &[&str]) -> anyhow::Result<String> {
        let cli = Cli::try_parse_from(std::iter::once("stylenerf").chain(args.iter().copied()))?;
        let Command::Client(command) = cli.command else {
            panic!("not a client command: {args:?}");
        };
        let mut out = Vec::new();
        execute(command, &mut out).await?;
        Ok(String::from_utf8(out)?)
    }

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
        assert_eq!(duration(75.0), "1m15s");
        // The metrics a person reads, in a fixed order with four significant digits; the
        // internal ones stay out of the line.
        let progress = pb::Progress {
            step: 120,
            total: 800,
            loss: 0.0123,
            eta_seconds: 80.0,
            metrics: [
                ("lr".to_string(), 0.00005),
                ("rays".to_string(), 8192.0),
                ("psnr".to_string(), 24.3149),
                ("samples_per_ray".to_string(), 29.5),
                ("style".to_string(), 1.5),
            ]
            .into(),
            ..Default::default()
        };
        let line = describe_progress(&progress);
        assert_eq!(
            line,
            "120/800 ETA 1m20s loss 0.01230 psnr 24.31 style 1.500 lr 5.00e-5"
        );
        // In the watch view (16-column stage name, bar, time run) at 80 columns, what is cut
        // is the end of the metrics, never the step or the ETA.
        let shown = 80 - 16 - 20 - "12m03s ".len();
        assert!(
            line.find("ETA 1m20s").unwrap() + "ETA 1m20s".len() <= shown,
            "{line}"
        );
        assert_eq!(clock(3_723_000), "01:02:03");
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn commands_print_json() {
        let dir = tempfile::tempdir().unwrap();
        let mut config = stylenerf_server::CoordinatorConfig::local(&dir.path().join("coord"));
        config.settings_check = Some(super::super::common::engine_settings_check());
        let coordinator = stylenerf_server::Coordinator::start(config).await.unwrap();
        let endpoint = coordinator.endpoint();
        let scene = dir.path().join("scene");
        let options = GenerateOptions {
            size: 8,
            views: 2,
            ..Default::default()
        };
        generate(&options, &scene).unwrap();
        let style = std::fs::read_dir(scene.join("images"))
            .unwrap()
            .map(|e| e.unwrap().path())
            .find(|p| p.extension().is_some_and(|e| e == "png"))
            .unwrap();
        let (scene, style) = (scene.display().to_string(), style.display().to_string());
        let common = ["--endpoint", endpoint.as_str(), "--output", "json"];

        let submit = [
            &[
                "submit", "--data", &scene, "--style", &style, "--preset", "tiny",
            ][..],
            &["--set", "nerf_pretrain.steps=10", "--blend", "0:1"],
            &common,
        ]
        .concat();
        // Overrides that would exhaust or break a worker are refused at submission.
        for (set, key) in [
            (
                "nerf_pretrain.rays_per_batch=1000000000000",
                "nerf_pretrain.rays_per_batch",
            ),
            (
                "nerf_pretrain.field.grid.log2_table_size=60",
                "log2_table_size",
            ),
            ("nerf_pretrain.stpes=10", "nerf_pretrain.stpes"),
        ] {
            let refused = [
                &[
                    "submit", "--data", &scene, "--style", &style, "--preset", "tiny",
                ][..],
                &["--set", set],
                &common,
            ]
            .concat();
            let err = run_line(&refused).await.unwrap_err().to_string();
            assert!(
                err.contains("config_overrides_json.") && err.contains(key),
                "{set}: {err}"
            );
        }
        let submitted: Value = serde_json::from_str(&run_line(&submit).await.unwrap()).unwrap();
        assert_eq!(submitted["created"], true);
        // Proto JSON: the messages read back with the protocol's own JSON mapping.
        let created: pb::Job = serde_json::from_value(submitted["job"].clone()).unwrap();
        assert_eq!(created.state(), pb::JobState::Queued);
        assert_eq!(submitted["job"]["state"], "JOB_STATE_QUEUED");
        let overrides: Value = serde_json::from_str(&created.config_overrides_json).unwrap();
        assert_eq!(overrides["nerf_pretrain.steps"], 10);
        assert_eq!(
            submitted["uploads"][0]["kind"],
            "UPLOAD_KIND_DATASET_ARCHIVE"
        );
        let job = submitted["job"]["id"].as_str().unwrap().to_string();

        let status: Value = serde_json::from_str(
            &run_line(&[&["status", &job][..], &common].concat())
                .await
                .unwrap(),
        )
        .unwrap();
        assert_eq!(status["tasks"][0]["stage"], "STAGE_NERF_PRETRAIN");
        assert_eq!(status["tasks"][0]["state"], "TASK_STATE_READY");
        let list: Value =
            serde_json::from_str(&run_line(&[&["list"][..], &common].concat()).await.unwrap())
                .unwrap();
        assert_eq!(list[0]["id"], job.as_str());
        let cancelled: Value = serde_json::from_str(
            &run_line(&[&["cancel", &job][..], &common].concat())
                .await
                .unwrap(),
        )
        .unwrap();
        assert_eq!(cancelled["state"], "JOB_STATE_CANCELLED");
        let events = run_line(&[&["events", &job][..], &common].concat())
            .await
            .unwrap();
        let kinds: Vec<String> = events
            .lines()
            .map(|l| {
                serde_json::from_str::<Value>(l).unwrap()["kind"]
                    .as_str()
                    .unwrap()
                    .into()
            })
            .collect();
        assert_eq!(
            kinds.first().map(String::as_str),
            Some("EVENT_KIND_JOB_CREATED")
        );
        assert_eq!(
            kinds.last().map(String::as_str),
            Some("EVENT_KIND_JOB_STATE")
        );
        // `watch` of a cancelled job fails (exit status 1) after printing its events.
        let err = run_line(&[&["watch", &job][..], &common].concat())
            .await
            .unwrap_err();
        assert!(err.to_string().contains("cancelled"), "{err}");
        let fetched: Value = serde_json::from_str(
            &run_line(
                &[
                    &["fetch", &job, "--inputs", "--out"][..],
                    &[dir.path().join("out").to_str().unwrap()],
                    &common,
                ]
                .concat(),
            )
            .await
            .unwrap(),
        )
        .unwrap();
        assert_eq!(fetched["files"].as_array().unwrap().len(), 2);
        let err = run_line(&[&["status", "j-nope"][..], &common].concat())
            .await
            .unwrap_err();
        assert!(err.to_string().contains("not found"), "{err}");

        coordinator.shutdown().await.unwrap();
    }
}
