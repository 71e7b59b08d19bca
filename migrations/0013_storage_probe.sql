-- The storage writer's probe: one row rewritten while writes fail, to learn when the disk
-- takes writes again (src/storage/health.rs).
CREATE TABLE storage_probe (
    id INTEGER PRIMARY KEY CHECK (id = 1),
    at TEXT NOT NULL,
    room BLOB NOT NULL
);
