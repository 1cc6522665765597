//! Exploration Quality Score and Exploration Efficiency Score (paper §IV-B).
//!
//! The paper writes EQS = Σₙ (n Σₖ k) over rings n of radius 10n around the start, k counting
//! the 2 m² segments the trajectory covers. Our reading (SPEC §1; settled against the paper's
//! Tables III–V by `mapless analyze eqs`, see docs/simulator.md), every size configurable:
//!
//! ```text
//!   cells: squares of side 2 m (the paper's "2 m² segments"), a fixed grid anchored at the
//!          map's min corner
//!   ring of a cell: n = ⌊ |centre − start| / w ⌋ + 1,  w = 2.5 m
//!   k_n = number of distinct cells of ring n whose square the vehicle's centre enters
//!   EQS = Σₙ n · k_n            EES = EQS / path length (m)   (0 for a path of length 0)
//! ```
//!
//! The other readings stay selectable: any ring width, and the printed inner sum taken
//! literally (`inner_sum: triangular`, EQS = Σₙ n · k_n (k_n + 1) / 2).
//!
//! Cells are recorded at every pose the simulator reports (once per step, and at the start),
//! so the start cell always counts. Time in shaded regions is also accumulated here.

use crate::config::{ExplorationConfig, InnerSum};
use crate::scene::Aabb;

/// Per-episode exploration bookkeeping. O(1) per visit; memory one bit per cell.
#[derive(Clone, Debug)]
pub struct ExplorationTracker {
    origin: (f64, f64),
    side_m: f64,
    ring_m: f64,
    inner: InnerSum,
    /// k_n per ring (index n − 1), for the triangular inner sum.
    ring_cells: Vec<u32>,
    nx: usize,
    ny: usize,
    visited: Vec<u64>,
    start: (f64, f64),
    last: (f64, f64),
    eqs: u64,
    cells: u32,
    distance_m: f64,
    shaded_s: f64,
}

impl ExplorationTracker {
    pub fn new(bounds: Aabb, cfg: &ExplorationConfig) -> Self {
        let side = cfg.cell_area_m2.sqrt();
        let nx = (bounds.width() / side).ceil().max(1.0) as usize;
        let ny = (bounds.height() / side).ceil().max(1.0) as usize;
        ExplorationTracker {
            origin: (bounds.min_x, bounds.min_y),
            side_m: side,
            ring_m: cfg.ring_width_m,
            inner: cfg.inner_sum,
            ring_cells: Vec::new(),
            nx,
            ny,
            visited: vec![0; (nx * ny).div_ceil(64)],
            start: (0.0, 0.0),
            last: (0.0, 0.0),
            eqs: 0,
            cells: 0,
            distance_m: 0.0,
            shaded_s: 0.0,
        }
    }

    /// Where the episode started (x, y in metres): the centre of the EQS rings.
    pub fn start(&self) -> (f64, f64) {
        self.start
    }

    /// Starts a new episode at (x, y).
    pub fn reset(&mut self, x: f64, y: f64) {
        self.visited.fill(0);
        self.ring_cells.clear();
        self.start = (x, y);
        self.last = (x, y);
        self.eqs = 0;
        self.cells = 0;
        self.distance_m = 0.0;
        self.shaded_s = 0.0;
        self.mark(x, y);
    }

    /// Records the next pose; `shaded_dt_s` is the time to credit to shaded regions (0 if the
    /// vehicle is not in one). Returns what the pose added to the EQS: 0 when its cell was
    /// visited before, more when it enters a new one.
    #[inline]
    pub fn visit(&mut self, x: f64, y: f64, shaded_dt_s: f64) -> u64 {
        self.distance_m += (x - self.last.0).hypot(y - self.last.1);
        self.last = (x, y);
        self.shaded_s += shaded_dt_s;
        self.mark(x, y)
    }

    #[inline]
    fn mark(&mut self, x: f64, y: f64) -> u64 {
        // Clamped at 0 first, so truncation is floor.
        let i = (((x - self.origin.0) / self.side_m).max(0.0) as usize).min(self.nx - 1);
        let j = (((y - self.origin.1) / self.side_m).max(0.0) as usize).min(self.ny - 1);
        let k = j * self.nx + i;
        let (word, bit) = (k / 64, 1u64 << (k % 64));
        if self.visited[word] & bit != 0 {
            return 0;
        }
        self.visited[word] |= bit;
        let cx = self.origin.0 + (i as f64 + 0.5) * self.side_m;
        let cy = self.origin.1 + (j as f64 + 0.5) * self.side_m;
        let ring = ((cx - self.start.0).hypot(cy - self.start.1) / self.ring_m).floor() as u64 + 1;
        let gained = match self.inner {
            InnerSum::Linear => ring,
            InnerSum::Triangular => {
                // n·T(k) − n·T(k − 1) = n·k for the k-th cell of ring n.
                let idx = (ring - 1) as usize;
                if self.ring_cells.len() <= idx {
                    self.ring_cells.resize(idx + 1, 0);
                }
                self.ring_cells[idx] += 1;
                ring * u64::from(self.ring_cells[idx])
            }
        };
        self.eqs += gained;
        self.cells += 1;
        gained
    }

    pub fn eqs(&self) -> u64 {
        self.eqs
    }
    pub fn ees(&self) -> f64 {
        if self.distance_m > 0.0 { self.eqs as f64 / self.distance_m } else { 0.0 }
    }
    pub fn distance_m(&self) -> f64 {
        self.distance_m
    }
    pub fn cells_visited(&self) -> u32 {
        self.cells
    }
    pub fn shaded_time_s(&self) -> f64 {
        self.shaded_s
    }
    pub fn cell_side_m(&self) -> f64 {
        self.side_m
    }
    /// Visited cells as (i, j) grid indices, for drawing.
    pub fn visited_cells(&self) -> Vec<(usize, usize)> {
        (0..self.nx * self.ny).filter(|k| self.visited[k / 64] & (1 << (k % 64)) != 0).map(|k| (k % self.nx, k / self.nx)).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tracker(cell_area: f64) -> ExplorationTracker {
        let b = Aabb { min_x: 0.0, min_y: 0.0, max_x: 40.0, max_y: 40.0 };
        ExplorationTracker::new(b, &ExplorationConfig { cell_area_m2: cell_area, ring_width_m: 10.0, inner_sum: InnerSum::Linear })
    }

    #[test]
    fn triangular_inner_sum_weighs_the_kth_cell_of_ring_n_by_n_k() {
        // The straight line of the first test: 5 cells in ring 1, 5 in ring 2, 3 in ring 3.
        // Triangular: 1·T(5) + 2·T(5) + 3·T(3) = 15 + 30 + 18 = 63.
        let b = Aabb { min_x: 0.0, min_y: 0.0, max_x: 40.0, max_y: 40.0 };
        let mut t = ExplorationTracker::new(b, &ExplorationConfig { cell_area_m2: 4.0, ring_width_m: 10.0, inner_sum: InnerSum::Triangular });
        for _ in 0..2 {
            // Twice: a reset must forget the ring counts.
            t.reset(1.0, 1.0);
            for k in 1..=240 {
                t.visit(1.0 + k as f64 * 0.1, 1.0, 0.0);
            }
            assert_eq!(t.cells_visited(), 13);
            assert_eq!(t.eqs(), 63);
        }
    }

    #[test]
    fn default_reading_is_two_metre_cells_and_rings_of_two_and_a_half() {
        // The straight line of the first test under the default reading: cell i (centre 2i + 1,
        // distance 2i from the start) is in ring ⌊2i / 2.5⌋ + 1, i = 0..=12 →
        // 1, 1, 2, 3, 4, 5, 5, 6, 7, 8, 9, 9, 10: EQS = 70 over 24 m, EES 2.92.
        let b = Aabb { min_x: 0.0, min_y: 0.0, max_x: 40.0, max_y: 40.0 };
        let mut t = ExplorationTracker::new(b, &ExplorationConfig::default());
        t.reset(1.0, 1.0);
        for k in 1..=240 {
            t.visit(1.0 + k as f64 * 0.1, 1.0, 0.0);
        }
        assert!((t.cell_side_m() - 2.0).abs() < 1e-12);
        assert_eq!(t.cells_visited(), 13);
        assert_eq!(t.eqs(), 70);
    }

    #[test]
    fn straight_line_counts_each_cell_once_with_its_ring() {
        // 4 m² cells (side 2 m) for round numbers. Start at (1, 1) = centre of cell (0, 0).
        // Drive along y = 1 to x = 25: cells i = 0..=12 are entered; cell i has centre
        // x = 2i + 1, distance 2i from the start → ring ⌊2i/10⌋ + 1:
        // i = 0..4 → ring 1 (5 cells), i = 5..9 → ring 2 (5), i = 10..12 → ring 3 (3).
        // EQS = 5·1 + 5·2 + 3·3 = 24; path 24 m → EES = 1.0.
        let mut t = tracker(4.0);
        t.reset(1.0, 1.0);
        for k in 1..=240 {
            t.visit(1.0 + k as f64 * 0.1, 1.0, 0.0);
        }
        assert_eq!(t.cells_visited(), 13);
        assert_eq!(t.eqs(), 24);
        assert!((t.distance_m() - 24.0).abs() < 1e-9);
        assert!((t.ees() - 1.0).abs() < 1e-9);
    }

    #[test]
    fn revisiting_cells_adds_distance_but_no_score() {
        let mut t = tracker(4.0);
        t.reset(1.0, 1.0);
        // Back and forth within cells (0,0) and (1,0) ten times: 2 cells, both ring 1.
        for _ in 0..10 {
            t.visit(3.0, 1.0, 0.0);
            t.visit(1.0, 1.0, 0.0);
        }
        assert_eq!(t.eqs(), 2);
        assert!((t.distance_m() - 40.0).abs() < 1e-9);
        assert!((t.ees() - 0.05).abs() < 1e-12);
    }

    #[test]
    fn default_cells_are_two_square_metres() {
        // Side √2 = 1.41421 m. From (0.5, 0.5) to (0.5, 3.0): y crosses 1.414 and 2.828 → 3 cells.
        let mut t = tracker(2.0);
        t.reset(0.5, 0.5);
        t.visit(0.5, 3.0, 0.0);
        assert!((t.cell_side_m() - 2f64.sqrt()).abs() < 1e-12);
        assert_eq!(t.cells_visited(), 2); // only poses are recorded: start and end cells
        t.visit(0.5, 2.0, 0.0);
        assert_eq!(t.cells_visited(), 3);
        assert_eq!(t.eqs(), 3);
    }

    #[test]
    fn far_ring_cells_weigh_more_and_shade_time_accumulates() {
        let mut t = tracker(4.0);
        t.reset(1.0, 1.0);
        // Jump to the cell centred at (31, 1): distance 30 → ring 4.
        t.visit(31.0, 1.0, 0.1);
        t.visit(31.0, 1.0, 0.1);
        assert_eq!(t.eqs(), 1 + 4);
        assert!((t.shaded_time_s() - 0.2).abs() < 1e-12);
        assert!(t.visited_cells().contains(&(15, 0)));
    }

    #[test]
    fn zero_distance_gives_zero_efficiency() {
        let mut t = tracker(2.0);
        t.reset(5.0, 5.0);
        assert_eq!(t.eqs(), 1);
        assert_eq!(t.ees(), 0.0);
    }
}
