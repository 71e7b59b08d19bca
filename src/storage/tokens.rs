//! API tokens: a random secret shown once, stored only as its sha256.

use super::{Db, DbError};
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
}

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

/// Makes and stores a token.
pub async fn create(
    db: &Db,
    role: Role,
    name: &str,
    created_by: &str,
) -> Result<NewToken, DbError> {
    let mut bytes = [0u8; 32];
    rand::rng().fill_bytes(&mut bytes);
    let secret: String = std::iter::once("celld_".to_string())
        .chain(bytes.iter().map(|b| format!("{b:02x}")))
        .collect();
    let id = sqlx::query_scalar::<_, i64>(
        "INSERT INTO tokens (name, role, token_hash, created_by) VALUES (?, ?, ?, ?) RETURNING id",
    )
    .bind(name)
    .bind(role.as_str())
    .bind(hash(&secret))
    .bind(created_by)
    .fetch_all(&db.writer)
    .await;
    let id = db.track(id.and_then(super::only_row))?;
    Ok(NewToken {
        id,
        name: name.to_string(),
        role,
        token: secret,
    })
}

/// The caller whose secret has this [`hash`], if any.
pub async fn find_by_hash(db: &Db, token_hash: &str) -> Result<Option<Caller>, DbError> {
    let row: Option<(i64, String, String)> =
        sqlx::query_as("SELECT id, name, role FROM tokens WHERE token_hash = ?")
            .bind(token_hash)
            .fetch_optional(&db.reader)
            .await?;
    Ok(row.and_then(|(token_id, name, role)| {
        Some(Caller {
            token_id,
            name,
            role: Role::parse(&role)?,
        })
    }))
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

    #[test]
    fn roles_are_ordered_by_what_they_may_do() {
        assert!(Role::Viewer < Role::Operator && Role::Operator < Role::Admin);
        assert_eq!(Role::parse("operator"), Some(Role::Operator));
        assert_eq!(Role::parse("root"), None);
    }
}
