-- What each demonstration's recorded states are: the paper's absolute state, or the
-- cell-relative inputs of a policy for any cell (docs/design.md §6). Sets stored before were
-- all absolute.
ALTER TABLE demonstrations ADD COLUMN inputs TEXT NOT NULL DEFAULT 'absolute'
    CHECK (inputs IN ('absolute', 'cell-relative'));
