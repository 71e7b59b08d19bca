-- Whether an evaluation ran on cells drawn around this cell over the ranges the product is
-- specified for (`celld eval --randomise-cells`), each kept robot on a cell of its own with its
-- camera noise and calibration error drawn too. Evaluations from before ran on the cell itself.
-- The activation gate reads only those.
ALTER TABLE policy_evaluations ADD COLUMN randomise_cells INTEGER NOT NULL DEFAULT 0;
