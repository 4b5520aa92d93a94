//! The FRI wire messages as prost structs (FRI.md, "Messages"): the union of
//! the fields of versions 1.11 to 2.7 ([`super::version`] says which version
//! has which; the codec drops the fields a version lacks after decoding and
//! never writes them).
//!
//! Written by hand from the public field table; no `.proto` file and no `protoc`.
//! proto2 semantics: fields that FRI declares `required` are `Option`s here so the
//! decoder can tell "absent" from "zero" and refuse a message that lacks one
//! ([`super::codec`] checks them); the encoders always fill them. Joint arrays
//! are written unpacked (tag `0x09` + 8-byte little-endian double per value), as
//! KUKA's client SDK writes them; prost's decoder accepts packed and unpacked.

/// Controller -> client, once per send period.
#[derive(Clone, PartialEq, prost::Message)]
pub struct FriMonitoringMessage {
    /// Required: identifier and counters.
    #[prost(message, optional, tag = "1")]
    pub header: Option<MessageHeader>,
    /// Robot configuration and status.
    #[prost(message, optional, tag = "2")]
    pub robot_info: Option<RobotInfo>,
    /// Measured and commanded joint data.
    #[prost(message, optional, tag = "3")]
    pub monitor_data: Option<MessageMonitorData>,
    /// Session state, quality and cadence.
    #[prost(message, optional, tag = "4")]
    pub connection_info: Option<ConnectionInfo>,
    /// Interpolator data (sent in COMMANDING_* only).
    #[prost(message, optional, tag = "5")]
    pub ipo_data: Option<MessageIpoData>,
    /// Frames the client is asked to command (at most 5).
    #[prost(message, repeated, tag = "6")]
    pub requested_transformations: Vec<Transformation>,
    /// Length and checksum (optional).
    #[prost(message, optional, tag = "15")]
    pub end_of_message_data: Option<MessageEndOf>,
}

/// Client -> controller, the answer to a monitoring message.
#[derive(Clone, PartialEq, prost::Message)]
pub struct FriCommandMessage {
    /// Required: identifier and counters.
    #[prost(message, optional, tag = "1")]
    pub header: Option<MessageHeader>,
    /// The command (absent in a header-only reply).
    #[prost(message, optional, tag = "2")]
    pub command_data: Option<MessageCommandData>,
    /// Length and checksum (optional).
    #[prost(message, optional, tag = "15")]
    pub end_of_message_data: Option<MessageEndOf>,
}

/// Message identifier and counters (all three required).
#[derive(Clone, Copy, PartialEq, prost::Message)]
pub struct MessageHeader {
    /// `0x245142` monitoring, `0x34001` command.
    #[prost(uint32, optional, tag = "1")]
    pub message_identifier: Option<u32>,
    /// The sender's counter, +1 per message.
    #[prost(uint32, optional, tag = "2")]
    pub sequence_counter: Option<u32>,
    /// The counter of the last message received from the other side.
    #[prost(uint32, optional, tag = "3")]
    pub reflected_sequence_counter: Option<u32>,
}

/// Session state and cadence (sessionState and quality required).
#[derive(Clone, Copy, PartialEq, prost::Message)]
pub struct ConnectionInfo {
    /// [`SessionState`].
    #[prost(enumeration = "SessionState", optional, tag = "1")]
    pub session_state: Option<i32>,
    /// [`ConnectionQuality`].
    #[prost(enumeration = "ConnectionQuality", optional, tag = "2")]
    pub quality: Option<i32>,
    /// Controller send period, ms (1..100).
    #[prost(uint32, optional, tag = "3")]
    pub send_period: Option<u32>,
    /// The client answers every n-th message (missing or 0 means 1).
    #[prost(uint32, optional, tag = "4")]
    pub receive_multiplier: Option<u32>,
}

/// Robot configuration.
#[derive(Clone, PartialEq, prost::Message)]
pub struct RobotInfo {
    /// Number of joints (7).
    #[prost(int32, optional, tag = "1")]
    pub number_of_joints: Option<i32>,
    /// [`SafetyState`].
    #[prost(enumeration = "SafetyState", optional, tag = "2")]
    pub safety_state: Option<i32>,
    /// [`DriveState`], one per joint, unpacked varints.
    #[prost(enumeration = "DriveState", repeated, packed = "false", tag = "5")]
    pub drive_state: Vec<i32>,
    /// [`OperationMode`].
    #[prost(enumeration = "OperationMode", optional, tag = "6")]
    pub operation_mode: Option<i32>,
    /// [`ControlMode`].
    #[prost(enumeration = "ControlMode", optional, tag = "7")]
    pub control_mode: Option<i32>,
}

/// Measured and commanded joint data (all optional).
#[derive(Clone, PartialEq, prost::Message)]
pub struct MessageMonitorData {
    /// Measured joint positions, rad.
    #[prost(message, optional, tag = "1")]
    pub measured_joint_position: Option<JointValues>,
    /// Measured joint torques, N m.
    #[prost(message, optional, tag = "2")]
    pub measured_torque: Option<JointValues>,
    /// The controller's commanded joint positions, rad (FRI 1.x only).
    #[prost(message, optional, tag = "3")]
    pub commanded_joint_position: Option<JointValues>,
    /// Commanded joint torques, N m.
    #[prost(message, optional, tag = "4")]
    pub commanded_torque: Option<JointValues>,
    /// Estimated external torques, N m.
    #[prost(message, optional, tag = "5")]
    pub external_torque: Option<JointValues>,
    /// Estimated external Cartesian force and torque at the flange (FRI 2.7), 6 values.
    #[prost(message, optional, tag = "6")]
    pub external_force: Option<CartesianVector>,
    /// IO values the client asked for (at most 10; from FRI 1.14).
    #[prost(message, repeated, tag = "8")]
    pub read_io_request: Vec<FriIoValue>,
    /// Measured Cartesian pose (FRI 2.x, 7-value quaternion transformation).
    #[prost(message, optional, tag = "9")]
    pub measured_cartesian_pose: Option<Transformation>,
    /// Measured redundancy information (FRI 2.x).
    #[prost(message, optional, tag = "10")]
    pub measured_redundancy_information: Option<RedundancyInformation>,
    /// Controller time of the measurement (Unix time).
    #[prost(message, optional, tag = "15")]
    pub timestamp: Option<TimeStamp>,
}

/// Interpolator data.
#[derive(Clone, PartialEq, prost::Message)]
pub struct MessageIpoData {
    /// The interpolator's joint positions, rad (COMMANDING_* only).
    #[prost(message, optional, tag = "1")]
    pub joint_position: Option<JointValues>,
    /// The interpolator's Cartesian pose (FRI 2.x).
    #[prost(message, optional, tag = "2")]
    pub cartesian_pose: Option<Transformation>,
    /// The interpolator's redundancy information (FRI 2.x).
    #[prost(message, optional, tag = "3")]
    pub redundancy_information: Option<RedundancyInformation>,
    /// [`ClientCommandMode`].
    #[prost(enumeration = "ClientCommandMode", optional, tag = "10")]
    pub client_command_mode: Option<i32>,
    /// [`OverlayType`].
    #[prost(enumeration = "OverlayType", optional, tag = "11")]
    pub overlay_type: Option<i32>,
    /// Tracking performance, 0..1.
    #[prost(double, optional, tag = "12")]
    pub tracking_performance: Option<f64>,
}

/// The client's command.
#[derive(Clone, PartialEq, prost::Message)]
pub struct MessageCommandData {
    /// Absolute joint positions, rad.
    #[prost(message, optional, tag = "1")]
    pub joint_position: Option<JointValues>,
    /// Cartesian wrench feed-forward (at most 6).
    #[prost(message, optional, tag = "2")]
    pub cartesian_wrench_feed_forward: Option<CartesianVector>,
    /// Joint torques, N m.
    #[prost(message, optional, tag = "3")]
    pub joint_torque: Option<JointValues>,
    /// Commanded frames (at most 5).
    #[prost(message, repeated, tag = "4")]
    pub commanded_transformations: Vec<Transformation>,
    /// IO values to write (at most 10; from FRI 1.14).
    #[prost(message, repeated, tag = "5")]
    pub write_io_request: Vec<FriIoValue>,
    /// Commanded Cartesian pose (FRI 2.x).
    #[prost(message, optional, tag = "6")]
    pub cartesian_pose: Option<Transformation>,
    /// Commanded redundancy information (FRI 2.x).
    #[prost(message, optional, tag = "7")]
    pub redundancy_information: Option<RedundancyInformation>,
}

/// The arm's redundancy (FRI 2.x; both fields required).
#[derive(Clone, Copy, PartialEq, prost::Message)]
pub struct RedundancyInformation {
    /// `RedundancyStrategy`: E1 0, NONE 4.
    #[prost(int32, optional, tag = "1")]
    pub strategy: Option<i32>,
    /// The redundancy value (E1: the elbow angle, rad).
    #[prost(double, optional, tag = "2")]
    pub value: Option<f64>,
}

/// One value per joint: always exactly 7, written unpacked.
#[derive(Clone, PartialEq, prost::Message)]
pub struct JointValues {
    /// The values.
    #[prost(double, repeated, packed = "false", tag = "1")]
    pub value: Vec<f64>,
}

/// Up to 6 Cartesian values.
#[derive(Clone, PartialEq, prost::Message)]
pub struct CartesianVector {
    /// The values.
    #[prost(double, repeated, packed = "false", tag = "1")]
    pub element: Vec<f64>,
}

/// Unix time (both fields required).
#[derive(Clone, Copy, PartialEq, prost::Message)]
pub struct TimeStamp {
    /// Seconds.
    #[prost(uint32, optional, tag = "1")]
    pub sec: Option<u32>,
    /// Nanoseconds.
    #[prost(uint32, optional, tag = "2")]
    pub nanosec: Option<u32>,
}

/// A named frame: FRI 1.x `Transformation` (12 values, a 3x4 matrix) or FRI
/// 2.x `QuaternionTransformation` (7 values, under the same field numbers).
#[derive(Clone, PartialEq, prost::Message)]
pub struct Transformation {
    /// Required: the frame's name (at most 64 bytes).
    #[prost(string, optional, tag = "1")]
    pub name: Option<String>,
    /// 1.x: 12 values, a row-major 3x4 matrix; 2.x: 7 values, x y z (mm) and
    /// the quaternion.
    #[prost(double, repeated, packed = "false", tag = "2")]
    pub matrix: Vec<f64>,
    /// When the frame was valid.
    #[prost(message, optional, tag = "3")]
    pub timestamp: Option<TimeStamp>,
}

/// One IO value.
#[derive(Clone, PartialEq, prost::Message)]
pub struct FriIoValue {
    /// Required: the IO's name.
    #[prost(string, optional, tag = "1")]
    pub name: Option<String>,
    /// Required: [`IoType`].
    #[prost(enumeration = "IoType", optional, tag = "2")]
    pub r#type: Option<i32>,
    /// Required: [`IoDirection`].
    #[prost(enumeration = "IoDirection", optional, tag = "3")]
    pub direction: Option<i32>,
    /// Boolean or digital value.
    #[prost(uint64, optional, tag = "4")]
    pub digital_value: Option<u64>,
    /// Analog value.
    #[prost(double, optional, tag = "5")]
    pub analog_value: Option<f64>,
}

/// End-of-message data.
#[derive(Clone, Copy, PartialEq, prost::Message)]
pub struct MessageEndOf {
    /// Length of the message, bytes.
    #[prost(int32, optional, tag = "1")]
    pub message_length: Option<i32>,
    /// Checksum.
    #[prost(message, optional, tag = "2")]
    pub message_checksum: Option<Checksum>,
}

/// A CRC-32 checksum.
#[derive(Clone, Copy, PartialEq, prost::Message)]
pub struct Checksum {
    /// The CRC-32.
    #[prost(int32, optional, tag = "1")]
    pub crc32: Option<i32>,
}

/// `FRISessionState`.
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, prost::Enumeration, serde::Serialize,
)]
#[serde(rename_all = "SCREAMING_SNAKE_CASE")]
#[repr(i32)]
pub enum SessionState {
    /// No session (sent when a session closes); the client sends nothing.
    Idle = 0,
    /// Connection quality not yet good enough.
    MonitoringWait = 1,
    /// Quality good enough for commanding.
    MonitoringReady = 2,
    /// Overlay motion queued; the client mirrors the ipo joint positions.
    CommandingWait = 3,
    /// The client commands.
    CommandingActive = 4,
}

impl SessionState {
    /// The name KUKA uses (`COMMANDING_ACTIVE`).
    pub const fn name(self) -> &'static str {
        match self {
            Self::Idle => "IDLE",
            Self::MonitoringWait => "MONITORING_WAIT",
            Self::MonitoringReady => "MONITORING_READY",
            Self::CommandingWait => "COMMANDING_WAIT",
            Self::CommandingActive => "COMMANDING_ACTIVE",
        }
    }

    /// True in COMMANDING_WAIT and COMMANDING_ACTIVE.
    pub const fn is_commanding(self) -> bool {
        matches!(self, Self::CommandingWait | Self::CommandingActive)
    }
}

/// `FRIConnectionQuality`.
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, prost::Enumeration, serde::Serialize,
)]
#[serde(rename_all = "SCREAMING_SNAKE_CASE")]
#[repr(i32)]
pub enum ConnectionQuality {
    /// Poor.
    Poor = 0,
    /// Fair.
    Fair = 1,
    /// Good (needed for commanding).
    Good = 2,
    /// Excellent.
    Excellent = 3,
}

impl ConnectionQuality {
    /// The name KUKA uses (`GOOD`).
    pub const fn name(self) -> &'static str {
        match self {
            Self::Poor => "POOR",
            Self::Fair => "FAIR",
            Self::Good => "GOOD",
            Self::Excellent => "EXCELLENT",
        }
    }
}

/// `SafetyState`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, prost::Enumeration)]
#[repr(i32)]
pub enum SafetyState {
    /// Normal operation.
    NormalOperation = 0,
    /// Safety stop 0.
    SafetyStopLevel0 = 1,
    /// Safety stop 1.
    SafetyStopLevel1 = 2,
    /// Safety stop 2.
    SafetyStopLevel2 = 3,
}

/// `OperationMode`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, prost::Enumeration)]
#[repr(i32)]
pub enum OperationMode {
    /// T1.
    TestMode1 = 0,
    /// T2.
    TestMode2 = 1,
    /// AUT.
    AutomaticMode = 2,
}

/// `DriveState`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, prost::Enumeration)]
#[repr(i32)]
pub enum DriveState {
    /// Off.
    Off = 0,
    /// Transitioning.
    Transitioning = 1,
    /// Active.
    Active = 2,
}

/// `ControlMode`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, prost::Enumeration)]
#[repr(i32)]
pub enum ControlMode {
    /// Position control.
    PositionControlmode = 0,
    /// Cartesian impedance.
    CartesianImpedance = 1,
    /// Joint impedance.
    JointImpedance = 2,
    /// No control mode.
    NoControlmode = 3,
}

/// `ClientCommandMode`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, prost::Enumeration)]
#[repr(i32)]
pub enum ClientCommandMode {
    /// No command mode.
    NoCommandMode = 0,
    /// Joint positions (POSITION up to 1.16, JOINT_POSITION from 2.5).
    Position = 1,
    /// Cartesian wrench.
    Wrench = 2,
    /// Joint torques.
    Torque = 3,
    /// Cartesian pose (FRI 2.x).
    CartesianPose = 4,
}

/// `OverlayType`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, prost::Enumeration)]
#[repr(i32)]
pub enum OverlayType {
    /// No overlay.
    NoOverlay = 0,
    /// Joint overlay.
    Joint = 1,
    /// Cartesian overlay.
    Cartesian = 2,
}

/// `FRIIOType`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, prost::Enumeration)]
#[repr(i32)]
pub enum IoType {
    /// Boolean.
    Boolean = 0,
    /// Digital.
    Digital = 1,
    /// Analog.
    Analog = 2,
}

/// `FRIIODirection`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, prost::Enumeration)]
#[repr(i32)]
pub enum IoDirection {
    /// Input.
    Input = 0,
    /// Output.
    Output = 1,
}
