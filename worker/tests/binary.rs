//! The `stylenerf-worker` binary as an operator starts it: before its coordinator is up it
//! waits (as a Kubernetes pod must, rather than crash-looping), logging JSON lines that say so.

use std::process::{Command, Stdio};
use std::time::Duration;

#[test]
fn waits_for_a_coordinator_that_is_not_up_yet_logging_json() {
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let scratch = tempfile::tempdir().unwrap();
    let mut child = Command::new(env!("CARGO_BIN_EXE_stylenerf-worker"))
        .args(["--log-format", "json", "--log", "warn"])
        .args(["--endpoint", &format!("http://127.0.0.1:{port}")])
        .arg("--scratch-dir")
        .arg(scratch.path())
        .env_remove("STYLENERF_LOG")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    std::thread::sleep(Duration::from_secs(3));
    assert!(
        child.try_wait().unwrap().is_none(),
        "the worker exited instead of waiting"
    );
    child.kill().unwrap();
    let output = child.wait_with_output().unwrap();
    let stderr = String::from_utf8(output.stderr).unwrap();
    let lines: Vec<serde_json::Value> = stderr
        .lines()
        .map(|line| serde_json::from_str(line).unwrap_or_else(|e| panic!("{e}: {line:?}")))
        .collect();
    assert!(
        lines
            .iter()
            .any(|l| l["fields"]["message"] == "the coordinator is not reachable yet; waiting"),
        "{stderr}"
    );
}
