//! Live UDP reception of LiDAR packets with a large kernel receive buffer (socket2), so a burst
//! of packets while the odometry is busy with a scan is queued, not lost.
//!
//! A VLP-32C sends about 1.8 MB/s, an OS1-128 in the RNG19 profile about 16 MB/s: the default
//! 8 MiB buffer holds half a second of the largest. The kernel caps the size at
//! `net.core.rmem_max`; [`UdpSource::recv_buffer_size`] says what was granted and a warning is
//! logged when it is less than asked (raise it with `sysctl -w net.core.rmem_max=...`).

use socket2::{Domain, Protocol, Socket, Type};
use std::io;
use std::net::{SocketAddr, UdpSocket};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

/// The receive buffer asked for by default.
pub const DEFAULT_RCVBUF: usize = 8 << 20;

/// A bound UDP socket for one LiDAR stream.
#[derive(Debug)]
pub struct UdpSource {
    sock: UdpSocket,
    rcvbuf: usize,
}

/// Host time now, ns since 1970 (the capture time of a received datagram).
pub fn host_time_ns() -> u64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map(|d| d.as_nanos() as u64).unwrap_or(0)
}

impl UdpSource {
    /// Binds `addr` (e.g. `0.0.0.0:2368`) with a receive buffer of `rcvbuf` bytes and a read
    /// timeout. No `SO_REUSEADDR`: a port another program listens on is an error
    /// (`AddrInUse`), not two programs silently sharing (or splitting) the stream.
    pub fn bind(addr: SocketAddr, rcvbuf: usize, timeout: Duration) -> io::Result<Self> {
        let sock = Socket::new(Domain::for_address(addr), Type::DGRAM, Some(Protocol::UDP))?;
        if let Err(e) = sock.set_recv_buffer_size(rcvbuf) {
            log::warn!("udp {addr}: could not set SO_RCVBUF to {rcvbuf}: {e}");
        }
        sock.bind(&addr.into())?;
        sock.set_read_timeout(Some(timeout))?;
        let granted = sock.recv_buffer_size().unwrap_or(0);
        // Linux reports twice the usable size (bookkeeping overhead included).
        if granted < rcvbuf {
            log::warn!(
                "udp {addr}: receive buffer is {granted} bytes, less than the {rcvbuf} asked for; raise net.core.rmem_max to avoid losing LiDAR bursts"
            );
        }
        Ok(Self { sock: sock.into(), rcvbuf: granted })
    }

    /// The receive buffer the kernel granted, bytes.
    pub fn recv_buffer_size(&self) -> usize {
        self.rcvbuf
    }

    /// The bound address.
    pub fn local_addr(&self) -> io::Result<SocketAddr> {
        self.sock.local_addr()
    }

    /// Receives one datagram into `buf`: its length, sender and host receive time (ns), or
    /// `None` when the timeout passed with nothing. A datagram longer than `buf` is truncated
    /// by the kernel; the decoders then reject it by its size.
    pub fn recv(&self, buf: &mut [u8]) -> io::Result<Option<(usize, SocketAddr, u64)>> {
        match self.sock.recv_from(buf) {
            Ok((n, from)) => Ok(Some((n, from, host_time_ns()))),
            Err(e) if matches!(e.kind(), io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut) => Ok(None),
            Err(e) => Err(e),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn loopback_burst_is_received_whole() {
        let src = UdpSource::bind("127.0.0.1:0".parse().unwrap(), DEFAULT_RCVBUF, Duration::from_millis(200))
            .unwrap();
        assert!(src.recv_buffer_size() > 0);
        let to = src.local_addr().unwrap();
        let tx = UdpSocket::bind("127.0.0.1:0").unwrap();
        // A burst of 100 Velodyne-size datagrams before the receiver reads anything.
        for k in 0..100u8 {
            let mut p = [k; 1206];
            p[0] = k;
            tx.send_to(&p, to).unwrap();
        }
        let mut buf = [0u8; 65_536];
        let mut got = Vec::new();
        while let Some((n, _, t)) = src.recv(&mut buf).unwrap() {
            assert_eq!(n, 1206);
            assert!(t > 0);
            got.push(buf[0]);
        }
        // Loopback with an 8 MiB buffer (or whatever the kernel granted, >= 200 KB by default)
        // holds the whole burst (120 KB).
        assert_eq!(got, (0..100).collect::<Vec<u8>>());
    }
}
