//! The state shared by the services and background tasks of one coordinator: database,
//! storage, configuration, the live event feed, the "tasks became ready" notifier for
//! long-polling workers, the group-commit writer, the shutdown signal, the bound on concurrent
//! input validations, and the upload sessions in use.

use crate::config::CoordinatorConfig;
use crate::db::Db;
use crate::events::EventBatch;
use crate::storage::Storage;
use crate::writer::Writer;
use std::collections::HashMap;
use std::sync::atomic::AtomicI64;
use std::sync::Mutex;
use stylenerf_proto::v1 as pb;
use tokio::sync::{broadcast, watch, Notify, Semaphore};

pub struct Shared {
    pub db: Db,
    /// Group-commit queue of the hot write paths.
    pub writer: Writer,
    pub storage: Storage,
    pub config: CoordinatorConfig,
    /// Every committed event, for live `WatchJob` streams.
    pub events: broadcast::Sender<pb::Event>,
    /// Woken when tasks become ready, so waiting `LeaseTask` calls retry at once.
    pub ready: Notify,
    /// Becomes `true` when the coordinator shuts down.
    pub shutdown: watch::Receiver<bool>,
    /// When `LeaseTask` next looks for expired leases itself (epoch ms).
    pub next_expiry_check: AtomicI64,
    /// Bounds how many inputs are validated at once (decoding an image takes memory).
    pub validations: Semaphore,
    /// Worker id → the principal that registered it. An id's owner never changes, so this
    /// cache of `workers.owner` spares every heartbeat a database read.
    pub worker_owners: Mutex<HashMap<String, String>>,
    /// Series of the queue gauges set by the last refresh (stage, device class, label set), so
    /// that one whose tasks are all gone is set back to zero rather than left at its last
    /// value (per coordinator: others in the same process keep their own).
    pub queue_series: Mutex<std::collections::BTreeSet<(&'static str, &'static str, String)>>,
    /// The HTTP download endpoint, when the coordinator serves one (`--http-listen`).
    pub downloads: Option<crate::http_download::Downloads>,
    /// Resumable upload sessions being appended to or finished now (one call at a time each).
    pub busy_upload_sessions: Mutex<std::collections::HashSet<String>>,
}

impl Shared {
    /// Publishes the events of a committed transaction.
    pub fn publish(&self, batch: EventBatch) {
        crate::events::publish(&self.events, batch);
    }

    /// Wakes every waiting `LeaseTask` long-poll.
    pub fn wake_workers(&self) {
        self.ready.notify_waiters();
    }

    /// Runs `pass` at once and then every `interval` (a late pass delays the next) until the
    /// coordinator shuts down: the loop of the background sweeps.
    pub async fn every<F, Fut>(&self, interval: std::time::Duration, mut pass: F)
    where
        F: FnMut() -> Fut,
        Fut: std::future::Future<Output = ()>,
    {
        let mut shutdown = self.shutdown.clone();
        let mut tick = tokio::time::interval(interval);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            tokio::select! {
                _ = tick.tick() => {}
                _ = shutdown.wait_for(|stop| *stop) => return,
            }
            pass().await;
        }
    }
}
