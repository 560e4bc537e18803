//! Job webhooks end to end on loopback: a receiver that fails its first request gets every
//! chosen event, signed per Standard Webhooks with the job's secret, retried after the failure;
//! the delivery log says so; private destinations are refused unless allowed.

use base64::Engine;
use hmac::{KeyInit, Mac};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use stylenerf_server::proto::v1 as pb;
use stylenerf_testkit::*;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// One request the receiver got: its headers (lower-case names) and body.
#[derive(Debug, Clone)]
struct Received {
    headers: Vec<(String, String)>,
    body: Vec<u8>,
}

impl Received {
    fn header(&self, name: &str) -> &str {
        self.headers
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, v)| v.as_str())
            .unwrap_or("")
    }
}

/// An HTTP receiver on loopback answering 500 to its first request and 204 after.
async fn receiver() -> (String, Arc<Mutex<Vec<Received>>>) {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("http://{}/hook", listener.local_addr().unwrap());
    let got = Arc::new(Mutex::new(Vec::new()));
    let log = got.clone();
    tokio::spawn(async move {
        loop {
            let Ok((mut socket, _)) = listener.accept().await else {
                return;
            };
            let log = log.clone();
            tokio::spawn(async move {
                let mut data = Vec::new();
                let mut buf = [0u8; 4096];
                let (head_end, length) = loop {
                    let n = socket.read(&mut buf).await.unwrap_or(0);
                    if n == 0 {
                        return;
                    }
                    data.extend_from_slice(&buf[..n]);
                    if let Some(end) = data.windows(4).position(|w| w == b"\r\n\r\n") {
                        let head = String::from_utf8_lossy(&data[..end]).to_lowercase();
                        let length = head
                            .lines()
                            .find_map(|l| l.strip_prefix("content-length:"))
                            .and_then(|v| v.trim().parse::<usize>().ok())
                            .unwrap_or(0);
                        break (end + 4, length);
                    }
                };
                while data.len() < head_end + length {
                    let n = socket.read(&mut buf).await.unwrap_or(0);
                    if n == 0 {
                        break;
                    }
                    data.extend_from_slice(&buf[..n]);
                }
                let head = String::from_utf8_lossy(&data[..head_end]).to_string();
                let headers = head
                    .lines()
                    .skip(1)
                    .filter_map(|l| l.split_once(':'))
                    .map(|(n, v)| (n.trim().to_lowercase(), v.trim().to_string()))
                    .collect();
                let first = {
                    let mut log = log.lock().unwrap();
                    log.push(Received {
                        headers,
                        body: data[head_end..].to_vec(),
                    });
                    log.len() == 1
                };
                let status = if first {
                    "500 Internal Server Error"
                } else {
                    "204 No Content"
                };
                let _ = socket
                    .write_all(
                        format!(
                            "HTTP/1.1 {status}\r\ncontent-length: 0\r\nconnection: close\r\n\r\n"
                        )
                        .as_bytes(),
                    )
                    .await;
            });
        }
    });
    (url, got)
}

fn expected_signature(secret: &str, id: &str, timestamp: &str, body: &[u8]) -> String {
    let key = base64::engine::general_purpose::STANDARD
        .decode(secret.trim_start_matches("whsec_"))
        .unwrap();
    let mut mac = hmac::Hmac::<sha2::Sha256>::new_from_slice(&key).unwrap();
    mac.update(format!("{id}.{timestamp}.").as_bytes());
    mac.update(body);
    format!(
        "v1,{}",
        base64::engine::general_purpose::STANDARD.encode(mac.finalize().into_bytes())
    )
}

#[tokio::test]
async fn webhooks_deliver_signed_events_and_retry_failures() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = config(dir.path());
    config.webhook_allow_private = true;
    let server = start(config).await;
    let (url, received) = receiver().await;
    let mut alice = jobs_client(&server, Some(ALICE)).await;
    let mut request = job_request(&mut alice).await;
    request.webhook = Some(pb::Webhook {
        url: url.clone(),
        events: vec![
            pb::EventKind::JobState as i32,
            pb::EventKind::TaskState as i32,
        ],
    });
    let created = alice.create_job(request).await.unwrap().into_inner();
    let secret = created.webhook_secret.clone();
    assert!(secret.starts_with("whsec_"), "{secret:?}");
    let job = created.job.unwrap();
    let mut worker = FakeWorker::register(&server, "cpu", 0).await;
    worker.run_one().await;
    alice
        .cancel_job(pb::CancelJobRequest {
            job_id: job.id.clone(),
            reason: String::new(),
        })
        .await
        .unwrap();

    // Every chosen event of the job, in the log; wait until all are delivered (the first
    // after a retry some seconds later).
    let mut deliveries = Vec::new();
    for _ in 0..200 {
        deliveries = alice
            .list_webhook_deliveries(pb::ListWebhookDeliveriesRequest {
                job_id: job.id.clone(),
            })
            .await
            .unwrap()
            .into_inner()
            .deliveries;
        if !deliveries.is_empty() && deliveries.iter().all(|d| d.state == "delivered") {
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert!(
        deliveries.iter().all(|d| d.state == "delivered"),
        "{deliveries:#?}"
    );
    let kinds: Vec<i32> = deliveries.iter().map(|d| d.kind).collect();
    assert!(
        kinds.contains(&(pb::EventKind::JobState as i32)),
        "{kinds:?}"
    );
    assert!(
        kinds.contains(&(pb::EventKind::TaskState as i32)),
        "{kinds:?}"
    );
    assert!(
        !kinds.contains(&(pb::EventKind::JobCreated as i32)),
        "not chosen: {kinds:?}"
    );
    assert_eq!(
        deliveries.iter().map(|d| d.attempts).max(),
        Some(2),
        "{deliveries:#?}"
    );
    assert!(deliveries.iter().any(|d| d.last_status == 204));

    let received = received.lock().unwrap().clone();
    assert_eq!(received.len(), deliveries.len() + 1, "one retry");
    for request in &received {
        let id = request.header("webhook-id");
        let timestamp = request.header("webhook-timestamp");
        assert_eq!(
            request.header("webhook-signature"),
            expected_signature(&secret, id, timestamp, &request.body),
            "{request:?}"
        );
        // The body is the event in proto JSON.
        let event: pb::Event = serde_json::from_slice(&request.body).unwrap();
        assert_eq!(event.job_id, job.id);
    }

    // Private destinations need the operator's permission; other schemes are refused.
    server.shutdown().await.unwrap();
    let server = start(stylenerf_testkit::config(dir.path())).await;
    let mut alice = jobs_client(&server, Some(ALICE)).await;
    for (target, needle) in [
        (url.as_str(), "loopback or private"),
        (
            "http://169.254.169.254/latest/meta-data",
            "loopback or private",
        ),
        ("ftp://example.com/hook", "expected http or https"),
    ] {
        let mut request = job_request(&mut alice).await;
        request.webhook = Some(pb::Webhook {
            url: target.into(),
            events: vec![],
        });
        let refused = alice.create_job(request).await.unwrap_err();
        assert_eq!(refused.code(), tonic::Code::InvalidArgument, "{target}");
        assert!(
            bad_fields(&refused).contains(&"webhook.url".to_string()),
            "{refused:?}"
        );
        assert!(
            refused.message().contains(needle) || format!("{refused:?}").contains(needle),
            "{target}: {refused:?}"
        );
    }
    server.shutdown().await.unwrap();
}
