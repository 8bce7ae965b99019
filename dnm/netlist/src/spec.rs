//! What a module kind declares about itself: its ports, message types, parameters and trigger.
//!
//! These are plain data so that the netlist can be validated without starting anything. The
//! module SDK builds them from Rust types; external module executables print them as JSON.

use std::collections::BTreeMap;
use std::fmt;

use serde::{Deserialize, Serialize};

/// How a port's payload is laid out in shared memory.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "layout")]
pub enum Payload {
    /// A fixed-size plain-old-data value of exactly `size_bytes`.
    Fixed { size_bytes: usize },
    /// A variable-size byte payload of at most `max_bytes` (images, point clouds, text).
    Bytes { max_bytes: usize },
}

/// Payloads above this many bytes are large: their ports reserve fewer, deeper-costing
/// subscriber slots.
pub const LARGE_PAYLOAD_BYTES: usize = 64 * 1024;
/// Subscribers an output port admits at least (its readers and spares may need more).
pub const MIN_SUBSCRIBERS: usize = 16;
/// The same for a large port: each subscriber reserves whole samples.
pub const MIN_LARGE_SUBSCRIBERS: usize = 6;
/// Subscribers the DNM itself may hold on a port beside its readers: the recorder, the Zenoh
/// egress, the bridge's monitor and a watch.
pub const DNM_SUBSCRIBERS: usize = 4;
/// Subscriber slots a port keeps beyond its readers in the netlist: the DNM's own, and room for
/// tools and a crashed reader's slot not yet swept.
pub const SPARE_SUBSCRIBERS: usize = 8;
/// The same for a large port, whose every slot reserves samples of shared memory.
pub const SPARE_LARGE_SUBSCRIBERS: usize = 5;
/// Shared memory the subscriber slots of one port may reserve (a port's readers are refused
/// beyond it, but a large port always admits [`MIN_LARGE_READERS`]).
pub const PORT_MEMORY: usize = 64 << 20;
/// Readers a large port admits whatever its samples' size.
pub const MIN_LARGE_READERS: usize = 4;
/// Samples one subscriber slot of a port reserves (a recorder's buffer and two borrowed).
pub(crate) const SAMPLES_PER_SUBSCRIBER: usize = 10;
/// Readers one port feeds on one DNM at most, whatever its size: a service admits 256 nodes
/// (`MAX_MODULES`), and the DNM's own, the publishers' and tools' nodes need some of them.
pub const MAX_READERS: usize = 240;

impl Payload {
    /// The largest number of payload bytes a sample of this port can hold.
    pub fn max_bytes(&self) -> usize {
        match *self {
            Payload::Fixed { size_bytes } => size_bytes,
            Payload::Bytes { max_bytes } => max_bytes,
        }
    }

    /// Whether ports of this payload use the large-port limits.
    pub fn is_large(&self) -> bool {
        self.max_bytes() > LARGE_PAYLOAD_BYTES
    }

    fn spare(&self) -> usize {
        if self.is_large() {
            SPARE_LARGE_SUBSCRIBERS
        } else {
            SPARE_SUBSCRIBERS
        }
    }

    /// Subscribers a port of this payload admits with `readers` modules reading it on its DNM:
    /// at least [`MIN_SUBSCRIBERS`] ([`MIN_LARGE_SUBSCRIBERS`]), and the readers plus the spares.
    pub fn subscribers_for(&self, readers: usize) -> usize {
        let floor = if self.is_large() {
            MIN_LARGE_SUBSCRIBERS
        } else {
            MIN_SUBSCRIBERS
        };
        (readers + self.spare()).max(floor)
    }

    /// Readers one port of this payload can feed on one DNM: as many as [`PORT_MEMORY`] holds
    /// samples for (with the spares), at most [`MAX_READERS`], and a large port at least
    /// [`MIN_LARGE_READERS`].
    pub fn max_readers(&self) -> usize {
        let slots = PORT_MEMORY / (SAMPLES_PER_SUBSCRIBER * self.max_bytes().max(1));
        let readers = slots.saturating_sub(self.spare()).min(MAX_READERS);
        if self.is_large() {
            readers.max(MIN_LARGE_READERS)
        } else {
            readers
        }
    }
}

/// Encoding of fixed-size messages: the `repr(C)` little-endian layout of the fields in the
/// schema.
pub const POD_ENCODING: &str = "dnm-pod";

/// The type carried by a port: a schema name and encoding that recordings and other tools use
/// to decode it, plus its shared-memory layout.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct MessageType {
    /// For example `dnm_msgs/Tick`.
    pub schema_name: String,
    /// For example `dnm-pod` (little-endian `repr(C)` layout described by `schema`).
    pub encoding: String,
    /// The schema text (field list) for decoders.
    pub schema: String,
    pub payload: Payload,
    /// The standard (ROS 2) message recordings store this type as, so robotics tools draw it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub standard: Option<Standard>,
}

/// How a fixed-size message type is recorded as a standard ROS 2 message: which field of the
/// standard message each of its fields becomes.
///
/// `fields` pairs a field path of the standard message (`pose.pose.position.x`,
/// `angular_velocity.z`, `name[0]`) with where its value comes from:
/// - a field of ours (`x`, `gyro[2]`);
/// - a number (`-1`) or text in single quotes (`'odom'`); `$module` is the producing module's
///   name;
/// - for a quaternion path (`pose.pose.orientation`, `transform.rotation`): `yaw`, or
///   `roll pitch yaw`, fields of ours in radians.
///
/// Fields of the standard message named nowhere are zero (or empty); the header's stamp is the
/// sample's send time. Where the standard message cannot hold every field of ours exactly, the
/// recorder keeps our bytes beside it (`<port>/raw`), so a replay stays exact.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Standard {
    /// For example `nav_msgs/msg/Odometry`.
    pub name: String,
    /// `[standard field path, source]` pairs.
    pub fields: Vec<[String; 2]>,
    /// Where the message is a body's pose (a transform to the body's frame): the body, as a URDF
    /// document whose root link is that frame. Recordings carry it once per file, as a
    /// `std_msgs/msg/String` on `/<dnm>/_robot_description/<module>`, so tools that draw URDF
    /// (Rerun, Foxglove) draw the body where the poses put it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub body: Option<String>,
}

impl MessageType {
    /// Two ports may be linked when the producer's type is the consumer's type.
    pub fn compatible_with(&self, input: &MessageType) -> bool {
        self.schema_name == input.schema_name
            && self.encoding == input.encoding
            && match (self.payload, input.payload) {
                (Payload::Fixed { size_bytes: a }, Payload::Fixed { size_bytes: b }) => a == b,
                (Payload::Bytes { .. }, Payload::Bytes { .. }) => true,
                _ => false,
            }
    }
}

impl fmt::Display for MessageType {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.payload {
            Payload::Fixed { size_bytes } => write!(f, "{} ({size_bytes} B)", self.schema_name),
            Payload::Bytes { max_bytes } => {
                write!(f, "{} (bytes, up to {max_bytes} B)", self.schema_name)
            }
        }
    }
}

/// One input or output port of a kind.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct PortSpec {
    pub name: String,
    pub message: MessageType,
}

impl PortSpec {
    /// The port as tools away from its DNM are told of it: without a body's URDF
    /// ([`Standard::body`]), which only the DNM's recorder writes and which would cross the
    /// radio in every answer otherwise.
    pub fn without_body(&self) -> PortSpec {
        let mut p = self.clone();
        if let Some(s) = p.message.standard.as_mut() {
            s.body = None;
        }
        p
    }
}

/// The type of a parameter.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ParamKind {
    Float,
    Int,
    Bool,
    String,
}

impl fmt::Display for ParamKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            ParamKind::Float => "float",
            ParamKind::Int => "integer",
            ParamKind::Bool => "boolean",
            ParamKind::String => "string",
        })
    }
}

/// A parameter value as given in a netlist.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum ParamValue {
    Bool(bool),
    Int(i64),
    Float(f64),
    String(String),
}

impl ParamValue {
    pub fn kind(&self) -> ParamKind {
        match self {
            ParamValue::Bool(_) => ParamKind::Bool,
            ParamValue::Int(_) => ParamKind::Int,
            ParamValue::Float(_) => ParamKind::Float,
            ParamValue::String(_) => ParamKind::String,
        }
    }

    /// Converts to the declared kind where that loses nothing (an integer given for a float).
    pub fn coerce(self, kind: ParamKind) -> Option<ParamValue> {
        match (self, kind) {
            (ParamValue::Int(i), ParamKind::Float) => Some(ParamValue::Float(i as f64)),
            (v, k) if v.kind() == k => Some(v),
            _ => None,
        }
    }

    pub fn as_f64(&self) -> Option<f64> {
        match *self {
            ParamValue::Float(v) => Some(v),
            ParamValue::Int(v) => Some(v as f64),
            _ => None,
        }
    }

    pub fn as_i64(&self) -> Option<i64> {
        match *self {
            ParamValue::Int(v) => Some(v),
            _ => None,
        }
    }

    pub fn as_bool(&self) -> Option<bool> {
        match *self {
            ParamValue::Bool(v) => Some(v),
            _ => None,
        }
    }

    pub fn as_str(&self) -> Option<&str> {
        match self {
            ParamValue::String(v) => Some(v),
            _ => None,
        }
    }
}

impl fmt::Display for ParamValue {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ParamValue::Bool(v) => write!(f, "{v}"),
            ParamValue::Int(v) => write!(f, "{v}"),
            ParamValue::Float(v) => write!(f, "{v}"),
            ParamValue::String(v) => write!(f, "{v:?}"),
        }
    }
}

/// A declared parameter. Without a default it must be given in the netlist.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ParamSpec {
    pub name: String,
    pub kind: ParamKind,
    pub default: Option<ParamValue>,
    #[serde(default)]
    pub doc: String,
}

/// When a module's step runs.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "mode")]
pub enum Trigger {
    /// At a fixed rate; a netlist may override the rate per module.
    Periodic { rate_hz: f64 },
    /// Whenever an input connected in the active task has new data.
    OnInput,
}

/// Everything the DNM and the validator need to know about a module kind.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct KindSpec {
    pub name: String,
    #[serde(default)]
    pub summary: String,
    pub inputs: Vec<PortSpec>,
    pub outputs: Vec<PortSpec>,
    pub params: Vec<ParamSpec>,
    pub trigger: Trigger,
}

impl KindSpec {
    pub fn input(&self, port: &str) -> Option<&PortSpec> {
        self.inputs.iter().find(|p| p.name == port)
    }

    pub fn output(&self, port: &str) -> Option<&PortSpec> {
        self.outputs.iter().find(|p| p.name == port)
    }

    pub fn param(&self, name: &str) -> Option<&ParamSpec> {
        self.params.iter().find(|p| p.name == name)
    }
}

/// Where a kind's executable comes from.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "from")]
pub enum KindSource {
    /// Compiled into the standard module host shipped with the DNM.
    BuiltIn,
    /// An executable built with the module SDK, declared in the netlist.
    Exec { path: String },
}

/// A kind and where it runs from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CatalogEntry {
    pub spec: KindSpec,
    pub source: KindSource,
}

/// The module kinds a netlist may use, by name.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Catalog {
    kinds: BTreeMap<String, CatalogEntry>,
}

impl Catalog {
    pub fn new() -> Self {
        Self::default()
    }

    /// The catalog as tools away from the DNM are told of it (see [`PortSpec::without_body`]).
    pub fn without_bodies(&self) -> Catalog {
        let mut c = self.clone();
        for e in c.kinds.values_mut() {
            for p in e.spec.inputs.iter_mut().chain(e.spec.outputs.iter_mut()) {
                *p = p.without_body();
            }
        }
        c
    }

    /// Adds or replaces a kind.
    pub fn insert(&mut self, spec: KindSpec, source: KindSource) {
        self.kinds
            .insert(spec.name.clone(), CatalogEntry { spec, source });
    }

    pub fn get(&self, kind: &str) -> Option<&CatalogEntry> {
        self.kinds.get(kind)
    }

    pub fn names(&self) -> impl Iterator<Item = &str> + Clone {
        self.kinds.keys().map(String::as_str)
    }

    pub fn iter(&self) -> impl Iterator<Item = &CatalogEntry> {
        self.kinds.values()
    }
}
