//! One LiDAR packet and its ground truth as owned buffers: shared by [`crate::scenario`] (the
//! decoder round-trip helpers) and [`crate::stream`] (the wire stream), so that neither module
//! needs the other's internals.

use crate::lidar::EchoSource;
use crate::lidar::ouster::{self, Ouster, OusterTruth};
use crate::lidar::velodyne::{self, TruthPoint, Velodyne};

/// Encodes Velodyne data packet `k` with its ground truth (every non-zero data point).
pub fn velodyne_packet<S: EchoSource>(v: &Velodyne, k: u64, src: &mut S) -> (Vec<u8>, Vec<TruthPoint>) {
    let mut buf = [0u8; velodyne::DATA_PACKET_LEN];
    let mut truth = [TruthPoint::default(); velodyne::POINTS_PER_PACKET];
    let n = v.data_packet(k, src, &mut buf, &mut truth);
    (buf.to_vec(), truth[..n].to_vec())
}

/// Encodes Ouster lidar packet `k` with its ground truth (every non-zero pixel).
pub fn ouster_packet<S: EchoSource>(o: &Ouster, k: u64, src: &mut S) -> (Vec<u8>, Vec<OusterTruth>) {
    let mut buf = vec![0u8; o.packet_len()];
    let mut truth = vec![OusterTruth::default(); ouster::COLUMNS_PER_PACKET * o.beams()];
    // The buffers are sized for this packet: the encoder cannot refuse them.
    let n = o.lidar_packet(k, src, &mut buf, &mut truth).unwrap_or(0);
    truth.truncate(n);
    (buf, truth)
}
