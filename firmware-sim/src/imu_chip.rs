//! A simulated TDK InvenSense ICM-42688-P 6-axis MEMS IMU: its noise, its bias drift and its
//! register interface, behind an `embedded-hal` 1.0 I2C bus ([`MockI2c`]).
//!
//! # Noise model (ICM-42688-P datasheet DS-000347, rev. 1.7)
//!
//! | figure | datasheet | SI value used |
//! |---|---|---|
//! | gyroscope rate noise spectral density | 0.0028 deg/s/sqrt(Hz) | 4.887e-5 rad/s/sqrt(Hz) |
//! | accelerometer noise spectral density (low-noise mode) | 70 ug/sqrt(Hz) | 6.865e-4 m/s^2/sqrt(Hz) |
//! | gyroscope zero-rate-output change over temperature | +-0.005 deg/s/degC | see bias random walk |
//! | accelerometer zero-g level change over temperature | +-0.15 mg/degC | see bias random walk |
//!
//! The datasheet gives no bias random walk (consumer MEMS datasheets rarely do). It is derived
//! from the temperature coefficients above, for a board whose temperature wanders by 1 degC
//! (1 sigma) over 100 s: sigma_bw = coefficient * 1 degC / sqrt(100 s), i.e. 8.73e-6 rad/s^2/sqrt(Hz)
//! for the gyroscope and 1.47e-4 m/s^3/sqrt(Hz) for the accelerometer. The turn-on biases
//! are drawn once per seed with sigma 0.1 deg/s and 5 mg (a factory-trimmed part after
//! assembly; the datasheet's untrimmed tolerances are +-0.5 deg/s and +-20 mg).
//!
//! Discretisation (the Kalibr/Allan convention): at output data rate f a sample carries white
//! noise of sigma = density * sqrt(f) and the bias takes a step of sigma_bw / sqrt(f).
//! Samples are then quantised to the 16-bit registers for the configured full scale (with
//! saturation), as the real part does.
//!
//! # Registers (bank 0)
//! `WHO_AM_I` (0x75) = 0x47; `PWR_MGMT0` (0x4E) turns the sensors on (low-noise mode 0b11 per
//! sensor); `GYRO_CONFIG0` (0x4F) and `ACCEL_CONFIG0` (0x50) hold the full scale (bits 7:5) and
//! output data rate (bits 3:0); `INT_STATUS` (0x2D) bit 3 is data-ready, cleared on read;
//! `TEMP_DATA1..GYRO_DATA_Z0` (0x1D-0x2A) are big-endian 16-bit temperature, accelerometer and
//! gyroscope outputs, read in one burst (the address auto-increments). Sensors that are off
//! read -32768.

use embedded_hal::i2c::{ErrorKind, ErrorType, I2c, NoAcknowledgeSource, Operation, SevenBitAddress};
use loglio_core::imu::ImuNoise;

use crate::rng::SplitMix64;

/// I2C address with AP_AD0 low.
pub const I2C_ADDRESS: u8 = 0x68;
/// Register addresses.
pub mod reg {
    /// Device configuration (bit 0: soft reset).
    pub const DEVICE_CONFIG: u8 = 0x11;
    /// Temperature, high byte (the burst starts here).
    pub const TEMP_DATA1: u8 = 0x1D;
    /// Accelerometer X, high byte.
    pub const ACCEL_DATA_X1: u8 = 0x1F;
    /// Gyroscope X, high byte.
    pub const GYRO_DATA_X1: u8 = 0x25;
    /// Interrupt status (bit 3: data ready), cleared on read.
    pub const INT_STATUS: u8 = 0x2D;
    /// Power management.
    pub const PWR_MGMT0: u8 = 0x4E;
    /// Gyroscope full scale and output data rate.
    pub const GYRO_CONFIG0: u8 = 0x4F;
    /// Accelerometer full scale and output data rate.
    pub const ACCEL_CONFIG0: u8 = 0x50;
    /// Identity.
    pub const WHO_AM_I: u8 = 0x75;
    /// Register bank selection.
    pub const REG_BANK_SEL: u8 = 0x76;
}
/// `WHO_AM_I` value.
pub const WHO_AM_I: u8 = 0x47;
/// `INT_STATUS` data-ready bit.
pub const DATA_RDY: u8 = 1 << 3;

/// The chip's noise: its densities (the figures the filter models, so one type for both) and
/// its turn-on biases, drawn once per seed.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ChipNoise {
    /// White noise and bias random walk densities, SI units.
    pub density: ImuNoise,
    /// Standard deviation of the turn-on gyroscope bias, rad/s.
    pub gyro_bias_init: f64,
    /// Standard deviation of the turn-on accelerometer bias, m/s^2.
    pub accel_bias_init: f64,
}

impl ChipNoise {
    /// The ICM-42688-P figures (see the module documentation).
    pub const fn icm42688p() -> Self {
        const DEG: f64 = core::f64::consts::PI / 180.0;
        const G: f64 = 9.80665;
        Self {
            density: ImuNoise {
                gyro: 0.0028 * DEG,
                acc: 70e-6 * G,
                gyro_bias_walk: 0.005 * DEG / 10.0,
                acc_bias_walk: 0.15e-3 * G / 10.0,
            },
            gyro_bias_init: 0.1 * DEG,
            accel_bias_init: 5e-3 * G,
        }
    }

    /// A perfect IMU (quantisation remains).
    pub const fn none() -> Self {
        Self {
            density: ImuNoise { gyro: 0.0, acc: 0.0, gyro_bias_walk: 0.0, acc_bias_walk: 0.0 },
            gyro_bias_init: 0.0,
            accel_bias_init: 0.0,
        }
    }
}

/// Gyroscope full scale (`GYRO_FS_SEL`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GyroFs {
    /// +-2000 deg/s
    Dps2000 = 0,
    /// +-1000 deg/s
    Dps1000 = 1,
    /// +-500 deg/s
    Dps500 = 2,
    /// +-250 deg/s
    Dps250 = 3,
    /// +-125 deg/s
    Dps125 = 4,
}

impl GyroFs {
    /// The full scale of `dps` deg/s (125, 250, 500, 1000 or 2000).
    pub fn from_dps(dps: u32) -> Option<Self> {
        [Self::Dps2000, Self::Dps1000, Self::Dps500, Self::Dps250, Self::Dps125]
            .into_iter()
            .find(|f| f.dps() == dps)
    }

    /// The full scale, deg/s.
    pub fn dps(&self) -> u32 {
        2000 >> (*self as u32)
    }
}

/// Accelerometer full scale (`ACCEL_FS_SEL`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AccelFs {
    /// +-16 g
    G16 = 0,
    /// +-8 g
    G8 = 1,
    /// +-4 g
    G4 = 2,
    /// +-2 g
    G2 = 3,
}

impl AccelFs {
    /// The full scale of `g` g (2, 4, 8 or 16).
    pub fn from_g(g: u32) -> Option<Self> {
        [Self::G16, Self::G8, Self::G4, Self::G2].into_iter().find(|f| f.g() == g)
    }

    /// The full scale, g.
    pub fn g(&self) -> u32 {
        16 >> (*self as u32)
    }
}

/// Output data rate (`GYRO_ODR`/`ACCEL_ODR` codes).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Odr {
    /// 1 kHz
    Hz1000 = 6,
    /// 200 Hz
    Hz200 = 7,
    /// 100 Hz
    Hz100 = 8,
    /// 500 Hz
    Hz500 = 15,
}

impl Odr {
    /// Samples per second.
    pub fn hz(&self) -> u32 {
        match self {
            Odr::Hz1000 => 1000,
            Odr::Hz200 => 200,
            Odr::Hz100 => 100,
            Odr::Hz500 => 500,
        }
    }

    /// From samples per second.
    pub fn from_hz(hz: u32) -> Option<Odr> {
        [Odr::Hz100, Odr::Hz200, Odr::Hz500, Odr::Hz1000].into_iter().find(|o| o.hz() == hz)
    }
}

/// Radians per second per LSB of a gyroscope full-scale code (32768 LSB = full scale).
pub fn gyro_lsb(fs_code: u8) -> f64 {
    let dps = 2000.0 / (1u32 << (fs_code & 7)) as f64;
    dps / 32768.0 * core::f64::consts::PI / 180.0
}

/// m/s^2 per LSB of an accelerometer full-scale code.
pub fn accel_lsb(fs_code: u8) -> f64 {
    let g = 16.0 / (1u32 << (fs_code & 3)) as f64;
    g / 32768.0 * 9.80665
}

/// The simulated chip.
#[derive(Clone, Debug)]
pub struct Icm42688 {
    regs: [u8; 128],
    ptr: u8,
    noise: ChipNoise,
    rng: SplitMix64,
    gyro_bias: [f64; 3],
    accel_bias: [f64; 3],
    /// Samples latched.
    pub samples: u64,
}

impl Icm42688 {
    /// A chip after power-on, with turn-on biases drawn from `seed`.
    pub fn new(noise: ChipNoise, seed: u64) -> Self {
        let mut rng = SplitMix64::new(seed, 0x01C4_2688);
        let gyro_bias = core::array::from_fn(|_| rng.gauss() * noise.gyro_bias_init);
        let accel_bias = core::array::from_fn(|_| rng.gauss() * noise.accel_bias_init);
        let mut c = Self { regs: [0; 128], ptr: 0, noise, rng, gyro_bias, accel_bias, samples: 0 };
        c.reset();
        c
    }

    fn reset(&mut self) {
        self.regs = [0; 128];
        self.regs[reg::WHO_AM_I as usize] = WHO_AM_I;
        self.regs[reg::GYRO_CONFIG0 as usize] = 0x06;
        self.regs[reg::ACCEL_CONFIG0 as usize] = 0x06;
        for a in reg::ACCEL_DATA_X1..=0x2A {
            self.regs[a as usize] = if (a - reg::ACCEL_DATA_X1).is_multiple_of(2) { 0x80 } else { 0x00 };
        }
    }

    /// The current turn-on plus drifted biases (gyro rad/s, accel m/s^2).
    pub fn biases(&self) -> ([f64; 3], [f64; 3]) {
        (self.gyro_bias, self.accel_bias)
    }

    /// The configured output data rate, Hz (gyroscope ODR code).
    pub fn odr_hz(&self) -> Option<u32> {
        let code = self.regs[reg::GYRO_CONFIG0 as usize] & 0x0F;
        [Odr::Hz100, Odr::Hz200, Odr::Hz500, Odr::Hz1000]
            .into_iter()
            .find(|o| *o as u8 == code)
            .map(|o| o.hz())
    }

    /// Rad/s per LSB at the configured full scale.
    pub fn gyro_lsb(&self) -> f64 {
        gyro_lsb(self.regs[reg::GYRO_CONFIG0 as usize] >> 5)
    }

    /// m/s^2 per LSB at the configured full scale.
    pub fn accel_lsb(&self) -> f64 {
        accel_lsb(self.regs[reg::ACCEL_CONFIG0 as usize] >> 5)
    }

    /// Latches one output sample: the true angular rate (rad/s) and specific force (m/s^2) at
    /// the sampling instant. Noise, biases (with their random walk over one sample period) and
    /// quantisation are applied; the data-ready flag is set. Returns the raw (gyro, accel)
    /// register values.
    pub fn sample(&mut self, gyro: [f64; 3], accel: [f64; 3]) -> ([i16; 3], [i16; 3]) {
        let hz = self.odr_hz().unwrap_or(1000) as f64;
        let pm = self.regs[reg::PWR_MGMT0 as usize];
        let (gyro_on, accel_on) = (pm & 0x0C == 0x0C, pm & 0x03 == 0x03);
        let n = self.noise;
        let sq = libm::sqrt(hz);
        let (glsb, alsb) = (self.gyro_lsb(), self.accel_lsb());
        let mut g = [i16::MIN; 3];
        let mut a = [i16::MIN; 3];
        for i in 0..3 {
            self.gyro_bias[i] += n.density.gyro_bias_walk / sq * self.rng.gauss();
            self.accel_bias[i] += n.density.acc_bias_walk / sq * self.rng.gauss();
            let gm = gyro[i] + self.gyro_bias[i] + n.density.gyro * sq * self.rng.gauss();
            let am = accel[i] + self.accel_bias[i] + n.density.acc * sq * self.rng.gauss();
            if gyro_on {
                g[i] = quantise(gm / glsb);
            }
            if accel_on {
                a[i] = quantise(am / alsb);
            }
        }
        // 30 degC: TEMP_DATA = (T - 25) * 132.48.
        let temp = (5.0 * 132.48) as i16;
        let mut w = |r: u8, v: i16| self.regs[r as usize..r as usize + 2].copy_from_slice(&v.to_be_bytes());
        w(reg::TEMP_DATA1, temp);
        for i in 0..3 {
            w(reg::ACCEL_DATA_X1 + 2 * i as u8, a[i]);
            w(reg::GYRO_DATA_X1 + 2 * i as u8, g[i]);
        }
        self.regs[reg::INT_STATUS as usize] |= DATA_RDY;
        self.samples += 1;
        (g, a)
    }

    /// A register read as the host sees it (with read side effects).
    pub fn read_reg(&mut self, addr: u8) -> u8 {
        let a = (addr & 0x7F) as usize;
        let v = self.regs[a];
        if addr == reg::INT_STATUS {
            self.regs[a] &= !DATA_RDY;
        }
        v
    }

    /// A register write as the host does it. Read-only registers ignore writes.
    pub fn write_reg(&mut self, addr: u8, value: u8) {
        match addr {
            reg::DEVICE_CONFIG if value & 1 != 0 => self.reset(),
            reg::PWR_MGMT0 | reg::GYRO_CONFIG0 | reg::ACCEL_CONFIG0 | reg::REG_BANK_SEL => {
                self.regs[addr as usize] = value
            }
            _ => {}
        }
    }
}

fn quantise(x: f64) -> i16 {
    let r = libm::round(x);
    if r >= 32767.0 {
        32767
    } else if r <= -32768.0 {
        -32768
    } else {
        r as i16
    }
}

/// Error of the mock bus.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BusError {
    /// Nobody answered at that address.
    NoDevice,
}

impl embedded_hal::i2c::Error for BusError {
    fn kind(&self) -> ErrorKind {
        ErrorKind::NoAcknowledge(NoAcknowledgeSource::Address)
    }
}

/// An I2C bus with one ICM-42688-P on it. Writes set the register pointer (first byte) and
/// write registers; reads return registers from the pointer on, auto-incrementing. The bus owns
/// the chip; the simulation reaches it through [`MockI2c::chip_mut`] to latch samples (what the
/// chip's own clock does on real hardware).
#[derive(Clone, Debug)]
pub struct MockI2c {
    chip: Icm42688,
    address: u8,
    /// Transactions served.
    pub transactions: u64,
}

impl MockI2c {
    /// A bus with `chip` at `address`.
    pub fn new(chip: Icm42688, address: u8) -> Self {
        Self { chip, address, transactions: 0 }
    }

    /// The chip.
    pub fn chip(&self) -> &Icm42688 {
        &self.chip
    }

    /// The chip, to latch samples.
    pub fn chip_mut(&mut self) -> &mut Icm42688 {
        &mut self.chip
    }
}

impl ErrorType for MockI2c {
    type Error = BusError;
}

impl I2c<SevenBitAddress> for MockI2c {
    fn transaction(&mut self, address: u8, operations: &mut [Operation<'_>]) -> Result<(), Self::Error> {
        if address != self.address {
            return Err(BusError::NoDevice);
        }
        self.transactions += 1;
        let chip = &mut self.chip;
        for op in operations {
            match op {
                Operation::Write(bytes) => {
                    if let Some((&first, rest)) = bytes.split_first() {
                        chip.ptr = first;
                        for &b in rest {
                            let p = chip.ptr;
                            chip.write_reg(p, b);
                            chip.ptr = p.wrapping_add(1) & 0x7F;
                        }
                    }
                }
                Operation::Read(buf) => {
                    for b in buf.iter_mut() {
                        let p = chip.ptr;
                        *b = chip.read_reg(p);
                        chip.ptr = p.wrapping_add(1) & 0x7F;
                    }
                }
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn registers_identity_config_and_burst() {
        let mut bus = MockI2c::new(Icm42688::new(ChipNoise::none(), 1), I2C_ADDRESS);
        let mut id = [0u8];
        bus.write_read(I2C_ADDRESS, &[reg::WHO_AM_I], &mut id).unwrap();
        assert_eq!(id[0], WHO_AM_I);
        assert_eq!(bus.write_read(0x69, &[reg::WHO_AM_I], &mut id), Err(BusError::NoDevice));
        // Sensors off: outputs read -32768.
        bus.chip_mut().sample([0.1, 0.0, 0.0], [0.0, 0.0, 9.8]);
        let mut burst = [0u8; 14];
        bus.write_read(I2C_ADDRESS, &[reg::TEMP_DATA1], &mut burst).unwrap();
        assert_eq!(i16::from_be_bytes([burst[2], burst[3]]), i16::MIN);
        // +-500 deg/s, +-4 g, 200 Hz, low-noise mode.
        bus.write(I2C_ADDRESS, &[reg::GYRO_CONFIG0, (GyroFs::Dps500 as u8) << 5 | Odr::Hz200 as u8]).unwrap();
        bus.write(I2C_ADDRESS, &[reg::ACCEL_CONFIG0, (AccelFs::G4 as u8) << 5 | Odr::Hz200 as u8]).unwrap();
        bus.write(I2C_ADDRESS, &[reg::PWR_MGMT0, 0x0F]).unwrap();
        assert_eq!(bus.chip().odr_hz(), Some(200));
        let (g, a) = bus.chip_mut().sample([0.1, -0.2, 3.0], [1.0, -2.0, 9.80665]);
        let mut st = [0u8];
        bus.write_read(I2C_ADDRESS, &[reg::INT_STATUS], &mut st).unwrap();
        assert_eq!(st[0] & DATA_RDY, DATA_RDY);
        bus.write_read(I2C_ADDRESS, &[reg::INT_STATUS], &mut st).unwrap();
        assert_eq!(st[0] & DATA_RDY, 0, "cleared on read");
        bus.write_read(I2C_ADDRESS, &[reg::TEMP_DATA1], &mut burst).unwrap();
        let rd = |i: usize| i16::from_be_bytes([burst[i], burst[i + 1]]);
        assert_eq!([rd(2), rd(4), rd(6)], a);
        assert_eq!([rd(8), rd(10), rd(12)], g);
        // Exact quantisation without noise: 500/32768 deg/s and 4/32768 g per LSB.
        let glsb = 500.0 / 32768.0 * core::f64::consts::PI / 180.0;
        assert_eq!(g[2], libm::round(3.0 / glsb) as i16);
        assert_eq!(a[2], libm::round(9.80665 / (4.0 / 32768.0 * 9.80665)) as i16);
        // Saturation: 600 deg/s clips at +32767.
        let (g, _) = bus.chip_mut().sample([10.5, -10.5, 0.0], [0.0; 3]);
        assert_eq!((g[0], g[1]), (32767, -32768));
    }

    #[test]
    fn white_noise_and_bias_walk_have_datasheet_statistics() {
        let noise = ChipNoise { gyro_bias_init: 0.0, accel_bias_init: 0.0, ..ChipNoise::icm42688p() };
        let mut chip = Icm42688::new(noise, 9);
        chip.write_reg(reg::GYRO_CONFIG0, (GyroFs::Dps250 as u8) << 5 | Odr::Hz200 as u8);
        chip.write_reg(reg::ACCEL_CONFIG0, (AccelFs::G2 as u8) << 5 | Odr::Hz200 as u8);
        chip.write_reg(reg::PWR_MGMT0, 0x0F);
        let n = 20_000;
        let (mut sg, mut sa) = (0.0, 0.0);
        for _ in 0..n {
            let (g, a) = chip.sample([0.0; 3], [0.0; 3]);
            sg += (g[0] as f64 * chip.gyro_lsb()).powi(2);
            sa += (a[1] as f64 * chip.accel_lsb()).powi(2);
        }
        // Expected sigma: density * sqrt(200 Hz) (bias walk adds < 1 % over 100 s); quantisation
        // adds lsb^2/12.
        let eg = noise.density.gyro.powi(2) * 200.0 + chip.gyro_lsb().powi(2) / 12.0;
        let ea = noise.density.acc.powi(2) * 200.0 + chip.accel_lsb().powi(2) / 12.0;
        assert!((sg / n as f64 / eg - 1.0).abs() < 0.06, "{} vs {eg}", sg / n as f64);
        assert!((sa / n as f64 / ea - 1.0).abs() < 0.06, "{} vs {ea}", sa / n as f64);
        // Bias random walk: after 100 s the bias spread over many chips is sigma_bw * 10 s^0.5.
        let mut s2 = 0.0;
        let chips = 200;
        for seed in 0..chips {
            let mut c = Icm42688::new(noise, 1000 + seed);
            c.write_reg(reg::GYRO_CONFIG0, Odr::Hz100 as u8);
            for _ in 0..10_000 {
                c.sample([0.0; 3], [0.0; 3]);
            }
            s2 += c.biases().0[2].powi(2);
        }
        let expect = noise.density.gyro_bias_walk.powi(2) * 100.0;
        assert!((s2 / chips as f64 / expect - 1.0).abs() < 0.35, "{} vs {expect}", s2 / chips as f64);
    }
}
