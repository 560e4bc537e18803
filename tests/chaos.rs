//! The chaos benchmark, short: three tiny jobs submitted while worker and coordinator
//! processes are killed with SIGKILL a dozen times (one coordinator outage of eight seconds
//! while a stage runs among them). `stylenerf bench chaos` checks every guarantee itself — every acknowledged job
//! succeeds, each stage succeeds exactly once by the event log, a kill costs at most a
//! checkpoint interval — and exits non-zero with the violations listed otherwise.

use std::process::Command;

#[test]
fn jobs_survive_random_sigkills_of_workers_and_the_coordinator() {
    let output = Command::new(env!("CARGO_BIN_EXE_stylenerf"))
        .args([
            "--log", "warn", "bench", "chaos", "--jobs", "3", "--kills", "12",
        ])
        .args(["--workers", "2", "--seed", "1", "--timeout-secs", "600"])
        .output()
        .expect("runs stylenerf bench chaos");
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success(),
        "stdout:\n{stdout}\nstderr:\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let report: serde_json::Value = serde_json::from_str(&stdout).expect("a JSON report");
    assert_eq!(report["jobs_acknowledged"], 3);
    assert_eq!(report["jobs_succeeded"], 3);
    assert_eq!(
        report["worker_kills"].as_u64().unwrap() + report["coordinator_kills"].as_u64().unwrap(),
        12
    );
    assert_eq!(report["violations"].as_array().unwrap().len(), 0);
    // The outage came while a stage ran: its worker retried instead of failing the task.
    let retried: u64 = report["retried_calls"]
        .as_object()
        .unwrap()
        .values()
        .map(|n| n.as_u64().unwrap())
        .sum();
    assert!(retried > 0, "{report}");
}
