//! Deleting user data: `DeleteJob` removes a finished job's objects and records (only its
//! owner or an admin, only once it is finished), and `--retention-days` does the same by age,
//! uploads included.

use std::path::Path;
use std::time::Duration;
use stylenerf_server::proto::v1 as pb;
use stylenerf_testkit::*;

/// Files under `dir` (recursively).
fn files_under(dir: &Path) -> usize {
    std::fs::read_dir(dir)
        .map(|entries| {
            entries
                .flatten()
                .map(|e| {
                    if e.path().is_dir() {
                        files_under(&e.path())
                    } else {
                        1
                    }
                })
                .sum()
        })
        .unwrap_or(0)
}

#[tokio::test]
async fn a_finished_job_is_deleted_with_its_objects() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("artifacts");
    let server = start(config(dir.path())).await;
    let mut alice = jobs_client(&server, Some(ALICE)).await;
    let job = create_job(&mut alice).await;
    let mut worker = FakeWorker::register(&server, "cpu", 0).await;
    worker.run_one().await; // an output object and its artifact row
    let job_dir = store.join("jobs").join(&job.id);
    let stored = files_under(&job_dir);
    assert!(stored >= 4, "inputs and an output: {stored}");

    let delete = |id: &str| pb::DeleteJobRequest { job_id: id.into() };
    let running = alice.delete_job(delete(&job.id)).await.unwrap_err();
    assert_eq!(running.code(), tonic::Code::FailedPrecondition);
    assert!(running.message().contains("cancel it first"), "{running:?}");
    // Someone else's job is not there for them.
    let mut bob = jobs_client(&server, Some(BOB)).await;
    alice
        .cancel_job(pb::CancelJobRequest {
            job_id: job.id.clone(),
            reason: String::new(),
        })
        .await
        .unwrap();
    let theirs = bob.delete_job(delete(&job.id)).await.unwrap_err();
    assert_eq!(theirs.code(), tonic::Code::NotFound);
    assert_eq!(
        files_under(&job_dir),
        stored,
        "nothing deleted by a refused call"
    );

    let deleted = alice
        .delete_job(delete(&job.id))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(deleted.deleted_objects as usize, stored);
    assert!(deleted.deleted_bytes > 0);
    assert_eq!(files_under(&job_dir), 0);
    let gone = alice
        .get_job(pb::GetJobRequest {
            job_id: job.id.clone(),
        })
        .await
        .unwrap_err();
    assert_eq!(gone.code(), tonic::Code::NotFound);
    let events = alice
        .watch_job(pb::WatchJobRequest {
            job_id: job.id.clone(),
            after_seq: 0,
            skip_progress: false,
        })
        .await;
    assert!(events.is_err(), "its events are gone too");
    let again = alice.delete_job(delete(&job.id)).await.unwrap_err();
    assert_eq!(again.code(), tonic::Code::NotFound);
    // The other jobs are untouched.
    let other = create_job(&mut alice).await;
    assert_eq!(get_job(&mut alice, &other.id).await.id, other.id);
    server.shutdown().await.unwrap();
}

#[tokio::test]
async fn retention_deletes_old_finished_jobs_and_uploads() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("artifacts");
    let mut config = config(dir.path());
    config.retention = Some(Duration::from_millis(300));
    config.retention_sweep_interval = Duration::from_millis(50);
    let server = start(config).await;
    let mut alice = jobs_client(&server, Some(ALICE)).await;
    let finished = create_job(&mut alice).await;
    alice
        .cancel_job(pb::CancelJobRequest {
            job_id: finished.id.clone(),
            reason: String::new(),
        })
        .await
        .unwrap();
    // A job still queued is kept however old.
    let queued = create_job(&mut alice).await;
    assert!(files_under(&store.join("uploads")) > 0);
    let mut deleted = false;
    for _ in 0..100 {
        tokio::time::sleep(Duration::from_millis(50)).await;
        let status = alice
            .get_job(pb::GetJobRequest {
                job_id: finished.id.clone(),
            })
            .await;
        if status.is_err_and(|s| s.code() == tonic::Code::NotFound) {
            deleted = true;
            break;
        }
    }
    assert!(deleted, "the finished job outlived its retention");
    assert_eq!(files_under(&store.join("jobs").join(&finished.id)), 0);
    for _ in 0..100 {
        if files_under(&store.join("uploads")) == 0 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert_eq!(
        files_under(&store.join("uploads")),
        0,
        "old uploads are deleted"
    );
    assert_eq!(get_job(&mut alice, &queued.id).await.id, queued.id);
    assert!(files_under(&store.join("jobs").join(&queued.id)) > 0);
    server.shutdown().await.unwrap();
}
