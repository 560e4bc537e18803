//! The gRPC services: `JobService` for clients, `WorkerService` and `ArtifactService` for
//! workers. Each checks the caller's role, validates arguments and delegates to the domain
//! modules.

pub mod artifact_api;
pub mod job_api;
pub mod worker_api;
