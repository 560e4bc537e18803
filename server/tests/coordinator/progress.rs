//! Progress throttling: heartbeats always update the task row and reach live watchers, but a
//! task's progress is stored as an event only once per `progress_event_interval` (the first
//! progress of a lease always is).

use futures::StreamExt;
use std::time::Duration;
use stylenerf_server::proto::v1 as pb;
use stylenerf_testkit::*;

#[tokio::test]
async fn progress_events_are_throttled_but_watchers_see_every_heartbeat() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = config(dir.path());
    config.progress_event_interval = Duration::from_secs(3600);
    let server = start(config).await;
    let mut client = jobs_client(&server, Some(ALICE)).await;
    let job = create_job(&mut client).await;
    let watch_request = pb::WatchJobRequest {
        job_id: job.id.clone(),
        after_seq: 0,
        skip_progress: false,
    };
    let mut watch = client
        .watch_job(watch_request.clone())
        .await
        .unwrap()
        .into_inner();

    let mut worker = FakeWorker::register(&server, "cpu", 0).await;
    let task = worker.lease(5000).await.expect("a task is ready");
    for step in 1..=4 {
        worker.heartbeat(&task, step).await.unwrap();
    }

    // Live: every heartbeat's progress; only the first was stored (it has a seq).
    let mut live = Vec::new();
    while live.len() < 4 {
        let event = tokio::time::timeout(Duration::from_secs(5), watch.next())
            .await
            .expect("progress arrives live")
            .unwrap()
            .unwrap();
        if event.kind() == pb::EventKind::TaskProgress {
            live.push((event.seq, event.progress.unwrap().step));
        }
    }
    assert_eq!(
        live.iter().map(|(_, step)| *step).collect::<Vec<_>>(),
        [1, 2, 3, 4]
    );
    assert!(live[0].0 > 0, "the first progress of a lease is stored");
    assert!(live[1..].iter().all(|(seq, _)| *seq == 0), "{live:?}");

    // The task row always has the latest progress.
    let now = get_job(&mut client, &job.id).await;
    assert_eq!(now.tasks[0].progress.as_ref().unwrap().step, 4);

    // The stored history has one progress event.
    client
        .cancel_job(pb::CancelJobRequest {
            job_id: job.id.clone(),
            reason: String::new(),
        })
        .await
        .unwrap();
    let history: Vec<pb::Event> = client
        .watch_job(watch_request)
        .await
        .unwrap()
        .into_inner()
        .map(|e| e.unwrap())
        .collect()
        .await;
    let stored: Vec<u64> = history
        .iter()
        .filter(|e| e.kind() == pb::EventKind::TaskProgress)
        .map(|e| e.progress.as_ref().unwrap().step)
        .collect();
    assert_eq!(stored, [1]);
    assert!(history.windows(2).all(|w| w[0].seq < w[1].seq));
    assert_eq!(history.last().unwrap().job_state(), pb::JobState::Cancelled);
    server.shutdown().await.unwrap();
}
