//! Scheduling by priority (higher first, then the longest-waiting) and job deadlines (an
//! unfinished job fails when its deadline passes); both checked at submission.

use std::time::Duration;
use stylenerf_server::proto::v1 as pb;
use stylenerf_testkit::*;

fn now_ms() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_millis() as i64
}

#[tokio::test]
async fn higher_priority_jobs_are_leased_first_and_late_jobs_fail() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(config(dir.path())).await;
    let mut alice = jobs_client(&server, Some(ALICE)).await;
    let mut ids = Vec::new();
    for priority in [0, 10, -5] {
        let mut request = job_request(&mut alice).await;
        request.priority = priority;
        let job = create(&mut alice, request).await;
        assert_eq!(job.priority, priority);
        ids.push(job.id);
    }
    let mut worker = FakeWorker::register(&server, "cpu", 0).await;
    let mut order = Vec::new();
    for _ in 0..3 {
        order.push(worker.lease(1000).await.expect("a task").job_id);
    }
    assert_eq!(order, vec![ids[1].clone(), ids[0].clone(), ids[2].clone()]);

    // A deadline that passes while the job waits fails it, saying why.
    let mut request = job_request(&mut alice).await;
    request.deadline_at_ms = now_ms() + 300;
    let late = create(&mut alice, request).await;
    let mut failed = None;
    for _ in 0..100 {
        let job = get_job(&mut alice, &late.id).await;
        if job.state() == pb::JobState::Failed {
            failed = Some(job);
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let failed = failed.expect("the late job failed");
    assert!(failed.error.contains("deadline passed"), "{}", failed.error);
    assert!(failed
        .tasks
        .iter()
        .all(|t| t.state() == pb::TaskState::Cancelled));

    // Checked at submission.
    for (priority, deadline, field) in [
        (101, 0, "priority"),
        (0, now_ms() - 1000, "deadline_at_ms"),
        (0, now_ms() + 400 * 86_400_000, "deadline_at_ms"),
    ] {
        let mut request = job_request(&mut alice).await;
        request.priority = priority;
        request.deadline_at_ms = deadline;
        let refused = alice.create_job(request).await.unwrap_err();
        assert!(
            bad_fields(&refused).contains(&field.to_string()),
            "{refused:?}"
        );
    }
    server.shutdown().await.unwrap();
}
