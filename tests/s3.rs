//! The artifact store on a real S3 API: a moto server (`moto_server`, from PyPI's
//! `moto[server]`; `.ci/run` installs it) started by the test, and the chaos harness run
//! against it — a tiny job whose uploaded inputs, checkpoints and outputs all live in the
//! bucket, while workers and the coordinator are killed with SIGKILL. A killed worker's task
//! must resume from a checkpoint read back from S3.
//!
//! Without `moto_server` (on `PATH`, or named by `STYLENERF_MOTO_SERVER`) the test says so
//! and passes, unless `STYLENERF_REQUIRE_TEST_TOOLS` is set, as `.ci/run` does.

use std::io::{Read, Write};
use std::net::TcpStream;
mod support;

use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};
use stylenerf_engine::image_io::save_rgb_png;
use stylenerf_engine::style2d::painted;
use support::{log_tail, run, Service, CLIENT_TOKEN};

/// `moto_server`, where it is installed.
fn moto_server() -> Option<PathBuf> {
    if let Some(path) = std::env::var_os("STYLENERF_MOTO_SERVER") {
        return Some(PathBuf::from(path));
    }
    std::env::split_paths(&std::env::var_os("PATH")?)
        .map(|dir| dir.join("moto_server"))
        .find(|path| path.is_file())
}

/// A moto server on loopback, stopped when dropped.
struct Moto {
    child: Child,
    endpoint: String,
}

impl Drop for Moto {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// One HTTP/1.1 request without a body; returns the status line and the body.
fn exchange(addr: &str, method: &str, path: &str) -> std::io::Result<(String, Vec<u8>)> {
    let mut stream = TcpStream::connect(addr)?;
    stream.set_read_timeout(Some(Duration::from_secs(10)))?;
    write!(
        stream,
        "{method} {path} HTTP/1.1\r\nHost: {addr}\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"
    )?;
    let mut reply = Vec::new();
    stream.read_to_end(&mut reply)?;
    let head_end = reply
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .map_or(reply.len(), |i| i + 4);
    let head = String::from_utf8_lossy(&reply[..head_end]);
    let status = head.lines().next().unwrap_or_default().to_string();
    // Bodies here are small and not chunked (moto answers with Content-Length).
    Ok((status, reply[head_end..].to_vec()))
}

/// The status line of a request.
fn request(addr: &str, method: &str, path: &str) -> std::io::Result<String> {
    exchange(addr, method, path).map(|(status, _)| status)
}

fn start_moto(program: &PathBuf) -> Moto {
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let addr = format!("127.0.0.1:{port}");
    let child = Command::new(program)
        .args(["-H", "127.0.0.1", "-p", &port.to_string()])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap_or_else(|e| panic!("starting {}: {e}", program.display()));
    let moto = Moto {
        child,
        endpoint: format!("http://{addr}"),
    };
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        match request(&addr, "GET", "/") {
            Ok(status) if status.contains(" 200 ") => break,
            _ if Instant::now() < deadline => std::thread::sleep(Duration::from_millis(200)),
            other => panic!("moto did not answer on {addr}: {other:?}"),
        }
    }
    let status = request(&addr, "PUT", "/stylenerf-ci").expect("creates the bucket");
    assert!(status.contains(" 200 "), "creating the bucket: {status}");
    moto
}

#[test]
fn a_job_runs_and_resumes_with_every_artifact_in_s3() {
    let Some(program) = moto_server() else {
        assert!(
            std::env::var_os("STYLENERF_REQUIRE_TEST_TOOLS").is_none(),
            "STYLENERF_REQUIRE_TEST_TOOLS is set but moto_server was not found: \
             pip install 'moto[server]', or set STYLENERF_MOTO_SERVER"
        );
        eprintln!("skipped: moto_server not found (pip install 'moto[server]'; .ci/run does)");
        return;
    };
    let moto = start_moto(&program);
    let output = Command::new(env!("CARGO_BIN_EXE_stylenerf"))
        .args([
            "--log", "warn", "bench", "chaos", "--jobs", "3", "--kills", "12",
        ])
        .args(["--workers", "2", "--seed", "9", "--timeout-secs", "600"])
        .args(["--storage", "s3://stylenerf-ci/cluster"])
        .env("AWS_ENDPOINT", &moto.endpoint)
        .env("AWS_ALLOW_HTTP", "true")
        .env("AWS_ACCESS_KEY_ID", "testing")
        .env("AWS_SECRET_ACCESS_KEY", "testing")
        .env("AWS_REGION", "us-east-1")
        .output()
        .expect("runs stylenerf bench chaos");
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success(),
        "stdout:\n{stdout}\nstderr:\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let report: serde_json::Value = serde_json::from_str(&stdout).expect("a JSON report");
    assert_eq!(report["jobs_succeeded"], 3, "{report}");
    assert_eq!(
        report["violations"].as_array().unwrap().len(),
        0,
        "{report}"
    );
    // Inputs, checkpoints and outputs went to the bucket (read back through S3's listing).
    for kind in ["uploads", "checkpoints", "outputs"] {
        assert!(
            report["stored_objects"][kind].as_u64().unwrap_or(0) > 0,
            "no {kind} in the bucket: {report}"
        );
    }
    // At least one killed task resumed from the checkpoint its worker had stored in S3.
    assert!(
        report["resumed_from_store"].as_u64().unwrap() > 0,
        "{report}"
    );
}

#[test]
fn artifact_urls_are_presigned_by_the_bucket() {
    let Some(program) = moto_server() else {
        assert!(
            std::env::var_os("STYLENERF_REQUIRE_TEST_TOOLS").is_none(),
            "STYLENERF_REQUIRE_TEST_TOOLS is set but moto_server was not found"
        );
        eprintln!("skipped: moto_server not found (pip install 'moto[server]'; .ci/run does)");
        return;
    };
    let moto = start_moto(&program);
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let scene = d.join("scene");
    run(&[
        "scene",
        "generate",
        "--out",
        scene.to_str().unwrap(),
        "--size",
        "16",
        "--views",
        "4",
    ]);
    let style = d.join("waves.png");
    save_rgb_png(
        &style,
        32,
        32,
        painted::paint("waves", 32).unwrap().as_raw(),
    )
    .unwrap();
    let env = [
        ("AWS_ENDPOINT", moto.endpoint.as_str()),
        ("AWS_ALLOW_HTTP", "true"),
        ("AWS_ACCESS_KEY_ID", "testing"),
        ("AWS_SECRET_ACCESS_KEY", "testing"),
        ("AWS_REGION", "us-east-1"),
    ];
    let service = Service::start_with(d, Some("s3://stylenerf-ci/presigned"), &env, &[]);
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let (job, url) = runtime.block_on(async {
        // The coordinator process needs a moment to answer.
        let deadline = Instant::now() + Duration::from_secs(60);
        let client = loop {
            match stylenerf_client::Client::connect(&service.endpoint, Some(CLIENT_TOKEN)).await {
                Ok(client) if client.list(&Default::default()).await.is_ok() => break client,
                _ if Instant::now() < deadline => {
                    tokio::time::sleep(Duration::from_millis(200)).await
                }
                _ => panic!("no coordinator: {}", log_tail(d, "coordinator.log")),
            }
        };
        let mut spec = stylenerf_client::JobSpec::new(
            stylenerf_client::Input::path(&scene),
            [stylenerf_client::Input::path(&style)],
        );
        spec.preset = Some("tiny".into());
        let job = client.submit(&spec).await.unwrap().job;
        let url = client
            .artifact_url(&job.id, &job.style_keys[0], 120)
            .await
            .unwrap();
        (job, url)
    });
    drop(service);
    // The bucket signed it: the URL points at the S3 API, not the coordinator.
    let address = moto.endpoint.trim_start_matches("http://");
    let path = url
        .url
        .strip_prefix(&moto.endpoint)
        .unwrap_or_else(|| panic!("{} is not a URL of {}", url.url, moto.endpoint));
    assert!(
        path.contains("X-Amz-Signature=") && path.contains("X-Amz-Credential=testing"),
        "{}",
        url.url
    );
    assert!(path.contains(&job.id), "{}", url.url);
    let (status, body) = exchange(address, "GET", path).unwrap();
    assert!(status.contains(" 200 "), "{status}");
    assert_eq!(
        body,
        std::fs::read(&style).unwrap(),
        "the stored copy of the style"
    );
    assert_eq!(url.size, body.len() as u64);
    // (moto does not check signatures, so a tampered URL would open here too: the signing is
    // object_store's SigV4; what this test shows is that the coordinator hands out the
    // bucket's own URL, with the asked lifetime, and that it serves the object.)
    assert!(path.contains("X-Amz-Expires=120"), "{}", url.url);
}
