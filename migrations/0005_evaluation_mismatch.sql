-- The twin's departures from the cell file an evaluation ran under (sim::fault::Mismatch):
-- camera noise scale, robot calibration scale and an injected fault. Evaluations from before
-- ran under none (1, 1, no fault). The activation gate reads only those.
ALTER TABLE policy_evaluations ADD COLUMN noise_scale REAL NOT NULL DEFAULT 1;
ALTER TABLE policy_evaluations ADD COLUMN calibration_scale REAL NOT NULL DEFAULT 1;
ALTER TABLE policy_evaluations ADD COLUMN fault TEXT;
