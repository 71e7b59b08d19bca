-- Training runs started over HTTP, and the lineage they give: demonstrations → run → policy.
CREATE TABLE training_runs (
    id                 INTEGER PRIMARY KEY,
    status             TEXT NOT NULL CHECK (status IN ('running', 'succeeded', 'failed', 'cancelled')),
    settings           TEXT NOT NULL,
    -- JSON array of the demonstrations it learned from.
    demonstration_ids  TEXT NOT NULL,
    stage              TEXT,
    progress           REAL NOT NULL DEFAULT 0,
    -- JSON array of {stage, x, value}.
    curve              TEXT NOT NULL DEFAULT '[]',
    figures            TEXT,
    policy_id          INTEGER REFERENCES policies (id),
    error              TEXT,
    created_by         TEXT NOT NULL,
    started_at         TEXT NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ', 'now')),
    finished_at        TEXT
);
ALTER TABLE policies ADD COLUMN training_run_id INTEGER REFERENCES training_runs (id);
