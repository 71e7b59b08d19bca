//! Who may sign in and what they may do: user name and password (a celld API token), checked by
//! [`Plant::sign_in`]; no anonymous sign-in. Everyone signed in reads, browses and subscribes;
//! only operators may call the cell's methods.

use super::plant::{Plant, PlantUser, Refused};
use async_trait::async_trait;
use opcua::server::ServerEndpoint;
use opcua::server::authenticator::{
    AuthManager, Password, UserToken, user_pass_security_policy_id, user_pass_security_policy_uri,
};
use opcua::types::{Error, NodeId, StatusCode, UAString, UserTokenPolicy, UserTokenType};

/// The [`AuthManager`] over [`Plant::sign_in`].
pub struct PlantAuth<P> {
    plant: P,
}

impl<P: Plant> PlantAuth<P> {
    pub fn new(plant: P) -> Self {
        PlantAuth { plant }
    }
}

const OPERATOR: &str = "operator:";
const VIEWER: &str = "viewer:";

/// The server's token for `user`: its role, key and name (two sessions of one user share it).
pub fn user_token(user: &PlantUser) -> UserToken {
    let role = if user.may_operate { OPERATOR } else { VIEWER };
    UserToken(format!("{role}{}:{}", user.key, user.name))
}

/// The user a token stands for; none for a token this module did not make (anonymous).
pub fn token_user(token: &UserToken) -> Option<PlantUser> {
    let (may_operate, rest) = match token.0.strip_prefix(OPERATOR) {
        Some(rest) => (true, rest),
        None => (false, token.0.strip_prefix(VIEWER)?),
    };
    let (key, name) = rest.split_once(':')?;
    Some(PlantUser {
        name: name.to_string(),
        may_operate,
        key: key.to_string(),
    })
}

/// The OPC UA status for a refusal.
pub fn status(refused: &Refused) -> StatusCode {
    match refused {
        Refused::BadIdentity(_) | Refused::NotAllowed(_) => StatusCode::BadUserAccessDenied,
        Refused::InvalidState(_) => StatusCode::BadInvalidState,
        Refused::InvalidArgument(_) => StatusCode::BadInvalidArgument,
        Refused::Unavailable(_) => StatusCode::BadResourceUnavailable,
    }
}

#[async_trait]
impl<P: Plant> AuthManager for PlantAuth<P> {
    async fn authenticate_username_identity_token(
        &self,
        _endpoint: &ServerEndpoint,
        username: &str,
        password: &Password,
    ) -> Result<UserToken, Error> {
        match self.plant.sign_in(username, password.get()).await {
            Ok(user) => Ok(user_token(&user)),
            Err(refused) => {
                tracing::info!(user = username, "OPC UA sign-in refused: {refused}");
                Err(Error::new(status(&refused), refused.to_string()))
            }
        }
    }

    /// The cell's methods (outside namespace 0) only for operators; the standard ones (namespace
    /// 0, such as GetMonitoredItems) for everyone signed in.
    fn is_user_executable(&self, token: &UserToken, method_id: &NodeId) -> bool {
        method_id.namespace == 0 || token_user(token).is_some_and(|u| u.may_operate)
    }

    fn user_token_policies(&self, endpoint: &ServerEndpoint) -> Vec<UserTokenPolicy> {
        vec![UserTokenPolicy {
            policy_id: user_pass_security_policy_id(endpoint),
            token_type: UserTokenType::UserName,
            issued_token_type: UAString::null(),
            issuer_endpoint_url: UAString::null(),
            security_policy_uri: user_pass_security_policy_uri(endpoint),
        }]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tokens_round_trip_and_anonymous_is_nobody() {
        for user in [
            PlantUser {
                name: "ada".into(),
                may_operate: true,
                key: "9f2c".into(),
            },
            PlantUser {
                name: "viewer:odd".into(),
                may_operate: false,
                key: "77".into(),
            },
        ] {
            assert_eq!(token_user(&user_token(&user)), Some(user));
        }
        assert_eq!(token_user(&UserToken("ANONYMOUS".into())), None);
    }

    #[test]
    fn refusals_map_to_their_status() {
        assert_eq!(
            status(&Refused::NotAllowed("x".into())),
            StatusCode::BadUserAccessDenied
        );
        assert_eq!(
            status(&Refused::InvalidState("x".into())),
            StatusCode::BadInvalidState
        );
        assert_eq!(
            status(&Refused::Unavailable("x".into())),
            StatusCode::BadResourceUnavailable
        );
    }
}
