//! API tokens: made (the secret shown once, stored as a hash) and audited, for the API, the
//! first start and `celld token create` alike.

use super::{Error, Result};
use crate::storage::tokens::{self, NewToken, Role};
use crate::storage::{Db, audit};
use serde_json::json;

/// Makes a token for `name` (spaces around it dropped; 1 to 100 characters) with `role`.
/// `created_by` is stored with the token, `actor` in the audit log.
pub async fn create(
    db: &Db,
    role: Role,
    name: &str,
    created_by: &str,
    actor: &str,
) -> Result<NewToken> {
    let name = name.trim();
    if name.is_empty() || name.chars().count() > 100 {
        return Err(Error::unprocessable("name must be 1 to 100 characters"));
    }
    let token = tokens::create(db, role, name, created_by).await?;
    audit::record(
        db,
        actor,
        "token.create",
        json!({"token_id": token.id, "name": name, "role": role}),
    )
    .await?;
    Ok(token)
}
