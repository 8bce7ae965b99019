//! Standard ROS 2 messages: a fixed-size message type that declares its standard equivalent
//! ([`dnm_netlist::Standard`]) is recorded as that message, CDR-encoded, so Rerun, Foxglove and
//! PlotJuggler draw it without our code; and a replay maps it back.
//!
//! A [`StandardMapping`] is compiled once per channel from the message type: where each field
//! of the standard message comes from (one of our fields, a constant, the module's name, the
//! send stamp, a quaternion from our yaw or roll/pitch/yaw). It knows whether the standard
//! message holds every one of our fields exactly ([`StandardMapping::exact`]); when it does not
//! (a `float32` field, a quaternion, a field with no place in it), the recorder keeps our bytes
//! beside it.

use dnm_netlist::MessageType;

/// Why a recorded message could not be read back into its port's bytes (the recording is
/// damaged, or was not written by this recorder).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum DecodeError {
    #[error("message shorter than its CDR header")]
    ShortHeader,
    #[error("CDR byte sequence runs past the message")]
    SequencePastEnd,
    #[error("not little-endian CDR")]
    NotLittleEndian,
    #[error("the image message ends early")]
    ImageEndsEarly,
    /// `encoding` as the message spells it (with its terminating NUL).
    #[error("image encoding {encoding} is not rgb8")]
    NotRgb8 { encoding: String },
    #[error("big-endian CDR is not read")]
    BigEndian,
    #[error("not CDR (no little-endian encapsulation header)")]
    NotCdr,
    #[error("the message ends early")]
    EndsEarly,
    #[error("a list longer than the message")]
    ListTooLong,
    #[error("expected {expected} element(s) in the list")]
    ListCount { expected: u32 },
}

const SEP: &str =
    "================================================================================\n";

/// Leaf types of a standard message, in CDR order.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Ty {
    /// `builtin_interfaces/Time`: `int32 sec`, `uint32 nanosec`.
    Stamp,
    Str,
    F64,
    F32,
    U8,
    Bool,
    /// `float64[N]`.
    F64Arr(usize),
    /// `float32[]`, `float64[]`, `string[]`.
    F32Seq,
    F64Seq,
    StrSeq,
    /// A sequence of structures written with this many elements (its leaves follow).
    Count(u32),
}

struct Def {
    name: &'static str,
    schema: fn() -> String,
}

macro_rules! xyz {
    ($p:literal) => {
        [
            (concat!($p, ".x"), Ty::F64),
            (concat!($p, ".y"), Ty::F64),
            (concat!($p, ".z"), Ty::F64),
        ]
    };
}

const HEADER: [(&str, Ty); 2] = [("header.stamp", Ty::Stamp), ("header.frame_id", Ty::Str)];

fn header_deps() -> String {
    format!(
        "{SEP}MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n{SEP}MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n"
    )
}
fn vector3() -> String {
    format!("{SEP}MSG: geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z\n")
}
fn quaternion() -> String {
    format!(
        "{SEP}MSG: geometry_msgs/Quaternion\nfloat64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n"
    )
}
fn twist() -> String {
    format!(
        "{SEP}MSG: geometry_msgs/Twist\nVector3 linear\nVector3 angular\n{}",
        vector3()
    )
}

fn concat<const A: usize, const B: usize>(
    a: [(&'static str, Ty); A],
    b: [(&'static str, Ty); B],
) -> Vec<(&'static str, Ty)> {
    a.into_iter().chain(b).collect()
}

static TWIST_STAMPED: std::sync::LazyLock<Vec<(&str, Ty)>> = std::sync::LazyLock::new(|| {
    let mut v = HEADER.to_vec();
    v.extend(xyz!("twist.linear"));
    v.extend(xyz!("twist.angular"));
    v
});
static ODOMETRY: std::sync::LazyLock<Vec<(&str, Ty)>> = std::sync::LazyLock::new(|| {
    let mut v = concat(HEADER, [("child_frame_id", Ty::Str)]);
    v.extend(xyz!("pose.pose.position"));
    v.extend(xyz!("pose.pose.orientation"));
    v.push(("pose.pose.orientation.w", Ty::F64));
    v.push(("pose.covariance", Ty::F64Arr(36)));
    v.extend(xyz!("twist.twist.linear"));
    v.extend(xyz!("twist.twist.angular"));
    v.push(("twist.covariance", Ty::F64Arr(36)));
    v
});
static IMU: std::sync::LazyLock<Vec<(&str, Ty)>> = std::sync::LazyLock::new(|| {
    let mut v = HEADER.to_vec();
    v.extend(xyz!("orientation"));
    v.push(("orientation.w", Ty::F64));
    v.push(("orientation_covariance", Ty::F64Arr(9)));
    v.extend(xyz!("angular_velocity"));
    v.push(("angular_velocity_covariance", Ty::F64Arr(9)));
    v.extend(xyz!("linear_acceleration"));
    v.push(("linear_acceleration_covariance", Ty::F64Arr(9)));
    v
});
static BATTERY: std::sync::LazyLock<Vec<(&str, Ty)>> = std::sync::LazyLock::new(|| {
    concat(
        HEADER,
        [
            ("voltage", Ty::F32),
            ("temperature", Ty::F32),
            ("current", Ty::F32),
            ("charge", Ty::F32),
            ("capacity", Ty::F32),
            ("design_capacity", Ty::F32),
            ("percentage", Ty::F32),
            ("power_supply_status", Ty::U8),
            ("power_supply_health", Ty::U8),
            ("power_supply_technology", Ty::U8),
            ("present", Ty::Bool),
            ("cell_voltage", Ty::F32Seq),
            ("cell_temperature", Ty::F32Seq),
            ("location", Ty::Str),
            ("serial_number", Ty::Str),
        ],
    )
});
static RANGE: std::sync::LazyLock<Vec<(&str, Ty)>> = std::sync::LazyLock::new(|| {
    concat(
        HEADER,
        [
            ("radiation_type", Ty::U8),
            ("field_of_view", Ty::F32),
            ("min_range", Ty::F32),
            ("max_range", Ty::F32),
            ("range", Ty::F32),
        ],
    )
});
static JOINT_STATE: std::sync::LazyLock<Vec<(&str, Ty)>> = std::sync::LazyLock::new(|| {
    concat(
        HEADER,
        [
            ("name", Ty::StrSeq),
            ("position", Ty::F64Seq),
            ("velocity", Ty::F64Seq),
            ("effort", Ty::F64Seq),
        ],
    )
});
static TF_MESSAGE: std::sync::LazyLock<Vec<(&str, Ty)>> = std::sync::LazyLock::new(|| {
    let mut v = vec![("transforms", Ty::Count(1))];
    v.extend(HEADER);
    v.push(("child_frame_id", Ty::Str));
    v.extend(xyz!("transform.translation"));
    v.extend(xyz!("transform.rotation"));
    v.push(("transform.rotation.w", Ty::F64));
    v
});

/// A standard message's leaves, in CDR order.
type Leaves = std::sync::LazyLock<Vec<(&'static str, Ty)>>;

fn defs() -> [(Def, &'static Leaves); 7] {
    let d = |name, schema: fn() -> String| Def { name, schema };
    [
        (
            d("geometry_msgs/msg/TwistStamped", || {
                format!(
                    "std_msgs/Header header\ngeometry_msgs/Twist twist\n{}{}",
                    header_deps(),
                    twist()
                )
            }),
            &TWIST_STAMPED,
        ),
        (
            d("nav_msgs/msg/Odometry", || {
                format!(
                    "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/PoseWithCovariance pose\ngeometry_msgs/TwistWithCovariance twist\n{}{SEP}MSG: geometry_msgs/PoseWithCovariance\nPose pose\nfloat64[36] covariance\n{SEP}MSG: geometry_msgs/Pose\nPoint position\nQuaternion orientation\n{SEP}MSG: geometry_msgs/Point\nfloat64 x\nfloat64 y\nfloat64 z\n{}{SEP}MSG: geometry_msgs/TwistWithCovariance\nTwist twist\nfloat64[36] covariance\n{}",
                    header_deps(),
                    quaternion(),
                    twist()
                )
            }),
            &ODOMETRY,
        ),
        (
            d("sensor_msgs/msg/Imu", || {
                format!(
                    "std_msgs/Header header\ngeometry_msgs/Quaternion orientation\nfloat64[9] orientation_covariance\ngeometry_msgs/Vector3 angular_velocity\nfloat64[9] angular_velocity_covariance\ngeometry_msgs/Vector3 linear_acceleration\nfloat64[9] linear_acceleration_covariance\n{}{}{}",
                    header_deps(),
                    quaternion(),
                    vector3()
                )
            }),
            &IMU,
        ),
        (
            d("sensor_msgs/msg/BatteryState", || {
                format!(
                    "uint8 POWER_SUPPLY_STATUS_UNKNOWN = 0\nuint8 POWER_SUPPLY_STATUS_CHARGING = 1\nuint8 POWER_SUPPLY_STATUS_DISCHARGING = 2\nuint8 POWER_SUPPLY_STATUS_NOT_CHARGING = 3\nuint8 POWER_SUPPLY_STATUS_FULL = 4\nuint8 POWER_SUPPLY_TECHNOLOGY_UNKNOWN = 0\nuint8 POWER_SUPPLY_TECHNOLOGY_NIMH = 1\nuint8 POWER_SUPPLY_TECHNOLOGY_LION = 2\nstd_msgs/Header header\nfloat32 voltage\nfloat32 temperature\nfloat32 current\nfloat32 charge\nfloat32 capacity\nfloat32 design_capacity\nfloat32 percentage\nuint8 power_supply_status\nuint8 power_supply_health\nuint8 power_supply_technology\nbool present\nfloat32[] cell_voltage\nfloat32[] cell_temperature\nstring location\nstring serial_number\n{}",
                    header_deps()
                )
            }),
            &BATTERY,
        ),
        (
            d("sensor_msgs/msg/Range", || {
                format!(
                    "uint8 ULTRASOUND=0\nuint8 INFRARED=1\nstd_msgs/Header header\nuint8 radiation_type\nfloat32 field_of_view\nfloat32 min_range\nfloat32 max_range\nfloat32 range\n{}",
                    header_deps()
                )
            }),
            &RANGE,
        ),
        (
            d("sensor_msgs/msg/JointState", || {
                format!(
                    "std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\nfloat64[] effort\n{}",
                    header_deps()
                )
            }),
            &JOINT_STATE,
        ),
        (
            d("tf2_msgs/msg/TFMessage", || {
                format!(
                    "geometry_msgs/TransformStamped[] transforms\n{SEP}MSG: geometry_msgs/TransformStamped\nstd_msgs/Header header\nstring child_frame_id\nTransform transform\n{}{SEP}MSG: geometry_msgs/Transform\nVector3 translation\nQuaternion rotation\n{}{}",
                    header_deps(),
                    vector3(),
                    quaternion()
                )
            }),
            &TF_MESSAGE,
        ),
    ]
}

/// The standard messages a message type may declare.
pub fn supported() -> Vec<&'static str> {
    defs().iter().map(|(d, _)| d.name).collect()
}

/// One of our fields (every fixed-size field is 8 bytes: `float64`, `int64`, `uint64`).
#[derive(Debug, Clone)]
struct Field {
    name: String,
    offset: usize,
    ty: NTy,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum NTy {
    F64,
    I64,
    U64,
}

/// Our fields, from the schema (`float64 x`, `float64[3] gyro`).
fn fields(schema: &str) -> Result<Vec<Field>, String> {
    let mut out = Vec::new();
    let mut offset = 0;
    for line in schema.lines() {
        let line = line.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        let mut parts = line.split_whitespace();
        let (Some(ty), Some(name)) = (parts.next(), parts.next()) else {
            return Err(format!("schema line `{line}` is not `<type> <name>`"));
        };
        let (base, n) = match ty.split_once('[') {
            Some((b, rest)) => {
                let n: usize = rest
                    .trim_end_matches(']')
                    .parse()
                    .map_err(|_| format!("`{ty}`: only fixed-size arrays have a standard form"))?;
                (b, Some(n))
            }
            None => (ty, None),
        };
        let nty = match base {
            "float64" => NTy::F64,
            "int64" => NTy::I64,
            "uint64" => NTy::U64,
            other => {
                return Err(format!(
                    "field `{name}` is {other}: only 8-byte fields map to a standard message"
                ));
            }
        };
        match n {
            None => {
                out.push(Field {
                    name: name.to_string(),
                    offset,
                    ty: nty,
                });
                offset += 8;
            }
            Some(n) => {
                for i in 0..n {
                    out.push(Field {
                        name: format!("{name}[{i}]"),
                        offset,
                        ty: nty,
                    });
                    offset += 8;
                }
            }
        }
    }
    Ok(out)
}

/// Where a value of the standard message comes from.
#[derive(Debug, Clone)]
enum Src {
    Zero,
    Const(f64),
    Text(String),
    Module,
    Field(usize),
    /// Component (x, y, z, w) of the quaternion of roll, pitch, yaw (fields; `None`: zero).
    Quat([Option<usize>; 3], usize),
}

/// How one of our fields is read back from the standard message.
#[derive(Debug, Clone)]
enum Back {
    /// Leaf `leaf`, element `elem`.
    Leaf(usize, usize),
    /// Roll (0), pitch (1) or yaw (2) of the quaternion whose x leaf is `leaf`.
    Angle(usize, usize),
    /// Not in the standard message.
    Lost,
}

/// Why a message type's declaration of its standard equivalent cannot be followed (the
/// recorder then records the message as it is): the declaration is to be fixed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum StandardMappingError {
    #[error("{schema}: only fixed-size messages map to a standard message")]
    NotFixedSize { schema: String },
    #[error(
        "{schema}: `{standard}` is not a standard message the recorder knows; it knows {}",
        known.join(", ")
    )]
    UnknownStandard {
        schema: String,
        standard: String,
        known: Vec<&'static str>,
    },
    /// A field of the schema that no standard message can hold.
    #[error("{schema}: {reason}")]
    Schema { schema: String, reason: String },
    #[error("{schema}: its schema describes {described} bytes but the message is {declared}")]
    Size {
        schema: String,
        described: usize,
        declared: usize,
    },
    /// One declared field, `to` (in the standard message) from `from` (ours).
    #[error("{schema}: standard field `{to}` from `{from}`: {why}")]
    Field {
        schema: String,
        to: String,
        from: String,
        why: String,
    },
    #[error("{schema}: list elements must be declared from [0] on, without gaps")]
    ListGap { schema: String },
}

/// How a message type is written as, and read back from, its standard message.
#[derive(Debug, Clone)]
pub struct StandardMapping {
    name: &'static str,
    schema: String,
    leaves: Vec<(Ty, Vec<Src>)>,
    fields: Vec<Field>,
    size: usize,
    back: Vec<Back>,
    exact: bool,
}

impl StandardMapping {
    /// The mapping for `message`, `None` when it declares no standard equivalent; an error says
    /// why a declaration cannot be followed.
    pub fn of(message: &MessageType) -> Result<Option<StandardMapping>, StandardMappingError> {
        let Some(std) = &message.standard else {
            return Ok(None);
        };
        let schema = || message.schema_name.clone();
        if message.encoding != dnm_netlist::POD_ENCODING {
            return Err(StandardMappingError::NotFixedSize { schema: schema() });
        }
        let all = defs();
        let Some((def, leaves)) = all.iter().find(|(d, _)| d.name == std.name) else {
            return Err(StandardMappingError::UnknownStandard {
                schema: schema(),
                standard: std.name.clone(),
                known: supported(),
            });
        };
        let fields = fields(&message.schema).map_err(|reason| StandardMappingError::Schema {
            schema: schema(),
            reason,
        })?;
        let size = fields.len() * 8;
        if let dnm_netlist::Payload::Fixed { size_bytes } = message.payload
            && size_bytes != size
        {
            return Err(StandardMappingError::Size {
                schema: schema(),
                described: size,
                declared: size_bytes,
            });
        }
        let mut draft = Draft::new(leaves, &fields);
        for [to, from] in &std.fields {
            draft
                .map(to, from, &std.name)
                .map_err(|why| StandardMappingError::Field {
                    schema: schema(),
                    to: to.clone(),
                    from: from.clone(),
                    why,
                })?;
        }
        if draft.has_gaps() {
            // Gaps in a list would write zeros the declaration did not ask for.
            return Err(StandardMappingError::ListGap { schema: schema() });
        }
        let exact = draft.exact && draft.back.iter().all(|b| !matches!(b, Back::Lost));
        Ok(Some(StandardMapping {
            name: def.name,
            schema: (def.schema)(),
            leaves: draft.srcs,
            back: draft.back,
            fields,
            size,
            exact,
        }))
    }

    /// The standard message's name, e.g. `nav_msgs/msg/Odometry`.
    pub fn name(&self) -> &'static str {
        self.name
    }

    /// Its ROS 2 `.msg` schema with its dependencies, as MCAP tools expect.
    pub fn schema(&self) -> &str {
        &self.schema
    }

    /// Whether the standard message holds every one of our fields exactly (no `float32`, no
    /// quaternion, none left out).
    pub fn exact(&self) -> bool {
        self.exact
    }

    /// Our fields the standard message has no place for.
    pub fn lost(&self) -> Vec<&str> {
        self.fields
            .iter()
            .zip(&self.back)
            .filter(|(_, b)| matches!(b, Back::Lost))
            .map(|(f, _)| f.name.as_str())
            .collect()
    }

    fn native(&self, bytes: &[u8], i: usize) -> f64 {
        let f = &self.fields[i];
        let Some(b) = bytes.get(f.offset..f.offset + 8) else {
            return 0.0;
        };
        let b: [u8; 8] = b.try_into().unwrap_or([0; 8]);
        match f.ty {
            NTy::F64 => f64::from_le_bytes(b),
            NTy::I64 => i64::from_le_bytes(b) as f64,
            NTy::U64 => u64::from_le_bytes(b) as f64,
        }
    }

    fn value(&self, src: &Src, bytes: &[u8]) -> f64 {
        match src {
            Src::Zero | Src::Text(_) | Src::Module => 0.0,
            Src::Const(c) => *c,
            Src::Field(i) => self.native(bytes, *i),
            Src::Quat(rpy, c) => {
                let a = |k: usize| rpy[k].map_or(0.0, |i| self.native(bytes, i)) / 2.0;
                let (sr, cr) = a(0).sin_cos();
                let (sp, cp) = a(1).sin_cos();
                let (sy, cy) = a(2).sin_cos();
                match c {
                    0 => sr * cp * cy - cr * sp * sy,
                    1 => cr * sp * cy + sr * cp * sy,
                    2 => cr * cp * sy - sr * sp * cy,
                    _ => cr * cp * cy + sr * sp * sy,
                }
            }
        }
    }

    /// Our message `bytes`, sent at `stamp_unix_ns` by `module`, as the standard message (CDR,
    /// little-endian, with its encapsulation header).
    pub fn encode(&self, bytes: &[u8], stamp_unix_ns: u64, module: &str) -> Vec<u8> {
        let mut w = Cdr::new(self.leaves.len() * 8);
        fn text<'a>(s: &'a Src, module: &'a str) -> &'a str {
            match s {
                Src::Text(t) => t.as_str(),
                Src::Module => module,
                _ => "",
            }
        }
        for (ty, srcs) in &self.leaves {
            match ty {
                Ty::Stamp => {
                    // `int32 sec`, as ROS 2 has it.
                    w.i32((stamp_unix_ns / 1_000_000_000) as i32);
                    w.u32((stamp_unix_ns % 1_000_000_000) as u32);
                }
                Ty::Str => w.string(text(&srcs[0], module)),
                Ty::F64 | Ty::F64Arr(_) => {
                    for s in srcs {
                        w.f64(self.value(s, bytes));
                    }
                }
                Ty::F32 => w.f32(self.value(&srcs[0], bytes) as f32),
                Ty::U8 => w.0.push(self.value(&srcs[0], bytes) as u8),
                Ty::Bool => w.0.push(u8::from(self.value(&srcs[0], bytes) != 0.0)),
                Ty::F32Seq => {
                    w.u32(srcs.len() as u32);
                    for s in srcs {
                        w.f32(self.value(s, bytes) as f32);
                    }
                }
                Ty::F64Seq => {
                    w.u32(srcs.len() as u32);
                    for s in srcs {
                        w.f64(self.value(s, bytes));
                    }
                }
                Ty::StrSeq => {
                    w.u32(srcs.len() as u32);
                    for s in srcs {
                        w.string(text(s, module));
                    }
                }
                Ty::Count(n) => w.u32(*n),
            }
        }
        w.0
    }

    /// Our message's bytes from a standard message this mapping wrote. Fields it has no place for
    /// are zero; `float32` fields come back as `float32` held them.
    pub fn decode(&self, data: &[u8]) -> Result<Vec<u8>, DecodeError> {
        match data.get(..2) {
            Some([0, 1]) => {}
            Some([0, 0]) => return Err(DecodeError::BigEndian),
            _ => return Err(DecodeError::NotCdr),
        }
        let mut r = Reader { data, at: 4 };
        let mut values: Vec<Vec<f64>> = Vec::with_capacity(self.leaves.len());
        for (ty, _) in &self.leaves {
            let mut v = Vec::new();
            match ty {
                Ty::Stamp => {
                    r.u32()?;
                    r.u32()?;
                }
                Ty::Str => r.string()?,
                Ty::F64 => v.push(r.f64()?),
                Ty::F64Arr(n) => {
                    for _ in 0..*n {
                        v.push(r.f64()?);
                    }
                }
                Ty::F32 => v.push(f64::from(r.f32()?)),
                Ty::U8 | Ty::Bool => v.push(f64::from(r.u8()?)),
                Ty::F32Seq | Ty::F64Seq | Ty::StrSeq => {
                    let n = r.u32()? as usize;
                    if n > r.data.len() {
                        return Err(DecodeError::ListTooLong);
                    }
                    for _ in 0..n {
                        match ty {
                            Ty::F32Seq => v.push(f64::from(r.f32()?)),
                            Ty::F64Seq => v.push(r.f64()?),
                            _ => r.string()?,
                        }
                    }
                }
                Ty::Count(n) => {
                    if r.u32()? != *n {
                        return Err(DecodeError::ListCount { expected: *n });
                    }
                }
            }
            values.push(v);
        }
        let mut out = vec![0u8; self.size];
        for (i, f) in self.fields.iter().enumerate() {
            let v = match &self.back[i] {
                Back::Lost => 0.0,
                Back::Leaf(leaf, elem) => values[*leaf].get(*elem).copied().unwrap_or(0.0),
                Back::Angle(x, angle) => {
                    let q = |c: usize| {
                        values
                            .get(x + c)
                            .and_then(|v| v.first())
                            .copied()
                            .unwrap_or(0.0)
                    };
                    let (qx, qy, qz, qw) = (q(0), q(1), q(2), q(3));
                    match angle {
                        0 => (2.0 * (qw * qx + qy * qz)).atan2(1.0 - 2.0 * (qx * qx + qy * qy)),
                        1 => (2.0 * (qw * qy - qz * qx)).clamp(-1.0, 1.0).asin(),
                        _ => (2.0 * (qw * qz + qx * qy)).atan2(1.0 - 2.0 * (qy * qy + qz * qz)),
                    }
                }
            };
            let b = match f.ty {
                NTy::F64 => v.to_le_bytes(),
                NTy::I64 => (v.round() as i64).to_le_bytes(),
                NTy::U64 => (v.round() as u64).to_le_bytes(),
            };
            out[f.offset..f.offset + 8].copy_from_slice(&b);
        }
        Ok(out)
    }
}

/// A [`StandardMapping`] being built from a declaration: where each leaf of the standard
/// message comes from, and how each of our fields is read back.
struct Draft<'a> {
    /// The standard message's leaves, in CDR order.
    leaves: &'a [(&'static str, Ty)],
    /// Ours.
    fields: &'a [Field],
    srcs: Vec<(Ty, Vec<Src>)>,
    back: Vec<Back>,
    /// Whether every field mapped so far is held exactly.
    exact: bool,
}

impl<'a> Draft<'a> {
    /// Nothing mapped yet: every leaf zero, every field lost.
    fn new(leaves: &'a [(&'static str, Ty)], fields: &'a [Field]) -> Self {
        let srcs = leaves
            .iter()
            .map(|(_, ty)| {
                let n = match ty {
                    Ty::F64Arr(n) => *n,
                    Ty::F32Seq | Ty::F64Seq | Ty::StrSeq => 0,
                    _ => 1,
                };
                (*ty, vec![Src::Zero; n])
            })
            .collect();
        Self {
            leaves,
            fields,
            srcs,
            back: vec![Back::Lost; fields.len()],
            exact: true,
        }
    }

    /// Our field `name`.
    fn field(&self, name: &str) -> Option<usize> {
        self.fields.iter().position(|f| f.name == name)
    }

    /// The standard message's leaf `path`.
    fn leaf(&self, path: &str) -> Option<usize> {
        self.leaves.iter().position(|(p, _)| *p == path)
    }

    /// Maps standard field `to` (of standard message `standard`) from `from`; an error says
    /// why it cannot be.
    fn map(&mut self, to: &str, from: &str, standard: &str) -> Result<(), String> {
        // A quaternion from yaw, or roll pitch yaw.
        if let Some(x) = self.leaf(&format!("{to}.x"))
            && self.leaf(&format!("{to}.w")).is_some()
        {
            return self.quaternion(x, from);
        }
        self.value(to, from, standard)
    }

    /// The quaternion whose x leaf is `x`, from `yaw` or `roll pitch yaw` (`from`).
    fn quaternion(&mut self, x: usize, from: &str) -> Result<(), String> {
        let names: Vec<&str> = from.split_whitespace().collect();
        let idx: Vec<Option<usize>> = names.iter().map(|n| self.field(n)).collect();
        if idx.iter().any(Option::is_none) || !(names.len() == 1 || names.len() == 3) {
            return Err(
                "a quaternion comes from `yaw` or `roll pitch yaw`, fields of the message".into(),
            );
        }
        let rpy = if idx.len() == 1 {
            [None, None, idx[0]]
        } else {
            [idx[0], idx[1], idx[2]]
        };
        if (0..4).any(|c| !matches!(self.srcs[x + c].1.first(), Some(Src::Zero))) {
            return Err("that quaternion is given twice".into());
        }
        for c in 0..4 {
            self.srcs[x + c].1 = vec![Src::Quat(rpy, c)];
        }
        for (angle, f) in rpy.iter().enumerate() {
            if let Some(f) = f {
                if !matches!(self.back[*f], Back::Lost) {
                    return Err("that field is mapped twice".into());
                }
                self.back[*f] = Back::Angle(x, angle);
            }
        }
        self.exact = false;
        Ok(())
    }

    /// Leaf `to` (`path` or `path[i]`) from `from`: one of our fields, a number, 'text' or
    /// `$module`.
    fn value(&mut self, to: &str, from: &str, standard: &str) -> Result<(), String> {
        let (path, elem) = match to.split_once('[') {
            Some((p, rest)) => (
                p,
                Some(
                    rest.trim_end_matches(']')
                        .parse::<usize>()
                        .map_err(|_| "bad index")?,
                ),
            ),
            None => (to, None),
        };
        let leaf = self
            .leaf(path)
            .ok_or_else(|| format!("{standard} has no such field"))?;
        let ty = self.srcs[leaf].0;
        let slot = match (ty, elem) {
            (Ty::F64Arr(n), Some(i)) if i < n => i,
            (Ty::F32Seq | Ty::F64Seq | Ty::StrSeq, Some(i)) if i < 64 => {
                if self.srcs[leaf].1.len() <= i {
                    self.srcs[leaf].1.resize(i + 1, Src::Zero);
                }
                i
            }
            (Ty::Stamp | Ty::Count(_), _) => return Err("written by the recorder".into()),
            (Ty::F64Arr(_) | Ty::F32Seq | Ty::F64Seq | Ty::StrSeq, _) => {
                return Err("name an element, e.g. `name[0]`".into());
            }
            (_, None) => 0,
            (_, Some(_)) => return Err("not a list".into()),
        };
        let src = if from == "$module" {
            Src::Module
        } else if let Some(text) = from.strip_prefix('\'').and_then(|t| t.strip_suffix('\'')) {
            Src::Text(text.to_string())
        } else if let Ok(c) = from.parse::<f64>() {
            Src::Const(c)
        } else if let Some(f) = self.field(from) {
            if !matches!(self.back[f], Back::Lost) {
                return Err("that field is mapped twice".into());
            }
            self.back[f] = Back::Leaf(leaf, slot);
            let lossless =
                matches!(ty, Ty::F64 | Ty::F64Arr(_) | Ty::F64Seq) && self.fields[f].ty == NTy::F64;
            self.exact &= lossless;
            if matches!(ty, Ty::Str | Ty::StrSeq) {
                return Err("a number cannot be a text field".into());
            }
            Src::Field(f)
        } else {
            return Err("neither a field of the message, a number, 'text' nor $module".into());
        };
        let is_text = matches!(ty, Ty::Str | Ty::StrSeq);
        if is_text != matches!(src, Src::Text(_) | Src::Module) {
            return Err(
                "text fields take 'text' or $module, number fields numbers or fields".into(),
            );
        }
        if !matches!(self.srcs[leaf].1[slot], Src::Zero) {
            return Err("that standard field is given twice".into());
        }
        self.srcs[leaf].1[slot] = src;
        Ok(())
    }

    /// Whether a list has an element not declared before a declared one.
    fn has_gaps(&self) -> bool {
        self.srcs.iter().any(|(ty, s)| {
            matches!(ty, Ty::F32Seq | Ty::F64Seq | Ty::StrSeq)
                && s.iter().any(|s| matches!(s, Src::Zero))
        })
    }
}

/// Little-endian CDR writer (after the encapsulation header, alignment is relative to it).
pub(crate) struct Cdr(pub(crate) Vec<u8>);

impl Cdr {
    /// A message of about `capacity` bytes, its encapsulation header written.
    pub(crate) fn new(capacity: usize) -> Self {
        Self::reuse(Vec::new(), capacity)
    }
    /// [`Cdr::new`] in `v`'s memory (its contents are dropped).
    pub(crate) fn reuse(mut v: Vec<u8>, capacity: usize) -> Self {
        v.clear();
        v.reserve(capacity + 64);
        v.extend_from_slice(&[0, 1, 0, 0]);
        Cdr(v)
    }
    fn align(&mut self, n: usize) {
        while !(self.0.len() - 4).is_multiple_of(n) {
            self.0.push(0);
        }
    }
    pub(crate) fn u32(&mut self, v: u32) {
        self.align(4);
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    pub(crate) fn i32(&mut self, v: i32) {
        self.align(4);
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    pub(crate) fn f32(&mut self, v: f32) {
        self.align(4);
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    pub(crate) fn f64(&mut self, v: f64) {
        self.align(8);
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    pub(crate) fn string(&mut self, s: &str) {
        self.u32(s.len() as u32 + 1);
        self.0.extend_from_slice(s.as_bytes());
        self.0.push(0);
    }
    pub(crate) fn bytes(&mut self, b: &[u8]) {
        self.u32(b.len() as u32);
        self.0.extend_from_slice(b);
    }
}

struct Reader<'a> {
    data: &'a [u8],
    at: usize,
}

impl Reader<'_> {
    fn take(&mut self, align: usize, n: usize) -> Result<&[u8], DecodeError> {
        while !(self.at - 4).is_multiple_of(align) {
            self.at += 1;
        }
        let b = self
            .data
            .get(self.at..self.at.saturating_add(n))
            .ok_or(DecodeError::EndsEarly)?;
        self.at += n;
        Ok(b)
    }
    fn u8(&mut self) -> Result<u8, DecodeError> {
        Ok(self.take(1, 1)?[0])
    }
    fn u32(&mut self) -> Result<u32, DecodeError> {
        let b = self.take(4, 4)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }
    fn f32(&mut self) -> Result<f32, DecodeError> {
        Ok(f32::from_bits(self.u32()?))
    }
    fn f64(&mut self) -> Result<f64, DecodeError> {
        let b = self.take(8, 8)?;
        Ok(f64::from_le_bytes(
            b.try_into().map_err(|_| DecodeError::EndsEarly)?,
        ))
    }
    fn string(&mut self) -> Result<(), DecodeError> {
        let n = self.u32()? as usize;
        self.take(1, n)?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;
    use dnm_netlist::{Payload, Standard};

    fn message(schema: &str, standard: &str, fields: &[(&str, &str)]) -> MessageType {
        MessageType {
            schema_name: "t/T".into(),
            encoding: dnm_netlist::POD_ENCODING.into(),
            schema: schema.into(),
            payload: Payload::Fixed {
                size_bytes: schema.lines().count() * 8,
            },
            standard: Some(Standard {
                name: standard.into(),
                fields: fields
                    .iter()
                    .map(|(a, b)| [a.to_string(), b.to_string()])
                    .collect(),
                body: None,
            }),
        }
    }

    fn f64s(v: &[f64]) -> Vec<u8> {
        v.iter().flat_map(|x| x.to_le_bytes()).collect()
    }

    #[test]
    fn a_twist_maps_exactly_and_back() {
        let m = message(
            "float64 linear\nfloat64 angular\n",
            "geometry_msgs/msg/TwistStamped",
            &[
                ("twist.linear.x", "linear"),
                ("twist.angular.z", "angular"),
                ("header.frame_id", "'base_link'"),
            ],
        );
        let p = StandardMapping::of(&m).unwrap().unwrap();
        assert!(p.exact());
        let native = f64s(&[0.25, -0.125]);
        let cdr = p.encode(&native, 1_700_000_000_123_456_789, "m");
        // header: sec, nanosec, "base_link\0" (len 10), padded to 24 bytes; then 6 float64.
        assert_eq!(&cdr[4..8], &1_700_000_000u32.to_le_bytes());
        assert_eq!(&cdr[8..12], &123_456_789u32.to_le_bytes());
        assert_eq!(&cdr[12..16], &10u32.to_le_bytes());
        assert_eq!(&cdr[16..26], b"base_link\0");
        assert_eq!(cdr.len(), 4 + 24 + 48);
        assert_eq!(p.decode(&cdr).unwrap(), native);
    }

    #[test]
    fn yaw_becomes_a_quaternion_and_comes_back_within_rounding() {
        let m = message(
            "float64 x\nfloat64 y\nfloat64 yaw\nfloat64 distance\n",
            "nav_msgs/msg/Odometry",
            &[
                ("pose.pose.position.x", "x"),
                ("pose.pose.position.y", "y"),
                ("pose.pose.orientation", "yaw"),
            ],
        );
        let p = StandardMapping::of(&m).unwrap().unwrap();
        assert!(!p.exact());
        assert_eq!(p.lost(), vec!["distance"]);
        let back = p
            .decode(&p.encode(&f64s(&[1.0, 2.0, 2.5, 7.0]), 0, "m"))
            .unwrap();
        let v: Vec<f64> = back
            .chunks(8)
            .map(|c| f64::from_le_bytes(c.try_into().unwrap()))
            .collect();
        assert_eq!((v[0], v[1], v[3]), (1.0, 2.0, 0.0));
        assert!((v[2] - 2.5).abs() < 1e-12);
    }

    #[test]
    fn roll_pitch_yaw_round_trip() {
        let m = message(
            "float64 roll\nfloat64 pitch\nfloat64 yaw\n",
            "tf2_msgs/msg/TFMessage",
            &[("transform.rotation", "roll pitch yaw")],
        );
        let p = StandardMapping::of(&m).unwrap().unwrap();
        let back = p
            .decode(&p.encode(&f64s(&[0.1, -0.2, 3.0]), 0, "m"))
            .unwrap();
        let v: Vec<f64> = back
            .chunks(8)
            .map(|c| f64::from_le_bytes(c.try_into().unwrap()))
            .collect();
        for (a, b) in v.iter().zip([0.1, -0.2, 3.0]) {
            assert!((a - b).abs() < 1e-12, "{v:?}");
        }
    }

    #[test]
    fn declarations_that_cannot_be_followed_say_why() {
        let bad = [
            (
                "nav_msgs/msg/Nope",
                vec![("a", "x")],
                "not a standard message",
            ),
            (
                "sensor_msgs/msg/Range",
                vec![("rang", "x")],
                "has no such field",
            ),
            (
                "sensor_msgs/msg/Range",
                vec![("range", "nope")],
                "neither a field",
            ),
            (
                "sensor_msgs/msg/JointState",
                vec![("velocity", "x")],
                "name an element",
            ),
            (
                "sensor_msgs/msg/JointState",
                vec![("velocity[1]", "x")],
                "without gaps",
            ),
            (
                "sensor_msgs/msg/Range",
                vec![("range", "x"), ("max_range", "x")],
                "mapped twice",
            ),
            (
                "sensor_msgs/msg/Range",
                vec![("header.frame_id", "x")],
                "text field",
            ),
        ];
        for (name, fields, why) in bad {
            let e = StandardMapping::of(&message("float64 x\n", name, &fields))
                .unwrap_err()
                .to_string();
            assert!(e.contains(why), "{name} {fields:?}: {e}");
        }
    }

    #[test]
    fn damaged_messages_are_errors_not_panics() {
        let m = message(
            "float64 x\n",
            "sensor_msgs/msg/JointState",
            &[("name[0]", "$module"), ("position[0]", "x")],
        );
        let p = StandardMapping::of(&m).unwrap().unwrap();
        let good = p.encode(&f64s(&[4.0]), 5, "wheel");
        for n in 0..good.len() {
            assert!(p.decode(&good[..n]).is_err());
        }
        let mut huge = good.clone();
        huge[20..24].copy_from_slice(&u32::MAX.to_le_bytes());
        let _ = p.decode(&huge);
        assert_eq!(p.decode(&good).unwrap(), f64s(&[4.0]));
    }
}
