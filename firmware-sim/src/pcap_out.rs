//! A classic libpcap writer (microsecond timestamps, Ethernet link type) that wraps UDP
//! payloads in Ethernet II / IPv4 / UDP headers with valid checksums, as a capture on the
//! sensor's network would show them. Datagrams are written unfragmented (as captured on a
//! loopback or jumbo-frame interface; Ouster packets exceed a 1500-byte MTU), or as IPv4
//! fragments with [`PcapWriter::write_udp_fragments`]. The one pcap writer of the workspace: the
//! host's reader tests write their captures with it too.

use std::io::{self, Write};

/// Link type Ethernet.
const LINKTYPE_ETHERNET: u32 = 1;

/// Addresses of one simulated sensor on the network.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Endpoint {
    /// Sensor MAC address.
    pub src_mac: [u8; 6],
    /// Sensor IPv4 address.
    pub src_ip: [u8; 4],
    /// Host IPv4 address.
    pub dst_ip: [u8; 4],
}

impl Endpoint {
    /// A Velodyne at its factory address 192.168.1.201 (Velodyne OUI 60:76:88) sending to
    /// 192.168.1.77.
    pub const VELODYNE: Endpoint = Endpoint {
        src_mac: [0x60, 0x76, 0x88, 0x00, 0x12, 0x34],
        src_ip: [192, 168, 1, 201],
        dst_ip: [192, 168, 1, 77],
    };
    /// An Ouster at 169.254.10.20 (Ouster OUI bc:0f:a7) sending to 169.254.10.1.
    pub const OUSTER: Endpoint = Endpoint {
        src_mac: [0xBC, 0x0F, 0xA7, 0x00, 0x12, 0x34],
        src_ip: [169, 254, 10, 20],
        dst_ip: [169, 254, 10, 1],
    };
}

/// Writes a pcap file.
#[derive(Debug)]
pub struct PcapWriter<W: Write> {
    out: W,
    ip_id: u16,
    /// Records written.
    pub records: u64,
}

/// The Internet checksum (RFC 1071) of `data`, continuing from `sum`.
fn ones_complement_sum(mut sum: u32, data: &[u8]) -> u32 {
    let mut chunks = data.chunks_exact(2);
    for c in &mut chunks {
        sum += u16::from_be_bytes([c[0], c[1]]) as u32;
    }
    if let [b] = chunks.remainder() {
        sum += (*b as u32) << 8;
    }
    sum
}

fn fold(mut sum: u32) -> u16 {
    while sum >> 16 != 0 {
        sum = (sum & 0xFFFF) + (sum >> 16);
    }
    !(sum as u16)
}

/// A UDP datagram (header with its checksum over the pseudo-header, then `payload`).
fn udp_datagram(ep: &Endpoint, src_port: u16, dst_port: u16, payload: &[u8]) -> Vec<u8> {
    let udp_len = 8 + payload.len();
    let mut u = Vec::with_capacity(udp_len);
    u.extend_from_slice(&src_port.to_be_bytes());
    u.extend_from_slice(&dst_port.to_be_bytes());
    u.extend_from_slice(&(udp_len as u16).to_be_bytes());
    u.extend_from_slice(&[0, 0]);
    u.extend_from_slice(payload);
    let mut pseudo = [0u8; 12];
    pseudo[..4].copy_from_slice(&ep.src_ip);
    pseudo[4..8].copy_from_slice(&ep.dst_ip);
    pseudo[9] = 17;
    pseudo[10..12].copy_from_slice(&(udp_len as u16).to_be_bytes());
    let cs = fold(ones_complement_sum(ones_complement_sum(0, &pseudo), &u));
    // 0 means "no checksum": a computed 0 is sent as 0xFFFF.
    let cs = if cs == 0 { 0xFFFF } else { cs };
    u[6..8].copy_from_slice(&cs.to_be_bytes());
    u
}

/// An Ethernet II broadcast frame with an IPv4 header (protocol UDP; `flags`: the flags and
/// fragment offset field) around `body`.
fn ipv4_frame(ep: &Endpoint, id: u16, flags: u16, body: &[u8]) -> Vec<u8> {
    let ip_len = 20 + body.len();
    let mut f = Vec::with_capacity(14 + ip_len);
    f.extend_from_slice(&[0xFF; 6]);
    f.extend_from_slice(&ep.src_mac);
    f.extend_from_slice(&0x0800u16.to_be_bytes());
    let ip0 = f.len();
    f.extend_from_slice(&[0x45, 0x00]);
    f.extend_from_slice(&(ip_len as u16).to_be_bytes());
    f.extend_from_slice(&id.to_be_bytes());
    f.extend_from_slice(&flags.to_be_bytes());
    f.extend_from_slice(&[64, 17, 0, 0]);
    f.extend_from_slice(&ep.src_ip);
    f.extend_from_slice(&ep.dst_ip);
    let cs = fold(ones_complement_sum(0, &f[ip0..ip0 + 20]));
    f[ip0 + 10..ip0 + 12].copy_from_slice(&cs.to_be_bytes());
    f.extend_from_slice(body);
    f
}

impl<W: Write> PcapWriter<W> {
    /// Writes the global header.
    pub fn new(mut out: W) -> io::Result<Self> {
        out.write_all(&0xA1B2_C3D4u32.to_le_bytes())?;
        out.write_all(&2u16.to_le_bytes())?;
        out.write_all(&4u16.to_le_bytes())?;
        out.write_all(&0i32.to_le_bytes())?;
        out.write_all(&0u32.to_le_bytes())?;
        out.write_all(&65_535u32.to_le_bytes())?;
        out.write_all(&LINKTYPE_ETHERNET.to_le_bytes())?;
        Ok(Self { out, ip_id: 0, records: 0 })
    }

    /// The Ethernet frame of a UDP datagram (unfragmented, "don't fragment" set).
    pub fn frame(&mut self, ep: &Endpoint, src_port: u16, dst_port: u16, payload: &[u8]) -> Vec<u8> {
        let udp = udp_datagram(ep, src_port, dst_port, payload);
        let id = self.next_ip_id();
        ipv4_frame(ep, id, 0x4000, &udp)
    }

    fn next_ip_id(&mut self) -> u16 {
        let id = self.ip_id;
        self.ip_id = self.ip_id.wrapping_add(1);
        id
    }

    /// Writes one UDP datagram captured at `t_ns` (Unix ns).
    pub fn write_udp(
        &mut self,
        t_ns: u64,
        ep: &Endpoint,
        src_port: u16,
        dst_port: u16,
        payload: &[u8],
    ) -> io::Result<()> {
        let frame = self.frame(ep, src_port, dst_port, payload);
        self.write_frame(t_ns, &frame)
    }

    /// Writes one UDP datagram as IPv4 fragments of at most `mtu` bytes of IP packet each, as a
    /// standard-MTU network delivers an Ouster packet (the reader's reassembly is tested on these).
    pub fn write_udp_fragments(
        &mut self,
        t_ns: u64,
        ep: &Endpoint,
        (src_port, dst_port): (u16, u16),
        payload: &[u8],
        mtu: usize,
    ) -> io::Result<()> {
        let udp = udp_datagram(ep, src_port, dst_port, payload);
        let id = self.next_ip_id();
        let max_body = (mtu.saturating_sub(20) / 8 * 8).max(8);
        let mut off = 0;
        loop {
            let end = (off + max_body).min(udp.len());
            let more = end < udp.len();
            let flags = (off / 8) as u16 | if more { 0x2000 } else { 0 };
            self.write_frame(t_ns, &ipv4_frame(ep, id, flags, &udp[off..end]))?;
            if !more {
                return Ok(());
            }
            off = end;
        }
    }

    /// Writes one record holding `frame` (any bytes) as captured at `t_ns` (Unix ns).
    pub fn write_frame(&mut self, t_ns: u64, frame: &[u8]) -> io::Result<()> {
        self.out.write_all(&((t_ns / 1_000_000_000) as u32).to_le_bytes())?;
        self.out.write_all(&(((t_ns / 1_000) % 1_000_000) as u32).to_le_bytes())?;
        self.out.write_all(&(frame.len() as u32).to_le_bytes())?;
        self.out.write_all(&(frame.len() as u32).to_le_bytes())?;
        self.out.write_all(frame)?;
        self.records += 1;
        Ok(())
    }

    /// Flushes and returns the writer.
    pub fn finish(mut self) -> io::Result<W> {
        self.out.flush()?;
        Ok(self.out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn headers_lengths_and_checksums() {
        let mut w = PcapWriter::new(Vec::new()).unwrap();
        let payload: Vec<u8> = (0..1206u32).map(|i| (i * 7) as u8).collect();
        w.write_udp(1_714_565_400_123_456_789, &Endpoint::VELODYNE, 2368, 2368, &payload).unwrap();
        let b = w.finish().unwrap();
        assert_eq!(&b[..4], &[0xD4, 0xC3, 0xB2, 0xA1]);
        assert_eq!(b.len(), 24 + 16 + 1248);
        let rec = &b[24..];
        assert_eq!(u32::from_le_bytes(rec[0..4].try_into().unwrap()), 1_714_565_400);
        assert_eq!(u32::from_le_bytes(rec[4..8].try_into().unwrap()), 123_456);
        assert_eq!(u32::from_le_bytes(rec[8..12].try_into().unwrap()), 1248);
        let f = &rec[16..];
        // A correct IPv4 header sums to 0xFFFF; so does a UDP datagram with its pseudo-header.
        assert_eq!(fold(ones_complement_sum(0, &f[14..34])), 0);
        let mut pseudo = [0u8; 12];
        pseudo[..4].copy_from_slice(&f[26..30]);
        pseudo[4..8].copy_from_slice(&f[30..34]);
        pseudo[9] = 17;
        pseudo[10..12].copy_from_slice(&f[38..40]);
        assert_eq!(fold(ones_complement_sum(ones_complement_sum(0, &pseudo), &f[34..])), 0);
        assert_eq!(u16::from_be_bytes([f[36], f[37]]), 2368);
        assert_eq!(&f[42..], &payload[..]);
    }
}
