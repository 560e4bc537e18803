//! Lease expiry and requeue, fencing tokens against stale workers, running out of attempts,
//! retryable failures, and cancellation reaching a heartbeat.

use futures::StreamExt;
use std::time::Duration;
use stylenerf_server::proto::v1 as pb;
use stylenerf_testkit::*;

#[tokio::test]
async fn expired_lease_is_requeued_and_stale_worker_is_fenced_off() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = config(dir.path());
    config.lease_ttl = Duration::from_millis(300);
    config.max_attempts = 2;
    let server = start(config).await;
    let mut client = jobs_client(&server, Some(ALICE)).await;
    let job = create_job(&mut client).await;

    let mut stale = FakeWorker::register(&server, "cpu", 0).await;
    let mut fresh = FakeWorker::register(&server, "cpu", 0).await;
    let first = stale.lease(1000).await.unwrap();
    assert_eq!(first.attempt, 1);
    // No heartbeat: the reaper requeues the task, and a waiting worker gets it at once.
    let second = fresh.lease(3000).await.expect("requeued task leased again");
    assert_eq!(second.task_id, first.task_id);
    assert_eq!(second.attempt, 2);
    assert!(second.fencing_token > first.fencing_token);

    let heartbeat = stale.heartbeat(&first, 1).await.unwrap_err();
    assert_eq!(heartbeat.code(), tonic::Code::FailedPrecondition);
    let completion = stale.complete(&first).await.unwrap_err();
    assert_eq!(completion.code(), tonic::Code::FailedPrecondition);
    assert!(
        completion.message().contains("fencing token"),
        "{}",
        completion.message()
    );

    let task = get_job(&mut client, &job.id).await.tasks[0].clone();
    assert_eq!(task.state(), pb::TaskState::Leased);
    assert!(task.error.contains("expired"));

    // The second holder also goes silent: out of attempts, the job fails with the reason.
    tokio::time::sleep(Duration::from_millis(700)).await;
    let failed = get_job(&mut client, &job.id).await;
    assert_eq!(failed.state(), pb::JobState::Failed);
    assert!(
        failed.error.contains("nerf_pretrain failed"),
        "{}",
        failed.error
    );
    assert!(failed.error.contains("expired"), "{}", failed.error);
    assert!(failed.tasks[1..]
        .iter()
        .all(|t| t.state() == pb::TaskState::Cancelled));
    let late = fresh.heartbeat(&second, 2).await.unwrap_err();
    assert_eq!(late.code(), tonic::Code::FailedPrecondition);
    server.shutdown().await.unwrap();
}

#[tokio::test]
async fn heartbeats_keep_a_lease_and_retryable_failures_requeue() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = config(dir.path());
    config.lease_ttl = Duration::from_millis(400);
    let server = start(config).await;
    let mut client = jobs_client(&server, Some(ALICE)).await;
    let job = create_job(&mut client).await;
    let mut worker = FakeWorker::register(&server, "cpu", 0).await;
    let task = worker.lease(1000).await.unwrap();
    for step in 0..6 {
        tokio::time::sleep(Duration::from_millis(150)).await;
        worker
            .heartbeat(&task, step)
            .await
            .expect("lease still held");
    }
    let failed = worker
        .workers
        .fail_task(pb::FailTaskRequest {
            worker_id: worker.id.clone(),
            task_id: task.task_id,
            fencing_token: task.fencing_token,
            reason: "out of memory".into(),
            retryable: true,
        })
        .await
        .unwrap()
        .into_inner();
    assert!(failed.requeued);
    let again = worker.lease(1000).await.unwrap();
    assert_eq!((again.task_id, again.attempt), (task.task_id, 2));
    worker
        .workers
        .fail_task(pb::FailTaskRequest {
            worker_id: worker.id.clone(),
            task_id: again.task_id,
            fencing_token: again.fencing_token,
            reason: "scene has no valid frames".into(),
            retryable: false,
        })
        .await
        .unwrap();
    let job = get_job(&mut client, &job.id).await;
    assert_eq!(job.state(), pb::JobState::Failed);
    assert!(job.error.contains("scene has no valid frames"));
    server.shutdown().await.unwrap();
}

#[tokio::test]
async fn cancellation_reaches_the_heartbeat() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(config(dir.path())).await;
    let mut client = jobs_client(&server, Some(ALICE)).await;
    let job = create_job(&mut client).await;
    let mut worker = FakeWorker::register(&server, "cpu", 0).await;
    let task = worker.lease(1000).await.unwrap();
    assert!(!worker.heartbeat(&task, 1).await.unwrap().cancel);
    let watch = watch(&mut client, &job.id, 0, true).await;

    let cancelled = client
        .cancel_job(pb::CancelJobRequest {
            job_id: job.id.clone(),
            reason: "changed my mind".into(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(cancelled.state(), pb::JobState::Cancelled);
    assert!(cancelled.error.contains("changed my mind"));
    assert!(worker.heartbeat(&task, 2).await.unwrap().cancel);
    // A cancelled task's worker may no longer store objects for it; completing it is a
    // harmless no-op; nothing else is handed out.
    let key = format!("{}late.bin", task.output_prefix);
    let late = worker
        .artifacts
        .put_object(tokio_stream::iter([pb::PutObjectChunk {
            part: Some(pb::put_object_chunk::Part::Header(pb::PutObjectHeader {
                key,
                size: 0,
                sha256: sha256(b""),
            })),
        }]))
        .await
        .unwrap_err();
    assert_eq!(late.code(), tonic::Code::PermissionDenied, "{late:?}");
    worker
        .workers
        .complete_task(pb::CompleteTaskRequest {
            worker_id: worker.id.clone(),
            task_id: task.task_id,
            fencing_token: task.fencing_token,
            ..Default::default()
        })
        .await
        .unwrap();
    assert!(worker.lease(200).await.is_none());
    let job = get_job(&mut client, &job.id).await;
    assert_eq!(job.state(), pb::JobState::Cancelled);
    assert!(job
        .tasks
        .iter()
        .all(|t| t.state() == pb::TaskState::Cancelled));

    let events: Vec<pb::Event> = watch.map(|e| e.unwrap()).collect().await;
    assert_eq!(events.last().unwrap().job_state(), pb::JobState::Cancelled);
    server.shutdown().await.unwrap();
}

/// Completions arriving together are committed together (group commit); one that must be
/// rolled back (an output outside its prefix) fails alone and the others still commit.
#[tokio::test]
async fn a_rejected_completion_does_not_take_its_group_down() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(config(dir.path())).await;
    let mut client = jobs_client(&server, Some(ALICE)).await;
    let mut leased = Vec::new();
    for _ in 0..6 {
        create_job(&mut client).await;
        let mut worker = FakeWorker::register(&server, "cpu", 0).await;
        let task = worker.lease(5000).await.expect("a task is ready");
        leased.push((worker, task));
    }
    let calls = leased
        .into_iter()
        .enumerate()
        .map(|(i, (mut worker, task))| async move {
            let key = if i == 3 {
                "jobs/elsewhere/out.bin".to_string()
            } else {
                format!("{}out.bin", task.output_prefix)
            };
            let reply = worker
                .workers
                .complete_task(pb::CompleteTaskRequest {
                    worker_id: worker.id.clone(),
                    task_id: task.task_id,
                    fencing_token: task.fencing_token,
                    outputs: vec![pb::Artifact {
                        key,
                        size: 1,
                        sha256: "0".repeat(64),
                    }],
                    metrics: Default::default(),
                })
                .await;
            (task, reply)
        });
    let results = futures::future::join_all(calls).await;
    for (i, (task, reply)) in results.iter().enumerate() {
        let job = get_job(&mut client, &task.job_id).await;
        if i == 3 {
            let status = reply.as_ref().unwrap_err();
            assert_eq!(status.code(), tonic::Code::InvalidArgument);
            assert_eq!(bad_fields(status), ["outputs[0].key"]);
            assert_eq!(job.tasks[0].state(), pb::TaskState::Leased, "rolled back");
            assert!(job.tasks[0].outputs.is_empty());
        } else {
            assert!(reply.is_ok(), "task {i}: {reply:?}");
            assert_eq!(job.tasks[0].state(), pb::TaskState::Succeeded);
            assert_eq!(job.tasks[0].outputs.len(), 1);
            assert_eq!(
                job.tasks[1].state(),
                pb::TaskState::Ready,
                "dependent promoted"
            );
        }
    }
    server.shutdown().await.unwrap();
}
