//! API tokens: made (the secret shown once, stored as a hash), listed, revoked and audited, for
//! the API, the first start and `celld token` alike; and the check of a presented secret, with
//! the cache of the callers already looked up.

use super::{Context, Error, Result};
use crate::storage::tokens::{self, Caller, NewToken, Role, TokenInfo};
use crate::storage::{Db, audit};
use serde_json::json;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

/// Longest life a token may be given at creation, s (ten years).
pub const MAX_EXPIRES_IN_S: u64 = 10 * 365 * 24 * 3600;

/// How long a cached caller is trusted before its row is read again: the delay before a
/// revocation made elsewhere (`celld token revoke` on the database of a running service)
/// takes effect. One made through the API evicts the cache at once.
pub const RECHECK: Duration = Duration::from_secs(2);

/// A caller whose token was found valid, as cached by the hash of its secret.
#[derive(Debug, Clone)]
pub struct KnownCaller {
    caller: Caller,
    /// When the token stops authenticating, ms since the Unix epoch.
    expires_unix_ms: Option<i64>,
    /// When its row was last read.
    checked_at: Instant,
}

/// Why a presented secret authenticates nobody (401), or the lookup failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum AuthError {
    #[error("unknown token")]
    Unknown,
    #[error("token `{name}` was revoked at {at}")]
    Revoked { name: String, at: String },
    #[error("token `{name}` expired at {at}")]
    Expired { name: String, at: String },
    #[error("storage: {0}")]
    Storage(String),
}

/// Makes a token for `name` (spaces around it dropped; 1 to 100 characters) with `role`,
/// expiring `expires_in_s` from now (1..=[`MAX_EXPIRES_IN_S`]) when given. `created_by` is
/// stored with the token, `actor` in the audit log.
pub async fn create(
    db: &Db,
    role: Role,
    name: &str,
    expires_in_s: Option<u64>,
    created_by: &str,
    actor: &str,
) -> Result<NewToken> {
    let name = name.trim();
    if name.is_empty() || name.chars().count() > 100 {
        return Err(Error::unprocessable("name must be 1 to 100 characters"));
    }
    if let Some(seconds) = expires_in_s
        && !(1..=MAX_EXPIRES_IN_S).contains(&seconds)
    {
        return Err(Error::unprocessable(format!(
            "expires_in_s = {seconds} is outside 1..={MAX_EXPIRES_IN_S}"
        )));
    }
    let token = tokens::create(db, role, name, created_by, expires_in_s).await?;
    audit::record(
        db,
        actor,
        "token.create",
        json!({"token_id": token.id, "name": name, "role": role, "expires_at": token.expires_at}),
    )
    .await?;
    Ok(token)
}

/// A lifetime as `celld token create --expires-in` takes it: whole seconds, or a number with
/// `s`, `m`, `h` or `d` (`90m`, `30d`); in seconds.
pub fn parse_lifetime(text: &str) -> std::result::Result<u64, String> {
    let text = text.trim();
    let (number, unit) = match text.char_indices().last() {
        Some((at, unit @ ('s' | 'm' | 'h' | 'd'))) => (&text[..at], unit),
        _ => (text, 's'),
    };
    let count: u64 = number.parse().map_err(|_| {
        format!("`{text}` is not a lifetime: whole seconds, or a number with s, m, h or d")
    })?;
    let unit_s = match unit {
        'm' => 60,
        'h' => 3600,
        'd' => 86_400,
        _ => 1,
    };
    count
        .checked_mul(unit_s)
        .filter(|s| (1..=MAX_EXPIRES_IN_S).contains(s))
        .ok_or_else(|| format!("`{text}` is outside 1 s..={MAX_EXPIRES_IN_S} s"))
}

/// Every token, oldest first, without secrets.
pub async fn list(db: &Db) -> Result<Vec<TokenInfo>> {
    Ok(tokens::list(db).await?)
}

/// Revokes token `id` in storage and audits it; revoking a revoked token answers it as it is.
/// The last admin token that still authenticates is refused ([`Error::Conflict`]): with it
/// gone nobody could make or revoke tokens over the API.
pub async fn revoke_stored(db: &Db, id: i64, by: &str) -> Result<TokenInfo> {
    let found = tokens::get(db, id)
        .await?
        .ok_or_else(|| Error::not_found(format!("no token with id {id}")))?;
    if found.revoked_at.is_some() {
        return Ok(found);
    }
    if !tokens::revoke(db, id, by).await? {
        let now = tokens::get(db, id).await?;
        return match now {
            Some(info) if info.revoked_at.is_some() => Ok(info),
            _ => Err(Error::conflict(format!(
                "token {id} (`{}`) is the last admin token that authenticates: make another \
                 admin token first (POST /api/tokens or `celld token create --role admin`)",
                found.name
            ))),
        };
    }
    audit::record(
        db,
        by,
        "token.revoke",
        json!({"token_id": id, "name": found.name, "role": found.role}),
    )
    .await?;
    tokens::get(db, id)
        .await?
        .ok_or_else(|| Error::not_found(format!("no token with id {id}")))
}

/// [`revoke_stored`] by `caller`, and the token forgotten by this service's cache, so that its
/// next request is refused. A token does not revoke itself (409): another admin token does, so
/// a revocation over the API always leaves an admin that can make the next token.
pub async fn revoke(context: &Context, id: i64, caller: &Caller) -> Result<TokenInfo> {
    if caller.token_id == id {
        return Err(Error::conflict(format!(
            "token {id} (`{}`) is the one making this request: revoke it with another admin \
             token, or with `celld token revoke {id}`",
            caller.name
        )));
    }
    let info = revoke_stored(&context.db, id, &caller.name).await?;
    if let Ok(mut known) = context.known_callers.write() {
        known.retain(|_, k| k.caller.token_id != id);
    }
    Ok(info)
}

/// Milliseconds since the Unix epoch, now.
fn now_unix_ms() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as i64)
}

/// The caller a presented secret names, if its token neither is revoked nor has expired: from
/// the cache while its row was read under [`RECHECK`] ago (the expiry checked every time),
/// else from storage.
pub async fn authenticate(
    context: &Context,
    secret: &str,
) -> std::result::Result<Caller, AuthError> {
    authenticate_hash(context, &tokens::hash(secret)).await
}

/// [`authenticate`] by the secret's hash, for a session that keeps the hash rather than the
/// secret (OPC UA's).
pub async fn authenticate_hash(
    context: &Context,
    hash: &str,
) -> std::result::Result<Caller, AuthError> {
    let hash = hash.to_string();
    let now = Instant::now();
    let known = context
        .known_callers
        .read()
        .ok()
        .and_then(|k| k.get(&hash).cloned());
    if let Some(known) = known
        && now.duration_since(known.checked_at) < RECHECK
        && known.expires_unix_ms.is_none_or(|at| now_unix_ms() < at)
    {
        return Ok(known.caller);
    }
    let found = tokens::find_by_hash(&context.db, &hash)
        .await
        .map_err(|e| AuthError::Storage(e.to_string()))?
        // Tokens are fleet-wide: one another cell made, as the fleet last told this one.
        .or_else(|| context.fleet.as_ref().and_then(|link| link.token(&hash)));
    let refused = match &found {
        None => Some(AuthError::Unknown),
        Some(found) => match (&found.revoked_at, &found.expires_at, found.expires_unix_ms) {
            (Some(at), _, _) => Some(AuthError::Revoked {
                name: found.caller.name.clone(),
                at: at.clone(),
            }),
            (None, Some(at), Some(ms)) if now_unix_ms() >= ms => Some(AuthError::Expired {
                name: found.caller.name.clone(),
                at: at.clone(),
            }),
            _ => None,
        },
    };
    if let Ok(mut known) = context.known_callers.write() {
        match (&refused, &found) {
            (None, Some(found)) => {
                known.insert(
                    hash,
                    KnownCaller {
                        caller: found.caller.clone(),
                        expires_unix_ms: found.expires_unix_ms,
                        checked_at: now,
                    },
                );
            }
            _ => {
                known.remove(&hash);
            }
        }
    }
    match (refused, found) {
        (Some(refused), _) => Err(refused),
        (None, Some(found)) => Ok(found.caller),
        (None, None) => Err(AuthError::Unknown),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_lifetime_is_seconds_or_a_number_with_its_unit() {
        assert_eq!(parse_lifetime("3600"), Ok(3600));
        assert_eq!(parse_lifetime("45s"), Ok(45));
        assert_eq!(parse_lifetime("90m"), Ok(5400));
        assert_eq!(parse_lifetime(" 12h "), Ok(43_200));
        assert_eq!(parse_lifetime("30d"), Ok(2_592_000));
        assert_eq!(parse_lifetime("3650d"), Ok(MAX_EXPIRES_IN_S));
        for bad in [
            "",
            "d",
            "0",
            "1.5h",
            "-3",
            "2w",
            "3651d",
            "99999999999999999999d",
        ] {
            assert!(parse_lifetime(bad).is_err(), "{bad}");
        }
    }
}
