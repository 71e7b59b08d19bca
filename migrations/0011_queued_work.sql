-- Evaluations and training runs wait in one queue behind a limit (workflows::queue): both may
-- now be `queued`. SQLite cannot change a CHECK, so both tables are made again with their
-- rows, as its documented procedure does. Policies name training runs: their links are kept
-- aside while the table is replaced, so no foreign key is broken on the way.
CREATE TABLE policy_evaluations_new (
    id                 INTEGER PRIMARY KEY,
    policy_id          INTEGER NOT NULL REFERENCES policies (id),
    status             TEXT NOT NULL CHECK (status IN ('queued', 'running', 'done', 'failed')),
    episodes           INTEGER NOT NULL,
    seed               INTEGER NOT NULL,
    -- CellConfig::config_hash of the cell it ran on; the gate needs the current cell's.
    cell_hash          TEXT NOT NULL,
    success_rate       REAL,
    avg_steps          REAL,
    failures           TEXT,
    error              TEXT,
    requested_by       TEXT NOT NULL,
    -- When it was asked for, then when it left the queue and started.
    started_at         TEXT NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ', 'now')),
    finished_at        TEXT,
    noise_scale        REAL NOT NULL DEFAULT 1,
    calibration_scale  REAL NOT NULL DEFAULT 1,
    fault              TEXT,
    randomise_cells    INTEGER NOT NULL DEFAULT 0
);
INSERT INTO policy_evaluations_new (id, policy_id, status, episodes, seed, cell_hash,
        success_rate, avg_steps, failures, error, requested_by, started_at, finished_at,
        noise_scale, calibration_scale, fault, randomise_cells)
    SELECT id, policy_id, status, episodes, seed, cell_hash, success_rate, avg_steps, failures,
           error, requested_by, started_at, finished_at, noise_scale, calibration_scale, fault,
           randomise_cells
    FROM policy_evaluations;
DROP TABLE policy_evaluations;
ALTER TABLE policy_evaluations_new RENAME TO policy_evaluations;
CREATE INDEX policy_evaluations_policy ON policy_evaluations (policy_id);

CREATE TEMPORARY TABLE policy_lineage AS
    SELECT id, training_run_id FROM policies WHERE training_run_id IS NOT NULL;
UPDATE policies SET training_run_id = NULL WHERE training_run_id IS NOT NULL;
CREATE TABLE training_runs_new (
    id                 INTEGER PRIMARY KEY,
    status             TEXT NOT NULL
                       CHECK (status IN ('queued', 'running', 'succeeded', 'failed', 'cancelled')),
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
    -- When it was asked for, then when it left the queue and started.
    started_at         TEXT NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ', 'now')),
    finished_at        TEXT
);
INSERT INTO training_runs_new (id, status, settings, demonstration_ids, stage, progress, curve,
        figures, policy_id, error, created_by, started_at, finished_at)
    SELECT id, status, settings, demonstration_ids, stage, progress, curve, figures, policy_id,
           error, created_by, started_at, finished_at
    FROM training_runs;
DROP TABLE training_runs;
ALTER TABLE training_runs_new RENAME TO training_runs;
UPDATE policies SET training_run_id =
    (SELECT l.training_run_id FROM policy_lineage l WHERE l.id = policies.id)
    WHERE id IN (SELECT id FROM policy_lineage);
DROP TABLE policy_lineage;
