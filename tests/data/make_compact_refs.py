#!/usr/bin/env python3
"""Builds the compact reference decodes and the xz-compressed captures in tests/data from the
shared data folder (run once by hand; the tests never read the shared folder).

    python3 tests/data/make_compact_refs.py /path/to/shared/data

Compact reference format (little-endian, xz-compressed, one file per reference frame):
- Velodyne `<name>.frame<k>.vref.xz`: N = the frame's point count from `<name>.ref.json`, then
  columns x[N], y[N], z[N] (int32, units of 0.1 mm, rounded from velodyne_decoder's float32
  metres), t[N] (int32 ns relative to the frame stamp, rounded), ring[N] (uint8),
  return_type[N] (uint8; 1 strongest, 2 last, 3 both).
- Ouster `<name>.frame<k>.oref.xz`: the pixels whose SDK xyz is not (0, 0, 0) (range != 0), in
  the SDK's staggered row-major order (beam, then measurement id): x[N], y[N], z[N] (int32,
  0.1 mm), N = valid_px of `<name>.oref.json` (the SDK's ref.json; where an incomplete frame's
  reference holds stale data in columns the capture lacks, `loglio_valid_px_in_capture` gives
  the count over the columns present, and only those pixels are stored).
"""
import json, lzma, os, shutil, sys
import struct
import numpy as np

src = sys.argv[1]


def udp_payloads(path, port):
    """UDP payloads to `port` of a classic little-endian Ethernet/IPv4 pcap."""
    b = open(path, 'rb').read()
    off, out = 24, []
    while off + 16 <= len(b):
        incl = struct.unpack('<I', b[off + 8:off + 12])[0]
        d = b[off + 16:off + 16 + incl]
        off += 16 + incl
        ihl = (d[14] & 15) * 4
        u = 14 + ihl
        if d[23] == 17 and struct.unpack('>H', d[u + 2:u + 4])[0] == port:
            out.append(d[u + 8:u + struct.unpack('>H', d[u + 4:u + 6])[0]])
    return out


def legacy_columns(path, frame_id, h):
    """Measurement ids of the valid columns of a LEGACY-profile frame in a capture."""
    col = 16 + 12 * h + 4
    mids = set()
    for p in udp_payloads(path, 7502):
        for c in range(len(p) // col):
            o = c * col
            ts, mid, fid = struct.unpack('<QHH', p[o:o + 12])
            if fid == frame_id and p[o + col - 4:o + col] == b'\xff\xff\xff\xff':
                mids.add(mid)
    return sorted(mids)
dst = os.path.dirname(os.path.abspath(__file__))

def xz(data, path):
    with open(path, 'wb') as f:
        f.write(lzma.compress(data, format=lzma.FORMAT_XZ, check=lzma.CHECK_CRC32, preset=9 | lzma.PRESET_EXTREME))

VELODYNE = {
    'velodyne-veloview': ['vlp-16-test-90deg-1-50-frames', 'monterey-first-100-packets'],
    'velodyne-nebula': ['vlp16_dual_nebula_1673400471', 'vlp32c_nebula_1713492677'],
    'rust-lidar-utils': ['hdl32_example', 'velodyne_example', 'velodyne_vlp16', 'velodyne_vlp32'],
}
OUSTER = {
    'ouster-sdk': ['OS-0-128-U1_v2.3.0_1024x10', 'OS-0-32-U1_v2.2.0_1024x10',
                   'OS-1-128_767798045_1024x10_20230712_120049', 'OS-1-128_v2.3.0_1024x10_lb_n3',
                   'OS-1-32-G_v2.1.1_1024x10', 'OS-1-64_1024x10_fw20', 'OS-2-128-U1_v2.3.0_1024x10',
                   'OS-2-32-U0_v2.0.0_1024x10'],
    'rust-lidar-utils': ['ouster_example'],
}

for folder, names in VELODYNE.items():
    os.makedirs(f'{dst}/{folder}', exist_ok=True)
    for name in names:
        xz(open(f'{src}/{folder}/{name}.pcap', 'rb').read(), f'{dst}/{folder}/{name}.pcap.xz')
        ref = json.load(open(f'{src}/{folder}/ref-velodyne_decoder/{name}.ref.json'))
        shutil.copy(f'{src}/{folder}/ref-velodyne_decoder/{name}.ref.json', f'{dst}/{folder}/{name}.vref.json')
        for k in range(ref['dumped_frames']):
            a = np.fromfile(f'{src}/{folder}/ref-velodyne_decoder/{name}.frame{k}.xyzitcrr.f32le.bin', '<f4').reshape(-1, 8)
            assert len(a) == ref['frames'][k]['points']
            xyz = np.round(a[:, :3].astype(np.float64) * 1e4).astype('<i4')
            t = np.round(a[:, 4].astype(np.float64) * 1e9).astype('<i4')
            ring = a[:, 6].astype('u1')
            rt = a[:, 7].astype('u1')
            blob = xyz[:, 0].tobytes() + xyz[:, 1].tobytes() + xyz[:, 2].tobytes() + t.tobytes() + ring.tobytes() + rt.tobytes()
            xz(blob, f'{dst}/{folder}/{name}.frame{k}.vref.xz')

for folder, names in OUSTER.items():
    os.makedirs(f'{dst}/{folder}', exist_ok=True)
    for name in names:
        xz(open(f'{src}/{folder}/{name}.pcap', 'rb').read(), f'{dst}/{folder}/{name}.pcap.xz')
        ref = json.load(open(f'{src}/{folder}/ref-ouster-sdk/{name}.ref.json'))
        out_json = json.load(open(f'{src}/{folder}/ref-ouster-sdk/{name}.ref.json'))
        meta = ref['metadata']
        shutil.copy(f'{src}/{folder}/{meta}', f'{dst}/{folder}/{meta}')
        imu = f'{src}/{folder}/ref-ouster-sdk/{name}.imu.csv'
        if os.path.exists(imu):
            shutil.copy(imu, f'{dst}/{folder}/{name}.imu.csv')
        for k, fr in enumerate(ref['frames']):
            h, w = ref['pixels_per_column'], ref['columns_per_frame']
            a = np.fromfile(f'{src}/{folder}/ref-ouster-sdk/{name}.frame{k}.xyz_m.f32le.bin', '<f4').reshape(-1, 3)
            v = np.any(a != 0, axis=1)
            assert v.sum() == fr['valid_px'], (name, k)
            if not fr['complete'] and ref['udp_profile_lidar'] == 'LEGACY':
                # The SDK (0.12) leaves the previous frame's data in the columns an incomplete
                # frame never received: keep only the columns the capture holds.
                present = np.zeros(w, bool)
                present[legacy_columns(f'{src}/{folder}/{name}.pcap', fr['frame_id'], h)] = True
                keep = np.broadcast_to(present, (h, w)).reshape(-1)
                if (v & ~keep).any():
                    out_json['frames'][k]['loglio_valid_px_in_capture'] = int((v & keep).sum())
                    out_json['frames'][k]['loglio_note'] = (
                        'the SDK reference repeats the previous frame in the %d columns this capture lacks; '
                        'only the %d columns present are compared' % (w - present.sum(), present.sum()))
                v = v & keep
            q = np.round(a[v].astype(np.float64) * 1e4).astype('<i4')
            xz(q[:, 0].tobytes() + q[:, 1].tobytes() + q[:, 2].tobytes(), f'{dst}/{folder}/{name}.frame{k}.oref.xz')
        json.dump(out_json, open(f'{dst}/{folder}/{name}.oref.json', 'w'), indent=1)

for f in ['VLP16.calib.yaml', 'VLP32.calib.yaml', 'HDL32.calib.yaml']:
    shutil.copy(f'{src}/velodyne-nebula/{f}', f'{dst}/velodyne-nebula/{f}')
print('done')
