//! End-to-end tests of the whole service: an embedded coordinator (real SQLite file and
//! artifact folder, real gRPC on loopback) with workers running as separate processes of the
//! built `stylenerf` binary, driven through the client library, on a tiny generated scene
//! with the `tiny` preset.
//!
//! - a job with two worker processes completes and its artifacts download;
//! - a worker killed with SIGKILL in the middle of a stage: the other worker takes the task
//!   after the lease expires and resumes from the uploaded checkpoint;
//! - the coordinator restarts in the middle of a job (same database, same port);
//! - a cancelled job stops its worker within seconds.
//!
//! The tests run one at a time (they share two CPU cores in CI) and wait on conditions with
//! deadlines rather than fixed sleeps.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::json;
use stylenerf_client::{pb, Client, Input, JobSpec, WatchOptions};
use stylenerf_engine::image_io::save_rgb_png;
use stylenerf_engine::style2d::painted;
use stylenerf_server::{Coordinator, CoordinatorConfig, CoordinatorHandle};
use stylenerf_testkit::{eventually, tiny_scene, Source};

/// One test at a time: each runs training processes.
static SERIAL: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

/// Generous bound for a whole tiny job on a loaded 2-core machine.
const JOB_TIMEOUT: Duration = Duration::from_secs(240);

/// A worker process; killed when dropped.
struct WorkerProcess {
    id: String,
    child: Child,
    log: PathBuf,
}

impl WorkerProcess {
    /// Starts `stylenerf worker` against `endpoint`: checkpoints every 10 steps, JSON logs in
    /// `dir/<id>.log`.
    fn spawn(endpoint: &str, dir: &Path, id: &str) -> Self {
        let log = dir.join(format!("{id}.log"));
        let stderr = std::fs::File::create(&log).expect("worker log file");
        let child = Command::new(env!("CARGO_BIN_EXE_stylenerf"))
            .args(["--log", "info", "--log-format", "json", "worker"])
            .args(["--endpoint", endpoint, "--worker-id", id, "--name", id])
            .args([
                "--checkpoint-every-steps",
                "10",
                "--checkpoint-every-secs",
                "0",
            ])
            .args(["--lease-wait-secs", "1", "--scratch-dir"])
            .arg(dir.join("scratch").join(id))
            .env_remove("STYLENERF_LOG")
            .stdout(Stdio::null())
            .stderr(stderr)
            .spawn()
            .expect("worker process starts");
        WorkerProcess {
            id: id.to_string(),
            child,
            log,
        }
    }

    fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }
}

impl Drop for WorkerProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A coordinator with short leases and fast heartbeats, its data folder, a scene and a style.
struct Cluster {
    dir: tempfile::TempDir,
    config: CoordinatorConfig,
    coordinator: Option<CoordinatorHandle>,
    endpoint: String,
    workers: Vec<WorkerProcess>,
}

impl Cluster {
    async fn start(workers: usize) -> Self {
        let dir = tempfile::tempdir().unwrap();
        let mut config = CoordinatorConfig::local(&dir.path().join("coordinator"));
        config.lease_ttl = Duration::from_secs(3);
        config.heartbeat_interval = Duration::from_millis(300);
        config.reaper_interval = Duration::from_millis(100);
        config.max_lease_wait = Duration::from_secs(1);
        config.progress_event_interval = Duration::ZERO;
        let coordinator = Coordinator::start(config.clone()).await.unwrap();
        // A restart binds the same port.
        config.listen = coordinator.local_addr();
        let endpoint = coordinator.endpoint();
        let workers = (0..workers)
            .map(|i| WorkerProcess::spawn(&endpoint, dir.path(), &format!("w-e2e-{i}")))
            .collect();
        Cluster {
            dir,
            config,
            coordinator: Some(coordinator),
            endpoint,
            workers,
        }
    }

    async fn client(&self) -> Client {
        Client::connect(&self.endpoint, None).await.unwrap()
    }

    /// Submits a `tiny` job on a 32×32, 8-view scene with one painted style.
    async fn submit(&self, overrides: serde_json::Value) -> String {
        let scene = self.dir.path().join("scene");
        tiny_scene(&scene);
        let style = self.dir.path().join("waves.png");
        let image = painted::paint("waves", 64).unwrap();
        save_rgb_png(&style, 64, 64, image.as_raw()).unwrap();
        let mut spec = JobSpec::new(Input::path(&scene), [Input::path(&style)]);
        spec.preset = Some("tiny".into());
        spec.overrides = overrides.as_object().cloned().unwrap_or_default();
        self.client().await.submit(&spec).await.unwrap().job.id
    }

    fn worker(&mut self, id: &str) -> &mut WorkerProcess {
        self.workers.iter_mut().find(|w| w.id == id).unwrap()
    }

    async fn shutdown(mut self) {
        self.workers.clear();
        if let Some(coordinator) = self.coordinator.take() {
            coordinator.shutdown().await.unwrap();
        }
    }
}

/// The job (errors, e.g. while the coordinator restarts, count as "not yet").
async fn job(client: &Client, id: &str) -> Option<pb::Job> {
    client.get(id).await.ok()
}

/// Waits until the job is terminal and returns it.
async fn finished(client: &Client, id: &str) -> pb::Job {
    eventually("job ends", JOB_TIMEOUT, || async {
        job(client, id).await.filter(|j| {
            matches!(
                pb::JobState::try_from(j.state),
                Ok(pb::JobState::Succeeded | pb::JobState::Failed | pb::JobState::Cancelled)
            )
        })
    })
    .await
}

fn assert_succeeded(job: &pb::Job) {
    assert_eq!(
        job.state,
        pb::JobState::Succeeded as i32,
        "job {} ended {:?}: {}",
        job.id,
        pb::JobState::try_from(job.state),
        job.error
    );
}

/// Waits until the first stage is leased and has reported at least `steps` steps (with a
/// checkpoint in the store when `checkpoint`); returns the task.
async fn running_first_stage(client: &Client, id: &str, steps: u64, checkpoint: bool) -> pb::Task {
    eventually("first stage running", JOB_TIMEOUT, || async {
        let task = job(client, id).await?.tasks.into_iter().next()?;
        let step = task.progress.as_ref().map_or(0, |p| p.step);
        if task.state != pb::TaskState::Leased as i32 || step < steps {
            return None;
        }
        if checkpoint {
            let ckpts = client.artifacts(id, "nerf_pretrain/ckpt/").await.ok()?;
            if !ckpts.iter().any(|a| a.key.ends_with(".json")) {
                return None;
            }
        }
        Some(task)
    })
    .await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_through_two_worker_processes_completes_and_downloads() {
    let _serial = SERIAL.lock().await;
    let cluster = Cluster::start(2).await;
    let id = cluster.submit(json!({})).await;
    let client = cluster.client().await;
    let done = tokio::time::timeout(JOB_TIMEOUT, client.wait(&id))
        .await
        .expect("the job ends in time")
        .unwrap();
    assert_succeeded(&done);
    assert_eq!(done.tasks.len(), Source::Dataset.stages().len());
    assert!(done.tasks.iter().all(|t| t.worker_id.starts_with("w-e2e-")));

    let out = cluster.dir.path().join("out");
    let files = client.download(&id, &out).await.unwrap();
    assert!(files.iter().all(|f| f.path.starts_with(&out) && f.size > 0));
    let stylized = out.join("render_stylized");
    let spec = std::fs::read_dir(&stylized)
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.is_dir())
        .expect("a stylized render folder");
    for file in ["animation.gif", "sheet.png"] {
        assert!(spec.join(file).is_file(), "{file} missing in {spec:?}");
    }
    assert!(std::fs::read_dir(spec.join("frames")).unwrap().count() > 0);
    assert!(stylized.join("eval.md").is_file());
    assert!(out.join("nerf_pretrain/field.safetensors").is_file());
    // Checkpoints stay on the server unless asked for.
    assert!(files.iter().all(|f| !f.key.contains("/ckpt/")));
    cluster.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_killed_worker_s_task_resumes_from_its_checkpoint_on_the_other_worker() {
    let _serial = SERIAL.lock().await;
    let mut cluster = Cluster::start(2).await;
    let id = cluster.submit(json!({"nerf_pretrain.steps": 400})).await;
    let client = cluster.client().await;
    let task = running_first_stage(&client, &id, 30, true).await;
    let victim = task.worker_id.clone();
    let killed = cluster.worker(&victim);
    killed.child.kill().unwrap(); // SIGKILL: no checkpoint, no release.
    killed.child.wait().unwrap();

    // The lease expires, the other worker takes the task and resumes from the checkpoint.
    let retaken = eventually("task leased again", JOB_TIMEOUT, || async {
        let task = job(&client, &id).await?.tasks.into_iter().next()?;
        (task.attempt >= 2 && task.worker_id != victim).then_some(task)
    })
    .await;
    assert!(
        !retaken.error.is_empty(),
        "the lost lease is recorded: {retaken:?}"
    );
    let done = finished(&client, &id).await;
    assert_succeeded(&done);
    let resumed_from = resumed_from(&client, &id).await;
    assert!(resumed_from > 0, "resumed from step {resumed_from}");
    assert_eq!(done.tasks[0].attempt, 2);
    cluster.shutdown().await;
}

/// The step the first stage resumed from after the kill, from its progress events
/// (`step 40/400, resumed from step 30`).
async fn resumed_from(client: &Client, id: &str) -> u64 {
    use futures::StreamExt;
    let mut events = client.watch(id, WatchOptions::default()).await.unwrap();
    let mut step = 0;
    while let Some(event) = events.next().await {
        let event = event.unwrap();
        if event.stage != pb::Stage::NerfPretrain as i32 {
            continue;
        }
        let message = event.progress.map(|p| p.message).unwrap_or_default();
        if let Some((_, rest)) = message.split_once("resumed from step ") {
            let digits: String = rest.chars().take_while(char::is_ascii_digit).collect();
            step = step.max(digits.parse().unwrap_or(0));
        }
    }
    step
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_completes_across_a_coordinator_restart() {
    let _serial = SERIAL.lock().await;
    let mut cluster = Cluster::start(2).await;
    let id = cluster.submit(json!({"nerf_pretrain.steps": 200})).await;
    let client = cluster.client().await;
    running_first_stage(&client, &id, 10, false).await;

    cluster
        .coordinator
        .take()
        .unwrap()
        .shutdown()
        .await
        .unwrap();
    let restarted = Coordinator::start(cluster.config.clone()).await.unwrap();
    assert_eq!(restarted.endpoint(), cluster.endpoint);
    cluster.coordinator = Some(restarted);

    let client = cluster.client().await;
    let done = finished(&client, &id).await;
    assert_succeeded(&done);
    assert!(!client
        .artifacts(&id, "render_stylized/")
        .await
        .unwrap()
        .is_empty());
    cluster.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cancelling_a_running_job_stops_its_worker_within_seconds() {
    let _serial = SERIAL.lock().await;
    let mut cluster = Cluster::start(2).await;
    let id = cluster
        .submit(json!({"nerf_pretrain.steps": 1_000_000}))
        .await;
    let client = cluster.client().await;
    let task = running_first_stage(&client, &id, 5, false).await;

    let cancelled = client.cancel(&id, "e2e test").await.unwrap();
    let at = Instant::now();
    assert_eq!(cancelled.state, pb::JobState::Cancelled as i32);
    let worker = cluster.worker(&task.worker_id);
    eventually(
        "the worker stops the stage",
        Duration::from_secs(30),
        || async {
            worker
                .log_text()
                .contains("\"result\":\"Cancelled\"")
                .then_some(())
        },
    )
    .await;
    assert!(
        at.elapsed() < Duration::from_secs(10),
        "the worker stopped {:?} after the cancel",
        at.elapsed()
    );
    let done = finished(&client, &id).await;
    assert_eq!(done.state, pb::JobState::Cancelled as i32);
    assert!(done
        .tasks
        .iter()
        .all(|t| t.state != pb::TaskState::Leased as i32));
    cluster.shutdown().await;
}
