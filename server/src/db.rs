//! SQLite access: opens the database in WAL mode with the migrations of `migrations/` applied,
//! as one single-connection pool for writes (SQLite allows one writer; serialising writes in
//! the process avoids busy retries; the group-commit `writer` and the rare other writes share
//! it) and a small pool of read-only connections, so reads never wait for the writer.

use sqlx::sqlite::{SqliteConnectOptions, SqliteJournalMode, SqlitePoolOptions, SqliteSynchronous};
use sqlx::SqlitePool;
use std::path::Path;
use std::time::Duration;

/// The coordinator's database.
#[derive(Clone, Debug)]
pub struct Db {
    /// Every state change goes through this one connection, in a transaction.
    pub write: SqlitePool,
    /// Read-only connections for queries (WAL readers do not block the writer).
    pub read: SqlitePool,
}

impl Db {
    /// Opens (creating if needed) the database file and applies pending migrations.
    pub async fn open(path: &Path) -> anyhow::Result<Db> {
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir)?;
        }
        let options = SqliteConnectOptions::new()
            .filename(path)
            .create_if_missing(true)
            .journal_mode(SqliteJournalMode::Wal)
            // In WAL mode NORMAL survives process crashes (SIGKILL); only an OS crash or power
            // loss can drop the last transactions.
            .synchronous(SqliteSynchronous::Normal)
            .busy_timeout(Duration::from_secs(10))
            .foreign_keys(true);
        // Connections are local and never go stale: skip the ping sqlx would otherwise send
        // (one more round trip to the connection's thread) before every use.
        let write = SqlitePoolOptions::new()
            .test_before_acquire(false)
            .max_connections(1)
            .min_connections(1)
            .connect_with(options.clone())
            .await?;
        sqlx::migrate!("../migrations").run(&write).await?;
        let read = SqlitePoolOptions::new()
            .test_before_acquire(false)
            .max_connections(4)
            .connect_with(options.read_only(true))
            .await?;
        Ok(Db { write, read })
    }

    /// Closes both pools (the file can then be reopened by another coordinator).
    pub async fn close(&self) {
        self.read.close().await;
        self.write.close().await;
    }
}
