//! The files a run writes, a sink of its own: the trajectory (TUM) and per-scan CSV as scans
//! come, the map, plots and evaluation at the end.

use std::io;
use std::path::{Path, PathBuf};

use loglio_core::eskf::PropagationFlags;
use loglio_core::output::{ScanResult, Status};
use nalgebra::{Quaternion, UnitQuaternion, Vector3};

use crate::error::PipelineError;
use crate::eval::{self, EvalOptions, EvalReport, Trajectory};
use crate::output::{self, PcdEncoding, ScanCsvWriter, ScanRecord, TumWriter};
use crate::run::engine::Engine;
use crate::run::runner::scan_status;

/// Where and what to write.
#[derive(Clone, Debug, Default)]
pub struct OutputOptions {
    /// The output directory (`None`: write nothing).
    pub dir: Option<PathBuf>,
    /// A ground truth to evaluate against (ATE, error plot).
    pub gt: Option<Trajectory>,
    /// Write the map (PLY and PCD).
    pub map: bool,
    /// Write the plots (PNG and SVG).
    pub plots: bool,
}

/// One pose of the estimated trajectory.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EstPose {
    /// Scan end, ns.
    pub t_ns: u64,
    /// IMU position in the world, m.
    pub p: [f64; 3],
    /// IMU orientation in the world (w, x, y, z).
    pub q_wxyz: [f64; 4],
}

/// The streaming outputs: trajectory (TUM) and per-scan CSV, written as scans come; map, plots
/// and evaluation at [`Outputs::finish`]. [`Outputs::flush`] makes the files whole at any time.
#[derive(Debug)]
pub struct Outputs {
    opt: OutputOptions,
    tum: Option<TumWriter>,
    csv: Option<ScanCsvWriter>,
    /// Every pose written (for the plots and the evaluation).
    pub poses: Vec<EstPose>,
    /// A scan was predicted without IMU (LiDAR-only): `eval.json` says so.
    lidar_only: bool,
}

/// What [`Outputs::finish`] produced.
#[derive(Clone, Debug, Default)]
pub struct Finished {
    /// Files written.
    pub files: Vec<PathBuf>,
    /// The evaluation against the ground truth, if one was given.
    pub eval: Option<EvalReport>,
    /// Map points written.
    pub map_points: usize,
}

impl Outputs {
    /// Opens the streaming files in `opt.dir` (created if missing).
    pub fn new(opt: OutputOptions) -> Result<Outputs, PipelineError> {
        let (tum, csv) = match &opt.dir {
            Some(d) => (
                Some(TumWriter::create(&d.join("trajectory.tum"))?),
                Some(ScanCsvWriter::create(&d.join("scans.csv"))?),
            ),
            None => (None, None),
        };
        Ok(Outputs { opt, tum, csv, poses: Vec::new(), lidar_only: false })
    }

    /// Records one scan's result.
    pub fn record(
        &mut self,
        index: u64,
        res: &ScanResult,
        process_ms: f64,
        map_voxels: usize,
    ) -> io::Result<()> {
        let pose = &res.pose;
        self.lidar_only |= res.propagation.has(PropagationFlags::LIDAR_ONLY);
        let initialising = matches!(res.status, Status::Initialising(_));
        let q = pose.rotation.quaternion();
        let e = EstPose {
            t_ns: pose.t_ns,
            p: [pose.position.x, pose.position.y, pose.position.z],
            q_wxyz: [q.w, q.i, q.j, q.k],
        };
        // Before the IMU initialisation the pose is a placeholder: not part of the trajectory.
        if !initialising {
            self.poses.push(e);
            if let Some(t) = &mut self.tum {
                t.write(e.t_ns, e.p, e.q_wxyz)?;
            }
        }
        if let Some(c) = &mut self.csv {
            let a = &res.associations;
            c.write(&ScanRecord {
                index,
                start_ns: res.scan_start_ns,
                end_ns: pose.t_ns,
                points_in: res.points[0],
                points_used: res.points[1],
                large_surfel: a.large_surfel,
                small_surfel: a.small_surfel,
                point_to_plane: a.plane,
                unmatched: res.points[1].saturating_sub(a.accepted()),
                iterations: res.update.iterations as u32,
                status: scan_status(&res.status),
                process_ms,
                map_voxels: map_voxels as u64,
            })?;
        }
        // Whole lines on disk after every scan: a crash or a power cut loses nothing estimated.
        self.flush()
    }

    /// Sets the ground truth to evaluate against at [`Self::finish`].
    pub fn set_ground_truth(&mut self, gt: Option<Trajectory>) {
        self.opt.gt = gt;
    }

    /// Flushes the streaming files (Ctrl-C).
    pub fn flush(&mut self) -> io::Result<()> {
        if let Some(t) = &mut self.tum {
            t.flush()?;
        }
        if let Some(c) = &mut self.csv {
            c.flush()?;
        }
        Ok(())
    }

    /// The estimate as an evaluation trajectory.
    pub fn trajectory(&self) -> Trajectory {
        let mut stamps = Vec::with_capacity(self.poses.len());
        let mut poses = Vec::with_capacity(self.poses.len());
        for p in &self.poses {
            stamps.push(p.t_ns as f64 * 1e-9);
            let [w, x, y, z] = p.q_wxyz;
            let r = UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z))
                .to_rotation_matrix()
                .into_inner();
            poses.push(eval::Pose { r, t: Vector3::from(p.p) });
        }
        Trajectory { stamps: Some(stamps), poses }
    }

    /// Closes the streams and writes the map, the plots and the evaluation.
    pub fn finish(mut self, engine: &dyn Engine) -> Result<Finished, PipelineError> {
        let mut out = Finished::default();
        self.flush()?;
        if let Some(t) = self.tum.take() {
            t.finish()?;
        }
        if let Some(c) = self.csv.take() {
            c.finish()?;
        }
        if let Some(gt) = &self.opt.gt {
            let est = self.trajectory();
            if est.len() >= 3 {
                let opt = EvalOptions::default(); // evo's defaults: SE(3), 10 ms pairing
                match eval::evaluate(gt, &est, &opt) {
                    Ok(r) => out.eval = Some(r),
                    Err(e) => crate::diag::warn(format!("no evaluation against the ground truth: {e}")),
                }
            } else {
                crate::diag::warn("no evaluation against the ground truth: fewer than 3 poses");
            }
        }
        let Some(dir) = self.opt.dir.clone() else { return Ok(out) };
        out.files.push(dir.join("trajectory.tum"));
        out.files.push(dir.join("scans.csv"));
        if self.opt.map {
            let mut pts = Vec::new();
            engine.map_points(&mut pts);
            out.map_points = pts.len();
            let ply = dir.join("map.ply");
            output::write_ply_file(&ply, &pts, true)?;
            let pcd = dir.join("map.pcd");
            output::write_pcd_file(&pcd, &pts, true, PcdEncoding::Binary)?;
            out.files.extend([ply, pcd]);
        }
        if self.opt.plots {
            let est: Vec<[f64; 3]> = self.poses.iter().map(|p| p.p).collect();
            for ext in ["png", "svg"] {
                let p = dir.join(format!("trajectory.{ext}"));
                match &out.eval {
                    Some(r) => output::plot_trajectory_top_view(
                        &p,
                        "Trajectory, top view (SE(3)-aligned to the ground truth)",
                        "loglio",
                        &r.est_positions,
                        Some(&r.gt_positions),
                    ),
                    None => {
                        output::plot_trajectory_top_view(&p, "Trajectory, top view", "loglio", &est, None)
                    }
                }
                .map_err(|e| PipelineError(e.0))?;
                out.files.push(p);
                if let Some(r) = &out.eval {
                    let p = dir.join(format!("error.{ext}"));
                    let title = format!("APE translation (SE(3)-aligned), rmse {:.3} m", r.ape_trans.rmse);
                    output::plot_error_over_time(
                        &p,
                        &title,
                        "time since start [s]",
                        "error [m]",
                        &r.ape_series,
                    )
                    .map_err(|e| PipelineError(e.0))?;
                    out.files.push(p);
                }
            }
        }
        if let Some(r) = &out.eval {
            let p = dir.join("eval.json");
            let mut json = r.to_json();
            if self.lidar_only {
                // The motion model first: a LiDAR-only figure is not a LiDAR-inertial one.
                json.replace_range(..1, "{\"motion_model\": \"lidar-only (no IMU): constant velocity\", ");
            }
            std::fs::write(&p, json).map_err(|e| PipelineError(format!("{}: {e}", p.display())))?;
            out.files.push(p);
        }
        Ok(out)
    }
}

/// Writes a trajectory as TUM (for the ground truth of simulated runs).
pub fn write_tum(path: &Path, poses: &[EstPose]) -> Result<(), PipelineError> {
    let mut w = TumWriter::create(path)?;
    for p in poses {
        w.write(p.t_ns, p.p, p.q_wxyz)?;
    }
    w.finish()?;
    Ok(())
}
