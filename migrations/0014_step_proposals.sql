-- What the controller proposed at each step before the shield's rules shaped it into `action`
-- (JSON text of six numbers like `action`, mm and deg; NULL for a controller without rules),
-- and the rules that changed it (JSON text: their names in pipeline order; NULL where none
-- did). Steps recorded before have neither.
ALTER TABLE steps ADD COLUMN proposed TEXT;
ALTER TABLE steps ADD COLUMN rules TEXT;
