//! `stylenerf up --workers N`: a local cluster for trying the distributed mode. Runs a
//! coordinator in this process (SQLite and artifacts under the data folder, no authentication,
//! loopback by default) and N workers as real separate processes (this executable's `worker`
//! command), prints the endpoint and how to submit a job with the client commands, and on
//! Ctrl-C/SIGTERM stops the workers (each checkpoints and releases its task) and then the
//! coordinator.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command};
use std::time::{Duration, Instant};

use anyhow::Context;
use clap::Args;
use stylenerf_server::{Coordinator, CoordinatorConfig};

use super::coordinator::shutdown_signal;

/// How long workers get to checkpoint and release their tasks before they are killed.
const WORKER_STOP_TIMEOUT: Duration = Duration::from_secs(60);

/// Options of `stylenerf up`.
#[derive(Debug, Args)]
pub struct UpArgs {
    /// Worker processes to start.
    #[arg(long, default_value_t = 2)]
    pub workers: usize,
    /// Folder for the coordinator's database and artifacts and the workers' scratch space.
    #[arg(long, default_value = "stylenerf-data")]
    pub data_dir: PathBuf,
    /// gRPC listen address of the coordinator (no authentication: keep it on loopback or a
    /// trusted network).
    #[arg(long, default_value = "127.0.0.1:50051")]
    pub listen: SocketAddr,
    /// Further `stylenerf worker` flags for every worker, after `--`, e.g.
    /// `-- --checkpoint-every-steps 100 --device cuda`.
    #[arg(last = true, value_name = "WORKER FLAGS")]
    pub worker_args: Vec<String>,
}

pub fn run(args: UpArgs) -> anyhow::Result<()> {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    runtime.block_on(up(args))
}

async fn up(args: UpArgs) -> anyhow::Result<()> {
    std::fs::create_dir_all(&args.data_dir)
        .with_context(|| format!("creating {}", args.data_dir.display()))?;
    let data_dir = args.data_dir.canonicalize()?;
    let mut config =
        super::common::with_engine_checks(CoordinatorConfig::local(&data_dir.join("coordinator")));
    config.listen = args.listen;
    let coordinator = Coordinator::start(config)
        .await
        .with_context(|| format!("starting the coordinator on {}", args.listen))?;
    let endpoint = coordinator.endpoint();

    let exe = std::env::current_exe().context("locating the stylenerf executable")?;
    let mut workers = Vec::with_capacity(args.workers);
    for i in 0..args.workers {
        match spawn_worker(&exe, &endpoint, &data_dir, i, &args.worker_args) {
            Ok(child) => workers.push(child),
            Err(e) => {
                stop_workers(&mut workers).await;
                coordinator.shutdown().await?;
                return Err(e);
            }
        }
    }

    println!("coordinator: {endpoint} (data in {})", data_dir.display());
    println!("workers: {} processes", workers.len());
    println!("submit a job from another terminal:");
    println!("  export STYLENERF_ENDPOINT={endpoint}");
    println!("  stylenerf submit --data SCENE_DIR --style STYLE.png --preset quick --wait");
    println!("  stylenerf list; stylenerf watch JOB; stylenerf fetch JOB --out out/");
    println!("Ctrl-C stops the workers (they checkpoint) and then the coordinator.");

    let mut tick = tokio::time::interval(Duration::from_secs(1));
    loop {
        tokio::select! {
            _ = shutdown_signal() => break,
            _ = tick.tick() => report_exits(&mut workers),
        }
    }
    eprintln!("stopping {} workers", workers.len());
    stop_workers(&mut workers).await;
    eprintln!("stopping the coordinator");
    coordinator.shutdown().await
}

/// Starts worker `index` as a child process of this executable.
fn spawn_worker(
    exe: &Path,
    endpoint: &str,
    data_dir: &Path,
    index: usize,
    extra: &[String],
) -> anyhow::Result<(String, Child)> {
    let name = format!("local-{index}");
    let mut command = Command::new(exe);
    command
        .arg("worker")
        .args(["--endpoint", endpoint, "--name", &name, "--scratch-dir"])
        .arg(data_dir.join("workers").join(&name))
        .args(extra);
    // Their own process group: Ctrl-C in the terminal reaches only `up`, which then asks every
    // worker once to stop (a second signal would make a worker exit without checkpointing).
    #[cfg(unix)]
    std::os::unix::process::CommandExt::process_group(&mut command, 0);
    let child = command
        .spawn()
        .with_context(|| format!("starting worker {name} ({})", exe.display()))?;
    Ok((name, child))
}

/// Says so when a worker process exited on its own.
fn report_exits(workers: &mut Vec<(String, Child)>) {
    workers.retain_mut(|(name, child)| match child.try_wait() {
        Ok(Some(status)) => {
            eprintln!("worker {name} exited ({status})");
            false
        }
        _ => true,
    });
}

/// Asks every worker to stop (SIGTERM: checkpoint and release), waits for them, and kills the
/// ones still running after [`WORKER_STOP_TIMEOUT`].
async fn stop_workers(workers: &mut Vec<(String, Child)>) {
    for (name, child) in workers.iter_mut() {
        if let Err(e) = terminate(child) {
            eprintln!("worker {name}: {e}");
        }
    }
    let deadline = Instant::now() + WORKER_STOP_TIMEOUT;
    while !workers.is_empty() && Instant::now() < deadline {
        report_exits(workers);
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    for (name, child) in workers.iter_mut() {
        eprintln!("worker {name} did not stop in time; killing it");
        let _ = child.kill();
        let _ = child.wait();
    }
    workers.clear();
}

/// SIGTERM on Unix; elsewhere the process is killed.
fn terminate(child: &mut Child) -> std::io::Result<()> {
    #[cfg(unix)]
    {
        let pid = libc::pid_t::try_from(child.id()).map_err(std::io::Error::other)?;
        // SAFETY: `kill` has no memory-safety preconditions; the pid is our own child's.
        if unsafe { libc::kill(pid, libc::SIGTERM) } != 0 {
            return Err(std::io::Error::last_os_error());
        }
        Ok(())
    }
    #[cfg(not(unix))]
    {
        child.kill()
    }
}
