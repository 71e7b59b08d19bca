-- The fleet's database on PostgreSQL: what every cell replicates, keyed by its cell id, and
-- the fleet's own tables (cells' heartbeats, the policy registry, activation requests).
-- The replicated tables have the cell's SQLite columns and types (INTEGER as BIGINT, REAL as
-- DOUBLE PRECISION, BLOB as BYTEA; times stay the cell's ISO 8601 UTC text) with `cell_id` first.
-- No foreign keys: rows arrive in the order the cell committed them, a batch at a time, and a
-- cell's rows are its own.

CREATE TABLE jobs (
    cell_id TEXT NOT NULL,
    id BIGINT NOT NULL,
    status TEXT NOT NULL,
    controller TEXT NOT NULL,
    policy_id BIGINT,
    seed BIGINT NOT NULL,
    initial_pos_mm DOUBLE PRECISION NOT NULL,
    initial_ori_deg DOUBLE PRECISION NOT NULL,
    demonstration BIGINT NOT NULL,
    created_by TEXT,
    created_at TEXT NOT NULL,
    started_at TEXT,
    finished_at TEXT,
    steps BIGINT NOT NULL,
    failure_reason TEXT,
    reward DOUBLE PRECISION,
    lateral_mm DOUBLE PRECISION,
    depth_error_mm DOUBLE PRECISION,
    tilt_deg DOUBLE PRECISION,
    hole_arc_mm DOUBLE PRECISION,
    PRIMARY KEY (cell_id, id)
);
CREATE TABLE steps (
    cell_id TEXT NOT NULL,
    job_id BIGINT NOT NULL,
    step BIGINT NOT NULL,
    t_s DOUBLE PRECISION NOT NULL,
    state TEXT NOT NULL,
    action TEXT NOT NULL,
    actor TEXT,
    scale DOUBLE PRECISION,
    legs_mm TEXT NOT NULL,
    verdict TEXT NOT NULL,
    veto_reason TEXT,
    reward_global DOUBLE PRECISION NOT NULL,
    reward_position DOUBLE PRECISION NOT NULL,
    reward_orientation DOUBLE PRECISION NOT NULL,
    reward_error DOUBLE PRECISION NOT NULL,
    reward_step DOUBLE PRECISION NOT NULL,
    reward_total DOUBLE PRECISION NOT NULL,
    compute_us DOUBLE PRECISION NOT NULL,
    sd_lateral_mm DOUBLE PRECISION,
    sd_axial_mm DOUBLE PRECISION,
    sd_tilt_deg DOUBLE PRECISION,
    noise_scale DOUBLE PRECISION,
    detected TEXT,
    proposed TEXT,
    rules TEXT,
    PRIMARY KEY (cell_id, job_id, step)
);
CREATE TABLE policy_evaluations (
    cell_id TEXT NOT NULL,
    id BIGINT NOT NULL,
    policy_id BIGINT NOT NULL,
    status TEXT NOT NULL,
    episodes BIGINT NOT NULL,
    seed BIGINT NOT NULL,
    cell_hash TEXT NOT NULL,
    success_rate DOUBLE PRECISION,
    avg_steps DOUBLE PRECISION,
    failures TEXT,
    error TEXT,
    requested_by TEXT NOT NULL,
    started_at TEXT NOT NULL,
    finished_at TEXT,
    noise_scale DOUBLE PRECISION NOT NULL,
    calibration_scale DOUBLE PRECISION NOT NULL,
    fault TEXT,
    randomise_cells BIGINT NOT NULL,
    rules TEXT NOT NULL,
    PRIMARY KEY (cell_id, id)
);
CREATE TABLE demonstrations (
    cell_id TEXT NOT NULL,
    id BIGINT NOT NULL,
    name TEXT NOT NULL,
    source TEXT NOT NULL,
    cell_hash TEXT NOT NULL,
    job_id BIGINT,
    episodes BIGINT NOT NULL,
    steps BIGINT NOT NULL,
    body TEXT NOT NULL,
    created_by TEXT,
    created_at TEXT NOT NULL,
    inputs TEXT NOT NULL,
    PRIMARY KEY (cell_id, id)
);
CREATE TABLE training_runs (
    cell_id TEXT NOT NULL,
    id BIGINT NOT NULL,
    status TEXT NOT NULL,
    settings TEXT NOT NULL,
    demonstration_ids TEXT NOT NULL,
    stage TEXT,
    progress DOUBLE PRECISION NOT NULL,
    curve TEXT NOT NULL,
    figures TEXT,
    policy_id BIGINT,
    error TEXT,
    created_by TEXT NOT NULL,
    started_at TEXT NOT NULL,
    finished_at TEXT,
    PRIMARY KEY (cell_id, id)
);
CREATE TABLE audit (
    cell_id TEXT NOT NULL,
    id BIGINT NOT NULL,
    at TEXT NOT NULL,
    actor TEXT NOT NULL,
    action TEXT NOT NULL,
    detail TEXT NOT NULL,
    PRIMARY KEY (cell_id, id)
);
CREATE TABLE machine_transitions (
    cell_id TEXT NOT NULL,
    id BIGINT NOT NULL,
    at TEXT NOT NULL,
    from_state TEXT NOT NULL,
    to_state TEXT NOT NULL,
    cause TEXT NOT NULL,
    PRIMARY KEY (cell_id, id)
);
CREATE TABLE tokens (
    cell_id TEXT NOT NULL,
    id BIGINT NOT NULL,
    name TEXT NOT NULL,
    role TEXT NOT NULL,
    token_hash TEXT NOT NULL,
    created_at TEXT NOT NULL,
    created_by TEXT,
    expires_at TEXT,
    revoked_at TEXT,
    revoked_by TEXT,
    PRIMARY KEY (cell_id, id)
);
CREATE TABLE policies (
    cell_id TEXT NOT NULL,
    id BIGINT NOT NULL,
    name TEXT NOT NULL,
    sha256 TEXT NOT NULL,
    metadata TEXT NOT NULL,
    shapes TEXT NOT NULL,
    status TEXT NOT NULL,
    uploaded_by TEXT,
    created_at TEXT NOT NULL,
    training_run_id BIGINT,
    PRIMARY KEY (cell_id, id)
);
CREATE INDEX jobs_cell_created_at ON jobs (cell_id, created_at);
CREATE INDEX jobs_created_at ON jobs (created_at);

-- Each cell's heartbeat: what `GET /api/fleet/cells` shows.
CREATE TABLE fleet_cells (
    cell_id        TEXT PRIMARY KEY,
    last_heard_at  TIMESTAMPTZ NOT NULL,
    state          TEXT NOT NULL,
    stop_reason    TEXT,
    estop_latched  BOOLEAN NOT NULL,
    -- JSON {id, name, sha256} of the cell's active policy, or NULL.
    active_policy  TEXT,
    -- JSON: the PackML counters.
    counters       TEXT NOT NULL,
    config_hash    TEXT NOT NULL,
    -- Rows the cell has not replicated yet, and how old the oldest sent in its last batch was.
    backlog        BIGINT NOT NULL,
    lag_s          DOUBLE PRECISION
);

-- The fleet's registry: a policy uploaded on any cell, once, for every cell to pull.
CREATE TABLE fleet_policy_files (
    sha256      TEXT PRIMARY KEY,
    name        TEXT NOT NULL,
    file        BYTEA NOT NULL,
    uploaded_by TEXT,
    created_at  TEXT NOT NULL,
    first_cell  TEXT NOT NULL
);

-- "Activate on every cell where it passed": one request, one result per cell.
CREATE TABLE fleet_activations (
    id           BIGSERIAL PRIMARY KEY,
    sha256       TEXT NOT NULL,
    requested_by TEXT NOT NULL,
    requested_at TIMESTAMPTZ NOT NULL DEFAULT now()
);
CREATE TABLE fleet_activation_results (
    activation_id BIGINT NOT NULL REFERENCES fleet_activations (id),
    cell_id       TEXT NOT NULL,
    outcome       TEXT NOT NULL
                  CHECK (outcome IN ('activated', 'already_active', 'not_passed', 'missing')),
    detail        TEXT NOT NULL,
    at            TIMESTAMPTZ NOT NULL DEFAULT now(),
    PRIMARY KEY (activation_id, cell_id)
);
