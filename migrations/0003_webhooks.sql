-- Webhooks. A job's subscription, set at creation: where its events go, which kinds
-- (comma-separated event kinds as stored in `events.kind`), and the secret that signs them.
CREATE TABLE job_webhooks (
    job_id TEXT PRIMARY KEY,
    url    TEXT NOT NULL,
    kinds  TEXT NOT NULL,
    secret TEXT NOT NULL
);

-- One row per event to deliver, written in the transaction that stores the event, so an
-- acknowledged state change is delivered even across coordinator restarts.
CREATE TABLE webhook_deliveries (
    id              INTEGER PRIMARY KEY,
    job_id          TEXT    NOT NULL,
    event_seq       INTEGER NOT NULL,
    state           TEXT    NOT NULL,             -- pending|delivered|failed
    attempts        INTEGER NOT NULL DEFAULT 0,
    next_attempt_at INTEGER NOT NULL,
    last_status     INTEGER NOT NULL DEFAULT 0,
    last_error      TEXT    NOT NULL DEFAULT '',
    delivered_at    INTEGER NOT NULL DEFAULT 0
);
CREATE INDEX webhook_deliveries_due ON webhook_deliveries (state, next_attempt_at);
CREATE INDEX webhook_deliveries_job ON webhook_deliveries (job_id, id);
