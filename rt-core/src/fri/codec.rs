//! Encoding and decoding FRI datagrams (versions 1.11 to 2.7) without
//! allocating per message.
//!
//! Every encoder and decoder speaks one [`FriVersion`] (`new()`: 1.15): 2.7
//! datagrams are framed (length + CRC-32, [`super::framing`]); after decoding,
//! the fields the version does not define are dropped (a decoder of that
//! version's schema skips them as unknown), and the encoders write only fields
//! the version defines.
//!
//! [`MonitoringDecoder`] and [`CommandDecoder`] decode into a message they keep
//! and reuse (the joint arrays keep their capacity), check proto2's required
//! fields and the 7-value joint arrays, and return a fixed-size, `Copy` view
//! ([`Monitoring`], [`Command`]). [`MonitoringEncoder`] and [`CommandEncoder`]
//! write into a fixed 1500-byte buffer they own. Only IO values and
//! transformations (which isochron neither sends nor asks for) allocate when
//! they appear in a datagram.

use prost::Message;

use super::framing::{FRAME_OVERHEAD, FrameError, frame_in_place, unframe};
use super::proto::{
    ClientCommandMode, ConnectionInfo, ConnectionQuality, ControlMode, DriveState,
    FriCommandMessage, FriMonitoringMessage, JointValues, MessageCommandData, MessageHeader,
    MessageIpoData, MessageMonitorData, OperationMode, OverlayType, RobotInfo, SafetyState,
    SessionState, TimeStamp,
};
use super::version::FriVersion;
use crate::kinematics::iiwa7::JOINTS;

/// `header.messageIdentifier` of a monitoring message (controller -> client).
pub const MONITORING_MESSAGE_ID: u32 = 0x0024_5142;
/// `header.messageIdentifier` of a command message (client -> controller).
pub const COMMAND_MESSAGE_ID: u32 = 0x0003_4001;
/// Largest FRI datagram, bytes.
pub const MAX_DATAGRAM_BYTES: usize = 1500;

/// Seven joint values.
pub type Joints = [f64; JOINTS];

/// Why a datagram was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum CodecError {
    /// Longer than an FRI datagram may be.
    #[error("datagram of {len} bytes exceeds the FRI maximum of {MAX_DATAGRAM_BYTES}")]
    TooLong {
        /// Its length, bytes.
        len: usize,
    },
    /// Not a protobuf message of this type.
    #[error("malformed protobuf: {0}")]
    Malformed(#[from] prost::DecodeError),
    /// A field FRI declares `required` is absent.
    #[error("required field {0} is missing")]
    MissingField(&'static str),
    /// The other side speaks another message type ("incompatible IDs").
    #[error("message identifier {got:#x}, expected {expected:#x} (incompatible IDs)")]
    WrongIdentifier {
        /// The identifier in the datagram.
        got: u32,
        /// The identifier this decoder expects.
        expected: u32,
    },
    /// A joint array without exactly 7 values.
    #[error("{field} has {got} values, expected exactly 7")]
    JointCount {
        /// The field, e.g. `monitorData.measuredJointPosition`.
        field: &'static str,
        /// How many values it had.
        got: usize,
    },
    /// An enum value this FRI version does not define, in a field we act on.
    #[error("{field} = {value} is not a known value")]
    UnknownEnum {
        /// The field.
        field: &'static str,
        /// The value.
        value: i32,
    },
    /// The encoded message does not fit in one datagram.
    #[error("encoded message exceeds {MAX_DATAGRAM_BYTES} bytes")]
    EncodeOverflow,
    /// A 2.7 frame with a wrong length field or CRC-32.
    #[error("FRI 2.7 framing: {0}")]
    Frame(#[from] FrameError),
    /// A value array of the wrong size (transformations, external force).
    #[error("{field} has {got} values, expected {expected}")]
    ValueCount {
        /// The field.
        field: &'static str,
        /// How many values it had.
        got: usize,
        /// How many this version defines.
        expected: usize,
    },
}

/// Cartesian force and torque, N and N m (`externalForce`, FRI 2.7).
pub type Wrench = [f64; 6];

/// Controller time (Unix time).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct UnixTime {
    /// Seconds.
    pub sec: u32,
    /// Nanoseconds.
    pub nanosec: u32,
}

impl UnixTime {
    /// From nanoseconds since the Unix epoch (seconds wrap after 2106).
    pub const fn from_ns(ns: u64) -> Self {
        Self {
            sec: (ns / 1_000_000_000) as u32,
            nanosec: (ns % 1_000_000_000) as u32,
        }
    }
}

/// A decoded monitoring message: what the client acts on, fixed size, `Copy`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Monitoring {
    /// The controller's `sequenceCounter`.
    pub sequence_counter: u32,
    /// The `sequenceCounter` of the last command the controller received.
    pub reflected_sequence_counter: u32,
    /// `connectionInfo.sessionState`.
    pub session_state: SessionState,
    /// `connectionInfo.quality`.
    pub quality: ConnectionQuality,
    /// `connectionInfo.sendPeriod`, ms (0 when absent).
    pub send_period_ms: u32,
    /// `connectionInfo.receiveMultiplier`, normalised: missing or 0 is 1.
    pub receive_multiplier: u32,
    /// `robotInfo.safetyState`.
    pub safety_state: Option<SafetyState>,
    /// `robotInfo.operationMode`.
    pub operation_mode: Option<OperationMode>,
    /// `robotInfo.controlMode`.
    pub control_mode: Option<ControlMode>,
    /// `robotInfo.driveState`, when all 7 are present and known.
    pub drive_state: Option<[DriveState; JOINTS]>,
    /// Measured joint positions, rad.
    pub measured_joint_position_rad: Option<Joints>,
    /// Measured joint torques, N m.
    pub measured_torque_nm: Option<Joints>,
    /// The controller's commanded joint positions, rad.
    pub commanded_joint_position_rad: Option<Joints>,
    /// Commanded joint torques, N m.
    pub commanded_torque_nm: Option<Joints>,
    /// External torques, N m.
    pub external_torque_nm: Option<Joints>,
    /// External force and torque at the flange, N and N m (FRI 2.7 only).
    pub external_force: Option<Wrench>,
    /// Controller time of the measurement.
    pub timestamp: Option<UnixTime>,
    /// `ipoData.jointPosition`, rad (COMMANDING_* only).
    pub ipo_joint_position_rad: Option<Joints>,
    /// `ipoData.clientCommandMode`.
    pub client_command_mode: Option<ClientCommandMode>,
    /// `ipoData.overlayType`.
    pub overlay_type: Option<OverlayType>,
    /// `ipoData.trackingPerformance`.
    pub tracking_performance: Option<f64>,
}

impl Default for Monitoring {
    fn default() -> Self {
        Self {
            sequence_counter: 0,
            reflected_sequence_counter: 0,
            session_state: SessionState::Idle,
            quality: ConnectionQuality::Poor,
            send_period_ms: 0,
            receive_multiplier: 1,
            safety_state: None,
            operation_mode: None,
            control_mode: None,
            drive_state: None,
            measured_joint_position_rad: None,
            measured_torque_nm: None,
            commanded_joint_position_rad: None,
            commanded_torque_nm: None,
            external_torque_nm: None,
            external_force: None,
            timestamp: None,
            ipo_joint_position_rad: None,
            client_command_mode: None,
            overlay_type: None,
            tracking_performance: None,
        }
    }
}

/// A decoded command message.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Command {
    /// The client's `sequenceCounter`.
    pub sequence_counter: u32,
    /// The `sequenceCounter` of the monitoring message this answers.
    pub reflected_sequence_counter: u32,
    /// `commandData.jointPosition`, rad.
    pub joint_position_rad: Option<Joints>,
    /// `commandData.jointTorque`, N m.
    pub joint_torque_nm: Option<Joints>,
}

fn joint_values(src: &Joints) -> JointValues {
    JointValues {
        value: src.to_vec(),
    }
}

/// Reads a joint array: absent or empty is `None`, 7 values is `Some`, else an error.
fn read_joints(
    field: &'static str,
    jv: Option<&JointValues>,
) -> Result<Option<Joints>, CodecError> {
    match jv {
        None => Ok(None),
        Some(j) if j.value.is_empty() => Ok(None),
        Some(j) => match <Joints>::try_from(j.value.as_slice()) {
            Ok(a) => Ok(Some(a)),
            Err(_) => Err(CodecError::JointCount {
                field,
                got: j.value.len(),
            }),
        },
    }
}

/// Writes a joint array in place (keeping its allocation), or removes it.
fn write_joints(slot: &mut Option<JointValues>, src: Option<&Joints>) {
    match src {
        Some(q) => {
            let jv = slot.get_or_insert_with(|| JointValues {
                value: Vec::with_capacity(JOINTS),
            });
            jv.value.clear();
            jv.value.extend_from_slice(q);
        }
        None => *slot = None,
    }
}

fn check_header(h: Option<&MessageHeader>, expected: u32) -> Result<(u32, u32), CodecError> {
    let h = h.ok_or(CodecError::MissingField("header"))?;
    let id = h
        .message_identifier
        .ok_or(CodecError::MissingField("header.messageIdentifier"))?;
    let seq = h
        .sequence_counter
        .ok_or(CodecError::MissingField("header.sequenceCounter"))?;
    let refl = h
        .reflected_sequence_counter
        .ok_or(CodecError::MissingField("header.reflectedSequenceCounter"))?;
    if id != expected {
        return Err(CodecError::WrongIdentifier { got: id, expected });
    }
    Ok((seq, refl))
}

fn check_timestamp(
    field: &'static str,
    t: Option<&TimeStamp>,
) -> Result<Option<UnixTime>, CodecError> {
    match t {
        None => Ok(None),
        Some(t) => {
            let sec = t.sec.ok_or(CodecError::MissingField(field))?;
            let nanosec = t.nanosec.ok_or(CodecError::MissingField(field))?;
            Ok(Some(UnixTime { sec, nanosec }))
        }
    }
}

fn check_transformations<'a>(
    ts: impl IntoIterator<Item = &'a super::proto::Transformation>,
    version: FriVersion,
) -> Result<(), CodecError> {
    for t in ts {
        if t.name.is_none() {
            return Err(CodecError::MissingField("transformation.name"));
        }
        let expected = version.transformation_values();
        if !t.matrix.is_empty() && t.matrix.len() != expected {
            return Err(CodecError::ValueCount {
                field: "transformation values",
                got: t.matrix.len(),
                expected,
            });
        }
        check_timestamp("transformation.timestamp", t.timestamp.as_ref())?;
    }
    Ok(())
}

fn check_redundancy(r: Option<&super::proto::RedundancyInformation>) -> Result<(), CodecError> {
    match r {
        Some(r) if r.strategy.is_none() || r.value.is_none() => {
            Err(CodecError::MissingField("redundancyInformation"))
        }
        _ => Ok(()),
    }
}

/// Drops the fields `version` does not define (its decoder skips them as unknown).
fn strip_monitoring(msg: &mut FriMonitoringMessage, version: FriVersion) {
    if !version.has_end_of_message() {
        msg.end_of_message_data = None;
    }
    if let Some(md) = &mut msg.monitor_data {
        if !version.has_commanded_joint_position()
            && let Some(jv) = &mut md.commanded_joint_position
        {
            jv.value.clear();
        }
        if !version.has_external_force()
            && let Some(f) = &mut md.external_force
        {
            f.element.clear();
        }
        if !version.has_io() {
            md.read_io_request.clear();
        }
        if !version.is_2x() {
            md.measured_cartesian_pose = None;
            md.measured_redundancy_information = None;
        }
    }
    if !version.is_2x()
        && let Some(ipo) = &mut msg.ipo_data
    {
        ipo.cartesian_pose = None;
        ipo.redundancy_information = None;
    }
}

/// Drops the command fields `version` does not define.
fn strip_command(msg: &mut FriCommandMessage, version: FriVersion) {
    if !version.has_end_of_message() {
        msg.end_of_message_data = None;
    }
    if let Some(cd) = &mut msg.command_data {
        if !version.has_io() {
            cd.write_io_request.clear();
        }
        if !version.is_2x() {
            cd.cartesian_pose = None;
            cd.redundancy_information = None;
        }
    }
}

fn check_io(ios: &[super::proto::FriIoValue]) -> Result<(), CodecError> {
    for io in ios {
        if io.name.is_none() {
            return Err(CodecError::MissingField("ioValue.name"));
        }
        if io.r#type.is_none() {
            return Err(CodecError::MissingField("ioValue.type"));
        }
        if io.direction.is_none() {
            return Err(CodecError::MissingField("ioValue.direction"));
        }
    }
    Ok(())
}

fn opt_enum<E: TryFrom<i32>>(v: Option<i32>) -> Option<E> {
    v.and_then(|x| E::try_from(x).ok())
}

/// Checks a decoded monitoring message (of `version`'s fields, see
/// [`strip_monitoring`]) and returns its view.
///
/// Joint arrays that are present but empty count as absent (so a decoder that
/// reuses its message can keep their allocations).
///
/// # Errors
///
/// [`CodecError::MissingField`] for an absent required field or header;
/// [`CodecError::WrongIdentifier`] for another message type; [`CodecError::UnknownEnum`]
/// for an undefined session state or quality; [`CodecError::JointCount`] or
/// [`CodecError::ValueCount`] for an array of the wrong size.
pub fn monitoring_view(
    msg: &FriMonitoringMessage,
    version: FriVersion,
) -> Result<Monitoring, CodecError> {
    let (seq, refl) = check_header(msg.header.as_ref(), MONITORING_MESSAGE_ID)?;
    let ci = msg
        .connection_info
        .as_ref()
        .ok_or(CodecError::MissingField("connectionInfo"))?;
    let state = ci
        .session_state
        .ok_or(CodecError::MissingField("connectionInfo.sessionState"))?;
    let quality = ci
        .quality
        .ok_or(CodecError::MissingField("connectionInfo.quality"))?;
    let session_state = SessionState::try_from(state).map_err(|_| CodecError::UnknownEnum {
        field: "connectionInfo.sessionState",
        value: state,
    })?;
    let quality = ConnectionQuality::try_from(quality).map_err(|_| CodecError::UnknownEnum {
        field: "connectionInfo.quality",
        value: quality,
    })?;
    let mut v = Monitoring {
        sequence_counter: seq,
        reflected_sequence_counter: refl,
        session_state,
        quality,
        send_period_ms: ci.send_period.unwrap_or(0),
        receive_multiplier: ci.receive_multiplier.unwrap_or(1).max(1),
        ..Monitoring::default()
    };
    check_transformations(&msg.requested_transformations, version)?;
    if let Some(ri) = &msg.robot_info {
        v.safety_state = opt_enum(ri.safety_state);
        v.operation_mode = opt_enum(ri.operation_mode);
        v.control_mode = opt_enum(ri.control_mode);
        if ri.drive_state.len() == JOINTS {
            let mut ds = [DriveState::Off; JOINTS];
            let mut all = true;
            for (d, raw) in ds.iter_mut().zip(&ri.drive_state) {
                match DriveState::try_from(*raw) {
                    Ok(x) => *d = x,
                    Err(_) => all = false,
                }
            }
            v.drive_state = all.then_some(ds);
        }
    }
    if let Some(md) = &msg.monitor_data {
        v.measured_joint_position_rad = read_joints(
            "monitorData.measuredJointPosition",
            md.measured_joint_position.as_ref(),
        )?;
        v.measured_torque_nm =
            read_joints("monitorData.measuredTorque", md.measured_torque.as_ref())?;
        v.commanded_joint_position_rad = read_joints(
            "monitorData.commandedJointPosition",
            md.commanded_joint_position.as_ref(),
        )?;
        v.commanded_torque_nm =
            read_joints("monitorData.commandedTorque", md.commanded_torque.as_ref())?;
        v.external_torque_nm =
            read_joints("monitorData.externalTorque", md.external_torque.as_ref())?;
        v.timestamp = check_timestamp("monitorData.timestamp", md.timestamp.as_ref())?;
        check_io(&md.read_io_request)?;
        check_transformations(md.measured_cartesian_pose.as_ref(), version)?;
        check_redundancy(md.measured_redundancy_information.as_ref())?;
        v.external_force = match &md.external_force {
            Some(f) if !f.element.is_empty() => {
                Some(<Wrench>::try_from(f.element.as_slice()).map_err(|_| {
                    CodecError::ValueCount {
                        field: "monitorData.externalForce",
                        got: f.element.len(),
                        expected: 6,
                    }
                })?)
            }
            _ => None,
        };
    }
    if let Some(ipo) = &msg.ipo_data {
        v.ipo_joint_position_rad =
            read_joints("ipoData.jointPosition", ipo.joint_position.as_ref())?;
        v.client_command_mode = opt_enum(ipo.client_command_mode);
        v.overlay_type = opt_enum(ipo.overlay_type);
        v.tracking_performance = ipo.tracking_performance;
        check_transformations(ipo.cartesian_pose.as_ref(), version)?;
        check_redundancy(ipo.redundancy_information.as_ref())?;
        if let Some(m) = ipo.client_command_mode
            && !(0..=version.max_client_command_mode()).contains(&m)
        {
            v.client_command_mode = None;
        }
    }
    Ok(v)
}

/// Checks a decoded command message and returns its view.
///
/// # Errors
///
/// [`CodecError::MissingField`] or [`CodecError::WrongIdentifier`] for a bad header
/// or a missing required field; [`CodecError::JointCount`] or
/// [`CodecError::ValueCount`] for an array of the wrong size.
pub fn command_view(msg: &FriCommandMessage, version: FriVersion) -> Result<Command, CodecError> {
    let (seq, refl) = check_header(msg.header.as_ref(), COMMAND_MESSAGE_ID)?;
    let mut c = Command {
        sequence_counter: seq,
        reflected_sequence_counter: refl,
        ..Command::default()
    };
    if let Some(cd) = &msg.command_data {
        c.joint_position_rad =
            read_joints("commandData.jointPosition", cd.joint_position.as_ref())?;
        c.joint_torque_nm = read_joints("commandData.jointTorque", cd.joint_torque.as_ref())?;
        check_transformations(&cd.commanded_transformations, version)?;
        check_transformations(cd.cartesian_pose.as_ref(), version)?;
        check_redundancy(cd.redundancy_information.as_ref())?;
        check_io(&cd.write_io_request)?;
    }
    Ok(c)
}

/// Just the header of any FRI message (other fields are skipped).
#[derive(Clone, Copy, PartialEq, prost::Message)]
struct HeaderPeek {
    #[prost(message, optional, tag = "1")]
    header: Option<MessageHeader>,
}

/// Turns a structural decode error into `WrongIdentifier` when the datagram is a
/// well-formed message of the other kind (clearer: "incompatible IDs").
fn classify(err: prost::DecodeError, bytes: &[u8], expected: u32) -> CodecError {
    match HeaderPeek::decode(bytes) {
        Ok(HeaderPeek {
            header:
                Some(MessageHeader {
                    message_identifier: Some(got),
                    ..
                }),
        }) if got != expected => CodecError::WrongIdentifier { got, expected },
        _ => CodecError::Malformed(err),
    }
}

fn check_len(bytes: &[u8]) -> Result<(), CodecError> {
    if bytes.len() > MAX_DATAGRAM_BYTES {
        Err(CodecError::TooLong { len: bytes.len() })
    } else {
        Ok(())
    }
}

/// The protobuf bytes of a datagram of `version`: checks the size and, for
/// 2.7, the frame's length and CRC.
///
/// # Errors
///
/// [`CodecError::TooLong`] for a datagram longer than FRI allows;
/// [`CodecError::Frame`] for a 2.7 frame with a wrong length field or CRC-32.
pub fn payload(bytes: &[u8], version: FriVersion) -> Result<&[u8], CodecError> {
    check_len(bytes)?;
    if version.framed() {
        Ok(unframe(bytes)?)
    } else {
        Ok(bytes)
    }
}

/// Decodes and checks an FRI 1.15 monitoring datagram into a fresh message
/// (allocates; for tools and tests; the session uses [`MonitoringDecoder`]).
///
/// # Errors
///
/// As [`decode_monitoring_message_of`].
pub fn decode_monitoring_message(bytes: &[u8]) -> Result<FriMonitoringMessage, CodecError> {
    decode_monitoring_message_of(bytes, FriVersion::V1_15)
}

/// Decodes and checks a monitoring datagram of `version` (allocates).
///
/// # Errors
///
/// [`CodecError::TooLong`] or [`CodecError::Frame`] as [`payload`];
/// [`CodecError::Malformed`] or [`CodecError::WrongIdentifier`] when the bytes do not
/// decode as a monitoring message; the errors of [`monitoring_view`].
pub fn decode_monitoring_message_of(
    bytes: &[u8],
    version: FriVersion,
) -> Result<FriMonitoringMessage, CodecError> {
    let pb = payload(bytes, version)?;
    let mut msg =
        FriMonitoringMessage::decode(pb).map_err(|e| classify(e, pb, MONITORING_MESSAGE_ID))?;
    strip_monitoring(&mut msg, version);
    monitoring_view(&msg, version)?;
    Ok(msg)
}

/// Decodes and checks an FRI 1.15 command datagram into a fresh message (allocates).
///
/// # Errors
///
/// As [`decode_command_message_of`].
pub fn decode_command_message(bytes: &[u8]) -> Result<FriCommandMessage, CodecError> {
    decode_command_message_of(bytes, FriVersion::V1_15)
}

/// Decodes and checks a command datagram of `version` (allocates).
///
/// # Errors
///
/// [`CodecError::TooLong`] or [`CodecError::Frame`] as [`payload`];
/// [`CodecError::Malformed`] or [`CodecError::WrongIdentifier`] when the bytes do not
/// decode as a command message; the errors of [`command_view`].
pub fn decode_command_message_of(
    bytes: &[u8],
    version: FriVersion,
) -> Result<FriCommandMessage, CodecError> {
    let pb = payload(bytes, version)?;
    let mut msg = FriCommandMessage::decode(pb).map_err(|e| classify(e, pb, COMMAND_MESSAGE_ID))?;
    strip_command(&mut msg, version);
    command_view(&msg, version)?;
    Ok(msg)
}

/// Encodes `msg` into `buf` as a datagram of `version` (framed for 2.7).
fn encode_into(
    msg: &impl Message,
    buf: &mut [u8; MAX_DATAGRAM_BYTES],
    version: FriVersion,
) -> Result<usize, CodecError> {
    let start = if version.framed() { 4 } else { 0 };
    let room = MAX_DATAGRAM_BYTES - if version.framed() { FRAME_OVERHEAD } else { 0 };
    let mut rest: &mut [u8] = &mut buf[start..room + start];
    msg.encode(&mut rest)
        .map_err(|_| CodecError::EncodeOverflow)?;
    let n = room - rest.len();
    if version.framed() {
        frame_in_place(&mut buf[..], n).ok_or(CodecError::EncodeOverflow)
    } else {
        Ok(n)
    }
}

/// Decodes monitoring datagrams, reusing one message (no allocation per datagram
/// once the joint arrays have been seen).
#[derive(Debug, Default)]
pub struct MonitoringDecoder {
    msg: FriMonitoringMessage,
    version: FriVersion,
}

impl MonitoringDecoder {
    /// An FRI 1.15 decoder.
    pub fn new() -> Self {
        Self::default()
    }

    /// A decoder of `version`'s datagrams.
    pub fn with_version(version: FriVersion) -> Self {
        Self {
            version,
            ..Self::default()
        }
    }

    /// The version it decodes.
    pub fn version(&self) -> FriVersion {
        self.version
    }

    fn reset(&mut self) {
        let m = &mut self.msg;
        m.header = None;
        m.connection_info = None;
        m.end_of_message_data = None;
        m.requested_transformations.clear();
        if let Some(ri) = &mut m.robot_info {
            ri.number_of_joints = None;
            ri.safety_state = None;
            ri.drive_state.clear();
            ri.operation_mode = None;
            ri.control_mode = None;
        }
        if let Some(md) = &mut m.monitor_data {
            for jv in [
                &mut md.measured_joint_position,
                &mut md.measured_torque,
                &mut md.commanded_joint_position,
                &mut md.commanded_torque,
                &mut md.external_torque,
            ]
            .into_iter()
            .flatten()
            {
                jv.value.clear();
            }
            if let Some(f) = &mut md.external_force {
                f.element.clear();
            }
            md.read_io_request.clear();
            md.measured_cartesian_pose = None;
            md.measured_redundancy_information = None;
            md.timestamp = None;
        }
        if let Some(ipo) = &mut m.ipo_data {
            if let Some(jv) = &mut ipo.joint_position {
                jv.value.clear();
            }
            ipo.cartesian_pose = None;
            ipo.redundancy_information = None;
            ipo.client_command_mode = None;
            ipo.overlay_type = None;
            ipo.tracking_performance = None;
        }
    }

    /// Decodes and checks one datagram.
    ///
    /// # Errors
    ///
    /// As [`decode_monitoring_message_of`].
    pub fn decode(&mut self, bytes: &[u8]) -> Result<Monitoring, CodecError> {
        let pb = payload(bytes, self.version)?;
        self.reset();
        self.msg
            .merge(pb)
            .map_err(|e| classify(e, pb, MONITORING_MESSAGE_ID))?;
        strip_monitoring(&mut self.msg, self.version);
        monitoring_view(&self.msg, self.version)
    }
}

/// Decodes command datagrams, reusing one message.
#[derive(Debug, Default)]
pub struct CommandDecoder {
    msg: FriCommandMessage,
    version: FriVersion,
}

impl CommandDecoder {
    /// An FRI 1.15 decoder.
    pub fn new() -> Self {
        Self::default()
    }

    /// A decoder of `version`'s datagrams.
    pub fn with_version(version: FriVersion) -> Self {
        Self {
            version,
            ..Self::default()
        }
    }

    /// The version it decodes.
    pub fn version(&self) -> FriVersion {
        self.version
    }

    fn reset(&mut self) {
        let m = &mut self.msg;
        m.header = None;
        m.end_of_message_data = None;
        if let Some(cd) = &mut m.command_data {
            for jv in [&mut cd.joint_position, &mut cd.joint_torque]
                .into_iter()
                .flatten()
            {
                jv.value.clear();
            }
            if let Some(w) = &mut cd.cartesian_wrench_feed_forward {
                w.element.clear();
            }
            cd.commanded_transformations.clear();
            cd.write_io_request.clear();
            cd.cartesian_pose = None;
            cd.redundancy_information = None;
        }
    }

    /// Decodes and checks one datagram.
    ///
    /// # Errors
    ///
    /// As [`decode_command_message_of`].
    pub fn decode(&mut self, bytes: &[u8]) -> Result<Command, CodecError> {
        let pb = payload(bytes, self.version)?;
        self.reset();
        self.msg
            .merge(pb)
            .map_err(|e| classify(e, pb, COMMAND_MESSAGE_ID))?;
        strip_command(&mut self.msg, self.version);
        command_view(&self.msg, self.version)
    }
}

/// Encodes command datagrams into a buffer it owns (no allocation per message).
#[derive(Debug)]
pub struct CommandEncoder {
    msg: FriCommandMessage,
    /// The command data while a header-only reply is sent (keeps its allocation).
    stash: Option<MessageCommandData>,
    buf: [u8; MAX_DATAGRAM_BYTES],
    version: FriVersion,
}

impl Default for CommandEncoder {
    fn default() -> Self {
        Self::new()
    }
}

impl CommandEncoder {
    /// An FRI 1.15 encoder.
    pub fn new() -> Self {
        Self::with_version(FriVersion::default())
    }

    /// An encoder of `version`'s datagrams.
    pub fn with_version(version: FriVersion) -> Self {
        let mut cd = MessageCommandData::default();
        write_joints(&mut cd.joint_position, Some(&[0.0; JOINTS]));
        Self {
            msg: FriCommandMessage {
                header: Some(MessageHeader {
                    message_identifier: Some(COMMAND_MESSAGE_ID),
                    sequence_counter: Some(0),
                    reflected_sequence_counter: Some(0),
                }),
                command_data: None,
                end_of_message_data: None,
            },
            stash: Some(cd),
            buf: [0; MAX_DATAGRAM_BYTES],
            version,
        }
    }

    /// Encodes a command: header only when `joint_position_rad` is `None`, else
    /// the header and 7 joint positions (unpacked). Returns the datagram.
    ///
    /// # Errors
    ///
    /// [`CodecError::EncodeOverflow`] when the encoded message does not fit in one
    /// datagram.
    pub fn encode(
        &mut self,
        sequence_counter: u32,
        reflected_sequence_counter: u32,
        joint_position_rad: Option<&Joints>,
    ) -> Result<&[u8], CodecError> {
        self.msg.header = Some(MessageHeader {
            message_identifier: Some(COMMAND_MESSAGE_ID),
            sequence_counter: Some(sequence_counter),
            reflected_sequence_counter: Some(reflected_sequence_counter),
        });
        match joint_position_rad {
            Some(q) => {
                if self.msg.command_data.is_none() {
                    self.msg.command_data = self.stash.take();
                }
                let cd = self.msg.command_data.get_or_insert_with(Default::default);
                write_joints(&mut cd.joint_position, Some(q));
            }
            None => {
                if let Some(cd) = self.msg.command_data.take() {
                    self.stash = Some(cd);
                }
            }
        }
        let n = encode_into(&self.msg, &mut self.buf, self.version)?;
        Ok(&self.buf[..n])
    }
}

/// Encodes monitoring datagrams into a buffer it owns (no allocation per message).
#[derive(Debug)]
pub struct MonitoringEncoder {
    msg: FriMonitoringMessage,
    ipo_stash: Option<MessageIpoData>,
    force_stash: Option<super::proto::CartesianVector>,
    buf: [u8; MAX_DATAGRAM_BYTES],
    version: FriVersion,
}

impl Default for MonitoringEncoder {
    fn default() -> Self {
        Self::new()
    }
}

impl MonitoringEncoder {
    /// An FRI 1.15 encoder.
    pub fn new() -> Self {
        Self::with_version(FriVersion::default())
    }

    /// An encoder of `version`'s datagrams.
    pub fn with_version(version: FriVersion) -> Self {
        let zeros = [0.0; JOINTS];
        let mut md = MessageMonitorData::default();
        for jv in [
            &mut md.measured_joint_position,
            &mut md.measured_torque,
            &mut md.commanded_joint_position,
            &mut md.commanded_torque,
            &mut md.external_torque,
        ] {
            write_joints(jv, Some(&zeros));
        }
        let mut ipo = MessageIpoData::default();
        write_joints(&mut ipo.joint_position, Some(&zeros));
        Self {
            msg: FriMonitoringMessage {
                robot_info: Some(RobotInfo {
                    drive_state: Vec::with_capacity(JOINTS),
                    ..RobotInfo::default()
                }),
                monitor_data: Some(md),
                ..FriMonitoringMessage::default()
            },
            ipo_stash: Some(ipo),
            force_stash: Some(super::proto::CartesianVector {
                element: Vec::with_capacity(6),
            }),
            buf: [0; MAX_DATAGRAM_BYTES],
            version,
        }
    }

    /// Encodes `m`: every field that is `Some` in the view and defined in the
    /// encoder's version is written, joint arrays as 7 unpacked doubles.
    /// Returns the datagram.
    ///
    /// # Errors
    ///
    /// [`CodecError::EncodeOverflow`] when the encoded message does not fit in one
    /// datagram.
    pub fn encode(&mut self, m: &Monitoring) -> Result<&[u8], CodecError> {
        let msg = &mut self.msg;
        msg.header = Some(MessageHeader {
            message_identifier: Some(MONITORING_MESSAGE_ID),
            sequence_counter: Some(m.sequence_counter),
            reflected_sequence_counter: Some(m.reflected_sequence_counter),
        });
        msg.connection_info = Some(ConnectionInfo {
            session_state: Some(m.session_state as i32),
            quality: Some(m.quality as i32),
            send_period: Some(m.send_period_ms),
            receive_multiplier: Some(m.receive_multiplier),
        });
        let ri = msg.robot_info.get_or_insert_with(Default::default);
        ri.number_of_joints = Some(JOINTS as i32);
        ri.safety_state = m.safety_state.map(|x| x as i32);
        ri.operation_mode = m.operation_mode.map(|x| x as i32);
        ri.control_mode = m.control_mode.map(|x| x as i32);
        ri.drive_state.clear();
        if let Some(ds) = &m.drive_state {
            ri.drive_state.extend(ds.iter().map(|d| *d as i32));
        }
        let md = msg.monitor_data.get_or_insert_with(Default::default);
        write_joints(
            &mut md.measured_joint_position,
            m.measured_joint_position_rad.as_ref(),
        );
        write_joints(&mut md.measured_torque, m.measured_torque_nm.as_ref());
        let commanded = m
            .commanded_joint_position_rad
            .as_ref()
            .filter(|_| self.version.has_commanded_joint_position());
        write_joints(&mut md.commanded_joint_position, commanded);
        write_joints(&mut md.commanded_torque, m.commanded_torque_nm.as_ref());
        write_joints(&mut md.external_torque, m.external_torque_nm.as_ref());
        match (&m.external_force, self.version.has_external_force()) {
            (Some(f), true) => {
                if md.external_force.is_none() {
                    md.external_force = self.force_stash.take();
                }
                let cv = md.external_force.get_or_insert_with(Default::default);
                cv.element.clear();
                cv.element.extend_from_slice(f);
            }
            _ => {
                if let Some(cv) = md.external_force.take() {
                    self.force_stash = Some(cv);
                }
            }
        }
        md.timestamp = m.timestamp.map(|t| TimeStamp {
            sec: Some(t.sec),
            nanosec: Some(t.nanosec),
        });
        let has_ipo = m.ipo_joint_position_rad.is_some()
            || m.client_command_mode.is_some()
            || m.overlay_type.is_some()
            || m.tracking_performance.is_some();
        if has_ipo {
            if msg.ipo_data.is_none() {
                msg.ipo_data = self.ipo_stash.take();
            }
            let ipo = msg.ipo_data.get_or_insert_with(Default::default);
            write_joints(&mut ipo.joint_position, m.ipo_joint_position_rad.as_ref());
            ipo.client_command_mode = m.client_command_mode.map(|x| x as i32);
            ipo.overlay_type = m.overlay_type.map(|x| x as i32);
            ipo.tracking_performance = m.tracking_performance;
        } else if let Some(ipo) = msg.ipo_data.take() {
            self.ipo_stash = Some(ipo);
        }
        let n = encode_into(&self.msg, &mut self.buf, self.version)?;
        Ok(&self.buf[..n])
    }
}

/// Builds a full prost command message (allocates; for tools and tests).
pub fn command_message(
    sequence_counter: u32,
    reflected_sequence_counter: u32,
    joint_position_rad: Option<&Joints>,
) -> FriCommandMessage {
    FriCommandMessage {
        header: Some(MessageHeader {
            message_identifier: Some(COMMAND_MESSAGE_ID),
            sequence_counter: Some(sequence_counter),
            reflected_sequence_counter: Some(reflected_sequence_counter),
        }),
        command_data: joint_position_rad.map(|q| MessageCommandData {
            joint_position: Some(joint_values(q)),
            ..MessageCommandData::default()
        }),
        end_of_message_data: None,
    }
}
