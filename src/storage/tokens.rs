//! API tokens: a random secret shown once, stored only as its sha256; each may expire and may
//! be revoked (the row stays, so the audit log's names still resolve).

use super::{Db, DbError, NOW};
use rand::RngCore;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

/// What a token may do; each role includes the ones before it.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize, utoipa::ToSchema,
)]
#[serde(rename_all = "snake_case")]
pub enum Role {
    Viewer,
    Operator,
    Admin,
}

impl Role {
    pub fn as_str(&self) -> &'static str {
        match self {
            Role::Viewer => "viewer",
            Role::Operator => "operator",
            Role::Admin => "admin",
        }
    }

    pub fn parse(text: &str) -> Option<Role> {
        [Role::Viewer, Role::Operator, Role::Admin]
            .into_iter()
            .find(|r| r.as_str() == text)
    }
}

/// Who is calling, once their token is known.
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct Caller {
    pub token_id: i64,
    pub name: String,
    pub role: Role,
}

/// A freshly made token: the secret exists only here.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct NewToken {
    pub id: i64,
    pub name: String,
    pub role: Role,
    pub token: String,
    /// When it stops authenticating (UTC); none: never.
    pub expires_at: Option<String>,
}

/// Whether a token authenticates now.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum TokenState {
    Active,
    Expired,
    Revoked,
}

/// A token as listed: never its secret nor its hash.
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct TokenInfo {
    pub id: i64,
    pub name: String,
    pub role: Role,
    pub state: TokenState,
    pub created_at: String,
    pub created_by: Option<String>,
    /// When it stops authenticating (UTC); none: never.
    pub expires_at: Option<String>,
    pub revoked_at: Option<String>,
    pub revoked_by: Option<String>,
}

/// A token found by its secret's hash, with what decides whether it still authenticates.
#[derive(Debug, Clone, PartialEq)]
pub struct FoundToken {
    pub caller: Caller,
    pub expires_at: Option<String>,
    /// `expires_at` as milliseconds since the Unix epoch, for comparing with the clock.
    pub expires_unix_ms: Option<i64>,
    pub revoked_at: Option<String>,
}

/// `expires_at` (the schema's text) as milliseconds since the Unix epoch, in SQL.
const EXPIRES_UNIX_MS: &str =
    "CAST(ROUND((julianday(expires_at) - 2440587.5) * 86400000.0) AS INTEGER)";

/// sha256 of a token's secret, hex: what is stored.
pub fn hash(secret: &str) -> String {
    hash_bytes(secret.as_bytes())
}

/// sha256, hex.
pub fn hash_bytes(bytes: &[u8]) -> String {
    Sha256::digest(bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// Makes and stores a token, expiring `expires_in_s` seconds from now when given.
pub async fn create(
    db: &Db,
    role: Role,
    name: &str,
    created_by: &str,
    expires_in_s: Option<u64>,
) -> Result<NewToken, DbError> {
    let mut bytes = [0u8; 32];
    rand::rng().fill_bytes(&mut bytes);
    let secret: String = std::iter::once("celld_".to_string())
        .chain(bytes.iter().map(|b| format!("{b:02x}")))
        .collect();
    // SQLite's date modifier: "+N seconds" from now, in the schema's format.
    let expires = expires_in_s.map(|s| format!("+{s} seconds"));
    let row: Result<Vec<(i64, Option<String>)>, _> = sqlx::query_as(
        "INSERT INTO tokens (name, role, token_hash, created_by, expires_at)
         VALUES (?, ?, ?, ?, CASE WHEN ?5 IS NULL THEN NULL
                                  ELSE strftime('%Y-%m-%dT%H:%M:%fZ', 'now', ?5) END)
         RETURNING id, expires_at",
    )
    .bind(name)
    .bind(role.as_str())
    .bind(hash(&secret))
    .bind(created_by)
    .bind(expires)
    .fetch_all(&db.writer)
    .await;
    let (id, expires_at) = db.track(row.and_then(super::only_row))?;
    Ok(NewToken {
        id,
        name: name.to_string(),
        role,
        token: secret,
        expires_at,
    })
}

/// The token whose secret has this [`hash`], if any, revoked and expired ones included.
pub async fn find_by_hash(db: &Db, token_hash: &str) -> Result<Option<FoundToken>, DbError> {
    type Row = (
        i64,
        String,
        String,
        Option<String>,
        Option<i64>,
        Option<String>,
    );
    let row: Option<Row> = sqlx::query_as(&format!(
        "SELECT id, name, role, expires_at, {EXPIRES_UNIX_MS}, revoked_at
         FROM tokens WHERE token_hash = ?"
    ))
    .bind(token_hash)
    .fetch_optional(&db.reader)
    .await?;
    Ok(row.and_then(
        |(token_id, name, role, expires_at, expires_unix_ms, revoked_at)| {
            Some(FoundToken {
                caller: Caller {
                    token_id,
                    name,
                    role: Role::parse(&role)?,
                },
                expires_at,
                expires_unix_ms,
                revoked_at,
            })
        },
    ))
}

/// A row of `tokens` as listed.
#[derive(sqlx::FromRow)]
struct InfoRow {
    id: i64,
    name: String,
    role: String,
    state: String,
    created_at: String,
    created_by: Option<String>,
    expires_at: Option<String>,
    revoked_at: Option<String>,
    revoked_by: Option<String>,
}

impl InfoRow {
    fn info(self) -> Option<TokenInfo> {
        Some(TokenInfo {
            id: self.id,
            name: self.name,
            role: Role::parse(&self.role)?,
            state: match self.state.as_str() {
                "revoked" => TokenState::Revoked,
                "expired" => TokenState::Expired,
                _ => TokenState::Active,
            },
            created_at: self.created_at,
            created_by: self.created_by,
            expires_at: self.expires_at,
            revoked_at: self.revoked_at,
            revoked_by: self.revoked_by,
        })
    }
}

fn info_query(filter: &str) -> String {
    format!(
        "SELECT id, name, role, created_at, created_by, expires_at, revoked_at, revoked_by,
                CASE WHEN revoked_at IS NOT NULL THEN 'revoked'
                     WHEN expires_at IS NOT NULL AND expires_at <= {NOW} THEN 'expired'
                     ELSE 'active' END AS state
         FROM tokens {filter}"
    )
}

/// Every token, oldest first.
pub async fn list(db: &Db) -> Result<Vec<TokenInfo>, DbError> {
    let rows: Vec<InfoRow> = sqlx::query_as(&info_query("ORDER BY id"))
        .fetch_all(&db.reader)
        .await?;
    Ok(rows.into_iter().filter_map(InfoRow::info).collect())
}

/// The token with `id`, if any. Read from the writer, so that it sees a revocation just made.
pub async fn get(db: &Db, id: i64) -> Result<Option<TokenInfo>, DbError> {
    let row: Option<InfoRow> = sqlx::query_as(&info_query("WHERE id = ?"))
        .bind(id)
        .fetch_optional(&db.writer)
        .await?;
    Ok(row.and_then(InfoRow::info))
}

/// Revokes token `id` unless it is revoked already or it is the last admin token that still
/// authenticates (one statement on the one writer, so two revocations cannot both take the
/// last two). Returns whether it was revoked.
pub async fn revoke(db: &Db, id: i64, by: &str) -> Result<bool, DbError> {
    let done = sqlx::query(&format!(
        "UPDATE tokens SET revoked_at = {NOW}, revoked_by = ?
         WHERE id = ? AND revoked_at IS NULL
           AND (role != 'admin'
                OR (expires_at IS NOT NULL AND expires_at <= {NOW})
                OR (SELECT COUNT(*) FROM tokens AS other
                    WHERE other.id != ?2 AND other.role = 'admin' AND other.revoked_at IS NULL
                      AND (other.expires_at IS NULL OR other.expires_at > {NOW})) > 0)"
    ))
    .bind(by)
    .bind(id)
    .execute(&db.writer)
    .await;
    Ok(db.track(done)?.rows_affected() == 1)
}

pub async fn count(db: &Db) -> Result<i64, DbError> {
    sqlx::query_scalar("SELECT COUNT(*) FROM tokens")
        .fetch_one(&db.reader)
        .await
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hash_is_sha256_hex() {
        // sha256("abc"), FIPS 180-2 appendix B.1.
        assert_eq!(
            hash("abc"),
            "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
        );
    }

    async fn open() -> (tempfile::TempDir, Db) {
        let dir = tempfile::tempdir().unwrap();
        let db = Db::open(&dir.path().join("cell.db")).await.unwrap();
        (dir, db)
    }

    #[tokio::test]
    async fn a_token_is_found_by_its_hash_until_revoked_and_the_last_admin_stays() {
        let (_dir, db) = open().await;
        let first = create(&db, Role::Admin, "first", "test", None)
            .await
            .unwrap();
        let operator = create(&db, Role::Operator, "op", "test", None)
            .await
            .unwrap();
        let found = find_by_hash(&db, &hash(&operator.token)).await.unwrap();
        let found = found.unwrap();
        assert_eq!(found.caller.name, "op");
        assert_eq!((found.expires_at, found.revoked_at), (None, None));
        assert!(
            find_by_hash(&db, &hash("celld_nothing"))
                .await
                .unwrap()
                .is_none()
        );

        // The only admin that authenticates cannot be revoked; once a second exists it can.
        assert!(!revoke(&db, first.id, "test").await.unwrap());
        let second = create(&db, Role::Admin, "second", "test", None)
            .await
            .unwrap();
        assert!(revoke(&db, first.id, "test").await.unwrap());
        assert!(
            !revoke(&db, first.id, "test").await.unwrap(),
            "already revoked"
        );
        assert!(!revoke(&db, second.id, "test").await.unwrap());
        assert!(revoke(&db, operator.id, "test").await.unwrap());

        let listed = list(&db).await.unwrap();
        let states: Vec<(i64, TokenState)> = listed.iter().map(|t| (t.id, t.state)).collect();
        assert_eq!(
            states,
            [
                (first.id, TokenState::Revoked),
                (operator.id, TokenState::Revoked),
                (second.id, TokenState::Active)
            ]
        );
        assert_eq!(listed[0].revoked_by.as_deref(), Some("test"));
        let found = find_by_hash(&db, &hash(&operator.token))
            .await
            .unwrap()
            .unwrap();
        assert_eq!(found.revoked_at, listed[1].revoked_at);
    }

    #[tokio::test]
    async fn an_expiry_is_stored_as_text_and_as_the_epoch_milliseconds_it_names() {
        let (_dir, db) = open().await;
        let token = create(&db, Role::Viewer, "brief", "test", Some(3600))
            .await
            .unwrap();
        let at = token.expires_at.clone().unwrap();
        let found = find_by_hash(&db, &hash(&token.token))
            .await
            .unwrap()
            .unwrap();
        assert_eq!(found.expires_at.as_deref(), Some(at.as_str()));
        // An hour from the clock now, give or take the test's own time.
        let now_ms = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap()
            .as_millis() as i64;
        let left_ms = found.expires_unix_ms.unwrap() - now_ms;
        assert!(
            (3_590_000..=3_600_000).contains(&left_ms),
            "{left_ms} ms left"
        );
        // The epoch milliseconds of a hand-picked stamp: 2001-09-09T01:46:40Z is 10^9 s.
        let (ms,): (i64,) = sqlx::query_as(&format!(
            "SELECT {} FROM (SELECT '2001-09-09T01:46:40.250Z' AS expires_at)",
            EXPIRES_UNIX_MS
        ))
        .fetch_one(&db.reader)
        .await
        .unwrap();
        assert_eq!(ms, 1_000_000_000_250);
        let expired = create(&db, Role::Viewer, "gone", "test", Some(0))
            .await
            .unwrap();
        let listed = get(&db, expired.id).await.unwrap().unwrap();
        assert_eq!(listed.state, TokenState::Expired);
        assert_eq!(
            get(&db, token.id).await.unwrap().unwrap().state,
            TokenState::Active
        );
        assert!(get(&db, 99).await.unwrap().is_none());
    }

    #[test]
    fn roles_are_ordered_by_what_they_may_do() {
        assert!(Role::Viewer < Role::Operator && Role::Operator < Role::Admin);
        assert_eq!(Role::parse("operator"), Some(Role::Operator));
        assert_eq!(Role::parse("root"), None);
    }
}
