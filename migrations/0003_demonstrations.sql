-- Expert demonstrations: recorded by a job in demonstration mode, imported, or scripted.
-- `body` is the demonstration as JSON Lines (learning::demos format, one step a line), written
-- canonically, so an export is byte-for-byte what the next export of a re-import gives.
CREATE TABLE demonstrations (
    id          INTEGER PRIMARY KEY,
    name        TEXT NOT NULL,
    source      TEXT NOT NULL CHECK (source IN ('recorded', 'imported', 'scripted')),
    cell_hash   TEXT NOT NULL,
    job_id      INTEGER REFERENCES jobs (id),
    episodes    INTEGER NOT NULL,
    steps       INTEGER NOT NULL,
    body        TEXT NOT NULL,
    created_by  TEXT,
    created_at  TEXT NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ', 'now'))
);
