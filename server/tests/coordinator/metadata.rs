//! Job metadata: the integrator's key-value pairs are kept with the job, returned with it,
//! filter `ListJobs`, and are checked at submission.

use stylenerf_server::proto::v1 as pb;
use stylenerf_testkit::*;

#[tokio::test]
async fn metadata_is_kept_filtered_and_checked() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(config(dir.path())).await;
    let mut alice = jobs_client(&server, Some(ALICE)).await;
    let pairs = |list: &[(&str, &str)]| {
        list.iter()
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect::<std::collections::HashMap<_, _>>()
    };
    let mut ids = Vec::new();
    for customer in ["42", "7"] {
        let mut request = job_request(&mut alice).await;
        request.metadata = pairs(&[("customer", customer), ("order/id", "A-17")]);
        let job = create(&mut alice, request).await;
        assert_eq!(job.metadata["customer"], customer);
        ids.push(job.id);
    }
    assert_eq!(
        get_job(&mut alice, &ids[0]).await.metadata["order/id"],
        "A-17"
    );
    let list = |metadata| pb::ListJobsRequest {
        metadata,
        ..Default::default()
    };
    let found = alice
        .list_jobs(list(pairs(&[("customer", "42")])))
        .await
        .unwrap()
        .into_inner()
        .jobs;
    assert_eq!(
        found.iter().map(|j| j.id.clone()).collect::<Vec<_>>(),
        vec![ids[0].clone()]
    );
    let both = alice
        .list_jobs(list(pairs(&[("order/id", "A-17")])))
        .await
        .unwrap()
        .into_inner()
        .jobs;
    assert_eq!(both.len(), 2);
    let none = alice
        .list_jobs(list(pairs(&[("customer", "42"), ("order/id", "B-1")])))
        .await
        .unwrap()
        .into_inner()
        .jobs;
    assert!(none.is_empty());

    // Checked at submission, naming the pair.
    let mut request = job_request(&mut alice).await;
    request.metadata = pairs(&[("bad key!", "x"), ("note", "line\nbreak")]);
    let refused = alice.create_job(request).await.unwrap_err();
    assert_eq!(refused.code(), tonic::Code::InvalidArgument);
    let fields = bad_fields(&refused);
    assert!(
        fields.contains(&"metadata[\"bad key!\"]".to_string()),
        "{fields:?}"
    );
    assert!(
        fields.contains(&"metadata[\"note\"]".to_string()),
        "{fields:?}"
    );
    let mut request = job_request(&mut alice).await;
    request.metadata = (0..33)
        .map(|i| (format!("k{i}"), "v".to_string()))
        .collect();
    let refused = alice.create_job(request).await.unwrap_err();
    assert!(bad_fields(&refused).contains(&"metadata".to_string()));
    server.shutdown().await.unwrap();
}
