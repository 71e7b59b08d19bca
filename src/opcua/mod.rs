//! The OPC UA server: a plant's PLC or SCADA sees and commands the cell (async-opcua, pure
//! Rust on tokio). It knows the cell only through [`Plant`]; [`cell::CellPlant`] implements it
//! over the running service.
//!
//! Browse tree, in namespace `urn:celld:cell` under Objects (browse names from OPC 30050 PackML,
//! OPC 40001-1 Machinery and OPC 40010-1 Robotics where they fit; every variable read-only):
//!
//! ```text
//! Cell                              events: job ends (severity 100), alarms (their severity)
//! ├─ Identification                 Manufacturer, Model, ProductInstanceUri, SerialNumber,
//! │                                 SoftwareRevision, ComponentName (the cell's name)
//! ├─ PackML
//! │  ├─ Status                      StateCurrent (Int32), StateCurrentName, UnitModeCurrent,
//! │  │  │                           UnitModeCurrentName
//! │  │  └─ StopReason               ID (Int32, 0: none), Value (message)
//! │  └─ Admin                       ProdProcessedCount, ProdDefectiveCount, EStopCount (UInt64),
//! │                                 LastCycleTime, MeanCycleTime (Double, s)
//! ├─ Job                            Id (Int64, 0: none), Controller, Step, PoseErrorMm, SigmaMm
//! ├─ Safety                         EmergencyStop, DriverLatched (Boolean), DriverLatchReason
//! ├─ Alarms                         ActiveAlarms (String[]), ActiveAlarmCount
//! └─ Start(Controller String, Seed Int64 < 0: random) -> JobId Int64;
//!    Stop(), Abort(), Reset(), Clear()        operators only, else BadUserAccessDenied
//! ```
//!
//! Endpoints, certificates and sign-in: see [`server`].

pub mod address_space;
pub mod auth;
pub mod cell;
pub mod methods;
pub mod plant;
pub mod server;

pub use plant::{
    Identification, Plant, PlantAlarm, PlantEvent, PlantJob, PlantMethod, PlantUser, PlantView,
    Refused,
};
pub use server::{OpcUaServer, OpcUaSettings, serve};
