//! The Prometheus endpoint as an autoscaler and a dashboard read it: queue depth per stage,
//! device class and label set, per-RPC latency with bounded method names, queue wait, process
//! metrics, build info, and `/healthz`.

use std::io::{Read, Write};
use std::time::Duration;
use stylenerf_server::proto::v1 as pb;
use stylenerf_testkit::*;

/// `GET path` on the metrics port: (status line, body).
fn get(addr: std::net::SocketAddr, path: &str) -> (String, String) {
    let mut stream = std::net::TcpStream::connect(addr).unwrap();
    write!(
        stream,
        "GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut reply = String::new();
    stream.read_to_string(&mut reply).unwrap();
    let (head, body) = reply.split_once("\r\n\r\n").unwrap_or((&reply, ""));
    (
        head.lines().next().unwrap_or("").to_string(),
        body.to_string(),
    )
}

/// The value of the first sample whose line starts with `series` (name and labels).
fn sample(text: &str, series: &str) -> Option<f64> {
    text.lines()
        .find(|line| line.starts_with(series))
        .and_then(|line| line.rsplit(' ').next())
        .and_then(|v| v.parse().ok())
}

/// Scrapes until `series` has `value` (the gauges are refreshed by the reaper).
async fn wait_for(addr: std::net::SocketAddr, series: &str, value: f64) -> String {
    for _ in 0..100 {
        let (_, text) = tokio::task::spawn_blocking(move || get(addr, "/metrics"))
            .await
            .unwrap();
        if sample(&text, series) == Some(value) {
            return text;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let (_, text) = get(addr, "/metrics");
    panic!("{series} never reached {value}:\n{text}");
}

#[tokio::test]
async fn metrics_split_the_queue_by_device_class_and_labels() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = config(dir.path());
    config.metrics_listen = Some("127.0.0.1:0".parse().unwrap());
    let server = start(config).await;
    let addr = server.metrics_addr().expect("metrics served");
    let mut client = jobs_client(&server, Some(ALICE)).await;

    // A CUDA job that needs a labelled worker: nobody can take it, so it stays queued.
    let mut request = job_request(&mut client).await;
    request.requirements = Some(pb::Requirements {
        require_cuda: true,
        labels: vec!["zone-metrics-b".into(), "a100".into()],
        memory_bytes: 0,
    });
    client.create_job(request).await.unwrap();
    let cuda = r#"stylenerf_queue_depth{stage="nerf_pretrain",device="cuda",labels="a100,zone-metrics-b"}"#;
    let text = wait_for(addr, cuda, 1.0).await;
    // Every stage has a zero series per class, so an autoscaler reads 0 rather than nothing.
    assert!(
        text.contains(r#"stylenerf_queue_depth{stage="render_stylized",device="cpu",labels=""}"#),
        "{text}"
    );

    // A CPU job with the same labels and a worker that has them: it is leased, and the queue
    // wait is recorded for the CPU class.
    let mut request = job_request(&mut client).await;
    request.requirements = Some(pb::Requirements {
        require_cuda: false,
        labels: vec!["zone-metrics-b".into(), "a100".into()],
        memory_bytes: 0,
    });
    client.create_job(request).await.unwrap();
    let cpu =
        r#"stylenerf_queue_depth{stage="nerf_pretrain",device="cpu",labels="a100,zone-metrics-b"}"#;
    wait_for(addr, cpu, 1.0).await;
    let mut workers = worker_client(&server, Some(WORKER)).await;
    let id = workers
        .register_worker(pb::RegisterWorkerRequest {
            name: "labelled".into(),
            capabilities: Some(pb::Capabilities {
                device: "cpu".into(),
                memory_bytes: 0,
                labels: vec!["a100".into(), "zone-metrics-b".into()],
                max_tasks: 4,
                tools: Vec::new(),
            }),
            worker_id: String::new(),
        })
        .await
        .unwrap()
        .into_inner()
        .worker_id;
    let mut worker = FakeWorker {
        id,
        workers,
        artifacts: artifact_client(&server, Some(WORKER)).await,
    };
    assert!(
        worker.lease(1000).await.is_some(),
        "the labelled CPU task is leased"
    );
    // Its series drops back to zero (not left at its last value); the CUDA one stays.
    let text = wait_for(addr, cpu, 0.0).await;
    assert_eq!(sample(&text, cuda), Some(1.0), "{text}");
    let running = r#"stylenerf_tasks_running{stage="nerf_pretrain",device="cpu",labels="a100,zone-metrics-b"}"#;
    assert_eq!(sample(&text, running), Some(1.0), "{text}");
    assert!(
        text.contains(r#"stylenerf_queue_wait_seconds_count{stage="nerf_pretrain",device="cpu"}"#),
        "{text}"
    );

    // Per-RPC latency by method and code; a path the server does not serve is `unknown`.
    let channel = channel(&server).await;
    let mut grpc = tonic::client::Grpc::new(channel);
    grpc.ready().await.unwrap();
    let bogus: Result<tonic::Response<()>, tonic::Status> = grpc
        .unary(
            tonic::Request::new(()),
            http::uri::PathAndQuery::from_static("/evil.Service/Method-12345"),
            tonic_prost::ProstCodec::default(),
        )
        .await;
    assert!(bogus.is_err());
    let (_, text) = tokio::task::spawn_blocking(move || get(addr, "/metrics"))
        .await
        .unwrap();
    assert!(
        text.contains(
            r#"stylenerf_rpc_duration_seconds_count{method="/stylenerf.v1.JobService/CreateJob",code="Ok"}"#
        ),
        "{text}"
    );
    assert!(
        text.contains(r#"method="unknown",code="Unimplemented""#),
        "{text}"
    );
    assert!(!text.contains("evil"), "{text}");
    // The process and the build.
    assert!(
        sample(&text, "process_resident_memory_bytes").unwrap_or(0.0) > 0.0,
        "{text}"
    );
    assert!(text.contains("stylenerf_build_info{version=\""), "{text}");

    let (status, body) = tokio::task::spawn_blocking(move || get(addr, "/healthz"))
        .await
        .unwrap();
    assert!(status.contains(" 200 "), "{status}");
    assert_eq!(body.trim(), "ok");
    server.shutdown().await.unwrap();
}
