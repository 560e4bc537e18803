//! Group commit for the hot write paths (create job, lease, heartbeat, complete, fail, reap).
//!
//! SQLite has one writer, and sqlx runs the write connection on its own thread, so every
//! statement, BEGIN and COMMIT is a round trip between a Tokio worker and that thread. RPCs
//! therefore do not open their own transactions: they queue an operation here, and one writer
//! task runs every operation queued at that moment inside a single transaction, appends all
//! their events with one multi-row INSERT, commits, publishes the events and only then replies
//! to each caller. Durability is unchanged: no RPC replies before its changes are committed.
//!
//! If an operation fails with a database error or asks for a rollback ([`OpError::Abort`]), the
//! whole group is rolled back and its operations are run again one by one, each in its own
//! transaction, so one bad request never affects another. Operations must therefore be
//! re-runnable (they are closures that read all their inputs from captured, owned data).
//! The writer task keeps running when a caller goes away (a cancelled RPC): its operation still
//! commits or rolls back as a whole.

use crate::errors::internal;
use crate::events::{commit, publish, EventBatch};
use futures::future::BoxFuture;
use sqlx::{SqliteConnection, SqlitePool};
use stylenerf_proto::v1 as pb;
use tokio::sync::{broadcast, mpsc, oneshot};
use tonic::Status;

/// Most operations committed together.
const MAX_GROUP: usize = 64;

/// Why an operation did not produce a value.
#[derive(Debug)]
pub enum OpError {
    /// A database error: the group is rolled back and the operation retried alone once.
    Db(sqlx::Error),
    /// The operation's changes must not be kept: it is rolled back and the caller gets this
    /// status (when run alone; in a group, everything is retried alone first).
    Abort(Status),
}

impl From<sqlx::Error> for OpError {
    fn from(e: sqlx::Error) -> Self {
        OpError::Db(e)
    }
}

/// An operation's result inside the writer: a value to hand back after the commit.
pub type OpResult<T> = Result<T, OpError>;

/// A queued operation with its type erased.
trait QueuedOp: Send {
    /// Runs the operation in the open transaction and keeps its value.
    fn run<'c>(
        &'c mut self,
        conn: &'c mut SqliteConnection,
        batch: &'c mut EventBatch,
    ) -> BoxFuture<'c, Result<(), OpError>>;
    /// Sends the kept value (after the commit) or the error to the caller.
    fn finish(self: Box<Self>, failure: Option<Status>);
}

struct Typed<T, F> {
    op: F,
    value: Option<T>,
    reply: oneshot::Sender<Result<T, Status>>,
}

impl<T, F> QueuedOp for Typed<T, F>
where
    T: Send + 'static,
    F: for<'c> Fn(&'c mut SqliteConnection, &'c mut EventBatch) -> BoxFuture<'c, OpResult<T>>
        + Send
        + 'static,
{
    fn run<'c>(
        &'c mut self,
        conn: &'c mut SqliteConnection,
        batch: &'c mut EventBatch,
    ) -> BoxFuture<'c, Result<(), OpError>> {
        Box::pin(async move {
            self.value = Some((self.op)(conn, batch).await?);
            Ok(())
        })
    }

    fn finish(self: Box<Self>, failure: Option<Status>) {
        let result = match (failure, self.value) {
            (None, Some(value)) => Ok(value),
            (Some(status), _) => Err(status),
            (None, None) => Err(internal("write operation finished without a value")),
        };
        // The caller may have gone away (cancelled RPC): the work is committed regardless.
        let _ = self.reply.send(result);
    }
}

/// Handle to the writer task.
#[derive(Clone)]
pub struct Writer {
    queue: mpsc::UnboundedSender<Box<dyn QueuedOp>>,
}

impl Writer {
    /// Spawns the writer task on the write pool; committed events go to `events`.
    pub fn spawn(pool: SqlitePool, events: broadcast::Sender<pb::Event>) -> Writer {
        let (queue, rx) = mpsc::unbounded_channel();
        tokio::spawn(run(pool, rx, events));
        Writer { queue }
    }

    /// Runs `op` in the next group transaction and returns its value once committed. Events the
    /// operation pushes to the batch are stored and published with the commit.
    pub async fn write<T, F>(&self, op: F) -> Result<T, Status>
    where
        T: Send + 'static,
        F: for<'c> Fn(&'c mut SqliteConnection, &'c mut EventBatch) -> BoxFuture<'c, OpResult<T>>
            + Send
            + 'static,
    {
        let (reply, answer) = oneshot::channel();
        let op = Box::new(Typed {
            op,
            value: None,
            reply,
        });
        self.queue
            .send(op)
            .map_err(|_| Status::unavailable("the coordinator is shutting down"))?;
        answer
            .await
            .map_err(|_| Status::unavailable("the coordinator is shutting down"))?
    }
}

async fn run(
    pool: SqlitePool,
    mut queue: mpsc::UnboundedReceiver<Box<dyn QueuedOp>>,
    events: broadcast::Sender<pb::Event>,
) {
    let mut ops: Vec<Box<dyn QueuedOp>> = Vec::with_capacity(MAX_GROUP);
    while let Some(first) = queue.recv().await {
        ops.push(first);
        while ops.len() < MAX_GROUP {
            match queue.try_recv() {
                Ok(op) => ops.push(op),
                Err(_) => break,
            }
        }
        metrics::histogram!("stylenerf_write_group_size").record(ops.len() as f64);
        match run_group(&pool, &mut ops).await {
            Ok(batch) => {
                publish(&events, batch);
                for op in ops.drain(..) {
                    op.finish(None);
                }
            }
            Err(error) if ops.len() == 1 => {
                let op = ops.pop().expect("one operation");
                op.finish(Some(status(error)));
            }
            Err(error) => {
                tracing::debug!(
                    ?error,
                    size = ops.len(),
                    "group rolled back; retrying alone"
                );
                for op in ops.drain(..) {
                    let mut single = vec![op];
                    let outcome = run_group(&pool, &mut single).await;
                    let op = single.pop().expect("one operation");
                    match outcome {
                        Ok(batch) => {
                            publish(&events, batch);
                            op.finish(None);
                        }
                        Err(error) => op.finish(Some(status(error))),
                    }
                }
            }
        }
    }
}

/// Runs the operations in one transaction and commits; on any error the transaction is
/// rolled back (dropped) and nothing of the group is kept.
async fn run_group(
    pool: &SqlitePool,
    ops: &mut [Box<dyn QueuedOp>],
) -> Result<EventBatch, OpError> {
    let mut batch = EventBatch::default();
    let mut tx = pool.begin().await?;
    for op in ops.iter_mut() {
        op.run(&mut tx, &mut batch).await?;
    }
    commit(tx, &mut batch).await?;
    Ok(batch)
}

fn status(error: OpError) -> Status {
    match error {
        OpError::Db(e) => internal(e),
        OpError::Abort(status) => status,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::db::Db;

    async fn insert(writer: &Writer, value: &'static str) -> Result<(), Status> {
        writer
            .write(move |conn, _| {
                Box::pin(async move {
                    sqlx::query("INSERT INTO probe (value) VALUES (?)")
                        .bind(value)
                        .execute(&mut *conn)
                        .await?;
                    Ok(())
                })
            })
            .await
    }

    async fn abort(writer: &Writer) -> Result<(), Status> {
        writer
            .write(|conn, _| {
                Box::pin(async move {
                    sqlx::query("INSERT INTO probe (value) VALUES ('aborted')")
                        .execute(&mut *conn)
                        .await?;
                    Err::<(), _>(OpError::Abort(Status::aborted("asked to roll back")))
                })
            })
            .await
    }

    /// SQLite rolls a whole transaction back by itself on a full disk or an I/O error; a
    /// `RAISE(ROLLBACK)` trigger does the same on demand. Every write acknowledged after such a
    /// failure (and after a later rollback that sqlx turns into a savepoint rollback when it
    /// has lost count) must be on disk for a new connection.
    #[tokio::test]
    async fn writes_after_an_automatic_rollback_are_durable() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("coordinator.db");
        let db = Db::open(&path).await.unwrap();
        sqlx::raw_sql(
            "CREATE TABLE probe (value TEXT NOT NULL); \
             CREATE TRIGGER full_disk BEFORE INSERT ON probe WHEN NEW.value = 'full' \
             BEGIN SELECT RAISE(ROLLBACK, 'database or disk is full'); END;",
        )
        .execute(&db.write)
        .await
        .unwrap();
        let (events, _) = broadcast::channel(16);
        let writer = Writer::spawn(db.write.clone(), events);

        insert(&writer, "before").await.unwrap();
        let error = insert(&writer, "full").await.unwrap_err();
        assert!(error.message().contains("disk is full"), "{error:?}");
        assert_eq!(
            abort(&writer).await.unwrap_err().code(),
            tonic::Code::Aborted
        );
        insert(&writer, "after 1").await.unwrap();
        insert(&writer, "after 2").await.unwrap();

        let fresh = Db::open(&path).await.unwrap();
        let stored: Vec<String> = sqlx::query_scalar("SELECT value FROM probe ORDER BY rowid")
            .fetch_all(&fresh.read)
            .await
            .unwrap();
        assert_eq!(stored, ["before", "after 1", "after 2"]);
    }
}
