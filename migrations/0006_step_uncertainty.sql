-- How sure the cell was of the state after each step (the state filter's σ and the camera's
-- noise as it learned it), and any fault it noticed at that step. Steps recorded before have
-- none.
ALTER TABLE steps ADD COLUMN sd_lateral_mm REAL;
ALTER TABLE steps ADD COLUMN sd_axial_mm REAL;
ALTER TABLE steps ADD COLUMN sd_tilt_deg REAL;
ALTER TABLE steps ADD COLUMN noise_scale REAL;
ALTER TABLE steps ADD COLUMN detected TEXT;
