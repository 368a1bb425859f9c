//! Classic libpcap files: UDP datagrams out of Ethernet (with optional 802.1Q / 802.1ad VLAN
//! tags), Linux cooked (SLL, SLL2), BSD loopback or raw IPv4 captures.
//!
//! - Both byte orders and both timestamp resolutions (microsecond magic 0xA1B2C3D4, nanosecond
//!   magic 0xA1B23C4D) are read.
//! - Fragmented IPv4 datagrams (large Ouster packets on a 1500-byte MTU) are reassembled in a
//!   bounded buffer (16 datagrams in flight, 2 s of capture time); fragments that never complete
//!   are counted in [`PcapStats::fragments_incomplete`].
//! - A corrupt record header (a length beyond the snapshot length, a timestamp fraction out of
//!   range) does not end the replay: the reader searches forward for the next plausible record
//!   (two consecutive headers that fit together) and counts what it skipped. A file cut short in
//!   the middle of a record ends the replay with [`PcapStats::truncated_at_eof`] set. Only a bad
//!   global header, an unsupported link type, an I/O error or a corruption with no good record
//!   after it within 16 MiB are errors.
//! - Frames that are not IPv4/UDP, or whose headers are malformed, are skipped and counted.
//!
//! A whole replay: pcap -> Velodyne decoder -> scan assembler (the same as in docs/sensors.md):
//!
//! ```no_run
//! use loglio_core::scan::ScanPoint;
//! use loglio_core::scan_assembly::{AssemblerConfig, ScanAssembler};
//! use loglio_core::sensor::velodyne::{Config, Decoder, Model};
//! use loglio_host::input::{pcap::PcapReader, time_align::VelodyneClock};
//!
//! let mut dec = Decoder::new(Config::new(Model::Vlp16))?; // layout: dec.layout() (for Ring FALS)
//! let (mut a, mut b) = (vec![ScanPoint::default(); 40_000], vec![ScanPoint::default(); 40_000]);
//! let mut asm = ScanAssembler::new(AssemblerConfig::cut_at_degrees(0.0), &mut a, &mut b);
//! let clock = VelodyneClock::new();
//! let mut pcap = PcapReader::open("drive.pcap")?;
//! while let Some(udp) = pcap.next_udp()? {
//!     if udp.dst_port != 2368 {
//!         continue; // 8308: position packets
//!     }
//!     let Ok((pkt, repr)) = dec.parse(udp.payload) else { continue }; // counted in dec.stats
//!     let t = clock.resolve(repr.timestamp_us, udp.ts_ns); // or udp.ts_ns (capture time)
//!     if let Ok(Some(info)) = asm.push_packet(dec.meta(&repr, t), |sink| dec.points(&pkt, sink)) {
//!         let scan = asm.scan(); // ScanView: start_ns + points with t, row, col
//!         println!("scan {}: {} points, complete: {}", info.index, scan.points.len(), info.complete);
//!     }
//! }
//! println!("{:?} {:?} {:?}", pcap.stats, dec.stats, asm.stats);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

use std::fs::File;
use std::io::{self, BufReader, Read};
use std::net::Ipv4Addr;
use std::path::Path;

/// Largest record the reader accepts (libpcap's own limit for non-USB link types).
pub const MAX_RECORD: u32 = 262_144;
const RESYNC_LIMIT: usize = 16 << 20;
const REASM_SLOTS: usize = 16;
const REASM_TIMEOUT_NS: u64 = 2_000_000_000;

/// Link-layer header types this reader understands.
pub mod linktype {
    /// BSD loopback (4-byte address family).
    pub const NULL: u32 = 0;
    /// Ethernet II.
    pub const ETHERNET: u32 = 1;
    /// Raw IP (OpenBSD value).
    pub const RAW_101: u32 = 101;
    /// Linux cooked capture v1.
    pub const LINUX_SLL: u32 = 113;
    /// Raw IPv4.
    pub const IPV4: u32 = 228;
    /// Linux cooked capture v2.
    pub const LINUX_SLL2: u32 = 276;
}

/// Errors that end a replay.
#[derive(Debug)]
pub enum PcapError {
    /// Reading the file failed.
    Io(io::Error),
    /// The file does not start with a pcap magic number (pcapng is not supported).
    BadMagic(u32),
    /// The global header is shorter than 24 bytes.
    ShortGlobalHeader,
    /// A pcap version other than 2.x.
    UnsupportedVersion(u16, u16),
    /// A link type this reader cannot take apart.
    UnsupportedLinkType(u32),
    /// A corrupt record header with no plausible record after it.
    Corrupt {
        /// Index of the last good record.
        after_record: u64,
        /// Byte offset of the corrupt header.
        offset: u64,
        /// What was wrong.
        reason: &'static str,
    },
}

impl std::fmt::Display for PcapError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Io(e) => write!(f, "pcap: read error: {e}"),
            Self::BadMagic(m) if *m == 0x0A0D_0D0A => {
                write!(f, "pcap: this is a pcapng file; convert it with `editcap -F pcap`")
            }
            Self::BadMagic(m) => write!(f, "pcap: bad magic number {m:#010x} (not a libpcap file)"),
            Self::ShortGlobalHeader => write!(f, "pcap: file shorter than the 24-byte global header"),
            Self::UnsupportedVersion(a, b) => {
                write!(f, "pcap: unsupported format version {a}.{b} (want 2.x)")
            }
            Self::UnsupportedLinkType(t) => {
                write!(
                    f,
                    "pcap: unsupported link type {t} (Ethernet, Linux SLL/SLL2, loopback and raw IPv4 are read)"
                )
            }
            Self::Corrupt { after_record, offset, reason } => write!(
                f,
                "pcap: corrupt record header at byte {offset} (after record {after_record}): {reason}; no valid record follows"
            ),
        }
    }
}

impl std::error::Error for PcapError {}

impl From<io::Error> for PcapError {
    fn from(e: io::Error) -> Self {
        Self::Io(e)
    }
}

/// What the reader read, skipped and repaired.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct PcapStats {
    /// Records read.
    pub records: u64,
    /// UDP datagrams delivered.
    pub udp: u64,
    /// IPv4 packets of other protocols.
    pub non_udp: u64,
    /// Frames that are not IPv4 (ARP, IPv6, ...).
    pub non_ipv4: u64,
    /// Frames with malformed or truncated Ethernet/IPv4/UDP headers.
    pub malformed: u64,
    /// Frames cut by the capture's snapshot length (their UDP payload is incomplete: skipped).
    pub snapped: u64,
    /// Frames whose IPv4 total length exceeds the frame (read by their UDP length).
    pub ip_length_mismatch: u64,
    /// IPv4 fragments seen.
    pub fragments: u64,
    /// Datagrams reassembled from fragments.
    pub reassembled: u64,
    /// Datagrams whose fragments never all arrived (timed out, evicted, or open at the end).
    pub fragments_incomplete: u64,
    /// Corrupt record headers skipped over.
    pub corrupt_records: u64,
    /// Bytes skipped while resynchronising.
    pub skipped_bytes: u64,
    /// The file ended inside a record.
    pub truncated_at_eof: bool,
}

/// A UDP datagram from the capture.
#[derive(Debug, Clone, Copy)]
pub struct UdpPacket<'a> {
    /// Capture time, ns since 1970.
    pub ts_ns: u64,
    /// Source address.
    pub src: Ipv4Addr,
    /// Destination address.
    pub dst: Ipv4Addr,
    /// Source port.
    pub src_port: u16,
    /// Destination port.
    pub dst_port: u16,
    /// Payload.
    pub payload: &'a [u8],
}

#[derive(Debug)]
struct Slot {
    key: (u32, u32, u16),
    first_ns: u64,
    data: Vec<u8>,
    /// Received byte ranges (start, end), unsorted.
    have: Vec<(usize, usize)>,
    total: Option<usize>,
    used: bool,
}

/// Reads UDP datagrams from a classic pcap stream.
#[derive(Debug)]
pub struct PcapReader<R: Read> {
    src: R,
    buf: Vec<u8>,
    pos: usize,
    eof: bool,
    file_offset: u64,
    big_endian: bool,
    nanos: bool,
    snaplen: u32,
    linktype: u32,
    last_sec: Option<u32>,
    slots: Vec<Slot>,
    out: Vec<u8>,
    /// What was read and skipped so far.
    pub stats: PcapStats,
}

impl PcapReader<BufReader<File>> {
    /// Opens a file.
    pub fn open(path: impl AsRef<Path>) -> Result<Self, PcapError> {
        Self::new(BufReader::with_capacity(1 << 20, File::open(path)?))
    }
}

impl<'a> PcapReader<&'a [u8]> {
    /// Reads from bytes in memory.
    pub fn from_bytes(bytes: &'a [u8]) -> Result<Self, PcapError> {
        Self::new(bytes)
    }
}

#[derive(Clone, Copy)]
struct RecordHeader {
    sec: u32,
    frac: u32,
    incl: u32,
    orig: u32,
}

impl<R: Read> PcapReader<R> {
    /// Reads the global header.
    pub fn new(src: R) -> Result<Self, PcapError> {
        let mut r = Self {
            src,
            buf: Vec::with_capacity(1 << 16),
            pos: 0,
            eof: false,
            file_offset: 0,
            big_endian: false,
            nanos: false,
            snaplen: 0,
            linktype: 0,
            last_sec: None,
            slots: Vec::new(),
            out: Vec::with_capacity(65_536),
            stats: PcapStats::default(),
        };
        r.fill(24)?;
        if r.available() < 24 {
            if r.available() >= 4 {
                let m = u32::from_le_bytes(r.buf[r.pos..r.pos + 4].try_into().expect("4 bytes"));
                if !matches!(m, 0xA1B2_C3D4 | 0xA1B2_3C4D | 0xD4C3_B2A1 | 0x4D3C_B2A1) {
                    return Err(PcapError::BadMagic(m));
                }
            }
            return Err(PcapError::ShortGlobalHeader);
        }
        let h = &r.buf[r.pos..r.pos + 24];
        let magic = u32::from_le_bytes(h[0..4].try_into().expect("4 bytes"));
        (r.big_endian, r.nanos) = match magic {
            0xA1B2_C3D4 => (false, false),
            0xA1B2_3C4D => (false, true),
            0xD4C3_B2A1 => (true, false),
            0x4D3C_B2A1 => (true, true),
            m => return Err(PcapError::BadMagic(m)),
        };
        let major = r.u16(&h[4..6]);
        let minor = r.u16(&h[6..8]);
        if major != 2 {
            return Err(PcapError::UnsupportedVersion(major, minor));
        }
        r.snaplen = r.u32(&h[16..20]);
        r.linktype = r.u32(&h[20..24]) & 0x0FFF_FFFF;
        use linktype::*;
        if !matches!(r.linktype, NULL | ETHERNET | RAW_101 | LINUX_SLL | IPV4 | LINUX_SLL2) {
            return Err(PcapError::UnsupportedLinkType(r.linktype));
        }
        r.consume(24);
        Ok(r)
    }

    /// The capture's link type.
    pub fn linktype(&self) -> u32 {
        self.linktype
    }

    /// The capture's snapshot length.
    pub fn snaplen(&self) -> u32 {
        self.snaplen
    }

    fn u16(&self, b: &[u8]) -> u16 {
        let a = [b[0], b[1]];
        if self.big_endian { u16::from_be_bytes(a) } else { u16::from_le_bytes(a) }
    }

    fn u32(&self, b: &[u8]) -> u32 {
        let a = [b[0], b[1], b[2], b[3]];
        if self.big_endian { u32::from_be_bytes(a) } else { u32::from_le_bytes(a) }
    }

    fn available(&self) -> usize {
        self.buf.len() - self.pos
    }

    /// Makes at least `n` bytes available unless the stream ends first.
    fn fill(&mut self, n: usize) -> io::Result<()> {
        if self.available() >= n || self.eof {
            return Ok(());
        }
        if self.pos > 0 && self.pos >= self.buf.len() / 2 {
            self.buf.drain(..self.pos);
            self.pos = 0;
        }
        let mut chunk = [0u8; 1 << 16];
        while self.available() < n {
            let k = match self.src.read(&mut chunk) {
                Ok(k) => k,
                Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
                Err(e) => return Err(e),
            };
            if k == 0 {
                self.eof = true;
                break;
            }
            self.buf.extend_from_slice(&chunk[..k]);
        }
        Ok(())
    }

    fn consume(&mut self, n: usize) {
        self.pos += n;
        self.file_offset += n as u64;
    }

    fn header_at(&self, at: usize) -> RecordHeader {
        let h = &self.buf[at..at + 16];
        RecordHeader {
            sec: self.u32(&h[0..4]),
            frac: self.u32(&h[4..8]),
            incl: self.u32(&h[8..12]),
            orig: self.u32(&h[12..16]),
        }
    }

    /// Why a record header is implausible, if it is.
    fn implausible(&self, h: &RecordHeader) -> Option<&'static str> {
        let limit = if self.snaplen == 0 { MAX_RECORD } else { self.snaplen.clamp(65_535, MAX_RECORD) };
        if h.incl > limit {
            return Some("captured length exceeds the snapshot length");
        }
        if h.orig < h.incl {
            return Some("captured length exceeds the original length");
        }
        if h.frac >= if self.nanos { 1_000_000_000 } else { 1_000_000 } {
            return Some("timestamp fraction out of range");
        }
        if let Some(last) = self.last_sec
            && (h.sec as i64 - last as i64).abs() > 86_400
        {
            return Some("timestamp more than a day from the previous record");
        }
        None
    }

    /// The next record's frame bytes (in `self.buf[start..start + incl]`) and time, or `None`
    /// at the end.
    fn next_record(&mut self) -> Result<Option<(usize, usize, u64, bool)>, PcapError> {
        loop {
            self.fill(16)?;
            let avail = self.available();
            if avail == 0 {
                return Ok(None);
            }
            if avail < 16 {
                self.stats.truncated_at_eof = true;
                log::warn!("pcap: file ends inside a record header ({avail} bytes left)");
                self.consume(avail);
                return Ok(None);
            }
            let h = self.header_at(self.pos);
            if let Some(reason) = self.implausible(&h) {
                self.resync(reason)?;
                continue;
            }
            let incl = h.incl as usize;
            self.fill(16 + incl)?;
            if self.available() < 16 + incl {
                self.stats.truncated_at_eof = true;
                log::warn!(
                    "pcap: file ends inside record {} ({} of {} bytes)",
                    self.stats.records,
                    self.available() - 16,
                    incl
                );
                let a = self.available();
                self.consume(a);
                return Ok(None);
            }
            let start = self.pos + 16;
            self.consume(16 + incl);
            self.stats.records += 1;
            self.last_sec = Some(h.sec);
            let ts_ns =
                h.sec as u64 * 1_000_000_000 + if self.nanos { h.frac as u64 } else { h.frac as u64 * 1000 };
            return Ok(Some((start, incl, ts_ns, h.incl < h.orig)));
        }
    }

    /// Skips forward to the next offset where two consecutive plausible record headers sit (or
    /// one that ends exactly at the end of the file).
    fn resync(&mut self, reason: &'static str) -> Result<(), PcapError> {
        let offset = self.file_offset;
        self.stats.corrupt_records += 1;
        log::warn!("pcap: corrupt record header at byte {offset}: {reason}; searching for the next record");
        let mut skipped = 0usize;
        loop {
            self.consume(1);
            skipped += 1;
            if skipped > RESYNC_LIMIT {
                return Err(PcapError::Corrupt { after_record: self.stats.records, offset, reason });
            }
            self.fill(16)?;
            if self.available() < 16 {
                // Nothing plausible before the end: the tail is garbage.
                let a = self.available();
                self.consume(a);
                self.stats.skipped_bytes += (skipped + a) as u64;
                self.stats.truncated_at_eof = true;
                return Ok(());
            }
            let h = self.header_at(self.pos);
            if self.implausible(&h).is_some() || h.incl < 14 {
                continue;
            }
            let next = 16 + h.incl as usize;
            self.fill(next + 16)?;
            let ok = if self.available() == next {
                true
            } else if self.available() >= next + 16 {
                let h2 = self.header_at(self.pos + next);
                self.implausible(&h2).is_none() && (h2.sec as i64 - h.sec as i64).abs() <= 60
            } else {
                false
            };
            if ok {
                self.stats.skipped_bytes += skipped as u64;
                return Ok(());
            }
        }
    }

    /// The next UDP datagram, reassembled if it was fragmented; `None` at the end of the file.
    pub fn next_udp(&mut self) -> Result<Option<UdpPacket<'_>>, PcapError> {
        loop {
            let Some((start, len, ts_ns, snapped)) = self.next_record()? else {
                let open = self.slots.iter().filter(|s| s.used).count() as u64;
                if open > 0 {
                    self.stats.fragments_incomplete += open;
                    log::warn!("pcap: {open} fragmented datagram(s) never completed");
                    self.slots.iter_mut().for_each(|s| s.used = false);
                }
                return Ok(None);
            };
            let buf = std::mem::take(&mut self.buf);
            let parsed = self.parse_frame(&buf[start..start + len], ts_ns, snapped);
            self.buf = buf;
            if let Some(meta) = parsed {
                return Ok(Some(UdpPacket { payload: &self.out, ..meta }));
            }
        }
    }

    /// Takes a frame apart; on success the payload is in `self.out`.
    fn parse_frame(&mut self, frame: &[u8], ts_ns: u64, snapped: bool) -> Option<UdpPacket<'static>> {
        let ip = self.link_payload(frame)?;
        if ip.len() < 20 || ip[0] >> 4 != 4 {
            self.stats.malformed += 1;
            return None;
        }
        let ihl = (ip[0] & 0x0F) as usize * 4;
        let total = u16::from_be_bytes([ip[2], ip[3]]) as usize;
        if ihl < 20 || total < ihl || ip.len() < ihl {
            self.stats.malformed += 1;
            return None;
        }
        let total = if ip.len() < total {
            if snapped {
                self.stats.snapped += 1;
                return None;
            }
            // The IPv4 length claims more than the frame holds. Velodyne position packets do
            // this (their IP header carries the data packets' length); the UDP length below
            // still has to fit in what was captured.
            self.stats.ip_length_mismatch += 1;
            ip.len()
        } else {
            total
        };
        let ip = &ip[..total];
        if ip[9] != 17 {
            self.stats.non_udp += 1;
            return None;
        }
        let src = Ipv4Addr::new(ip[12], ip[13], ip[14], ip[15]);
        let dst = Ipv4Addr::new(ip[16], ip[17], ip[18], ip[19]);
        let flags_frag = u16::from_be_bytes([ip[6], ip[7]]);
        let more = flags_frag & 0x2000 != 0;
        let frag_off = (flags_frag & 0x1FFF) as usize * 8;
        let body = &ip[ihl..];
        if more || frag_off != 0 {
            self.stats.fragments += 1;
            let id = u16::from_be_bytes([ip[4], ip[5]]);
            let key = (u32::from(src), u32::from(dst), id);
            if !self.add_fragment(key, frag_off, body, more, ts_ns) {
                return None;
            }
            self.stats.reassembled += 1;
        } else {
            self.out.clear();
            self.out.extend_from_slice(body);
        }
        // `self.out` holds the whole UDP datagram.
        let d = &self.out;
        if d.len() < 8 {
            self.stats.malformed += 1;
            return None;
        }
        let ulen = u16::from_be_bytes([d[4], d[5]]) as usize;
        if ulen < 8 || ulen > d.len() {
            self.stats.malformed += 1;
            return None;
        }
        let src_port = u16::from_be_bytes([d[0], d[1]]);
        let dst_port = u16::from_be_bytes([d[2], d[3]]);
        self.out.truncate(ulen);
        self.out.drain(..8);
        self.stats.udp += 1;
        Some(UdpPacket { ts_ns, src, dst, src_port, dst_port, payload: &[] })
    }

    /// The IPv4 packet inside a link-layer frame, or `None` (counted).
    fn link_payload<'f>(&mut self, f: &'f [u8]) -> Option<&'f [u8]> {
        let (ethertype, rest): (u16, &[u8]) = match self.linktype {
            linktype::ETHERNET => {
                if f.len() < 14 {
                    self.stats.malformed += 1;
                    return None;
                }
                let mut et = u16::from_be_bytes([f[12], f[13]]);
                let mut at = 14;
                // Up to two VLAN tags (802.1Q, 802.1ad / QinQ).
                for _ in 0..2 {
                    if matches!(et, 0x8100 | 0x88A8 | 0x9100) {
                        if f.len() < at + 4 {
                            self.stats.malformed += 1;
                            return None;
                        }
                        et = u16::from_be_bytes([f[at + 2], f[at + 3]]);
                        at += 4;
                    }
                }
                (et, &f[at..])
            }
            linktype::LINUX_SLL => {
                if f.len() < 16 {
                    self.stats.malformed += 1;
                    return None;
                }
                (u16::from_be_bytes([f[14], f[15]]), &f[16..])
            }
            linktype::LINUX_SLL2 => {
                if f.len() < 20 {
                    self.stats.malformed += 1;
                    return None;
                }
                (u16::from_be_bytes([f[0], f[1]]), &f[20..])
            }
            linktype::NULL => {
                if f.len() < 4 {
                    self.stats.malformed += 1;
                    return None;
                }
                let fam = u32::from_le_bytes([f[0], f[1], f[2], f[3]]);
                let fam_be = u32::from_be_bytes([f[0], f[1], f[2], f[3]]);
                (if fam == 2 || fam_be == 2 { 0x0800 } else { 0 }, &f[4..])
            }
            _ => (0x0800, f),
        };
        if ethertype != 0x0800 {
            self.stats.non_ipv4 += 1;
            return None;
        }
        Some(rest)
    }

    /// Adds a fragment; returns true when its datagram is complete (then it is in `self.out`).
    fn add_fragment(
        &mut self,
        key: (u32, u32, u16),
        off: usize,
        body: &[u8],
        more: bool,
        ts_ns: u64,
    ) -> bool {
        // Expire stale datagrams.
        for s in self.slots.iter_mut().filter(|s| s.used) {
            if ts_ns.saturating_sub(s.first_ns) > REASM_TIMEOUT_NS {
                s.used = false;
                self.stats.fragments_incomplete += 1;
                log::warn!("pcap: fragmented datagram {:?} timed out incomplete", s.key.2);
            }
        }
        let end = off + body.len();
        if end > 65_535 {
            self.stats.malformed += 1;
            return false;
        }
        let idx = match self.slots.iter().position(|s| s.used && s.key == key) {
            Some(i) => i,
            None => {
                let free = self.slots.iter().position(|s| !s.used);
                let i = match free {
                    Some(i) => i,
                    None if self.slots.len() < REASM_SLOTS => {
                        self.slots.push(Slot {
                            key,
                            first_ns: 0,
                            data: Vec::new(),
                            have: Vec::new(),
                            total: None,
                            used: false,
                        });
                        self.slots.len() - 1
                    }
                    None => {
                        // Evict the oldest.
                        let (i, _) = self
                            .slots
                            .iter()
                            .enumerate()
                            .min_by_key(|(_, s)| s.first_ns)
                            .expect("slots are full");
                        self.stats.fragments_incomplete += 1;
                        i
                    }
                };
                let s = &mut self.slots[i];
                s.key = key;
                s.first_ns = ts_ns;
                s.data.clear();
                s.have.clear();
                s.total = None;
                s.used = true;
                i
            }
        };
        let s = &mut self.slots[idx];
        if s.data.len() < end {
            s.data.resize(end, 0);
        }
        s.data[off..end].copy_from_slice(body);
        s.have.push((off, end));
        if !more {
            s.total = Some(end);
        }
        let Some(total) = s.total else { return false };
        // Complete when the ranges cover [0, total).
        s.have.sort_unstable();
        let mut reach = 0;
        for &(a, b) in &s.have {
            if a > reach {
                return false;
            }
            reach = reach.max(b);
        }
        if reach < total {
            return false;
        }
        s.used = false;
        self.out.clear();
        self.out.extend_from_slice(&s.data[..total]);
        true
    }
}

#[cfg(test)]
mod tests {
    use loglio_firmware_sim::pcap_out::{Endpoint, PcapWriter};

    use super::*;

    /// A Velodyne broadcasting.
    const EP: Endpoint = Endpoint { dst_ip: [255; 4], ..Endpoint::VELODYNE };

    fn payload(k: u8, n: usize) -> Vec<u8> {
        (0..n).map(|i| (i as u8).wrapping_mul(7).wrapping_add(k)).collect()
    }

    fn capture(n: usize, len: usize, mtu: Option<usize>) -> Vec<u8> {
        let mut w = PcapWriter::new(Vec::new()).unwrap();
        for k in 0..n {
            let t = 1_600_000_000_000_000_000 + k as u64 * 1_000_000;
            match mtu {
                Some(mtu) => w.write_udp_fragments(t, &EP, (2368, 2368), &payload(k as u8, len), mtu),
                None => w.write_udp(t, &EP, 2368, 2368, &payload(k as u8, len)),
            }
            .unwrap();
        }
        w.finish().unwrap()
    }

    fn read_all(bytes: &[u8]) -> (Vec<(u64, Vec<u8>)>, PcapStats) {
        let mut r = PcapReader::from_bytes(bytes).unwrap();
        let mut out = Vec::new();
        while let Some(p) = r.next_udp().unwrap() {
            out.push((p.ts_ns, p.payload.to_vec()));
        }
        (out, r.stats)
    }

    #[test]
    fn round_trip_plain_and_fragmented() {
        let (pk, st) = read_all(&capture(5, 1206, None));
        assert_eq!(pk.len(), 5);
        assert_eq!(pk[3].1, payload(3, 1206));
        assert_eq!(pk[3].0, 1_600_000_000_003_000_000);
        assert_eq!(st.udp, 5);
        let (pk, st) = read_all(&capture(4, 12_608, Some(1500)));
        assert_eq!(pk.len(), 4);
        assert_eq!(pk[2].1, payload(2, 12_608));
        assert_eq!(st.fragments, 4 * 9);
        assert_eq!(st.reassembled, 4);
        assert_eq!(st.fragments_incomplete, 0);
    }

    #[test]
    fn missing_fragment_is_reported_and_neighbours_kept() {
        let mut w = PcapWriter::new(Vec::new()).unwrap();
        w.write_udp_fragments(1, &EP, (7502, 7502), &payload(0, 4000), 1500).unwrap();
        let good = w.finish().unwrap();
        // Keep the global header and all records but the second fragment.
        let mut bytes = good[..24].to_vec();
        let mut at = 24;
        let mut k = 0;
        while at < good.len() {
            let incl = u32::from_le_bytes(good[at + 8..at + 12].try_into().unwrap()) as usize;
            if k != 1 {
                bytes.extend_from_slice(&good[at..at + 16 + incl]);
            }
            at += 16 + incl;
            k += 1;
        }
        let mut w = PcapWriter::new(Vec::new()).unwrap();
        w.write_udp(2, &EP, 7502, 7502, &payload(9, 100)).unwrap();
        bytes.extend_from_slice(&w.finish().unwrap()[24..]);
        let (pk, st) = read_all(&bytes);
        assert_eq!(pk.len(), 1);
        assert_eq!(pk[0].1, payload(9, 100));
        assert_eq!(st.fragments, 2);
        assert_eq!(st.fragments_incomplete, 1);
    }

    #[test]
    fn corrupt_global_headers_are_clear_errors() {
        let good = capture(1, 10, None);
        let mut bad = good.clone();
        bad[0] = 0x00;
        let e = PcapReader::from_bytes(&bad).unwrap_err();
        assert!(matches!(e, PcapError::BadMagic(_)), "{e}");
        assert!(e.to_string().contains("bad magic"));
        let pcapng = [0x0A, 0x0D, 0x0D, 0x0A, 0, 0, 0, 0];
        assert!(PcapReader::from_bytes(&pcapng).unwrap_err().to_string().contains("pcapng"));
        assert!(matches!(PcapReader::from_bytes(&good[..20]).unwrap_err(), PcapError::ShortGlobalHeader));
        let mut v = good.clone();
        v[4] = 3;
        assert!(matches!(PcapReader::from_bytes(&v).unwrap_err(), PcapError::UnsupportedVersion(3, 4)));
        let mut l = good.clone();
        l[20] = 147;
        assert!(matches!(PcapReader::from_bytes(&l).unwrap_err(), PcapError::UnsupportedLinkType(147)));
    }

    #[test]
    fn corrupt_record_header_is_skipped_and_later_records_kept() {
        let good = capture(6, 1206, None);
        let rec = 16 + 14 + 20 + 8 + 1206;
        let mut bad = good.clone();
        // Record 2's captured length: absurd.
        let at = 24 + 2 * rec + 8;
        bad[at..at + 4].copy_from_slice(&0x7FFF_FFFFu32.to_le_bytes());
        let (pk, st) = read_all(&bad);
        assert_eq!(pk.len(), 5, "records 0, 1, 3, 4, 5 survive");
        assert_eq!(pk[2].1, payload(3, 1206));
        assert_eq!(st.corrupt_records, 1);
        assert_eq!(st.skipped_bytes, rec as u64);
        // A timestamp fraction out of range.
        let mut bad = good.clone();
        let at = 24 + 4 * rec + 4;
        bad[at..at + 4].copy_from_slice(&2_000_000u32.to_le_bytes());
        let (pk, st) = read_all(&bad);
        assert_eq!(pk.len(), 5);
        assert_eq!(st.corrupt_records, 1);
    }

    #[test]
    fn truncated_file_keeps_what_came_before() {
        let good = capture(3, 1206, None);
        for cut in [good.len() - 1, good.len() - 700, good.len() - 1264 + 5] {
            let (pk, st) = read_all(&good[..cut]);
            assert_eq!(pk.len(), 2, "cut at {cut}");
            assert!(st.truncated_at_eof);
        }
        let (pk, st) = read_all(&good[..24]);
        assert!(pk.is_empty() && !st.truncated_at_eof);
    }

    #[test]
    fn vlan_tags_non_udp_and_garbage_frames() {
        let mut w = PcapWriter::new(Vec::new()).unwrap();
        // A QinQ double-tagged frame.
        let inner = w.frame(&EP, 2368, 2368, &[1, 2, 3, 4]);
        let mut tagged = inner[..12].to_vec();
        tagged.extend_from_slice(&[0x88, 0xA8, 0x00, 0x05, 0x81, 0x00, 0x00, 0x07]);
        tagged.extend_from_slice(&inner[12..]);
        w.write_frame(1, &tagged).unwrap();
        // ARP, garbage, TCP, a UDP length beyond the packet, a short frame.
        let mut arp = inner.clone();
        arp[12..14].copy_from_slice(&0x0806u16.to_be_bytes());
        w.write_frame(2, &arp).unwrap();
        w.write_frame(3, &[0xAB; 60]).unwrap();
        let mut tcp = inner.clone();
        tcp[14 + 9] = 6;
        w.write_frame(4, &tcp).unwrap();
        let mut long_udp = inner.clone();
        long_udp[14 + 20 + 4..14 + 20 + 6].copy_from_slice(&500u16.to_be_bytes());
        w.write_frame(5, &long_udp).unwrap();
        w.write_frame(6, &[1, 2, 3]).unwrap();
        w.write_udp(7, &EP, 2368, 2368, &[9; 10]).unwrap();
        let (pk, st) = read_all(&w.finish().unwrap());
        assert_eq!(pk.len(), 2);
        assert_eq!(pk[0].1, [1, 2, 3, 4]);
        assert_eq!(pk[1].1, [9; 10]);
        assert_eq!(st.non_ipv4, 2, "ARP and the 0xABAB ethertype");
        assert_eq!(st.non_udp, 1);
        assert_eq!(st.malformed, 2);
    }
}
