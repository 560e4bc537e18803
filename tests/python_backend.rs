//! The integrator's target: a Python web backend written only from `proto/` and docs/API.md
//! (`tests/python/backend.py`: stubs generated with grpcio-tools) creates a job against a real
//! coordinator and worker (processes of the built binary on loopback), learns of its progress
//! only from signed webhooks, and downloads the animation through a signed URL with plain HTTP —
//! no gRPC stream held.
//!
//! Needs Python with `grpcio` and `grpcio-tools` (`STYLENERF_TEST_PYTHON`, default `python3`;
//! `.ci/run` installs them). Without them the test says so and passes, unless
//! `STYLENERF_REQUIRE_TEST_TOOLS` is set, as `.ci/run` does.

mod support;

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};
use support::{log_tail, run, Service, CLIENT_TOKEN};

/// Python with grpcio and grpcio-tools, if there is one.
fn python() -> Option<PathBuf> {
    let python = PathBuf::from(
        std::env::var_os("STYLENERF_TEST_PYTHON").unwrap_or_else(|| "python3".into()),
    );
    let ok = Command::new(&python)
        .args(["-c", "import grpc, grpc_tools"])
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    ok.then_some(python)
}

#[test]
fn a_python_backend_gets_webhooks_and_downloads_through_a_url() {
    let Some(python) = python() else {
        assert!(
            std::env::var_os("STYLENERF_REQUIRE_TEST_TOOLS").is_none(),
            "STYLENERF_REQUIRE_TEST_TOOLS is set but Python with grpcio and grpcio-tools was \
             not found (STYLENERF_TEST_PYTHON)"
        );
        eprintln!("skipped: no Python with grpcio and grpcio-tools (.ci/run installs them)");
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let dir_arg = |name: &str| d.join(name).display().to_string();
    run(&[
        "scene",
        "generate",
        "--out",
        &dir_arg("scene"),
        "--size",
        "24",
        "--views",
        "6",
    ]);
    run(&["stylize", "export-styles", "--out", &dir_arg("styles")]);
    let scene = stylenerf_client::pack_scene(&d.join("scene")).unwrap();

    let service = Service::start(d, &["--webhook-allow-private"]);
    let (endpoint, http) = (service.endpoint.clone(), service.http.clone());
    let started = Instant::now();
    let output = Command::new(&python)
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/backend.py"))
        .args([endpoint.as_str(), CLIENT_TOKEN])
        .arg(&scene.path)
        .arg(d.join("styles").join("waves.png"))
        .arg(d)
        .output()
        .unwrap();
    drop(service);
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success(),
        "backend.py failed after {:?}:\nstdout: {stdout}\nstderr: {}\ncoordinator log tail: {}",
        started.elapsed(),
        String::from_utf8_lossy(&output.stderr),
        log_tail(d, "coordinator.log")
    );
    let report: serde_json::Value = serde_json::from_str(stdout.trim()).expect("one JSON line");
    assert_eq!(
        report["states"].as_array().unwrap().last().unwrap(),
        "JOB_STATE_SUCCEEDED"
    );
    assert!(report["states"].as_array().unwrap().len() >= 2, "{report}");
    assert_eq!(report["content_type"], "image/gif");
    // The link points at the coordinator's HTTP listener.
    assert!(
        report["url"]
            .as_str()
            .unwrap()
            .starts_with(&format!("{http}/v1/artifacts/")),
        "{report}"
    );
    assert_eq!(report["gif"], true, "{report}");
    assert_eq!(report["sha256_matches"], true, "{report}");
    assert!(started.elapsed() < Duration::from_secs(600));
}
