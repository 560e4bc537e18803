-- Progress events are throttled per task: `progress_event_at` is when the task's last
-- `task_progress` event was stored (epoch ms; 0 = none during the current lease). The latest
-- progress itself is always on the task row (`progress`).
ALTER TABLE tasks ADD COLUMN progress_event_at INTEGER NOT NULL DEFAULT 0;
