//! The StylizedNeRF coordinator: accepts scene + style jobs over gRPC, persists them in SQLite,
//! splits each job into its five stage tasks and leases them to workers, stores inputs and
//! artifacts in an object store, and exposes health, reflection and Prometheus metrics.
//!
//! Embedding: `Coordinator::start(CoordinatorConfig::local(dir))` returns a handle with
//! `local_addr()`, `endpoint()` and `shutdown()`.

mod api;
pub mod auth;
mod backup;
pub mod bench;
pub mod config;
mod coordinator;
mod db;
pub mod errors;
mod events;
mod http_download;
mod inputs;
mod jobs;
pub mod metrics_http;
mod model;
mod photos;
mod quotas;
mod retention;
mod rpc_metrics;
mod scheduler;
mod state;
pub mod storage;
mod upload_sessions;
pub mod validation;
mod web;
mod webhooks;
mod writer;

pub use api::job_api::CAMERA_PATH_KINDS;
pub use auth::{AuthConfig, Role, TokenEntry};
pub use config::{
    ArtifactUrls, CoordinatorArgs, CoordinatorConfig, EngineChecks, Limits, Quota, Quotas,
    TlsConfig,
};
pub use coordinator::{Coordinator, CoordinatorHandle};
pub use stylenerf_proto as proto;
