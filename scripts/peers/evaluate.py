#!/usr/bin/env python3
"""ATE of every peer (and optional extra trajectories, e.g. loglio's) on every scenario.

    evaluate.py --bags BAGS --results RESULTS [--extra NAME=DIR ...] [--loglio PATH]

BAGS holds one folder per scenario (from sim2bag: groundtruth.tum, scans.csv); RESULTS holds
RESULTS/<peer>/<scenario>.tum and .json (from run_peer.py). Each --extra NAME=DIR adds a column
NAME read from DIR/<scenario>.tum (or DIR/<scenario>/trajectory.tum), with its status and
timing, when present, from DIR/<scenario>.json (as run_loglio.py writes it): {"status": ..,
"ms_per_scan": .., "cpu_ms_per_scan": .., "process_cpu_ms_per_scan": ..} (all optional).

The ATE is `loglio eval GT EST --align se3 --json` (evo's definitions: each estimated pose
paired with the ground-truth pose nearest in time, SE(3) Umeyama alignment on the positions,
RMSE of the position errors). The ground truth has a pose at every scan's start, middle and
end, so every peer's stamp finds its exact truth; --t-max-diff 2 ms (the truth also has every
200 Hz IMU sample, so a stamp elsewhere is still paired within 2.5 ms) and the largest
pairing gap is reported.

Writes RESULTS/summary.json, RESULTS/summary.csv and RESULTS/summary.md (the peers table of docs/figures.md).
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
from pathlib import Path

PEERS = ("genz-lio", "rko-lio", "kiss-icp", "dlio", "lio-sam")
SCENARIOS = ("vehicle", "handheld", "corridor", "drone", "rotation")


def stamps(path: Path):
    out = []
    for line in path.read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        t = line.split()[0]
        s, _, f = t.partition(".")
        out.append(int(s) * 1_000_000_000 + int((f or "0").ljust(9, "0")[:9]))
    return out


def max_gap_ms(gt: list[int], est: list[int]) -> float:
    import bisect

    worst = 0
    for t in est:
        i = bisect.bisect_left(gt, t)
        d = min(abs(gt[j] - t) for j in (i - 1, i) if 0 <= j < len(gt))
        worst = max(worst, d)
    return worst / 1e6


def run_eval(loglio: list[str], gt: Path, est: Path, offset: float = 0.0, max_diff: float = 0.002):
    cmd = [*loglio, "eval", str(gt), str(est), "--align", "se3", "--t-max-diff", str(max_diff), "--json"]
    if offset:
        cmd += ["--t-offset", f"{offset:.3f}"]
    p = subprocess.run(cmd, capture_output=True, text=True)
    if p.returncode != 0:
        return {"error": (p.stderr or p.stdout).strip()}
    return json.loads(p.stdout)


def evaluate(loglio: list[str], gt: Path, est: Path):
    r = run_eval(loglio, gt, est)
    if "error" in r:
        return r
    r["max_pair_gap_ms"] = max_gap_ms(stamps(gt), stamps(est))
    # Diagnostic only (not the headline figure): the ATE with the estimate's stamps shifted by
    # the offset in [-0.3, 0.3] s (10 ms steps) that minimises it, to expose a pose stamped at
    # another time than the one it describes (a wrapper's convention, a processing lag).
    best = (r["ape_trans_m"]["rmse"], 0.0)
    for k in range(-30, 31):
        if k == 0:
            continue
        o = k * 0.01
        q = run_eval(loglio, gt, est, offset=o, max_diff=0.003)
        if "error" not in q and q["matched"] >= 0.95 * r["matched"] and q["ape_trans_m"]["rmse"] < best[0]:
            best = (q["ape_trans_m"]["rmse"], o)
    r["ate_best_offset_m"], r["best_offset_s"] = best
    return r


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bags", type=Path, required=True)
    ap.add_argument("--results", type=Path, required=True)
    ap.add_argument("--extra", action="append", default=[], metavar="NAME=DIR")
    ap.add_argument("--loglio", default="target/release/loglio", help="the loglio binary (for `loglio eval`)")
    ap.add_argument(
        "--scenarios",
        default=" ".join(SCENARIOS),
        help="scenarios to evaluate, space-separated (default: the five static ones; run-all passes its own)",
    )
    a = ap.parse_args()
    scenarios = a.scenarios.split()
    loglio = [a.loglio]

    columns = []  # (name, tum(scenario), timing(scenario))
    for peer in PEERS:
        d = a.results / peer

        def tum(s, d=d):
            return d / f"{s}.tum"

        def timing(s, d=d):
            j = d / f"{s}.json"
            if not j.exists():
                return None
            r = json.loads(j.read_text())
            return r

        columns.append((peer, tum, timing))
    for e in a.extra:
        name, _, dir_ = e.partition("=")
        d = Path(dir_)

        def tum(s, d=d):
            p = d / f"{s}.tum"
            return p if p.exists() else d / s / "trajectory.tum"

        def timing(s, d=d):
            j = d / f"{s}.json"
            if not j.exists():
                return None
            r = json.loads(j.read_text())
            return {
                "status": r.get("status", "ok"),
                "error": r.get("error"),
                "timing": {
                    "wall_ms_per_scan_mean": r.get("ms_per_scan"),
                    "wall_ms_per_scan_median": r.get("ms_per_scan_median"),
                    "cpu_ms_per_scan_mean": r.get("cpu_ms_per_scan"),
                    # run_loglio.py: the whole process's CPU per scan (an upper bound).
                    "process_cpu_ms_per_scan": r.get("process_cpu_ms_per_scan"),
                },
                "machine": {"load_avg_before": r.get("load_avg_before"), "load_avg_after": r.get("load_avg_after")},
            }

        columns.append((name, tum, timing))

    rows = []
    for s in scenarios:
        gt = a.bags / s / "groundtruth.tum"
        if not gt.exists():
            print(f"no ground truth for {s} ({gt}), skipped", file=sys.stderr)
            continue
        n_scans = sum(1 for _ in open(a.bags / s / "scans.csv")) - 1
        for name, tum, timing in columns:
            row = {"scenario": s, "method": name, "scans": n_scans}
            info = timing(s)
            t = tum(s)
            if info is not None and info.get("status") == "stopped":
                row["stopped"] = info.get("stopped")
            if info is not None and info.get("status") not in ("ok", "stopped"):
                row["status"] = "failed"
                row["error"] = info.get("error")
            elif not t.exists() or len(stamps(t)) == 0:
                row["status"] = "missing" if info is None else "no poses"
            else:
                ev = evaluate(loglio, gt, t)
                if "error" in ev:
                    row.update(status="eval failed", error=ev["error"])
                else:
                    row.update(
                        status="ok",
                        poses=ev["est_poses"],
                        matched=ev["matched"],
                        ate_rmse_m=ev["ape_trans_m"]["rmse"],
                        ate_max_m=ev["ape_trans_m"]["max"],
                        ape_rot_rmse_deg=ev["ape_rot_deg"]["rmse"],
                        max_pair_gap_ms=ev["max_pair_gap_ms"],
                        ate_best_offset_m=ev["ate_best_offset_m"],
                        best_offset_s=ev["best_offset_s"],
                    )
            if info is not None and "timing" in info:
                tm = info["timing"]
                row["wall_ms_per_scan"] = tm.get("wall_ms_per_scan_mean")
                row["wall_ms_per_scan_median"] = tm.get("wall_ms_per_scan_median")
                row["cpu_ms_per_scan"] = tm.get("cpu_ms_per_scan_mean")
                if tm.get("process_cpu_ms_per_scan") is not None:
                    row["process_cpu_ms_per_scan"] = tm["process_cpu_ms_per_scan"]
                if "machine" in info:
                    row["load_avg_before"] = (info["machine"].get("load_avg_before") or [None])[0]
                    row["load_avg_after"] = (info["machine"].get("load_avg_after") or [None])[0]
            rows.append(row)
            print(
                f"{s:9} {name:10} {row.get('status'):9} ATE {row.get('ate_rmse_m', float('nan')):.4f} m, "
                f"{row.get('wall_ms_per_scan') or float('nan'):.1f} ms/scan wall, "
                f"{row.get('cpu_ms_per_scan') or float('nan'):.1f} ms/scan CPU"
            )

    a.results.mkdir(parents=True, exist_ok=True)
    (a.results / "summary.json").write_text(json.dumps(rows, indent=2))
    keys = sorted({k for r in rows for k in r}, key=lambda k: (k not in ("scenario", "method", "status"), k))
    with open(a.results / "summary.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)

    # Markdown: one row per scenario, one column per method: "ATE m / ms per scan (CPU ms)".
    names = [c[0] for c in columns]
    by = {(r["scenario"], r["method"]): r for r in rows}

    def cell(r):
        if r is None:
            return "see note"
        if r.get("status") != "ok":
            return r.get("status", "?")
        ms = r.get("wall_ms_per_scan")
        cpu = r.get("cpu_ms_per_scan")
        t = f" / {ms:.1f} ms" if ms is not None else ""
        t += f" ({cpu:.1f} CPU)" if cpu is not None else ""
        if cpu is None and r.get("process_cpu_ms_per_scan") is not None:
            t += f" (<= {r['process_cpu_ms_per_scan']:.1f} CPU, whole process)"
        partial = "" if r["matched"] >= 0.95 * r["scans"] else f" [{r['matched']}/{r['scans']} poses]"
        if r.get("stopped"):
            partial = f" [stopped at scan {r['stopped']['at_scan']}: {r['stopped']['error']}]"
        shifted = ""
        if r["ate_best_offset_m"] < 0.8 * r["ate_rmse_m"]:
            shifted = f" [{r['ate_best_offset_m']:.3f} m at {r['best_offset_s'] * 1e3:+.0f} ms]"
        return f"{r['ate_rmse_m']:.3f} m{t}{partial}{shifted}"

    md = ["| scenario | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    for s in scenarios:
        if not any(k[0] == s for k in by):
            continue
        md.append(f"| {s} | " + " | ".join(cell(by.get((s, n))) for n in names) + " |")
    (a.results / "summary.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
