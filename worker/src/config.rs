//! The worker's settings ([`WorkerConfig`]) and the command-line flags that build them
//! ([`WorkerArgs`], shared by `stylenerf worker` and the `stylenerf-worker` binary); every flag
//! can also be given as a `STYLENERF_*` environment variable.

use std::path::PathBuf;
use std::time::Duration;

use clap::Args;

/// Everything a worker needs to run.
#[derive(Debug, Clone)]
pub struct WorkerConfig {
    /// Coordinator URL, `http://host:port` or `https://host:port`.
    pub endpoint: String,
    /// Worker (or admin) token; `None` for a coordinator without authentication.
    pub token: Option<String>,
    /// PEM certificate of the CA that signed the coordinator's certificate (TLS).
    pub ca_cert: Option<PathBuf>,
    /// Name shown to operators.
    pub name: String,
    /// Reuse this worker id (after a restart); `None` = a new id.
    pub worker_id: Option<String>,
    /// `cpu`, `cuda` or `cuda:N`.
    pub device: String,
    /// Memory budget for tasks in bytes (0 = no limit): a task is only leased when its memory
    /// estimate fits what the running tasks leave.
    pub memory_bytes: u64,
    /// Labels matched against the jobs' required labels (`zone=eu`, …).
    pub labels: Vec<String>,
    /// Tasks run at once.
    pub max_tasks: usize,
    /// Checkpoint every this many steps (0: by time only).
    pub checkpoint_every_steps: u64,
    /// Checkpoint when this much time passed since the last one.
    pub checkpoint_every: Option<Duration>,
    /// How often new local checkpoints are uploaded.
    pub checkpoint_upload_every: Duration,
    /// Longest `LeaseTask` long-poll (the coordinator caps it too).
    pub lease_wait: Duration,
    /// Per-task scratch folders go here; `None` = a folder in the system temp dir.
    pub scratch_dir: Option<PathBuf>,
    /// Keep each task's scratch folder after it ends (debugging).
    pub keep_scratch: bool,
    /// VGG encoder weights for the 2D stages (any format `weights import` reads); `None` =
    /// the bundled VGG-16.
    pub encoder: Option<PathBuf>,
}

impl WorkerConfig {
    /// Defaults for a worker of `endpoint`: CPU, no memory limit, one task at a time,
    /// checkpoints every 500 steps or 60 s.
    pub fn new(endpoint: impl Into<String>) -> Self {
        Self {
            endpoint: endpoint.into(),
            token: None,
            ca_cert: None,
            name: default_name(),
            worker_id: None,
            device: "cpu".into(),
            memory_bytes: 0,
            labels: Vec::new(),
            max_tasks: 1,
            checkpoint_every_steps: 500,
            checkpoint_every: Some(Duration::from_secs(60)),
            checkpoint_upload_every: Duration::from_secs(1),
            lease_wait: Duration::from_secs(20),
            scratch_dir: None,
            keep_scratch: false,
            encoder: None,
        }
    }
}

fn default_name() -> String {
    std::env::var("HOSTNAME")
        .ok()
        .filter(|h| !h.is_empty())
        .or_else(|| {
            std::fs::read_to_string("/etc/hostname")
                .ok()
                .map(|h| h.trim().to_string())
                .filter(|h| !h.is_empty())
        })
        .unwrap_or_else(|| "worker".into())
}

/// `stylenerf worker` flags.
#[derive(Debug, Clone, Args)]
pub struct WorkerArgs {
    /// Coordinator URL.
    #[arg(
        long,
        env = "STYLENERF_ENDPOINT",
        default_value = "http://127.0.0.1:50051"
    )]
    pub endpoint: String,
    /// Worker token (role `worker`), sent as `authorization: Bearer <token>`.
    #[arg(long, env = "STYLENERF_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    /// PEM certificate of the CA that signed the coordinator's TLS certificate (https
    /// endpoints).
    #[arg(long, env = "STYLENERF_CA_CERT")]
    pub ca_cert: Option<PathBuf>,
    /// Worker name shown to operators (default: the host name).
    #[arg(long, env = "STYLENERF_WORKER_NAME")]
    pub name: Option<String>,
    /// Reuse a worker id from a previous run (default: register a new one).
    #[arg(long, env = "STYLENERF_WORKER_ID")]
    pub worker_id: Option<String>,
    /// Compute device: cpu, cuda or cuda:N.
    #[arg(long, env = "STYLENERF_DEVICE", default_value = "cpu")]
    pub device: String,
    /// Memory budget for tasks in MiB (device memory on CUDA); 0 = no limit. Tasks whose
    /// estimate does not fit what the running tasks leave are not leased.
    #[arg(long, env = "STYLENERF_MEMORY_MIB", default_value_t = 0)]
    pub memory_mib: u64,
    /// Labels offered to jobs that require them, e.g. `--label zone=eu` (repeatable, or
    /// comma-separated in the variable).
    #[arg(long = "label", env = "STYLENERF_LABELS", value_delimiter = ',')]
    pub labels: Vec<String>,
    /// Tasks to run at once.
    #[arg(long, env = "STYLENERF_MAX_TASKS", default_value_t = 1)]
    pub max_tasks: usize,
    /// Checkpoint every N training steps (0: by time only).
    #[arg(long, env = "STYLENERF_CHECKPOINT_EVERY_STEPS", default_value_t = 500)]
    pub checkpoint_every_steps: u64,
    /// Also checkpoint when this many seconds passed since the last checkpoint (0: by steps
    /// only).
    #[arg(long, env = "STYLENERF_CHECKPOINT_EVERY_SECS", default_value_t = 60)]
    pub checkpoint_every_secs: u64,
    /// Longest LeaseTask long-poll in seconds.
    #[arg(long, env = "STYLENERF_LEASE_WAIT_SECS", default_value_t = 20)]
    pub lease_wait_secs: u64,
    /// Folder for per-task scratch space (inputs, outputs, checkpoints); default: the system
    /// temp dir.
    #[arg(long, env = "STYLENERF_SCRATCH_DIR")]
    pub scratch_dir: Option<PathBuf>,
    /// Keep each task's scratch folder after it ends (debugging).
    #[arg(long)]
    pub keep_scratch: bool,
    /// VGG encoder weights for the 2D stages (default: the bundled VGG-16).
    #[arg(long, env = "STYLENERF_ENCODER")]
    pub encoder: Option<PathBuf>,
}

impl WorkerArgs {
    pub fn into_config(self) -> WorkerConfig {
        let mut c = WorkerConfig::new(self.endpoint);
        c.token = self.token.filter(|t| !t.is_empty());
        c.ca_cert = self.ca_cert;
        if let Some(name) = self.name {
            c.name = name;
        }
        c.worker_id = self.worker_id.filter(|w| !w.is_empty());
        c.device = self.device;
        c.memory_bytes = self.memory_mib.saturating_mul(1 << 20);
        c.labels = self.labels.into_iter().filter(|l| !l.is_empty()).collect();
        c.max_tasks = self.max_tasks.max(1);
        c.checkpoint_every_steps = self.checkpoint_every_steps;
        c.checkpoint_every = (self.checkpoint_every_secs > 0)
            .then(|| Duration::from_secs(self.checkpoint_every_secs));
        c.lease_wait = Duration::from_secs(self.lease_wait_secs.max(1));
        c.scratch_dir = self.scratch_dir;
        c.keep_scratch = self.keep_scratch;
        c.encoder = self.encoder;
        c
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::{CommandFactory, Parser};

    #[derive(Debug, Parser)]
    struct Cli {
        #[command(flatten)]
        worker: WorkerArgs,
    }

    #[test]
    fn flags_build_the_config() {
        Cli::command().debug_assert();
        let cli = Cli::parse_from([
            "w",
            "--endpoint",
            "http://c:1",
            "--memory-mib",
            "512",
            "--label",
            "zone=eu",
            "--label",
            "gpu=a100",
            "--max-tasks",
            "2",
            "--checkpoint-every-secs",
            "0",
        ]);
        let c = cli.worker.into_config();
        assert_eq!(c.endpoint, "http://c:1");
        assert_eq!(c.memory_bytes, 512 << 20);
        assert_eq!(c.labels, ["zone=eu", "gpu=a100"]);
        assert_eq!((c.max_tasks, c.checkpoint_every), (2, None));
    }
}
