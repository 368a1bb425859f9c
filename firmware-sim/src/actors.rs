//! Moving actors: vehicles and pedestrians as boxes that follow paths over time.
//!
//! An [`Actor`] is an upright box (rotated about z only) whose centre follows piecewise-linear
//! waypoints `(t, x, y, z)`; its heading is the direction of motion of the segment it is on (a
//! segment without motion keeps the heading of the nearest one that moves). An actor exists only
//! between its first and its last waypoint times. Because every segment is a straight
//! translation of a box at a fixed heading, where an actor is at any instant, and the volume it
//! sweeps over any time range, have exact closed forms ([`Actor::pose_at`],
//! [`Actor::swept_contains`]).
//!
//! The LiDAR meets the actors where they are at each firing's own time ([`Actors::cast`], called
//! by [`crate::lidar::scanner::WorldEchoes`] with the firing time), so a moving car is distorted
//! across a scan as on a real sensor. There are few actors: each ray tests each existing actor's
//! bounding sphere first (a few multiplications) and the exact box slabs only on a sphere hit.

use std::io::Write;

use crate::raycast::{Hit, Ray, Shape, ray_box};
use crate::terrain::Terrain;

/// [`Hit::prim`] of an actor: this bit set, the actor's id in the low bits.
pub const ACTOR_PRIM: u32 = 0x8000_0000;

/// What an actor is.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ActorKind {
    /// A car, 4.5 x 1.8 x 1.5 m.
    Car,
    /// A bus, 12 x 2.5 x 3.2 m.
    Bus,
    /// A truck, 12 x 2.5 x 3.2 m.
    Truck,
    /// A pedestrian, 0.5 x 0.5 x 1.8 m.
    Pedestrian,
}

impl ActorKind {
    /// Full size (length along the heading, width, height), metres.
    pub fn size(self) -> [f64; 3] {
        match self {
            Self::Car => [4.5, 1.8, 1.5],
            Self::Bus | Self::Truck => [12.0, 2.5, 3.2],
            Self::Pedestrian => [0.5, 0.5, 1.8],
        }
    }

    /// Name (`car`, `bus`, `truck`, `pedestrian`).
    pub fn name(self) -> &'static str {
        match self {
            Self::Car => "car",
            Self::Bus => "bus",
            Self::Truck => "truck",
            Self::Pedestrian => "pedestrian",
        }
    }

    /// Surface reflectivity (0-100 diffuse).
    pub fn reflectivity(self) -> u8 {
        match self {
            Self::Car => 55,
            Self::Bus => 50,
            Self::Truck => 45,
            Self::Pedestrian => 25,
        }
    }

    /// Whether it is a vehicle.
    pub fn is_vehicle(self) -> bool {
        self != Self::Pedestrian
    }
}

/// A waypoint of an actor's centre: seconds since the scenario start and world position.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Waypoint {
    /// Seconds since the scenario start.
    pub t: f64,
    /// Centre of the box, metres.
    pub p: [f64; 3],
}

/// Where an actor is at one instant.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ActorPose {
    /// The actor's id.
    pub id: u32,
    /// What it is.
    pub kind: ActorKind,
    /// Centre of the box, metres.
    pub c: [f64; 3],
    /// Heading (the box's length axis), radians from +x.
    pub yaw: f64,
    /// Full size (length, width, height).
    pub size: [f64; 3],
    /// Velocity of the centre, m/s.
    pub velocity: [f64; 3],
}

impl ActorPose {
    /// The box as a ray-casting shape.
    pub fn shape(&self) -> Shape {
        Shape::boxed(self.c, self.size, self.yaw)
    }

    /// Whether a world point lies inside the box (boundary included).
    pub fn contains(&self, p: [f64; 3]) -> bool {
        let (cos, sin) = (libm::cos(self.yaw), libm::sin(self.yaw));
        inside_box(p, self.c, [self.size[0] * 0.5, self.size[1] * 0.5, self.size[2] * 0.5], cos, sin)
    }
}

/// Whether a ray may meet the sphere (centre `c`, radius `r`) before `best`: false only when it
/// surely does not (a negative radius: never).
#[inline]
fn sphere_before(ray: &Ray, c: [f64; 3], r: f64, best: f64) -> bool {
    if r < 0.0 {
        return false;
    }
    let p = [ray.o[0] - c[0], ray.o[1] - c[1], ray.o[2] - c[2]];
    let b = p[0] * ray.d[0] + p[1] * ray.d[1] + p[2] * ray.d[2];
    let cc = p[0] * p[0] + p[1] * p[1] + p[2] * p[2] - r * r;
    // Outside and pointing away, or passing by, or entering beyond the best hit.
    !(b * b - cc < 0.0 || (cc > 0.0 && b > 0.0) || -b - r >= best)
}

#[inline]
fn inside_box(p: [f64; 3], c: [f64; 3], h: [f64; 3], cos: f64, sin: f64) -> bool {
    let (dx, dy, dz) = (p[0] - c[0], p[1] - c[1], p[2] - c[2]);
    let (lx, ly) = (cos * dx + sin * dy, -sin * dx + cos * dy);
    lx.abs() <= h[0] && ly.abs() <= h[1] && dz.abs() <= h[2]
}

/// One moving box.
#[derive(Clone, Debug, PartialEq)]
pub struct Actor {
    /// Id (its index in the scenario's list).
    pub id: u32,
    /// What it is.
    pub kind: ActorKind,
    /// Half extents (length, width, height).
    half: [f64; 3],
    /// Radius of the bounding sphere (half the box diagonal).
    radius: f64,
    /// Its highest speed on any segment, m/s.
    vmax: f64,
    refl: u8,
    way: Vec<Waypoint>,
    /// Per segment (waypoint k to k + 1): cos and sin of the heading.
    heading: Vec<[f64; 2]>,
}

impl Actor {
    /// An actor following `way` (at least two waypoints, times strictly increasing). Heading is
    /// along each segment's xy motion; segments without motion keep the previous moving
    /// segment's heading (the next one's before the first move; `still_yaw` if it never moves).
    pub fn new(id: u32, kind: ActorKind, way: Vec<Waypoint>, still_yaw: f64) -> Actor {
        assert!(way.len() >= 2, "an actor needs two waypoints");
        assert!(way.windows(2).all(|w| w[1].t > w[0].t), "waypoint times must increase");
        let yaws: Vec<Option<f64>> = way
            .windows(2)
            .map(|w| {
                let (dx, dy) = (w[1].p[0] - w[0].p[0], w[1].p[1] - w[0].p[1]);
                (dx * dx + dy * dy > 1e-12).then(|| libm::atan2(dy, dx))
            })
            .collect();
        let first = yaws.iter().flatten().next().copied().unwrap_or(still_yaw);
        let mut last = first;
        let heading = yaws
            .iter()
            .map(|y| {
                if let Some(y) = y {
                    last = *y;
                }
                [libm::cos(last), libm::sin(last)]
            })
            .collect();
        let s = kind.size();
        let half = [s[0] * 0.5, s[1] * 0.5, s[2] * 0.5];
        let radius = libm::sqrt(half[0] * half[0] + half[1] * half[1] + half[2] * half[2]);
        let vmax = way
            .windows(2)
            .map(|w| {
                let d = [w[1].p[0] - w[0].p[0], w[1].p[1] - w[0].p[1], w[1].p[2] - w[0].p[2]];
                libm::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) / (w[1].t - w[0].t)
            })
            .fold(0.0, f64::max);
        Actor { id, kind, half, radius, vmax, refl: kind.reflectivity(), way, heading }
    }

    /// An actor whose box stands on the ground: `path` gives (t, x, y) of its centre, and the
    /// centre's height is the ground's plus half the box height at each waypoint. Each segment
    /// longer than 2 m is split so the box follows the ground's shape.
    pub fn on_ground(
        id: u32,
        kind: ActorKind,
        path: &[[f64; 3]],
        terrain: &Terrain,
        still_yaw: f64,
    ) -> Actor {
        let hz = kind.size()[2] * 0.5;
        let at = |t: f64, x: f64, y: f64| Waypoint { t, p: [x, y, terrain.height(x, y) + hz] };
        let mut way = Vec::with_capacity(path.len());
        for (k, q) in path.iter().enumerate() {
            if k > 0 {
                let p = path[k - 1];
                let n = libm::ceil(libm::hypot(q[1] - p[1], q[2] - p[2]) / 2.0).max(1.0) as usize;
                for i in 1..n {
                    let f = i as f64 / n as f64;
                    way.push(at(
                        p[0] + f * (q[0] - p[0]),
                        p[1] + f * (q[1] - p[1]),
                        p[2] + f * (q[2] - p[2]),
                    ));
                }
            }
            way.push(at(q[0], q[1], q[2]));
        }
        Actor::new(id, kind, way, still_yaw)
    }

    /// An actor on the ground driving a straight line from `p0` at `t0` to `p1` at `t1` at
    /// constant speed.
    pub fn line(
        id: u32,
        kind: ActorKind,
        t0: f64,
        p0: [f64; 2],
        t1: f64,
        p1: [f64; 2],
        terrain: &Terrain,
    ) -> Actor {
        let yaw = libm::atan2(p1[1] - p0[1], p1[0] - p0[0]);
        Actor::on_ground(id, kind, &[[t0, p0[0], p0[1]], [t1, p1[0], p1[1]]], terrain, yaw)
    }

    /// The waypoints.
    pub fn waypoints(&self) -> &[Waypoint] {
        &self.way
    }

    /// The time range in which it exists, seconds.
    pub fn time_range(&self) -> (f64, f64) {
        (self.way[0].t, self.way[self.way.len() - 1].t)
    }

    /// The segment at `t`, starting the search at `hint` (updated); `None` outside its time range.
    #[inline]
    fn segment(&self, t: f64, hint: &mut u32) -> Option<usize> {
        let n = self.heading.len();
        let (t0, t1) = self.time_range();
        if !(t >= t0 && t <= t1) {
            return None;
        }
        let mut k = (*hint as usize).min(n - 1);
        if !(self.way[k].t <= t && t <= self.way[k + 1].t) {
            if k + 2 <= n && self.way[k + 1].t <= t && t <= self.way[k + 2].t {
                k += 1;
            } else {
                k = self.way.partition_point(|w| w.t <= t).saturating_sub(1).min(n - 1);
            }
        }
        *hint = k as u32;
        Some(k)
    }

    #[inline]
    fn centre_on(&self, k: usize, t: f64) -> [f64; 3] {
        let (a, b) = (&self.way[k], &self.way[k + 1]);
        let f = (t - a.t) / (b.t - a.t);
        [a.p[0] + f * (b.p[0] - a.p[0]), a.p[1] + f * (b.p[1] - a.p[1]), a.p[2] + f * (b.p[2] - a.p[2])]
    }

    /// Where it is at `t` seconds; `None` outside its time range.
    pub fn pose_at(&self, t: f64) -> Option<ActorPose> {
        let k = self.segment(t, &mut 0)?;
        let (a, b) = (&self.way[k], &self.way[k + 1]);
        let dt = b.t - a.t;
        let [cos, sin] = self.heading[k];
        Some(ActorPose {
            id: self.id,
            kind: self.kind,
            c: self.centre_on(k, t),
            yaw: libm::atan2(sin, cos),
            size: self.kind.size(),
            velocity: [(b.p[0] - a.p[0]) / dt, (b.p[1] - a.p[1]) / dt, (b.p[2] - a.p[2]) / dt],
        })
    }

    /// Whether a world point lies inside the volume the box swept between `t0` and `t1`
    /// (clipped to its time range): exact, segment by segment (a box translated along a straight
    /// segment at a fixed heading covers `p` iff some fraction s in [0, 1] of the way puts `p`
    /// inside it, which is an interval per box axis).
    pub fn swept_contains(&self, p: [f64; 3], t0: f64, t1: f64) -> bool {
        let (a0, a1) = self.time_range();
        let (t0, t1) = (t0.max(a0), t1.min(a1));
        if t0 > t1 {
            return false;
        }
        let mut hint = 0;
        let (Some(k0), Some(k1)) = (self.segment(t0, &mut hint), self.segment(t1, &mut hint)) else {
            return false;
        };
        for k in k0..=k1 {
            let (ta, tb) = (t0.max(self.way[k].t), t1.min(self.way[k + 1].t));
            let (ca, cb) = (self.centre_on(k, ta), self.centre_on(k, tb));
            let [cos, sin] = self.heading[k];
            let (qx, qy, qz) = (p[0] - ca[0], p[1] - ca[1], p[2] - ca[2]);
            let (ex, ey, ez) = (cb[0] - ca[0], cb[1] - ca[1], cb[2] - ca[2]);
            let q = [cos * qx + sin * qy, -sin * qx + cos * qy, qz];
            let e = [cos * ex + sin * ey, -sin * ex + cos * ey, ez];
            let (mut lo, mut hi) = (0.0f64, 1.0f64);
            for a in 0..3 {
                // -h <= q - s e <= h
                let h = self.half[a];
                if e[a].abs() < 1e-15 {
                    if q[a].abs() > h {
                        lo = 1.0;
                        hi = 0.0;
                    }
                } else {
                    let (s1, s2) = ((q[a] - h) / e[a], (q[a] + h) / e[a]);
                    lo = lo.max(s1.min(s2));
                    hi = hi.min(s1.max(s2));
                }
            }
            if lo <= hi {
                return true;
            }
        }
        false
    }
}

/// The actors of a scenario.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Actors {
    list: Vec<Actor>,
}

impl Actors {
    /// A set of actors (ids should be their indices).
    pub fn new(list: Vec<Actor>) -> Self {
        Self { list }
    }

    /// The actors.
    pub fn list(&self) -> &[Actor] {
        &self.list
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.list.is_empty()
    }

    /// Where every existing actor is at `t` seconds.
    pub fn at(&self, t: f64) -> Vec<ActorPose> {
        self.list.iter().filter_map(|a| a.pose_at(t)).collect()
    }

    /// The id of an actor whose box contains a world point at `t` seconds.
    pub fn inside(&self, p: [f64; 3], t: f64) -> Option<u32> {
        self.list.iter().find(|a| a.pose_at(t).is_some_and(|q| q.contains(p))).map(|a| a.id)
    }

    /// The id of an actor whose swept volume over [t0, t1] seconds contains a world point.
    pub fn inside_swept(&self, p: [f64; 3], t0: f64, t1: f64) -> Option<u32> {
        self.list.iter().find(|a| a.swept_contains(p, t0, t1)).map(|a| a.id)
    }

    /// Spheres that hold each actor's box at every time in [t, t + dt] (centre and radius; a
    /// negative radius: the actor does not exist then), for [`Self::cast_near`].
    pub fn spheres(&self, t: f64, dt: f64, out: &mut Vec<[f64; 4]>) {
        out.clear();
        out.extend(self.list.iter().map(|a| {
            let (t0, t1) = a.time_range();
            if t + dt < t0 || t > t1 {
                return [0.0, 0.0, 0.0, -1.0];
            }
            let Some(k) = a.segment(t.clamp(t0, t1), &mut 0) else { return [0.0, 0.0, 0.0, -1.0] };
            let c = a.centre_on(k, t.clamp(t0, t1));
            [c[0], c[1], c[2], a.radius + a.vmax * dt * 1.001 + 1e-6]
        }));
    }

    /// The nearest actor surface a ray meets at `t` seconds, closer than `t_max`. `hints` keeps
    /// each actor's last segment between calls (any content is valid; one entry per actor).
    pub fn cast(&self, ray: &Ray, t: f64, t_max: f64, hints: &mut [u32]) -> Option<Hit> {
        self.cast_near(ray, t, t_max, hints, None)
    }

    /// [`Self::cast`] that first rejects the actors whose sphere of [`Self::spheres`] (made for
    /// a time range holding `t`) the ray misses: the same answer, cheaper for many rays.
    pub fn cast_near(
        &self,
        ray: &Ray,
        t: f64,
        t_max: f64,
        hints: &mut [u32],
        spheres: Option<&[[f64; 4]]>,
    ) -> Option<Hit> {
        let mut best = t_max;
        let mut hit = None;
        for (i, (a, hint)) in self.list.iter().zip(hints.iter_mut()).enumerate() {
            if let Some(sp) = spheres.and_then(|s| s.get(i))
                && !sphere_before(ray, [sp[0], sp[1], sp[2]], sp[3], best)
            {
                continue;
            }
            let Some(k) = a.segment(t, hint) else { continue };
            let c = a.centre_on(k, t);
            // Bounding sphere: reject rays that miss it or meet it beyond the best hit.
            if !sphere_before(ray, c, a.radius, best) {
                continue;
            }
            let [cos, sin] = a.heading[k];
            if let Some((d, n)) = ray_box(ray, c, a.half, cos, sin, 0.0, best) {
                best = d;
                hit = Some(Hit { t: d, n, refl: a.refl, fraction: 1.0, prim: ACTOR_PRIM | a.id });
            }
        }
        hit
    }

    /// Writes every existing actor's pose at `hz` from `t0` to `t1` seconds as CSV: absolute time
    /// (`start_ns` plus the offset), seconds since the start, id, kind, centre, heading, size and
    /// velocity.
    pub fn write_csv(
        &self,
        mut w: impl Write,
        start_ns: u64,
        t0: f64,
        t1: f64,
        hz: f64,
    ) -> std::io::Result<()> {
        writeln!(w, "t_ns,t_s,id,kind,x,y,z,yaw,length,width,height,vx,vy,vz")?;
        let n = libm::floor((t1 - t0) * hz + 1e-9) as u64;
        for i in 0..=n {
            let off_ns = (t0 * 1e9) as u64 + i * (1e9 / hz) as u64;
            let t = off_ns as f64 / 1e9;
            for q in self.at(t) {
                writeln!(
                    w,
                    "{},{:.3},{},{},{:.4},{:.4},{:.4},{:.5},{},{},{},{:.4},{:.4},{:.4}",
                    start_ns + off_ns,
                    t,
                    q.id,
                    q.kind.name(),
                    q.c[0],
                    q.c[1],
                    q.c[2],
                    q.yaw,
                    q.size[0],
                    q.size[1],
                    q.size[2],
                    q.velocity[0],
                    q.velocity[1],
                    q.velocity[2]
                )?;
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn flat() -> Terrain {
        Terrain::flat(0.0)
    }

    #[test]
    fn a_ray_meets_a_moving_box_where_it_is_at_each_firing_time() {
        // A car driving along +x at 10 m/s from x = 10 at t = 1 s, centre 0.75 m above flat ground.
        let car = Actor::line(0, ActorKind::Car, 1.0, [10.0, 5.0], 5.0, [50.0, 5.0], &flat());
        let actors = Actors::new(vec![car]);
        let mut hints = [0u32];
        // A ray along +y from the origin at height 0.5 m: it meets the car's near side (y = 4.1)
        // only while the car spans x = 0 ... it never does; cast across its path at x = 20 and 30.
        for (t, x) in [(2.0, 20.0), (3.0, 30.0)] {
            let ray = Ray { o: [x, 0.0, 0.5], d: [0.0, 1.0, 0.0] };
            let h = actors.cast(&ray, t, 100.0, &mut hints).unwrap();
            assert!((h.t - 4.1).abs() < 1e-12, "{t}: {h:?}");
            assert_eq!(h.n, [0.0, -1.0, 0.0]);
            assert_eq!(h.prim, ACTOR_PRIM);
            // A ray along -x from far ahead meets the car's front at its position at t.
            let ray = Ray { o: [100.0, 5.0, 0.7], d: [-1.0, 0.0, 0.0] };
            let h = actors.cast(&ray, t, 200.0, &mut hints).unwrap();
            assert!((h.t - (100.0 - (x + 2.25))).abs() < 1e-12, "{t}: {h:?}");
            // Half a car length behind its tail: missed at t, met at t - 0.3 s (3 m back).
            let ray = Ray { o: [x - 2.5, 0.0, 0.5], d: [0.0, 1.0, 0.0] };
            assert!(actors.cast(&ray, t, 100.0, &mut hints).is_none());
            assert!(actors.cast(&ray, t - 0.3, 100.0, &mut hints).is_some());
        }
        // Before and after its time range it does not exist; t_max bounds the hit.
        let ray = Ray { o: [10.0, 0.0, 0.5], d: [0.0, 1.0, 0.0] };
        assert!(actors.cast(&ray, 0.99, 100.0, &mut hints).is_none());
        assert!(actors.cast(&ray, 1.0, 100.0, &mut hints).is_some());
        assert!(actors.cast(&ray, 1.0, 4.0, &mut hints).is_none());
        let ray = Ray { o: [50.0, 0.0, 0.5], d: [0.0, 1.0, 0.0] };
        assert!(actors.cast(&ray, 5.01, 100.0, &mut hints).is_none());
    }

    #[test]
    fn hints_do_not_change_answers_and_headings_follow_the_motion() {
        // An L-shaped path with a wait at the corner.
        let a = Actor::on_ground(
            3,
            ActorKind::Pedestrian,
            &[[0.0, 0.0, 0.0], [10.0, 10.0, 0.0], [12.0, 10.0, 0.0], [22.0, 10.0, 10.0]],
            &flat(),
            0.0,
        );
        let p = a.pose_at(5.0).unwrap();
        assert!((p.c[0] - 5.0).abs() < 1e-12 && p.yaw == 0.0 && (p.c[2] - 0.9).abs() < 1e-12);
        assert!((p.velocity[0] - 1.0).abs() < 1e-12);
        let p = a.pose_at(11.0).unwrap();
        assert_eq!(p.c[0], 10.0);
        assert_eq!(p.yaw, 0.0, "waiting keeps the heading");
        assert_eq!(p.velocity, [0.0; 3]);
        let p = a.pose_at(17.0).unwrap();
        assert!((p.yaw - core::f64::consts::FRAC_PI_2).abs() < 1e-12 && (p.c[1] - 5.0).abs() < 1e-12);
        let actors = Actors::new(vec![a]);
        let mut hints = [7u32];
        for i in 0..2200 {
            let t = (i * 7919 % 2200) as f64 * 0.01;
            let ray = Ray { o: [5.0, -20.0, 1.0], d: [0.0, 1.0, 0.0] };
            assert_eq!(actors.cast(&ray, t, 100.0, &mut hints), actors.cast(&ray, t, 100.0, &mut [0]));
        }
    }

    #[test]
    fn culling_spheres_do_not_change_answers() {
        let car = Actor::line(0, ActorKind::Car, 1.0, [10.0, 5.0], 5.0, [50.0, 5.0], &flat());
        let ped = Actor::line(1, ActorKind::Pedestrian, 0.0, [30.0, 3.0], 8.0, [30.0, -3.0], &flat());
        let actors = Actors::new(vec![car, ped]);
        let mut sp = Vec::new();
        let mut hits = 0;
        for i in 0..8000 {
            let t = i as f64 * 0.001;
            if i % 11 == 0 {
                actors.spheres(t, 0.011, &mut sp);
            }
            let a = (i as f64 * 0.37).sin();
            let ray = Ray { o: [30.0, -20.0, 0.7], d: [a, libm::sqrt(1.0 - a * a), 0.0] };
            let want = actors.cast(&ray, t, 100.0, &mut [0, 0]);
            assert_eq!(actors.cast_near(&ray, t, 100.0, &mut [0, 0], Some(&sp)), want, "{t}");
            hits += want.is_some() as u32;
        }
        assert!(hits > 100, "{hits}");
    }

    #[test]
    fn inside_and_swept_volume_are_exact() {
        let car = Actor::line(0, ActorKind::Car, 0.0, [0.0, 0.0], 10.0, [100.0, 0.0], &flat());
        let actors = Actors::new(vec![car]);
        // At t = 2 s the car spans x in [17.75, 22.25], y in [-0.9, 0.9], z in [0, 1.5].
        assert_eq!(actors.inside([22.2, 0.8, 1.4], 2.0), Some(0));
        assert_eq!(actors.inside([22.3, 0.0, 1.0], 2.0), None);
        assert_eq!(actors.inside([20.0, 0.0, 1.6], 2.0), None);
        // Swept over [2, 3] s: x in [17.75, 32.25].
        assert_eq!(actors.inside_swept([32.2, 0.0, 1.0], 2.0, 3.0), Some(0));
        assert_eq!(actors.inside_swept([17.8, -0.85, 0.1], 2.0, 3.0), Some(0));
        assert_eq!(actors.inside_swept([32.3, 0.0, 1.0], 2.0, 3.0), None);
        assert_eq!(actors.inside_swept([25.0, 0.95, 1.0], 2.0, 3.0), None);
        // A turning path: the corner's two boxes, not the gap between their headings.
        let turn = Actor::on_ground(
            1,
            ActorKind::Car,
            &[[0.0, 0.0, 0.0], [1.0, 10.0, 0.0], [2.0, 10.0, 10.0]],
            &flat(),
            0.0,
        );
        assert!(turn.swept_contains([5.0, 0.0, 0.5], 0.0, 2.0));
        assert!(turn.swept_contains([10.0, 5.0, 0.5], 0.0, 2.0));
        assert!(!turn.swept_contains([5.0, 5.0, 0.5], 0.0, 2.0));
        assert!(!turn.swept_contains([10.0, 5.0, 0.5], 0.0, 1.0));
        // Dense sampling of poses agrees with the closed form.
        for i in 0..400 {
            let p = [(i % 20) as f64 * 0.7 - 1.0, (i / 20) as f64 * 0.7 - 2.0, 0.7];
            let sampled = (0..=2000).any(|k| turn.pose_at(k as f64 * 0.001).is_some_and(|q| q.contains(p)));
            assert_eq!(sampled, turn.swept_contains(p, 0.0, 2.0), "{p:?}");
        }
    }

    #[test]
    fn csv_lists_the_existing_actors() {
        let a = Actor::line(0, ActorKind::Bus, 0.0, [0.0, 0.0], 1.0, [12.0, 0.0], &flat());
        let b = Actor::line(1, ActorKind::Pedestrian, 0.5, [0.0, 5.0], 2.0, [0.0, 7.0], &flat());
        let mut out = Vec::new();
        Actors::new(vec![a, b]).write_csv(&mut out, 1_000_000_000, 0.0, 2.0, 10.0).unwrap();
        let text = String::from_utf8(out).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[0], "t_ns,t_s,id,kind,x,y,z,yaw,length,width,height,vx,vy,vz");
        // The bus at 11 stamps (0 ... 1 s), the pedestrian at 16 (0.5 ... 2 s).
        assert_eq!(lines.len(), 1 + 11 + 16);
        assert!(
            lines[1].starts_with("1000000000,0.000,0,bus,0.0000,0.0000,1.6000,0.00000,12,2.5,3.2,12.0000")
        );
    }
}
