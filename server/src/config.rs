//! Coordinator configuration: the `CoordinatorConfig` used by embedders, and the command-line
//! options (`CoordinatorArgs`, flags and environment variables) layered over an optional TOML
//! file. Precedence: flag or environment variable, then the file, then the default.

use crate::auth::{AuthConfig, TokenEntry};
use anyhow::Context;
use serde::Deserialize;
use serde_json::{Map, Value};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;
use stylenerf_plan::DatasetFacts;

/// Everything a coordinator needs to start.
#[derive(Debug, Clone)]
pub struct CoordinatorConfig {
    /// gRPC listen address (port 0 = an ephemeral port, see `CoordinatorHandle::local_addr`).
    pub listen: SocketAddr,
    /// Prometheus `/metrics` listen address; `None` = no metrics endpoint.
    pub metrics_listen: Option<SocketAddr>,
    /// SQLite database file (created with its directory if missing).
    pub database: PathBuf,
    /// Object store: a local directory (plain path or `file://` URL) or, when built with the
    /// `cloud` feature, an `s3://`, `gs://` or `az://` URL.
    pub storage_url: String,
    pub auth: AuthConfig,
    pub tls: Option<TlsConfig>,
    /// Lease duration; each heartbeat extends the lease by this much.
    pub lease_ttl: Duration,
    /// Heartbeat interval suggested to workers (should be well below `lease_ttl`).
    pub heartbeat_interval: Duration,
    /// Longest a `LeaseTask` long-poll waits.
    pub max_lease_wait: Duration,
    /// A task's progress is stored as a `task_progress` event at most this often (the first
    /// progress of each lease always is); heartbeats in between update the task row and reach
    /// live `WatchJob` streams without a stored event. Zero stores every heartbeat's progress.
    pub progress_event_interval: Duration,
    /// Leases per task before the job fails.
    pub max_attempts: u32,
    /// How often expired leases are requeued and gauges refreshed.
    pub reaper_interval: Duration,
    /// A worker not heard from for this long no longer counts as live.
    pub worker_timeout: Duration,
    /// On shutdown, health turns NOT_SERVING at once and calls are still served for this long,
    /// so that load balancers and Kubernetes readiness probes stop sending new calls first.
    pub drain_grace: Duration,
    /// Snapshot the database to the object store this often (`None`: no backups), and once
    /// more at a clean shutdown.
    pub backup_interval: Option<Duration>,
    /// Snapshots kept in the store (the oldest are deleted).
    pub backups_kept: usize,
    /// At start, if the database file does not exist, download the newest snapshot first.
    pub restore_from_backup: bool,
    /// HTTP download endpoint for signed artifact URLs (`GetArtifactUrl`); `None` = none.
    pub http_listen: Option<SocketAddr>,
    /// Base URL clients reach `http_listen` at (default `http://<bound address>`).
    pub public_url: Option<String>,
    /// Secret key of the URL signatures (at least 32 bytes); `None` = a random key per start,
    /// so URLs stop working when the coordinator restarts.
    pub url_signing_key: Option<Vec<u8>>,
    /// Let webhooks reach loopback and private addresses (development, in-cluster receivers).
    pub webhook_allow_private: bool,
    /// Who signs the URLs of `GetArtifactUrl`.
    pub artifact_urls: ArtifactUrls,
    /// Finished jobs and uploads older than this are deleted (objects and rows); `None` keeps
    /// everything.
    pub retention: Option<Duration>,
    /// How often the retention sweep runs.
    pub retention_sweep_interval: Duration,
    /// A resumable upload session unused for this long is deleted with its bytes.
    pub upload_session_ttl: Duration,
    /// What each owner may use at once (running tasks, stored bytes).
    pub quotas: Quotas,
    /// Accepted preset names.
    pub presets: Vec<String>,
    pub limits: Limits,
    /// Directory for upload spool files (default: the system temporary directory).
    pub spool_dir: Option<PathBuf>,
    /// What the workers would refuse, checked at submission: a job's settings and a dataset as
    /// the stages load it. `None` checks only what this crate knows (the overrides form a JSON
    /// object; the archive is safe and its scene file names images it holds). The `stylenerf`
    /// binary installs the engine's checks; this crate does not link the engine.
    pub engine_checks: Option<Arc<dyn EngineChecks>>,
}

/// The checks a coordinator borrows from the engine, so that a submission is refused with what
/// a worker would refuse instead of failing a task after the upload was accepted.
pub trait EngineChecks: Send + Sync {
    /// Every problem of a job's `(preset, overrides)` as `(field, reason)`: the engine's
    /// settings, their types and bounds.
    fn settings(&self, preset: &str, overrides: &Map<String, Value>) -> Vec<(String, String)>;

    /// Why the dataset archive (an uncompressed tar already checked for safety) at `archive`
    /// would not load in a stage, if it would not; else what settings depend on in it. Runs on
    /// a blocking thread.
    fn dataset(&self, archive: &Path) -> Result<DatasetFacts, String>;

    /// What a stage would refuse of a job's `(preset, overrides)`, already found valid by
    /// [`EngineChecks::settings`], on a dataset with these facts, as `(field, reason)`.
    fn dataset_settings(
        &self,
        preset: &str,
        overrides: &Map<String, Value>,
        dataset: &DatasetFacts,
    ) -> Vec<(String, String)>;
}

impl std::fmt::Debug for dyn EngineChecks {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("EngineChecks")
    }
}

/// TLS certificate chain and private key, PEM files.
#[derive(Debug, Clone)]
pub struct TlsConfig {
    pub cert: PathBuf,
    pub key: PathBuf,
}

/// Size and count limits checked at submission.
#[derive(Debug, Clone)]
pub struct Limits {
    /// Largest dataset archive.
    pub max_dataset_bytes: u64,
    /// Largest single archive member.
    pub max_member_bytes: u64,
    /// Most members in an archive.
    pub max_archive_members: u64,
    /// Most camera frames in a scene.
    pub max_frames: u64,
    /// Largest style image file.
    pub max_style_bytes: u64,
    /// Largest style image width or height.
    pub max_style_dimension: u32,
    /// Most styles per job.
    pub max_styles: usize,
    /// Most frames of a stylized render.
    pub max_render_frames: u32,
    /// Largest object a worker may store through `ArtifactService`.
    pub max_object_bytes: u64,
    /// Most unfinished resumable upload sessions per owner.
    pub max_upload_sessions: usize,
}

impl Default for Limits {
    fn default() -> Self {
        const MIB: u64 = 1 << 20;
        Limits {
            max_dataset_bytes: 2048 * MIB,
            max_member_bytes: 512 * MIB,
            max_archive_members: 100_000,
            max_frames: 10_000,
            max_style_bytes: 32 * MIB,
            max_style_dimension: 8192,
            max_styles: 8,
            max_render_frames: 3600,
            max_object_bytes: 4096 * MIB,
            max_upload_sessions: 16,
        }
    }
}

/// Who signs artifact URLs (`--artifact-urls`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum ArtifactUrls {
    /// The object store where it signs URLs (S3, GCS, Azure), else the coordinator.
    #[default]
    Auto,
    /// Always the object store: clients download from it directly (it must sign URLs).
    Store,
    /// Always the coordinator's HTTP endpoint (`--http-listen`), e.g. when clients cannot
    /// reach the store.
    Coordinator,
}

/// One owner's quota; 0 = no limit.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Quota {
    /// Most tasks of the owner's jobs leased at once.
    #[serde(default)]
    pub running_tasks: u32,
    /// Most bytes stored for the owner: uploads, open upload sessions and job outputs.
    #[serde(default, rename = "stored_gib", deserialize_with = "gib_to_bytes")]
    pub stored_bytes: u64,
}

/// `gib` GiB in bytes, if it is zero or positive (`name` names it in the error).
fn gib_bytes(gib: f64, name: &str) -> Result<u64, String> {
    if gib.is_finite() && gib >= 0.0 {
        Ok((gib * (1u64 << 30) as f64) as u64)
    } else {
        Err(format!(
            "{name} must be zero or a positive number, not {gib}"
        ))
    }
}

fn gib_to_bytes<'de, D: serde::Deserializer<'de>>(d: D) -> Result<u64, D::Error> {
    gib_bytes(f64::deserialize(d)?, "stored_gib").map_err(serde::de::Error::custom)
}

/// Per-owner quotas: a default for every owner, and owners of their own.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Quotas {
    pub default: Quota,
    pub owners: std::collections::BTreeMap<String, Quota>,
}

impl Quotas {
    /// The quota of `owner`.
    pub fn of(&self, owner: &str) -> Quota {
        self.owners.get(owner).copied().unwrap_or(self.default)
    }

    /// Whether any owner has a running-task limit (the scheduler then counts).
    pub fn limits_running_tasks(&self) -> bool {
        self.default.running_tasks > 0 || self.owners.values().any(|q| q.running_tasks > 0)
    }
}

impl CoordinatorConfig {
    /// A loopback coordinator for embedding (demo, tests, `stylenerf up`): ephemeral port, no
    /// metrics endpoint, SQLite and artifacts under `data_dir`, authentication disabled.
    pub fn local(data_dir: &Path) -> Self {
        CoordinatorConfig {
            listen: SocketAddr::from(([127, 0, 0, 1], 0)),
            metrics_listen: None,
            database: data_dir.join("coordinator.db"),
            storage_url: data_dir.join("artifacts").display().to_string(),
            auth: AuthConfig::Disabled,
            tls: None,
            lease_ttl: Duration::from_secs(30),
            heartbeat_interval: Duration::from_secs(5),
            max_lease_wait: Duration::from_secs(20),
            progress_event_interval: Duration::from_secs(30),
            max_attempts: 3,
            reaper_interval: Duration::from_secs(1),
            worker_timeout: Duration::from_secs(60),
            drain_grace: Duration::ZERO,
            backup_interval: None,
            http_listen: None,
            public_url: None,
            url_signing_key: None,
            webhook_allow_private: false,
            retention: None,
            retention_sweep_interval: Duration::from_secs(3600),
            upload_session_ttl: Duration::from_secs(24 * 3600),
            quotas: Quotas::default(),
            artifact_urls: ArtifactUrls::Auto,
            backups_kept: 48,
            restore_from_backup: false,
            presets: stylenerf_plan::Preset::ALL
                .iter()
                .map(|p| p.name().to_string())
                .collect(),
            limits: Limits::default(),
            spool_dir: None,
            engine_checks: None,
        }
    }
}

/// Command-line options of `stylenerf coordinator`. Every option can also be set with its
/// environment variable or in the `--config` TOML file (same names with underscores).
#[derive(Debug, Clone, Default, clap::Args)]
pub struct CoordinatorArgs {
    /// TOML file with any of these options (keys as the long flags with `_` for `-`).
    #[arg(long, env = "STYLENERF_CONFIG")]
    pub config: Option<PathBuf>,
    /// gRPC listen address [default: 127.0.0.1:50051].
    #[arg(long, env = "STYLENERF_LISTEN")]
    pub listen: Option<SocketAddr>,
    /// Prometheus metrics listen address, or `off` [default: 127.0.0.1:9464].
    #[arg(long, env = "STYLENERF_METRICS_LISTEN")]
    pub metrics_listen: Option<String>,
    /// SQLite database file [default: stylenerf-data/coordinator.db].
    #[arg(long, env = "STYLENERF_DATABASE")]
    pub database: Option<PathBuf>,
    /// Artifact store: a directory, `file:///dir`, or (with the `cloud` build feature)
    /// `s3://bucket/prefix`, `gs://bucket/prefix`, `az://container/prefix` with credentials
    /// from the usual AWS_*, GOOGLE_*, AZURE_* variables [default: stylenerf-data/artifacts].
    #[arg(long, env = "STYLENERF_STORAGE")]
    pub storage: Option<String>,
    /// File of bearer tokens, one `role:name:token` per line (role: client, worker or admin;
    /// `#` starts a comment).
    #[arg(long, env = "STYLENERF_TOKENS_FILE")]
    pub tokens_file: Option<PathBuf>,
    /// Further tokens, `role:name:token` entries separated by commas or newlines.
    #[arg(long, env = "STYLENERF_TOKENS", hide_env_values = true)]
    pub tokens: Option<String>,
    /// Accept every call without a token, as an admin (local development only).
    #[arg(long, env = "STYLENERF_INSECURE_NO_AUTH")]
    pub insecure_no_auth: bool,
    /// TLS certificate chain (PEM); enables TLS together with --tls-key.
    #[arg(long, env = "STYLENERF_TLS_CERT", requires = "tls_key")]
    pub tls_cert: Option<PathBuf>,
    /// TLS private key (PEM).
    #[arg(long, env = "STYLENERF_TLS_KEY", requires = "tls_cert")]
    pub tls_key: Option<PathBuf>,
    /// Lease duration in seconds; heartbeats extend it [default: 30].
    #[arg(long, env = "STYLENERF_LEASE_TTL")]
    pub lease_ttl: Option<f64>,
    /// Heartbeat interval suggested to workers, in seconds [default: 5].
    #[arg(long, env = "STYLENERF_HEARTBEAT_INTERVAL")]
    pub heartbeat_interval: Option<f64>,
    /// Longest LeaseTask long-poll, in seconds [default: 20].
    #[arg(long, env = "STYLENERF_MAX_LEASE_WAIT")]
    pub max_lease_wait: Option<f64>,
    /// Store a task's progress as an event at most every this many seconds; heartbeats in
    /// between update the task and live watchers only; 0 stores every one [default: 30].
    #[arg(long, env = "STYLENERF_PROGRESS_EVENT_INTERVAL")]
    pub progress_event_interval: Option<f64>,
    /// Leases per task before its job fails [default: 3].
    #[arg(long, env = "STYLENERF_MAX_ATTEMPTS")]
    pub max_attempts: Option<u32>,
    /// On SIGTERM, report NOT_SERVING and keep serving this many seconds before stopping, so
    /// that readiness probes take the coordinator out of rotation first [default: 0].
    #[arg(long, env = "STYLENERF_DRAIN_GRACE")]
    pub drain_grace: Option<f64>,
    /// Snapshot the database into the artifact store (`backups/`) every this many seconds,
    /// and at a clean shutdown; 0 = never [default: 0].
    #[arg(long, env = "STYLENERF_BACKUP_EVERY")]
    pub backup_every: Option<f64>,
    /// Snapshots kept in the store [default: 48].
    #[arg(long, env = "STYLENERF_BACKUPS_KEPT")]
    pub backups_kept: Option<usize>,
    /// If the database file does not exist, start from the newest snapshot in the store.
    #[arg(long, env = "STYLENERF_RESTORE_FROM_BACKUP")]
    pub restore_from_backup: bool,
    /// HTTP address of the download endpoint for signed artifact URLs (`GetArtifactUrl`,
    /// `stylenerf url`), e.g. `0.0.0.0:8080`; unset = no HTTP downloads.
    #[arg(long, env = "STYLENERF_HTTP_LISTEN")]
    pub http_listen: Option<SocketAddr>,
    /// Base URL clients reach the download endpoint at, e.g. `https://stylenerf.example.com`
    /// behind a proxy [default: http://<--http-listen address>].
    #[arg(long, env = "STYLENERF_PUBLIC_URL")]
    pub public_url: Option<String>,
    /// File holding the secret that signs download URLs (at least 32 bytes; keep it to keep
    /// URLs valid across restarts) [default: a random secret per start].
    #[arg(long, env = "STYLENERF_URL_SIGNING_KEY_FILE")]
    pub url_signing_key_file: Option<PathBuf>,
    /// Let job webhooks reach loopback, private and link-local addresses (refused by default:
    /// a webhook is a request the coordinator makes for a client).
    #[arg(long, env = "STYLENERF_WEBHOOK_ALLOW_PRIVATE")]
    pub webhook_allow_private: bool,
    /// Who signs artifact URLs (`GetArtifactUrl`): `auto` (the object store where it can —
    /// S3, GCS, Azure — else this coordinator's HTTP endpoint), `store` or `coordinator`
    /// [default: auto].
    #[arg(long, env = "STYLENERF_ARTIFACT_URLS", value_enum)]
    pub artifact_urls: Option<ArtifactUrls>,
    /// Delete finished jobs (their objects and records) and uploads older than this many days,
    /// checked hourly; 0 = keep everything [default: 0].
    #[arg(long, env = "STYLENERF_RETENTION_DAYS")]
    pub retention_days: Option<f64>,
    /// Delete a resumable upload session (and the bytes it holds) after this many hours
    /// without an append [default: 24].
    #[arg(long, env = "STYLENERF_UPLOAD_SESSION_HOURS")]
    pub upload_session_hours: Option<f64>,
    /// Most tasks of one owner's jobs running at once; 0 = no limit [default: 0]. Owners of
    /// their own: `[quotas.<name>]` in the config file.
    #[arg(long, env = "STYLENERF_MAX_RUNNING_TASKS_PER_OWNER")]
    pub max_running_tasks_per_owner: Option<u32>,
    /// Most GiB stored for one owner (uploads, upload sessions, job outputs); new uploads and
    /// jobs are refused beyond; 0 = no limit [default: 0].
    #[arg(long, env = "STYLENERF_MAX_STORED_GIB_PER_OWNER")]
    pub max_stored_gib_per_owner: Option<f64>,
    /// Accepted preset names, comma-separated [default: tiny,quick,standard,paper].
    #[arg(long, env = "STYLENERF_PRESETS", value_delimiter = ',')]
    pub presets: Option<Vec<String>>,
    /// Largest dataset archive in MiB [default: 2048].
    #[arg(long, env = "STYLENERF_MAX_DATASET_MIB")]
    pub max_dataset_mib: Option<u64>,
    /// Largest style image in MiB [default: 32].
    #[arg(long, env = "STYLENERF_MAX_STYLE_MIB")]
    pub max_style_mib: Option<u64>,
    /// Most styles per job [default: 8].
    #[arg(long, env = "STYLENERF_MAX_STYLES")]
    pub max_styles: Option<usize>,
    /// Directory for upload spool files [default: the system temporary directory].
    #[arg(long, env = "STYLENERF_SPOOL_DIR")]
    pub spool_dir: Option<PathBuf>,
}

/// The `--config` file: the same options as the flags.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct FileConfig {
    listen: Option<SocketAddr>,
    metrics_listen: Option<String>,
    database: Option<PathBuf>,
    storage: Option<String>,
    tokens_file: Option<PathBuf>,
    tokens: Option<String>,
    insecure_no_auth: Option<bool>,
    tls_cert: Option<PathBuf>,
    tls_key: Option<PathBuf>,
    lease_ttl: Option<f64>,
    heartbeat_interval: Option<f64>,
    max_lease_wait: Option<f64>,
    progress_event_interval: Option<f64>,
    max_attempts: Option<u32>,
    drain_grace: Option<f64>,
    backup_every: Option<f64>,
    backups_kept: Option<usize>,
    restore_from_backup: Option<bool>,
    retention_days: Option<f64>,
    upload_session_hours: Option<f64>,
    artifact_urls: Option<ArtifactUrls>,
    max_running_tasks_per_owner: Option<u32>,
    max_stored_gib_per_owner: Option<f64>,
    /// Owners' own quotas, by principal name.
    #[serde(default)]
    quotas: std::collections::BTreeMap<String, Quota>,
    webhook_allow_private: Option<bool>,
    http_listen: Option<SocketAddr>,
    public_url: Option<String>,
    url_signing_key_file: Option<PathBuf>,
    presets: Option<Vec<String>>,
    max_dataset_mib: Option<u64>,
    max_style_mib: Option<u64>,
    max_styles: Option<usize>,
    spool_dir: Option<PathBuf>,
}

impl CoordinatorArgs {
    /// Resolves flags, environment, the config file and defaults into a configuration.
    pub fn into_config(self) -> anyhow::Result<CoordinatorConfig> {
        let file: FileConfig = match &self.config {
            Some(path) => {
                let text = std::fs::read_to_string(path)
                    .with_context(|| format!("reading config file {}", path.display()))?;
                toml::from_str(&text)
                    .with_context(|| format!("parsing config file {}", path.display()))?
            }
            None => FileConfig::default(),
        };
        let data = PathBuf::from("stylenerf-data");
        let mut config = CoordinatorConfig::local(&data);
        config.listen = self
            .listen
            .or(file.listen)
            .unwrap_or_else(|| SocketAddr::from(([127, 0, 0, 1], 50051)));
        let metrics = self
            .metrics_listen
            .or(file.metrics_listen)
            .unwrap_or_else(|| "127.0.0.1:9464".into());
        config.metrics_listen = if metrics == "off" {
            None
        } else {
            Some(
                metrics
                    .parse()
                    .with_context(|| format!("--metrics-listen {metrics:?}"))?,
            )
        };
        if let Some(db) = self.database.or(file.database) {
            config.database = db;
        }
        if let Some(storage) = self.storage.or(file.storage) {
            config.storage_url = storage;
        }
        let insecure = self.insecure_no_auth || file.insecure_no_auth.unwrap_or(false);
        let mut tokens = Vec::new();
        if let Some(path) = self.tokens_file.or(file.tokens_file) {
            let text = std::fs::read_to_string(&path)
                .with_context(|| format!("reading tokens file {}", path.display()))?;
            tokens.extend(
                TokenEntry::parse_list(&text)
                    .with_context(|| format!("in tokens file {}", path.display()))?,
            );
        }
        if let Some(list) = self.tokens.or(file.tokens) {
            tokens.extend(TokenEntry::parse_list(&list).context("in --tokens")?);
        }
        config.auth = match (insecure, tokens.is_empty()) {
            (true, _) => AuthConfig::Disabled,
            (false, false) => AuthConfig::Tokens(tokens),
            (false, true) => anyhow::bail!(
                "no tokens configured: give --tokens-file or --tokens, or --insecure-no-auth for \
                 local development"
            ),
        };
        config.tls = match (
            self.tls_cert.or(file.tls_cert),
            self.tls_key.or(file.tls_key),
        ) {
            (Some(cert), Some(key)) => Some(TlsConfig { cert, key }),
            (None, None) => None,
            _ => anyhow::bail!("TLS needs both a certificate and a key"),
        };
        config.lease_ttl = seconds(
            self.lease_ttl.or(file.lease_ttl),
            "lease_ttl",
            config.lease_ttl,
            false,
        )?;
        config.heartbeat_interval = seconds(
            self.heartbeat_interval.or(file.heartbeat_interval),
            "heartbeat_interval",
            config.heartbeat_interval,
            false,
        )?;
        config.max_lease_wait = seconds(
            self.max_lease_wait.or(file.max_lease_wait),
            "max_lease_wait",
            config.max_lease_wait,
            false,
        )?;
        config.progress_event_interval = seconds(
            self.progress_event_interval
                .or(file.progress_event_interval),
            "progress_event_interval",
            config.progress_event_interval,
            true,
        )?;
        config.drain_grace = seconds(
            self.drain_grace.or(file.drain_grace),
            "drain_grace",
            config.drain_grace,
            true,
        )?;
        let backup_every = seconds(
            self.backup_every.or(file.backup_every),
            "backup_every",
            Duration::ZERO,
            true,
        )?;
        config.backup_interval = (!backup_every.is_zero()).then_some(backup_every);
        if let Some(n) = self.backups_kept.or(file.backups_kept) {
            anyhow::ensure!(n >= 1, "backups_kept must be at least 1");
            config.backups_kept = n;
        }
        config.restore_from_backup =
            self.restore_from_backup || file.restore_from_backup.unwrap_or(false);
        let retention = seconds(
            self.retention_days
                .or(file.retention_days)
                .map(|d| d * 86_400.0),
            "retention_days",
            Duration::ZERO,
            true,
        )?;
        config.retention = (!retention.is_zero()).then_some(retention);
        if let Some(n) = self
            .max_running_tasks_per_owner
            .or(file.max_running_tasks_per_owner)
        {
            config.quotas.default.running_tasks = n;
        }
        if let Some(gib) = self
            .max_stored_gib_per_owner
            .or(file.max_stored_gib_per_owner)
        {
            config.quotas.default.stored_bytes =
                gib_bytes(gib, "max_stored_gib_per_owner").map_err(anyhow::Error::msg)?;
        }
        config.quotas.owners = file.quotas;
        config.upload_session_ttl = seconds(
            self.upload_session_hours
                .or(file.upload_session_hours)
                .map(|h| h * 3600.0),
            "upload_session_hours",
            config.upload_session_ttl,
            false,
        )?;
        config.webhook_allow_private =
            self.webhook_allow_private || file.webhook_allow_private.unwrap_or(false);
        config.artifact_urls = self
            .artifact_urls
            .or(file.artifact_urls)
            .unwrap_or_default();
        config.http_listen = self.http_listen.or(file.http_listen);
        config.public_url = self.public_url.or(file.public_url);
        if let Some(path) = self.url_signing_key_file.or(file.url_signing_key_file) {
            let key = std::fs::read(&path)
                .with_context(|| format!("reading the URL signing key {}", path.display()))?;
            config.url_signing_key = Some(key);
        }
        if let Some(n) = self.max_attempts.or(file.max_attempts) {
            anyhow::ensure!(n >= 1, "max_attempts must be at least 1");
            config.max_attempts = n;
        }
        if let Some(presets) = self.presets.or(file.presets) {
            config.presets = presets;
        }
        if let Some(mib) = self.max_dataset_mib.or(file.max_dataset_mib) {
            config.limits.max_dataset_bytes = mib << 20;
        }
        if let Some(mib) = self.max_style_mib.or(file.max_style_mib) {
            config.limits.max_style_bytes = mib << 20;
        }
        if let Some(n) = self.max_styles.or(file.max_styles) {
            config.limits.max_styles = n;
        }
        config.spool_dir = self.spool_dir.or(file.spool_dir);
        Ok(config)
    }
}

/// A duration option given in seconds: `default` when unset; a finite positive number (or
/// zero, with `zero_ok`) otherwise.
fn seconds(
    value: Option<f64>,
    name: &str,
    default: Duration,
    zero_ok: bool,
) -> anyhow::Result<Duration> {
    match value {
        None => Ok(default),
        Some(s) if s.is_finite() && (s > 0.0 || (zero_ok && s == 0.0)) => {
            Ok(Duration::from_secs_f64(s))
        }
        Some(s) if zero_ok => {
            anyhow::bail!("{name} must be zero or a positive number of seconds, not {s}")
        }
        Some(s) => anyhow::bail!("{name} must be a positive number of seconds, not {s}"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        args: CoordinatorArgs,
    }

    fn config_from(file: &str, flags: &[&str]) -> anyhow::Result<CoordinatorConfig> {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("coordinator.toml");
        std::fs::write(&path, file).unwrap();
        let path = path.to_str().unwrap();
        let mut argv = vec!["coordinator", "--insecure-no-auth", "--config", path];
        argv.extend(flags);
        Cli::parse_from(argv).args.into_config()
    }

    #[test]
    fn quotas_come_from_flags_and_owners_from_the_file() {
        let file = "max_stored_gib_per_owner = 0.5\n\
                    [quotas.bob]\nrunning_tasks = 8\nstored_gib = 2\n\
                    [quotas.carol]\nrunning_tasks = 1\n";
        let config = config_from(file, &["--max-running-tasks-per-owner", "3"]).unwrap();
        let quotas = &config.quotas;
        assert_eq!(
            quotas.of("alice"),
            Quota {
                running_tasks: 3,
                stored_bytes: 1 << 29
            }
        );
        assert_eq!(
            quotas.of("bob"),
            Quota {
                running_tasks: 8,
                stored_bytes: 2 << 30
            }
        );
        // An owner's own quota replaces the default as a whole: carol stores without limit.
        assert_eq!(quotas.of("carol").stored_bytes, 0);
        assert!(quotas.limits_running_tasks());
        assert!(!Quotas::default().limits_running_tasks());
    }

    #[test]
    fn bad_quotas_are_refused_with_their_name() {
        let err = config_from("[quotas.bob]\nstored_gib = -1\n", &[]).unwrap_err();
        assert!(format!("{err:#}").contains("stored_gib"), "{err:#}");
        let err = config_from("[quotas.bob]\nrunning = 1\n", &[]).unwrap_err();
        assert!(format!("{err:#}").contains("running"), "{err:#}");
        let err = config_from("", &["--max-stored-gib-per-owner", "NaN"]).unwrap_err();
        assert!(
            err.to_string().contains("max_stored_gib_per_owner"),
            "{err:#}"
        );
    }
}
