use loglio_firmware_sim::lidar::SensorModel;
use loglio_firmware_sim::scenario::{Scenario, ScenarioKind};
use std::time::Instant;
fn main() {
    for kind in [ScenarioKind::Vehicle, ScenarioKind::Handheld, ScenarioKind::Corridor, ScenarioKind::Drone] {
        let t = Instant::now();
        let sc = Scenario::new(kind, SensorModel::Vlp32c, 1);
        let build = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let mut pts = 0;
        let n = 20;
        for j in 0..n {
            pts += sc.scan(j * 10).points.len();
        }
        let dt = t.elapsed().as_secs_f64();
        let rays = n as f64 * 32.0 * 1809.0;
        println!(
            "{kind:?}: build {build:.2}s; {n} scans {dt:.2}s -> {:.2} Mrays/s, {:.0} pts/scan",
            rays / dt / 1e6,
            pts as f64 / n as f64
        );
    }
}
