//! The worker against an embedded coordinator on loopback (real SQLite file, token auth): the
//! stages of a tiny job, resuming from a checkpoint after a shutdown, cancellation
//! through the heartbeat, non-retryable user errors, and the memory budget.

mod support;

use std::time::{Duration, Instant};

use stylenerf_server::proto::v1 as pb;
use stylenerf_worker::{TaskResult, Worker, WorkerEvent};
use support::*;

fn finished(event: &WorkerEvent) -> Option<(pb::Stage, TaskResult)> {
    match event {
        WorkerEvent::TaskFinished { stage, result, .. } => Some((*stage, result.clone())),
        _ => None,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn runs_every_stage_and_stores_its_artifacts() {
    let dir = tempfile::tempdir().unwrap();
    let coordinator = coordinator(dir.path()).await;
    let job = submit(&coordinator, dir.path(), serde_json::json!({}), 0).await;
    let mut worker = spawn_worker(worker_config(&coordinator, dir.path())).await;
    for expected in stylenerf_testkit::Source::Dataset
        .stages()
        .into_iter()
        .map(pb::Stage::from)
    {
        let (stage, result) = worker.wait_for(Duration::from_secs(180), finished).await;
        assert_eq!(stage, expected);
        let TaskResult::Completed { outputs, metrics } = result else {
            panic!("{stage:?} did not complete: {result:?}");
        };
        assert_eq!(
            outputs.last().unwrap().key,
            format!("jobs/{job}/{}/manifest.json", stage_dir(stage))
        );
        if stage == pb::Stage::NerfPretrain {
            assert!(metrics["test_psnr"] > 10.0, "{metrics:?}");
        }
    }
    let summary = worker.stop().await;
    assert_eq!((summary.completed, summary.failed), (5, 0));

    let job = get_job(&coordinator, &job).await;
    assert_eq!(job.state, pb::JobState::Succeeded as i32, "{}", job.error);
    let keys = list(&coordinator, &format!("jobs/{}/", job.id)).await;
    for file in [
        "nerf_pretrain/field.safetensors",
        "nerf_pretrain/field.json",
        "nerf_pretrain/metrics.json",
        "render_views/cameras.json",
        "decoder_pretrain/decoder.safetensors",
        "decoder_pretrain/adain_decoder.safetensors",
        "decoder_pretrain/vae.safetensors",
        "decoder_pretrain/styles.json",
        "decoder_pretrain/manifest.json",
        "mutual_learning/style_module.safetensors",
        "mutual_learning/latents.safetensors",
        "render_stylized/eval.md",
        "render_stylized/style-0/animation.gif",
        "render_stylized/style-0/sheet.png",
    ] {
        let key = format!("jobs/{}/{file}", job.id);
        assert!(keys.contains(&key), "{key} missing from {keys:#?}");
    }
    for task in &job.tasks {
        assert_eq!(task.state, pb::TaskState::Succeeded as i32);
        assert!(task.outputs.iter().all(|o| !o.key.contains("/ckpt/")));
    }
    coordinator.shutdown().await.unwrap();
}

fn stage_dir(stage: pb::Stage) -> &'static str {
    stylenerf_worker::stages::stage_name(stage as i32)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_second_worker_resumes_from_the_first_ones_checkpoint() {
    let dir = tempfile::tempdir().unwrap();
    let coordinator = coordinator(dir.path()).await;
    let overrides = serde_json::json!({"nerf_pretrain": {"steps": 600}});
    let job = submit(&coordinator, dir.path(), overrides, 0).await;
    let first = spawn_worker(worker_config(&coordinator, dir.path())).await;
    let ckpt = format!("jobs/{job}/nerf_pretrain/ckpt/");
    eventually("a checkpoint stored", Duration::from_secs(60), || async {
        let keys = list(&coordinator, &ckpt).await;
        keys.iter().any(|k| k.ends_with(".json")).then_some(())
    })
    .await;
    let summary = first.stop().await;
    assert_eq!(summary.released, 1, "{summary:?}");
    let task = &get_job(&coordinator, &job).await.tasks[0];
    assert_eq!(task.state, pb::TaskState::Ready as i32);
    assert!(
        task.error.contains("worker shutting down"),
        "{}",
        task.error
    );

    let mut second = spawn_worker(worker_config(&coordinator, dir.path())).await;
    let (attempt, resumed_from) = second
        .wait_for(Duration::from_secs(30), |e| match e {
            WorkerEvent::TaskStarted {
                attempt,
                resumed_from,
                ..
            } => Some((*attempt, *resumed_from)),
            _ => None,
        })
        .await;
    assert_eq!(attempt, 2);
    assert!(resumed_from >= 10, "resumed from step {resumed_from}");
    // The progress the coordinator sees says so too.
    eventually("the resume reported", Duration::from_secs(30), || async {
        let job = get_job(&coordinator, &job).await;
        let progress = job.tasks[0].progress.clone().unwrap_or_default();
        progress
            .message
            .contains(&format!("resumed from step {resumed_from}"))
            .then_some(())
    })
    .await;
    let (stage, result) = second.wait_for(Duration::from_secs(120), finished).await;
    assert_eq!(stage, pb::Stage::NerfPretrain);
    let TaskResult::Completed { metrics, .. } = result else {
        panic!("not completed: {result:?}");
    };
    assert_eq!(metrics["resumed_from"], resumed_from as f64);
    assert_eq!(metrics["steps"], 600.0);
    second.stop().await;
    coordinator.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_truncated_newest_checkpoint_costs_one_interval_not_the_job() {
    let dir = tempfile::tempdir().unwrap();
    let coordinator = coordinator(dir.path()).await;
    let overrides = serde_json::json!({"nerf_pretrain": {"steps": 600}});
    let job = submit(&coordinator, dir.path(), overrides, 0).await;
    let first = spawn_worker(worker_config(&coordinator, dir.path())).await;
    let ckpt = format!("jobs/{job}/nerf_pretrain/ckpt/");
    let step_of = |key: &str| -> Option<u64> {
        key.rsplit('/')
            .next()?
            .strip_prefix("step-")?
            .strip_suffix(".json")?
            .parse()
            .ok()
    };
    eventually("checkpoints stored", Duration::from_secs(60), || async {
        let steps = list(&coordinator, &ckpt)
            .await
            .iter()
            .filter_map(|k| step_of(k))
            .count();
        (steps >= 2).then_some(())
    })
    .await;
    first.stop().await;
    let mut steps: Vec<u64> = list(&coordinator, &ckpt)
        .await
        .iter()
        .filter_map(|k| step_of(k))
        .collect();
    steps.sort_unstable();
    let (older, newest) = (steps[steps.len() - 2], steps[steps.len() - 1]);
    // The store loses the end of the newest checkpoint's tensors (a torn copy, a bad disk).
    let weights = dir
        .path()
        .join("artifacts")
        .join(format!("{ckpt}step-{newest:08}.safetensors"));
    let bytes = std::fs::read(&weights).unwrap();
    std::fs::write(&weights, &bytes[..bytes.len() / 3]).unwrap();

    let mut second = spawn_worker(worker_config(&coordinator, dir.path())).await;
    let resumed_from = second
        .wait_for(Duration::from_secs(30), |e| match e {
            WorkerEvent::TaskStarted { resumed_from, .. } => Some(*resumed_from),
            _ => None,
        })
        .await;
    assert_eq!(resumed_from, older, "checkpoints {steps:?}");
    let (_, result) = second.wait_for(Duration::from_secs(120), finished).await;
    assert!(matches!(result, TaskResult::Completed { .. }), "{result:?}");
    second.stop().await;
    coordinator.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_worker_started_before_its_coordinator_waits_for_it() {
    let dir = tempfile::tempdir().unwrap();
    let listen = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap();
    let endpoint = format!("http://{listen}");
    let registering = tokio::spawn(Worker::register(worker_config_for(&endpoint, dir.path())));
    tokio::time::sleep(Duration::from_millis(1500)).await;
    assert!(
        !registering.is_finished(),
        "the worker waits instead of exiting"
    );
    let coordinator = coordinator_on(dir.path(), listen).await;
    let worker = tokio::time::timeout(Duration::from_secs(30), registering)
        .await
        .expect("registers once the coordinator is up")
        .unwrap()
        .expect("registers");
    assert!(worker.id().starts_with("w-"), "{}", worker.id());
    drop(worker);
    coordinator.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cancelling_the_job_stops_the_stage_within_seconds() {
    let dir = tempfile::tempdir().unwrap();
    let coordinator = coordinator(dir.path()).await;
    let overrides = serde_json::json!({"nerf_pretrain.steps": 1_000_000});
    let job = submit(&coordinator, dir.path(), overrides, 0).await;
    let mut worker = spawn_worker(worker_config(&coordinator, dir.path())).await;
    worker
        .wait_for(Duration::from_secs(30), |e| {
            matches!(e, WorkerEvent::TaskStarted { .. }).then_some(())
        })
        .await;
    tokio::time::sleep(Duration::from_millis(500)).await;
    jobs(&coordinator)
        .await
        .cancel_job(pb::CancelJobRequest {
            job_id: job.clone(),
            reason: "test".into(),
        })
        .await
        .unwrap();
    let cancelled_at = Instant::now();
    let (_, result) = worker.wait_for(Duration::from_secs(30), finished).await;
    assert_eq!(result, TaskResult::Cancelled);
    assert!(
        cancelled_at.elapsed() < Duration::from_secs(5),
        "stopped after {:?}",
        cancelled_at.elapsed()
    );
    let summary = worker.stop().await;
    assert_eq!(summary.cancelled, 1);
    coordinator.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bad_override_fails_the_job_at_once_naming_the_key() {
    let dir = tempfile::tempdir().unwrap();
    let coordinator = coordinator(dir.path()).await;
    let overrides = serde_json::json!({"nerf_pretrain": {"stepz": 5}});
    let job = submit(&coordinator, dir.path(), overrides, 0).await;
    let mut worker = spawn_worker(worker_config(&coordinator, dir.path())).await;
    let (_, result) = worker.wait_for(Duration::from_secs(30), finished).await;
    let TaskResult::Failed { reason, retryable } = result else {
        panic!("{result:?}");
    };
    assert!(!retryable);
    assert!(
        reason.contains("stepz") && reason.contains("no such setting"),
        "{reason}"
    );
    worker.stop().await;
    let job = get_job(&coordinator, &job).await;
    assert_eq!(job.state, pb::JobState::Failed as i32);
    assert_eq!(job.tasks[0].attempt, 1);
    coordinator.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_worker_does_not_take_a_task_larger_than_its_memory_budget() {
    let dir = tempfile::tempdir().unwrap();
    let coordinator = coordinator(dir.path()).await;
    let job = submit(&coordinator, dir.path(), serde_json::json!({}), 1 << 30).await;
    let mut config = worker_config(&coordinator, dir.path());
    config.memory_bytes = 256 << 20;
    let mut small = spawn_worker(config).await;
    let waited = tokio::time::timeout(Duration::from_secs(3), small.events.recv()).await;
    assert!(
        waited.is_err(),
        "the small worker did something: {waited:?}"
    );
    let task = &get_job(&coordinator, &job).await.tasks[0];
    assert_eq!(task.state, pb::TaskState::Ready as i32);
    assert_eq!(task.attempt, 0);
    assert_eq!(small.stop().await, Default::default());

    // A worker whose budget fits takes it.
    let mut config = worker_config(&coordinator, dir.path());
    config.memory_bytes = 2 << 30;
    let mut big = spawn_worker(config).await;
    big.wait_for(Duration::from_secs(10), |e| {
        matches!(e, WorkerEvent::TaskStarted { .. }).then_some(())
    })
    .await;
    big.stop().await;
    coordinator.shutdown().await.unwrap();
}
