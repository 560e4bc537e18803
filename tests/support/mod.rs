//! What the tests that run the service as processes share: a coordinator and a worker started
//! as processes of the built binary on loopback (real SQLite file, local store, token auth, the
//! HTTP listener), killed when dropped, and `stylenerf` commands run to completion.

// Compiled into each test binary that declares `mod support;`; each uses a part of it.
#![allow(dead_code)]

use std::path::Path;
use std::process::{Child, Command, Stdio};

/// The client token the service accepts (principal `web`).
pub const CLIENT_TOKEN: &str = "client-token-0123456789";
const WORKER_TOKEN: &str = "worker-token-0123456789";

/// A coordinator and one worker; both killed when dropped.
pub struct Service {
    processes: Vec<Child>,
    /// The gRPC endpoint.
    pub endpoint: String,
    /// The HTTP listener (page, JSON API, signed downloads), e.g. `http://127.0.0.1:8080`.
    pub http: String,
}

impl Drop for Service {
    fn drop(&mut self) {
        for child in &mut self.processes {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

fn spawn(dir: &Path, log: &str, env: &[(&str, &str)], args: &[&str]) -> Child {
    Command::new(env!("CARGO_BIN_EXE_stylenerf"))
        .args(["--log", "info", "--log-format", "json"])
        .args(args)
        .envs(env.iter().copied())
        .env_remove("STYLENERF_LOG")
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(dir.join(log)).unwrap())
        .spawn()
        .unwrap()
}

impl Service {
    /// Starts both under `dir` (database, store, scratch and the logs `coordinator.log`,
    /// `worker.log`), the coordinator with `extra` flags too.
    pub fn start(dir: &Path, extra: &[&str]) -> Service {
        Service::start_with(dir, None, &[], extra)
    }

    /// [`Service::start`] with another artifact store (a URL) and more environment for both
    /// processes (the store's credentials).
    pub fn start_with(
        dir: &Path,
        storage: Option<&str>,
        env: &[(&str, &str)],
        extra: &[&str],
    ) -> Service {
        let (grpc, http) = (free_port(), free_port());
        let endpoint = format!("http://127.0.0.1:{grpc}");
        let tokens = format!("client:web:{CLIENT_TOKEN},worker:pool:{WORKER_TOKEN}");
        let path = |name: &str| dir.join(name).display().to_string();
        let listen = format!("127.0.0.1:{grpc}");
        let http_listen = format!("127.0.0.1:{http}");
        let mut coordinator = vec![
            "coordinator",
            "--listen",
            &listen,
            "--metrics-listen",
            "off",
            "--http-listen",
            &http_listen,
            "--tokens",
            &tokens,
        ];
        let (database, scratch) = (path("coordinator.db"), path("scratch"));
        let store = storage.map_or_else(|| path("store"), str::to_string);
        coordinator.extend(["--database", &database, "--storage", &store]);
        coordinator.extend(extra);
        let mut processes = vec![spawn(dir, "coordinator.log", env, &coordinator)];
        processes.push(spawn(
            dir,
            "worker.log",
            env,
            &[
                "worker",
                "--endpoint",
                &endpoint,
                "--token",
                WORKER_TOKEN,
                "--lease-wait-secs",
                "1",
                "--scratch-dir",
                &scratch,
            ],
        ));
        Service {
            processes,
            endpoint,
            http: format!("http://{http_listen}"),
        }
    }
}

/// The last lines of a log under `dir`, for failure messages.
pub fn log_tail(dir: &Path, log: &str) -> String {
    std::fs::read_to_string(dir.join(log))
        .unwrap_or_default()
        .lines()
        .rev()
        .take(10)
        .collect::<Vec<_>>()
        .join("\n")
}

/// Runs `stylenerf <args>` to completion.
pub fn run(args: &[&str]) {
    let status = Command::new(env!("CARGO_BIN_EXE_stylenerf"))
        .args(["--log", "warn"])
        .args(args)
        .stdout(Stdio::null())
        .status()
        .unwrap();
    assert!(status.success(), "stylenerf {args:?}");
}
