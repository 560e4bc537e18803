-- Initial schema of the coordinator: jobs, their stage tasks and dependencies, workers, the
-- event log that `WatchJob` replays, task output manifests, and validated uploads.
-- Times are Unix epoch milliseconds; JSON columns hold UTF-8 JSON text. Rows are never
-- deleted, so plain INTEGER PRIMARY KEYs (no AUTOINCREMENT bookkeeping) stay increasing.

CREATE TABLE jobs (
    row             INTEGER PRIMARY KEY,
    id              TEXT    NOT NULL UNIQUE,
    owner           TEXT    NOT NULL,
    name            TEXT    NOT NULL,
    state           TEXT    NOT NULL,             -- queued|running|succeeded|failed|cancelled
    preset          TEXT    NOT NULL,
    overrides       TEXT    NOT NULL,             -- JSON object
    require_cuda    INTEGER NOT NULL,
    labels          TEXT    NOT NULL,             -- JSON array of strings
    memory_bytes    INTEGER NOT NULL,
    dataset_key     TEXT    NOT NULL,
    style_keys      TEXT    NOT NULL,             -- JSON array of object keys
    idempotency_key TEXT,
    error           TEXT    NOT NULL DEFAULT '',
    created_at      INTEGER NOT NULL,
    updated_at      INTEGER NOT NULL,
    finished_at     INTEGER NOT NULL DEFAULT 0
);
CREATE UNIQUE INDEX jobs_idempotency ON jobs (owner, idempotency_key)
    WHERE idempotency_key IS NOT NULL;
CREATE INDEX jobs_owner ON jobs (owner, row);

CREATE TABLE tasks (
    id               INTEGER PRIMARY KEY,
    job_id           TEXT    NOT NULL REFERENCES jobs (id),
    stage            TEXT    NOT NULL,
    state            TEXT    NOT NULL,            -- pending|ready|leased|succeeded|failed|cancelled
    core             INTEGER NOT NULL,            -- 1: one of the five stages; 0: a further render
    config           TEXT    NOT NULL,            -- JSON object handed to the worker
    memory_bytes     INTEGER NOT NULL,
    output_prefix    TEXT    NOT NULL,
    attempt          INTEGER NOT NULL DEFAULT 0,
    max_attempts     INTEGER NOT NULL,
    fencing_token    INTEGER NOT NULL DEFAULT 0,  -- incremented by every lease
    worker_id        TEXT    NOT NULL DEFAULT '',
    lease_expires_at INTEGER NOT NULL DEFAULT 0,
    leased_at        INTEGER NOT NULL DEFAULT 0,
    progress         TEXT    NOT NULL DEFAULT '{}',
    error            TEXT    NOT NULL DEFAULT '',
    ready_at         INTEGER NOT NULL DEFAULT 0,
    created_at       INTEGER NOT NULL,
    started_at       INTEGER NOT NULL DEFAULT 0,
    finished_at      INTEGER NOT NULL DEFAULT 0
);
CREATE INDEX tasks_job ON tasks (job_id, id);
CREATE INDEX tasks_ready ON tasks (state, ready_at);
CREATE INDEX tasks_lease ON tasks (state, lease_expires_at);
CREATE INDEX tasks_worker ON tasks (worker_id, state);

CREATE TABLE task_deps (
    task_id    INTEGER NOT NULL REFERENCES tasks (id),
    depends_on INTEGER NOT NULL REFERENCES tasks (id),
    PRIMARY KEY (task_id, depends_on)
);
CREATE INDEX task_deps_reverse ON task_deps (depends_on);

CREATE TABLE workers (
    id            TEXT    PRIMARY KEY,
    name          TEXT    NOT NULL,
    owner         TEXT    NOT NULL,
    device        TEXT    NOT NULL,
    memory_bytes  INTEGER NOT NULL,
    labels        TEXT    NOT NULL,               -- JSON array of strings
    max_tasks     INTEGER NOT NULL,
    registered_at INTEGER NOT NULL,
    last_seen_at  INTEGER NOT NULL
);

CREATE TABLE events (
    seq        INTEGER PRIMARY KEY,
    job_id     TEXT    NOT NULL,
    at         INTEGER NOT NULL,
    kind       TEXT    NOT NULL,                  -- job_created|job_state|task_state|task_progress
    task_id    INTEGER NOT NULL DEFAULT 0,
    stage      TEXT    NOT NULL DEFAULT '',
    job_state  TEXT    NOT NULL DEFAULT '',
    task_state TEXT    NOT NULL DEFAULT '',
    attempt    INTEGER NOT NULL DEFAULT 0,
    progress   TEXT    NOT NULL DEFAULT '',       -- JSON progress of task_progress events
    message    TEXT    NOT NULL DEFAULT ''
);
CREATE INDEX events_job ON events (job_id, seq);

CREATE TABLE artifacts (
    key     TEXT    PRIMARY KEY,
    job_id  TEXT    NOT NULL,
    task_id INTEGER NOT NULL,
    size    INTEGER NOT NULL,
    sha256  TEXT    NOT NULL
);
CREATE INDEX artifacts_task ON artifacts (task_id);
CREATE INDEX artifacts_job ON artifacts (job_id, key);

CREATE TABLE uploads (
    id         TEXT    PRIMARY KEY,
    owner      TEXT    NOT NULL,
    kind       TEXT    NOT NULL,                  -- dataset|style
    key        TEXT    NOT NULL,
    filename   TEXT    NOT NULL,
    size       INTEGER NOT NULL,
    sha256     TEXT    NOT NULL,
    summary    TEXT    NOT NULL,
    created_at INTEGER NOT NULL
);
