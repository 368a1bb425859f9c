//! The IMU board's firmware: reads an ICM-42688-P over I2C, timestamps each sample and sends it
//! as a loglio serial IMU frame (`loglio_core::sensor::imu_frame`).
//!
//! Written against the `embedded-hal` 1.0 [`I2c`] and `embedded-io` 0.7 [`Write`] traits only,
//! `no_std` and without a heap, exactly as it would run on a microcontroller: the simulator
//! plugs in a mock bus ([`crate::imu_chip::MockI2c`]) and a byte sink (a pseudo-terminal, a
//! file, a buffer).
//!
//! Timing: the board's data-ready interrupt latches its clock when the chip signals a new
//! sample; the handler ([`ImuBoard::on_data_ready`]) reads the interrupt status and the 14-byte
//! burst (temperature, accelerometer, gyroscope), converts to SI units in f32 and writes one
//! frame. The frame's timestamp is the latched interrupt time.

use embedded_hal::i2c::I2c;
use embedded_io::Write;
use loglio_core::sensor::imu_frame::{self, FRAME_MAX, ImuFrame};

use crate::imu_chip::{AccelFs, DATA_RDY, GyroFs, Odr, WHO_AM_I, accel_lsb, gyro_lsb, reg};

/// How the board configures the chip.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BoardConfig {
    /// Gyroscope full scale.
    pub gyro_fs: GyroFs,
    /// Accelerometer full scale.
    pub accel_fs: AccelFs,
    /// Output data rate.
    pub odr: Odr,
}

impl Default for BoardConfig {
    /// +-500 deg/s (fast handheld rotation stays far from clipping), +-4 g, 200 Hz.
    fn default() -> Self {
        Self { gyro_fs: GyroFs::Dps500, accel_fs: AccelFs::G4, odr: Odr::Hz200 }
    }
}

/// What went wrong on the board.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BoardError<B, W> {
    /// The bus failed.
    Bus(B),
    /// `WHO_AM_I` was not 0x47: wrong or missing chip.
    WrongChip(u8),
    /// The interrupt fired but the chip had no new sample.
    NoData,
    /// The serial port failed.
    Serial(W),
}

impl<B: core::fmt::Debug, W: core::fmt::Debug> core::fmt::Display for BoardError<B, W> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::Bus(e) => write!(f, "I2C bus error: {e:?}"),
            Self::WrongChip(id) => write!(f, "unexpected WHO_AM_I 0x{id:02x} (want 0x47)"),
            Self::NoData => f.write_str("data-ready interrupt without new data"),
            Self::Serial(e) => write!(f, "serial write error: {e:?}"),
        }
    }
}

/// Counters of the board.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct BoardStats {
    /// Frames sent.
    pub frames: u64,
    /// Interrupts without data.
    pub empty: u64,
}

/// The IMU board.
#[derive(Debug)]
pub struct ImuBoard<B, W> {
    bus: B,
    serial: W,
    address: u8,
    seq: u32,
    gyro_scale: f32,
    accel_scale: f32,
    /// Counters.
    pub stats: BoardStats,
}

/// A serial sink that drops every byte (for generating samples without a port).
#[derive(Clone, Copy, Debug, Default)]
pub struct Discard;

impl embedded_io::ErrorType for Discard {
    type Error = core::convert::Infallible;
}

impl Write for Discard {
    fn write(&mut self, buf: &[u8]) -> Result<usize, Self::Error> {
        Ok(buf.len())
    }
    fn flush(&mut self) -> Result<(), Self::Error> {
        Ok(())
    }
}

/// Converts raw register values to SI with the board's f32 scale factors (what the frames
/// carry, bit for bit).
pub fn to_si(raw: [i16; 3], scale: f32) -> [f32; 3] {
    [raw[0] as f32 * scale, raw[1] as f32 * scale, raw[2] as f32 * scale]
}

impl<B: I2c, W: Write> ImuBoard<B, W> {
    /// A board with the chip at `address` on `bus`, sending frames to `serial`.
    pub fn new(bus: B, serial: W, address: u8) -> Self {
        Self { bus, serial, address, seq: 0, gyro_scale: 0.0, accel_scale: 0.0, stats: BoardStats::default() }
    }

    /// Checks the chip's identity, configures full scales and rate, and turns the sensors on
    /// in low-noise mode.
    pub fn init(&mut self, cfg: BoardConfig) -> Result<(), BoardError<B::Error, W::Error>> {
        let mut id = [0u8];
        self.bus.write_read(self.address, &[reg::WHO_AM_I], &mut id).map_err(BoardError::Bus)?;
        if id[0] != WHO_AM_I {
            return Err(BoardError::WrongChip(id[0]));
        }
        let g = (cfg.gyro_fs as u8) << 5 | cfg.odr as u8;
        let a = (cfg.accel_fs as u8) << 5 | cfg.odr as u8;
        self.bus.write(self.address, &[reg::GYRO_CONFIG0, g, a]).map_err(BoardError::Bus)?;
        self.bus.write(self.address, &[reg::PWR_MGMT0, 0x0F]).map_err(BoardError::Bus)?;
        self.gyro_scale = gyro_lsb(cfg.gyro_fs as u8) as f32;
        self.accel_scale = accel_lsb(cfg.accel_fs as u8) as f32;
        Ok(())
    }

    /// f32 scale factors (rad/s per LSB, m/s^2 per LSB) after [`Self::init`].
    pub fn scales(&self) -> (f32, f32) {
        (self.gyro_scale, self.accel_scale)
    }

    /// The data-ready interrupt handler: `t_ns` is the board clock latched by the interrupt.
    /// Reads the sample, sends its frame and returns it.
    pub fn on_data_ready(&mut self, t_ns: u64) -> Result<ImuFrame, BoardError<B::Error, W::Error>> {
        let mut st = [0u8];
        self.bus.write_read(self.address, &[reg::INT_STATUS], &mut st).map_err(BoardError::Bus)?;
        if st[0] & DATA_RDY == 0 {
            self.stats.empty += 1;
            return Err(BoardError::NoData);
        }
        let mut b = [0u8; 14];
        self.bus.write_read(self.address, &[reg::TEMP_DATA1], &mut b).map_err(BoardError::Bus)?;
        let rd = |i: usize| i16::from_be_bytes([b[i], b[i + 1]]);
        let frame = ImuFrame {
            seq: self.seq,
            t_ns,
            gyro: to_si([rd(8), rd(10), rd(12)], self.gyro_scale),
            acc: to_si([rd(2), rd(4), rd(6)], self.accel_scale),
        };
        self.seq = self.seq.wrapping_add(1);
        let mut out = [0u8; FRAME_MAX];
        // The frame always fits FRAME_MAX by construction.
        let n = imu_frame::encode(&frame, &mut out).unwrap_or(0);
        self.serial.write_all(&out[..n]).map_err(BoardError::Serial)?;
        self.stats.frames += 1;
        Ok(frame)
    }

    /// The bus (the simulation reaches the chip through it).
    pub fn bus_mut(&mut self) -> &mut B {
        &mut self.bus
    }

    /// The serial sink (e.g. to inspect what was sent).
    pub fn serial(&mut self) -> &mut W {
        &mut self.serial
    }

    /// Gives the bus and the serial sink back.
    pub fn release(self) -> (B, W) {
        (self.bus, self.serial)
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use std::vec::Vec;

    use loglio_core::sensor::imu_frame::FrameDecoder;

    use super::*;
    use crate::imu_chip::{ChipNoise, I2C_ADDRESS, Icm42688, MockI2c};

    #[test]
    fn frames_round_trip_through_the_core_decoder() {
        let mut board = ImuBoard::new(
            MockI2c::new(Icm42688::new(ChipNoise::icm42688p(), 3), I2C_ADDRESS),
            Vec::new(),
            I2C_ADDRESS,
        );
        board.init(BoardConfig::default()).unwrap();
        assert_eq!(board.bus_mut().chip().odr_hz(), Some(200));
        let mut sent = Vec::new();
        let mut raws = Vec::new();
        for k in 0..500u64 {
            let t = k as f64 * 0.005;
            let raw =
                board.bus_mut().chip_mut().sample([libm::sin(t), 0.2, -3.0 * t], [0.3, libm::cos(t), 9.8]);
            raws.push(raw);
            sent.push(board.on_data_ready(1_000_000 + k * 5_000_000).unwrap());
        }
        // An interrupt without a sample is counted, nothing is sent.
        assert_eq!(board.on_data_ready(9), Err(BoardError::NoData));
        assert_eq!(board.stats, BoardStats { frames: 500, empty: 1 });
        let (gs, as_) = board.scales();
        let (_, bytes) = board.release();
        let mut dec = FrameDecoder::new();
        let mut got = Vec::new();
        let mut rest = &bytes[..];
        while !rest.is_empty() {
            let (n, f) = dec.feed(rest);
            got.extend(f);
            rest = &rest[n..];
        }
        assert_eq!(got, sent);
        for (k, (f, (g, a))) in got.iter().zip(&raws).enumerate() {
            assert_eq!(f.seq, k as u32);
            assert_eq!(f.gyro, to_si(*g, gs));
            assert_eq!(f.acc, to_si(*a, as_));
        }
        assert_eq!(dec.stats.frames, 500);
        assert_eq!(dec.stats.seq_gaps + dec.stats.crc + dec.stats.dropped_bytes, 0);
    }

    #[test]
    fn wrong_chip_is_reported() {
        let mut board =
            ImuBoard::new(MockI2c::new(Icm42688::new(ChipNoise::none(), 3), 0x69), Vec::new(), I2C_ADDRESS);
        assert!(matches!(board.init(BoardConfig::default()), Err(BoardError::Bus(_))));
    }
}
