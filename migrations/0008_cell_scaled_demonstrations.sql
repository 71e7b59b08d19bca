-- A demonstration's recorded states may also be the cell-scaled inputs of a policy for any
-- cell (the tilt in the cell's own unit; docs/design.md §6). SQLite cannot widen a CHECK in
-- place, so the table is made again with it and every row copied as it is. No other table
-- refers to a demonstration by key (a training run lists its ids in JSON).
CREATE TABLE demonstrations_widened (
    id          INTEGER PRIMARY KEY,
    name        TEXT NOT NULL,
    source      TEXT NOT NULL CHECK (source IN ('recorded', 'imported', 'scripted')),
    cell_hash   TEXT NOT NULL,
    job_id      INTEGER REFERENCES jobs (id),
    episodes    INTEGER NOT NULL,
    steps       INTEGER NOT NULL,
    body        TEXT NOT NULL,
    created_by  TEXT,
    created_at  TEXT NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ', 'now')),
    inputs      TEXT NOT NULL DEFAULT 'absolute'
        CHECK (inputs IN ('absolute', 'cell-relative', 'cell-scaled'))
);
INSERT INTO demonstrations_widened
    (id, name, source, cell_hash, job_id, episodes, steps, body, created_by, created_at, inputs)
SELECT id, name, source, cell_hash, job_id, episodes, steps, body, created_by, created_at, inputs
FROM demonstrations;
DROP TABLE demonstrations;
ALTER TABLE demonstrations_widened RENAME TO demonstrations;
