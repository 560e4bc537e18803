//! Roles and tokens: clients see only their own jobs, admins see all, workers only reach the
//! worker services, and missing or wrong tokens are refused.

use stylenerf_server::proto::v1 as pb;
use stylenerf_testkit::*;
use tonic::Code;

#[tokio::test]
async fn roles_and_tokens_are_enforced() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(config(dir.path())).await;
    let mut alice = jobs_client(&server, Some(ALICE)).await;
    let job = create_job(&mut alice).await;
    assert_eq!(job.owner, "alice");

    // Another client cannot see, list, watch or cancel it.
    let mut bob = jobs_client(&server, Some(BOB)).await;
    let hidden = bob
        .get_job(pb::GetJobRequest {
            job_id: job.id.clone(),
        })
        .await
        .unwrap_err();
    assert_eq!(hidden.code(), Code::NotFound);
    let cancel = bob
        .cancel_job(pb::CancelJobRequest {
            job_id: job.id.clone(),
            reason: String::new(),
        })
        .await
        .unwrap_err();
    assert_eq!(cancel.code(), Code::NotFound);
    let listed = bob.list_jobs(pb::ListJobsRequest::default()).await.unwrap();
    assert!(listed.into_inner().jobs.is_empty());
    let others = bob
        .list_jobs(pb::ListJobsRequest {
            owner: "alice".into(),
            ..Default::default()
        })
        .await
        .unwrap_err();
    assert_eq!(others.code(), Code::InvalidArgument);
    // Nor use her uploads.
    let mut request = job_request(&mut alice).await;
    request.name = "stolen".into();
    let stolen = bob.create_job(request).await.unwrap_err();
    assert_eq!(bad_fields(&stolen), ["dataset.upload_id"]);

    // The admin sees everything.
    let mut admin = jobs_client(&server, Some(ADMIN)).await;
    assert_eq!(get_job(&mut admin, &job.id).await.owner, "alice");
    let all = admin
        .list_jobs(pb::ListJobsRequest {
            owner: "alice".into(),
            include_tasks: true,
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(all.jobs.len(), 1);
    assert_eq!(all.jobs[0].tasks.len(), Source::Dataset.stages().len());

    // A worker token cannot use the job API; a client token cannot use the worker APIs.
    let mut as_worker = jobs_client(&server, Some(WORKER)).await;
    let denied = as_worker
        .get_job(pb::GetJobRequest {
            job_id: job.id.clone(),
        })
        .await
        .unwrap_err();
    assert_eq!(denied.code(), Code::PermissionDenied);
    let mut client_as_worker = worker_client(&server, Some(ALICE)).await;
    let denied = client_as_worker
        .register_worker(pb::RegisterWorkerRequest::default())
        .await
        .unwrap_err();
    assert_eq!(denied.code(), Code::PermissionDenied);
    let mut client_artifacts = artifact_client(&server, Some(ALICE)).await;
    let denied = client_artifacts
        .list_objects(pb::ListObjectsRequest {
            prefix: format!("jobs/{}/", job.id),
        })
        .await
        .unwrap_err();
    assert_eq!(denied.code(), Code::PermissionDenied);
    // The worker token works where it should.
    let mut worker = FakeWorker::register(&server, "cpu", 0).await;
    assert!(worker.lease(1000).await.is_some());

    // Wrong or missing tokens.
    let mut wrong = jobs_client(&server, Some("not-a-valid-token-at-all")).await;
    let refused = wrong
        .list_jobs(pb::ListJobsRequest::default())
        .await
        .unwrap_err();
    assert_eq!(refused.code(), Code::Unauthenticated);
    let mut anonymous = worker_client(&server, None).await;
    let refused = anonymous
        .register_worker(pb::RegisterWorkerRequest::default())
        .await
        .unwrap_err();
    assert_eq!(refused.code(), Code::Unauthenticated);
    server.shutdown().await.unwrap();
}
