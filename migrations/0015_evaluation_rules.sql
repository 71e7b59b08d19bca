-- The rules an evaluation ran its policy with (`all`, `none` or a comma-separated list of rule
-- names, docs/policy-rules.md). Evaluations before this column ran with every rule.
ALTER TABLE policy_evaluations ADD COLUMN rules TEXT NOT NULL DEFAULT 'all';
