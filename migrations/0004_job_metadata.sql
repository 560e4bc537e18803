-- The integrator's key-value pairs of a job (a JSON object of strings), set at creation.
ALTER TABLE jobs ADD COLUMN metadata TEXT NOT NULL DEFAULT '{}';
