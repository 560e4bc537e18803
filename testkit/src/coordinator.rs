//! Coordinators for tests: one token set for every role (two clients, two worker principals,
//! an operator), a fast reaper, and a start that panics with the reason.

use std::path::Path;
use std::time::Duration;
use stylenerf_server::{
    AuthConfig, Coordinator, CoordinatorConfig, CoordinatorHandle, Role, TokenEntry,
};

pub const ALICE: &str = "client-alice-0123456789";
pub const BOB: &str = "client-bob-0123456789ab";
pub const WORKER: &str = "worker-token-0123456789";
/// A second worker principal (another pool, or an intruder with a worker token).
pub const OTHER_WORKER: &str = "worker-token-b-0123456789";
pub const ADMIN: &str = "admin-token-0123456789a";

/// The tokens of [`ALICE`], [`BOB`], [`WORKER`], [`OTHER_WORKER`] and [`ADMIN`].
pub fn tokens() -> AuthConfig {
    let entry = |role, name: &str, token: &str| TokenEntry {
        role,
        name: name.into(),
        token: token.into(),
    };
    AuthConfig::Tokens(vec![
        entry(Role::Client, "alice", ALICE),
        entry(Role::Client, "bob", BOB),
        entry(Role::Worker, "worker", WORKER),
        entry(Role::Worker, "other-worker", OTHER_WORKER),
        entry(Role::Admin, "root", ADMIN),
    ])
}

/// A coordinator under `dir` (SQLite file, local store) on `127.0.0.1:0`: token auth, a reaper
/// every 50 ms, lease polls of at most 5 s.
pub fn config(dir: &Path) -> CoordinatorConfig {
    let mut config = CoordinatorConfig::local(dir);
    config.auth = tokens();
    config.reaper_interval = Duration::from_millis(50);
    config.max_lease_wait = Duration::from_secs(5);
    config
}

pub async fn start(config: CoordinatorConfig) -> CoordinatorHandle {
    Coordinator::start(config)
        .await
        .expect("coordinator starts")
}
