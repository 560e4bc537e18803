-- Progress events are throttled per task: `progress_event_at` is when the task's last
-- `task_progress` event was stored (epoch ms; 0 = none during the current lease), and
-- `progress_event_stored` says whether the latest heartbeat stored one (set by the same UPDATE,
-- which sees the old `progress_event_at`, so the heartbeat learns the decision from RETURNING).
-- The latest progress itself is always on the task row (`progress`).
ALTER TABLE tasks ADD COLUMN progress_event_at INTEGER NOT NULL DEFAULT 0;
ALTER TABLE tasks ADD COLUMN progress_event_stored INTEGER NOT NULL DEFAULT 0;
