-- Tokens may expire and be revoked. A revoked or expired token authenticates nothing; its row
-- stays, so the audit log's actors and `GET /api/tokens` still name it.
ALTER TABLE tokens ADD COLUMN expires_at TEXT;
ALTER TABLE tokens ADD COLUMN revoked_at TEXT;
ALTER TABLE tokens ADD COLUMN revoked_by TEXT;
