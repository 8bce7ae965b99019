//! Beetle-One, simulated: a planetary test rover with wheelchair-style differential drive,
//! driven by joystick or by computer.
//!
//! - [`devices`]: the physical layer's devices, each a module: wheel motors, the world (physics),
//!   wheel encoders, IMU, battery, camera, range sensor. They share one [`world::Terrain`] and
//!   read the rover's true pose from the world module, so what the camera sees and what the
//!   encoders count agree with the commanded motion.
//! - [`control`]: the software: joystick, mixer, odometry, autopilot, obstacle stop, watchdog,
//!   telemetry.
//! - [`kinematics`], [`world`]: the models, usable without a DNM.
//!
//! `configs/beetle.toml` wires them on four DNMs (`rover`, `drive`, `vision`, `ground`) with the
//! tasks `teleop` and `auto`.
//!
//! ```
//! let registry = dnm_rover::register(dnm_module::Registry::new());
//! assert!(registry.find("watchdog").is_some());
//! ```

pub mod control;
pub mod devices;
pub mod kinematics;
pub mod msgs;
pub mod world;

use dnm_module::Registry;

/// Adds every Beetle-One kind to `registry`.
pub fn register(registry: Registry) -> Registry {
    registry
        .register::<devices::WheelMotor>()
        .register::<devices::RoverWorld>()
        .register::<devices::WheelEncoders>()
        .register::<devices::ImuSensor>()
        .register::<devices::Battery>()
        .register::<devices::Camera>()
        .register::<devices::RangeSensor>()
        .register::<control::Joystick>()
        .register::<control::Mixer>()
        .register::<control::Odometer>()
        .register::<control::Autopilot>()
        .register::<control::ObstacleStop>()
        .register::<control::Watchdog>()
        .register::<control::TelemetryOut>()
}
