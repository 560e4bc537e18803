//! `stylenerf bench chaos`: the service under fire. A coordinator and workers run as separate
//! processes of this binary on loopback (real SQLite file, real object store folder, the real
//! engine on the `tiny` preset); jobs are submitted while processes are killed with SIGKILL at
//! random moments — workers, and the coordinator (once, while a live worker holds a stage, with
//! an outage of eight seconds, so that stages finish while it is away; repeated, twice at most,
//! when no worker had to retry through it) — and restarted; one worker kill is
//! aimed, at the first worker seen holding a task with a checkpoint in the store. At the end every
//! acknowledged job must exist and have succeeded, each of its stages must have succeeded
//! exactly once (its event log), and a killed worker must have run at most one checkpoint
//! interval since its newest checkpoint, which the next attempt resumes from (or from a newer
//! one). Prints a JSON report and fails on any violation; `tests/chaos.rs` runs a short
//! version.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use serde::Serialize;
use stylenerf_client::{pb, Client, Input, JobSpec, WatchOptions};
use stylenerf_engine::image_io::save_rgb_png;
use stylenerf_engine::scene::generate::{generate, GenerateOptions};
use stylenerf_engine::style2d::painted;
use stylenerf_engine::Rng;
use stylenerf_server::storage::Storage;

/// Options of `stylenerf bench chaos`.
#[derive(Debug, Clone, clap::Args)]
pub struct BenchChaosArgs {
    /// Jobs to submit (tiny preset, shortened schedules).
    #[arg(long, default_value_t = 20)]
    pub jobs: usize,
    /// SIGKILLs to deliver (workers and the coordinator).
    #[arg(long, default_value_t = 100)]
    pub kills: usize,
    /// Worker processes kept running.
    #[arg(long, default_value_t = 2)]
    pub workers: usize,
    /// Seed of the kill schedule.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Give up after this many seconds.
    #[arg(long, default_value_t = 3600)]
    pub timeout_secs: u64,
    /// Keep the cluster's files (database, store, logs) here instead of a temporary folder.
    #[arg(long)]
    pub dir: Option<PathBuf>,
    /// The coordinator's artifact store (a folder or an `s3://`, `gs://`, `az://` URL, with
    /// its options in the environment as for `coordinator --storage`); by default a folder
    /// beside the database. Checkpoints are read back through the same store.
    #[arg(long)]
    pub storage: Option<String>,
}

/// Steps between checkpoints of the workers: the most a kill may cost, with upload lag.
const CHECKPOINT_EVERY: u64 = 5;

/// The workers' JSON log, in the run's folder (all workers append to it).
const WORKERS_LOG: &str = "workers.log";

/// What a run found.
#[derive(Debug, Default, Serialize)]
pub struct ChaosReport {
    pub jobs_acknowledged: usize,
    pub jobs_succeeded: usize,
    pub worker_kills: usize,
    pub coordinator_kills: usize,
    /// Worker kills that stopped a stage in the middle (a leased task with progress).
    pub kills_mid_stage: usize,
    /// Longest the coordinator was away at once (seconds).
    pub longest_outage_secs: f64,
    /// Most stage steps a worker kill lost: its step then (as of its last heartbeat) less the
    /// newest checkpoint in the store, which the next attempt resumes from.
    pub most_steps_lost: u64,
    /// Most steps a killed worker had run since its newest local checkpoint (the checkpoint
    /// policy's bound: `--checkpoint-every-steps`); the rest of a loss is upload lag.
    pub most_steps_since_local_checkpoint: u64,
    /// Killed tasks whose final attempt resumed from a checkpoint read back from the store
    /// (at least the newest one stored when the task was last killed).
    pub resumed_from_store: usize,
    /// Coordinator calls the workers retried through outages, by call (from their logs).
    pub retried_calls: BTreeMap<String, usize>,
    /// Long outages that no worker retried through (its stage had just ended) and that were
    /// therefore repeated.
    pub outages_missed: usize,
    pub wall_secs: f64,
    /// Objects in the artifact store at the end, by kind (`uploads`, `checkpoints`,
    /// `outputs`): where inputs, checkpoints and results went.
    pub stored_objects: BTreeMap<String, usize>,
    /// Every broken guarantee, described.
    pub violations: Vec<String>,
}

pub fn run(args: BenchChaosArgs) -> anyhow::Result<()> {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    let report = runtime.block_on(chaos(&args))?;
    println!("{}", serde_json::to_string_pretty(&report)?);
    anyhow::ensure!(
        report.violations.is_empty(),
        "{} guarantees broken",
        report.violations.len()
    );
    Ok(())
}

/// A child process of this binary, killed when dropped.
struct Process(Child);

impl Process {
    fn spawn(args: &[String], log: &Path) -> anyhow::Result<Process> {
        let stderr = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(log)?;
        let child = Command::new(std::env::current_exe()?)
            .args(args)
            .env_remove("STYLENERF_LOG")
            .stdout(Stdio::null())
            .stderr(stderr)
            .spawn()?;
        Ok(Process(child))
    }

    /// SIGKILL, and reap.
    fn kill(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

impl Drop for Process {
    fn drop(&mut self) {
        self.kill();
    }
}

/// The cluster's processes and how to restart them.
struct Cluster {
    dir: PathBuf,
    endpoint: String,
    coordinator_args: Vec<String>,
    coordinator: Process,
    workers: Vec<(String, Process)>,
    generation: usize,
}

impl Cluster {
    fn start(dir: &Path, storage: &str, workers: usize) -> anyhow::Result<Cluster> {
        let port = std::net::TcpListener::bind("127.0.0.1:0")?
            .local_addr()?
            .port();
        let endpoint = format!("http://127.0.0.1:{port}");
        let coordinator_args: Vec<String> = [
            "--log-format",
            "json",
            "coordinator",
            "--listen",
            &format!("127.0.0.1:{port}"),
            "--metrics-listen",
            "off",
            "--database",
            &dir.join("coordinator.db").display().to_string(),
            "--storage",
            storage,
            "--insecure-no-auth",
            "--lease-ttl",
            "3",
            "--heartbeat-interval",
            "0.3",
            "--max-lease-wait",
            "1",
            "--max-attempts",
            "1000",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        let coordinator = Process::spawn(&coordinator_args, &dir.join("coordinator.log"))?;
        let mut cluster = Cluster {
            dir: dir.to_path_buf(),
            endpoint,
            coordinator_args,
            coordinator,
            workers: Vec::new(),
            generation: 0,
        };
        for _ in 0..workers {
            cluster.spawn_worker()?;
        }
        Ok(cluster)
    }

    fn spawn_worker(&mut self) -> anyhow::Result<()> {
        self.generation += 1;
        let id = format!("w-chaos-{}", self.generation);
        let args: Vec<String> = [
            "--log-format",
            "json",
            "worker",
            "--endpoint",
            &self.endpoint,
            "--worker-id",
            &id,
            "--name",
            &id,
            "--checkpoint-every-steps",
            &CHECKPOINT_EVERY.to_string(),
            "--checkpoint-every-secs",
            "0",
            "--lease-wait-secs",
            "1",
            "--scratch-dir",
            &self.dir.join("scratch").display().to_string(),
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        let process = Process::spawn(&args, &self.dir.join(WORKERS_LOG))?;
        self.workers.push((id, process));
        Ok(())
    }

    fn restart_coordinator(&mut self) -> anyhow::Result<()> {
        self.coordinator =
            Process::spawn(&self.coordinator_args, &self.dir.join("coordinator.log"))?;
        Ok(())
    }
}

/// Makes the scene and style the jobs share.
fn inputs(dir: &Path) -> anyhow::Result<(PathBuf, PathBuf)> {
    let scene = dir.join("scene");
    generate(
        &GenerateOptions {
            size: 24,
            views: 6,
            ..Default::default()
        },
        &scene,
    )?;
    let style = dir.join("waves.png");
    let image =
        painted::paint("waves", 48).ok_or_else(|| anyhow::anyhow!("no painted style `waves`"))?;
    save_rgb_png(&style, 48, 48, image.as_raw())?;
    Ok((scene, style))
}

/// What a worker kill cost one task.
#[derive(Debug, Clone, Copy)]
struct Loss {
    /// The task's step at its last heartbeat.
    step: u64,
    /// Its newest checkpoint in the worker's scratch folder.
    local: u64,
    /// Its newest checkpoint in the store.
    stored: u64,
}

/// The newest checkpoint step among checkpoint file names (`step-N.json`).
fn newest_step(names: impl Iterator<Item = String>) -> u64 {
    names
        .filter_map(|name| {
            name.strip_prefix("step-")?
                .strip_suffix(".json")?
                .parse()
                .ok()
        })
        .max()
        .unwrap_or(0)
}

/// The newest checkpoint step in a local checkpoint folder.
fn newest_local_checkpoint(dir: &Path) -> u64 {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return 0;
    };
    newest_step(
        entries
            .flatten()
            .filter_map(|e| e.file_name().into_string().ok()),
    )
}

/// The newest checkpoint step a task has in the store (`<output prefix>ckpt/`).
async fn newest_stored_checkpoint(store: &Storage, output_prefix: &str) -> u64 {
    let objects = store
        .list(&format!("{output_prefix}ckpt/"))
        .await
        .unwrap_or_default();
    newest_step(
        objects
            .into_iter()
            .filter_map(|(key, _)| key.rsplit('/').next().map(str::to_string)),
    )
}

/// Objects in the store by kind: uploaded inputs, checkpoints, and everything else the jobs
/// wrote.
async fn stored_objects(store: &Storage) -> anyhow::Result<BTreeMap<String, usize>> {
    let mut kinds = BTreeMap::new();
    for (key, _) in store.list("").await? {
        let kind = if key.starts_with("uploads/") {
            "uploads"
        } else if key.contains("/ckpt/") {
            "checkpoints"
        } else {
            "outputs"
        };
        *kinds.entry(kind.to_string()).or_default() += 1;
    }
    Ok(kinds)
}

async fn chaos(args: &BenchChaosArgs) -> anyhow::Result<ChaosReport> {
    let temp = tempfile::tempdir()?;
    let dir = args
        .dir
        .clone()
        .unwrap_or_else(|| temp.path().to_path_buf());
    std::fs::create_dir_all(&dir)?;
    let (scene, style) = inputs(&dir)?;
    let started = Instant::now();
    let deadline = started + Duration::from_secs(args.timeout_secs);
    let storage = args
        .storage
        .clone()
        .unwrap_or_else(|| dir.join("store").display().to_string());
    let store = Storage::open(&storage)?;
    let mut cluster = Cluster::start(&dir, &storage, args.workers.max(1))?;
    let workers_log = dir.join(WORKERS_LOG);
    let mut rng = Rng::new(args.seed);
    let mut report = ChaosReport::default();
    let mut acknowledged: Vec<String> = Vec::new();
    // What each worker kill cost, per task.
    let mut losses: BTreeMap<u64, Vec<Loss>> = BTreeMap::new();
    let mut outage_done = false;
    let mut outage_waits = 0;
    let mut stored_kill_done = false;

    let spec = |i: usize| {
        let mut spec = JobSpec::new(Input::path(&scene), [Input::path(&style)]);
        spec.name = format!("chaos-{i}");
        spec.preset = Some("tiny".into());
        // A retried submission (no reply seen) must not make a second job.
        spec.idempotency_key = Some(format!("chaos-{}-{i}", args.seed));
        for (key, value) in [
            ("nerf_pretrain.steps", 40),
            ("decoder_pretrain.steps", 4),
            ("mutual_learning.steps", 8),
        ] {
            spec.overrides.insert(key.into(), value.into());
        }
        spec
    };

    let kills = args.kills;
    while report.worker_kills + report.coordinator_kills < kills || acknowledged.len() < args.jobs {
        anyhow::ensure!(Instant::now() < deadline, "timed out during the kills");
        // Without kills (`--kills 0`: a throughput run) every job is submitted at once.
        if kills > 0 {
            tokio::time::sleep(Duration::from_millis(300 + rng.below(1500) as u64)).await;
        }
        if acknowledged.len() < args.jobs {
            if let Ok(client) = Client::connect(&cluster.endpoint, None).await {
                if let Ok(submitted) = client.submit(&spec(acknowledged.len())).await {
                    acknowledged.push(submitted.job.id);
                }
            }
        }
        if report.worker_kills + report.coordinator_kills >= kills {
            continue;
        }
        // One kill is kept for this: as soon as a worker holds a task with a checkpoint in
        // the store, that worker, so that the resume from the store is exercised whatever the
        // timing of the random kills (given up only when no task is left to run).
        if !stored_kill_done {
            if let Some(victim) =
                worker_with_stored_checkpoint(&cluster, &acknowledged, &store).await
            {
                kill_worker(&mut cluster, victim, &acknowledged, &store, &mut losses).await?;
                report.worker_kills += 1;
                stored_kill_done = true;
                continue;
            }
            if acknowledged.len() == args.jobs && all_terminal(&cluster, &acknowledged).await {
                stored_kill_done = true;
            }
        }
        if report.worker_kills + report.coordinator_kills + usize::from(!stored_kill_done) >= kills
        {
            continue;
        }
        // Once, as soon as a stage runs, a long outage: the stage finishes (or checkpoints)
        // while the coordinator is away, and its worker retries until it is back.
        let outage = !outage_done && !acknowledged.is_empty();
        let mut retries_before = 0;
        if outage || rng.below(5) == 0 {
            if outage {
                // Busy: a live worker holds a task (a killed worker's task stays leased until
                // its lease expires, and nobody would retry for it).
                let busy = match Client::connect(&cluster.endpoint, None).await {
                    Ok(client) => cluster_busy(&client, &cluster, &acknowledged).await,
                    Err(_) => false,
                };
                // (When every job is done, nothing will be leased again: go ahead anyway.)
                outage_waits += 1;
                if !busy && outage_waits < 20 {
                    continue;
                }
                outage_done = true;
                retries_before = retried_calls(&workers_log).values().sum();
            }
            cluster.coordinator.kill();
            report.coordinator_kills += 1;
            let away = if outage {
                Duration::from_secs(8)
            } else {
                Duration::from_millis(rng.below(1000) as u64)
            };
            tokio::time::sleep(away).await;
            report.longest_outage_secs = report.longest_outage_secs.max(away.as_secs_f64());
            cluster.restart_coordinator()?;
            // The stage may have ended just before the kill: then nobody retried, and the
            // outage is tried again (twice at most) while kills are left.
            let retries_after: usize = retried_calls(&workers_log).values().sum();
            if outage && retries_after == retries_before && report.outages_missed < 2 {
                report.outages_missed += 1;
                outage_done = false;
                outage_waits = 0;
            }
        } else {
            let victim = rng.below(cluster.workers.len());
            kill_worker(&mut cluster, victim, &acknowledged, &store, &mut losses).await?;
            report.worker_kills += 1;
        }
    }

    let client = loop {
        anyhow::ensure!(
            Instant::now() < deadline,
            "the coordinator did not come back"
        );
        match Client::connect(&cluster.endpoint, None).await {
            Ok(client) if client.get(&acknowledged[0]).await.is_ok() => break client,
            _ => tokio::time::sleep(Duration::from_millis(200)).await,
        }
    };
    for id in &acknowledged {
        let job = loop {
            anyhow::ensure!(Instant::now() < deadline, "job {id} did not finish in time");
            match client.get(id).await {
                Ok(job) if is_terminal(&job) => break Some(job),
                Ok(_) => tokio::time::sleep(Duration::from_millis(500)).await,
                Err(e) if e.to_string().contains("not found") => break None,
                Err(_) => tokio::time::sleep(Duration::from_millis(500)).await,
            }
        };
        let Some(job) = job else {
            report
                .violations
                .push(format!("acknowledged job {id} is missing"));
            continue;
        };
        if job.state() == pb::JobState::Succeeded {
            report.jobs_succeeded += 1;
        } else {
            report
                .violations
                .push(format!("job {id} ended {:?}: {}", job.state(), job.error));
        }
        check_stages_once(&client, &job, &mut report).await?;
        check_losses(&job, &losses, &mut report);
    }
    report.jobs_acknowledged = acknowledged.len();
    report.kills_mid_stage = losses.values().map(Vec::len).sum();
    let all = || losses.values().flatten();
    report.most_steps_lost = all()
        .map(|l| l.step.saturating_sub(l.stored))
        .max()
        .unwrap_or(0);
    report.most_steps_since_local_checkpoint = all()
        .map(|l| l.step.saturating_sub(l.local))
        .max()
        .unwrap_or(0);
    report.retried_calls = retried_calls(&workers_log);
    report.stored_objects = stored_objects(&store).await?;
    report.wall_secs = started.elapsed().as_secs_f64();
    drop(cluster);
    Ok(report)
}

/// Stages that checkpoint (the render stages restart their frames instead).
const CHECKPOINTED: [pb::Stage; 3] = [
    pb::Stage::NerfPretrain,
    pb::Stage::DecoderPretrain,
    pb::Stage::MutualLearning,
];

/// SIGKILLs worker `victim` (an index into the cluster's workers) and starts a fresh one,
/// recording what the kill cost each checkpointed task it held: its step, and its newest
/// checkpoints locally and in the store just before it died.
async fn kill_worker(
    cluster: &mut Cluster,
    victim: usize,
    jobs: &[String],
    store: &Storage,
    losses: &mut BTreeMap<u64, Vec<Loss>>,
) -> anyhow::Result<()> {
    let (id, mut process) = cluster.workers.swap_remove(victim);
    let running = match Client::connect(&cluster.endpoint, None).await {
        Ok(client) => leased_by(&client, jobs, &id).await,
        Err(_) => Vec::new(),
    };
    process.kill();
    for task in running
        .into_iter()
        .filter(|t| CHECKPOINTED.contains(&t.stage()))
    {
        let local = cluster
            .dir
            .join("scratch")
            .join(&id)
            .join(format!("task-{}", task.id))
            .join("out/ckpt");
        losses.entry(task.id).or_default().push(Loss {
            step: task.progress.as_ref().map_or(0, |p| p.step),
            local: newest_local_checkpoint(&local),
            stored: newest_stored_checkpoint(store, &task.output_prefix).await,
        });
    }
    cluster.spawn_worker()
}

/// The index of a worker that holds a checkpointed task with a checkpoint in the store now.
async fn worker_with_stored_checkpoint(
    cluster: &Cluster,
    jobs: &[String],
    store: &Storage,
) -> Option<usize> {
    let client = Client::connect(&cluster.endpoint, None).await.ok()?;
    for (index, (id, _)) in cluster.workers.iter().enumerate() {
        for task in leased_by(&client, jobs, id).await {
            if CHECKPOINTED.contains(&task.stage())
                && newest_stored_checkpoint(store, &task.output_prefix).await > 0
            {
                return Some(index);
            }
        }
    }
    None
}

/// Whether every job of `jobs` has ended (false while the coordinator is away).
async fn all_terminal(cluster: &Cluster, jobs: &[String]) -> bool {
    let Ok(client) = Client::connect(&cluster.endpoint, None).await else {
        return false;
    };
    for job in jobs {
        match client.get(job).await {
            Ok(job) if is_terminal(&job) => {}
            _ => return false,
        }
    }
    true
}

fn is_terminal(job: &pb::Job) -> bool {
    matches!(
        job.state(),
        pb::JobState::Succeeded | pb::JobState::Failed | pb::JobState::Cancelled
    )
}

/// The tasks of `jobs` that worker `id` holds now.
async fn leased_by(client: &Client, jobs: &[String], id: &str) -> Vec<pb::Task> {
    let mut tasks = Vec::new();
    for job in jobs {
        if let Ok(job) = client.get(job).await {
            tasks.extend(
                job.tasks
                    .into_iter()
                    .filter(|t| t.state() == pb::TaskState::Leased && t.worker_id == id),
            );
        }
    }
    tasks
}

/// Each stage of the job succeeded exactly once, by its event log.
async fn check_stages_once(
    client: &Client,
    job: &pb::Job,
    report: &mut ChaosReport,
) -> anyhow::Result<()> {
    use futures::StreamExt;
    let mut events = client
        .watch(
            &job.id,
            WatchOptions {
                skip_progress: true,
                ..Default::default()
            },
        )
        .await?;
    let mut succeeded: BTreeMap<String, usize> = BTreeMap::new();
    while let Some(event) = events.next().await {
        let event = event?;
        if event.task_state() == pb::TaskState::Succeeded {
            *succeeded
                .entry(event.stage().as_str_name().to_string())
                .or_default() += 1;
        }
    }
    for task in &job.tasks {
        let stage = task.stage().as_str_name().to_string();
        let count = succeeded.get(&stage).copied().unwrap_or(0);
        if count != 1 {
            report.violations.push(format!(
                "job {}: stage {stage} succeeded {count} times",
                job.id
            ));
        }
    }
    Ok(())
}

/// Whether a live worker of `cluster` holds a task of `jobs` now.
async fn cluster_busy(client: &Client, cluster: &Cluster, jobs: &[String]) -> bool {
    for (id, _) in &cluster.workers {
        if !leased_by(client, jobs, id).await.is_empty() {
            return true;
        }
    }
    false
}

/// Retry warnings in the workers' JSON log, counted by call.
fn retried_calls(log: &Path) -> BTreeMap<String, usize> {
    let mut calls = BTreeMap::new();
    for line in std::fs::read_to_string(log).unwrap_or_default().lines() {
        let Ok(entry) = serde_json::from_str::<serde_json::Value>(line) else {
            continue;
        };
        let fields = &entry["fields"];
        if fields["message"] == "coordinator call failed; retrying" {
            let call = fields["call"].as_str().unwrap_or("");
            // `uploading jobs/<job>/…` and the like, by their verb.
            let name = call.split_whitespace().next().unwrap_or(call).to_string();
            *calls.entry(name).or_default() += 1;
        }
    }
    calls
}

/// A killed worker had run at most one checkpoint interval since its newest local checkpoint,
/// and the task's final attempt resumed from at least the newest checkpoint stored when it
/// was last killed.
fn check_losses(job: &pb::Job, losses: &BTreeMap<u64, Vec<Loss>>, report: &mut ChaosReport) {
    for task in &job.tasks {
        let Some(kills) = losses.get(&task.id) else {
            continue;
        };
        for loss in kills {
            if loss.step.saturating_sub(loss.local) > CHECKPOINT_EVERY {
                report.violations.push(format!(
                    "task {}: killed at step {} with no checkpoint after step {}",
                    task.id, loss.step, loss.local
                ));
            }
        }
        let resumed = task
            .progress
            .as_ref()
            .and_then(|p| p.metrics.get("resumed_from"))
            .copied();
        let last_checkpoint = kills.last().map_or(0, |l| l.stored);
        if let Some(resumed) = resumed.filter(|_| last_checkpoint > 0) {
            if (resumed as u64) >= last_checkpoint {
                report.resumed_from_store += 1;
            } else {
                report.violations.push(format!(
                    "task {} resumed from step {resumed} although step {last_checkpoint} was stored",
                    task.id
                ));
            }
        }
    }
}
