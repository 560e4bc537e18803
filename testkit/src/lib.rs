//! What the service's tests share, written once: coordinators on `127.0.0.1:0` with a real
//! SQLite file and token auth ([`coordinator`]), clients that carry a role's token
//! ([`clients`]), small inputs and their uploads ([`inputs`]), a fake worker that runs stages
//! through the worker APIs without the engine ([`fake_worker`]) and waiting on a condition
//! ([`eventually`]). The coordinator's, the worker's, the client library's and the binary's
//! tests all stand on it; each adds only what is its own (a real worker, processes).
//!
//! Everything is re-exported at the top: tests write `use stylenerf_testkit::*;`.

pub mod clients;
pub mod coordinator;
pub mod fake_worker;
pub mod inputs;

pub use clients::*;
pub use coordinator::*;
pub use fake_worker::*;
pub use inputs::*;
/// The catalogue, for tests that count or list a job's stages.
pub use stylenerf_plan::{Source, Stage};
/// The protocol's messages and the status codes the tests compare with.
pub use stylenerf_proto::v1 as pb;
pub use tonic::Code;

use std::future::Future;
use std::time::{Duration, Instant};

/// Polls `f` every 50 ms until it returns `Some`; panics after `timeout`, naming `what`.
pub async fn eventually<T, F: Future<Output = Option<T>>>(
    what: &str,
    timeout: Duration,
    mut f: impl FnMut() -> F,
) -> T {
    let deadline = Instant::now() + timeout;
    loop {
        if let Some(t) = f().await {
            return t;
        }
        assert!(Instant::now() < deadline, "{what}: not within {timeout:?}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}
