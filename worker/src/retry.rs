//! Retrying calls to the coordinator through a short outage. A stage's finished work must not
//! be thrown away because the coordinator restarted while its outputs were being uploaded or
//! its completion reported: transient failures (the coordinator unreachable or overloaded)
//! are retried with jittered exponential backoff for about a minute — a lease outlives an
//! outage shorter than its TTL — while answers that retrying cannot change (a stale lease,
//! a refused request) come back at once. Registering and leasing wait without a deadline
//! ([`patient`]): a worker started before its coordinator waits for it.

use std::future::Future;
use std::time::Duration;

use backon::{ExponentialBuilder, Retryable};
use tonic::{Code, Status};

/// The backoff between attempts: 0.25 s doubling to 8 s, with jitter, 10 retries (about a
/// minute in all).
fn policy() -> ExponentialBuilder {
    ExponentialBuilder::default()
        .with_min_delay(Duration::from_millis(250))
        .with_max_delay(Duration::from_secs(8))
        .with_max_times(10)
        .with_jitter()
}

/// The backoff while waiting for the coordinator without a deadline (registering at start-up,
/// the lease loop): 0.5 s doubling to 30 s, jittered so that a fleet of workers does not knock
/// in step, never giving up.
pub fn patient() -> ExponentialBuilder {
    ExponentialBuilder::default()
        .with_min_delay(Duration::from_millis(500))
        .with_max_delay(Duration::from_secs(30))
        .without_max_times()
        .with_jitter()
}

/// Whether a failed call may succeed if made again unchanged.
pub fn is_transient(status: &Status) -> bool {
    matches!(
        status.code(),
        Code::Unavailable | Code::DeadlineExceeded | Code::ResourceExhausted | Code::Aborted
    ) || (status.code() == Code::Unknown && status.message().contains("transport"))
}

/// Runs `call` until it succeeds, fails for good, or the retries run out; `what` names the
/// call in the log.
pub async fn with_retries<T, F, Fut>(what: &str, call: F) -> Result<T, Status>
where
    F: FnMut() -> Fut,
    Fut: Future<Output = Result<T, Status>>,
{
    call.retry(policy())
        .when(is_transient)
        .notify(|status, delay| {
            tracing::warn!(
                call = what,
                code = ?status.code(),
                error = status.message(),
                retry_in = ?delay,
                "coordinator call failed; retrying"
            );
        })
        .await
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicU32, Ordering};

    #[tokio::test(start_paused = true)]
    async fn transient_failures_are_retried_and_others_are_not() {
        let calls = AtomicU32::new(0);
        let result = with_retries("test", || async {
            match calls.fetch_add(1, Ordering::SeqCst) {
                0..=2 => Err(Status::unavailable("coordinator restarting")),
                n => Ok(n),
            }
        })
        .await;
        assert_eq!(result.unwrap(), 3);

        let calls = AtomicU32::new(0);
        let result: Result<(), _> = with_retries("test", || async {
            calls.fetch_add(1, Ordering::SeqCst);
            Err(Status::failed_precondition("stale lease"))
        })
        .await;
        assert_eq!(result.unwrap_err().code(), Code::FailedPrecondition);
        assert_eq!(calls.load(Ordering::SeqCst), 1);

        let calls = AtomicU32::new(0);
        let result: Result<(), _> = with_retries("test", || async {
            calls.fetch_add(1, Ordering::SeqCst);
            Err(Status::unavailable("down for good"))
        })
        .await;
        assert!(result.is_err());
        assert_eq!(calls.load(Ordering::SeqCst), 11);
    }
}
