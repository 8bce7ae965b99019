//! Message types: what ports carry.
//!
//! A fixed-size message is a `#[repr(C)]` plain-old-data struct ([`bytemuck::Pod`]) sent as its
//! little-endian in-memory layout (encoding [`POD_ENCODING`]); its `SCHEMA` lists the fields in
//! ROS 2 `.msg` syntax so recordings can be decoded without our code. Variable-size payloads
//! (images, text) implement [`BytesMessage`] and are written straight into shared memory.

use bytemuck::{Pod, Zeroable};
use dnm_netlist::{MessageType, Payload};

pub use dnm_netlist::POD_ENCODING;

/// A message type's standard ROS 2 equivalent: its name and `(standard field, source)` pairs
/// (see [`dnm_netlist::Standard`]).
pub type StandardMap = Option<(&'static str, &'static [(&'static str, &'static str)])>;

/// A fixed-size message type.
pub trait Message: Pod {
    /// Schema name, e.g. `dnm_msgs/Tick`.
    const SCHEMA_NAME: &'static str;
    /// Field list in ROS 2 `.msg` syntax, in layout order.
    const SCHEMA: &'static str;
    /// The standard ROS 2 message recordings store this type as, with where each of its fields
    /// comes from (see [`dnm_netlist::Standard`]): `("nav_msgs/msg/Odometry",
    /// &[("pose.pose.position.x", "x"), ("pose.pose.orientation", "yaw"), …])`. `None`: recorded
    /// as it is, under `SCHEMA_NAME`.
    const STANDARD: StandardMap = None;
    /// Where [`Message::STANDARD`] makes this a body's pose: the body, as a URDF document whose
    /// root link is the pose's frame (see [`dnm_netlist::Standard::body`]).
    const BODY: Option<&'static str> = None;

    fn message_type() -> MessageType {
        MessageType {
            schema_name: Self::SCHEMA_NAME.to_string(),
            encoding: POD_ENCODING.to_string(),
            schema: Self::SCHEMA.to_string(),
            payload: Payload::Fixed {
                size_bytes: size_of::<Self>(),
            },
            standard: Self::STANDARD.map(|(name, fields)| dnm_netlist::Standard {
                name: name.to_string(),
                fields: fields
                    .iter()
                    .map(|(to, from)| [to.to_string(), from.to_string()])
                    .collect(),
                body: Self::BODY.map(str::to_string),
            }),
        }
    }
}

/// A variable-size byte message type (for example an encoded image).
pub trait BytesMessage {
    const SCHEMA_NAME: &'static str;
    /// How the bytes are encoded, e.g. `dnm-image` or `application/json`.
    const ENCODING: &'static str;
    const SCHEMA: &'static str;

    fn message_type(max_bytes: usize) -> MessageType {
        MessageType {
            schema_name: Self::SCHEMA_NAME.to_string(),
            encoding: Self::ENCODING.to_string(),
            schema: Self::SCHEMA.to_string(),
            payload: Payload::Bytes { max_bytes },
            standard: None,
        }
    }
}

/// A counter value tagged with the module that produced it. Used to trace data through tasks.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Pod, Zeroable)]
pub struct Tick {
    /// Identifies the producing module (its `origin` parameter).
    pub origin: u64,
    /// Increments by one per message from that origin.
    pub seq: u64,
}

impl Message for Tick {
    const SCHEMA_NAME: &'static str = "dnm_msgs/Tick";
    const SCHEMA: &'static str = "uint64 origin\nuint64 seq\n";
}

/// What a module with two inputs read in one step: which origins fed each input, under which
/// task. Lets tests prove a task switch never mixes sources within a step.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Pod, Zeroable)]
pub struct PairReading {
    pub a_origin: u64,
    pub a_seq: u64,
    pub b_origin: u64,
    pub b_seq: u64,
    /// Netlist revision and task slot the step ran under.
    pub revision: u64,
    pub task_slot: u64,
}

impl Message for PairReading {
    const SCHEMA_NAME: &'static str = "dnm_msgs/PairReading";
    const SCHEMA: &'static str = "uint64 a_origin\nuint64 a_seq\nuint64 b_origin\nuint64 b_seq\nuint64 revision\nuint64 task_slot\n";
}

/// A scalar measurement.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Pod, Zeroable)]
pub struct Scalar {
    pub value: f64,
}

impl Message for Scalar {
    const SCHEMA_NAME: &'static str = "dnm_msgs/Scalar";
    const SCHEMA: &'static str = "float64 value\n";
}

/// Opaque bytes; the first 16 bytes of a blob written by the standard modules hold an origin and
/// a sequence number (as in [`Tick`]) so blobs can be traced too.
#[derive(Debug, Clone, Copy)]
pub struct Blob;

impl BytesMessage for Blob {
    const SCHEMA_NAME: &'static str = "dnm_msgs/Blob";
    const ENCODING: &'static str = "application/octet-stream";
    const SCHEMA: &'static str = "uint8[] data\n";
}
