//! A coordinator restarted on the same SQLite file and store mid-job loses nothing: the job,
//! its finished stages, a live lease (the worker's token still works) and the event log.

use futures::StreamExt;
use stylenerf_server::proto::v1 as pb;
use stylenerf_testkit::*;

#[tokio::test]
async fn restart_mid_job_loses_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(config(dir.path())).await;
    let mut client = jobs_client(&server, Some(ALICE)).await;
    let job = create_job(&mut client).await;
    let mut worker = FakeWorker::register(&server, "cpu", 0).await;
    worker.run_one().await;
    let held = worker.lease(1000).await.unwrap();
    assert_eq!(held.stage(), pb::Stage::RenderViews);
    worker.heartbeat(&held, 3).await.unwrap();
    let worker_id = worker.id.clone();
    server.shutdown().await.unwrap();

    // A new coordinator on the same files (on another port).
    let server = start(config(dir.path())).await;
    let mut client = jobs_client(&server, Some(ALICE)).await;
    let before = get_job(&mut client, &job.id).await;
    assert_eq!(before.state(), pb::JobState::Running);
    assert_eq!(before.tasks[0].state(), pb::TaskState::Succeeded);
    assert_eq!(before.tasks[1].state(), pb::TaskState::Leased);
    assert_eq!(before.tasks[1].progress.as_ref().unwrap().step, 3);

    let mut worker = FakeWorker::register(&server, "cpu", 0).await;
    worker.id = worker_id;
    worker
        .heartbeat(&held, 4)
        .await
        .expect("the lease survived");
    worker
        .complete(&held)
        .await
        .expect("completes across the restart");
    for _ in 0..3 {
        worker.run_one().await;
    }
    assert_eq!(
        get_job(&mut client, &job.id).await.state(),
        pb::JobState::Succeeded
    );

    let events: Vec<pb::Event> = watch(&mut client, &job.id, 0, true)
        .await
        .map(|e| e.unwrap())
        .collect()
        .await;
    let succeeded = events
        .iter()
        .filter(|e| e.task_state() == pb::TaskState::Succeeded)
        .count();
    assert_eq!(succeeded, 5, "every stage's completion is in the log");
    server.shutdown().await.unwrap();
}

#[tokio::test]
async fn health_reports_not_serving_while_draining() {
    use tonic_health::pb::health_check_response::ServingStatus;
    use tonic_health::pb::health_client::HealthClient;
    use tonic_health::pb::HealthCheckRequest;

    let dir = tempfile::tempdir().unwrap();
    let mut config = config(dir.path());
    config.drain_grace = std::time::Duration::from_secs(2);
    let server = start(config).await;
    let mut health = HealthClient::new(channel(&server).await);
    let status = |service: &str| HealthCheckRequest {
        service: service.into(),
    };
    let check =
        |reply: tonic::Response<tonic_health::pb::HealthCheckResponse>| reply.into_inner().status();
    assert_eq!(
        check(health.check(status("")).await.unwrap()),
        ServingStatus::Serving
    );
    let stopping = tokio::spawn(server.shutdown());
    tokio::time::sleep(std::time::Duration::from_millis(500)).await;
    for service in ["", "stylenerf.v1.JobService", "stylenerf.v1.WorkerService"] {
        let reply = health
            .check(status(service))
            .await
            .expect("still answering");
        assert_eq!(check(reply), ServingStatus::NotServing, "{service:?}");
    }
    assert!(!stopping.is_finished(), "calls are served during the grace");
    stopping.await.unwrap().unwrap();
}

/// Snapshots in the store (`backups/coordinator-*.db`), by name, oldest first. The local
/// store stages an upload under another name beside it, which is not a snapshot yet.
fn backups(store: &std::path::Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(store.join("backups"))
        .map(|entries| {
            entries
                .flatten()
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .filter(|name| name.starts_with("coordinator-") && name.ends_with(".db"))
                .collect()
        })
        .unwrap_or_default();
    names.sort();
    names
}

/// Waits (up to a minute) until the store's snapshots satisfy `done`.
async fn wait_for_backups(
    store: &std::path::Path,
    done: impl Fn(&[String]) -> bool,
) -> Vec<String> {
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
    loop {
        let names = backups(store);
        if done(&names) {
            return names;
        }
        assert!(std::time::Instant::now() < deadline, "snapshots: {names:?}");
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
}

#[tokio::test]
async fn a_lost_database_is_restored_from_the_store() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("artifacts");
    let mut first = config(dir.path());
    first.backup_interval = Some(std::time::Duration::from_millis(50));
    first.backups_kept = 2;
    let server = start(first.clone()).await;
    let mut client = jobs_client(&server, Some(ALICE)).await;
    let job = create_job(&mut client).await;
    // Periodic snapshots while serving (waited for, not timed: a loaded machine is slow)...
    let first_two = wait_for_backups(&store, |names| names.len() >= 2).await;
    wait_for_backups(&store, |names| names.iter().any(|n| !first_two.contains(n))).await;
    server.shutdown().await.unwrap();
    // ... pruned to the newest two: a later periodic one and the one taken at shutdown.
    let kept = backups(&store);
    assert_eq!(kept.len(), 2, "{kept:?}");
    assert!(
        kept.iter().all(|n| !first_two.contains(n)),
        "{first_two:?} pruned: {kept:?}"
    );

    // The machine is gone with its volume: a new coordinator, a new (empty) database path,
    // the same store.
    let mut second = config(&dir.path().join("elsewhere"));
    second.storage_url = first.storage_url.clone();
    second.restore_from_backup = true;
    assert!(!second.database.exists());
    let server = start(second.clone()).await;
    let mut client = jobs_client(&server, Some(ALICE)).await;
    let restored = get_job(&mut client, &job.id).await;
    assert_eq!(restored.state(), pb::JobState::Queued);
    let mut worker = FakeWorker::register(&server, "cpu", 0).await;
    let task = worker.lease(1000).await.expect("its first stage is leased");
    assert_eq!(task.job_id, job.id);
    let newer = create_job(&mut client).await;
    server.shutdown().await.unwrap();

    // With the database present, the flag changes nothing: the newer job is still there.
    let server = start(second).await;
    let mut client = jobs_client(&server, Some(ALICE)).await;
    assert_eq!(get_job(&mut client, &newer.id).await.id, newer.id);
    server.shutdown().await.unwrap();
}
