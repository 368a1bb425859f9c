//! Live mode: the scenario's LiDAR packets go to UDP ports on loopback and the IMU board's
//! frames to a pseudo-terminal, paced in real time (or faster), so `loglio` runs exactly as it
//! would on a vehicle: it opens the printed serial device and listens on the sensor's ports.
//!
//! The pseudo-terminal is put in raw mode (no line discipline touches the bytes) and written
//! without blocking: when nobody reads it and its buffer is full, frames are dropped and counted,
//! and the LiDAR stream is never held up.

use std::io;
use std::net::{Ipv4Addr, SocketAddr, UdpSocket};
use std::os::fd::OwnedFd;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use rustix::fs::{Mode, OFlags};
use rustix::pty::OpenptFlags;
use rustix::termios::OptionalActions;

use crate::scenario::Scenario;
use crate::stream::{Wire, WireEvent, WireStream};

/// A pseudo-terminal pair: the simulator writes the master; the host opens the slave's path.
#[derive(Debug)]
pub struct Pty {
    master: OwnedFd,
    /// Kept open so the line stays up while no reader is attached.
    slave: OwnedFd,
    /// Path of the slave device (e.g. /dev/pts/7).
    pub path: PathBuf,
}

impl Pty {
    /// Opens a pseudo-terminal in raw mode with a non-blocking master.
    pub fn open() -> io::Result<Pty> {
        let master = rustix::pty::openpt(OpenptFlags::RDWR | OpenptFlags::NOCTTY)?;
        rustix::pty::grantpt(&master)?;
        rustix::pty::unlockpt(&master)?;
        let name = rustix::pty::ptsname(&master, Vec::new())?;
        let path = PathBuf::from(name.to_string_lossy().into_owned());
        let slave = rustix::fs::open(&path, OFlags::RDWR | OFlags::NOCTTY | OFlags::NONBLOCK, Mode::empty())?;
        let mut t = rustix::termios::tcgetattr(&slave)?;
        t.make_raw();
        rustix::termios::tcsetattr(&slave, OptionalActions::Now, &t)?;
        let fl = rustix::fs::fcntl_getfl(&master)?;
        rustix::fs::fcntl_setfl(&master, fl | OFlags::NONBLOCK)?;
        Ok(Pty { master, slave, path })
    }

    /// Waits (at most `timeout`) until a reader has taken every byte written so far; closing
    /// the master earlier would discard them.
    pub fn wait_drained(&self, timeout: Duration) {
        let t = Instant::now();
        while t.elapsed() < timeout && rustix::io::ioctl_fionread(&self.slave).is_ok_and(|n| n > 0) {
            std::thread::sleep(Duration::from_millis(2));
        }
    }

    /// Writes `bytes` without blocking; returns false if the line is full (nothing written, or
    /// a partial frame that nobody read within 20 ms: the reader's decoder drops it and
    /// resynchronises at the next delimiter).
    pub fn try_write(&self, bytes: &[u8]) -> io::Result<bool> {
        let mut rest = bytes;
        let mut waited = Duration::ZERO;
        while !rest.is_empty() {
            match rustix::io::write(&self.master, rest) {
                Ok(n) => rest = &rest[n..],
                Err(rustix::io::Errno::AGAIN) if rest.len() == bytes.len() => return Ok(false),
                // A partial frame was written: finish it (briefly) so the stream stays framed,
                // but never wait on a line nobody reads.
                Err(rustix::io::Errno::AGAIN) if waited < Duration::from_millis(20) => {
                    std::thread::sleep(Duration::from_micros(200));
                    waited += Duration::from_micros(200);
                }
                Err(rustix::io::Errno::AGAIN) => return Ok(false),
                Err(e) => return Err(e.into()),
            }
        }
        Ok(true)
    }
}

/// Live-mode settings.
#[derive(Clone, Debug, PartialEq)]
pub struct LiveConfig {
    /// Where to send the UDP datagrams.
    pub host: Ipv4Addr,
    /// Speed-up over real time (1 = real time); 0 sends as fast as possible.
    pub rate: f64,
    /// Optional symlink to create pointing at the pseudo-terminal.
    pub pty_link: Option<PathBuf>,
    /// Port offset added to every destination port (to run several simulators at once).
    pub port_offset: u16,
}

/// What live mode sent.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LiveStats {
    /// UDP datagrams sent.
    pub datagrams: u64,
    /// IMU frames written to the pseudo-terminal.
    pub imu_frames: u64,
    /// IMU frames dropped because nobody read the pseudo-terminal.
    pub imu_dropped: u64,
    /// Largest lateness behind the schedule, microseconds.
    pub max_late_us: u64,
}

/// Runs a scenario live. `on_ready` is called with the pseudo-terminal path before the first
/// byte is sent.
pub fn run(sc: &Scenario, cfg: &LiveConfig, on_ready: impl FnOnce(&Pty)) -> anyhow::Result<LiveStats> {
    run_events(WireStream::new(sc), sc.start_ns(), cfg, on_ready)
}

/// Sends any wire stream live (e.g. a scenario's through `fault::FaultInjector`), paced from
/// `t0_ns`. An event stamped more than a second after the one before it (a wrong stamp, not a
/// pause: a real pause leaves no events) goes out at once instead of holding the stream back.
pub fn run_events(
    events: impl Iterator<Item = WireEvent>,
    t0_ns: u64,
    cfg: &LiveConfig,
    on_ready: impl FnOnce(&Pty),
) -> anyhow::Result<LiveStats> {
    let pty = Pty::open()?;
    if let Some(link) = &cfg.pty_link {
        let _ = std::fs::remove_file(link);
        std::os::unix::fs::symlink(&pty.path, link)?;
    }
    let sock = UdpSocket::bind(SocketAddr::from((Ipv4Addr::LOCALHOST, 0)))?;
    on_ready(&pty);
    let mut stats = LiveStats::default();
    let t0_wall = Instant::now();
    let mut clock = t0_ns;
    for ev in events {
        if ev.t_ns <= clock.saturating_add(1_000_000_000) {
            clock = clock.max(ev.t_ns);
        }
        if cfg.rate > 0.0 {
            let due = Duration::from_secs_f64(clock.saturating_sub(t0_ns) as f64 * 1e-9 / cfg.rate);
            let now = t0_wall.elapsed();
            if due > now {
                std::thread::sleep(due - now);
            } else {
                stats.max_late_us = stats.max_late_us.max((now - due).as_micros() as u64);
            }
        }
        match ev.wire {
            Wire::Udp { port, payload } => {
                sock.send_to(&payload, SocketAddr::from((cfg.host, port.wrapping_add(cfg.port_offset))))?;
                stats.datagrams += 1;
            }
            Wire::Serial(bytes) => {
                if pty.try_write(&bytes)? {
                    stats.imu_frames += 1;
                } else {
                    stats.imu_dropped += 1;
                }
            }
        }
    }
    // Give a reader the chance to take the last frames before the line goes down.
    pty.wait_drained(Duration::from_secs(1));
    if let Some(link) = &cfg.pty_link {
        let _ = std::fs::remove_file(link);
    }
    Ok(stats)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pty_carries_raw_bytes() {
        let pty = Pty::open().unwrap();
        // Bytes a line discipline would change (CR, NL, ^C, ^D, DEL) must arrive untouched.
        let data: Vec<u8> = vec![0x0D, 0x0A, 0x03, 0x04, 0x7F, 0x00, 0x11, 0x13, 0xFF, 0x1A];
        let reader = rustix::fs::open(&pty.path, OFlags::RDWR | OFlags::NOCTTY, Mode::empty()).unwrap();
        assert!(pty.try_write(&data).unwrap());
        let mut got = [0u8; 64];
        let mut n = 0;
        let t = Instant::now();
        while n < data.len() && t.elapsed() < Duration::from_secs(2) {
            n += rustix::io::read(&reader, &mut got[n..]).unwrap();
        }
        assert_eq!(&got[..n], &data[..]);
    }

    #[test]
    fn a_line_nobody_reads_never_blocks_the_writer() {
        let pty = Pty::open().unwrap();
        // Odd-sized frames until the line is full: the writer must come back each time, with
        // a partial frame at the end at worst.
        let frame = [0x5Au8; 37];
        let mut refused = 0;
        for _ in 0..10_000 {
            if !pty.try_write(&frame).unwrap() {
                refused += 1;
            }
        }
        assert!(refused > 0);
    }
}
