-- Scheduling by priority (higher first, then oldest ready first) and job deadlines. A task
-- carries its job's priority so that the ready queue is one index scan.
ALTER TABLE jobs ADD COLUMN priority INTEGER NOT NULL DEFAULT 0;
ALTER TABLE jobs ADD COLUMN deadline_at INTEGER NOT NULL DEFAULT 0;   -- epoch ms; 0 = none
ALTER TABLE tasks ADD COLUMN priority INTEGER NOT NULL DEFAULT 0;
CREATE INDEX tasks_ready_priority ON tasks (state, priority DESC, ready_at, id);
CREATE INDEX jobs_deadline ON jobs (deadline_at) WHERE deadline_at > 0;
