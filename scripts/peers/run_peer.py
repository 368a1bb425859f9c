#!/usr/bin/env python3
"""Runs one peer odometry on one scenario exported by `sim2bag` (see docs/peers.md).

    run_peer.py PEER SCENARIO_DIR OUT_DIR

PEER is one of kiss-icp, genz-lio, rko-lio, dlio, lio-sam. SCENARIO_DIR holds
`<scenario>.bag` and `scenario.json` (extrinsic, IMU noise figures, sensor layout).
Writes `OUT_DIR/<scenario>.tum` (the peer's trajectory as T_world_imu, whatever frame the
peer estimates, stamped at the time the peer's pose refers to), `OUT_DIR/<scenario>.json`
(timing, parameters, versions, notes) and, on failure, the JSON with "status": "failed" and
the error.

Timing: wall (time.perf_counter) and CPU (time.process_time: every thread of the process)
spent inside the peer's own calls (IMU ingestion and scan registration), summed per scan.
Reading and decoding the bag is not counted. Every peer is limited to one thread where it
allows (OMP_NUM_THREADS=1 as well).

One parameter set per peer, the same for every scenario: the peer's defaults for a 10 Hz
spinning LiDAR, plus the data's facts (extrinsic, IMU noise figures, the 32 rings, the bag's
timestamp conventions). Nothing is tuned per scenario.
"""

from __future__ import annotations

import os

# Before numpy and the peers load their thread pools.
for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "TBB_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import traceback  # noqa: E402
from importlib.metadata import version  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

PEERS = ("kiss-icp", "genz-lio", "rko-lio", "dlio", "lio-sam")
# Set by a peer that stopped with an error part-way (its poses up to there are kept).
STOPPED: dict = {}


# ----------------------------------------------------------------------------- helpers


def quat_xyzw_to_rot(q) -> np.ndarray:
    x, y, z, w = q
    n = np.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def rot_to_quat_xyzw(r: np.ndarray):
    # Shepperd's method.
    t = np.trace(r)
    if t > 0:
        s = np.sqrt(t + 1.0) * 2
        w, x, y, z = 0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = np.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2]) * 2
        w, x, y, z = (r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s
    elif r[1, 1] > r[2, 2]:
        s = np.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2]) * 2
        w, x, y, z = (r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s
    else:
        s = np.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1]) * 2
        w, x, y, z = (r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s
    q = np.array([x, y, z, w])
    return q / np.linalg.norm(q)


def se3(r: np.ndarray, t) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = t
    return m


def inv(m: np.ndarray) -> np.ndarray:
    r, t = m[:3, :3], m[:3, 3]
    return se3(r.T, -r.T @ t)


def write_tum(path: Path, poses):
    """poses: [(t_ns, 4x4)], written with exact nanosecond stamps."""
    with open(path, "w") as f:
        f.write("# timestamp tx ty tz qx qy qz qw (T_world_imu)\n")
        for t_ns, m in poses:
            q = rot_to_quat_xyzw(m[:3, :3])
            p = m[:3, 3]
            f.write(
                f"{t_ns // 1_000_000_000}.{t_ns % 1_000_000_000:09d} {p[0]:.9f} {p[1]:.9f} {p[2]:.9f} "
                f"{q[0]:.12f} {q[1]:.12f} {q[2]:.12f} {q[3]:.12f}\n"
            )


class Scenario:
    def __init__(self, d: Path):
        self.dir = d
        self.info = json.loads((d / "scenario.json").read_text())
        self.name = self.info["scenario"]
        self.bag = d / self.info["bag"]["file"]
        e = self.info["extrinsic_imu_lidar"]
        self.t_imu_lidar = se3(quat_xyzw_to_rot(e["quaternion_xyzw"]), e["translation_m"])
        self.t_lidar_imu = inv(self.t_imu_lidar)
        self.imu = self.info["imu"]
        self.rows = int(self.info["bag"]["rows"])
        self.lidar_topic = self.info["bag"]["lidar_topic"]
        self.imu_topic = self.info["bag"]["imu_topic"]
        self.max_range = float(self.info["lidar"]["max_range_m"])
        self.max_scans = None

    def messages(self):
        """Yields ("imu", t_ns, gyro, acc) and ("scan", start_ns, end_ns, xyz f64 (N,3),
        time f64 (N,) s since start, ring u16 (N,), intensity f32 (N,)) in bag order."""
        from rosbags.highlevel import AnyReader

        np_types = {1: "i1", 2: "u1", 3: "<i2", 4: "<u2", 5: "<i4", 6: "<u4", 7: "<f4", 8: "<f8"}
        scans = 0
        with AnyReader([self.bag]) as reader:
            conns = [c for c in reader.connections if c.topic in (self.lidar_topic, self.imu_topic)]
            for conn, rec_ns, raw in reader.messages(connections=conns):
                if self.max_scans is not None and scans >= self.max_scans:
                    return
                msg = reader.deserialize(raw, conn.msgtype)
                st = msg.header.stamp
                stamp = int(st.sec) * 1_000_000_000 + int(st.nanosec)
                if conn.topic == self.imu_topic:
                    g, a = msg.angular_velocity, msg.linear_acceleration
                    yield ("imu", stamp, np.array([g.x, g.y, g.z]), np.array([a.x, a.y, a.z]))
                else:
                    dt = np.dtype(
                        {
                            "names": [f.name for f in msg.fields],
                            "formats": [np_types[f.datatype] for f in msg.fields],
                            "offsets": [f.offset for f in msg.fields],
                            "itemsize": msg.point_step,
                        }
                    )
                    pts = np.frombuffer(bytes(msg.data), dtype=dt, count=msg.width * msg.height)
                    xyz = np.column_stack([pts["x"], pts["y"], pts["z"]]).astype(np.float64)
                    scans += 1
                    yield (
                        "scan",
                        stamp,
                        int(rec_ns),
                        xyz,
                        pts["time"].astype(np.float64),
                        pts["ring"].astype(np.uint16),
                        pts["intensity"].astype(np.float32),
                    )


class Clock:
    """Wall and process-CPU time spent in the peer's calls, accumulated per scan."""

    def __init__(self):
        self.wall = []
        self.cpu = []
        self._w = 0.0
        self._c = 0.0

    def __enter__(self):
        self._w0 = time.perf_counter()
        self._c0 = time.process_time()
        return self

    def __exit__(self, *a):
        self._w += time.perf_counter() - self._w0
        self._c += time.process_time() - self._c0

    def end_scan(self):
        self.wall.append(self._w)
        self.cpu.append(self._c)
        self._w = self._c = 0.0

    def summary(self):
        w, c = np.array(self.wall) * 1e3, np.array(self.cpu) * 1e3
        if len(w) == 0:
            return {"scans": 0}
        return {
            "scans": len(w),
            "wall_ms_per_scan_mean": float(w.mean()),
            "wall_ms_per_scan_median": float(np.median(w)),
            "wall_ms_per_scan_max": float(w.max()),
            "cpu_ms_per_scan_mean": float(c.mean()),
            "cpu_ms_per_scan_median": float(np.median(c)),
            "wall_s_total": float(w.sum() / 1e3),
            "cpu_s_total": float(c.sum() / 1e3),
        }


# ----------------------------------------------------------------------------- peers
# Each returns (poses [(t_ns, T_world_imu)], params dict, notes list).


def imu_discrete_variances(sc: Scenario):
    """FAST-LIO-style process noise: the per-sample variances the filter multiplies by dt^2,
    i.e. density^2 * rate for the white noises and the bias random walks."""
    rate = float(sc.imu["rate_hz"])
    return {
        "gyr_cov": sc.imu["gyro_noise_density_rad_s_sqrt_hz"] ** 2 * rate,
        "acc_cov": sc.imu["accel_noise_density_m_s2_sqrt_hz"] ** 2 * rate,
        "b_gyr_cov": sc.imu["gyro_bias_random_walk_rad_s2_sqrt_hz"] ** 2 * rate,
        "b_acc_cov": sc.imu["accel_bias_random_walk_m_s3_sqrt_hz"] ** 2 * rate,
    }


def run_kiss_icp(sc: Scenario, clock: Clock):
    from kiss_icp.config.parser import KISSConfig
    from kiss_icp.kiss_icp import KissICP

    cfg = KISSConfig()
    cfg.data.max_range = 100.0
    cfg.data.min_range = 0.0
    cfg.data.deskew = True
    cfg.mapping.voxel_size = cfg.data.max_range / 100.0  # kiss-icp's own default rule
    cfg.registration.max_num_threads = 1
    odom = KissICP(cfg)
    poses = []
    for m in sc.messages():
        if m[0] != "scan":
            continue
        _, start, end, xyz, t, _, _ = m
        with clock:
            odom.register_frame(xyz, t)
        clock.end_scan()
        # kiss-icp deskews to the scan's end (normalised time 1): its pose is the LiDAR's at
        # the last firing. LiDAR-only: the first pose is the identity.
        poses.append((start + int(round(t.max() * 1e9)), odom.last_pose @ sc.t_lidar_imu))
    params = cfg.model_dump() if hasattr(cfg, "model_dump") else cfg.dict()
    return poses, params, ["LiDAR only (no IMU); pose of the LiDAR mapped to the IMU frame with the true extrinsic"]


def run_genz_lio(sc: Scenario, clock: Clock):
    import genz_lio
    from genz_lio.config import load_config
    from genz_lio.datasets.rosbag import RosbagDataset
    from genz_lio.genz_lio_pybind import GenZLIO

    base = Path(genz_lio.__file__).parent / "configs" / "default" / "velodyne.yaml"
    cfg = load_config(base)
    cfg.max_threads = 1
    cfg.preprocess.scan_line = sc.rows
    cfg.preprocess.blind_max = 100.0
    cfg.mapping.extrinsic_est_en = False
    cfg.mapping.extrinsic_t = np.asarray(sc.t_imu_lidar[:3, 3], dtype=float)
    cfg.mapping.extrinsic_r = np.asarray(sc.t_imu_lidar[:3, :3], dtype=float)
    for k, v in imu_discrete_variances(sc).items():
        setattr(cfg.noise_model, k, float(v))
    odom = GenZLIO(cfg)
    data = RosbagDataset(sc.bag, lidar_topic=sc.lidar_topic, imu_topic=sc.imu_topic, preprocess=cfg.preprocess)
    poses, skipped = [], 0
    for fr in data:
        if sc.max_scans is not None and len(clock.wall) >= sc.max_scans:
            break
        if len(fr.imu) == 0:
            skipped += 1
            continue
        with clock:
            res = odom.register_scan(
                fr.points,
                fr.begin_time,
                fr.end_time,
                fr.imu,
                timestamps=fr.timestamps,
                intensities=fr.intensities,
                rings=fr.rings,
                timing_prepared=fr.timing_prepared,
            )
        clock.end_scan()
        if not res.valid:
            skipped += 1
            continue
        # res.pose: the IMU (body) pose at res.timestamp (the scan end), FAST-LIO style.
        poses.append((int(round(res.timestamp * 1e9)), np.array(res.pose)))
    params = {
        "base": "genz_lio/configs/default/velodyne.yaml",
        "max_threads": 1,
        "preprocess.scan_line": sc.rows,
        "preprocess.blind_max": 100.0,
        "mapping.extrinsic": "true T_imu_lidar, not estimated",
        "noise_model": imu_discrete_variances(sc),
    }
    notes = [f"{skipped} scans skipped (not initialised or invalid result)"]
    return poses, params, notes


def run_rko_lio(sc: Scenario, clock: Clock):
    from rko_lio.config import PipelineConfig
    from rko_lio.dataloaders import LidarIMUSequencer, dataloader_factory
    from rko_lio.lio_pipeline import LIOPipeline

    q = rot_to_quat_xyzw(sc.t_imu_lidar[:3, :3])
    t = sc.t_imu_lidar[:3, 3]
    user = {
        "lio": {"max_num_threads": 1},
        "lidar_timestamps": {"force_relative": True},
        # Base frame = the IMU: the trajectory is T_world_imu.
        "extrinsic_imu2base_quat_xyzw_xyz": [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
        "extrinsic_lidar2base_quat_xyzw_xyz": [float(v) for v in (*q, *t)],
        "log_dir": "/tmp/rko_lio_unused",
        "run_name": sc.name,
    }
    cfg = PipelineConfig.from_dict(json.loads(json.dumps(user)))
    loader = LidarIMUSequencer(
        dataloader_factory(
            name="rosbag",
            data_path=sc.dir,
            imu_topic=sc.imu_topic,
            lidar_topic=sc.lidar_topic,
            imu_frame_id=None,
            lidar_frame_id=None,
            base_frame_id=None,
            timestamp_config=cfg.lidar_timestamps,
        )
    )
    from rko_lio.rko_lio_pybind import RegistrationError

    pipe = LIOPipeline(cfg)
    notes = ["no IMU noise parameters exist in rko_lio (max_expected_jerk etc. left at defaults)"]
    try:
        for kind, d in loader:
            if sc.max_scans is not None and len(clock.wall) >= sc.max_scans:
                break
            if kind == "imu":
                with clock:
                    pipe.add_imu(**d)
            else:
                with clock:
                    pipe.register_scan(**d)
                clock.end_scan()
    except RegistrationError as e:
        # rko_lio's own command line ends here too; keep the poses up to this scan.
        clock.end_scan()
        STOPPED["at_scan"] = len(clock.wall)
        STOPPED["error"] = f"RegistrationError: {e}"
    stamps, ps = pipe.lio.poses_with_timestamps()
    poses = []
    for t_ns, p in zip(stamps, ps):
        # p: x y z qx qy qz qw of the base (IMU) frame.
        poses.append((int(t_ns), se3(quat_xyzw_to_rot(p[3:7]), p[0:3])))
    params = cfg.to_dict()
    params["log_dir"] = str(params["log_dir"])
    return poses, params, notes


def _evalio_scan(sc: Scenario, start, xyz, t, ring, intensity, cols, period):
    """A dense row-major evalio LidarMeasurement (rows x cols, missing returns at the origin),
    row = ring (0 = lowest), col = firing sequence (time / period)."""
    from evalio._cpp.helpers import DataType, Field, PointCloudMetadata, pc2_to_evalio
    from evalio.types import Stamp

    dt = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("time", "<f4"), ("ring", "<u2"), ("pad", "<u2")])
    grid = np.zeros(sc.rows * cols, dtype=dt)
    grid["ring"] = np.repeat(np.arange(sc.rows, dtype=np.uint16), cols)
    # A sequence fires at k * period + [0, 36.9 us]; the epsilon keeps a first firing at exactly
    # k * period (rounded down in float32) in column k.
    col = np.minimum((t / period + 1e-3).astype(np.int64), cols - 1)
    idx = ring.astype(np.int64) * cols + col
    grid["x"][idx], grid["y"][idx], grid["z"][idx] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    grid["intensity"][idx] = intensity
    grid["time"] = (np.tile(np.arange(cols), sc.rows) * period).astype(np.float32)
    grid["time"][idx] = t
    fields = [
        Field(name="x", datatype=DataType.FLOAT32, offset=0),
        Field(name="y", datatype=DataType.FLOAT32, offset=4),
        Field(name="z", datatype=DataType.FLOAT32, offset=8),
        Field(name="intensity", datatype=DataType.FLOAT32, offset=12),
        Field(name="time", datatype=DataType.FLOAT32, offset=16),
        Field(name="ring", datatype=DataType.UINT16, offset=20),
    ]
    meta = PointCloudMetadata(
        stamp=Stamp(sec=start // 1_000_000_000, nsec=start % 1_000_000_000),
        width=cols,
        height=sc.rows,
        point_step=dt.itemsize,
        row_step=dt.itemsize * cols,
        is_bigendian=0,
        is_dense=1,
    )
    from evalio._cpp.helpers import fill_col_row_major

    m = pc2_to_evalio(meta, fields, grid.tobytes())
    fill_col_row_major(m)
    return m, int(np.unique(idx).size) != len(idx)


# VLP-32C firing sequence (all 32 lasers once): 55.296 us (Velodyne's manual).
VLP32C_SEQUENCE_S = 55.296e-6


def run_evalio(name: str, sc: Scenario, clock: Clock):
    import evalio.pipelines as pl
    from evalio.types import SE3, SO3, ImuMeasurement, ImuParams, LidarParams, Stamp

    cls = {"dlio": pl.DLIO, "lio-sam": pl.LioSAM}[name]
    pipe = cls()
    params = {
        # DLIO calibrates the IMU over its first imu_calib_time seconds assuming the sensor is
        # at rest: every scenario rests for exactly 2 s, so 1.5 s (default 3 s runs into the motion).
        "dlio": {"imu_calib_time": 1.5},
        # LIO-SAM maps a scan only if mappingProcessInterval (0.15 s) has passed since the last
        # one, i.e. every other 10 Hz scan; evalio's wrapper then repeats the last mapped pose
        # for the skipped scan. 0 maps every scan, as every other method here does.
        "lio-sam": {"numberOfCores": 1, "mappingProcessInterval": 0.0},
    }[name]
    # evalio's own runner passes the defaults merged with the user's parameters: set_params with
    # a partial map leaves the others unset (LIO-SAM then divides by a zero downsampleRate).
    params = {**cls.default_params(), **params}
    unused = pipe.set_params(params)
    if unused:
        raise RuntimeError(f"unused parameters {unused}")
    period = VLP32C_SEQUENCE_S if sc.info["lidar"]["model"] == "vlp32c" else float("nan")
    max_t = float(sc.info["bag"]["max_point_time_s"])
    cols = int(max_t / period) + 1
    imu = sc.imu
    ip = ImuParams(
        gyro=imu["gyro_noise_density_rad_s_sqrt_hz"],
        accel=imu["accel_noise_density_m_s2_sqrt_hz"],
        gyro_bias=imu["gyro_bias_random_walk_rad_s2_sqrt_hz"],
        accel_bias=imu["accel_bias_random_walk_m_s3_sqrt_hz"],
        bias_init=1e-7,
        integration=1e-7,
        gravity=np.array([0.0, 0.0, -float(sc.info["gravity_m_s2"])]),
        rate=float(imu["rate_hz"]),
        brand="TDK",
        model="ICM-42688-P",
    )
    lp = LidarParams(num_rows=sc.rows, num_columns=cols, min_range=1.0, max_range=100.0, rate=10.0, brand="Velodyne", model="VLP-32C")
    pipe.set_imu_params(ip)
    pipe.set_lidar_params(lp)
    q = rot_to_quat_xyzw(sc.t_imu_lidar[:3, :3])
    tt = sc.t_imu_lidar[:3, 3]
    pipe.set_imu_T_lidar(SE3(SO3(qx=q[0], qy=q[1], qz=q[2], qw=q[3]), np.array(tt)))
    pipe.initialize()
    poses, collisions = [], 0
    for m in sc.messages():
        if m[0] == "imu":
            _, t_ns, g, a = m
            mm = ImuMeasurement(Stamp(sec=t_ns // 1_000_000_000, nsec=t_ns % 1_000_000_000), g, a)
            with clock:
                pipe.add_imu(mm)
        else:
            _, start, end, xyz, t, ring, inten = m
            scan, coll = _evalio_scan(sc, start, xyz, t, ring, inten, cols, period)
            collisions += coll
            with clock:
                pipe.add_lidar(scan)
            clock.end_scan()
        for stamp, pose in pipe.saved_estimates():
            t_ns = int(stamp.sec) * 1_000_000_000 + int(stamp.nsec)
            r = quat_xyzw_to_rot([pose.rot.qx, pose.rot.qy, pose.rot.qz, pose.rot.qw])
            poses.append((t_ns, se3(r, np.array(pose.trans))))
    all_params = dict(params)
    all_params["imu_params"] = {
        "gyro": ip.gyro,
        "accel": ip.accel,
        "gyro_bias": ip.gyro_bias,
        "accel_bias": ip.accel_bias,
        "bias_init": ip.bias_init,
        "integration": ip.integration,
        "rate": ip.rate,
    }
    all_params["lidar_params"] = {"num_rows": sc.rows, "num_columns": cols, "min_range": 1.0, "max_range": 100.0, "rate": 10.0}
    notes = [f"evalio {version('evalio')} pipeline {cls.name()} {cls.version()}; estimates are evalio's (IMU frame)"]
    if collisions:
        notes.append(f"{collisions} scans had two points in one range-image pixel")
    return poses, all_params, notes


def peer_version(peer: str) -> str:
    pkg = {"kiss-icp": "kiss-icp", "genz-lio": "genz-lio", "rko-lio": "rko_lio", "dlio": "evalio", "lio-sam": "evalio"}[peer]
    v = f"{pkg} {version(pkg)}"
    if peer in ("dlio", "lio-sam"):
        import evalio.pipelines as pl

        c = {"dlio": pl.DLIO, "lio-sam": pl.LioSAM}[peer]
        v += f" ({c.name()} {c.version()})"
    return v


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("peer", choices=PEERS)
    ap.add_argument("scenario_dir", type=Path)
    ap.add_argument("out_dir", type=Path)
    ap.add_argument("--max-scans", type=int, default=None, help="stop after this many scans (smoke tests)")
    a = ap.parse_args()
    sc = Scenario(a.scenario_dir)
    sc.max_scans = a.max_scans
    a.out_dir.mkdir(parents=True, exist_ok=True)
    clock = Clock()
    result = {
        "peer": a.peer,
        "version": None,
        "scenario": sc.name,
        "bag": str(sc.bag),
        "machine": {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(), "load_avg_before": os.getloadavg()},
        "threads_env": {k: os.environ.get(k) for k in ("OMP_NUM_THREADS", "TBB_NUM_THREADS")},
    }
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    result["machine"]["cpu"] = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    w0 = time.perf_counter()
    try:
        result["version"] = peer_version(a.peer)
        run = {
            "kiss-icp": run_kiss_icp,
            "genz-lio": run_genz_lio,
            "rko-lio": run_rko_lio,
            "dlio": lambda s, c: run_evalio("dlio", s, c),
            "lio-sam": lambda s, c: run_evalio("lio-sam", s, c),
        }[a.peer]
        poses, params, notes = run(sc, clock)
        poses.sort(key=lambda p: p[0])
        write_tum(a.out_dir / f"{sc.name}.tum", poses)
        result.update(status="ok" if not STOPPED else "stopped", poses=len(poses), params=params, notes=notes)
        if STOPPED:
            result["stopped"] = dict(STOPPED)
    except Exception as e:  # noqa: BLE001 - record any failure and carry on with the next peer
        result.update(status="failed", error=f"{type(e).__name__}: {e}", traceback=traceback.format_exc())
        print(traceback.format_exc(), file=sys.stderr)
    result["timing"] = clock.summary()
    result["run_wall_s"] = time.perf_counter() - w0
    result["machine"]["load_avg_after"] = os.getloadavg()
    (a.out_dir / f"{sc.name}.json").write_text(json.dumps(result, indent=2, default=str))
    t = result["timing"]
    print(
        f"{a.peer} {sc.name}: {result['status']}, {result.get('poses', 0)} poses, "
        f"{t.get('wall_ms_per_scan_mean', float('nan')):.1f} ms/scan wall, "
        f"{t.get('cpu_ms_per_scan_mean', float('nan')):.1f} ms/scan CPU"
    )
    return 0 if result["status"] in ("ok", "stopped") else 1


if __name__ == "__main__":
    sys.exit(main())
