use assembly_cell::config::cell::CellConfig;
use assembly_cell::policy::{self, eval};
use assembly_cell::sim::EnvOptions;
fn main() {
    let args: Vec<String> = std::env::args().collect();
    let name = args.get(1).cloned().unwrap_or("expert".into());
    for off in ["", "nonoise", "nocal", "noexec", "nolat", "nodrop", "all"] {
        let mut cell = CellConfig::reference();
        let i = &mut cell.imperfections;
        match off {
            "nonoise" => i.camera_noise = false,
            "nocal" => i.calibration_error = false,
            "noexec" => i.execution_error = false,
            "nolat" => i.latency = false,
            "nodrop" => {
                i.dropped_points = false;
                i.outliers = false
            }
            "all" => {
                i.camera_noise = false;
                i.calibration_error = false;
                i.execution_error = false;
                i.latency = false;
                i.dropped_points = false;
                i.outliers = false
            }
            _ => {}
        }
        let make = || policy::builtin(&name, &cell).unwrap();
        let (s, _) = eval::evaluate(&cell, EnvOptions::from_cell(&cell), 500, 1, &make, &|_| {});
        println!(
            "{off:8} success {:.3} steps {:?} vetoes {:.2} failures {:?}",
            s.success_rate, s.avg_steps, s.avg_vetoes, s.failures
        );
    }
}
