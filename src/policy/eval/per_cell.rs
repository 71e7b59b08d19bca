//! An evaluation on drawn cells read cell by cell: each drawn cell's success rate over its own
//! episodes, and how many cells reach a threshold. The activation gate asks its question of one
//! cell (the configured one); this asks it of every cell drawn, so a policy for any cell is seen
//! to pass on each, not only on average.

use super::{EpisodeReport, episode_seed, robot_blocks};
use crate::config::cell::CellConfig;
use crate::sim::EnvOptions;
use crate::sim::randomise::{CellRanges, cell_for};
use serde::Serialize;

/// One cell of an evaluation on drawn cells ([`super::evaluate_on_drawn_cells`]): what was
/// drawn, and how its episodes went.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DrawnCell {
    /// Its kept robot's index (with no kept robots, its episode's index).
    pub index: usize,
    /// The seed it was drawn from (`robot_seed` or `episode_seed` of the evaluation's seed).
    pub draw_seed: u64,
    pub bore_diameter_mm: f64,
    /// (Bore Φ − shaft Φ) / 2, mm.
    pub radial_clearance_mm: f64,
    pub depth_mm: f64,
    /// The robot's lengths over the base cell's (1 = the base cell's robot).
    pub robot_scale: f64,
    /// From the camera to the point it looks at, mm.
    pub camera_distance_mm: f64,
    /// Above the horizontal through that point, deg.
    pub camera_elevation_deg: f64,
    /// The drawn multiples of the data sheet's camera noise and of the cell file's calibration
    /// error.
    pub noise_scale: f64,
    pub calibration_scale: f64,
    pub episodes: usize,
    pub successes: usize,
    pub success_rate: f64,
}

impl DrawnCell {
    /// Whether its success rate reaches `threshold` (the threshold itself passes, as at the
    /// activation gate).
    pub fn reaches(&self, threshold: f64) -> bool {
        self.success_rate >= threshold
    }
}

/// The drawn cells of an evaluation on cells drawn over `ranges` around `base` with `options`
/// and `seed` (as [`super::evaluate_on_drawn_cells`] was called), each with the outcomes of
/// its episodes among `reports`: one cell per kept robot (its block of consecutive episodes),
/// or with `options.kept_robots` = 0 one per episode. Cells are in index order.
pub fn per_drawn_cell(
    base: &CellConfig,
    ranges: &CellRanges,
    options: EnvOptions,
    seed: u64,
    reports: &[EpisodeReport],
) -> Vec<DrawnCell> {
    let episodes = reports.len();
    let cells: Vec<(EnvOptions, u64, std::ops::Range<usize>)> = if options.kept_robots == 0 {
        (0..episodes)
            .map(|index| (options, episode_seed(seed, index), index..index + 1))
            .collect()
    } else {
        robot_blocks(options, episodes, seed)
            .into_iter()
            .map(|(kept, block)| (kept, kept.robot_seed, block))
            .collect()
    };
    cells
        .into_iter()
        .enumerate()
        .map(|(index, (kept, draw_seed, block))| {
            let (cell, drawn) = cell_for(base, &kept, Some(ranges), draw_seed);
            let ran: Vec<&EpisodeReport> = reports
                .iter()
                .filter(|report| block.contains(&report.index))
                .collect();
            let successes = ran.iter().filter(|report| report.succeeded()).count();
            described(&cell, base, drawn, index, draw_seed, ran.len(), successes)
        })
        .collect()
}

fn described(
    cell: &CellConfig,
    base: &CellConfig,
    drawn: EnvOptions,
    index: usize,
    draw_seed: u64,
    episodes: usize,
    successes: usize,
) -> DrawnCell {
    let camera = &cell.camera;
    let towards: Vec<f64> = (0..3)
        .map(|axis| camera.position_mm[axis] - camera.target_mm[axis])
        .collect();
    let distance = towards.iter().map(|d| d * d).sum::<f64>().sqrt();
    DrawnCell {
        index,
        draw_seed,
        bore_diameter_mm: cell.bore.diameter_mm,
        radial_clearance_mm: (cell.bore.diameter_mm - cell.shaft.diameter_mm) / 2.0,
        depth_mm: cell.bore.depth_mm,
        robot_scale: cell.robot.base_radius_mm / base.robot.base_radius_mm,
        camera_distance_mm: distance,
        camera_elevation_deg: (towards[2] / distance).asin().to_degrees(),
        noise_scale: drawn.noise_scale,
        calibration_scale: drawn.calibration_scale,
        episodes,
        successes,
        success_rate: successes as f64 / episodes.max(1) as f64,
    }
}

/// How many of `cells` reach `threshold`.
pub fn reaching(cells: &[DrawnCell], threshold: f64) -> usize {
    cells.iter().filter(|cell| cell.reaches(threshold)).count()
}

#[cfg(test)]
mod tests {
    use super::super::{evaluate_on_drawn_cells, robot_seed};
    use super::*;
    use crate::policy::Controller;
    use crate::sim::PoseErrors;

    fn report(index: usize, outcome: &str) -> EpisodeReport {
        EpisodeReport {
            index,
            seed: 0,
            outcome: outcome.to_string(),
            steps: 1,
            reward: 0.0,
            vetoes: 0,
            final_errors: PoseErrors::default(),
            rules: Default::default(),
        }
    }

    /// Five episodes on two kept robots: blocks 0..2 and 2..5, counted by hand.
    #[test]
    fn each_kept_robots_block_is_its_cells_episodes() {
        let base = CellConfig::reference();
        let options = EnvOptions {
            kept_robots: 2,
            ..EnvOptions::from_cell(&base)
        };
        let reports = [
            report(0, "success"),
            report(1, "step_limit"),
            report(2, "success"),
            report(3, "success"),
            report(4, "success"),
        ];
        let cells = per_drawn_cell(&base, &CellRanges::default(), options, 9, &reports);
        let counted: Vec<(usize, usize, usize, u64)> = cells
            .iter()
            .map(|c| (c.index, c.episodes, c.successes, c.draw_seed))
            .collect();
        assert_eq!(
            counted,
            vec![(0, 2, 1, robot_seed(9, 0)), (1, 3, 3, robot_seed(9, 1))]
        );
        assert_eq!(cells[0].success_rate, 0.5);
        assert_eq!(cells[1].success_rate, 1.0);
        assert_eq!(reaching(&cells, 0.95), 1);
        assert_eq!(reaching(&cells, 0.5), 2, "the threshold itself passes");
        assert_eq!(reaching(&cells, 1.0), 1);

        // No kept robots: a cell per episode, drawn from the episode's seed.
        let fresh = EnvOptions {
            kept_robots: 0,
            ..options
        };
        let cells = per_drawn_cell(&base, &CellRanges::default(), fresh, 9, &reports);
        assert_eq!(cells.len(), 5);
        assert_eq!(cells[3].draw_seed, episode_seed(9, 3));
        assert_eq!(
            cells.iter().map(|c| c.successes).collect::<Vec<_>>(),
            vec![1, 0, 1, 1, 1]
        );
    }

    /// Over a real evaluation the cells' counts sum to the evaluation's, and each cell is the
    /// one its robot ran on (the bore a controller was made for).
    #[test]
    fn the_cells_add_up_to_the_evaluation_and_are_the_ones_run_on() {
        let base = CellConfig::reference();
        let options = EnvOptions {
            kept_robots: 3,
            ..EnvOptions::from_cell(&base)
        };
        let ranges = CellRanges::default();
        let made_for = std::sync::Mutex::new(Vec::new());
        let make = |cell: &CellConfig| -> Box<dyn Controller> {
            made_for.lock().unwrap().push(cell.bore.diameter_mm);
            Box::new(crate::policy::expert::Expert::new(cell))
        };
        let (summary, reports) =
            evaluate_on_drawn_cells(&base, &ranges, options, 7, 4, &make, &|_| {});
        let cells = per_drawn_cell(&base, &ranges, options, 4, &reports);
        assert_eq!(cells.len(), summary.drawn_cells.unwrap());
        assert_eq!(cells.iter().map(|c| c.episodes).sum::<usize>(), 7);
        assert_eq!(
            cells.iter().map(|c| c.successes).sum::<usize>(),
            summary.successes
        );
        let mut made: Vec<f64> = made_for.into_inner().unwrap().split_off(1);
        let mut described: Vec<f64> = cells.iter().map(|c| c.bore_diameter_mm).collect();
        made.sort_by(f64::total_cmp);
        described.sort_by(f64::total_cmp);
        assert_eq!(made, described);
        for cell in &cells {
            assert!((ranges.noise_scale.0..=ranges.noise_scale.1).contains(&cell.noise_scale));
            assert!((ranges.depth_mm.0..=ranges.depth_mm.1).contains(&cell.depth_mm));
        }
    }
}
