//! Signed artifact URLs: `GetArtifactUrl` gives a caller who may read an object a URL that any
//! HTTP client can GET without a token, until it expires; altered or expired links are refused.

use std::io::{Read, Write};
use std::time::Duration;
use stylenerf_server::proto::v1 as pb;
use stylenerf_testkit::*;

/// `GET url` over HTTP/1.1: (status code, body).
fn http_get(url: &str) -> (u16, Vec<u8>) {
    let rest = url.strip_prefix("http://").unwrap();
    let (host, path) = rest.split_once('/').unwrap();
    let mut stream = std::net::TcpStream::connect(host).unwrap();
    write!(
        stream,
        "GET /{path} HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut reply = Vec::new();
    stream.read_to_end(&mut reply).unwrap();
    let split = reply.windows(4).position(|w| w == b"\r\n\r\n").unwrap();
    let head = String::from_utf8_lossy(&reply[..split]).to_string();
    let status = head.split_whitespace().nth(1).unwrap().parse().unwrap();
    (status, reply[split + 4..].to_vec())
}

async fn get(url: String) -> (u16, Vec<u8>) {
    tokio::task::spawn_blocking(move || http_get(&url))
        .await
        .unwrap()
}

#[tokio::test]
async fn signed_urls_serve_an_object_until_they_expire() {
    let dir = tempfile::tempdir().unwrap();
    let mut with_http = config(dir.path());
    with_http.http_listen = Some("127.0.0.1:0".parse().unwrap());
    let server = start(with_http).await;
    let mut alice = jobs_client(&server, Some(ALICE)).await;
    let job = create_job(&mut alice).await;
    let mut worker = FakeWorker::register(&server, "cpu", 0).await;
    let task = worker.run_one().await;
    let key = format!("{}result.bin", task.output_prefix);
    let expected = std::fs::read(dir.path().join("artifacts").join(&key)).unwrap();

    let request = |key: &str, ttl_seconds| pb::GetArtifactUrlRequest {
        job_id: job.id.clone(),
        key: key.into(),
        ttl_seconds,
    };
    let url = alice
        .get_artifact_url(request(&key, 0))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(url.size, expected.len() as u64);
    let (status, body) = get(url.url.clone()).await;
    assert_eq!(status, 200);
    assert_eq!(body, expected);

    // Altered: another key, a later expiry, another signature.
    let other = url.url.replace("result.bin", "other.bin");
    assert_eq!(get(other).await.0, 403);
    let later = url.url.replace(
        &format!("expires={}", url.expires_at_ms),
        &format!("expires={}", url.expires_at_ms + 1000),
    );
    assert_eq!(get(later).await.0, 403);
    let unsigned = url.url.split("&sig=").next().unwrap().to_string();
    assert_eq!(get(unsigned).await.0, 403);

    // Expired.
    let short = alice
        .get_artifact_url(request(&key, 1))
        .await
        .unwrap()
        .into_inner();
    tokio::time::sleep(Duration::from_millis(1100)).await;
    let (status, body) = get(short.url).await;
    assert_eq!(status, 403);
    assert!(String::from_utf8_lossy(&body).contains("expired"));

    // Only for callers who may read the job, objects that exist, keys of the job.
    let mut bob = jobs_client(&server, Some(BOB)).await;
    let theirs = bob.get_artifact_url(request(&key, 0)).await.unwrap_err();
    assert_eq!(theirs.code(), tonic::Code::NotFound);
    let missing = alice
        .get_artifact_url(request(&format!("jobs/{}/nothing.png", job.id), 0))
        .await
        .unwrap_err();
    assert_eq!(missing.code(), tonic::Code::NotFound);
    let outside = alice
        .get_artifact_url(request("uploads/x/dataset.tar", 0))
        .await
        .unwrap_err();
    assert_eq!(outside.code(), tonic::Code::InvalidArgument);
    let too_long = alice
        .get_artifact_url(request(&key, 8 * 86_400))
        .await
        .unwrap_err();
    assert_eq!(too_long.code(), tonic::Code::InvalidArgument);
    server.shutdown().await.unwrap();

    // Without --http-listen there is no URL to give.
    let server = start(config(dir.path())).await;
    let mut alice = jobs_client(&server, Some(ALICE)).await;
    let none = alice.get_artifact_url(request(&key, 0)).await.unwrap_err();
    assert_eq!(none.code(), tonic::Code::FailedPrecondition);
    server.shutdown().await.unwrap();
}

#[tokio::test]
async fn store_signed_urls_need_a_store_that_signs() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = config(dir.path());
    config.artifact_urls = stylenerf_server::ArtifactUrls::Store;
    let error = stylenerf_server::Coordinator::start(config)
        .await
        .err()
        .expect("a local folder signs no URLs")
        .to_string();
    assert!(error.contains("--artifact-urls store"), "{error}");
}
