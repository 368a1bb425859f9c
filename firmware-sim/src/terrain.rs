//! Uneven ground as a closed-form height function z = h(x, y).
//!
//! The ground is a tilted plane plus a sum of plane waves (long hills, medium undulations and
//! short bumps), so its height, gradient and their time derivatives along a path are exact
//! (see [`crate::jet`]). The vehicle rides on this function; the ray caster triangulates the same
//! function on a 1 m grid (`raycast::Heightfield`), which stays within a few millimetres of it.

use crate::jet::Jet;

/// One plane wave a * sin(kx * x + ky * y + phase).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Wave {
    /// Amplitude, metres.
    pub amplitude: f64,
    /// Wave vector x component, rad/m.
    pub kx: f64,
    /// Wave vector y component, rad/m.
    pub ky: f64,
    /// Phase, rad.
    pub phase: f64,
}

impl Wave {
    /// A wave of the given amplitude and wavelength travelling along `heading_deg`.
    pub fn new(amplitude: f64, wavelength: f64, heading_deg: f64, phase: f64) -> Self {
        let k = core::f64::consts::TAU / wavelength;
        let h = heading_deg.to_radians();
        Self { amplitude, kx: k * libm::cos(h), ky: k * libm::sin(h), phase }
    }
}

/// Most waves a terrain holds.
pub const MAX_WAVES: usize = 8;

/// The ground: z = z0 + gx x + gy y + sum of waves.
#[derive(Clone, Debug, PartialEq)]
pub struct Terrain {
    /// Height at the origin without waves, metres.
    pub z0: f64,
    /// Constant slope along x (rise per metre).
    pub gx: f64,
    /// Constant slope along y.
    pub gy: f64,
    waves: [Wave; MAX_WAVES],
    n: usize,
}

impl Terrain {
    /// Flat ground at height `z0`.
    pub const fn flat(z0: f64) -> Self {
        Self {
            z0,
            gx: 0.0,
            gy: 0.0,
            waves: [Wave { amplitude: 0.0, kx: 0.0, ky: 0.0, phase: 0.0 }; MAX_WAVES],
            n: 0,
        }
    }

    /// The town's rolling ground: grades up to about 9 % and 1.5 cm road bumps.
    pub fn town() -> Self {
        let mut t = Self::flat(0.0);
        t.gx = 0.015;
        t.gy = 0.010;
        for w in [
            Wave::new(1.2, 170.0, 20.0, 0.3),
            Wave::new(0.8, 110.0, 100.0, 1.1),
            Wave::new(0.35, 61.0, 45.0, 2.0),
            Wave::new(0.015, 7.3, 0.0, 0.0),
            Wave::new(0.015, 9.1, 90.0, 0.5),
        ] {
            t.push(w);
        }
        t
    }

    /// Adds a wave; ignored when [`MAX_WAVES`] are already present.
    pub fn push(&mut self, w: Wave) {
        if self.n < MAX_WAVES {
            self.waves[self.n] = w;
            self.n += 1;
        }
    }

    /// The waves.
    pub fn waves(&self) -> &[Wave] {
        &self.waves[..self.n]
    }

    /// Height at (x, y).
    pub fn height(&self, x: f64, y: f64) -> f64 {
        let mut z = self.z0 + self.gx * x + self.gy * y;
        for w in self.waves() {
            z += w.amplitude * libm::sin(w.kx * x + w.ky * y + w.phase);
        }
        z
    }

    /// Height and gradient (dz/dx, dz/dy) along a path given as jets of time.
    pub fn height_jet(&self, x: Jet, y: Jet) -> (Jet, Jet, Jet) {
        let mut z = Jet::c(self.z0) + x * self.gx + y * self.gy;
        let mut gx = Jet::c(self.gx);
        let mut gy = Jet::c(self.gy);
        for w in self.waves() {
            let arg = x * w.kx + y * w.ky + w.phase;
            let (s, c) = (arg.sin(), arg.cos());
            z = z + s * w.amplitude;
            gx = gx + c * (w.amplitude * w.kx);
            gy = gy + c * (w.amplitude * w.ky);
        }
        (z, gx, gy)
    }

    /// Largest |h| minus the plane part, an upper bound used to size ray-casting bounds.
    pub fn wave_bound(&self) -> f64 {
        self.waves().iter().map(|w| w.amplitude.abs()).sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gradient_matches_height_differences() {
        let t = Terrain::town();
        for (x, y) in [(0.0, 0.0), (13.7, -42.1), (-80.0, 55.5)] {
            let (z, gx, gy) = t.height_jet(Jet::c(x), Jet::c(y));
            assert_eq!(z.v, t.height(x, y));
            let h = 1e-5;
            let dx = (t.height(x + h, y) - t.height(x - h, y)) / (2.0 * h);
            let dy = (t.height(x, y + h) - t.height(x, y - h)) / (2.0 * h);
            assert!((gx.v - dx).abs() < 1e-8 && (gy.v - dy).abs() < 1e-8);
        }
    }
}
