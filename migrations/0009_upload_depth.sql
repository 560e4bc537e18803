-- Whether a dataset upload's training frames have depth maps, as the engine's loader found
-- (1 or 0; NULL for other kinds and for uploads from before): a job asking for a depth loss on
-- a dataset without depth is refused at submission.
ALTER TABLE uploads ADD COLUMN train_depth INTEGER;
