//! The simulated hardware of Beetle-One (the physical layer): each device is its own module, so
//! it can be reached and rewired like any other. The `world` module is the physics: it moves
//! the rover by what its wheel motors do; the sensors read the rover's true pose from it.

use dnm_module::{BytesOutput, Input, Io, Kind, Module, ModuleError, Output, Setup};
use dnm_netlist::KindSpec;
use nalgebra::{Isometry2, Point2, Vector2};

use crate::kinematics::DiffDrive;
use crate::msgs::*;
use crate::world::{CameraModel, Noise, Terrain};

const GRAVITY: f64 = 9.81;

/// Seconds since the previous step, clamped so a stall does not teleport the rover.
fn step_dt(last_ns: &mut u64, now_ns: u64, nominal: f64) -> f64 {
    let dt = if *last_ns == 0 {
        nominal
    } else {
        (now_ns.saturating_sub(*last_ns)) as f64 / 1e9
    };
    *last_ns = now_ns;
    dt.clamp(0.0, 0.1)
}

fn terrain(setup: &Setup<'_>) -> Result<Terrain, ModuleError> {
    let name = setup.param_str("terrain")?;
    Terrain::named(name).ok_or_else(|| ModuleError::Param {
        name: "terrain".into(),
        problem: format!("unknown terrain `{name}`; use `mars-yard` or `flat`"),
    })
}

fn drive(setup: &Setup<'_>) -> Result<DiffDrive, ModuleError> {
    Ok(DiffDrive {
        wheel_radius: setup.param_f64("wheel_radius")?,
        track: setup.param_f64("track")?,
    })
}

fn with_geometry(kind: Kind) -> Kind {
    kind.param_f64(
        "wheel_radius",
        DiffDrive::BEETLE.wheel_radius,
        "wheel radius, m",
    )
    .param_f64(
        "track",
        DiffDrive::BEETLE.track,
        "distance between the wheels, m",
    )
}

/// First-order model of a wheel motor with its controller.
#[derive(Debug, Clone, PartialEq)]
pub struct MotorModel {
    /// Time constant of the speed loop, s.
    pub tau: f64,
    pub max_omega: f64,
    pub current_limit: f64,
    /// Current with the wheel at rest, A.
    pub idle_current: f64,
    /// A per rad/s² of acceleration (inertia).
    pub accel_current: f64,
    /// A per rad/s of speed (rolling resistance).
    pub speed_current: f64,
    pub omega: f64,
}

impl MotorModel {
    pub fn beetle() -> Self {
        Self {
            tau: 0.15,
            max_omega: 10.0,
            current_limit: 8.0,
            idle_current: 0.2,
            accel_current: 0.12,
            speed_current: 0.25,
            omega: 0.0,
        }
    }

    /// Advances by `dt` towards `command`; returns the state reported.
    pub fn step(&mut self, command: f64, dt: f64) -> MotorState {
        let target = command.clamp(-self.max_omega, self.max_omega);
        let mut accel = (target - self.omega) / self.tau;
        let speed_part = self.idle_current + self.speed_current * self.omega.abs();
        let headroom = ((self.current_limit - speed_part) / self.accel_current).max(0.0);
        let limited = accel.abs() > headroom;
        if limited {
            accel = accel.signum() * headroom;
        }
        // Never overshoot the target within one step.
        let next = self.omega + accel * dt;
        self.omega = if (target - self.omega).signum() != (target - next).signum() {
            target
        } else {
            next
        };
        MotorState {
            omega: self.omega,
            command: target,
            current: speed_part + self.accel_current * accel.abs(),
            limited: f64::from(u8::from(limited)),
        }
    }
}

/// A wheel motor and its controller: follows the commanded wheel speed with a first-order
/// response, limited in speed and current.
#[derive(Debug)]
pub struct WheelMotor {
    command: Input<WheelCommand>,
    state: Output<MotorState>,
    model: MotorModel,
    last_ns: u64,
}

impl Module for WheelMotor {
    fn kind() -> KindSpec {
        Kind::new(
            "wheel_motor",
            "simulated wheel motor: first-order speed response, current draw and limits",
        )
        .input::<WheelCommand>("command")
        .output::<MotorState>("state")
        .param_f64("tau", 0.15, "speed time constant, s")
        .param_f64("max_omega", 10.0, "top wheel speed, rad/s")
        .param_f64("current_limit", 8.0, "current limit, A")
        .periodic(100.0)
        .build()
    }

    fn new(setup: &mut Setup<'_>) -> Result<Self, ModuleError> {
        let mut model = MotorModel::beetle();
        model.tau = setup.param_f64("tau")?;
        model.max_omega = setup.param_f64("max_omega")?;
        model.current_limit = setup.param_f64("current_limit")?;
        Ok(Self {
            command: setup.input("command")?,
            state: setup.output("state")?,
            model,
            last_ns: 0,
        })
    }

    fn step(&mut self, io: &mut Io<'_>) -> Result<(), ModuleError> {
        let dt = step_dt(&mut self.last_ns, io.now_ns(), 0.01);
        // A motor controller holds its last command (stopping stale commands is the watchdog's
        // job); with none ever received it stands still.
        let command = io.latest(&self.command).map_or(0.0, |c| c.omega);
        let state = self.model.step(command, dt);
        io.write(&self.state, &state)
    }
}

/// The physics: moves the rover by its wheels over the terrain, stops it at rocks (the wheels
/// then slip), and publishes the ground truth every device senses.
#[derive(Debug)]
pub struct RoverWorld {
    left: Input<MotorState>,
    right: Input<MotorState>,
    state: Output<WorldState>,
    drive: DiffDrive,
    terrain: Terrain,
    world_from_rover: Isometry2<f64>,
    truth: WorldState,
    last_ns: u64,
}

impl Module for RoverWorld {
    fn kind() -> KindSpec {
        with_geometry(
            Kind::new(
                "rover_world",
                "simulated world: rover pose from its wheels, terrain, rocks",
            )
            .input::<MotorState>("left")
            .input::<MotorState>("right")
            .output::<WorldState>("state"),
        )
        .param_string("terrain", "mars-yard", "`mars-yard` or `flat`")
        .param_f64("start_x", 0.0, "start position x, m")
        .param_f64("start_y", 0.0, "start position y, m")
        .param_f64("start_yaw", 0.0, "start heading, rad")
        .periodic(100.0)
        .build()
    }

    fn new(setup: &mut Setup<'_>) -> Result<Self, ModuleError> {
        let world_from_rover = Isometry2::new(
            Vector2::new(setup.param_f64("start_x")?, setup.param_f64("start_y")?),
            setup.param_f64("start_yaw")?,
        );
        Ok(Self {
            left: setup.input("left")?,
            right: setup.input("right")?,
            state: setup.output("state")?,
            drive: drive(setup)?,
            terrain: terrain(setup)?,
            world_from_rover,
            truth: WorldState::default(),
            last_ns: 0,
        })
    }

    fn step(&mut self, io: &mut Io<'_>) -> Result<(), ModuleError> {
        let dt = step_dt(&mut self.last_ns, io.now_ns(), 0.01);
        let wl = io.latest(&self.left).map_or(0.0, |m| m.omega);
        let wr = io.latest(&self.right).map_or(0.0, |m| m.omega);
        self.truth = advance(
            &self.drive,
            &self.terrain,
            &mut self.world_from_rover,
            &self.truth,
            wl,
            wr,
            dt,
        );
        io.write(&self.state, &self.truth)
    }
}

/// One physics step: wheels turn by `wl`, `wr` rad/s for `dt`; the rover follows unless a rock
/// is in the way.
pub fn advance(
    drive: &DiffDrive,
    terrain: &Terrain,
    world_from_rover: &mut Isometry2<f64>,
    prev: &WorldState,
    wl: f64,
    wr: f64,
    dt: f64,
) -> WorldState {
    let (dl, dr) = (wl * drive.wheel_radius * dt, wr * drive.wheel_radius * dt);
    let next = *world_from_rover * drive.arc(dl, dr);
    let mut s = *prev;
    let moved = !terrain.collides(&Point2::from(next.translation.vector));
    if moved {
        *world_from_rover = next;
        s.distance += ((dl + dr) / 2.0).abs();
    } else {
        s.blocked += 1;
    }
    let (linear, angular) = if moved {
        drive.body_velocity(wl, wr)
    } else {
        (0.0, 0.0)
    };
    let p = world_from_rover.translation.vector;
    let (pitch, roll) = terrain.attitude(world_from_rover);
    s.accel = if dt > 0.0 {
        (linear - prev.linear) / dt
    } else {
        0.0
    };
    s.x = p.x;
    s.y = p.y;
    s.z = terrain.height(p.x, p.y);
    s.yaw = world_from_rover.rotation.angle();
    s.pitch = pitch;
    s.roll = roll;
    s.linear = linear;
    s.angular = angular;
    s.wheel_left += wl * dt;
    s.wheel_right += wr * dt;
    s
}

/// Quadrature encoders on both wheels.
#[derive(Debug)]
pub struct WheelEncoders {
    world: Input<WorldState>,
    ticks: Output<EncoderTicks>,
    counts_per_rev: f64,
}

/// Encoder counts of a wheel turned `angle` rad.
pub fn counts(angle: f64, counts_per_rev: f64) -> i64 {
    (angle / std::f64::consts::TAU * counts_per_rev).floor() as i64
}

impl Module for WheelEncoders {
    fn kind() -> KindSpec {
        Kind::new(
            "wheel_encoders",
            "simulated quadrature encoders on both wheels",
        )
        .input::<WorldState>("world")
        .output::<EncoderTicks>("ticks")
        .param_i64("counts_per_rev", 4096, "counts per wheel revolution")
        .periodic(50.0)
        .build()
    }

    fn new(setup: &mut Setup<'_>) -> Result<Self, ModuleError> {
        Ok(Self {
            world: setup.input("world")?,
            ticks: setup.output("ticks")?,
            counts_per_rev: setup.param_i64("counts_per_rev")? as f64,
        })
    }

    fn step(&mut self, io: &mut Io<'_>) -> Result<(), ModuleError> {
        let Some(w) = io.latest(&self.world) else {
            return Ok(());
        };
        let ticks = EncoderTicks {
            left: counts(w.wheel_left, self.counts_per_rev),
            right: counts(w.wheel_right, self.counts_per_rev),
        };
        io.write(&self.ticks, &ticks)
    }
}

/// A 6-axis IMU with white noise and a gyro bias.
#[derive(Debug)]
pub struct ImuSensor {
    world: Input<WorldState>,
    imu: Output<Imu>,
    noise: Noise,
    gyro_noise: f64,
    gyro_bias: f64,
    accel_noise: f64,
}

/// What an ideal IMU measures on a rover in `state`.
pub fn ideal_imu(state: &WorldState) -> Imu {
    Imu {
        gyro: [0.0, 0.0, state.angular],
        accel: [
            state.accel + GRAVITY * state.pitch.sin(),
            -GRAVITY * state.roll.sin() * state.pitch.cos(),
            GRAVITY * state.pitch.cos() * state.roll.cos(),
        ],
    }
}

impl Module for ImuSensor {
    fn kind() -> KindSpec {
        Kind::new(
            "imu",
            "simulated IMU: gyro and accelerometer with noise and gyro bias",
        )
        .input::<WorldState>("world")
        .output::<Imu>("imu")
        .param_f64("gyro_noise", 0.002, "gyro noise, rad/s (1 sigma)")
        .param_f64("gyro_bias", 0.004, "gyro z bias, rad/s")
        .param_f64("accel_noise", 0.04, "accelerometer noise, m/s² (1 sigma)")
        .param_i64("seed", 1, "noise seed")
        .periodic(100.0)
        .build()
    }

    fn new(setup: &mut Setup<'_>) -> Result<Self, ModuleError> {
        Ok(Self {
            world: setup.input("world")?,
            imu: setup.output("imu")?,
            noise: Noise::new(setup.param_i64("seed")? as u64),
            gyro_noise: setup.param_f64("gyro_noise")?,
            gyro_bias: setup.param_f64("gyro_bias")?,
            accel_noise: setup.param_f64("accel_noise")?,
        })
    }

    fn step(&mut self, io: &mut Io<'_>) -> Result<(), ModuleError> {
        let Some(w) = io.latest(&self.world) else {
            return Ok(());
        };
        let mut m = ideal_imu(&w);
        m.gyro[2] += self.gyro_bias;
        for g in &mut m.gyro {
            *g += self.noise.gauss(self.gyro_noise);
        }
        for a in &mut m.accel {
            *a += self.noise.gauss(self.accel_noise);
        }
        io.write(&self.imu, &m)
    }
}

/// Battery pack model: open-circuit voltage falls with charge, internal resistance sags it.
#[derive(Debug, Clone, PartialEq)]
pub struct BatteryModel {
    pub capacity_ah: f64,
    pub charge: f64,
    pub internal_ohm: f64,
    /// Electronics' draw, A.
    pub base_current: f64,
}

impl BatteryModel {
    /// Drains by `current` (motors, A) over `dt` s; returns the pack's state.
    pub fn step(&mut self, motor_current: f64, dt: f64) -> BatteryState {
        let current = self.base_current + motor_current;
        self.charge = (self.charge - current * dt / (self.capacity_ah * 3600.0)).max(0.0);
        let open_circuit = 21.0 + 4.2 * self.charge;
        BatteryState {
            voltage: open_circuit - current * self.internal_ohm,
            current,
            charge: self.charge,
        }
    }
}

/// The battery, fed by what both motors draw.
#[derive(Debug)]
pub struct Battery {
    left: Input<MotorState>,
    right: Input<MotorState>,
    state: Output<BatteryState>,
    model: BatteryModel,
    last_ns: u64,
}

impl Module for Battery {
    fn kind() -> KindSpec {
        Kind::new(
            "battery",
            "simulated 24 V battery pack drained by the motors",
        )
        .input::<MotorState>("left")
        .input::<MotorState>("right")
        .output::<BatteryState>("state")
        .param_f64("capacity_ah", 20.0, "capacity, Ah")
        .param_f64("charge", 0.95, "initial state of charge, 0 to 1")
        .periodic(10.0)
        .build()
    }

    fn new(setup: &mut Setup<'_>) -> Result<Self, ModuleError> {
        Ok(Self {
            left: setup.input("left")?,
            right: setup.input("right")?,
            state: setup.output("state")?,
            model: BatteryModel {
                capacity_ah: setup.param_f64("capacity_ah")?,
                charge: setup.param_f64("charge")?,
                internal_ohm: 0.08,
                base_current: 1.5,
            },
            last_ns: 0,
        })
    }

    fn step(&mut self, io: &mut Io<'_>) -> Result<(), ModuleError> {
        let dt = step_dt(&mut self.last_ns, io.now_ns(), 0.1);
        let motors = io.latest(&self.left).map_or(0.0, |m| m.current)
            + io.latest(&self.right).map_or(0.0, |m| m.current);
        let state = self.model.step(motors, dt);
        io.write(&self.state, &state)
    }
}

/// The camera board's camera: RGB frames of the terrain from the rover's pose.
#[derive(Debug)]
pub struct Camera {
    world: Input<WorldState>,
    image: BytesOutput,
    model: CameraModel,
    terrain: Terrain,
}

impl Module for Camera {
    fn kind() -> KindSpec {
        let m = CameraModel::BEETLE;
        Kind::new(
            "camera",
            "simulated camera: 320x240 RGB frames of the terrain ahead",
        )
        .input::<WorldState>("world")
        .bytes_output::<Image>("image", IMAGE_HEADER + m.frame_bytes())
        .param_f64("fov_deg", 70.0, "horizontal field of view, degrees")
        .param_string("terrain", "mars-yard", "`mars-yard` or `flat`")
        .periodic(10.0)
        .build()
    }

    fn new(setup: &mut Setup<'_>) -> Result<Self, ModuleError> {
        let mut model = CameraModel::BEETLE;
        model.fov = setup.param_f64("fov_deg")?.to_radians();
        Ok(Self {
            world: setup.input("world")?,
            image: setup.bytes_output("image")?,
            model,
            terrain: terrain(setup)?,
        })
    }

    fn step(&mut self, io: &mut Io<'_>) -> Result<(), ModuleError> {
        let Some(w) = io.latest(&self.world) else {
            return Ok(());
        };
        let pose = Isometry2::new(Vector2::new(w.x, w.y), w.yaw);
        let m = self.model;
        let terrain = &self.terrain;
        io.write_bytes(&self.image, IMAGE_HEADER + m.frame_bytes(), |buf| {
            buf[0..4].copy_from_slice(&(m.width as u32).to_le_bytes());
            buf[4..8].copy_from_slice(&(m.height as u32).to_le_bytes());
            buf[8..12].copy_from_slice(&((m.width * 3) as u32).to_le_bytes());
            m.render(terrain, &pose, &mut buf[IMAGE_HEADER..]);
        })
    }
}

/// A forward-looking range sensor (a fan of rays).
#[derive(Debug)]
pub struct RangeSensor {
    world: Input<WorldState>,
    range: Output<Range>,
    terrain: Terrain,
    max: f64,
    fov: f64,
    noise: Noise,
    sigma: f64,
}

/// Nearest rock within `fov` of the heading, measured from the rover's nose.
pub fn sense_range(
    terrain: &Terrain,
    world_from_rover: &Isometry2<f64>,
    fov: f64,
    max: f64,
) -> f64 {
    let nose = world_from_rover * Point2::new(0.3, 0.0);
    (0..9)
        .map(|i| {
            let a = -fov / 2.0 + fov * i as f64 / 8.0;
            let dir = world_from_rover.rotation * Vector2::new(a.cos(), a.sin());
            terrain.ray(&nose, &dir, max).map_or(max, |(d, _)| d)
        })
        .fold(max, f64::min)
}

impl Module for RangeSensor {
    fn kind() -> KindSpec {
        Kind::new(
            "range_sensor",
            "simulated forward range sensor: nearest rock ahead",
        )
        .input::<WorldState>("world")
        .output::<Range>("range")
        .param_f64("max_range", 4.0, "m")
        .param_f64("fov_deg", 40.0, "beam spread, degrees")
        .param_f64("noise", 0.01, "m (1 sigma)")
        .param_string("terrain", "mars-yard", "`mars-yard` or `flat`")
        .param_i64("seed", 2, "noise seed")
        .periodic(20.0)
        .build()
    }

    fn new(setup: &mut Setup<'_>) -> Result<Self, ModuleError> {
        Ok(Self {
            world: setup.input("world")?,
            range: setup.output("range")?,
            terrain: terrain(setup)?,
            max: setup.param_f64("max_range")?,
            fov: setup.param_f64("fov_deg")?.to_radians(),
            noise: Noise::new(setup.param_i64("seed")? as u64),
            sigma: setup.param_f64("noise")?,
        })
    }

    fn step(&mut self, io: &mut Io<'_>) -> Result<(), ModuleError> {
        let Some(w) = io.latest(&self.world) else {
            return Ok(());
        };
        let pose = Isometry2::new(Vector2::new(w.x, w.y), w.yaw);
        let d = sense_range(&self.terrain, &pose, self.fov, self.max);
        let range = if d < self.max {
            (d + self.noise.gauss(self.sigma)).clamp(0.0, self.max)
        } else {
            d
        };
        io.write(
            &self.range,
            &Range {
                range,
                max: self.max,
            },
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn motor_follows_a_step_like_a_first_order_system() {
        let mut m = MotorModel::beetle();
        m.current_limit = 1e9; // no limit: pure first order
        let dt = 0.001;
        let mut t = 0.0;
        while t < m.tau - 1e-9 {
            m.step(5.0, dt);
            t += dt;
        }
        // After one time constant: 63.2 % of the step.
        assert!((m.omega / 5.0 - 0.632).abs() < 0.01, "{}", m.omega);
        for _ in 0..2000 {
            m.step(5.0, dt);
        }
        assert!((m.omega - 5.0).abs() < 1e-4);
        // Commands beyond the top speed are clamped.
        let s = m.step(50.0, dt);
        assert_eq!(s.command, m.max_omega);
    }

    #[test]
    fn current_limit_slows_acceleration_and_reports_it() {
        let mut fast = MotorModel::beetle();
        fast.current_limit = 1e9;
        let mut limited = MotorModel::beetle();
        let s = limited.step(10.0, 0.01);
        fast.step(10.0, 0.01);
        assert_eq!(s.limited, 1.0);
        assert!(s.current <= limited.current_limit + 1e-9);
        assert!(limited.omega < fast.omega);
        // At rest with no command: only the idle current.
        let mut idle = MotorModel::beetle();
        let s = idle.step(0.0, 0.01);
        assert!((s.current - idle.idle_current).abs() < 1e-12 && s.limited == 0.0);
    }

    #[test]
    fn world_moves_by_the_wheels_and_stops_at_rocks() {
        let d = DiffDrive::BEETLE;
        let flat = Terrain::named("flat").unwrap();
        let mut pose = Isometry2::identity();
        let mut s = WorldState::default();
        // 1 m/s straight for 2 s.
        let w = 1.0 / d.wheel_radius;
        for _ in 0..200 {
            s = advance(&d, &flat, &mut pose, &s, w, w, 0.01);
        }
        assert!((s.x - 2.0).abs() < 1e-9 && s.y.abs() < 1e-9 && (s.distance - 2.0).abs() < 1e-9);
        assert!((s.wheel_left - 2.0 / d.wheel_radius).abs() < 1e-9);
        // Towards the rock at (9, 1.5): the rover stops at its edge, the wheels keep turning.
        let yard = Terrain::mars_yard();
        let mut pose = Isometry2::new(Vector2::new(6.0, 1.5), 0.0);
        let mut s = WorldState::default();
        for _ in 0..500 {
            s = advance(&d, &yard, &mut pose, &s, w, w, 0.01);
        }
        assert!(s.blocked > 0);
        assert!(s.x < 9.0 - 0.6 - 0.35 + 1e-9 && s.x > 7.9, "{}", s.x);
        assert!(s.wheel_left > s.distance / d.wheel_radius);
    }

    #[test]
    fn encoders_count_whole_ticks() {
        assert_eq!(counts(std::f64::consts::TAU, 4096.0), 4096);
        assert_eq!(counts(-0.0001, 4096.0), -1);
        assert_eq!(counts(0.0, 4096.0), 0);
    }

    #[test]
    fn imu_sees_gravity_and_turn_rate() {
        let level = ideal_imu(&WorldState {
            angular: 0.5,
            ..WorldState::default()
        });
        assert_eq!(level.gyro, [0.0, 0.0, 0.5]);
        assert!((level.accel[2] - GRAVITY).abs() < 1e-12 && level.accel[0].abs() < 1e-12);
        let uphill = ideal_imu(&WorldState {
            pitch: 0.1,
            ..WorldState::default()
        });
        assert!((uphill.accel[0] - GRAVITY * 0.1f64.sin()).abs() < 1e-12);
    }

    #[test]
    fn battery_drains_and_sags_under_load() {
        let mut b = BatteryModel {
            capacity_ah: 1.0,
            charge: 1.0,
            internal_ohm: 0.1,
            base_current: 0.0,
        };
        let rest = b.step(0.0, 1.0);
        let load = b.step(10.0, 360.0); // 10 A for 0.1 h = 1 Ah
        assert!((rest.voltage - 25.2).abs() < 1e-9);
        assert!(load.charge.abs() < 1e-9);
        assert!((load.voltage - (21.0 - 1.0)).abs() < 1e-9);
    }

    #[test]
    fn range_sensor_sees_the_rock_ahead_only() {
        let yard = Terrain::mars_yard();
        let facing = Isometry2::new(Vector2::new(6.0, 1.5), 0.0);
        let d = sense_range(&yard, &facing, 40f64.to_radians(), 4.0);
        assert!((d - (9.0 - 0.6 - 6.3)).abs() < 1e-6, "{d}");
        let away = Isometry2::new(Vector2::new(6.0, 1.5), std::f64::consts::PI);
        assert_eq!(sense_range(&yard, &away, 40f64.to_radians(), 4.0), 4.0);
    }
}
