//! `cave`: a cellular-automaton cave. Rock is seeded on 1 m cells (45 % of them, the border
//! all rock), five rounds of the 4-5 rule (a cell is rock when at least 5 of its 3 × 3
//! neighbourhood are) carve chambers and passages, every open region but the largest is filled,
//! and the result is smoothed onto a 0.25 m grid (bilinear, threshold ½). Open cells not within
//! reach of the largest drivable piece are then filled too, so no pocket is left to start in.

use rand::Rng;
use rand_pcg::Pcg64Mcg;

use super::{DRIVABLE_CELL_M, DRIVE_CLEARANCE_M, DrivableSpace};
use crate::error::Result;
use crate::map::{Map, OccupancyGrid};

/// Side of a cellular-automaton cell (m).
const CA_CELL_M: f64 = 1.0;
/// Fine cells per CA cell (0.25 m grid).
const FINE: usize = 4;

pub(super) fn cave(rng: &mut Pcg64Mcg, size: f64, name: &str) -> Result<Map> {
    // Whole CA cells: the world's side is n cells (the drawn size rounded to a cell).
    let n = (size / CA_CELL_M).round() as usize;
    let size = n as f64 * CA_CELL_M;
    let idx = |i: usize, j: usize| j * n + i;
    let border = |i: usize, j: usize| i == 0 || j == 0 || i + 1 == n || j + 1 == n;
    let fill = rng.random_range(0.42..0.47);
    let mut rock: Vec<bool> = (0..n * n).map(|k| border(k % n, k / n) || rng.random_bool(fill)).collect();
    for _ in 0..5 {
        let prev = rock.clone();
        for j in 0..n {
            for i in 0..n {
                if border(i, j) {
                    continue;
                }
                let mut walls = 0;
                for dj in 0..3 {
                    for di in 0..3 {
                        walls += usize::from(prev[idx(i + di - 1, j + dj - 1)]);
                    }
                }
                rock[idx(i, j)] = walls >= 5;
            }
        }
    }
    keep_largest_open_region(&mut rock, n);
    // Bilinear smoothing onto the fine grid: open-ness 1 at open CA cell centres, 0 at rock.
    let m = n * FINE;
    let open = |i: isize, j: isize| -> f64 {
        let (i, j) = (i.clamp(0, n as isize - 1) as usize, j.clamp(0, n as isize - 1) as usize);
        if rock[idx(i, j)] { 0.0 } else { 1.0 }
    };
    let mut free = vec![false; m * m];
    for fj in 0..m {
        for fi in 0..m {
            // Fine cell centre in CA-cell units, relative to CA cell centres.
            let u = (fi as f64 + 0.5) / FINE as f64 - 0.5;
            let v = (fj as f64 + 0.5) / FINE as f64 - 0.5;
            let (i0, j0) = (u.floor() as isize, v.floor() as isize);
            let (tu, tv) = (u - i0 as f64, v - j0 as f64);
            let val = open(i0, j0) * (1.0 - tu) * (1.0 - tv) + open(i0 + 1, j0) * tu * (1.0 - tv) + open(i0, j0 + 1) * (1.0 - tu) * tv + open(i0 + 1, j0 + 1) * tu * tv;
            let on_border = fi < FINE || fj < FINE || fi >= m - FINE || fj >= m - FINE;
            free[fj * m + fi] = !on_border && val > 0.5;
        }
    }
    let res = CA_CELL_M / FINE as f64;
    let grid = OccupancyGrid { width: m, height: m, resolution_m: res, origin: [-size / 2.0, -size / 2.0], free };
    let map = Map::from_grid(name.into(), String::new(), grid);
    Ok(fill_unreachable(map))
}

/// Fills every open CA region but the largest (4-connected).
fn keep_largest_open_region(rock: &mut [bool], n: usize) {
    let mut label = vec![usize::MAX; n * n];
    let mut sizes = Vec::new();
    for s in 0..n * n {
        if rock[s] || label[s] != usize::MAX {
            continue;
        }
        let id = sizes.len();
        let (mut stack, mut count) = (vec![s], 0);
        label[s] = id;
        while let Some(k) = stack.pop() {
            count += 1;
            let (i, j) = (k % n, k / n);
            for (ok, k2) in [(i > 0, k.wrapping_sub(1)), (i + 1 < n, k + 1), (j > 0, k.wrapping_sub(n)), (j + 1 < n, k + n)] {
                if ok && !rock[k2] && label[k2] == usize::MAX {
                    label[k2] = id;
                    stack.push(k2);
                }
            }
        }
        sizes.push(count);
    }
    let Some(best) = (0..sizes.len()).max_by_key(|&p| (sizes[p], std::cmp::Reverse(p))) else { return };
    for k in 0..n * n {
        if !rock[k] && label[k] != best {
            rock[k] = true;
        }
    }
}

/// Blocks every open fine cell farther than the clearance (plus a cell) from the largest
/// drivable piece: pockets the car could start in but not leave, and slivers it cannot reach.
fn fill_unreachable(map: Map) -> Map {
    let space = DrivableSpace::of(&map, DRIVE_CLEARANCE_M, DRIVABLE_CELL_M);
    let Some(mut grid) = map.grid.clone() else { return map };
    if space.piece_sizes.is_empty() {
        return map;
    }
    let (w, h) = (grid.width, grid.height);
    let reach = ((DRIVE_CLEARANCE_M + grid.resolution_m) / grid.resolution_m).ceil() as isize;
    let mut near = vec![false; w * h];
    for j in 0..h {
        for i in 0..w {
            let x = map.bounds.min_x + (i as f64 + 0.5) * grid.resolution_m;
            let y = map.bounds.min_y + (j as f64 + 0.5) * grid.resolution_m;
            if space.piece_at(x, y) != Some(0) {
                continue;
            }
            for dj in -reach..=reach {
                for di in -reach..=reach {
                    let (ii, jj) = (i as isize + di, j as isize + dj);
                    if ii >= 0 && jj >= 0 && (ii as usize) < w && (jj as usize) < h && di * di + dj * dj <= reach * reach {
                        near[jj as usize * w + ii as usize] = true;
                    }
                }
            }
        }
    }
    for k in 0..w * h {
        grid.free[k] &= near[k];
    }
    Map::from_grid(map.name.clone(), map.description.clone(), grid)
}
