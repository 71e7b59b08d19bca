-- The PackML state's history: one row per transition, in order. The production counters live
-- in cell_state under the key `counters` (a JSON object), written in the same transaction.
CREATE TABLE machine_transitions (
    id         INTEGER PRIMARY KEY,
    at         TEXT NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ', 'now')),
    from_state TEXT NOT NULL,
    to_state   TEXT NOT NULL,
    cause      TEXT NOT NULL
);
