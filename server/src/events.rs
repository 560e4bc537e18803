//! The job event log: events are appended to the `events` table inside the transaction that
//! causes them, then published to live `WatchJob` streams after the commit; replays read the
//! table. Progress updates between two stored progress events of a task (see
//! `progress_event_interval`) are published live only, with `seq` 0.

use crate::model::{job_state_pb, stage_pb, task_state_pb, StoredProgress};
use sqlx::SqliteConnection;
use stylenerf_proto::v1 as pb;

/// An event about to be appended.
#[derive(Debug, Default)]
pub struct NewEvent<'a> {
    pub job_id: &'a str,
    pub kind: &'static str,
    pub task_id: i64,
    pub stage: &'a str,
    pub job_state: &'a str,
    pub task_state: &'a str,
    pub attempt: i64,
    pub progress: Option<&'a StoredProgress>,
    pub message: &'a str,
}

pub const JOB_CREATED: &str = "job_created";
pub const JOB_STATE: &str = "job_state";
pub const TASK_STATE: &str = "task_state";
pub const TASK_PROGRESS: &str = "task_progress";

impl<'a> NewEvent<'a> {
    pub fn job(job_id: &'a str, kind: &'static str, state: &'a str, message: &'a str) -> Self {
        NewEvent {
            job_id,
            kind,
            job_state: state,
            message,
            ..Default::default()
        }
    }

    pub fn task(
        job_id: &'a str,
        task_id: i64,
        stage: &'a str,
        state: &'a str,
        attempt: i64,
        message: &'a str,
    ) -> Self {
        NewEvent {
            job_id,
            kind: TASK_STATE,
            task_id,
            stage,
            task_state: state,
            attempt,
            message,
            ..Default::default()
        }
    }
}

/// Events of one transaction: collected while it runs, appended to the log with one
/// multi-row INSERT just before it commits, published after.
#[derive(Debug, Default)]
pub struct EventBatch {
    pending: Vec<EventRow>,
    pub events: Vec<pb::Event>,
}

impl EventBatch {
    /// Adds an event to the transaction's batch.
    pub fn push(&mut self, event: NewEvent<'_>) {
        self.pending.push(EventRow::from_new(event));
    }

    /// Adds an event that is published to live watchers after the commit but not stored (a
    /// throttled progress update); it carries `seq` 0.
    pub fn push_live(&mut self, event: NewEvent<'_>) {
        let mut row = EventRow::from_new(event);
        row.seq = 0;
        self.events.push(to_pb(row));
    }

    /// Appends the pending events to the log (inside the caller's transaction).
    async fn flush(&mut self, conn: &mut SqliteConnection) -> Result<(), sqlx::Error> {
        for chunk in std::mem::take(&mut self.pending).chunks(100) {
            let mut insert = sqlx::QueryBuilder::<sqlx::Sqlite>::new(
                "INSERT INTO events (job_id, at, kind, task_id, stage, job_state, task_state, \
                 attempt, progress, message) ",
            );
            insert.push_values(chunk, |mut row, e| {
                row.push_bind(e.job_id.clone())
                    .push_bind(e.at)
                    .push_bind(e.kind.clone())
                    .push_bind(e.task_id)
                    .push_bind(e.stage.clone())
                    .push_bind(e.job_state.clone())
                    .push_bind(e.task_state.clone())
                    .push_bind(e.attempt)
                    .push_bind(e.progress.clone())
                    .push_bind(e.message.clone());
            });
            insert.push(" RETURNING seq");
            // Rows are numbered in VALUES order; RETURNING order is unspecified.
            let mut seqs: Vec<i64> = insert.build_query_scalar().fetch_all(&mut *conn).await?;
            seqs.sort_unstable();
            if let (Some(first), Some(last)) = (seqs.first(), seqs.last()) {
                crate::webhooks::enqueue(conn, *first, *last).await?;
            }
            for (row, seq) in chunk.iter().zip(seqs) {
                self.events.push(to_pb(EventRow { seq, ..row.clone() }));
            }
        }
        Ok(())
    }
}

/// Appends the batch's events and commits the transaction.
pub async fn commit(
    mut tx: sqlx::Transaction<'_, sqlx::Sqlite>,
    batch: &mut EventBatch,
) -> Result<(), sqlx::Error> {
    batch.flush(&mut tx).await?;
    tx.commit().await
}

/// A row of the `events` table.
#[derive(Debug, Clone, sqlx::FromRow)]
pub struct EventRow {
    pub seq: i64,
    pub job_id: String,
    pub at: i64,
    pub kind: String,
    pub task_id: i64,
    pub stage: String,
    pub job_state: String,
    pub task_state: String,
    pub attempt: i64,
    pub progress: String,
    pub message: String,
}

impl EventRow {
    /// The row of a new event (its `seq` is assigned by the INSERT).
    fn from_new(event: NewEvent<'_>) -> EventRow {
        EventRow {
            seq: 0,
            job_id: event.job_id.to_string(),
            at: crate::model::now_ms(),
            kind: event.kind.to_string(),
            task_id: event.task_id,
            stage: event.stage.to_string(),
            job_state: event.job_state.to_string(),
            task_state: event.task_state.to_string(),
            attempt: event.attempt,
            progress: event
                .progress
                .map(StoredProgress::to_json)
                .unwrap_or_default(),
            message: event.message.to_string(),
        }
    }
}

/// Sends committed (and live-only) events to the live `WatchJob` streams.
pub fn publish(sender: &tokio::sync::broadcast::Sender<pb::Event>, batch: EventBatch) {
    for event in batch.events {
        // No receiver is fine: nobody is watching.
        let _ = sender.send(event);
    }
}

/// The protocol enum of a stored event kind.
pub fn kind_pb(kind: &str) -> pb::EventKind {
    match kind {
        JOB_CREATED => pb::EventKind::JobCreated,
        JOB_STATE => pb::EventKind::JobState,
        TASK_STATE => pb::EventKind::TaskState,
        TASK_PROGRESS => pb::EventKind::TaskProgress,
        _ => pb::EventKind::Unspecified,
    }
}

pub fn to_pb(row: EventRow) -> pb::Event {
    let kind = kind_pb(&row.kind);
    pb::Event {
        seq: row.seq as u64,
        job_id: row.job_id,
        at_ms: row.at,
        kind: kind as i32,
        task_id: row.task_id as u64,
        stage: stage_pb(&row.stage),
        job_state: job_state_pb(&row.job_state),
        task_state: task_state_pb(&row.task_state),
        attempt: row.attempt as u32,
        progress: (!row.progress.is_empty()).then(|| StoredProgress::parse(&row.progress).to_pb()),
        message: row.message,
    }
}

/// Events of a job after `after_seq`, oldest first, at most `limit`.
pub async fn read_after(
    pool: &sqlx::SqlitePool,
    scope: &Scope,
    after_seq: i64,
    limit: i64,
) -> Result<Vec<pb::Event>, sqlx::Error> {
    let query = match scope {
        Scope::Job(_) => {
            "SELECT e.seq, e.job_id, e.at, e.kind, e.task_id, e.stage, e.job_state, e.task_state, \
             e.attempt, e.progress, e.message FROM events e \
             WHERE e.job_id = ? AND e.seq > ? ORDER BY e.seq LIMIT ?"
        }
        Scope::Owner(_) => {
            "SELECT e.seq, e.job_id, e.at, e.kind, e.task_id, e.stage, e.job_state, e.task_state, \
             e.attempt, e.progress, e.message FROM events e JOIN jobs j ON j.id = e.job_id \
             WHERE j.owner = ? AND e.seq > ? ORDER BY e.seq LIMIT ?"
        }
        Scope::All => {
            "SELECT e.seq, e.job_id, e.at, e.kind, e.task_id, e.stage, e.job_state, e.task_state, \
             e.attempt, e.progress, e.message FROM events e \
             WHERE ? = '' AND e.seq > ? ORDER BY e.seq LIMIT ?"
        }
    };
    let key = match scope {
        Scope::Job(id) => id.as_str(),
        Scope::Owner(owner) => owner.as_str(),
        Scope::All => "",
    };
    let rows: Vec<EventRow> = sqlx::query_as(query)
        .bind(key)
        .bind(after_seq)
        .bind(limit)
        .fetch_all(pool)
        .await?;
    Ok(rows.into_iter().map(to_pb).collect())
}

/// Whose events a watch follows.
#[derive(Debug, Clone)]
pub enum Scope {
    /// One job (the stream ends with it).
    Job(String),
    /// Every job of one owner.
    Owner(String),
    /// Every job (admins).
    All,
}
