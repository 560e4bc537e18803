//! A job's event stream that survives disconnects: `WatchJob` is reopened with the last seen
//! `seq` as `after_seq` (with exponential back-off) when the connection drops or the
//! coordinator restarts, so callers see every event once, in order. The stream ends when the
//! coordinator ends it and the job is then terminal: a job reopened by `RenderJob` replays an
//! earlier terminal event and goes on, so callers should not stop at the first terminal event
//! but at the end of the stream.

use crate::client::Client;
use crate::error::{ClientError, Result};
use crate::names::is_terminal;
use crate::spec::WatchOptions;
use futures::Stream;
use std::pin::Pin;
use std::time::Duration;
use stylenerf_proto::v1 as pb;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::Streaming;

/// Events of one job, ending when the job is terminal (or with an error).
pub type EventStream = Pin<Box<dyn Stream<Item = Result<pb::Event>> + Send + 'static>>;

/// Reconnection attempts in a row before the stream gives up.
const MAX_RECONNECTS: u32 = 8;

/// The pause before reconnection attempt `attempt` (also between upload resumes).
pub(crate) fn backoff(attempt: u32) -> Duration {
    Duration::from_millis(250u64 << attempt.min(5)).min(Duration::from_secs(5))
}

/// Opens the watch (errors such as an unknown job are returned here, not in the stream) and
/// spawns the task that forwards events and reconnects.
pub(crate) async fn watch(
    client: Client,
    job_id: String,
    options: WatchOptions,
) -> Result<EventStream> {
    let stream = client
        .open_watch(&job_id, options.after_seq, options.skip_progress)
        .await?;
    let (tx, rx) = mpsc::channel(64);
    tokio::spawn(forward(client, job_id, options, stream, tx));
    Ok(Box::pin(ReceiverStream::new(rx)))
}

async fn forward(
    client: Client,
    job_id: String,
    options: WatchOptions,
    mut stream: Streaming<pb::Event>,
    tx: mpsc::Sender<Result<pb::Event>>,
) {
    let mut last = options.after_seq;
    let mut failures = 0u32;
    loop {
        let next = tokio::select! {
            next = stream.message() => next,
            _ = tx.closed() => return,
        };
        let mut cause = match next {
            Ok(Some(event)) => {
                failures = 0;
                last = last.max(event.seq);
                if tx.send(Ok(event)).await.is_err() {
                    return;
                }
                continue;
            }
            // The coordinator ends the stream after the terminal event (or after the replay of
            // a terminal job): finished if the job is terminal now, else reconnect.
            Ok(None) => match client.get(&job_id).await {
                Ok(job) if is_terminal(job.state) => return,
                Ok(_) => ClientError::Unreachable {
                    endpoint: client.endpoint().to_string(),
                    reason: "the event stream ended early".into(),
                },
                Err(e) => e,
            },
            Err(status) => ClientError::from_status(status, client.endpoint()),
        };
        loop {
            failures += 1;
            if !cause.is_retryable() || failures > MAX_RECONNECTS {
                let _ = tx.send(Err(cause)).await;
                return;
            }
            tracing::warn!(job = %job_id, error = %cause, attempt = failures, "watch interrupted; reconnecting");
            tokio::select! {
                _ = tokio::time::sleep(backoff(failures)) => {}
                _ = tx.closed() => return,
            }
            match client
                .open_watch(&job_id, last, options.skip_progress)
                .await
            {
                Ok(reopened) => {
                    stream = reopened;
                    break;
                }
                Err(e) => cause = e,
            }
        }
    }
}
