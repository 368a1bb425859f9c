#!/usr/bin/env python3
"""Runs loglio on one scenario exported by `sim2bag`, as the peers are run (docs/peers.md).

    run_loglio.py LOGLIO SCENARIO_DIR OUT_DIR [--mode full|plane-only|plain]

Writes a configuration with the data's facts taken from `scenario.json` exactly as
run_peer.py hands them to the peers (the extrinsic T_imu_lidar, the IMU's noise densities and
bias random walks, gravity), everything else the `vlp32c` preset's, the same for every
scenario; then runs `loglio bag BAG --config TOML --mode MODE --out OUT_DIR/<scenario>
--no-map` and writes, for evaluate.py's `--extra NAME=OUT_DIR`:

- `OUT_DIR/<scenario>.tum`: loglio's trajectory.tum (T_world_imu at each scan end),
- `OUT_DIR/<scenario>.json`: `ms_per_scan`, the mean of scans.csv's `process_ms` (the wall
  time inside the core's process_scan for each scan, the same span the peers' timing covers:
  loglio's IMU ingestion is a queue push and is not in it), over every scan in scans.csv;
  `process_cpu_ms_per_scan`, the whole process's CPU time (user + sys, bag reading, decoding
  and output included: an upper bound, not the in-call CPU the peers report) divided by the
  scans; the statuses; the configuration; the load average.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path


def config_toml(info: dict, mode: str, max_points: int | None = None) -> str:
    e = info["extrinsic_imu_lidar"]
    x, y, z, w = e["quaternion_xyzw"]
    t = e["translation_m"]
    imu = info["imu"]
    return (
        'preset = "vlp32c"\n'
        "[imu]\n"
        f"gyro_noise = {imu['gyro_noise_density_rad_s_sqrt_hz']!r}\n"
        f"acc_noise = {imu['accel_noise_density_m_s2_sqrt_hz']!r}\n"
        f"gyro_bias_walk = {imu['gyro_bias_random_walk_rad_s2_sqrt_hz']!r}\n"
        f"acc_bias_walk = {imu['accel_bias_random_walk_m_s3_sqrt_hz']!r}\n"
        f"gravity = {info['gravity_m_s2']!r}\n"
        "[extrinsics]\n"
        f"translation = [{t[0]!r}, {t[1]!r}, {t[2]!r}]\n"
        f"rotation_quat_wxyz = [{w!r}, {x!r}, {y!r}, {z!r}]\n"
        "[mapping]\n"
        f'association = "{mode}"\n'
        + (f"max_points = {max_points}\n" if max_points is not None else "")
    )


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("loglio")
    ap.add_argument("scenario_dir", type=Path)
    ap.add_argument("out_dir", type=Path)
    ap.add_argument("--mode", default="full", choices=("full", "plane-only", "plain"))
    ap.add_argument("--max-points", type=int, default=None, help="measurement budget (mapping.max_points; 0 = all; default: loglio's, 5000)")
    a = ap.parse_args()
    info = json.loads((a.scenario_dir / "scenario.json").read_text())
    name = info["scenario"]
    bag = a.scenario_dir / info["bag"]["file"]
    a.out_dir.mkdir(parents=True, exist_ok=True)
    run_dir = a.out_dir / name
    if run_dir.exists():
        shutil.rmtree(run_dir)
    run_dir.mkdir()
    toml = run_dir / "config.toml"
    toml.write_text(config_toml(info, a.mode, a.max_points))
    cmd = [
        a.loglio, "bag", str(bag), "--lidar-topic", info["bag"]["lidar_topic"], "--imu-topic", info["bag"]["imu_topic"],
        "--config", str(toml), "--mode", a.mode, "--out", str(run_dir), "--no-map",
    ]  # fmt: skip
    load_before = os.getloadavg()
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    w0 = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - w0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    (run_dir / "stdout.txt").write_text(p.stdout)
    (run_dir / "stderr.txt").write_text(p.stderr)
    result = {
        "method": f"loglio ({a.mode})" if a.max_points is None else f"loglio ({a.mode}, max_points {a.max_points})",
        "scenario": name,
        "bag": str(bag),
        "command": cmd,
        "config": toml.read_text(),
        "returncode": p.returncode,
        "run_wall_s": wall,
        "process_cpu_s": cpu,
        "load_avg_before": load_before,
        "load_avg_after": os.getloadavg(),
    }
    scans = []
    if (run_dir / "scans.csv").exists():
        with open(run_dir / "scans.csv") as f:
            scans = list(csv.DictReader(f))
    if p.returncode != 0 or not scans:
        result["status"] = "failed"
        result["error"] = (p.stderr or p.stdout).strip()[-2000:]
    else:
        ms = [float(s["process_ms"]) for s in scans]
        ms_sorted = sorted(ms)
        statuses: dict[str, int] = {}
        for s in scans:
            statuses[s["status"]] = statuses.get(s["status"], 0) + 1
        result.update(
            status="ok",
            scans=len(scans),
            ms_per_scan=sum(ms) / len(ms),
            ms_per_scan_median=ms_sorted[len(ms) // 2],
            ms_per_scan_max=ms_sorted[-1],
            process_cpu_ms_per_scan=cpu * 1e3 / len(scans),
            statuses=statuses,
        )
        shutil.copyfile(run_dir / "trajectory.tum", a.out_dir / f"{name}.tum")
    (a.out_dir / f"{name}.json").write_text(json.dumps(result, indent=2))
    print(
        f"loglio-{a.mode} {name}: {result['status']}, {result.get('scans', 0)} scans, "
        f"{result.get('ms_per_scan', float('nan')):.1f} ms/scan (process_ms), "
        f"{result.get('process_cpu_ms_per_scan', float('nan')):.1f} ms/scan whole-process CPU, {result.get('statuses')}"
    )
    return 0 if result["status"] == "ok" else 1


if __name__ == "__main__":
    sys.exit(main())
