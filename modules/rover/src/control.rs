//! Beetle-One's driving and monitoring software: joystick, mixer, odometry, autopilot, obstacle
//! stop, safety watchdog and telemetry.

use dnm_module::{BytesOutput, Input, Io, Kind, Module, ModuleError, Output, Setup};
use dnm_netlist::KindSpec;
use nalgebra::{Isometry2, Vector2};

use crate::kinematics::{DiffDrive, saturate, wrap};
use crate::msgs::*;

fn bad(name: &str, problem: impl Into<String>) -> ModuleError {
    ModuleError::Param {
        name: name.into(),
        problem: problem.into(),
    }
}

/// One segment of a joystick script: hold (linear, angular) for `seconds`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Segment {
    pub seconds: f64,
    pub twist: Twist,
}

/// Why [`parse_script`] failed: a segment that is not `SECONDS:LINEAR,ANGULAR`.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ScriptError {
    /// The segment lacks the `:` or the `,`.
    #[error("segment `{segment}` is not `SECONDS:LINEAR,ANGULAR` (e.g. `4:0.5,0`)")]
    Shape { segment: String },
    /// A number of the segment does not parse.
    #[error("segment `{segment}` is not `SECONDS:LINEAR,ANGULAR` (e.g. `4:0.5,0`)")]
    Number {
        segment: String,
        #[source]
        source: std::num::ParseFloatError,
    },
}

/// Parses `"SECONDS:LINEAR,ANGULAR; ..."`, e.g. `"4:0.5,0; 3:0.4,0.3"`.
pub fn parse_script(text: &str) -> Result<Vec<Segment>, ScriptError> {
    text.split(';')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|seg| {
            let shape = || ScriptError::Shape {
                segment: seg.to_string(),
            };
            let (t, v) = seg.split_once(':').ok_or_else(shape)?;
            let (l, a) = v.split_once(',').ok_or_else(shape)?;
            let num = |s: &str| {
                s.trim()
                    .parse::<f64>()
                    .map_err(|source| ScriptError::Number {
                        segment: seg.to_string(),
                        source,
                    })
            };
            Ok(Segment {
                seconds: num(t)?,
                twist: Twist {
                    linear: num(l)?,
                    angular: num(a)?,
                },
            })
        })
        .collect()
}

/// The twist a script commands `t` seconds after it started (zero after its end, unless it
/// loops).
pub fn script_at(script: &[Segment], t: f64, looping: bool) -> Twist {
    let total: f64 = script.iter().map(|s| s.seconds).sum();
    if script.is_empty() || total <= 0.0 {
        return Twist::default();
    }
    let mut t = if looping { t % total } else { t };
    for s in script {
        if t < s.seconds {
            return s.twist;
        }
        t -= s.seconds;
    }
    Twist::default()
}

/// The operator's joystick. Plays a script (the default, for headless runs); the sticks of a
/// real joystick are not read yet.
#[derive(Debug)]
pub struct Joystick {
    twist: Output<Twist>,
    script: Vec<Segment>,
    looping: bool,
    start_ns: u64,
}

impl Module for Joystick {
    fn kind() -> KindSpec {
        Kind::new("joystick", "operator joystick: plays a scripted drive")
            .output::<Twist>("twist")
            .param_string(
                "script",
                "4:0.5,0; 4:0.4,0.3; 4:0.5,0; 4:0.4,-0.3",
                "`SECONDS:LINEAR,ANGULAR; ...`",
            )
            .param_bool("loop", true, "start over at the end")
            .periodic(20.0)
            .build()
    }

    fn new(setup: &mut Setup<'_>) -> Result<Self, ModuleError> {
        Ok(Self {
            twist: setup.output("twist")?,
            script: parse_script(setup.param_str("script")?)
                .map_err(|e| bad("script", e.to_string()))?,
            looping: setup.param_bool("loop")?,
            start_ns: 0,
        })
    }

    fn step(&mut self, io: &mut Io<'_>) -> Result<(), ModuleError> {
        let now = io.now_ns();
        if self.start_ns == 0 {
            self.start_ns = now;
        }
        let t = (now - self.start_ns) as f64 / 1e9;
        let twist = script_at(&self.script, t, self.looping);
        io.write(&self.twist, &twist)
    }
}

/// Twist to wheel speeds, saturated so the path's curvature is kept.
#[derive(Debug)]
pub struct Mixer {
    twist: Input<Twist>,
    left: Output<WheelCommand>,
    right: Output<WheelCommand>,
    drive: DiffDrive,
    max_omega: f64,
}

impl Module for Mixer {
    fn kind() -> KindSpec {
        Kind::new(
            "mixer",
            "differential-drive mixer: twist to left/right wheel speeds",
        )
        .input::<Twist>("twist")
        .output::<WheelCommand>("left")
        .output::<WheelCommand>("right")
        .param_f64("wheel_radius", DiffDrive::BEETLE.wheel_radius, "m")
        .param_f64("track", DiffDrive::BEETLE.track, "m")
        .param_f64("max_omega", 10.0, "top wheel speed, rad/s")
        .on_input()
        .build()
    }

    fn new(setup: &mut Setup<'_>) -> Result<Self, ModuleError> {
        Ok(Self {
            twist: setup.input("twist")?,
            left: setup.output("left")?,
            right: setup.output("right")?,
            drive: DiffDrive {
                wheel_radius: setup.param_f64("wheel_radius")?,
                track: setup.param_f64("track")?,
            },
            max_omega: setup.param_f64("max_omega")?,
        })
    }

    fn step(&mut self, io: &mut Io<'_>) -> Result<(), ModuleError> {
        let Some(t) = io.read(&self.twist) else {
            return Ok(());
        };
        let (l, r) = self.drive.wheel_speeds(t.linear, t.angular);
        let (l, r) = saturate(l, r, self.max_omega);
        io.write(&self.left, &WheelCommand { omega: l })?;
        io.write(&self.right, &WheelCommand { omega: r })
    }
}

/// Dead reckoning from encoder counts.
#[derive(Debug, Clone)]
pub struct DeadReckoning {
    pub drive: DiffDrive,
    pub counts_per_rev: f64,
    pub world_from_rover: Isometry2<f64>,
    last: Option<EncoderTicks>,
    pub distance: f64,
}

impl DeadReckoning {
    pub fn new(drive: DiffDrive, counts_per_rev: f64) -> Self {
        Self {
            drive,
            counts_per_rev,
            world_from_rover: Isometry2::identity(),
            last: None,
            distance: 0.0,
        }
    }

    /// Takes new counts; returns the ground each wheel rolled since the last ones (m).
    pub fn update(&mut self, ticks: EncoderTicks) -> (f64, f64) {
        let Some(last) = self.last.replace(ticks) else {
            return (0.0, 0.0);
        };
        let per_count = std::f64::consts::TAU * self.drive.wheel_radius / self.counts_per_rev;
        let dl = (ticks.left - last.left) as f64 * per_count;
        let dr = (ticks.right - last.right) as f64 * per_count;
        self.world_from_rover *= self.drive.arc(dl, dr);
        self.distance += ((dl + dr) / 2.0).abs();
        (dl, dr)
    }
}

/// Wheel odometry: pose and velocity from encoder counts.
#[derive(Debug)]
pub struct Odometer {
    ticks: Input<EncoderTicks>,
    odom: Output<Odometry>,
    dr: DeadReckoning,
    last_ns: u64,
}

impl Module for Odometer {
    fn kind() -> KindSpec {
        Kind::new(
            "odometry",
            "wheel odometry: pose and velocity from encoder counts",
        )
        .input::<EncoderTicks>("ticks")
        .output::<Odometry>("odom")
        .param_f64("wheel_radius", DiffDrive::BEETLE.wheel_radius, "m")
        .param_f64("track", DiffDrive::BEETLE.track, "m")
        .param_i64(
            "counts_per_rev",
            4096,
            "encoder counts per wheel revolution",
        )
        .param_f64("start_x", 0.0, "start position x, m")
        .param_f64("start_y", 0.0, "start position y, m")
        .param_f64("start_yaw", 0.0, "start heading, rad")
        .on_input()
        .build()
    }

    fn new(setup: &mut Setup<'_>) -> Result<Self, ModuleError> {
        let mut dr = DeadReckoning::new(
            DiffDrive {
                wheel_radius: setup.param_f64("wheel_radius")?,
                track: setup.param_f64("track")?,
            },
            setup.param_i64("counts_per_rev")? as f64,
        );
        dr.world_from_rover = Isometry2::new(
            Vector2::new(setup.param_f64("start_x")?, setup.param_f64("start_y")?),
            setup.param_f64("start_yaw")?,
        );
        Ok(Self {
            ticks: setup.input("ticks")?,
            odom: setup.output("odom")?,
            dr,
            last_ns: 0,
        })
    }

    fn step(&mut self, io: &mut Io<'_>) -> Result<(), ModuleError> {
        let Some(ticks) = io.read(&self.ticks) else {
            return Ok(());
        };
        let now = io.header(&self.ticks).map_or(io.now_ns(), |h| h.stamp_ns);
        let dt = if self.last_ns == 0 {
            0.0
        } else {
            now.saturating_sub(self.last_ns) as f64 / 1e9
        };
        self.last_ns = now;
        let (dl, dr) = self.dr.update(ticks);
        let (linear, angular) = if dt > 0.0 {
            ((dl + dr) / 2.0 / dt, (dr - dl) / self.dr.drive.track / dt)
        } else {
            (0.0, 0.0)
        };
        let p = self.dr.world_from_rover.translation.vector;
        io.write(
            &self.odom,
            &Odometry {
                x: p.x,
                y: p.y,
                yaw: self.dr.world_from_rover.rotation.angle(),
                linear,
                angular,
                distance: self.dr.distance,
            },
        )
    }
}

/// Why [`parse_waypoints`] failed: a waypoint that is not `X,Y`.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum WaypointsError {
    /// The waypoint lacks the `,`.
    #[error("waypoint `{waypoint}` is not `X,Y` (metres, e.g. `4,2`)")]
    Shape { waypoint: String },
    /// A coordinate of the waypoint does not parse.
    #[error("waypoint `{waypoint}` is not `X,Y` (metres, e.g. `4,2`)")]
    Number {
        waypoint: String,
        #[source]
        source: std::num::ParseFloatError,
    },
}

/// Parses `"X,Y; X,Y; ..."`.
pub fn parse_waypoints(text: &str) -> Result<Vec<(f64, f64)>, WaypointsError> {
    text.split(';')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|wp| {
            let (x, y) = wp.split_once(',').ok_or_else(|| WaypointsError::Shape {
                waypoint: wp.to_string(),
            })?;
            let num = |s: &str| {
                s.trim()
                    .parse::<f64>()
                    .map_err(|source| WaypointsError::Number {
                        waypoint: wp.to_string(),
                        source,
                    })
            };
            Ok((num(x)?, num(y)?))
        })
        .collect()
}

/// Steering towards a waypoint: (linear, angular) for a rover at `odom`.
pub fn steer(odom: &Odometry, target: (f64, f64), max_speed: f64, max_turn: f64) -> Twist {
    let (dx, dy) = (target.0 - odom.x, target.1 - odom.y);
    let distance = dx.hypot(dy);
    let error = wrap(dy.atan2(dx) - odom.yaw);
    let angular = (2.0 * error).clamp(-max_turn, max_turn);
    // Turn on the spot when facing away; slow down on the last metre.
    let linear = max_speed * error.cos().max(0.0).powi(2) * distance.clamp(0.3, 1.0);
    Twist { linear, angular }
}

/// Computer control: drives through its waypoints using odometry.
#[derive(Debug)]
pub struct Autopilot {
    odom: Input<Odometry>,
    twist: Output<Twist>,
    progress: Output<Progress>,
    waypoints: Vec<(f64, f64)>,
    next: usize,
    tolerance: f64,
    max_speed: f64,
    max_turn: f64,
}

impl Module for Autopilot {
    fn kind() -> KindSpec {
        Kind::new(
            "autopilot",
            "waypoint autopilot: drives to each waypoint in turn by odometry",
        )
        .input::<Odometry>("odom")
        .output::<Twist>("twist")
        .output::<Progress>("progress")
        .param_string("waypoints", "4,0; 4,3; 0,3", "`X,Y; X,Y; ...` in metres")
        .param_f64("tolerance", 0.3, "reached within this distance, m")
        .param_f64("max_speed", 0.6, "m/s")
        .param_f64("max_turn", 0.8, "rad/s")
        .periodic(20.0)
        .build()
    }

    fn new(setup: &mut Setup<'_>) -> Result<Self, ModuleError> {
        Ok(Self {
            odom: setup.input("odom")?,
            twist: setup.output("twist")?,
            progress: setup.output("progress")?,
            waypoints: parse_waypoints(setup.param_str("waypoints")?)
                .map_err(|e| bad("waypoints", e.to_string()))?,
            next: 0,
            tolerance: setup.param_f64("tolerance")?,
            max_speed: setup.param_f64("max_speed")?,
            max_turn: setup.param_f64("max_turn")?,
        })
    }

    fn step(&mut self, io: &mut Io<'_>) -> Result<(), ModuleError> {
        // Without odometry (its input is linked only while it drives) it holds still.
        let Some(odom) = io.latest(&self.odom) else {
            return Ok(());
        };
        while let Some(&wp) = self.waypoints.get(self.next) {
            if (wp.0 - odom.x).hypot(wp.1 - odom.y) > self.tolerance {
                break;
            }
            self.next += 1;
        }
        let (twist, remaining) = match self.waypoints.get(self.next) {
            Some(&wp) => (
                steer(&odom, wp, self.max_speed, self.max_turn),
                (wp.0 - odom.x).hypot(wp.1 - odom.y),
            ),
            None => (Twist::default(), 0.0),
        };
        io.write(&self.twist, &twist)?;
        io.write(
            &self.progress,
            &Progress {
                reached: self.next as u64,
                total: self.waypoints.len() as u64,
                remaining,
            },
        )
    }
}

/// Stops forward motion when the range sensor sees a rock close ahead; turning stays allowed.
#[derive(Debug)]
pub struct ObstacleStop {
    twist_in: Input<Twist>,
    range: Input<Range>,
    twist: Output<Twist>,
    stop_distance: f64,
}

/// The command let through when the nearest rock ahead is `range` m away.
pub fn guard(t: Twist, range: Option<f64>, stop_distance: f64) -> Twist {
    match range {
        Some(r) if r < stop_distance && t.linear > 0.0 => Twist {
            linear: 0.0,
            angular: t.angular,
        },
        _ => t,
    }
}

impl Module for ObstacleStop {
    fn kind() -> KindSpec {
        Kind::new(
            "obstacle_stop",
            "blocks forward motion when a rock is close ahead",
        )
        .input::<Twist>("twist_in")
        .input::<Range>("range")
        .output::<Twist>("twist")
        .param_f64("stop_distance", 0.8, "m")
        .on_input()
        .build()
    }

    fn new(setup: &mut Setup<'_>) -> Result<Self, ModuleError> {
        Ok(Self {
            twist_in: setup.input("twist_in")?,
            range: setup.input("range")?,
            twist: setup.output("twist")?,
            stop_distance: setup.param_f64("stop_distance")?,
        })
    }

    fn step(&mut self, io: &mut Io<'_>) -> Result<(), ModuleError> {
        // Only a new command goes on: range readings alone must not keep a stale command alive.
        let Some(t) = io.read(&self.twist_in) else {
            return Ok(());
        };
        let range = io.latest(&self.range).map(|r| r.range);
        io.write(&self.twist, &guard(t, range, self.stop_distance))
    }
}

/// Stops the motors when commands go stale (the operator's link or the commanding module died).
#[derive(Debug)]
pub struct Watchdog {
    twist_in: Input<Twist>,
    twist: Output<Twist>,
    state_out: Output<WatchdogState>,
    state: WatchdogState,
}

impl Module for Watchdog {
    fn kind() -> KindSpec {
        Kind::new(
            "watchdog",
            "safety watchdog: commands a stop when commands go stale",
        )
        .input::<Twist>("twist_in")
        .output::<Twist>("twist")
        .output::<WatchdogState>("state")
        .param_f64(
            "timeout",
            0.5,
            "stale after this many seconds without a command",
        )
        .periodic(50.0)
        .build()
    }

    fn new(setup: &mut Setup<'_>) -> Result<Self, ModuleError> {
        let timeout = setup.param_f64("timeout")?;
        if timeout.is_nan() || timeout <= 0.0 {
            return Err(bad("timeout", "must be more than 0 s"));
        }
        Ok(Self {
            twist_in: setup.input("twist_in")?,
            twist: setup.output("twist")?,
            state_out: setup.output("state")?,
            state: WatchdogState {
                timeout_ns: (timeout * 1e9) as u64,
                ..WatchdogState::default()
            },
        })
    }

    fn step(&mut self, io: &mut Io<'_>) -> Result<(), ModuleError> {
        let now = io.now_ns();
        if io.read(&self.twist_in).is_some() {
            // A command is as old as the time it was sent, not the time it arrived: one that sat
            // in a queue (a radio fade, a source switched back to) is already stale.
            let sent = io
                .header(&self.twist_in)
                .map_or(now, |h| h.stamp_ns.min(now));
            self.state.last_command_ns = self.state.last_command_ns.max(sent);
        }
        let fresh = self.state.last_command_ns != 0
            && now.saturating_sub(self.state.last_command_ns) <= self.state.timeout_ns;
        let command = match io.latest(&self.twist_in) {
            Some(t) if fresh => {
                self.state.tripped = 0;
                t
            }
            _ => {
                if self.state.tripped == 0 && self.state.last_command_ns != 0 {
                    self.state.trips += 1;
                    self.state.tripped_at_ns = now;
                    tracing::warn!("commands stale: stopping the motors");
                }
                self.state.tripped = u64::from(self.state.last_command_ns != 0);
                Twist::default()
            }
        };
        io.write(&self.twist, &command)?;
        io.write(&self.state_out, &self.state)
    }
}

/// Telemetry for the operator: pose, speed, battery, range, as JSON.
#[derive(Debug)]
pub struct TelemetryOut {
    odom: Input<Odometry>,
    battery: Input<BatteryState>,
    range: Input<Range>,
    out: BytesOutput,
}

impl Module for TelemetryOut {
    fn kind() -> KindSpec {
        Kind::new(
            "telemetry",
            "operator telemetry: pose, speed, battery and range as JSON",
        )
        .input::<Odometry>("odom")
        .input::<BatteryState>("battery")
        .input::<Range>("range")
        .bytes_output::<Telemetry>("json", 1024)
        .periodic(2.0)
        .build()
    }

    fn new(setup: &mut Setup<'_>) -> Result<Self, ModuleError> {
        Ok(Self {
            odom: setup.input("odom")?,
            battery: setup.input("battery")?,
            range: setup.input("range")?,
            out: setup.bytes_output("json")?,
        })
    }

    fn step(&mut self, io: &mut Io<'_>) -> Result<(), ModuleError> {
        let odom = io.latest(&self.odom);
        let battery = io.latest(&self.battery);
        let range = io.latest(&self.range);
        let json = serde_json::json!({
            "x": odom.map(|o| o.x),
            "y": odom.map(|o| o.y),
            "yaw_deg": odom.map(|o| o.yaw.to_degrees()),
            "speed": odom.map(|o| o.linear),
            "distance": odom.map(|o| o.distance),
            "battery_v": battery.map(|b| b.voltage),
            "battery_charge": battery.map(|b| b.charge),
            "range": range.map(|r| r.range),
        })
        .to_string();
        let bytes = json.as_bytes();
        io.write_bytes(&self.out, bytes.len(), |buf| buf.copy_from_slice(bytes))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scripts_parse_and_play() {
        let s = parse_script("2:0.5,0; 1:0,0.4").unwrap();
        assert_eq!(s.len(), 2);
        assert_eq!(script_at(&s, 1.0, false).linear, 0.5);
        assert_eq!(script_at(&s, 2.5, false).angular, 0.4);
        assert_eq!(script_at(&s, 3.5, false), Twist::default());
        assert_eq!(script_at(&s, 3.5, true).linear, 0.5);
        assert!(
            parse_script("2:fast")
                .unwrap_err()
                .to_string()
                .contains("SECONDS:LINEAR,ANGULAR")
        );
        assert!(
            parse_waypoints("1,2; x,3")
                .unwrap_err()
                .to_string()
                .contains("`x,3`")
        );
        assert_eq!(
            parse_waypoints("1,2;3,4").unwrap(),
            [(1.0, 2.0), (3.0, 4.0)]
        );
    }

    #[test]
    fn parse_errors_name_the_bad_part_and_keep_the_number_error() {
        use std::error::Error;
        let shape = parse_script("1:0,0; 2").unwrap_err();
        assert_eq!(
            shape,
            ScriptError::Shape {
                segment: "2".into()
            }
        );
        assert_eq!(
            shape.to_string(),
            "segment `2` is not `SECONDS:LINEAR,ANGULAR` (e.g. `4:0.5,0`)"
        );
        assert!(shape.source().is_none());
        let number = parse_script("1:0,x").unwrap_err();
        assert!(matches!(&number, ScriptError::Number { segment, .. } if segment == "1:0,x"));
        assert_eq!(
            number.to_string(),
            "segment `1:0,x` is not `SECONDS:LINEAR,ANGULAR` (e.g. `4:0.5,0`)"
        );
        assert!(number.source().is_some());

        let shape = parse_waypoints("1,2; 3").unwrap_err();
        assert_eq!(
            shape.to_string(),
            "waypoint `3` is not `X,Y` (metres, e.g. `4,2`)"
        );
        assert!(shape.source().is_none());
        let number = parse_waypoints("1,y").unwrap_err();
        assert!(matches!(&number, WaypointsError::Number { waypoint, .. } if waypoint == "1,y"));
        assert!(number.source().is_some());
        // A module given a bad parameter reports the same text.
        let err = bad("waypoints", number.to_string());
        assert_eq!(
            err.to_string(),
            "parameter `waypoints`: waypoint `1,y` is not `X,Y` (metres, e.g. `4,2`)"
        );
    }

    #[test]
    fn odometry_recovers_a_driven_arc() {
        // Wheels turn as for a 2 m radius left arc; odometry from quantised counts follows it.
        let d = DiffDrive::BEETLE;
        let mut dr = DeadReckoning::new(d, 4096.0);
        let (wl, wr) = d.wheel_speeds(0.5, 0.25);
        let (mut al, mut ar) = (0.0f64, 0.0f64);
        let counts = |a: f64| (a / std::f64::consts::TAU * 4096.0).floor() as i64;
        dr.update(EncoderTicks { left: 0, right: 0 });
        for _ in 0..(2.0 * std::f64::consts::PI / 0.25 * 50.0) as usize {
            al += wl * 0.02;
            ar += wr * 0.02;
            dr.update(EncoderTicks {
                left: counts(al),
                right: counts(ar),
            });
        }
        // A full circle returns (nearly) to the start.
        let p = dr.world_from_rover.translation.vector;
        assert!(p.norm() < 0.01, "{p}");
        assert!((dr.distance - 2.0 * std::f64::consts::PI * 2.0).abs() < 0.01);
    }

    #[test]
    fn steering_turns_towards_the_waypoint_and_guard_blocks_forward_only() {
        let at = Odometry::default();
        let left = steer(&at, (0.0, 5.0), 0.6, 0.8);
        assert!(left.angular > 0.0 && left.linear.abs() < 1e-9);
        let ahead = steer(&at, (5.0, 0.0), 0.6, 0.8);
        assert!((ahead.linear - 0.6).abs() < 1e-9 && ahead.angular.abs() < 1e-9);
        let fwd = Twist {
            linear: 0.5,
            angular: 0.2,
        };
        assert_eq!(guard(fwd, Some(0.5), 0.8).linear, 0.0);
        assert_eq!(guard(fwd, Some(0.5), 0.8).angular, 0.2);
        assert_eq!(guard(fwd, Some(2.0), 0.8), fwd);
        let back = Twist {
            linear: -0.3,
            angular: 0.0,
        };
        assert_eq!(guard(back, Some(0.1), 0.8), back);
    }
}
