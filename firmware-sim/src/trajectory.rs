//! Smooth trajectories of the IMU frame with exact derivatives.
//!
//! Each trajectory is a closed-form function of time written over [`Jet`]s, so the position,
//! velocity and acceleration and the orientation, body angular rate and body angular
//! acceleration it returns are exact to rounding. Orientation is built from yaw, pitch and roll
//! (R = Rz(yaw) Ry(pitch) Rx(roll), z up); the body rates follow from the Euler-angle rates.
//!
//! Frames: the world is gravity-aligned with z up; the IMU frame is x forward, y left, z up.
//! The specific force an accelerometer measures is `R^T (a - g)` with g = (0, 0, -[`GRAVITY`]).
//!
//! Every trajectory starts with [`REST_S`] seconds exactly at rest (constant pose, zero
//! velocity and rate) and then blends into motion with quintic smoothsteps, so acceleration is
//! continuous everywhere.

use nalgebra::{Isometry3, Rotation3, Translation3, UnitQuaternion, Vector3};

use crate::jet::{Jet, smoothstep, smoothstep_integral};
use crate::terrain::Terrain;

/// Standard gravity, m/s^2.
pub const GRAVITY: f64 = 9.80665;
/// Every trajectory is at rest for this long at its start, seconds.
pub const REST_S: f64 = 2.0;

/// The full kinematic state of a frame at one instant.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Kinematics {
    /// Seconds since the trajectory's start.
    pub t: f64,
    /// Position in the world, metres.
    pub position: Vector3<f64>,
    /// Orientation: maps frame vectors into the world.
    pub rotation: Rotation3<f64>,
    /// World velocity, m/s.
    pub velocity: Vector3<f64>,
    /// World acceleration (kinematic, without gravity), m/s^2.
    pub acceleration: Vector3<f64>,
    /// Angular rate in the frame's own axes (what a gyroscope measures), rad/s.
    pub angular_velocity: Vector3<f64>,
    /// Time derivative of `angular_velocity` (also in the frame's axes), rad/s^2.
    pub angular_acceleration: Vector3<f64>,
}

impl Kinematics {
    /// The pose T_world_frame.
    pub fn pose(&self) -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::from(self.position),
            UnitQuaternion::from_rotation_matrix(&self.rotation),
        )
    }

    /// What an ideal accelerometer in this frame measures: R^T (a - g), m/s^2.
    pub fn specific_force(&self) -> Vector3<f64> {
        self.rotation.inverse() * (self.acceleration + Vector3::new(0.0, 0.0, GRAVITY))
    }

    /// The kinematics of a frame P rigidly attached to this one at `t_this_p` (P's pose in this
    /// frame): lever-arm velocity and acceleration terms included.
    pub fn attached(&self, t_this_p: &Isometry3<f64>) -> Kinematics {
        let r = t_this_p.translation.vector;
        let r_p = t_this_p.rotation.to_rotation_matrix();
        let (w, al) = (self.angular_velocity, self.angular_acceleration);
        Kinematics {
            t: self.t,
            position: self.position + self.rotation * r,
            rotation: self.rotation * r_p,
            velocity: self.velocity + self.rotation * w.cross(&r),
            acceleration: self.acceleration + self.rotation * (al.cross(&r) + w.cross(&w.cross(&r))),
            angular_velocity: r_p.inverse() * w,
            angular_acceleration: r_p.inverse() * al,
        }
    }
}

/// The kind of motion.
// One trajectory exists per scenario and this module is no_std without a heap: no boxing.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Debug, PartialEq)]
pub enum Trajectory {
    /// A car on a looping road through the town, following the ground's height and slope.
    Vehicle {
        /// The ground it drives on.
        terrain: Terrain,
    },
    /// A person walking a loop through the indoor hall holding the sensor, with gait.
    Handheld,
    /// A small robot driving 40 s down the long corridor.
    Corridor,
    /// A drone climbing from a courtyard among buildings into open sky.
    Drone {
        /// Ground height at the take-off point, metres.
        ground_z: f64,
    },
    /// Fast handheld rotation (up to about 180 deg/s) on the spot, in the hall.
    FastRotation,
    /// The vehicle's car on the same road, with a stop: it brakes from [`TRAFFIC_BRAKE_S`],
    /// stands exactly still from [`TRAFFIC_STOP_S`] to [`TRAFFIC_GO_S`] and drives on.
    Traffic {
        /// The ground it drives on.
        terrain: Terrain,
    },
    /// A car on a 3.1 km loop with bends around a wide district at 12.5 m/s on average, one lap and
    /// [`LONG_PAST_START_M`] more, so that it comes back past its start ([`LONG_DURATION_S`]).
    Long {
        /// The ground it drives on.
        terrain: Terrain,
    },
}

/// Vehicle loop: a rounded square of "radius" A with corner sharpness K and an asymmetry B.
const VEH_A: f64 = 80.0;
const VEH_K: f64 = 0.1;
const VEH_B: f64 = 6.0;
const VEH_THETA0: f64 = -1.2;
const VEH_SPEED: f64 = 6.7;
const VEH_RAMP_S: f64 = 5.0;
/// Height of the vehicle's IMU above the road, metres.
pub const VEH_IMU_HEIGHT: f64 = 1.75;
/// The traffic drive: time the car starts braking for its stop, seconds.
pub const TRAFFIC_BRAKE_S: f64 = 15.0;
/// The traffic drive: time the car drives on after its stop, seconds.
pub const TRAFFIC_GO_S: f64 = 29.0;

/// The long drive's loop: the vehicle loop's shape scaled up ([`LONG_A`] instead of 80 m), with
/// bends of [`LONG_W`] metres (7 and 5 per lap across x and y); 3.08 km long, every bend
/// wider than 53 m in radius.
pub const LONG_A: f64 = 470.0;
const LONG_K: f64 = 0.1;
const LONG_B: f64 = 35.0;
/// Amplitude of the long loop's bends, metres.
pub const LONG_W: f64 = 18.0;
const LONG_THETA0: f64 = -1.2;
/// The long drive's path-angle rate times [`LONG_A`], m/s (its speed is 20 m/s at most, 12.5
/// on average; the lateral acceleration stays under 1.3 m/s^2).
const LONG_SPEED: f64 = 12.0;
/// When the long drive is back at its start (one lap), seconds.
pub const LONG_LAP_S: f64 = REST_S + 0.5 * VEH_RAMP_S + core::f64::consts::TAU * LONG_A / LONG_SPEED;
/// How far the long drive goes on past its start, metres (along the path angle, about).
pub const LONG_PAST_START_M: f64 = 135.0;
/// The long drive's length, seconds: one lap and [`LONG_PAST_START_M`].
pub const LONG_DURATION_S: f64 = 262.0;

/// The traffic drive: time the car comes to a standstill (braking takes the ramp time), seconds.
pub const TRAFFIC_STOP_S: f64 = TRAFFIC_BRAKE_S + VEH_RAMP_S;

/// The traffic drive's path angle on the vehicle loop at `t` seconds (see [`road_point`]).
pub fn traffic_theta(t: f64) -> f64 {
    traffic_theta_jet(Jet::c(t)).v
}

/// A point of the vehicle loop (the town's road centre line) at path angle `theta`: (x, y) and
/// the derivative (dx/dtheta, dy/dtheta).
pub fn road_point(theta: f64) -> [f64; 4] {
    let (x, y, dx, dy) = vehicle_path(Jet::c(theta));
    [x.v, y.v, dx.v, dy.v]
}

/// The traffic drive's path angle: three smooth speed ramps (start, brake, go) and, between the
/// standstill and [`TRAFFIC_GO_S`], a constant (so position, velocity and rate are exactly still).
fn traffic_theta_jet(tj: Jet) -> Jet {
    let rate = VEH_SPEED / VEH_A;
    let t = tj.v;
    if (TRAFFIC_STOP_S..=TRAFFIC_GO_S).contains(&t) {
        return Jet::c(VEH_THETA0 + rate * (TRAFFIC_BRAKE_S - REST_S));
    }
    let r = 1.0 / VEH_RAMP_S;
    let ramps = smoothstep_integral((tj - REST_S) * r) - smoothstep_integral((tj - TRAFFIC_BRAKE_S) * r)
        + smoothstep_integral((tj - TRAFFIC_GO_S) * r);
    Jet::c(VEH_THETA0) + ramps * (rate * VEH_RAMP_S)
}

/// The car on the loop at path angle `th`: position and (roll, pitch, yaw) on the ground.
fn vehicle_on_road(terrain: &Terrain, th: Jet) -> ([Jet; 3], [Jet; 3]) {
    car_on_road(terrain, vehicle_path(th))
}

/// A car at a road point (x, y, dx/dtheta, dy/dtheta): position and (roll, pitch, yaw) on the
/// ground.
fn car_on_road(terrain: &Terrain, (x, y, dx, dy): (Jet, Jet, Jet, Jet)) -> ([Jet; 3], [Jet; 3]) {
    let yaw = dy.atan2(dx);
    let (zg, gx, gy) = terrain.height_jet(x, y);
    let (cy, sy) = (yaw.cos(), yaw.sin());
    let slope_fwd = gx * cy + gy * sy;
    let slope_left = gy * cy - gx * sy;
    let pitch = -slope_fwd.atan();
    let roll = slope_left.atan();
    ([x, y, zg + VEH_IMU_HEIGHT], [roll, pitch, yaw])
}

const WALK_SPEED: f64 = 1.25;
/// Height of the handheld sensor above the floor, metres.
pub const HAND_HEIGHT: f64 = 1.35;
const STEP_HZ: f64 = 1.8;

/// Where the drone takes off (x, y), metres.
pub const DRONE_START: [f64; 2] = [18.0, -12.0];
/// Height of the drone's IMU above the ground at rest, metres.
pub const DRONE_REST_HEIGHT: f64 = 0.3;
const DRONE_CLIMB_M: f64 = 70.0;
const DRONE_CLIMB_S: f64 = 30.0;

/// Where the fast-rotation sequence happens (x, y), metres, in the hall.
pub const ROTATION_SPOT: [f64; 2] = [4.0, -3.0];

/// Start of the corridor drive (x), metres; the corridor runs along +x.
pub const CORRIDOR_X0: f64 = 0.0;
/// Height of the corridor robot's IMU above the floor, metres.
pub const CORRIDOR_HEIGHT: f64 = 1.0;
const CORRIDOR_SPEED: f64 = 4.2;

impl Trajectory {
    /// Exact kinematics of the IMU frame at `t` seconds since the start.
    pub fn eval(&self, t: f64) -> Kinematics {
        let (p, e) = self.jets(t);
        from_jets(t, p, e)
    }

    /// Position and (roll, pitch, yaw) as jets of time.
    fn jets(&self, t: f64) -> ([Jet; 3], [Jet; 3]) {
        let tj = Jet::var(t);
        // Onset weight: 0 at rest, rising smoothly to 1 over 2 s.
        let onset = |dur: f64| smoothstep((tj - REST_S) * (1.0 / dur));
        let moving = tj - REST_S;
        match self {
            Trajectory::Vehicle { terrain } => {
                let th = Jet::c(VEH_THETA0)
                    + smoothstep_integral(moving * (1.0 / VEH_RAMP_S)) * (VEH_SPEED / VEH_A * VEH_RAMP_S);
                vehicle_on_road(terrain, th)
            }
            Trajectory::Traffic { terrain } => vehicle_on_road(terrain, traffic_theta_jet(tj)),
            Trajectory::Long { terrain } => {
                let th = Jet::c(LONG_THETA0)
                    + smoothstep_integral(moving * (1.0 / VEH_RAMP_S)) * (LONG_SPEED / LONG_A * VEH_RAMP_S);
                car_on_road(terrain, long_path(th))
            }
            Trajectory::Handheld => {
                let th = Jet::c(-0.4) + smoothstep_integral(moving * (1.0 / 2.5)) * (WALK_SPEED / 12.0 * 2.5);
                let (x, y, dx, dy) = walk_path(th);
                let heading = dy.atan2(dx);
                let w = onset(2.0);
                let ph = tj * (core::f64::consts::TAU * STEP_HZ);
                let half = tj * (core::f64::consts::PI * STEP_HZ);
                // Vertical bob at the step rate, lateral sway at the stride rate.
                let bob = w * ph.cos() * 0.02;
                let sway = w * (half + 0.4).sin() * 0.025;
                let (c, s) = (heading.cos(), heading.sin());
                let px = x - s * sway;
                let py = y + c * sway;
                let pz = bob + HAND_HEIGHT;
                let yaw = heading + w * (half + 0.3).sin() * 0.05;
                let pitch = w * (ph + 0.9).sin() * 0.025 - 0.08;
                let roll = w * (half + 1.7).sin() * 0.035;
                ([px, py, pz], [roll, pitch, yaw])
            }
            Trajectory::Corridor => {
                let w = onset(4.0);
                let x = Jet::c(CORRIDOR_X0)
                    + smoothstep_integral(moving * 0.25) * (CORRIDOR_SPEED * 4.0)
                    + w * (moving * 0.5).sin() * 1.0;
                let y = w * (moving * (core::f64::consts::TAU * 0.05)).sin() * 0.25;
                let z = w * (moving * (core::f64::consts::TAU * 0.7)).sin() * 0.01 + CORRIDOR_HEIGHT;
                let yaw = w * (moving * (core::f64::consts::TAU * 0.05) + 1.2).sin() * 0.05;
                let pitch = w * (moving * (core::f64::consts::TAU * 0.31)).sin() * 0.01;
                let roll = w * (moving * (core::f64::consts::TAU * 0.43) + 0.5).sin() * 0.012;
                ([x, y, z], [roll, pitch, yaw])
            }
            Trajectory::Drone { ground_z } => {
                let climb = smoothstep(moving * (1.0 / DRONE_CLIMB_S));
                let drift = smoothstep(moving * (1.0 / 20.0));
                let w = onset(3.0);
                let x = Jet::c(DRONE_START[0]) + drift * 5.0 + w * (moving * 0.4).sin() * 1.0;
                let y = Jet::c(DRONE_START[1]) - drift * 3.0 + w * (moving * 0.3 + 0.5).sin() * 0.8
                    - w * 0.8 * libm::sin(0.5);
                let z = climb * DRONE_CLIMB_M + (ground_z + DRONE_REST_HEIGHT);
                let yaw =
                    Jet::c(0.6) + smoothstep(moving * (1.0 / 25.0)) * 1.2 + w * (moving * 0.7).sin() * 0.1;
                let roll = w * (moving * (core::f64::consts::TAU * 0.3)).sin() * 0.06;
                let pitch = w * (moving * (core::f64::consts::TAU * 0.23) + 1.0).sin() * 0.05
                    - w * 0.05 * libm::sin(1.0);
                ([x, y, z], [roll, pitch, yaw])
            }
            Trajectory::FastRotation => {
                let w = onset(2.0);
                let tau = core::f64::consts::TAU;
                let x = Jet::c(ROTATION_SPOT[0]) + w * (moving * (tau * 0.13)).sin() * 0.3;
                let y = Jet::c(ROTATION_SPOT[1]) + w * (moving * (tau * 0.21)).sin() * 0.25;
                let z = Jet::c(HAND_HEIGHT) + w * (moving * (tau * 0.3)).sin() * 0.1;
                let yaw = Jet::c(0.3)
                    + w * (moving * (tau * 0.4)).sin() * 1.1
                    + smoothstep_integral(moving * 0.5) * 0.3;
                let pitch = w * (moving * (tau * 0.55)).sin() * 0.25;
                let roll = w * (moving * (tau * 0.7) + 0.8).sin() * 0.2 - w * 0.2 * libm::sin(0.8);
                ([x, y, z], [roll, pitch, yaw])
            }
        }
    }
}

/// The vehicle's loop as a function of the path angle: position and d/dtheta, as jets of time.
fn vehicle_path(th: Jet) -> (Jet, Jet, Jet, Jet) {
    rounded_loop(th, VEH_A, VEH_K, VEH_B)
}

/// A rounded square of "radius" `a`, corner sharpness `k` and asymmetry `b` at path angle `th`:
/// position and d/dtheta.
fn rounded_loop(th: Jet, a: f64, k: f64, b: f64) -> (Jet, Jet, Jet, Jet) {
    let (c1, s1) = (th.cos(), th.sin());
    let th3 = th * 3.0;
    let (c3, s3) = (th3.cos(), th3.sin());
    let th2 = th * 2.0;
    let (c2, s2) = (th2.cos(), th2.sin());
    let x = (c1 - c3 * k) * a + s2 * b;
    let y = (s1 + s3 * k) * a;
    let dx = (-s1 + s3 * (3.0 * k)) * a + c2 * (2.0 * b);
    let dy = (c1 + c3 * (3.0 * k)) * a;
    (x, y, dx, dy)
}

/// The long drive's loop: position and d/dtheta.
fn long_path(th: Jet) -> (Jet, Jet, Jet, Jet) {
    let (x, y, dx, dy) = rounded_loop(th, LONG_A, LONG_K, LONG_B);
    let (tn, tm) = (th * 7.0, th * 5.0);
    (
        x + tn.sin() * LONG_W,
        y + tm.cos() * LONG_W,
        dx + tn.cos() * (7.0 * LONG_W),
        dy - tm.sin() * (5.0 * LONG_W),
    )
}

/// The walking loop in the hall: position and d/dtheta.
fn walk_path(th: Jet) -> (Jet, Jet, Jet, Jet) {
    let (c1, s1) = (th.cos(), th.sin());
    let th2 = th * 2.0;
    let th3 = th * 3.0;
    let x = c1 * 14.0 + th2.sin() * 1.5;
    let y = s1 * 10.0 + th3.cos() * 1.0;
    let dx = -s1 * 14.0 + th2.cos() * 3.0;
    let dy = c1 * 10.0 - th3.sin() * 3.0;
    (x, y, dx, dy)
}

/// Builds the kinematics from jets of position and (roll, pitch, yaw).
fn from_jets(t: f64, p: [Jet; 3], e: [Jet; 3]) -> Kinematics {
    let [roll, pitch, yaw] = e;
    let rotation = Rotation3::from_euler_angles(roll.v, pitch.v, yaw.v);
    // Body rates from ZYX Euler rates; evaluated over first-order jets (angle, rate) so that the
    // derivative of each component is the body angular acceleration.
    let a = |j: Jet| Jet { v: j.v, d1: j.d1, d2: 0.0 };
    let (phi, th, rphi, rth, rpsi) = (a(roll), a(pitch), roll.rate(), pitch.rate(), yaw.rate());
    let (sphi, cphi, sth, cth) = (phi.sin(), phi.cos(), th.sin(), th.cos());
    let wx = rphi - rpsi * sth;
    let wy = rth * cphi + rpsi * cth * sphi;
    let wz = rpsi * cth * cphi - rth * sphi;
    Kinematics {
        t,
        position: Vector3::new(p[0].v, p[1].v, p[2].v),
        rotation,
        velocity: Vector3::new(p[0].d1, p[1].d1, p[2].d1),
        acceleration: Vector3::new(p[0].d2, p[1].d2, p[2].d2),
        angular_velocity: Vector3::new(wx.v, wy.v, wz.v),
        angular_acceleration: Vector3::new(wx.d1, wy.d1, wz.d1),
    }
}

/// The rotation vector (axis times angle) of a rotation, accurate down to tiny angles (unlike
/// `Rotation3::scaled_axis`, which returns zero below a threshold).
pub fn log_so3(r: &Rotation3<f64>) -> Vector3<f64> {
    let q = UnitQuaternion::from_rotation_matrix(r);
    let v = q.imag();
    let n = v.norm();
    if n == 0.0 {
        return Vector3::zeros();
    }
    let angle = 2.0 * libm::atan2(n, q.w);
    v * (angle / n)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn all() -> [Trajectory; 6] {
        [
            Trajectory::Vehicle { terrain: Terrain::town() },
            Trajectory::Handheld,
            Trajectory::Corridor,
            Trajectory::Drone { ground_z: 0.7 },
            Trajectory::FastRotation,
            Trajectory::Long { terrain: Terrain::town() },
        ]
    }

    #[test]
    fn derivatives_match_finite_differences() {
        let h = 1e-4;
        for traj in all() {
            for i in 0..400 {
                let t = 0.1 * i as f64 + 0.013;
                let k = traj.eval(t);
                let (kp, km) = (traj.eval(t + h), traj.eval(t - h));
                let v = (kp.position - km.position) / (2.0 * h);
                let a = (kp.velocity - km.velocity) / (2.0 * h);
                assert!((v - k.velocity).norm() < 1e-6 * (1.0 + k.velocity.norm()), "{traj:?} v at {t}");
                assert!(
                    (a - k.acceleration).norm() < 1e-5 * (1.0 + k.acceleration.norm()),
                    "{traj:?} a at {t}"
                );
                // Body rate: R^T dR/dt = [w]x, from the rotation change over +-h.
                let dr = km.rotation.inverse() * kp.rotation;
                let w = log_so3(&dr) / (2.0 * h);
                assert!(
                    (w - k.angular_velocity).norm() < 1e-6 * (1.0 + k.angular_velocity.norm()),
                    "w at {t}: {w} vs {}",
                    k.angular_velocity
                );
                let al = (kp.angular_velocity - km.angular_velocity) / (2.0 * h);
                assert!(
                    (al - k.angular_acceleration).norm() < 1e-5 * (1.0 + al.norm()),
                    "{traj:?} alpha at {t}"
                );
            }
        }
    }

    #[test]
    fn every_trajectory_rests_for_two_seconds_then_moves() {
        for traj in all() {
            let k0 = traj.eval(0.0);
            for i in 0..=40 {
                let k = traj.eval(REST_S * i as f64 / 40.0);
                assert_eq!(k.position, k0.position, "{traj:?}");
                assert_eq!(k.rotation, k0.rotation, "{traj:?}");
                assert_eq!(k.velocity, Vector3::zeros());
                assert_eq!(k.acceleration, Vector3::zeros());
                assert_eq!(k.angular_velocity, Vector3::zeros());
                assert!((k.specific_force() - k0.rotation.inverse() * Vector3::z() * GRAVITY).norm() < 1e-12);
            }
            let k = traj.eval(REST_S + 3.0);
            assert!(k.velocity.norm() + k.angular_velocity.norm() > 0.05, "{traj:?} does not move");
        }
    }

    #[test]
    fn limits_are_respected() {
        // Speeds and rates over 60 s (longer than any scenario), every 10 ms.
        let mut max = [(0.0f64, 0.0f64); 6];
        for (j, traj) in all().iter().enumerate() {
            for i in 0..6000 {
                let k = traj.eval(0.01 * i as f64);
                max[j].0 = max[j].0.max(k.velocity.norm());
                max[j].1 = max[j].1.max(k.angular_velocity.norm().to_degrees());
            }
        }
        let [veh, hand, corr, drone, rot, _] = max;
        assert!(veh.0 <= 10.0 && veh.0 > 8.0, "vehicle speed {veh:?}");
        assert!(hand.0 < 2.0 && hand.0 > 0.9, "walk speed {hand:?}");
        assert!(corr.0 <= 5.0 && corr.0 > 4.0, "corridor speed {corr:?}");
        assert!(drone.0 < 6.0, "drone speed {drone:?}");
        assert!(rot.1 <= 200.0 && rot.1 > 150.0, "rotation rate {rot:?}");
        assert!(veh.1 > 10.0, "the vehicle turns: {veh:?}");
    }

    #[test]
    fn drone_climbs_into_open_sky_and_corridor_runs_along_x() {
        let d = Trajectory::Drone { ground_z: 0.7 };
        assert!((d.eval(0.0).position.z - 1.0).abs() < 1e-12);
        assert!(d.eval(40.0).position.z > 70.0);
        let c = Trajectory::Corridor;
        let end = c.eval(40.0).position;
        assert!(end.x > 140.0 && end.x < 180.0 && end.y.abs() < 0.3, "{end:?}");
    }

    #[test]
    fn traffic_drive_stands_exactly_still_at_its_stop() {
        let traj = Trajectory::Traffic { terrain: Terrain::town() };
        let k0 = traj.eval(TRAFFIC_STOP_S);
        let mut t = TRAFFIC_STOP_S;
        while t <= TRAFFIC_GO_S {
            let k = traj.eval(t);
            assert_eq!(k.position, k0.position, "{t}");
            assert_eq!(k.rotation, k0.rotation, "{t}");
            assert_eq!(k.velocity, Vector3::zeros(), "{t}");
            assert_eq!(k.acceleration, Vector3::zeros(), "{t}");
            assert_eq!(k.angular_velocity, Vector3::zeros(), "{t}");
            assert_eq!(k.angular_acceleration, Vector3::zeros(), "{t}");
            t += 0.01;
        }
        // It drives before and after, continuously into and out of the stop.
        assert!(traj.eval(10.0).velocity.norm() > 4.0);
        assert!(traj.eval(40.0).velocity.norm() > 4.0);
        let (a, b) = (traj.eval(TRAFFIC_STOP_S - 1e-6), traj.eval(TRAFFIC_GO_S + 1e-6));
        assert!((a.position - k0.position).norm() < 1e-6 && (b.position - k0.position).norm() < 1e-6);
        // Same road as the vehicle drive, same derivatives as its finite differences.
        let h = 1e-4;
        for i in 0..600 {
            let t = 0.1 * i as f64 + 0.013;
            let (k, kp, km) = (traj.eval(t), traj.eval(t + h), traj.eval(t - h));
            let v = (kp.position - km.position) / (2.0 * h);
            assert!((v - k.velocity).norm() < 1e-6 * (1.0 + k.velocity.norm()), "v at {t}");
            let w = log_so3(&(km.rotation.inverse() * kp.rotation)) / (2.0 * h);
            assert!((w - k.angular_velocity).norm() < 1e-6 * (1.0 + k.angular_velocity.norm()), "w at {t}");
            let [x, y, ..] = road_point(traffic_theta(t));
            assert!((x - k.position.x).abs() < 1e-9 && (y - k.position.y).abs() < 1e-9);
        }
    }

    #[test]
    fn long_drive_goes_3_km_and_comes_back_past_its_start() {
        let traj = Trajectory::Long { terrain: Terrain::town() };
        let (mut dist, mut max_speed, mut max_lat, mut max_rate) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
        let dt = 0.05;
        let mut prev = traj.eval(0.0).position;
        let start = prev;
        let mut closest_after_lap = f64::INFINITY;
        let n = (LONG_DURATION_S / dt) as usize;
        for i in 1..=n {
            let t = i as f64 * dt;
            let k = traj.eval(t);
            dist += (k.position - prev).norm();
            prev = k.position;
            max_speed = max_speed.max(k.velocity.norm());
            max_rate = max_rate.max(k.angular_velocity.norm().to_degrees());
            let fwd = k.rotation * Vector3::x();
            max_lat = max_lat.max((k.acceleration - fwd * fwd.dot(&k.acceleration)).xy().norm());
            if t > LONG_LAP_S - 20.0 {
                closest_after_lap = closest_after_lap.min((k.position - start).xy().norm());
            }
        }
        assert!(dist > 3000.0 && dist < 3400.0, "{dist} m");
        assert!(max_speed > 15.0 && max_speed < 20.0, "{max_speed} m/s");
        assert!(max_lat < 2.0, "lateral acceleration {max_lat} m/s^2");
        assert!(max_rate > 10.0 && max_rate < 30.0, "{max_rate} deg/s");
        // It passes within a metre of where it started (the lap closes on the same road).
        assert!(closest_after_lap < 1.0, "{closest_after_lap} m");
        let (x, y, ..) = long_path(Jet::c(LONG_THETA0));
        assert!((x.v - start.x).abs() < 1e-9 && (y.v - start.y).abs() < 1e-9);
    }

    #[test]
    fn attached_frame_matches_its_own_differences() {
        let traj = Trajectory::FastRotation;
        let lever = Isometry3::new(Vector3::new(0.1, -0.05, 0.08), Vector3::new(0.02, -0.03, 0.05));
        let h = 1e-4;
        for t in [2.5, 7.3, 12.9] {
            let k = traj.eval(t).attached(&lever);
            let (kp, km) = (traj.eval(t + h).attached(&lever), traj.eval(t - h).attached(&lever));
            let v = (kp.position - km.position) / (2.0 * h);
            let a = (kp.velocity - km.velocity) / (2.0 * h);
            assert!((v - k.velocity).norm() < 1e-6);
            assert!((a - k.acceleration).norm() < 1e-5 * (1.0 + a.norm()));
            let w = log_so3(&(km.rotation.inverse() * kp.rotation)) / (2.0 * h);
            assert!((w - k.angular_velocity).norm() < 1e-6);
        }
    }
}
