//! The cell's nodes: built once at start, then kept equal to [`PlantView`] by writing only the
//! variables whose value changed (so data-change subscriptions fire on change), and
//! [`PlantEvent`]s raised as events from the `Cell` object.

use super::plant::{Identification, PlantEvent, PlantView};
use opcua::server::address_space::{
    AccessLevel, AddressSpace, BaseEventType, EventNotifier, MethodBuilder, ObjectBuilder,
    VariableBuilder,
};
use opcua::types::{
    Argument, ByteString, DataTypeId, DataValue, DateTime, LocalizedText, NodeId, ObjectId,
    ObjectTypeId, QualifiedName, UAString, VariableTypeId, Variant,
};

/// The celld namespace.
pub const NAMESPACE_URI: &str = "urn:celld:cell";

/// The node id of the `Cell` object, or of a node below it (`path` like "PackML.Status").
pub fn node_id(ns: u16, path: &str) -> NodeId {
    if path.is_empty() {
        NodeId::new(ns, "Cell")
    } else {
        NodeId::new(ns, format!("Cell.{path}"))
    }
}

/// A variable mirrored from the view.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Field {
    StateCurrent,
    StateCurrentName,
    UnitModeCurrent,
    UnitModeCurrentName,
    StopReasonId,
    StopReasonValue,
    ProcessedCount,
    DefectiveCount,
    EStopCount,
    LastCycleTime,
    MeanCycleTime,
    JobId,
    JobController,
    JobStep,
    JobPoseError,
    JobSigma,
    EmergencyStop,
    DriverLatched,
    DriverLatchReason,
    ActiveAlarms,
    ActiveAlarmCount,
}

impl Field {
    pub const ALL: [Field; 21] = [
        Field::StateCurrent,
        Field::StateCurrentName,
        Field::UnitModeCurrent,
        Field::UnitModeCurrentName,
        Field::StopReasonId,
        Field::StopReasonValue,
        Field::ProcessedCount,
        Field::DefectiveCount,
        Field::EStopCount,
        Field::LastCycleTime,
        Field::MeanCycleTime,
        Field::JobId,
        Field::JobController,
        Field::JobStep,
        Field::JobPoseError,
        Field::JobSigma,
        Field::EmergencyStop,
        Field::DriverLatched,
        Field::DriverLatchReason,
        Field::ActiveAlarms,
        Field::ActiveAlarmCount,
    ];

    /// The parent object's path below `Cell`, the browse name and the data type.
    pub fn place(self) -> (&'static str, &'static str, DataTypeId) {
        use DataTypeId as T;
        match self {
            Field::StateCurrent => ("PackML.Status", "StateCurrent", T::Int32),
            Field::StateCurrentName => ("PackML.Status", "StateCurrentName", T::String),
            Field::UnitModeCurrent => ("PackML.Status", "UnitModeCurrent", T::Int32),
            Field::UnitModeCurrentName => ("PackML.Status", "UnitModeCurrentName", T::String),
            Field::StopReasonId => ("PackML.Status.StopReason", "ID", T::Int32),
            Field::StopReasonValue => ("PackML.Status.StopReason", "Value", T::String),
            Field::ProcessedCount => ("PackML.Admin", "ProdProcessedCount", T::UInt64),
            Field::DefectiveCount => ("PackML.Admin", "ProdDefectiveCount", T::UInt64),
            Field::EStopCount => ("PackML.Admin", "EStopCount", T::UInt64),
            Field::LastCycleTime => ("PackML.Admin", "LastCycleTime", T::Double),
            Field::MeanCycleTime => ("PackML.Admin", "MeanCycleTime", T::Double),
            Field::JobId => ("Job", "Id", T::Int64),
            Field::JobController => ("Job", "Controller", T::String),
            Field::JobStep => ("Job", "Step", T::UInt32),
            Field::JobPoseError => ("Job", "PoseErrorMm", T::Double),
            Field::JobSigma => ("Job", "SigmaMm", T::Double),
            Field::EmergencyStop => ("Safety", "EmergencyStop", T::Boolean),
            Field::DriverLatched => ("Safety", "DriverLatched", T::Boolean),
            Field::DriverLatchReason => ("Safety", "DriverLatchReason", T::String),
            Field::ActiveAlarms => ("Alarms", "ActiveAlarms", T::String),
            Field::ActiveAlarmCount => ("Alarms", "ActiveAlarmCount", T::UInt32),
        }
    }

    /// The variable's path below `Cell` ("PackML.Status.StateCurrent").
    pub fn path(self) -> String {
        let (parent, name, _) = self.place();
        format!("{parent}.{name}")
    }

    /// Its value in `view`. Numbers that do not fit the OPC UA type saturate.
    pub fn value(self, view: &PlantView) -> Variant {
        let job = view.job.as_ref();
        let saturate = |n: u32| Variant::Int32(i32::try_from(n).unwrap_or(i32::MAX));
        match self {
            Field::StateCurrent => saturate(view.state_number),
            Field::StateCurrentName => Variant::from(view.state.as_str()),
            Field::UnitModeCurrent => saturate(view.unit_mode_number),
            Field::UnitModeCurrentName => Variant::from(view.unit_mode.as_str()),
            Field::StopReasonId => Variant::Int32(view.stop_reason_code),
            Field::StopReasonValue => Variant::from(view.stop_reason.as_str()),
            Field::ProcessedCount => Variant::UInt64(view.processed_count),
            Field::DefectiveCount => Variant::UInt64(view.defective_count),
            Field::EStopCount => Variant::UInt64(view.estop_count),
            Field::LastCycleTime => Variant::Double(view.last_cycle_time_s),
            Field::MeanCycleTime => Variant::Double(view.mean_cycle_time_s),
            Field::JobId => Variant::Int64(job.map_or(0, |j| j.id)),
            Field::JobController => Variant::from(job.map_or("", |j| j.controller.as_str())),
            Field::JobStep => Variant::UInt32(job.map_or(0, |j| j.step)),
            Field::JobPoseError => Variant::Double(job.map_or(0.0, |j| j.pose_error_mm)),
            Field::JobSigma => Variant::Double(job.map_or(0.0, |j| j.sigma_mm)),
            Field::EmergencyStop => Variant::Boolean(view.emergency_stop),
            Field::DriverLatched => Variant::Boolean(view.driver_latched),
            Field::DriverLatchReason => Variant::from(view.driver_latch_reason.as_str()),
            Field::ActiveAlarms => Variant::from(
                view.alarms
                    .iter()
                    .map(|a| {
                        let kind = if a.warning { "warning" } else { "alarm" };
                        format!(
                            "{} ({kind}, severity {}): {}",
                            a.code, a.severity, a.message
                        )
                    })
                    .collect::<Vec<String>>(),
            ),
            Field::ActiveAlarmCount => {
                Variant::UInt32(u32::try_from(view.alarms.len()).unwrap_or(u32::MAX))
            }
        }
    }
}

/// The variables whose value differs between `old` and `new`, with the new value. A NaN that
/// stays NaN is no change.
pub fn changes(old: &PlantView, new: &PlantView) -> Vec<(Field, Variant)> {
    Field::ALL
        .into_iter()
        .filter_map(|field| {
            let (before, after) = (field.value(old), field.value(new));
            let same = match (&before, &after) {
                (Variant::Double(a), Variant::Double(b)) => a == b || (a.is_nan() && b.is_nan()),
                _ => before == after,
            };
            (!same).then_some((field, after))
        })
        .collect()
}

/// The objects below `Cell`, parents first.
const OBJECTS: [&str; 8] = [
    "Identification",
    "PackML",
    "PackML.Status",
    "PackML.Status.StopReason",
    "PackML.Admin",
    "Job",
    "Safety",
    "Alarms",
];

/// The methods on `Cell`.
pub const METHODS: [&str; 5] = ["Start", "Stop", "Abort", "Reset", "Clear"];

/// Builds the `Cell` object and everything below it in namespace `ns`, with the values of
/// `view`.
pub fn build(space: &mut AddressSpace, ns: u16, id: &Identification, view: &PlantView) {
    let cell = node_id(ns, "");
    let display = if id.cell_name.is_empty() {
        "Cell"
    } else {
        id.cell_name.as_str()
    };
    ObjectBuilder::new(&cell, QualifiedName::new(ns, "Cell"), display)
        .description("The assembly cell (celld)")
        .event_notifier(EventNotifier::SUBSCRIBE_TO_EVENTS)
        .organized_by(ObjectId::ObjectsFolder)
        .has_type_definition(ObjectTypeId::BaseObjectType)
        .insert(space);
    for path in OBJECTS {
        let (parent, name) = path.rsplit_once('.').unwrap_or(("", path));
        ObjectBuilder::new(&node_id(ns, path), QualifiedName::new(ns, name), name)
            .component_of(node_id(ns, parent))
            .has_type_definition(ObjectTypeId::BaseObjectType)
            .insert(space);
    }

    let identification: [(&str, Variant, DataTypeId); 6] = [
        (
            "Manufacturer",
            LocalizedText::from(id.manufacturer.as_str()).into(),
            DataTypeId::LocalizedText,
        ),
        (
            "Model",
            LocalizedText::from(id.model.as_str()).into(),
            DataTypeId::LocalizedText,
        ),
        (
            "ProductInstanceUri",
            id.product_instance_uri.as_str().into(),
            DataTypeId::String,
        ),
        (
            "SerialNumber",
            id.serial_number.as_str().into(),
            DataTypeId::String,
        ),
        (
            "SoftwareRevision",
            id.software_revision.as_str().into(),
            DataTypeId::String,
        ),
        (
            "ComponentName",
            LocalizedText::from(id.cell_name.as_str()).into(),
            DataTypeId::LocalizedText,
        ),
    ];
    for (name, value, data_type) in identification {
        variable(space, ns, "Identification", name, data_type, value, false);
    }
    for field in Field::ALL {
        let (parent, name, data_type) = field.place();
        let array = field == Field::ActiveAlarms;
        variable(space, ns, parent, name, data_type, field.value(view), array);
    }

    for name in METHODS {
        let method = node_id(ns, name);
        let mut builder = MethodBuilder::new(&method, QualifiedName::new(ns, name), name)
            .component_of(cell.clone())
            .executable(true)
            .user_executable(true);
        if name == "Start" {
            let inputs: [Argument; 2] = [
                ("Controller", DataTypeId::String).into(),
                ("Seed", DataTypeId::Int64).into(),
            ];
            let outputs: [Argument; 1] = [("JobId", DataTypeId::Int64).into()];
            builder = builder
                .input_args(space, &node_id(ns, "Start.InputArguments"), &inputs)
                .output_args(space, &node_id(ns, "Start.OutputArguments"), &outputs);
        }
        builder.insert(space);
    }
}

/// A read-only variable.
fn variable(
    space: &mut AddressSpace,
    ns: u16,
    parent: &str,
    name: &str,
    data_type: DataTypeId,
    value: Variant,
    array: bool,
) {
    let id = node_id(ns, &format!("{parent}.{name}"));
    let mut builder = VariableBuilder::new(&id, QualifiedName::new(ns, name), name)
        .data_type(data_type)
        .value(value)
        .access_level(AccessLevel::CURRENT_READ)
        .user_access_level(AccessLevel::CURRENT_READ)
        .component_of(node_id(ns, parent))
        .has_type_definition(VariableTypeId::BaseDataVariableType);
    if array {
        builder = builder.value_rank(1).array_dimensions(&[0]);
    }
    builder.insert(space);
}

/// The value of a change at `time` (its source and server timestamp).
pub fn data_value(value: Variant, time: DateTime) -> DataValue {
    DataValue::new_at(value, time)
}

/// Severity of a job's end and of a cleared alarm: low (OPC UA 1-200).
pub const LOW_SEVERITY: u16 = 100;

/// The OPC UA event for `event`, raised by `source` (the `Cell` object) at `time`; `number`
/// makes its EventId unique.
pub fn event(
    event: &PlantEvent,
    source: &NodeId,
    source_name: &str,
    number: u64,
    time: DateTime,
) -> BaseEventType {
    let (message, severity) = match event {
        PlantEvent::JobEnded {
            id,
            status,
            reason,
            steps,
            cycle_time_s,
        } => {
            let mut text = format!("job {id} ended: {status} after {steps} steps");
            if let Some(seconds) = cycle_time_s {
                text.push_str(&format!(" in {seconds:.1} s"));
            }
            if let Some(reason) = reason {
                text.push_str(&format!(" ({reason})"));
            }
            (text, LOW_SEVERITY)
        }
        PlantEvent::Alarm { alarm, active } => {
            let kind = if alarm.warning { "warning" } else { "alarm" };
            if *active {
                (
                    format!("{kind} {}: {}", alarm.code, alarm.message),
                    alarm.severity.clamp(1, 1000),
                )
            } else {
                (
                    format!("{kind} {} cleared: {}", alarm.code, alarm.message),
                    LOW_SEVERITY,
                )
            }
        }
    };
    let mut id = b"celld".to_vec();
    id.extend_from_slice(&time.checked_ticks().to_be_bytes());
    id.extend_from_slice(&number.to_be_bytes());
    BaseEventType::new(
        ObjectTypeId::BaseEventType,
        ByteString::from(id),
        LocalizedText::from(message.as_str()),
        time,
    )
    .set_source_node(source.clone())
    .set_source_name(UAString::from(source_name))
    .set_severity(severity)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::opcua::plant::{PlantAlarm, PlantJob};

    #[test]
    fn only_changed_variables_are_written() {
        let old = PlantView {
            state: "Idle".into(),
            state_number: 4,
            processed_count: 7,
            last_cycle_time_s: f64::NAN,
            ..PlantView::default()
        };
        assert!(changes(&old, &old.clone()).is_empty(), "NaN stays NaN");

        let mut new = old.clone();
        new.state = "Execute".into();
        new.state_number = 6;
        new.processed_count = 8;
        let changed = changes(&old, &new);
        assert_eq!(
            changed,
            vec![
                (Field::StateCurrent, Variant::Int32(6)),
                (Field::StateCurrentName, Variant::from("Execute")),
                (Field::ProcessedCount, Variant::UInt64(8)),
            ]
        );

        // A job appearing changes its five variables; an alarm its two.
        let mut with_job = new.clone();
        with_job.job = Some(PlantJob {
            id: 12,
            controller: "expert".into(),
            step: 3,
            pose_error_mm: 0.25,
            sigma_mm: 0.01,
        });
        with_job.alarms.push(PlantAlarm {
            code: "E1".into(),
            severity: 700,
            message: "hot".into(),
            warning: false,
        });
        let fields: Vec<Field> = changes(&new, &with_job).into_iter().map(|c| c.0).collect();
        assert_eq!(
            fields,
            vec![
                Field::JobId,
                Field::JobController,
                Field::JobStep,
                Field::JobPoseError,
                Field::JobSigma,
                Field::ActiveAlarms,
                Field::ActiveAlarmCount,
            ]
        );
        assert_eq!(
            Field::ActiveAlarms.value(&with_job),
            Variant::from(vec!["E1 (alarm, severity 700): hot".to_string()])
        );
        // The job ends: its id goes back to 0, as before it began.
        assert_eq!(Field::JobId.value(&new), Variant::Int64(0));
    }

    #[test]
    fn numbers_beyond_the_opcua_type_saturate() {
        let view = PlantView {
            state_number: u32::MAX,
            ..PlantView::default()
        };
        assert_eq!(Field::StateCurrent.value(&view), Variant::Int32(i32::MAX));
    }

    #[test]
    fn paths_are_unique_and_below_known_objects() {
        let mut paths: Vec<String> = Field::ALL.iter().map(|f| f.path()).collect();
        for field in Field::ALL {
            assert!(OBJECTS.contains(&field.place().0), "{field:?}");
        }
        paths.sort();
        paths.dedup();
        assert_eq!(paths.len(), Field::ALL.len());
        assert_eq!(
            Field::StateCurrent.path(),
            "PackML.Status.StateCurrent",
            "OPC 30050's browse path"
        );
    }

    #[test]
    fn events_carry_message_and_severity() {
        let source = node_id(2, "");
        let time = DateTime::now();
        let ended = PlantEvent::JobEnded {
            id: 5,
            status: "succeeded".into(),
            reason: None,
            steps: 40,
            cycle_time_s: Some(12.34),
        };
        let e = event(&ended, &source, "Cell", 1, time);
        assert_eq!(e.severity, LOW_SEVERITY);
        assert_eq!(
            e.message.text.as_ref(),
            "job 5 ended: succeeded after 40 steps in 12.3 s"
        );
        assert_eq!(e.source_node, source);
        let alarm = PlantAlarm {
            code: "E7".into(),
            severity: 2000,
            message: "door open".into(),
            warning: false,
        };
        let raised = PlantEvent::Alarm {
            alarm: alarm.clone(),
            active: true,
        };
        let e2 = event(&raised, &source, "Cell", 2, time);
        assert_eq!(e2.severity, 1000, "clamped to OPC UA's range");
        assert_eq!(e2.message.text.as_ref(), "alarm E7: door open");
        assert_ne!(e.event_id, e2.event_id);
        let cleared = PlantEvent::Alarm {
            alarm,
            active: false,
        };
        assert_eq!(
            event(&cleared, &source, "Cell", 3, time).severity,
            LOW_SEVERITY
        );
    }
}
