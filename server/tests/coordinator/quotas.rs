//! Per-owner quotas: an owner at its running-task limit waits while others' tasks are leased
//! (an owner of its own may have another limit), and stored bytes bound uploads, resumable
//! appends and new jobs until finished jobs are deleted.

use std::collections::HashMap;
use stylenerf_server::proto::v1 as pb;
use stylenerf_server::Quota;
use stylenerf_testkit::*;
use tonic::Code;

#[tokio::test]
async fn an_owner_at_its_running_task_quota_waits_while_others_run() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = config(dir.path());
    config.quotas.default.running_tasks = 1;
    config.quotas.owners.insert(
        "bob".into(),
        Quota {
            running_tasks: 2,
            stored_bytes: 0,
        },
    );
    let server = start(config).await;
    let mut alice = jobs_client(&server, Some(ALICE)).await;
    let mut bob = jobs_client(&server, Some(BOB)).await;
    let mut owner_of = HashMap::new();
    // Alice's jobs are older: without quotas both would be leased first.
    for _ in 0..2 {
        owner_of.insert(create_job(&mut alice).await.id, "alice");
    }
    for _ in 0..2 {
        owner_of.insert(create_job(&mut bob).await.id, "bob");
    }
    let mut worker = FakeWorker::register(&server, "cpu", 0).await;
    let mut leased = Vec::new();
    for _ in 0..3 {
        leased.push(worker.lease(1000).await.expect("a task within the quotas"));
    }
    let owners: Vec<&str> = leased.iter().map(|t| owner_of[&t.job_id]).collect();
    assert_eq!(owners, ["alice", "bob", "bob"]);
    assert!(
        worker.lease(300).await.is_none(),
        "alice (1) and bob (2) are at their quotas"
    );
    // A finished task makes room for its owner.
    worker.complete(&leased[0]).await.unwrap();
    let next = worker.lease(1000).await.expect("alice's turn again");
    assert_eq!(owner_of[&next.job_id], "alice");
    server.shutdown().await.unwrap();
}

#[tokio::test]
async fn stored_bytes_bound_uploads_and_jobs_until_jobs_are_deleted() {
    let dir = tempfile::tempdir().unwrap();
    let scene = scene_tar();
    let mut config = config(dir.path());
    // Room for one job's uploads and copied inputs (about twice the scene), not for three.
    config.quotas.default.stored_bytes = 3 * scene.len() as u64;
    let server = start(config).await;
    let mut alice = jobs_client(&server, Some(ALICE)).await;
    let job = create_job(&mut alice).await;

    let refused = upload(
        &mut alice,
        pb::UploadKind::DatasetArchive,
        "more.tar",
        &scene,
    )
    .await
    .unwrap_err();
    assert_eq!(refused.code(), Code::ResourceExhausted, "{refused:?}");
    assert!(
        refused.message().contains("storage quota of \"alice\""),
        "{refused:?}"
    );
    // The same through a resumable session: a declared size at the start, else at the append.
    let start = |total_size| pb::StartUploadRequest {
        kind: pb::UploadKind::DatasetArchive as i32,
        filename: "more.tar".into(),
        total_size,
    };
    let declared = alice
        .start_upload(start(scene.len() as u64))
        .await
        .unwrap_err();
    assert_eq!(declared.code(), Code::ResourceExhausted);
    let session = alice.start_upload(start(0)).await.unwrap().into_inner();
    let messages = vec![
        pb::UploadSessionChunk {
            part: Some(pb::upload_session_chunk::Part::Resume(pb::UploadResume {
                session_id: session.session_id.clone(),
                offset: 0,
            })),
        },
        pb::UploadSessionChunk {
            part: Some(pb::upload_session_chunk::Part::Data(scene.clone())),
        },
    ];
    let appended = alice
        .append_upload(tokio_stream::iter(messages))
        .await
        .unwrap_err();
    assert_eq!(appended.code(), Code::ResourceExhausted, "{appended:?}");
    // Bob's bytes are his own.
    let mut bob = jobs_client(&server, Some(BOB)).await;
    upload(&mut bob, pb::UploadKind::DatasetArchive, "lego.tar", &scene)
        .await
        .expect("bob has room");

    // Deleting the finished job frees its inputs and outputs.
    alice
        .cancel_job(pb::CancelJobRequest {
            job_id: job.id.clone(),
            ..Default::default()
        })
        .await
        .unwrap();
    alice
        .delete_job(pb::DeleteJobRequest {
            job_id: job.id.clone(),
        })
        .await
        .unwrap();
    upload(
        &mut alice,
        pb::UploadKind::DatasetArchive,
        "more.tar",
        &scene,
    )
    .await
    .expect("room again");
    server.shutdown().await.unwrap();
}
