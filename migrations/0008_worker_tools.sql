-- The programs a worker advertises (`colmap`, `ffmpeg`): only workers with what a stage needs
-- are handed its tasks (the `poses` stage of jobs from photos).
ALTER TABLE workers ADD COLUMN tools TEXT NOT NULL DEFAULT '[]'; -- JSON array of strings
