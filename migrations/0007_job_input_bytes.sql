-- The bytes of a job's copied inputs (`jobs/<id>/inputs/`), counted in its owner's stored
-- bytes with uploads, open upload sessions and the job's recorded outputs (quotas).
ALTER TABLE jobs ADD COLUMN input_bytes INTEGER NOT NULL DEFAULT 0;
CREATE INDEX uploads_owner ON uploads (owner);
