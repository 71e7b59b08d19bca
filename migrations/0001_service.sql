-- celld serve: jobs and their steps, tokens, the audit log, the cell's latched state, and the
-- policy registry / demonstrations / training runs the next issues fill.
-- Times are UTC ISO 8601 text with milliseconds ('2026-11-22T10:00:00.000Z'): they sort as text.

CREATE TABLE tokens (
    id          INTEGER PRIMARY KEY,
    name        TEXT NOT NULL,
    role        TEXT NOT NULL CHECK (role IN ('viewer', 'operator', 'admin')),
    -- sha256 of the secret, hex; the secret itself is never stored.
    token_hash  TEXT NOT NULL UNIQUE,
    created_at  TEXT NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ', 'now')),
    created_by  TEXT
);

CREATE TABLE policies (
    id          INTEGER PRIMARY KEY,
    name        TEXT NOT NULL,
    sha256      TEXT NOT NULL UNIQUE,
    file        BLOB NOT NULL,
    metadata    TEXT NOT NULL DEFAULT '{}',
    shapes      TEXT NOT NULL DEFAULT '{}',
    status      TEXT NOT NULL DEFAULT 'candidate' CHECK (status IN ('candidate', 'active', 'retired')),
    uploaded_by TEXT,
    created_at  TEXT NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ', 'now'))
);

CREATE TABLE jobs (
    id              INTEGER PRIMARY KEY,
    status          TEXT NOT NULL CHECK (status IN
                        ('queued', 'running', 'succeeded', 'failed', 'cancelled', 'interrupted')),
    controller      TEXT NOT NULL,
    policy_id       INTEGER REFERENCES policies (id),
    seed            INTEGER NOT NULL,
    initial_pos_mm  REAL NOT NULL,
    initial_ori_deg REAL NOT NULL,
    demonstration   INTEGER NOT NULL DEFAULT 0,
    created_by      TEXT,
    created_at      TEXT NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ', 'now')),
    started_at      TEXT,
    finished_at     TEXT,
    steps           INTEGER NOT NULL DEFAULT 0,
    failure_reason  TEXT,
    reward          REAL,
    lateral_mm      REAL,
    depth_error_mm  REAL,
    tilt_deg        REAL,
    hole_arc_mm     REAL
);
CREATE INDEX jobs_status ON jobs (status);
CREATE INDEX jobs_created_at ON jobs (created_at);

-- One row per control step. Vectors are JSON arrays (state: 12 numbers, DESIGN.md §5; action:
-- 6 numbers, mm and deg; legs: 6 leg lengths, mm).
CREATE TABLE steps (
    job_id          INTEGER NOT NULL REFERENCES jobs (id) ON DELETE CASCADE,
    step            INTEGER NOT NULL,
    t_s             REAL NOT NULL,
    state           TEXT NOT NULL,
    action          TEXT NOT NULL,
    actor           TEXT,
    scale           REAL,
    legs_mm         TEXT NOT NULL,
    verdict         TEXT NOT NULL CHECK (verdict IN ('allowed', 'vetoed')),
    veto_reason     TEXT,
    reward_global   REAL NOT NULL,
    reward_position REAL NOT NULL,
    reward_orientation REAL NOT NULL,
    reward_error    REAL NOT NULL,
    reward_step     REAL NOT NULL,
    reward_total    REAL NOT NULL,
    compute_us      REAL NOT NULL,
    PRIMARY KEY (job_id, step)
) WITHOUT ROWID;

CREATE TABLE audit (
    id      INTEGER PRIMARY KEY,
    at      TEXT NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ', 'now')),
    actor   TEXT NOT NULL,
    action  TEXT NOT NULL,
    detail  TEXT NOT NULL DEFAULT '{}'
);

-- Latched cell state that must survive a restart (the e-stop latch).
CREATE TABLE cell_state (
    key   TEXT PRIMARY KEY,
    value TEXT NOT NULL
);
