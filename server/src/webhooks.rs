//! Job webhooks: validating a job's subscription at submission, enqueuing a delivery for each
//! chosen event in the transaction that stores the event (`enqueue`), and the delivery loop,
//! which POSTs each event as proto JSON signed per Standard Webhooks (`webhook-id`,
//! `webhook-timestamp`, `webhook-signature: v1,<base64 HMAC-SHA256>`) and retries failures
//! with growing, jittered delays until `MAX_ATTEMPTS`. Rows in `webhook_deliveries` are the
//! delivery log (`ListWebhookDeliveries`).
//!
//! A webhook URL is a request the coordinator makes on a client's behalf: loopback, private,
//! link-local and unspecified addresses are refused (at submission and again at each delivery,
//! after name resolution) unless the operator allows them with `--webhook-allow-private`.

use crate::errors::{internal, Violation};
use crate::events::{to_pb, EventRow};
use crate::model::now_ms;
use crate::state::Shared;
use base64::Engine;
use hmac::{KeyInit, Mac};
use sqlx::SqliteConnection;
use std::net::IpAddr;
use std::sync::Arc;
use std::time::Duration;
use stylenerf_proto::v1 as pb;
use tonic::Status;

/// Attempts before a delivery is given up.
pub const MAX_ATTEMPTS: i64 = 12;
/// Longest wait for an answer.
const TIMEOUT: Duration = Duration::from_secs(10);

/// A job's subscription as stored.
#[derive(Debug, Clone)]
pub struct NewWebhook {
    pub url: String,
    /// Event kinds as stored in `events.kind`, comma-separated.
    pub kinds: String,
    pub secret: String,
}

/// Whether deliveries may go to this address.
fn public(ip: IpAddr) -> bool {
    match ip {
        IpAddr::V4(v4) => {
            !(v4.is_loopback()
                || v4.is_private()
                || v4.is_link_local()
                || v4.is_unspecified()
                || v4.is_broadcast()
                || v4.octets()[0] == 100 && (v4.octets()[1] & 0xc0) == 64)
        }
        IpAddr::V6(v6) => {
            let segments = v6.segments();
            !(v6.is_loopback()
                || v6.is_unspecified()
                || (segments[0] & 0xfe00) == 0xfc00
                || (segments[0] & 0xffc0) == 0xfe80
                || v6
                    .to_ipv4_mapped()
                    .is_some_and(|v4| !public(IpAddr::V4(v4))))
        }
    }
}

/// Resolves the URL's host and checks every address (unless private ones are allowed).
async fn check_destination(url: &url::Url, allow_private: bool) -> Result<(), String> {
    let host = url.host_str().ok_or("the URL has no host")?;
    let port = url.port_or_known_default().ok_or("the URL has no port")?;
    if allow_private {
        return Ok(());
    }
    let host = host.trim_start_matches('[').trim_end_matches(']');
    let addresses: Vec<IpAddr> = tokio::net::lookup_host((host, port))
        .await
        .map_err(|e| format!("{host}: {e}"))?
        .map(|a| a.ip())
        .collect();
    if addresses.is_empty() {
        return Err(format!("{host} has no address"));
    }
    if let Some(ip) = addresses.iter().find(|ip| !public(**ip)) {
        return Err(format!(
            "{host} resolves to {ip}, a loopback or private address (the operator can allow \
             these with --webhook-allow-private)"
        ));
    }
    Ok(())
}

/// The stored kind of a protocol event kind.
fn kind_name(kind: pb::EventKind) -> Option<&'static str> {
    match kind {
        pb::EventKind::JobCreated => Some(crate::events::JOB_CREATED),
        pb::EventKind::JobState => Some(crate::events::JOB_STATE),
        pb::EventKind::TaskState => Some(crate::events::TASK_STATE),
        pb::EventKind::TaskProgress => Some(crate::events::TASK_PROGRESS),
        pb::EventKind::Unspecified => None,
    }
}

/// Checks a submission's webhook; on success, the subscription to store with a new secret.
pub async fn validate(
    webhook: Option<&pb::Webhook>,
    allow_private: bool,
    violations: &mut Vec<Violation>,
) -> Option<NewWebhook> {
    let webhook = webhook.filter(|w| !w.url.is_empty() || !w.events.is_empty())?;
    let mut kinds = Vec::new();
    for (i, kind) in webhook.events.iter().enumerate() {
        match pb::EventKind::try_from(*kind).ok().and_then(kind_name) {
            Some(name) if !kinds.contains(&name) => kinds.push(name),
            Some(_) => {}
            None => violations.push(Violation::new(
                format!("webhook.events[{i}]"),
                format!("{kind} is not an event kind"),
            )),
        }
    }
    if kinds.is_empty() {
        kinds.push(crate::events::JOB_STATE);
    }
    if webhook.url.len() > 2000 {
        violations.push(Violation::new("webhook.url", "longer than 2000 characters"));
        return None;
    }
    let url = match url::Url::parse(&webhook.url) {
        Ok(url) if matches!(url.scheme(), "http" | "https") => url,
        Ok(url) => {
            violations.push(Violation::new(
                "webhook.url",
                format!("scheme {:?}: expected http or https", url.scheme()),
            ));
            return None;
        }
        Err(e) => {
            violations.push(Violation::new("webhook.url", format!("not a URL: {e}")));
            return None;
        }
    };
    if !url.username().is_empty() || url.password().is_some() {
        violations.push(Violation::new(
            "webhook.url",
            "must not carry credentials (the deliveries are signed instead)",
        ));
        return None;
    }
    if let Err(reason) = check_destination(&url, allow_private).await {
        violations.push(Violation::new("webhook.url", reason));
        return None;
    }
    let mut secret = [0u8; 32];
    if getrandom::fill(&mut secret).is_err() {
        violations.push(Violation::new("webhook", "no randomness for its secret"));
        return None;
    }
    Some(NewWebhook {
        url: url.to_string(),
        kinds: kinds.join(","),
        secret: format!(
            "whsec_{}",
            base64::engine::general_purpose::STANDARD.encode(secret)
        ),
    })
}

/// Stores a job's subscription (in the transaction that inserts the job).
pub async fn subscribe(
    conn: &mut SqliteConnection,
    job_id: &str,
    webhook: &NewWebhook,
) -> Result<(), sqlx::Error> {
    sqlx::query("INSERT INTO job_webhooks (job_id, url, kinds, secret) VALUES (?, ?, ?, ?)")
        .bind(job_id)
        .bind(&webhook.url)
        .bind(&webhook.kinds)
        .bind(&webhook.secret)
        .execute(conn)
        .await?;
    Ok(())
}

/// Queues a delivery for each stored event in `first..=last` that a subscription wants (in the
/// transaction that stored the events).
pub async fn enqueue(
    conn: &mut SqliteConnection,
    first: i64,
    last: i64,
) -> Result<(), sqlx::Error> {
    sqlx::query(
        "INSERT INTO webhook_deliveries (job_id, event_seq, state, next_attempt_at) \
         SELECT e.job_id, e.seq, 'pending', e.at FROM events e \
         JOIN job_webhooks w ON w.job_id = e.job_id \
         WHERE e.seq BETWEEN ? AND ? AND instr(',' || w.kinds || ',', ',' || e.kind || ',') > 0",
    )
    .bind(first)
    .bind(last)
    .execute(conn)
    .await?;
    Ok(())
}

/// `v1,<base64 HMAC-SHA256 of "<id>.<timestamp>.<body>">` under a `whsec_` secret.
pub fn signature(secret: &str, id: &str, timestamp: i64, body: &[u8]) -> String {
    let key = base64::engine::general_purpose::STANDARD
        .decode(secret.trim_start_matches("whsec_"))
        .unwrap_or_default();
    let mut mac =
        hmac::Hmac::<sha2::Sha256>::new_from_slice(&key).expect("HMAC takes any key length");
    mac.update(format!("{id}.{timestamp}.").as_bytes());
    mac.update(body);
    format!(
        "v1,{}",
        base64::engine::general_purpose::STANDARD.encode(mac.finalize().into_bytes())
    )
}

/// Wait before attempt `attempts + 1`: 5 s doubling to an hour, with ±25 % jitter.
fn backoff(attempts: i64) -> Duration {
    let base = 5.0 * 2f64.powi(attempts.clamp(0, 20) as i32);
    let mut jitter = [0u8; 1];
    let _ = getrandom::fill(&mut jitter);
    let factor = 0.75 + 0.5 * f64::from(jitter[0]) / 255.0;
    Duration::from_secs_f64(base.min(3600.0) * factor)
}

#[derive(sqlx::FromRow)]
struct Due {
    id: i64,
    attempts: i64,
    url: String,
    secret: String,
    #[sqlx(flatten)]
    event: EventRow,
}

/// One attempt: `Ok(status)` for an answer (2xx or not), `Err` when there was none.
async fn attempt(client: &reqwest::Client, due: &Due, allow_private: bool) -> Result<u16, String> {
    let url = url::Url::parse(&due.url).map_err(|e| e.to_string())?;
    check_destination(&url, allow_private).await?;
    let body = serde_json::to_vec(&to_pb(due.event.clone())).map_err(|e| e.to_string())?;
    let id = due.id.to_string();
    let timestamp = now_ms() / 1000;
    let response = client
        .post(url)
        .header("content-type", "application/json")
        .header(
            "user-agent",
            concat!("stylenerf/", env!("CARGO_PKG_VERSION")),
        )
        .header("webhook-id", &id)
        .header("webhook-timestamp", timestamp.to_string())
        .header(
            "webhook-signature",
            signature(&due.secret, &id, timestamp, &body),
        )
        .body(body)
        .send()
        .await
        .map_err(|e| {
            let mut text = e.to_string();
            let mut source = std::error::Error::source(&e);
            while let Some(cause) = source {
                text = format!("{text}: {cause}");
                source = cause.source();
            }
            text
        })?;
    Ok(response.status().as_u16())
}

/// Delivers what is due, once.
async fn deliver_due(shared: &Shared, client: &reqwest::Client) -> Result<usize, sqlx::Error> {
    let due: Vec<Due> = sqlx::query_as(
        "SELECT d.id, d.attempts, w.url, w.secret, e.* FROM webhook_deliveries d \
         JOIN job_webhooks w ON w.job_id = d.job_id JOIN events e ON e.seq = d.event_seq \
         WHERE d.state = 'pending' AND d.next_attempt_at <= ? ORDER BY d.id LIMIT 32",
    )
    .bind(now_ms())
    .fetch_all(&shared.db.read)
    .await?;
    let allow_private = shared.config.webhook_allow_private;
    let results = futures::future::join_all(
        due.iter()
            .map(|d| async move { (d, attempt(client, d, allow_private).await) }),
    )
    .await;
    for (d, result) in results {
        let attempts = d.attempts + 1;
        let (status, error) = match &result {
            Ok(status) if (200..300).contains(status) => (*status, String::new()),
            Ok(status) => (*status, format!("answered HTTP {status}")),
            Err(e) => (0, e.chars().take(500).collect()),
        };
        let state = if error.is_empty() {
            "delivered"
        } else if attempts >= MAX_ATTEMPTS {
            "failed"
        } else {
            "pending"
        };
        let now = now_ms();
        sqlx::query(
            "UPDATE webhook_deliveries SET state = ?, attempts = ?, last_status = ?, \
             last_error = ?, next_attempt_at = ?, delivered_at = ? WHERE id = ?",
        )
        .bind(state)
        .bind(attempts)
        .bind(i64::from(status))
        .bind(&error)
        .bind(now + backoff(attempts - 1).as_millis() as i64)
        .bind(if state == "delivered" { now } else { 0 })
        .bind(d.id)
        .execute(&shared.db.write)
        .await?;
        metrics::counter!("stylenerf_webhook_attempts_total", "result" => state).increment(1);
    }
    Ok(due.len())
}

/// Delivers until shutdown: at once while there is work, else every half second.
pub async fn run(shared: Arc<Shared>) {
    // HTTPS uses rustls with ring, as the gRPC server does (an embedding program may have
    // installed a provider already).
    let _ = rustls::crypto::ring::default_provider().install_default();
    let client = match reqwest::Client::builder().timeout(TIMEOUT).build() {
        Ok(client) => client,
        Err(e) => {
            tracing::error!(error = %e, "webhooks disabled: no HTTP client");
            return;
        }
    };
    let mut shutdown = shared.shutdown.clone();
    loop {
        let busy = match deliver_due(&shared, &client).await {
            Ok(n) => n > 0,
            Err(e) => {
                tracing::warn!(error = %e, "webhook deliveries failed");
                false
            }
        };
        if busy {
            continue;
        }
        tokio::select! {
            _ = tokio::time::sleep(Duration::from_millis(500)) => {}
            _ = shutdown.wait_for(|stop| *stop) => return,
        }
    }
}

/// The delivery log of a job the caller may see.
pub async fn deliveries(shared: &Shared, job_id: &str) -> Result<Vec<pb::WebhookDelivery>, Status> {
    #[derive(sqlx::FromRow)]
    struct Row {
        id: i64,
        event_seq: i64,
        kind: String,
        url: String,
        state: String,
        attempts: i64,
        last_status: i64,
        last_error: String,
        next_attempt_at: i64,
        delivered_at: i64,
    }
    let rows: Vec<Row> = sqlx::query_as(
        "SELECT d.id, d.event_seq, e.kind, w.url, d.state, d.attempts, d.last_status, \
             d.last_error, d.next_attempt_at, d.delivered_at FROM webhook_deliveries d \
             JOIN job_webhooks w ON w.job_id = d.job_id JOIN events e ON e.seq = d.event_seq \
             WHERE d.job_id = ? ORDER BY d.id LIMIT 10000",
    )
    .bind(job_id)
    .fetch_all(&shared.db.read)
    .await
    .map_err(internal)?;
    Ok(rows
        .into_iter()
        .map(|r| pb::WebhookDelivery {
            id: r.id as u64,
            event_seq: r.event_seq as u64,
            kind: crate::events::kind_pb(&r.kind) as i32,
            url: r.url,
            next_attempt_at_ms: if r.state == "pending" {
                r.next_attempt_at
            } else {
                0
            },
            state: r.state,
            attempts: r.attempts as u32,
            last_status: r.last_status as u32,
            last_error: r.last_error,
            delivered_at_ms: r.delivered_at,
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn signatures_follow_standard_webhooks() {
        // The example of the Standard Webhooks specification.
        let secret = "whsec_MfKQ9r8GKYqrTwjUPD8ILPZIo2LaLaSw";
        let body = br#"{"test": 2432232314}"#;
        assert_eq!(
            signature(secret, "msg_p5jXN8AQM9LWM0D4loKWxJek", 1614265330, body),
            "v1,g0hM9SsE+OTPJTGt/tmIKtSyZlE3uFJELVlNIOLJ1OE="
        );
    }

    #[test]
    fn private_addresses_are_recognised() {
        for ip in [
            "127.0.0.1",
            "10.1.2.3",
            "192.168.0.1",
            "169.254.169.254",
            "0.0.0.0",
            "::1",
            "fd00::1",
            "::ffff:10.0.0.1",
            "100.64.0.1",
        ] {
            assert!(!public(ip.parse().unwrap()), "{ip}");
        }
        for ip in ["93.184.216.34", "2606:2800:220:1::1"] {
            assert!(public(ip.parse().unwrap()), "{ip}");
        }
    }
}
