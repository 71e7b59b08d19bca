-- Rows the fleet has not yet: one per insert, update or delete of a replicated row, written by
-- the triggers below in the same transaction as the row, so that a committed row is always
-- either in the fleet's PostgreSQL or here. The replicator sends the rows these keys name as
-- they are now (or their deletion) and deletes the outbox rows once PostgreSQL has committed.
-- The triggers write only while the cell is in a fleet (`cell_state` key `fleet` = 'on'):
-- joining a fleet fills the outbox with every row once.
CREATE TABLE fleet_outbox (
    seq         INTEGER PRIMARY KEY AUTOINCREMENT,
    table_name  TEXT NOT NULL,
    key1        INTEGER NOT NULL,
    -- The second key column (steps: the step), or NULL.
    key2        INTEGER,
    at          TEXT NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ', 'now'))
);

CREATE TRIGGER jobs_fleet_insert AFTER INSERT ON jobs
WHEN EXISTS (SELECT 1 FROM cell_state WHERE key = 'fleet' AND value = 'on')
BEGIN
    INSERT INTO fleet_outbox (table_name, key1, key2) VALUES ('jobs', NEW.id, NULL);
END;
CREATE TRIGGER jobs_fleet_update AFTER UPDATE ON jobs
WHEN EXISTS (SELECT 1 FROM cell_state WHERE key = 'fleet' AND value = 'on')
BEGIN
    INSERT INTO fleet_outbox (table_name, key1, key2) VALUES ('jobs', NEW.id, NULL);
END;
CREATE TRIGGER jobs_fleet_delete AFTER DELETE ON jobs
WHEN EXISTS (SELECT 1 FROM cell_state WHERE key = 'fleet' AND value = 'on')
BEGIN
    INSERT INTO fleet_outbox (table_name, key1, key2) VALUES ('jobs', OLD.id, NULL);
END;
CREATE TRIGGER steps_fleet_insert AFTER INSERT ON steps
WHEN EXISTS (SELECT 1 FROM cell_state WHERE key = 'fleet' AND value = 'on')
BEGIN
    INSERT INTO fleet_outbox (table_name, key1, key2) VALUES ('steps', NEW.job_id, NEW.step);
END;
CREATE TRIGGER steps_fleet_update AFTER UPDATE ON steps
WHEN EXISTS (SELECT 1 FROM cell_state WHERE key = 'fleet' AND value = 'on')
BEGIN
    INSERT INTO fleet_outbox (table_name, key1, key2) VALUES ('steps', NEW.job_id, NEW.step);
END;
CREATE TRIGGER steps_fleet_delete AFTER DELETE ON steps
WHEN EXISTS (SELECT 1 FROM cell_state WHERE key = 'fleet' AND value = 'on')
BEGIN
    INSERT INTO fleet_outbox (table_name, key1, key2) VALUES ('steps', OLD.job_id, OLD.step);
END;
CREATE TRIGGER policy_evaluations_fleet_insert AFTER INSERT ON policy_evaluations
WHEN EXISTS (SELECT 1 FROM cell_state WHERE key = 'fleet' AND value = 'on')
BEGIN
    INSERT INTO fleet_outbox (table_name, key1, key2) VALUES ('policy_evaluations', NEW.id, NULL);
END;
CREATE TRIGGER policy_evaluations_fleet_update AFTER UPDATE ON policy_evaluations
WHEN EXISTS (SELECT 1 FROM cell_state WHERE key = 'fleet' AND value = 'on')
BEGIN
    INSERT INTO fleet_outbox (table_name, key1, key2) VALUES ('policy_evaluations', NEW.id, NULL);
END;
CREATE TRIGGER policy_evaluations_fleet_delete AFTER DELETE ON policy_evaluations
WHEN EXISTS (SELECT 1 FROM cell_state WHERE key = 'fleet' AND value = 'on')
BEGIN
    INSERT INTO fleet_outbox (table_name, key1, key2) VALUES ('policy_evaluations', OLD.id, NULL);
END;
CREATE TRIGGER demonstrations_fleet_insert AFTER INSERT ON demonstrations
WHEN EXISTS (SELECT 1 FROM cell_state WHERE key = 'fleet' AND value = 'on')
BEGIN
    INSERT INTO fleet_outbox (table_name, key1, key2) VALUES ('demonstrations', NEW.id, NULL);
END;
CREATE TRIGGER demonstrations_fleet_update AFTER UPDATE ON demonstrations
WHEN EXISTS (SELECT 1 FROM cell_state WHERE key = 'fleet' AND value = 'on')
BEGIN
    INSERT INTO fleet_outbox (table_name, key1, key2) VALUES ('demonstrations', NEW.id, NULL);
END;
CREATE TRIGGER demonstrations_fleet_delete AFTER DELETE ON demonstrations
WHEN EXISTS (SELECT 1 FROM cell_state WHERE key = 'fleet' AND value = 'on')
BEGIN
    INSERT INTO fleet_outbox (table_name, key1, key2) VALUES ('demonstrations', OLD.id, NULL);
END;
CREATE TRIGGER training_runs_fleet_insert AFTER INSERT ON training_runs
WHEN EXISTS (SELECT 1 FROM cell_state WHERE key = 'fleet' AND value = 'on')
BEGIN
    INSERT INTO fleet_outbox (table_name, key1, key2) VALUES ('training_runs', NEW.id, NULL);
END;
CREATE TRIGGER training_runs_fleet_update AFTER UPDATE ON training_runs
WHEN EXISTS (SELECT 1 FROM cell_state WHERE key = 'fleet' AND value = 'on')
BEGIN
    INSERT INTO fleet_outbox (table_name, key1, key2) VALUES ('training_runs', NEW.id, NULL);
END;
CREATE TRIGGER training_runs_fleet_delete AFTER DELETE ON training_runs
WHEN EXISTS (SELECT 1 FROM cell_state WHERE key = 'fleet' AND value = 'on')
BEGIN
    INSERT INTO fleet_outbox (table_name, key1, key2) VALUES ('training_runs', OLD.id, NULL);
END;
CREATE TRIGGER audit_fleet_insert AFTER INSERT ON audit
WHEN EXISTS (SELECT 1 FROM cell_state WHERE key = 'fleet' AND value = 'on')
BEGIN
    INSERT INTO fleet_outbox (table_name, key1, key2) VALUES ('audit', NEW.id, NULL);
END;
CREATE TRIGGER audit_fleet_update AFTER UPDATE ON audit
WHEN EXISTS (SELECT 1 FROM cell_state WHERE key = 'fleet' AND value = 'on')
BEGIN
    INSERT INTO fleet_outbox (table_name, key1, key2) VALUES ('audit', NEW.id, NULL);
END;
CREATE TRIGGER audit_fleet_delete AFTER DELETE ON audit
WHEN EXISTS (SELECT 1 FROM cell_state WHERE key = 'fleet' AND value = 'on')
BEGIN
    INSERT INTO fleet_outbox (table_name, key1, key2) VALUES ('audit', OLD.id, NULL);
END;
CREATE TRIGGER machine_transitions_fleet_insert AFTER INSERT ON machine_transitions
WHEN EXISTS (SELECT 1 FROM cell_state WHERE key = 'fleet' AND value = 'on')
BEGIN
    INSERT INTO fleet_outbox (table_name, key1, key2) VALUES ('machine_transitions', NEW.id, NULL);
END;
CREATE TRIGGER machine_transitions_fleet_update AFTER UPDATE ON machine_transitions
WHEN EXISTS (SELECT 1 FROM cell_state WHERE key = 'fleet' AND value = 'on')
BEGIN
    INSERT INTO fleet_outbox (table_name, key1, key2) VALUES ('machine_transitions', NEW.id, NULL);
END;
CREATE TRIGGER machine_transitions_fleet_delete AFTER DELETE ON machine_transitions
WHEN EXISTS (SELECT 1 FROM cell_state WHERE key = 'fleet' AND value = 'on')
BEGIN
    INSERT INTO fleet_outbox (table_name, key1, key2) VALUES ('machine_transitions', OLD.id, NULL);
END;
CREATE TRIGGER tokens_fleet_insert AFTER INSERT ON tokens
WHEN EXISTS (SELECT 1 FROM cell_state WHERE key = 'fleet' AND value = 'on')
BEGIN
    INSERT INTO fleet_outbox (table_name, key1, key2) VALUES ('tokens', NEW.id, NULL);
END;
CREATE TRIGGER tokens_fleet_update AFTER UPDATE ON tokens
WHEN EXISTS (SELECT 1 FROM cell_state WHERE key = 'fleet' AND value = 'on')
BEGIN
    INSERT INTO fleet_outbox (table_name, key1, key2) VALUES ('tokens', NEW.id, NULL);
END;
CREATE TRIGGER tokens_fleet_delete AFTER DELETE ON tokens
WHEN EXISTS (SELECT 1 FROM cell_state WHERE key = 'fleet' AND value = 'on')
BEGIN
    INSERT INTO fleet_outbox (table_name, key1, key2) VALUES ('tokens', OLD.id, NULL);
END;
CREATE TRIGGER policies_fleet_insert AFTER INSERT ON policies
WHEN EXISTS (SELECT 1 FROM cell_state WHERE key = 'fleet' AND value = 'on')
BEGIN
    INSERT INTO fleet_outbox (table_name, key1, key2) VALUES ('policies', NEW.id, NULL);
END;
CREATE TRIGGER policies_fleet_update AFTER UPDATE ON policies
WHEN EXISTS (SELECT 1 FROM cell_state WHERE key = 'fleet' AND value = 'on')
BEGIN
    INSERT INTO fleet_outbox (table_name, key1, key2) VALUES ('policies', NEW.id, NULL);
END;
CREATE TRIGGER policies_fleet_delete AFTER DELETE ON policies
WHEN EXISTS (SELECT 1 FROM cell_state WHERE key = 'fleet' AND value = 'on')
BEGIN
    INSERT INTO fleet_outbox (table_name, key1, key2) VALUES ('policies', OLD.id, NULL);
END;
