//! Which reading of the paper's EQS formula do the paper's own tables support?
//! (`mapless analyze eqs`; the argument is written down in docs/simulator.md.)
//!
//! The paper prints EQS = Σ_{n=1}^{n_max} (n Σ_{k=1}^{k_max} k) over "2 m² segments" and circles
//! of "radius 10n", and reports for every trajectory its EQS and EES = EQS / d, so every row of
//! Tables III–V also gives the trajectory's length d. A reading (cell area, ring width, inner
//! sum) is plausible only if trajectories of that length, in a world of that size, driven by
//! this car, score what the row says without being freaks. So, for each row and reading:
//!
//! ```text
//!   draw N trajectories of length d in an empty box of the row's world size, under the car's
//!   kinematics (the simulator's exact bicycle step), from uniform random starts and headings,
//!   steered by a random smooth process (an Ornstein–Uhlenbeck steering command whose time
//!   constant, spread and bias are drawn per trajectory) that turns away from walls;
//!   score each under the reading; place the paper's EQS in that distribution (mid-rank
//!   percentile); the row fits when it lies between the 2.5th and 97.5th percentiles.
//! ```
//!
//! The row that the paper describes as "repeatedly traversing a circular trajectory in the same
//! vicinity" (DDPG-env2 on env3: EQS 3 over ~150 m) is placed among circling trajectories (a
//! constant steering command near the limit) instead. A reading is supported when every row
//! fits; among those the one whose worst row sits furthest from the tails is chosen. The set-up
//! is ours (the paper gives no trajectories), which is why the test asks only for what holds
//! robustly: the chosen reading fits every row, and the readings that the rows reject, reject.

use rand::{Rng, SeedableRng};
use rand_distr::StandardNormal;
use rand_pcg::Pcg64Mcg;
use serde::Serialize;

use crate::config::{ExplorationConfig, InnerSum, VehicleConfig};
use crate::explore::ExplorationTracker;
use crate::map::Map;
use crate::paper;
use crate::scene::Aabb;
use crate::vehicle::Pose;

/// A reading's name, e.g. `linear, 2.5 m rings, 4 m² cells`. A reading of the printed formula
/// is an [`ExplorationConfig`]: cell area, ring width, inner sum.
pub fn label(r: &ExplorationConfig) -> String {
    let inner = match r.inner_sum {
        InnerSum::Linear => "linear",
        InnerSum::Triangular => "triangular",
    };
    format!("{inner}, {} m rings, {} m² cells", r.ring_width_m, r.cell_area_m2)
}

/// The readings compared: 2 m² (side √2 m) and 2 m × 2 m cells; ring widths from 2 to 10 m;
/// linear and triangular inner sums.
pub fn candidate_readings() -> Vec<ExplorationConfig> {
    let mut v = Vec::new();
    for inner_sum in [InnerSum::Linear, InnerSum::Triangular] {
        for cell_area_m2 in [2.0, 4.0] {
            for ring_width_m in [2.0, 2.5, 3.0, 4.0, 5.0, 7.5, 10.0] {
                v.push(ExplorationConfig { cell_area_m2, ring_width_m, inner_sum });
            }
        }
    }
    v
}

/// One scored trajectory of the paper: a row of Table III, IV or V.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct PaperTrajectory {
    /// e.g. `Table III SAC-env1`.
    pub label: String,
    /// The world it was driven in (our built-in map of that name gives the box size).
    pub world: &'static str,
    pub eqs: f64,
    pub distance_m: f64,
    /// Steps of the trajectory where the paper gives them (Tables III and V), which sets the
    /// speed d / steps; otherwise the car drives at v_max.
    pub steps: Option<u32>,
    pub circling: bool,
}

/// Every row of Tables III–V.
pub fn paper_trajectories() -> Vec<PaperTrajectory> {
    let mut v = Vec::new();
    for (table, rows) in [("III", &paper::TABLE_III), ("IV", &paper::TABLE_IV)] {
        for r in rows.iter() {
            v.push(PaperTrajectory {
                label: format!("Table {table} {}-{}", r.algorithm.to_uppercase(), r.world),
                world: r.world,
                eqs: r.eqs,
                distance_m: r.distance_m(),
                steps: (r.world == "env1").then_some(paper::ENV1_TRAJECTORY_STEPS),
                circling: false,
            });
        }
    }
    for r in &paper::TABLE_V {
        v.push(PaperTrajectory {
            label: format!("Table V {}-{} on env3", r.algorithm.to_uppercase(), r.trained_on),
            world: "env3",
            eqs: r.eqs,
            distance_m: r.distance_m(),
            steps: Some(r.steps),
            circling: r.circling,
        });
    }
    v
}

/// Where one row falls under one reading.
#[derive(Clone, Debug, Serialize)]
pub struct RowFit {
    pub label: String,
    pub paper_eqs: f64,
    /// Mid-rank percentile of the paper's EQS among the simulated trajectories (0–100).
    pub percentile: f64,
    pub p5: f64,
    pub median: f64,
    pub p95: f64,
    pub fits: bool,
}

/// One reading against every row.
#[derive(Clone, Debug, Serialize)]
pub struct ReadingFit {
    pub reading: ExplorationConfig,
    pub label: String,
    pub rows: Vec<RowFit>,
    /// Rows between the 2.5th and 97.5th percentiles.
    pub rows_fitting: usize,
    /// min over rows of min(p, 100 − p): how far the worst row sits from a tail (percent).
    pub worst_tail: f64,
}

/// The whole analysis.
#[derive(Clone, Debug, Serialize)]
pub struct Analysis {
    pub trajectories_per_row: usize,
    pub seed: u64,
    pub rows: Vec<PaperTrajectory>,
    /// Sorted best first: most rows fitting, then largest worst tail.
    pub readings: Vec<ReadingFit>,
}

impl Analysis {
    /// The best reading, if it fits every row.
    pub fn supported(&self) -> Option<&ReadingFit> {
        self.readings.first().filter(|r| r.rows_fitting == self.rows.len())
    }
    pub fn find(&self, reading: &ExplorationConfig) -> Option<&ReadingFit> {
        self.readings.iter().find(|r| &r.reading == reading)
    }

    /// A Markdown page: every reading's percentiles per row, best first.
    pub fn markdown(&self) -> String {
        let mut s = format!(
            "Percentile of each paper row's EQS among {} simulated trajectories of the row's length (seed {}); \
             a row fits between 2.5 and 97.5 (marked `*` when it does not).\n\n",
            self.trajectories_per_row, self.seed
        );
        s += "| reading | fits | worst tail |";
        for r in &self.rows {
            s += &format!(" {} |", r.label.trim_start_matches("Table "));
        }
        s += "\n|---|---|---|";
        s += &"---|".repeat(self.rows.len());
        s += "\n";
        for f in &self.readings {
            s += &format!("| {} | {}/{} | {:.1} |", f.label, f.rows_fitting, f.rows.len(), f.worst_tail);
            for r in &f.rows {
                s += &format!(" {:.1}{} |", r.percentile, if r.fits { "" } else { "*" });
            }
            s += "\n";
        }
        s += "\nRow, the paper's EQS and length, and under the best reading the simulated 5th / 50th / 95th percentiles:\n\n";
        s += "| row | EQS | d (m) | p5 | median | p95 |\n|---|---|---|---|---|---|\n";
        if let Some(best) = self.readings.first() {
            for (row, fit) in self.rows.iter().zip(&best.rows) {
                s += &format!("| {} | {} | {:.1} | {:.0} | {:.0} | {:.0} |\n", row.label, row.eqs, row.distance_m, fit.p5, fit.median, fit.p95);
            }
        }
        s
    }
}

/// Bounds of the empty box standing in for `world` (our built-in map of that name).
fn world_box(world: &str) -> crate::error::Result<Aabb> {
    Ok(Map::builtin(world)?.bounds)
}

/// Distance from (x, y) along heading ψ to the box's edge.
fn ray_to_edge(b: &Aabb, x: f64, y: f64, psi: f64) -> f64 {
    let (s, c) = psi.sin_cos();
    let tx = if c > 1e-12 {
        (b.max_x - x) / c
    } else if c < -1e-12 {
        (b.min_x - x) / c
    } else {
        f64::INFINITY
    };
    let ty = if s > 1e-12 {
        (b.max_y - y) / s
    } else if s < -1e-12 {
        (b.min_y - y) / s
    } else {
        f64::INFINITY
    };
    tx.min(ty).max(0.0)
}

/// One trajectory of length `distance_m` (poses once per step, the start included), or `None`
/// if the car left the box (a collision: such trajectories are redrawn).
pub fn simulate_trajectory(b: &Aabb, row: &PaperTrajectory, vc: &VehicleConfig, rng: &mut Pcg64Mcg) -> Option<Vec<[f64; 2]>> {
    // Circling cars start where a circle of the car's smallest radius stays clear of walls and
    // keep circling (no wall avoidance); wanderers start 1 m from the walls and turn away.
    let margin_m = if row.circling { 3.0 } else { 1.0 };
    let x = rng.random_range(b.min_x + margin_m..b.max_x - margin_m);
    let y = rng.random_range(b.min_y + margin_m..b.max_y - margin_m);
    let mut pose = Pose { x_m: x, y_m: y, heading_rad: rng.random_range(-std::f64::consts::PI..std::f64::consts::PI) };
    let v_max_step = vc.v_max_mps * vc.dt_s;
    let per_step = row.steps.map_or(v_max_step, |n| (row.distance_m / f64::from(n)).min(v_max_step));
    // Circling rows: a speed of 30–100 % of that and a constant steering command near the limit.
    let (per_step, tau_s, sigma, mu) = if row.circling {
        let sign = if rng.random_bool(0.5) { 1.0 } else { -1.0 };
        (per_step * rng.random_range(0.3..1.0), 5.0, 0.05, sign * rng.random_range(0.7..1.0))
    } else {
        (per_step, rng.random_range(0.3f64.ln()..30f64.ln()).exp(), rng.random_range(0.05..1.0), rng.random_range(-0.3..0.3))
    };
    let a_speed = (2.0 * per_step / v_max_step - 1.0) as f32;
    let mut turn: f64 = mu;
    let mut poses = vec![[pose.x_m, pose.y_m]];
    let mut travelled = 0.0;
    let k = vc.dt_s / tau_s;
    while travelled < row.distance_m {
        let n: f64 = rng.sample(StandardNormal);
        turn += (mu - turn) * k + sigma * (2.0 * k).sqrt() * n;
        turn = turn.clamp(-1.0, 1.0);
        // Turn away from a wall closer than 3 m ahead, towards the side with more room.
        let mut cmd = turn;
        if !row.circling && ray_to_edge(b, pose.x_m, pose.y_m, pose.heading_rad) < 3.0 {
            let left = ray_to_edge(b, pose.x_m, pose.y_m, pose.heading_rad + 0.8);
            let right = ray_to_edge(b, pose.x_m, pose.y_m, pose.heading_rad - 0.8);
            cmd = if left >= right { 1.0 } else { -1.0 };
            turn = cmd;
        }
        let c = vc.command(a_speed, cmd as f32);
        let next = vc.advance(pose, c.v_mps, c.steer_rad, vc.dt_s);
        travelled += (next.x_m - pose.x_m).hypot(next.y_m - pose.y_m);
        pose = next;
        if !(b.min_x + 0.3..b.max_x - 0.3).contains(&pose.x_m) || !(b.min_y + 0.3..b.max_y - 0.3).contains(&pose.y_m) {
            return None;
        }
        poses.push([pose.x_m, pose.y_m]);
    }
    Some(poses)
}

fn score(tracker: &mut ExplorationTracker, poses: &[[f64; 2]]) -> u64 {
    tracker.reset(poses[0][0], poses[0][1]);
    for p in &poses[1..] {
        tracker.visit(p[0], p[1], 0.0);
    }
    tracker.eqs()
}

/// Mid-rank percentile of `x` in `sorted` (0–100).
fn percentile_of(sorted: &[u64], x: f64) -> f64 {
    let below = sorted.partition_point(|&v| (v as f64) < x);
    let at_or_below = sorted.partition_point(|&v| (v as f64) <= x);
    100.0 * (below as f64 + 0.5 * (at_or_below - below) as f64) / sorted.len() as f64
}

fn quantile(sorted: &[u64], q: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * q).round() as usize] as f64
}

/// Runs the analysis: `n` trajectories per row, every candidate reading. `progress` is called
/// after each row with (rows done, rows).
pub fn analyze(readings: &[ExplorationConfig], n: usize, seed: u64, mut progress: impl FnMut(usize, usize)) -> crate::error::Result<Analysis> {
    assert!(n >= 1 && !readings.is_empty(), "at least one trajectory per row and one reading");
    let rows = paper_trajectories();
    let vc = VehicleConfig::default();
    // scores[reading][row] = sorted EQS values.
    let mut scores: Vec<Vec<Vec<u64>>> = vec![Vec::with_capacity(rows.len()); readings.len()];
    for (ri, row) in rows.iter().enumerate() {
        let b = world_box(row.world)?;
        let mut trackers: Vec<ExplorationTracker> = readings.iter().map(|r| ExplorationTracker::new(b, r)).collect();
        let mut rng = Pcg64Mcg::seed_from_u64(seed ^ (ri as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15));
        let mut per_reading: Vec<Vec<u64>> = vec![Vec::with_capacity(n); readings.len()];
        let mut drawn = 0;
        while per_reading[0].len() < n {
            drawn += 1;
            assert!(drawn < 1000 * n, "trajectories of {} keep leaving the box", row.label);
            let Some(poses) = simulate_trajectory(&b, row, &vc, &mut rng) else { continue };
            for (t, out) in trackers.iter_mut().zip(per_reading.iter_mut()) {
                out.push(score(t, &poses));
            }
        }
        for (s, mut v) in scores.iter_mut().zip(per_reading) {
            v.sort_unstable();
            s.push(v);
        }
        progress(ri + 1, rows.len());
    }
    let mut fits: Vec<ReadingFit> = readings
        .iter()
        .zip(&scores)
        .map(|(reading, per_row)| {
            let rows: Vec<RowFit> = rows
                .iter()
                .zip(per_row)
                .map(|(row, sorted)| {
                    let p = percentile_of(sorted, row.eqs);
                    RowFit {
                        label: row.label.clone(),
                        paper_eqs: row.eqs,
                        percentile: p,
                        p5: quantile(sorted, 0.05),
                        median: quantile(sorted, 0.5),
                        p95: quantile(sorted, 0.95),
                        fits: (2.5..=97.5).contains(&p),
                    }
                })
                .collect();
            let rows_fitting = rows.iter().filter(|r| r.fits).count();
            let worst_tail = rows.iter().map(|r| r.percentile.min(100.0 - r.percentile)).fold(f64::INFINITY, f64::min);
            ReadingFit { reading: reading.clone(), label: label(reading), rows, rows_fitting, worst_tail }
        })
        .collect();
    fits.sort_by(|a, b| b.rows_fitting.cmp(&a.rows_fitting).then(b.worst_tail.total_cmp(&a.worst_tail)));
    Ok(Analysis { trajectories_per_row: n, seed, rows, readings: fits })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_default_reading_fits_every_row_and_the_rejected_ones_do_not() {
        let first_guess = ExplorationConfig { cell_area_m2: 2.0, ring_width_m: 10.0, inner_sum: InnerSum::Linear };
        let literal = ExplorationConfig { inner_sum: InnerSum::Triangular, ..first_guess.clone() };
        let default = ExplorationConfig::default();
        let a = analyze(&[first_guess.clone(), literal.clone(), default.clone()], 300, 11, |_, _| {}).unwrap();
        let fit = a.find(&default).unwrap();
        assert_eq!(fit.rows_fitting, 12, "{}", a.markdown());
        assert!(fit.worst_tail > 5.0, "{}", a.markdown());
        assert_eq!(a.supported().unwrap().reading, default);
        // Our first guess: no simulated 34.6 m trajectory in env1 reaches SAC's 91.
        let g = a.find(&first_guess).unwrap();
        let sac = g.rows.iter().find(|r| r.label == "Table III SAC-env1").unwrap();
        assert!(sac.percentile > 97.5, "{}", a.markdown());
        assert!(g.rows_fitting <= 6);
        // The printed formula taken literally: TD3-env2's 25 over 16 m is below almost all.
        let l = a.find(&literal).unwrap();
        let td3 = l.rows.iter().find(|r| r.label == "Table V TD3-env2 on env3").unwrap();
        assert!(td3.percentile < 2.5, "{}", a.markdown());
        assert!(l.rows_fitting <= 3);
    }

    #[test]
    fn percentiles_are_mid_ranks() {
        let s = [1, 2, 2, 3];
        assert_eq!(percentile_of(&s, 0.0), 0.0);
        assert_eq!(percentile_of(&s, 2.0), 50.0);
        assert_eq!(percentile_of(&s, 9.0), 100.0);
    }

    #[test]
    fn trajectories_have_the_rows_length_and_stay_in_the_box() {
        let b = world_box("env1").unwrap();
        let row = &paper_trajectories()[2]; // Table III SAC-env1, 34.6 m in 1000 steps
        let mut rng = Pcg64Mcg::seed_from_u64(7);
        let mut ok = 0;
        for _ in 0..50 {
            if let Some(p) = simulate_trajectory(&b, row, &VehicleConfig::default(), &mut rng) {
                let d: f64 = p.windows(2).map(|w| (w[1][0] - w[0][0]).hypot(w[1][1] - w[0][1])).sum();
                assert!(d >= row.distance_m && d < row.distance_m + 0.051, "{d}");
                // 0.0346 m per step: 1000 steps, as the paper's trajectory.
                assert!((p.len() as i64 - 1001).abs() <= 1, "{}", p.len());
                assert!(p.iter().all(|q| b.contains(q[0], q[1])));
                ok += 1;
            }
        }
        assert!(ok >= 45, "{ok} of 50 stayed in the box");
    }
}
