//! The node manager of the celld namespace: its nodes live in memory (the crate's in-memory
//! manager reads, browses and samples them); writes are refused; method calls go to
//! [`Plant::call`] for operators.

use super::address_space::{METHODS, NAMESPACE_URI, node_id};
use super::auth::{status, token_user};
use super::plant::{Plant, PlantMethod};
use async_trait::async_trait;
use opcua::server::address_space::AddressSpace;
use opcua::server::diagnostics::NamespaceMetadata;
use opcua::server::node_manager::memory::{InMemoryNodeManager, InMemoryNodeManagerImpl};
use opcua::server::node_manager::{MethodCall, RequestContext, ServerContext, WriteNode};
use opcua::sync::RwLock;
use opcua::types::{NodeId, StatusCode, Variant};

/// The node manager for the cell's nodes.
pub type CellNodeManager<P> = InMemoryNodeManager<CellNodes<P>>;

/// The celld namespace's behaviour on top of the in-memory nodes.
pub struct CellNodes<P> {
    plant: P,
    namespace: NamespaceMetadata,
}

impl<P: Plant> CellNodes<P> {
    /// Registers the celld namespace in the server and with `space`.
    pub fn new(plant: P, context: &ServerContext, space: &mut AddressSpace) -> Self {
        let index = context
            .type_tree
            .write()
            .namespaces_mut()
            .add_namespace(NAMESPACE_URI);
        space.add_namespace(NAMESPACE_URI, index);
        CellNodes {
            plant,
            namespace: NamespaceMetadata {
                namespace_uri: NAMESPACE_URI.to_string(),
                namespace_index: index,
                ..Default::default()
            },
        }
    }

    /// The namespace index of the cell's nodes.
    pub fn namespace_index(&self) -> u16 {
        self.namespace.namespace_index
    }

    /// The method `method_id` with `arguments` as a [`PlantMethod`], or the status that refuses
    /// it.
    fn parse(&self, method_id: &NodeId, arguments: &[Variant]) -> Result<PlantMethod, StatusCode> {
        let ns = self.namespace.namespace_index;
        let Some(name) = METHODS.into_iter().find(|m| node_id(ns, m) == *method_id) else {
            return Err(StatusCode::BadMethodInvalid);
        };
        parse_method(name, arguments)
    }
}

/// A method by its browse name and arguments. Start takes Controller (String) and Seed (an
/// integer; negative: a random seed); the others take nothing.
pub fn parse_method(name: &str, arguments: &[Variant]) -> Result<PlantMethod, StatusCode> {
    let expected = if name == "Start" { 2 } else { 0 };
    if arguments.len() < expected {
        return Err(StatusCode::BadArgumentsMissing);
    }
    if arguments.len() > expected {
        return Err(StatusCode::BadTooManyArguments);
    }
    Ok(match name {
        "Start" => {
            let controller = match &arguments[0] {
                Variant::String(s) if !s.is_null() && !s.as_ref().is_empty() => s.to_string(),
                _ => return Err(StatusCode::BadInvalidArgument),
            };
            let seed = integer(&arguments[1]).ok_or(StatusCode::BadTypeMismatch)?;
            PlantMethod::Start {
                controller,
                seed: u64::try_from(seed).ok(),
            }
        }
        "Stop" => PlantMethod::Stop,
        "Abort" => PlantMethod::Abort,
        "Reset" => PlantMethod::Reset,
        "Clear" => PlantMethod::Clear,
        _ => return Err(StatusCode::BadMethodInvalid),
    })
}

/// Any OPC UA integer as i64 (a UInt64 beyond i64 is refused).
fn integer(value: &Variant) -> Option<i64> {
    match *value {
        Variant::SByte(n) => Some(n.into()),
        Variant::Byte(n) => Some(n.into()),
        Variant::Int16(n) => Some(n.into()),
        Variant::UInt16(n) => Some(n.into()),
        Variant::Int32(n) => Some(n.into()),
        Variant::UInt32(n) => Some(n.into()),
        Variant::Int64(n) => Some(n),
        Variant::UInt64(n) => i64::try_from(n).ok(),
        _ => None,
    }
}

#[async_trait]
impl<P: Plant> InMemoryNodeManagerImpl for CellNodes<P> {
    async fn init(&self, _space: &mut AddressSpace, _context: ServerContext) {}

    fn name(&self) -> &str {
        "celld"
    }

    fn namespaces(&self) -> Vec<NamespaceMetadata> {
        vec![self.namespace.clone()]
    }

    /// Every variable is the cell's to change, never a client's.
    async fn write(
        &self,
        _context: &RequestContext,
        _space: &RwLock<AddressSpace>,
        nodes_to_write: &mut [&mut WriteNode],
    ) -> Result<(), StatusCode> {
        for node in nodes_to_write {
            node.set_status(StatusCode::BadNotWritable);
        }
        Ok(())
    }

    async fn call(
        &self,
        context: &RequestContext,
        _space: &RwLock<AddressSpace>,
        methods_to_call: &mut [&mut &mut MethodCall],
    ) -> Result<(), StatusCode> {
        for call in methods_to_call.iter_mut() {
            // The server checked `is_user_executable` already; this holds without it.
            let Some(user) = token_user(&context.token).filter(|u| u.may_operate) else {
                call.set_status(StatusCode::BadUserAccessDenied);
                continue;
            };
            let method = match self.parse(call.method_id(), call.arguments()) {
                Ok(method) => method,
                Err(code) => {
                    call.set_status(code);
                    continue;
                }
            };
            let is_start = matches!(method, PlantMethod::Start { .. });
            tracing::info!(user = %user.name, ?method, "OPC UA method call");
            match self.plant.call(&user, method).await {
                Ok(job) => {
                    if is_start {
                        call.set_outputs(vec![Variant::Int64(job.unwrap_or(0))]);
                    }
                    call.set_status(StatusCode::Good);
                }
                Err(refused) => {
                    tracing::info!(user = %user.name, "OPC UA method refused: {refused}");
                    call.set_status(status(&refused));
                }
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn start_takes_a_controller_and_a_seed() {
        assert_eq!(
            parse_method("Start", &[Variant::from("expert"), Variant::Int64(42)]),
            Ok(PlantMethod::Start {
                controller: "expert".into(),
                seed: Some(42)
            })
        );
        assert_eq!(
            parse_method("Start", &[Variant::from("expert"), Variant::Int32(-1)]),
            Ok(PlantMethod::Start {
                controller: "expert".into(),
                seed: None
            }),
            "a negative seed means a random one"
        );
        assert_eq!(
            parse_method("Start", &[Variant::from("expert")]),
            Err(StatusCode::BadArgumentsMissing)
        );
        assert_eq!(
            parse_method("Start", &[Variant::from(""), Variant::Int64(1)]),
            Err(StatusCode::BadInvalidArgument)
        );
        assert_eq!(
            parse_method("Start", &[Variant::from("expert"), Variant::from("x")]),
            Err(StatusCode::BadTypeMismatch)
        );
        assert_eq!(
            parse_method("Start", &[Variant::from("a"), Variant::UInt64(u64::MAX)]),
            Err(StatusCode::BadTypeMismatch)
        );
        assert_eq!(parse_method("Abort", &[]), Ok(PlantMethod::Abort));
        assert_eq!(
            parse_method("Stop", &[Variant::Int64(1)]),
            Err(StatusCode::BadTooManyArguments)
        );
    }
}
