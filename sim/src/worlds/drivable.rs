//! Where the car can drive: the lattice points whose distance to every surface is at least a
//! clearance, and how they hang together.

use std::collections::VecDeque;

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
        for j in 0..height {
            let y = b.min_y + (j as f64 + 0.5) * cell_m;
            for i in 0..width {
                let x = b.min_x + (i as f64 + 0.5) * cell_m;
                ok[j * width + i] = map.is_free(x, y) && scene.distance_to_nearest(x, y) >= clearance_m;
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
        DrivableSpace { cell_m, width, height, origin: [b.min_x, b.min_y], piece, piece_sizes }
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
