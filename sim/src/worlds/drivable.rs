//! Where the car can drive: the lattice points whose distance to every surface is at least a
//! clearance, and how they hang together.

use std::collections::VecDeque;

use crate::config::VehicleConfig;
use crate::map::Map;

/// The drivable lattice of a map and its 4-connected pieces.
#[derive(Clone, Debug)]
pub struct DrivableSpace {
    /// Lattice spacing (m); point (i, j) sits at the centre of cell (i, j) from the map's
    /// lower-left corner.
    pub cell_m: f64,
    pub width: usize,
    pub height: usize,
    origin: [f64; 2],
    /// Per point: the piece it belongs to (`None`: not drivable). Pieces are numbered by size,
    /// largest first.
    piece: Vec<Option<u32>>,
    /// Points per piece, largest first.
    pub piece_sizes: Vec<usize>,
    /// Per point: the distance to the nearest surface (m; 0 where the map is not free).
    clearance_m: Vec<f32>,
}

impl DrivableSpace {
    /// Samples `map` every `cell_m`: a point is drivable where the map is free and the nearest
    /// surface is at least `clearance_m` away.
    pub fn of(map: &Map, clearance_m: f64, cell_m: f64) -> DrivableSpace {
        let b = map.bounds;
        let width = (b.width() / cell_m).floor().max(1.0) as usize;
        let height = (b.height() / cell_m).floor().max(1.0) as usize;
        let scene = map.scene(0.0, 2.0);
        let mut ok = vec![false; width * height];
        let mut clear = vec![0.0f32; width * height];
        for j in 0..height {
            let y = b.min_y + (j as f64 + 0.5) * cell_m;
            for i in 0..width {
                let x = b.min_x + (i as f64 + 0.5) * cell_m;
                if map.is_free(x, y) {
                    let d = scene.distance_to_nearest(x, y);
                    clear[j * width + i] = d as f32;
                    ok[j * width + i] = d >= clearance_m;
                }
            }
        }
        // Label 4-connected pieces, then renumber them by size.
        let mut label: Vec<Option<u32>> = vec![None; width * height];
        let mut sizes = Vec::new();
        let mut queue = VecDeque::new();
        for start in 0..ok.len() {
            if !ok[start] || label[start].is_some() {
                continue;
            }
            let id = sizes.len() as u32;
            let mut n = 0usize;
            label[start] = Some(id);
            queue.push_back(start);
            while let Some(k) = queue.pop_front() {
                n += 1;
                let (i, j) = (k % width, k / width);
                let mut visit = |k2: usize| {
                    if ok[k2] && label[k2].is_none() {
                        label[k2] = Some(id);
                        queue.push_back(k2);
                    }
                };
                if i > 0 {
                    visit(k - 1);
                }
                if i + 1 < width {
                    visit(k + 1);
                }
                if j > 0 {
                    visit(k - width);
                }
                if j + 1 < height {
                    visit(k + width);
                }
            }
            sizes.push(n);
        }
        let mut order: Vec<usize> = (0..sizes.len()).collect();
        order.sort_by_key(|&p| (std::cmp::Reverse(sizes[p]), p));
        let mut rank = vec![0u32; sizes.len()];
        for (r, &p) in order.iter().enumerate() {
            rank[p] = r as u32;
        }
        let piece = label.into_iter().map(|l| l.map(|p| rank[p as usize])).collect();
        let piece_sizes = order.iter().map(|&p| sizes[p]).collect();
        DrivableSpace { cell_m, width, height, origin: [b.min_x, b.min_y], piece, piece_sizes, clearance_m: clear }
    }

    /// One piece, and not empty.
    pub fn is_connected(&self) -> bool {
        self.piece_sizes.len() == 1
    }

    /// Drivable area of all pieces (m²).
    pub fn area_m2(&self) -> f64 {
        self.piece_sizes.iter().sum::<usize>() as f64 * self.cell_m * self.cell_m
    }

    /// Share of the lattice that is drivable.
    pub fn share(&self) -> f64 {
        self.piece_sizes.iter().sum::<usize>() as f64 / (self.width * self.height) as f64
    }

    /// The piece of the lattice point nearest (x, y), if it is drivable (0 = the largest).
    pub fn piece_at(&self, x: f64, y: f64) -> Option<u32> {
        let i = ((x - self.origin[0]) / self.cell_m).floor();
        let j = ((y - self.origin[1]) / self.cell_m).floor();
        if i < 0.0 || j < 0.0 || i >= self.width as f64 || j >= self.height as f64 {
            return None;
        }
        self.piece[j as usize * self.width + i as usize]
    }

    /// True where lattice point (i, j) is drivable.
    pub fn drivable(&self, i: usize, j: usize) -> bool {
        i < self.width && j < self.height && self.piece[j * self.width + i].is_some()
    }

    /// The drivable points where `car`, which cannot reverse, may drive in but never out: the
    /// parts of the drivable space too narrow to turn round in that open onto the rest through
    /// one mouth only.
    ///
    /// A point is a turning centre where the nearest surface is at least the car's turning
    /// radius plus its circumradius away (a full circle about it is clear); the drivable points
    /// within the turning radius of a centre lie on such circles, and the car can turn there (a
    /// generous reading: it does not plan the turn). What is left of the drivable space is
    /// narrow: passages and nooks. One whose border with the turning space is a single
    /// 8-connected run of points leads nowhere (a dead end, however long); one that touches it in
    /// two or more runs is a way through (or closes a loop the car can drive round) and is not
    /// counted, nor is a piece with no turning space at all. A narrow loop round an obstacle that
    /// returns through its one mouth counts as a dead end: the reading errs towards more.
    pub fn dead_ends(&self, car: &VehicleConfig) -> Vec<(usize, usize)> {
        let turn_radius_m = car.min_turning_radius_m();
        let turn_clearance_m = turn_radius_m + car.circumradius_m();
        let (w, h) = (self.width, self.height);
        let at = |i: usize, j: usize| j * w + i;
        let drivable: Vec<bool> = self.piece.iter().map(Option::is_some).collect();
        // The turning space: every drivable point within the turning radius of a centre.
        let r = (turn_radius_m / self.cell_m).floor() as isize;
        let mut turn = vec![false; w * h];
        for j in 0..h {
            for i in 0..w {
                if !drivable[at(i, j)] || f64::from(self.clearance_m[at(i, j)]) < turn_clearance_m {
                    continue;
                }
                for dj in -r..=r {
                    for di in -r..=r {
                        let (ii, jj) = (i as isize + di, j as isize + dj);
                        if di * di + dj * dj <= r * r && ii >= 0 && jj >= 0 && (ii as usize) < w && (jj as usize) < h && drivable[at(ii as usize, jj as usize)] {
                            turn[at(ii as usize, jj as usize)] = true;
                        }
                    }
                }
            }
        }
        let neighbours4 = |k: usize| {
            let (i, j) = (k % w, k / w);
            [(i > 0).then(|| k - 1), (i + 1 < w).then(|| k + 1), (j > 0).then(|| k - w), (j + 1 < h).then(|| k + w)].into_iter().flatten()
        };
        let mut seen = vec![false; w * h];
        let mut mouth_seen = vec![false; w * h];
        let mut out = Vec::new();
        for start in 0..w * h {
            if !drivable[start] || turn[start] || seen[start] {
                continue;
            }
            // One passage (4-connected), and the turning-space points that border it.
            let (mut passage, mut mouth) = (vec![start], Vec::new());
            seen[start] = true;
            let mut q = 0;
            while q < passage.len() {
                let k = passage[q];
                q += 1;
                for k2 in neighbours4(k) {
                    if !drivable[k2] {
                        continue;
                    }
                    if turn[k2] {
                        if !mouth_seen[k2] {
                            mouth_seen[k2] = true;
                            mouth.push(k2);
                        }
                    } else if !seen[k2] {
                        seen[k2] = true;
                        passage.push(k2);
                    }
                }
            }
            // Runs of the border: its 8-connected pieces.
            let mut runs = 0;
            let mut stack = Vec::new();
            for &m0 in &mouth {
                if !mouth_seen[m0] {
                    continue;
                }
                runs += 1;
                mouth_seen[m0] = false;
                stack.push(m0);
                while let Some(k) = stack.pop() {
                    let (i, j) = ((k % w) as isize, (k / w) as isize);
                    for dj in -1..=1 {
                        for di in -1..=1 {
                            let (ii, jj) = (i + di, j + dj);
                            if ii >= 0 && jj >= 0 && (ii as usize) < w && (jj as usize) < h && mouth_seen[at(ii as usize, jj as usize)] {
                                mouth_seen[at(ii as usize, jj as usize)] = false;
                                stack.push(at(ii as usize, jj as usize));
                            }
                        }
                    }
                }
            }
            if runs == 1 {
                out.extend(passage.iter().map(|&k| (k % w, k / w)));
            }
        }
        out
    }

    /// Share of the drivable points that lie in [`dead_ends`](Self::dead_ends) (0 when nothing
    /// is drivable).
    pub fn dead_end_share(&self, car: &VehicleConfig) -> f64 {
        let all: usize = self.piece_sizes.iter().sum();
        if all == 0 { 0.0 } else { self.dead_ends(car).len() as f64 / all as f64 }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::Map;

    #[test]
    fn a_closed_wall_splits_the_space_and_a_doorway_joins_it() {
        let doc = |walls: &str| format!("format: mapless-vector-map/v1\nname: t\nbounds: {{ min: [0, 0], max: [10, 4] }}\nboundary_walls: true\nobstacles:\n{walls}");
        let closed = Map::from_vector_yaml(&doc("  - wall: { from: [5, 0], to: [5, 4] }\n"), "t".as_ref()).unwrap();
        let s = DrivableSpace::of(&closed, 0.45, 0.25);
        assert_eq!(s.piece_sizes.len(), 2, "{:?}", s.piece_sizes);
        assert_ne!(s.piece_at(2.0, 2.0), s.piece_at(8.0, 2.0));
        // A 1.5 m doorway passes a 0.9 m wide clearance disc; a 0.6 m one does not.
        let door = Map::from_vector_yaml(&doc("  - wall: { from: [5, 0], to: [5, 1.25] }\n  - wall: { from: [5, 2.75], to: [5, 4] }\n"), "t".as_ref()).unwrap();
        assert!(DrivableSpace::of(&door, 0.45, 0.25).is_connected());
        let slit = Map::from_vector_yaml(&doc("  - wall: { from: [5, 0], to: [5, 1.7] }\n  - wall: { from: [5, 2.3], to: [5, 4] }\n"), "t".as_ref()).unwrap();
        assert!(!DrivableSpace::of(&slit, 0.45, 0.25).is_connected());
        // Drivable area: the 10 × 4 box less a 0.45 m margin inside its walls, less the wall's band.
        let open = Map::from_vector_yaml(&doc(""), "t".as_ref()).unwrap();
        let a = DrivableSpace::of(&open, 0.45, 0.25).area_m2();
        assert!((a - 9.0 * 3.0).abs() < 1.5, "{a}");
    }
}
