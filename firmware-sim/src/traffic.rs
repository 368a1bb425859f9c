//! The traffic scenario's script: the vehicle's car drives the town's road with a stop at a
//! junction ([`crate::trajectory::Trajectory::Traffic`]) among moving actors.
//!
//! Road frame: arc length `s` along the road's centre line (the ego car drives it) and a lateral
//! offset `l` (positive to the left). The other lane's centre is [`LANE_M`] to the left; the
//! sidewalks' centres are [`SIDEWALK_M`] either side. The junction's cross street crosses the
//! road [`JUNCTION_AHEAD_M`] ahead of where the ego car stops, at right angles.
//!
//! | id | actor | what it does |
//! |---|---|---|
//! | 0 | truck | drives 14 m (centre to centre) ahead of the ego car for 8 s, then pulls away |
//! | 1, 2 | cars | oncoming in the other lane, meeting the ego car at 3.5 s and 6.5 s |
//! | 3 | car | overtakes the ego car in the other lane (7 m/s faster), passing it at ~16.7 s |
//! | 4, 5, 6 | cars | cross traffic on the cross street while the ego car waits (20-29 s) |
//! | 7 | bus | in the other lane, 1.5 m/s faster than the ego car: alongside it from 45.5 s to 56.5 s |
//! | 8, 9 | pedestrians | walking along the sidewalks |
//! | 10, 11 | pedestrians | crossing the road 7 m ahead of and 8 m behind the waiting ego car |
//! | 12 | pedestrian | walking along the cross street's sidewalk to the corner, then standing |
//!
//! The traffic world is the town of the same seed without what stands on the cross street
//! (within [`CROSS_CLEAR_M`] of its centre line) or in an actor's way (a parked car in the other
//! lane, a pole where a pedestrian waits); kerbs stay.

use crate::actors::{Actor, ActorKind, Actors};
use crate::raycast::{Prim, Shape};
use crate::terrain::Terrain;
use crate::trajectory::{TRAFFIC_STOP_S, road_point, traffic_theta};
use crate::world::{World, clearance, footprints_overlap};

/// Lateral offset of the other lane's cars from the road's centre line, metres (left).
pub const LANE_M: f64 = 2.8;
/// Lateral offset of the bus in the other lane, metres (it is wider; it overhangs the kerb a
/// little, as a bus in a narrow street does).
pub const BUS_LANE_M: f64 = 3.0;
/// Lateral offset of the sidewalks' centres, metres.
pub const SIDEWALK_M: f64 = 5.5;
/// Distance along the road from the ego car's stop (its IMU) to the cross street's centre line.
pub const JUNCTION_AHEAD_M: f64 = 14.0;
/// Half length of the cross street, metres.
pub const CROSS_HALF_LENGTH_M: f64 = 60.0;
/// Nothing stands within this distance of the cross street's centre line, metres.
pub const CROSS_CLEAR_M: f64 = 7.0;
/// Length of the traffic scenario, seconds.
pub const DURATION_S: f64 = 60.0;

/// The road's centre line by arc length (a table of the loop's path angle).
#[derive(Clone, Debug)]
pub struct Road {
    th0: f64,
    step: f64,
    s: Vec<f64>,
}

impl Road {
    /// The loop from path angle -3.5 to 4.5 rad (s = 0 at angle 0).
    pub fn new() -> Self {
        let (th0, th1, step) = (-3.5, 4.5, 1e-3);
        let n = ((th1 - th0) / step) as usize;
        let speed = |th: f64| {
            let [_, _, dx, dy] = road_point(th);
            libm::hypot(dx, dy)
        };
        let mut s = Vec::with_capacity(n + 1);
        let mut acc = 0.0;
        s.push(0.0);
        for i in 0..n {
            acc += speed(th0 + (i as f64 + 0.5) * step) * step;
            s.push(acc);
        }
        let zero = Road { th0, step, s: s.clone() }.s_of(0.0);
        Road { th0, step, s: s.iter().map(|v| v - zero).collect() }
    }

    /// Arc length at path angle `th`.
    pub fn s_of(&self, th: f64) -> f64 {
        let f = ((th - self.th0) / self.step).clamp(0.0, (self.s.len() - 1) as f64);
        let i = (f as usize).min(self.s.len() - 2);
        let u = f - i as f64;
        self.s[i] + u * (self.s[i + 1] - self.s[i])
    }

    /// Path angle at arc length `s`.
    pub fn th_of(&self, s: f64) -> f64 {
        let i = self.s.partition_point(|v| *v <= s).clamp(1, self.s.len() - 1) - 1;
        let u = ((s - self.s[i]) / (self.s[i + 1] - self.s[i])).clamp(0.0, 1.0);
        self.th0 + (i as f64 + u) * self.step
    }

    /// The point at arc length `s`, `l` metres to the left of the centre line.
    pub fn at(&self, s: f64, l: f64) -> [f64; 2] {
        let [x, y, dx, dy] = road_point(self.th_of(s));
        let n = libm::hypot(dx, dy);
        [x - dy / n * l, y + dx / n * l]
    }

    /// The unit direction of travel at arc length `s`.
    pub fn heading(&self, s: f64) -> [f64; 2] {
        let [_, _, dx, dy] = road_point(self.th_of(s));
        let n = libm::hypot(dx, dy);
        [dx / n, dy / n]
    }

    /// The ego car's arc length at `t` seconds.
    pub fn ego_s(&self, t: f64) -> f64 {
        self.s_of(traffic_theta(t))
    }
}

impl Default for Road {
    fn default() -> Self {
        Self::new()
    }
}

/// The traffic scenario's moving actors and junction.
#[derive(Clone, Debug)]
pub struct Traffic {
    /// The actors (ids = indices).
    pub actors: Actors,
    /// Centre of the junction (x, y).
    pub junction: [f64; 2],
    /// Unit direction of the cross street (to the right of the ego car's travel).
    pub cross: [f64; 2],
}

/// Times t0, t0 + dt, ..., t1.
fn times(t0: f64, t1: f64, dt: f64) -> Vec<f64> {
    let n = libm::ceil((t1 - t0) / dt - 1e-9).max(1.0) as usize;
    (0..=n).map(|i| if i == n { t1 } else { t0 + i as f64 * dt }).collect()
}

impl Traffic {
    /// The script on the town's ground.
    pub fn new(terrain: &Terrain) -> Traffic {
        let road = Road::new();
        let e = |t: f64| road.ego_s(t);
        let s_stop = e(TRAFFIC_STOP_S);
        let s_j = s_stop + JUNCTION_AHEAD_M;
        let junction = road.at(s_j, 0.0);
        let u = road.heading(s_j);
        let cross = [u[1], -u[0]];
        let mut list: Vec<Actor> = Vec::new();
        let along = |list: &mut Vec<Actor>,
                     kind: ActorKind,
                     t0: f64,
                     t1: f64,
                     dt: f64,
                     f: &dyn Fn(f64) -> (f64, f64)| {
            let path: Vec<[f64; 3]> = times(t0, t1, dt)
                .into_iter()
                .map(|t| {
                    let (s, l) = f(t);
                    let [x, y] = road.at(s, l);
                    [t, x, y]
                })
                .collect();
            let (s0, _) = f(t0);
            let h = road.heading(s0);
            let id = list.len() as u32;
            list.push(Actor::on_ground(id, kind, &path, terrain, libm::atan2(h[1], h[0])));
        };
        // 0: a truck close ahead, pulling away from 8 s.
        along(&mut list, ActorKind::Truck, 0.0, 24.0, 0.1, &|t| {
            let d = if t <= 8.0 {
                14.0
            } else if t <= 13.0 {
                14.0 + (t - 8.0) * (t - 8.0)
            } else {
                39.0 + 10.0 * (t - 13.0)
            };
            (e(t) + d, 0.0)
        });
        // 1, 2: oncoming cars.
        along(&mut list, ActorKind::Car, 0.0, 12.0, 0.1, &|t| (e(3.5) - 9.0 * (t - 3.5), LANE_M));
        along(&mut list, ActorKind::Car, 0.0, 14.0, 0.1, &|t| (e(6.5) - 10.0 * (t - 6.5), LANE_M));
        // 3: a car overtaking.
        along(&mut list, ActorKind::Car, 11.0, 27.0, 0.1, &|t| (e(t) - 40.0 + 7.0 * (t - 11.0), LANE_M));
        // 4, 5, 6: cross traffic, driving on the right of the cross street.
        let cross_at = |pos: f64, off: f64| {
            [junction[0] + pos * cross[0] + off * u[0], junction[1] + pos * cross[1] + off * u[1]]
        };
        let half = CROSS_HALF_LENGTH_M;
        for (t0, t1, dir) in [(18.0, 31.0, 1.0), (20.5, 33.5, -1.0), (15.5, 27.5, 1.0)] {
            let (a, b) = (cross_at(-dir * half, -dir * 2.0), cross_at(dir * half, -dir * 2.0));
            let id = list.len() as u32;
            list.push(Actor::line(id, ActorKind::Car, t0, a, t1, b, terrain));
        }
        // 7: a bus passing slowly alongside.
        along(&mut list, ActorKind::Bus, 24.0, DURATION_S, 0.1, &|t| {
            (e(t) - 9.0 + 1.5 * (t - 45.0), BUS_LANE_M)
        });
        // 8, 9: pedestrians on the sidewalks.
        along(&mut list, ActorKind::Pedestrian, 0.0, DURATION_S, 0.5, &|t| {
            (s_stop - 40.0 + 1.4 * t, -SIDEWALK_M)
        });
        along(&mut list, ActorKind::Pedestrian, 0.0, DURATION_S, 0.5, &|t| {
            (s_stop + 2.0 - 1.2 * t, SIDEWALK_M)
        });
        // 10, 11: pedestrians crossing the road ahead of and behind the waiting car.
        for (s, t0, t1, from) in [(s_stop + 7.0, 21.5, 30.5, -6.5), (s_stop - 8.0, 23.0, 32.0, 6.5)] {
            let [a, b] = [road.at(s, from), road.at(s, -from)];
            let id = list.len() as u32;
            let path = [[0.0, a[0], a[1]], [t0, a[0], a[1]], [t1, b[0], b[1]], [DURATION_S, b[0], b[1]]];
            list.push(Actor::on_ground(id, ActorKind::Pedestrian, &path, terrain, 0.0));
        }
        // 12: a pedestrian along the cross street to the corner.
        let (a, b) = (cross_at(-45.0, SIDEWALK_M), cross_at(-9.0, SIDEWALK_M));
        let t1 = 36.0 / 1.3;
        let id = list.len() as u32;
        let path = [[0.0, a[0], a[1]], [t1, b[0], b[1]], [DURATION_S, b[0], b[1]]];
        list.push(Actor::on_ground(id, ActorKind::Pedestrian, &path, terrain, 0.0));
        Traffic { actors: Actors::new(list), junction, cross }
    }

    /// The town of `seed` with the cross street and the actors' way cleared.
    pub fn world(&self, seed: u64) -> World {
        let cross_line: Vec<[f64; 3]> = (-80..=80)
            .map(|i| {
                let p = i as f64;
                [self.junction[0] + p * self.cross[0], self.junction[1] + p * self.cross[1], 0.0]
            })
            .collect();
        // Every actor's box every 0.1 s, with its xy bounds.
        let mut boxes: Vec<(Shape, [f64; 4])> = Vec::new();
        for a in self.actors.list() {
            let (t0, t1) = a.time_range();
            for t in times(t0, t1, 0.1) {
                if let Some(q) = a.pose_at(t) {
                    let s = q.shape();
                    let (lo, hi) = s.bounds();
                    boxes.push((s, [lo[0], lo[1], hi[0], hi[1]]));
                }
            }
        }
        let margin = 0.1;
        let in_the_way = |p: &Prim| -> bool {
            let (lo, hi) = p.shape.bounds();
            boxes.iter().any(|(s, b)| {
                let Shape::Box { c, h, .. } = *s else { return false };
                let (bottom, top) = (c[2] - h[2], c[2] + h[2]);
                lo[0] <= b[2] + margin
                    && hi[0] >= b[0] - margin
                    && lo[1] <= b[3] + margin
                    && hi[1] >= b[1] - margin
                    // Kerbs (up to 0.3 m above the actor's feet) and what is above its head stay.
                    && hi[2] > bottom + 0.3
                    && lo[2] < top
                    && footprints_overlap(&p.shape, s, margin)
            })
        };
        World::town_without(seed, |p| clearance(&p.shape, &cross_line) < CROSS_CLEAR_M || in_the_way(p))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::actors::ActorPose;
    use crate::trajectory::Trajectory;

    fn ego_box(traj: &Trajectory, t: f64) -> Shape {
        let k = traj.eval(t);
        let f = k.rotation * nalgebra::Vector3::x();
        Shape::boxed([k.position.x, k.position.y, 0.0], [4.5, 1.8, 1.0], libm::atan2(f.y, f.x))
    }

    #[test]
    fn road_table_is_consistent() {
        let road = Road::new();
        for th in [-3.0, -1.2, 0.0, 0.7, 3.9] {
            assert!((road.th_of(road.s_of(th)) - th).abs() < 1e-9, "{th}");
            let [x, y, ..] = road_point(th);
            let p = road.at(road.s_of(th), 0.0);
            assert!((p[0] - x).abs() < 1e-6 && (p[1] - y).abs() < 1e-6);
        }
        // Arc length grows like the car's speed: 6.7 m/s * 80 m/rad / 6.7 ... about 80 m per rad.
        let ds = road.s_of(0.5) - road.s_of(-0.5);
        assert!(ds > 50.0 && ds < 100.0, "{ds}");
    }

    #[test]
    fn nobody_collides_and_the_junction_is_clear() {
        let terrain = Terrain::town();
        let tr = Traffic::new(&terrain);
        let traj = Trajectory::Traffic { terrain: terrain.clone() };
        assert_eq!(tr.actors.list().len(), 13);
        let kinds: Vec<ActorKind> = tr.actors.list().iter().map(|a| a.kind).collect();
        for k in [ActorKind::Car, ActorKind::Bus, ActorKind::Truck, ActorKind::Pedestrian] {
            assert!(kinds.contains(&k), "{k:?}");
        }
        // Every 50 ms: no two actors overlap, and none overlaps the ego car.
        for i in 0..=1200 {
            let t = i as f64 * 0.05;
            let poses: Vec<ActorPose> = tr.actors.at(t);
            let ego = ego_box(&traj, t);
            for (a, p) in poses.iter().enumerate() {
                let sp = p.shape();
                assert!(!footprints_overlap(&sp, &ego, 0.05), "actor {} meets the ego car at {t}", p.id);
                for q in &poses[a + 1..] {
                    assert!(
                        !footprints_overlap(&sp, &q.shape(), 0.05),
                        "actors {} and {} meet at {t}",
                        p.id,
                        q.id
                    );
                }
            }
        }
        // The cross traffic passes in front of the waiting car.
        let mut crossing = 0;
        for i in 0..=90 {
            let t = TRAFFIC_STOP_S + i as f64 * 0.1;
            for p in tr.actors.at(t).iter().filter(|p| (4..=6).contains(&p.id)) {
                let d = libm::hypot(p.c[0] - tr.junction[0], p.c[1] - tr.junction[1]);
                crossing += (d < 5.0) as u32;
            }
        }
        assert!(crossing > 10, "{crossing}");
        // The world: nothing stands in the cross street or in an actor's way (above kerb height).
        let world = tr.world(1);
        let full = World::build(crate::world::SceneKind::Town, 1);
        let removed = full.scene.prims().len() - world.scene.prims().len();
        assert!(removed > 5 && removed < full.scene.prims().len() / 4, "{removed}");
        for p in world.scene.prims() {
            let d = p.shape.xy_distance(tr.junction);
            assert!(d > CROSS_CLEAR_M - 1e-9, "{p:?} at {d} from the junction");
        }
    }
}
