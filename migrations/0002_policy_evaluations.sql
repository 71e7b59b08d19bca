-- Evaluations of registered policies in the cell's twin (the activation gate reads them).
CREATE TABLE policy_evaluations (
    id            INTEGER PRIMARY KEY,
    policy_id     INTEGER NOT NULL REFERENCES policies (id),
    status        TEXT NOT NULL CHECK (status IN ('running', 'done', 'failed')),
    episodes      INTEGER NOT NULL,
    seed          INTEGER NOT NULL,
    -- CellConfig::config_hash of the cell it ran on; the gate needs the current cell's.
    cell_hash     TEXT NOT NULL,
    success_rate  REAL,
    avg_steps     REAL,
    failures      TEXT,
    error         TEXT,
    requested_by  TEXT NOT NULL,
    started_at    TEXT NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ', 'now')),
    finished_at   TEXT
);
CREATE INDEX policy_evaluations_policy ON policy_evaluations (policy_id);
-- At most one active policy.
CREATE UNIQUE INDEX policies_one_active ON policies (status) WHERE status = 'active';
