//! Backups of the coordinator's SQLite database to the object store, and restore at start.
//!
//! One coordinator owns one database file. To survive the loss of its machine or volume, it
//! can snapshot the database every `backup_interval` (`VACUUM INTO`: a consistent copy taken
//! by a reader while the coordinator keeps serving) and once more at a clean shutdown, upload
//! it as `backups/coordinator-<epoch ms>.db` beside the artifacts, and keep the newest
//! `backups_kept`. A coordinator started with `restore_from_backup` and no database file
//! downloads the newest snapshot first. What was written after that snapshot is lost (the
//! recovery point is one interval; docs/OPERATIONS.md says what that means for jobs).

use crate::state::Shared;
use crate::storage::Storage;
use std::path::Path;
use std::sync::Arc;

/// Where snapshots live in the store.
const PREFIX: &str = "backups/";

fn key(taken_at_ms: i64) -> String {
    format!("{PREFIX}coordinator-{taken_at_ms:013}.db")
}

/// Snapshots of the database in the store, oldest first.
async fn snapshots(storage: &Storage) -> anyhow::Result<Vec<String>> {
    let mut keys: Vec<String> = storage
        .list(PREFIX)
        .await?
        .into_iter()
        .map(|(key, _)| key)
        .filter(|key| key.ends_with(".db"))
        .collect();
    keys.sort();
    Ok(keys)
}

/// Takes a snapshot, uploads it and prunes old ones; returns its key.
pub async fn snapshot(shared: &Shared) -> anyhow::Result<String> {
    let dir = tempfile::tempdir_in(
        shared
            .config
            .database
            .parent()
            .filter(|d| !d.as_os_str().is_empty())
            .unwrap_or(Path::new(".")),
    )?;
    let file = dir.path().join("snapshot.db");
    let path = file
        .to_str()
        .ok_or_else(|| anyhow::anyhow!("snapshot path {} is not UTF-8", file.display()))?;
    sqlx::query("VACUUM INTO ?")
        .bind(path)
        .execute(&shared.db.read)
        .await?;
    let key = key(crate::model::now_ms());
    shared.storage.put_file(&key, &file).await?;
    let keys = snapshots(&shared.storage).await?;
    let excess = keys.len().saturating_sub(shared.config.backups_kept.max(1));
    for old in &keys[..excess] {
        shared.storage.delete(old).await?;
    }
    Ok(key)
}

/// Snapshots every `interval` until shutdown (failures are logged and retried next time).
pub async fn run(shared: Arc<Shared>, interval: std::time::Duration) {
    let mut shutdown = shared.shutdown.clone();
    let mut tick = tokio::time::interval(interval);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    tick.tick().await;
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            _ = shutdown.wait_for(|stop| *stop) => return,
        }
        match snapshot(&shared).await {
            Ok(key) => tracing::debug!(%key, "database backed up"),
            Err(e) => tracing::warn!(error = %e, "backing up the database failed"),
        }
    }
}

/// Before the database is opened: if `database` does not exist, downloads the newest snapshot
/// to it. Returns the key restored, or `None` when the file exists or there is no snapshot.
pub async fn restore(storage: &Storage, database: &Path) -> anyhow::Result<Option<String>> {
    if database.exists() {
        return Ok(None);
    }
    let Some(newest) = snapshots(storage).await?.pop() else {
        return Ok(None);
    };
    if let Some(dir) = database.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir)?;
    }
    // A write-ahead log without its database belongs to no snapshot.
    for suffix in ["-wal", "-shm"] {
        let mut stale = database.as_os_str().to_owned();
        stale.push(suffix);
        let _ = std::fs::remove_file(stale);
    }
    let mut partial = database.as_os_str().to_owned();
    partial.push(".restoring");
    let partial = std::path::PathBuf::from(partial);
    storage
        .get_to_file(&newest, &partial)
        .await
        .map_err(|s| anyhow::anyhow!("downloading {newest}: {}", s.message()))?;
    std::fs::File::open(&partial)?.sync_all()?;
    std::fs::rename(&partial, database)?;
    Ok(Some(newest))
}
