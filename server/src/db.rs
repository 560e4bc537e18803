//! SQLite access: opens the database in WAL mode with the migrations of `migrations/` applied,
//! as one single-connection pool for writes (SQLite allows one writer; serialising writes in
//! the process avoids busy retries; the group-commit `writer` and the rare other writes share
//! it) and a small pool of read-only connections, so reads never wait for the writer.
//!
//! A write connection is only reused when it is outside any transaction. SQLite rolls a
//! transaction back by itself on some errors (a full disk, an I/O error), and sqlx then fails
//! to roll it back again and keeps counting it as open; its next transaction would become a
//! savepoint whose commit never reaches the disk. Such a connection is closed on release and a
//! fresh one opened instead (see [`clean_after_release`]).

use sqlx::sqlite::{SqliteConnectOptions, SqliteJournalMode, SqlitePoolOptions, SqliteSynchronous};
use sqlx::{Connection, SqliteConnection, SqlitePool};
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
            .after_release(|conn, _| Box::pin(clean_after_release(conn)))
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

/// Whether a released write connection may be reused: true only when no transaction is left
/// open (after the rollback a dropped transaction queued has run).
async fn clean_after_release(conn: &mut SqliteConnection) -> Result<bool, sqlx::Error> {
    conn.ping().await?;
    let clean = !conn.is_in_transaction();
    if !clean {
        tracing::warn!("closing a write connection left inside a failed transaction");
    }
    Ok(clean)
}
