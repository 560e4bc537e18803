//! The client commands: `submit`, `status`, `watch`, `list`, `cancel`, `fetch`, `render` and
//! `events`, talking to a coordinator through `stylenerf-client`. Each takes `--endpoint` /
//! `--token` (or `STYLENERF_ENDPOINT` / `STYLENERF_TOKEN`) and `--output text|json`: text for
//! people, one JSON document (or one per line for event streams) for scripts. Their arguments
//! are in [`super::client_args`], the text they print in [`super::client_format`] and the live
//! view of `watch` in [`super::client_view`]; this module runs them.

use super::client_args::*;
use super::client_format::*;
use super::client_view::{StageTimes, WatchView};
use super::terminal_safe::TerminalSafe;
use futures::StreamExt;
use serde_json::{json, Value};
use std::io::Write;
use std::path::PathBuf;
use stylenerf_client::{
    json as to_json, names, pb, Client, DownloadOptions, JobSpec, ListFilter, RenderSpec,
    WatchOptions,
};

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

async fn submit(args: SubmitArgs, out: &mut dyn Write) -> anyhow::Result<()> {
    let json = args.connection.json();
    let spec = JobSpec {
        name: args.name.clone(),
        dataset: args.data.as_deref().map(parse_input),
        photos: args.photos.as_deref().map(parse_input),
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

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn commands_print_json() {
        let dir = tempfile::tempdir().unwrap();
        let config = super::super::common::with_engine_checks(
            stylenerf_server::CoordinatorConfig::local(&dir.path().join("coord")),
        );
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
        // The same scene without its depth maps.
        let flat = dir.path().join("flat");
        generate(&options, &flat).unwrap();
        let transforms = flat.join("transforms.json");
        let mut meta: Value =
            serde_json::from_str(&std::fs::read_to_string(&transforms).unwrap()).unwrap();
        for frame in meta["frames"].as_array_mut().unwrap() {
            frame.as_object_mut().unwrap().remove("depth_file_path");
        }
        std::fs::write(&transforms, meta.to_string()).unwrap();
        let (scene, style) = (scene.display().to_string(), style.display().to_string());
        let common = ["--endpoint", endpoint.as_str(), "--output", "json"];

        // (A depth loss is accepted for a dataset with depth maps.)
        let submit = [
            &[
                "submit", "--data", &scene, "--style", &style, "--preset", "tiny",
            ][..],
            &["--set", "nerf_pretrain.steps=10", "--blend", "0:1"],
            &["--set", "nerf_pretrain.depth_weight=0.1"],
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
        // So is what a stage would refuse on this dataset: a depth loss without depth maps.
        let without_depth = [
            &[
                "submit",
                "--data",
                flat.to_str().unwrap(),
                "--style",
                &style,
            ][..],
            &[
                "--preset",
                "tiny",
                "--set",
                "nerf_pretrain.depth_weight=0.1",
            ],
            &common,
        ]
        .concat();
        let err = run_line(&without_depth).await.unwrap_err().to_string();
        assert!(
            err.contains("config_overrides_json.nerf_pretrain.depth_weight")
                && err.contains("depth map"),
            "{err}"
        );
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
