//! What Beetle-One's ports carry. Fixed-size messages are `repr(C)` structs of `f64`/`u64`/`i64`
//! fields (no padding) whose `SCHEMA` lists them in ROS 2 `.msg` syntax; frames and telemetry are
//! byte messages.

use bytemuck::{Pod, Zeroable};
use dnm_module::msg::{BytesMessage, Message, StandardMap};

/// A velocity command: forward speed and turn rate.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, Pod, Zeroable)]
pub struct Twist {
    /// m/s, forward positive.
    pub linear: f64,
    /// rad/s, counter-clockwise positive.
    pub angular: f64,
}

impl Message for Twist {
    const SCHEMA_NAME: &'static str = "beetle_msgs/Twist";
    const SCHEMA: &'static str = "float64 linear\nfloat64 angular\n";
    const STANDARD: StandardMap = Some((
        "geometry_msgs/msg/TwistStamped",
        &[
            ("header.frame_id", "'base_link'"),
            ("twist.linear.x", "linear"),
            ("twist.angular.z", "angular"),
        ],
    ));
}

/// A wheel speed command.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, Pod, Zeroable)]
pub struct WheelCommand {
    /// rad/s of the wheel.
    pub omega: f64,
}

impl Message for WheelCommand {
    const SCHEMA_NAME: &'static str = "beetle_msgs/WheelCommand";
    const SCHEMA: &'static str = "float64 omega\n";
}

/// What a wheel motor reports.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, Pod, Zeroable)]
pub struct MotorState {
    /// Wheel speed, rad/s.
    pub omega: f64,
    /// Commanded wheel speed, rad/s (after limits).
    pub command: f64,
    /// Current drawn, A.
    pub current: f64,
    /// 1 while the current limit holds the motor back.
    pub limited: f64,
}

impl Message for MotorState {
    const SCHEMA_NAME: &'static str = "beetle_msgs/MotorState";
    const SCHEMA: &'static str =
        "float64 omega\nfloat64 command\nfloat64 current\nfloat64 limited\n";
    /// The wheel as a joint: its speed and current (the command and limit are kept beside it).
    const STANDARD: StandardMap = Some((
        "sensor_msgs/msg/JointState",
        &[
            ("name[0]", "$module"),
            ("velocity[0]", "omega"),
            ("effort[0]", "current"),
        ],
    ));
}

/// The simulator's ground truth: the rover's pose in the world and its wheels.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, Pod, Zeroable)]
pub struct WorldState {
    pub x: f64,
    pub y: f64,
    /// Terrain height under the rover, m.
    pub z: f64,
    pub yaw: f64,
    pub pitch: f64,
    pub roll: f64,
    /// Body speed, m/s, and turn rate, rad/s.
    pub linear: f64,
    pub angular: f64,
    /// Body acceleration along its heading, m/s².
    pub accel: f64,
    /// Wheel rotation since start, rad.
    pub wheel_left: f64,
    pub wheel_right: f64,
    /// Path length driven, m.
    pub distance: f64,
    /// Steps on which the rover pushed against an obstacle.
    pub blocked: u64,
}

impl Message for WorldState {
    const SCHEMA_NAME: &'static str = "beetle_msgs/WorldState";
    const SCHEMA: &'static str = "float64 x\nfloat64 y\nfloat64 z\nfloat64 yaw\nfloat64 pitch\nfloat64 roll\nfloat64 linear\nfloat64 angular\nfloat64 accel\nfloat64 wheel_left\nfloat64 wheel_right\nfloat64 distance\nuint64 blocked\n";
    /// The rover's pose in the world, as a transform `world` -> `base_link`.
    const STANDARD: StandardMap = Some((
        "tf2_msgs/msg/TFMessage",
        &[
            ("header.frame_id", "'world'"),
            ("child_frame_id", "'base_link'"),
            ("transform.translation.x", "x"),
            ("transform.translation.y", "y"),
            ("transform.translation.z", "z"),
            ("transform.rotation", "roll pitch yaw"),
        ],
    ));
    /// Beetle-One's hull, wheels and camera mast, drawn at the pose.
    const BODY: Option<&'static str> = Some(include_str!("../assets/beetle.urdf"));
}

/// Quadrature encoder counts of both wheels since start.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Pod, Zeroable)]
pub struct EncoderTicks {
    pub left: i64,
    pub right: i64,
}

impl Message for EncoderTicks {
    const SCHEMA_NAME: &'static str = "beetle_msgs/EncoderTicks";
    const SCHEMA: &'static str = "int64 left\nint64 right\n";
}

/// Gyro (rad/s) and accelerometer (m/s²) in the rover frame (x forward, y left, z up).
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, Pod, Zeroable)]
pub struct Imu {
    pub gyro: [f64; 3],
    pub accel: [f64; 3],
}

impl Message for Imu {
    const SCHEMA_NAME: &'static str = "beetle_msgs/Imu";
    const SCHEMA: &'static str = "float64[3] gyro\nfloat64[3] accel\n";
    const STANDARD: StandardMap = Some((
        "sensor_msgs/msg/Imu",
        &[
            ("header.frame_id", "'base_link'"),
            // No orientation estimate (the ROS convention).
            ("orientation_covariance[0]", "-1"),
            ("angular_velocity.x", "gyro[0]"),
            ("angular_velocity.y", "gyro[1]"),
            ("angular_velocity.z", "gyro[2]"),
            ("linear_acceleration.x", "accel[0]"),
            ("linear_acceleration.y", "accel[1]"),
            ("linear_acceleration.z", "accel[2]"),
        ],
    ));
}

/// The battery pack.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, Pod, Zeroable)]
pub struct BatteryState {
    pub voltage: f64,
    pub current: f64,
    /// State of charge, 0 to 1.
    pub charge: f64,
}

impl Message for BatteryState {
    const SCHEMA_NAME: &'static str = "beetle_msgs/BatteryState";
    const SCHEMA: &'static str = "float64 voltage\nfloat64 current\nfloat64 charge\n";
    const STANDARD: StandardMap = Some((
        "sensor_msgs/msg/BatteryState",
        &[
            ("header.frame_id", "$module"),
            ("voltage", "voltage"),
            ("current", "current"),
            ("percentage", "charge"),
            // Discharging, lithium-ion, present.
            ("power_supply_status", "2"),
            ("power_supply_technology", "2"),
            ("present", "1"),
            ("location", "$module"),
        ],
    ));
}

/// Distance to the nearest obstacle ahead.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, Pod, Zeroable)]
pub struct Range {
    /// m; equals `max` when nothing is in range.
    pub range: f64,
    pub max: f64,
}

impl Message for Range {
    const SCHEMA_NAME: &'static str = "beetle_msgs/Range";
    const SCHEMA: &'static str = "float64 range\nfloat64 max\n";
    const STANDARD: StandardMap = Some((
        "sensor_msgs/msg/Range",
        &[
            ("header.frame_id", "$module"),
            ("radiation_type", "1"),
            ("max_range", "max"),
            ("range", "range"),
        ],
    ));
}

/// Pose and velocity estimated from the wheels.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, Pod, Zeroable)]
pub struct Odometry {
    pub x: f64,
    pub y: f64,
    pub yaw: f64,
    pub linear: f64,
    pub angular: f64,
    pub distance: f64,
}

impl Message for Odometry {
    const SCHEMA_NAME: &'static str = "beetle_msgs/Odometry";
    const SCHEMA: &'static str =
        "float64 x\nfloat64 y\nfloat64 yaw\nfloat64 linear\nfloat64 angular\nfloat64 distance\n";
    /// The pose and velocity estimate (the distance driven is kept beside it).
    const STANDARD: StandardMap = Some((
        "nav_msgs/msg/Odometry",
        &[
            ("header.frame_id", "'odom'"),
            ("child_frame_id", "'base_link'"),
            ("pose.pose.position.x", "x"),
            ("pose.pose.position.y", "y"),
            ("pose.pose.orientation", "yaw"),
            ("twist.twist.linear.x", "linear"),
            ("twist.twist.angular.z", "angular"),
        ],
    ));
}

/// The autopilot's progress through its waypoints.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, Pod, Zeroable)]
pub struct Progress {
    pub reached: u64,
    pub total: u64,
    /// Distance to the current waypoint, m (0 when done).
    pub remaining: f64,
}

impl Message for Progress {
    const SCHEMA_NAME: &'static str = "beetle_msgs/Progress";
    const SCHEMA: &'static str = "uint64 reached\nuint64 total\nfloat64 remaining\n";
}

/// What the safety watchdog is doing.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, Pod, Zeroable)]
pub struct WatchdogState {
    /// 1 while commands are stale and the watchdog commands a stop.
    pub tripped: u64,
    /// Times it tripped since start.
    pub trips: u64,
    /// CLOCK_MONOTONIC ns when the newest command was sent (0: none yet).
    pub last_command_ns: u64,
    /// CLOCK_MONOTONIC ns of the last trip.
    pub tripped_at_ns: u64,
    /// Its timeout, ns.
    pub timeout_ns: u64,
}

impl Message for WatchdogState {
    const SCHEMA_NAME: &'static str = "beetle_msgs/WatchdogState";
    const SCHEMA: &'static str = "uint64 tripped\nuint64 trips\nuint64 last_command_ns\nuint64 tripped_at_ns\nuint64 timeout_ns\n";
}

/// An RGB image: a 12-byte header (width, height, row step; little-endian `u32`) then
/// `height` rows of `step` bytes, 3 bytes (r, g, b) per pixel.
#[derive(Debug, Clone, Copy)]
pub struct Image;

impl BytesMessage for Image {
    const SCHEMA_NAME: &'static str = "beetle_msgs/Image";
    const ENCODING: &'static str = "dnm-image-rgb8";
    const SCHEMA: &'static str = "uint32 width\nuint32 height\nuint32 step\nuint8[] data # rgb8\n";
}

/// Bytes of the header in front of an [`Image`]'s pixels.
pub const IMAGE_HEADER: usize = 12;

/// Where an [`Image`]'s pixels lie in its bytes, as its header says.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ImageLayout {
    pub width: usize,
    pub height: usize,
    /// Bytes from one row to the next, at least `3 * width`.
    pub step: usize,
}

impl ImageLayout {
    /// The layout of the image in `bytes`, if its header is whole, its rows are at least a
    /// row of pixels wide and all of them fit in `bytes`; `None` for anything else (a short or
    /// lying header from a faulty producer).
    pub fn of(bytes: &[u8]) -> Option<Self> {
        let word = |i: usize| -> Option<usize> {
            Some(u32::from_le_bytes(bytes.get(i * 4..i * 4 + 4)?.try_into().ok()?) as usize)
        };
        let (width, height, step) = (word(0)?, word(1)?, word(2)?);
        let end = step.checked_mul(height)?.checked_add(IMAGE_HEADER)?;
        (step >= width.checked_mul(3)? && end <= bytes.len()).then_some(Self {
            width,
            height,
            step,
        })
    }
}

#[cfg(test)]
mod image_tests {
    use super::*;

    fn image(width: u32, height: u32, step: u32, pixels: usize) -> Vec<u8> {
        let mut b: Vec<u8> = [width, height, step]
            .iter()
            .flat_map(|w| w.to_le_bytes())
            .collect();
        b.resize(IMAGE_HEADER + pixels, 0);
        b
    }

    #[test]
    fn an_image_s_layout_is_read_from_its_header_when_its_rows_fit() {
        let layout = ImageLayout::of(&image(320, 240, 960, 960 * 240)).unwrap();
        assert_eq!((layout.width, layout.height, layout.step), (320, 240, 960));
        // Padded rows.
        assert_eq!(ImageLayout::of(&image(2, 2, 8, 16)).unwrap().step, 8);
    }

    #[test]
    fn a_short_or_lying_header_gives_no_layout() {
        assert_eq!(
            ImageLayout::of(&[1, 0, 0, 0, 1, 0]),
            None,
            "header cut short"
        );
        assert_eq!(
            ImageLayout::of(&image(320, 240, 960, 960 * 239)),
            None,
            "rows missing"
        );
        assert_eq!(
            ImageLayout::of(&image(320, 240, 959, 960 * 240)),
            None,
            "rows too narrow"
        );
        assert_eq!(
            ImageLayout::of(&image(u32::MAX, 1, u32::MAX, 16)),
            None,
            "overflow"
        );
        assert_eq!(
            ImageLayout::of(&image(1, u32::MAX, u32::MAX, 16)),
            None,
            "overflow"
        );
    }
}

/// Telemetry for the operator, as JSON.
#[derive(Debug, Clone, Copy)]
pub struct Telemetry;

impl BytesMessage for Telemetry {
    const SCHEMA_NAME: &'static str = "beetle_msgs/Telemetry";
    const ENCODING: &'static str = "application/json";
    const SCHEMA: &'static str = "{\"type\":\"object\"}";
}
