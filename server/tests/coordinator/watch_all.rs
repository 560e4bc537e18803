//! `WatchJobs`: one stream of every event of the caller's jobs, replayed after a `seq` and then
//! live — never another tenant's.

use std::time::Duration;
use stylenerf_server::proto::v1 as pb;
use stylenerf_testkit::*;

/// Reads events until `done` says so (or fails after 10 s).
async fn until(
    stream: &mut tonic::Streaming<pb::Event>,
    mut done: impl FnMut(&[pb::Event]) -> bool,
) -> Vec<pb::Event> {
    let mut seen = Vec::new();
    while !done(&seen) {
        let event = tokio::time::timeout(Duration::from_secs(10), stream.message())
            .await
            .expect("an event within 10 s")
            .unwrap()
            .expect("the stream goes on");
        seen.push(event);
    }
    seen
}

#[tokio::test]
async fn a_caller_watches_all_its_jobs_and_only_its_own() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(config(dir.path())).await;
    let mut alice = jobs_client(&server, Some(ALICE)).await;
    let mut bob = jobs_client(&server, Some(BOB)).await;
    let first = create_job(&mut alice).await;
    let theirs = create_job(&mut bob).await;
    let request = |after_seq| pb::WatchJobsRequest {
        after_seq,
        skip_progress: true,
        owner: String::new(),
    };
    let mut stream = alice.watch_jobs(request(0)).await.unwrap().into_inner();
    // Replayed: the first job's creation. Live: a second job's.
    let second = create_job(&mut alice).await;
    let seen = until(&mut stream, |seen| {
        seen.iter().any(|e| e.job_id == second.id)
    })
    .await;
    assert!(seen.iter().any(|e| e.job_id == first.id), "{seen:?}");
    assert!(
        seen.iter().all(|e| e.job_id != theirs.id),
        "another tenant's events: {seen:?}"
    );
    assert!(seen.windows(2).all(|w| w[0].seq < w[1].seq), "in seq order");
    drop(stream);

    // Resumed after the last seq seen: only what came after.
    let last = seen.last().unwrap().seq;
    let mut resumed = alice.watch_jobs(request(last)).await.unwrap().into_inner();
    alice
        .cancel_job(pb::CancelJobRequest {
            job_id: first.id.clone(),
            reason: String::new(),
        })
        .await
        .unwrap();
    let more = until(&mut resumed, |seen| {
        seen.iter().any(|e| {
            e.job_id == first.id
                && e.kind == pb::EventKind::JobState as i32
                && e.job_state == pb::JobState::Cancelled as i32
        })
    })
    .await;
    assert!(more.iter().all(|e| e.seq > last), "{more:?}");

    // Another owner's stream: admins only.
    let denied = bob
        .watch_jobs(pb::WatchJobsRequest {
            owner: "alice".into(),
            ..request(0)
        })
        .await
        .unwrap_err();
    assert_eq!(denied.code(), tonic::Code::InvalidArgument);
    assert_eq!(bad_fields(&denied), vec!["owner".to_string()]);
    let mut admin = jobs_client(&server, Some(ADMIN)).await;
    let mut bobs = admin
        .watch_jobs(pb::WatchJobsRequest {
            owner: "bob".into(),
            ..request(0)
        })
        .await
        .unwrap()
        .into_inner();
    let seen = until(&mut bobs, |seen| !seen.is_empty()).await;
    assert!(seen.iter().all(|e| e.job_id == theirs.id), "{seen:?}");
    server.shutdown().await.unwrap();
}
