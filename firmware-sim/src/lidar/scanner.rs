//! The LiDAR's view of the simulated world: an [`EchoSource`] that casts every firing from the
//! sensor's true pose at its firing time, and the direct-scan generator that turns firings into
//! [`ScanPoint`]s the way the core's decoders would.
//!
//! Pose per firing: the trajectory is evaluated exactly on a fixed 1 ms grid of absolute time
//! (so the result does not depend on how the work is split) and carried to each laser's own
//! firing time, at most 1.04 ms later, with the exact velocity, acceleration, angular rate and
//! angular acceleration at the grid point: p + v dt + a dt^2 / 2 and R exp(w dt + alpha dt^2 / 2)
//! (exponential to second order). The neglected terms (jerk dt^3 / 6, the rotation's dt^3
//! terms) stay below 1e-8 m and 1e-8 rad for every scenario, far below the 1-4 mm range
//! resolution.
//!
//! Echo model: the range gets Gaussian noise (sigma of the sensor's [`RangeModel`]); a firing is
//! dropped (no return) at random with the model's dropout probability, more often at grazing
//! incidence, below the minimum range, and beyond a maximum range that shrinks for dark
//! surfaces (max_range * sqrt(reflectivity * cos(incidence) / 80), at least 30 %). All random
//! numbers are hashes of (seed, firing key), so packets and direct scans of the same seed carry
//! identical points.
//!
//! Moving actors ([`crate::actors`], the traffic scenario) are met where they are at each
//! firing's own time, after the static world: the nearer surface wins.

use loglio_core::range_image::RangeImageLayout;
use loglio_core::scan::ScanPoint;
use nalgebra::{Isometry3, Matrix3, Vector3};

use super::ouster::Ouster;
use super::velodyne::Velodyne;
use super::{Echo, EchoSource, Echoes, Firing, RangeModel, ReturnMode};
use crate::actors::Actors;
use crate::raycast::{Hit, Ray, Scene};
use crate::rng;
use crate::trajectory::Trajectory;

/// Spacing of the exact trajectory evaluations, ns.
pub const POSE_STEP_NS: u64 = 1_000_000;

/// Stream ids of the per-firing random numbers.
const S_NOISE_LAST: u64 = 0xA1;
const S_NOISE_FIRST: u64 = 0xA2;
const S_DROP: u64 = 0xA3;
const S_REFL: u64 = 0xA4;

/// What the sensor sees of the world along the trajectory.
#[derive(Clone, Debug)]
pub struct WorldEchoes<'a> {
    scene: &'a Scene,
    traj: &'a Trajectory,
    /// Pose of the LiDAR's output (sensor) frame in the IMU frame.
    t_il: Isometry3<f64>,
    /// Absolute time of the trajectory's t = 0, ns.
    start_ns: u64,
    seed: u64,
    range: RangeModel,
    t0: u64,
    r: Matrix3<f64>,
    p: Vector3<f64>,
    v: Vector3<f64>,
    a: Vector3<f64>,
    w: Vector3<f64>,
    al: Vector3<f64>,
    /// Moving actors, met where they are at each firing's time (none: a static world).
    actors: Option<&'a Actors>,
    /// Each actor's last path segment (a search hint).
    hints: Vec<u32>,
    /// Spheres holding each actor over the current pose step (a cheap first rejection).
    spheres: Vec<[f64; 4]>,
    /// Rays cast so far.
    pub rays: u64,
}

impl<'a> WorldEchoes<'a> {
    /// A source for a LiDAR mounted at `t_il` on the IMU that follows `traj` from `start_ns`.
    pub fn new(
        scene: &'a Scene,
        traj: &'a Trajectory,
        t_il: Isometry3<f64>,
        start_ns: u64,
        seed: u64,
        range: RangeModel,
    ) -> Self {
        Self {
            scene,
            traj,
            t_il,
            start_ns,
            seed,
            range,
            t0: u64::MAX,
            r: Matrix3::identity(),
            p: Vector3::zeros(),
            v: Vector3::zeros(),
            a: Vector3::zeros(),
            w: Vector3::zeros(),
            al: Vector3::zeros(),
            actors: None,
            hints: Vec::new(),
            spheres: Vec::new(),
            rays: 0,
        }
    }

    /// The same source with moving actors in the world (an empty set changes nothing).
    pub fn with_actors(mut self, actors: &'a Actors) -> Self {
        if !actors.is_empty() {
            self.hints = vec![0; actors.list().len()];
            self.actors = Some(actors);
        }
        self
    }

    fn echo(&self, h: &Hit, d: [f64; 3], key: u64, stream: u64) -> Option<Echo> {
        let cos = (h.n[0] * d[0] + h.n[1] * d[1] + h.n[2] * d[2]).abs();
        let m = &self.range;
        // One hash per echo; its independent derivatives drive dropout, noise and scatter.
        let hsh = rng::hash3(self.seed, key, stream);
        let mut p_drop = m.dropout;
        if cos < 0.1 {
            p_drop += 0.7 * (0.1 - cos) / 0.1;
        }
        if rng::to_unit(rng::mix64(hsh ^ S_DROP)) < p_drop {
            return None;
        }
        let refl_cos = (h.refl as f64 * cos * h.fraction as f64).max(1.0);
        let max = m.max_range * libm::sqrt(refl_cos / 80.0).clamp(0.3, 1.0);
        if h.t > max {
            return None;
        }
        let range = h.t + m.sigma * rng::gauss_from(hsh);
        if range < m.min_range {
            return None;
        }
        // Calibrated reflectivity: the surface's, with a little measurement scatter (retro-
        // reflectors keep their >100 values).
        let jitter = (rng::to_unit(rng::mix64(hsh ^ S_REFL)) - 0.5) * 6.0;
        let refl = if h.refl > 100 {
            h.refl
        } else {
            (h.refl as f64 * (0.7 + 0.3 * cos) + jitter).clamp(1.0, 100.0) as u8
        };
        Some(Echo { range, reflectivity: refl, strength: (refl_cos / (range * range).max(1.0)) as f32 })
    }
}

impl EchoSource for WorldEchoes<'_> {
    fn begin_sequence(&mut self, t_ns: u64) {
        let rel = t_ns.saturating_sub(self.start_ns);
        let base = self.start_ns + rel - rel % POSE_STEP_NS;
        if base == self.t0 {
            return;
        }
        self.t0 = base;
        if let Some(actors) = self.actors {
            // Every firing until the next begin_sequence is at most 1.1 ms after the grid point.
            let t = (base as i128 - self.start_ns as i128) as f64 * 1e-9;
            actors.spheres(t, (POSE_STEP_NS + 200_000) as f64 * 1e-9, &mut self.spheres);
        }
        let k = self.traj.eval((base - self.start_ns) as f64 * 1e-9).attached(&self.t_il);
        self.r = *k.rotation.matrix();
        self.p = k.position;
        self.v = k.velocity;
        self.a = k.acceleration;
        self.w = k.angular_velocity;
        self.al = k.angular_acceleration;
    }

    fn measure(&mut self, f: &Firing) -> Echoes {
        if self.t0 == u64::MAX || f.t_ns < self.t0 || f.t_ns - self.t0 > POSE_STEP_NS + 100_000 {
            self.begin_sequence(f.t_ns);
        }
        self.rays += 1;
        let dt = (f.t_ns as f64 - self.t0 as f64) * 1e-9;
        // Rotate by exp([w dt + alpha dt^2 / 2]) to second order, then by the grid point's rotation.
        let th = self.w * dt + self.al * (0.5 * dt * dt);
        let turn = |v: Vector3<f64>| {
            let c = th.cross(&v);
            v + c + 0.5 * th.cross(&c)
        };
        let p = self.p + self.v * dt + 0.5 * dt * dt * self.a;
        let o = self.r * turn(Vector3::from(f.origin)) + p;
        let d = (self.r * turn(Vector3::from(f.dir))).normalize();
        let ray = Ray { o: [o.x, o.y, o.z], d: [d.x, d.y, d.z] };
        let mut res = self.scene.cast(&ray, self.range.max_range, f.key);
        if let Some(actors) = self.actors {
            // The actors where they are at this firing's own time.
            let t = (f.t_ns as i128 - self.start_ns as i128) as f64 * 1e-9;
            let best = res.hit.map_or(self.range.max_range, |h| h.t);
            if let Some(h) = actors.cast_near(&ray, t, best, &mut self.hints, Some(&self.spheres)) {
                res.hit = Some(h);
                if res.partial.is_some_and(|p| p.t >= h.t) {
                    res.partial = None;
                }
            }
        }
        Echoes {
            last: res.hit.and_then(|h| self.echo(&h, ray.d, f.key, S_NOISE_LAST)),
            first: res.partial.and_then(|h| self.echo(&h, ray.d, f.key, S_NOISE_FIRST)),
        }
    }
}

/// One LiDAR scan in the core's format.
#[derive(Clone, Debug, PartialEq)]
pub struct SimScan {
    /// Scan number since the start (revolution or frame index).
    pub index: u64,
    /// Absolute time of the scan's first firing, ns; every point's `t` counts from here.
    pub start_ns: u64,
    /// Absolute time of the scan's last firing, ns.
    pub end_ns: u64,
    /// The points in firing order: LiDAR (sensor) frame at each point's firing time.
    pub points: Vec<ScanPoint>,
}

/// The firmware model behind a direct scanner.
#[derive(Clone, Debug)]
#[allow(clippy::large_enum_variant)] // one per scenario
pub enum Firmware {
    /// A Velodyne.
    Velodyne(Velodyne),
    /// An Ouster.
    Ouster(Ouster),
}

impl Firmware {
    /// The range-image layout of the direct scans: rows by elevation (row 0 highest), as the
    /// decoders number them; Velodyne columns clockwise from azimuth 0 (`columns()` per
    /// revolution: 1800 at 600 rpm, where the core's decoder uses one column per firing
    /// sequence, 1808), Ouster columns = measurement ids (staggered; the core's decoder
    /// destaggers), clockwise, with each row's column 0 at pi - beam azimuth in the sensor frame.
    /// Scans decoded from packets carry the decoder's layout instead (tests/sim_roundtrip.rs).
    pub fn layout(&self) -> RangeImageLayout {
        match self {
            Firmware::Velodyne(v) => {
                let rows = velodyne_rows(v);
                let mut l = RangeImageLayout::new(v.lasers(), v.columns(), true).expect("valid layout");
                for (laser, &row) in rows.iter().enumerate().take(v.lasers()) {
                    l.set_row(row as usize, v.elevation_deg(laser).to_radians() as f32, 0.0)
                        .expect("valid row");
                }
                l
            }
            Firmware::Ouster(o) => {
                let mut l = RangeImageLayout::new(o.beams(), o.columns(), true).expect("valid layout");
                for b in 0..o.beams() {
                    let az0 = core::f64::consts::PI - o.azimuth_deg(b).to_radians();
                    l.set_row(b, o.altitude_deg(b).to_radians() as f32, az0 as f32).expect("valid row");
                }
                l
            }
        }
    }
}

/// Row of each Velodyne laser: lasers sorted by elevation, highest first.
pub fn velodyne_rows(v: &Velodyne) -> [u16; 32] {
    let n = v.lasers();
    let mut order: [usize; 32] = core::array::from_fn(|i| i);
    order[..n].sort_by(|&a, &b| v.elevation_deg(b).total_cmp(&v.elevation_deg(a)));
    let mut rows = [0u16; 32];
    for (row, &laser) in order[..n].iter().enumerate() {
        rows[laser] = row as u16;
    }
    rows
}

/// Generates scans directly (no packets) from a firmware model and an echo source factory.
#[derive(Clone, Debug)]
pub struct DirectScanner {
    fw: Firmware,
    layout: RangeImageLayout,
    rows: [u16; 32],
    next_scan: u64,
    /// Worker threads per scan (rays are independent, so the result does not depend on it).
    pub threads: usize,
}

impl DirectScanner {
    /// A scanner over the firmware's firings.
    pub fn new(fw: Firmware) -> Self {
        let layout = fw.layout();
        let rows = match &fw {
            Firmware::Velodyne(v) => velodyne_rows(v),
            Firmware::Ouster(_) => core::array::from_fn(|i| i as u16),
        };
        Self { fw, layout, rows, next_scan: 0, threads: 1 }
    }

    /// The range-image layout of the scans' `row`/`col`.
    pub fn layout(&self) -> &RangeImageLayout {
        &self.layout
    }

    /// The firmware model.
    pub fn firmware(&self) -> &Firmware {
        &self.fw
    }

    /// The sequence (Velodyne) or column (Ouster) range [first, end) of scan `j`.
    fn scan_units(&self, j: u64) -> (u64, u64) {
        match &self.fw {
            Firmware::Velodyne(v) => {
                // A revolution starts at the first sequence whose start is at or after j * T.
                let per_rev_ns = 60.0e9 / v.config().rpm;
                let seq = v.sequence_ns() as f64;
                let first = |j: u64| libm::ceil(j as f64 * per_rev_ns / seq - 1e-9) as u64;
                (first(j), first(j + 1))
            }
            Firmware::Ouster(o) => {
                let w = o.columns() as u64;
                (j * w, (j + 1) * w)
            }
        }
    }

    /// Number of firings (rays) in scan `j`.
    pub fn rays_in_scan(&self, j: u64) -> u64 {
        let (a, b) = self.scan_units(j);
        (b - a) * self.units_width() as u64
    }

    /// Absolute time of the first firing of scan `j`, ns.
    pub fn scan_start_ns(&self, j: u64) -> u64 {
        let (a, _) = self.scan_units(j);
        self.unit_time(a)
    }

    /// Absolute time of the last firing of scan `j`, ns.
    pub fn scan_end_ns(&self, j: u64) -> u64 {
        let (_, b) = self.scan_units(j);
        match &self.fw {
            Firmware::Velodyne(v) => v.sequence_time_ns(b - 1) + v.firing_offset_ns(v.lasers() - 1),
            Firmware::Ouster(o) => o.column_time_ns(b - 1),
        }
    }

    fn unit_time(&self, u: u64) -> u64 {
        match &self.fw {
            Firmware::Velodyne(v) => v.sequence_time_ns(u),
            Firmware::Ouster(o) => o.column_time_ns(u),
        }
    }

    /// Skips `n` scans.
    pub fn skip(&mut self, n: u64) {
        self.next_scan += n;
    }

    /// Index of the next scan [`Self::next`] produces.
    pub fn next_index(&self) -> u64 {
        self.next_scan
    }

    /// Generates the next scan with echo sources made by `make_src` (one per worker thread).
    pub fn next<S: EchoSource + Send>(&mut self, make_src: impl Fn() -> S + Sync) -> SimScan {
        let j = self.next_scan;
        self.next_scan += 1;
        self.scan(j, make_src)
    }

    /// Generates scan `j`.
    pub fn scan<S: EchoSource + Send>(&self, j: u64, make_src: impl Fn() -> S + Sync) -> SimScan {
        let (a, b) = self.scan_units(j);
        let start_ns = self.unit_time(a);
        let threads = self.threads.clamp(1, 64);
        let points = if threads == 1 || b - a < 64 {
            let mut src = make_src();
            let mut pts = Vec::with_capacity(((b - a) as usize) * self.units_width());
            self.fill(a, b, start_ns, &mut src, &mut pts);
            pts
        } else {
            let chunk = (b - a).div_ceil(threads as u64);
            let parts: Vec<Vec<ScanPoint>> = std::thread::scope(|s| {
                let handles: Vec<_> = (0..threads as u64)
                    .map(|t| {
                        let (ca, cb) = ((a + t * chunk).min(b), (a + (t + 1) * chunk).min(b));
                        let make_src = &make_src;
                        s.spawn(move || {
                            let mut src = make_src();
                            let mut pts = Vec::with_capacity(((cb - ca) as usize) * self.units_width());
                            self.fill(ca, cb, start_ns, &mut src, &mut pts);
                            pts
                        })
                    })
                    .collect();
                handles.into_iter().map(|h| h.join().expect("scan worker panicked")).collect()
            });
            parts.concat()
        };
        SimScan { index: j, start_ns, end_ns: self.scan_end_ns(j), points }
    }

    fn units_width(&self) -> usize {
        match &self.fw {
            Firmware::Velodyne(v) => v.lasers(),
            Firmware::Ouster(o) => o.beams(),
        }
    }

    /// Appends the points of units [a, b) (times relative to `start_ns`).
    fn fill<S: EchoSource>(&self, a: u64, b: u64, start_ns: u64, src: &mut S, out: &mut Vec<ScanPoint>) {
        for u in a..b {
            match &self.fw {
                Firmware::Velodyne(v) => {
                    src.begin_sequence(v.sequence_time_ns(u));
                    let mode = v.config().return_mode;
                    let mut seq = [Firing { t_ns: 0, key: 0, beam: 0, origin: [0.0; 3], dir: [0.0; 3] }; 32];
                    v.sequence_firings(u, &mut seq);
                    for (l, &f) in seq.iter().enumerate().take(v.lasers()) {
                        let e = src.measure(&f);
                        let row = self.rows[l];
                        let az = libm::atan2(f.dir[1], f.dir[0]);
                        let col = self.layout.column_of(row as usize, az);
                        let mut push = |echo: Option<Echo>, ret: u8| {
                            let Some(echo) = echo else { return };
                            let raw = v.quantise(echo.range);
                            if raw == 0 {
                                return;
                            }
                            let r = raw as f64 * v.distance_unit();
                            out.push(point(&f, r, start_ns, row, col, echo.reflectivity as u16, ret));
                        };
                        match mode {
                            ReturnMode::Strongest => push(e.strongest(), 0),
                            ReturnMode::Last => push(e.last_echo(), 0),
                            ReturnMode::Dual => {
                                let (s, other) = dual_order(&e);
                                push(s, 0);
                                push(other, 1);
                            }
                        }
                    }
                }
                Firmware::Ouster(o) => {
                    let t = o.column_time_ns(u);
                    src.begin_sequence(t);
                    let col = (u % o.columns() as u64) as u16;
                    let (ct, st) = o.encoder_cos_sin(u);
                    for beam in 0..o.beams() {
                        let f = o.firing_at(u, beam, ct, st);
                        let Some(e) = src.measure(&f).strongest() else { continue };
                        let r_mm = libm::round((e.range + super::ouster::BEAM_ORIGIN_M) * 1000.0);
                        if !(1.0..=524_287.0).contains(&r_mm) {
                            continue;
                        }
                        let d = r_mm * 1e-3 - super::ouster::BEAM_ORIGIN_M;
                        out.push(point(&f, d, start_ns, beam as u16, col, e.reflectivity as u16, 0));
                    }
                }
            }
        }
    }
}

/// The two echoes of a dual return, strongest first.
fn dual_order(e: &Echoes) -> (Option<Echo>, Option<Echo>) {
    match (e.first, e.last) {
        (Some(f), Some(l)) => {
            if f.strength > l.strength {
                (Some(f), Some(l))
            } else {
                (Some(l), Some(f))
            }
        }
        (f, l) => (l.or(f), None),
    }
}

fn point(f: &Firing, r: f64, start_ns: u64, row: u16, col: u16, intensity: u16, ret: u8) -> ScanPoint {
    ScanPoint {
        xyz: [
            (f.origin[0] + r * f.dir[0]) as f32,
            (f.origin[1] + r * f.dir[1]) as f32,
            (f.origin[2] + r * f.dir[2]) as f32,
        ],
        t: ((f.t_ns - start_ns) as f64 * 1e-9) as f32,
        row,
        col,
        intensity,
        ret,
        flags: 0,
    }
}
