#![cfg(unix)]
//! `--log-format json` gives log collectors JSON lines only: the coordinator's stderr from
//! start to a SIGTERM shutdown parses line by line, with its endpoints as plain strings.

use std::process::{Command, Stdio};
use std::time::Duration;

#[test]
fn the_coordinator_logs_json_lines_only() {
    let dir = tempfile::tempdir().unwrap();
    let child = Command::new(env!("CARGO_BIN_EXE_stylenerf"))
        .args(["--log", "info", "--log-format", "json", "coordinator"])
        .args(["--listen", "127.0.0.1:0", "--metrics-listen", "127.0.0.1:0"])
        .arg("--database")
        .arg(dir.path().join("c.db"))
        .arg("--storage")
        .arg(dir.path().join("store"))
        .arg("--insecure-no-auth")
        .env_remove("STYLENERF_LOG")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    std::thread::sleep(Duration::from_secs(2));
    // SAFETY: signalling our own child process.
    unsafe { libc::kill(child.id() as i32, libc::SIGTERM) };
    let output = child.wait_with_output().unwrap();
    assert!(output.status.success(), "{output:?}");
    let stderr = String::from_utf8(output.stderr).unwrap();
    let lines: Vec<serde_json::Value> = stderr
        .lines()
        .map(|line| serde_json::from_str(line).unwrap_or_else(|e| panic!("{e}: {line:?}")))
        .collect();
    let listening = lines
        .iter()
        .find(|l| l["fields"]["message"] == "coordinator listening")
        .expect("a start-up line");
    let metrics = listening["fields"]["metrics"].as_str().unwrap();
    assert!(metrics.starts_with("http://127.0.0.1:"), "{metrics}");
    assert!(lines
        .iter()
        .any(|l| l["fields"]["message"] == "coordinator stopped"));
}
