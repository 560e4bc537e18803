-- Resumable uploads: a session per upload in progress, and the parts it has committed. Each
-- part is one object `upload-sessions/<session>/<offset>` in the artifact store, written
-- before its row; `committed` is the sum of the parts' sizes. `upload_id` is set by the
-- transaction that records the finished upload (its parts are then deleted).
CREATE TABLE upload_sessions (
    id TEXT PRIMARY KEY,
    owner TEXT NOT NULL,
    kind TEXT NOT NULL,
    filename TEXT NOT NULL,
    total_size INTEGER NOT NULL,   -- 0 = not declared
    committed INTEGER NOT NULL DEFAULT 0,
    upload_id TEXT,
    created_at INTEGER NOT NULL,
    updated_at INTEGER NOT NULL
);
CREATE INDEX upload_sessions_owner ON upload_sessions (owner);
CREATE INDEX upload_sessions_updated ON upload_sessions (updated_at);

CREATE TABLE upload_session_parts (
    session_id TEXT NOT NULL,
    offset INTEGER NOT NULL,
    size INTEGER NOT NULL,
    PRIMARY KEY (session_id, offset)
);
