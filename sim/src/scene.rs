//! Collision and ray-casting geometry: the map's obstacles flattened into line segments and
//! circles, indexed by a uniform grid.
//!
//! ```text
//!   Map (boxes, polygons, walls, circles)  --Scene::build-->  segments + circles
//!                                                              + grid: cell -> item ids
//! ```
//!
//! Two ray casters answer the same question (distance along a ray to the first surface):
//! - [`Scene::cast_ray`]: one ray, walking the grid cell by cell (Amanatides & Woo, 1987) and
//!   testing only the items registered in the cells it crosses. Cost: O(cells crossed + items
//!   in them). Best for sparse scans (7 beams).
//! - [`Scene::cast_fan`]: many rays from one origin at once. Every primitive within range is
//!   projected onto the fan's angular axis and intersected only with the beams it subtends.
//!   Cost: O(primitives in range + Σ beams subtended); the inner loop is branch-light and
//!   vectorises. Best for dense scans (100–1080 beams).
//!
//! Both are exact (up to f32 rounding) and are tested against each other and against parry2d.
//! Solid obstacles are represented by their boundary only: a ray or footprint meets a box at
//! its edges. That is exact for anything that starts outside every obstacle, which episode
//! starts guarantee (see `Map::is_free`).

/// Index bit marking a circle (vs a segment) in a grid cell's item list.
const CIRCLE_BIT: u32 = 1 << 31;

/// An axis-aligned rectangle.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Aabb {
    pub min_x: f64,
    pub min_y: f64,
    pub max_x: f64,
    pub max_y: f64,
}

impl Aabb {
    pub fn width(&self) -> f64 {
        self.max_x - self.min_x
    }
    pub fn height(&self) -> f64 {
        self.max_y - self.min_y
    }
    pub fn contains(&self, x: f64, y: f64) -> bool {
        x >= self.min_x && x <= self.max_x && y >= self.min_y && y <= self.max_y
    }
}

/// The vehicle's rectangular footprint, centred on the pose, long side along the heading.
#[derive(Clone, Copy, Debug)]
pub struct Footprint {
    pub half_length_m: f64,
    pub half_width_m: f64,
}

/// Most cells of a [`Scene`]'s grid index (4 M: a 4 km square at the simulator's 2 m cells).
pub const MAX_GRID_CELLS: usize = 1 << 22;

/// Obstacles as primitives, with a grid index. Immutable once built; shared by every vehicle.
#[derive(Clone, Debug)]
pub struct Scene {
    // Segments, structure of arrays (f32: ranges need millimetres, not nanometres).
    seg_ax: Vec<f32>,
    seg_ay: Vec<f32>,
    seg_bx: Vec<f32>,
    seg_by: Vec<f32>,
    // Circles.
    circ_x: Vec<f32>,
    circ_y: Vec<f32>,
    circ_r: Vec<f32>,
    // Uniform grid over `bounds`: items overlapping cell (i, j) are
    // `cell_items[cell_start[k]..cell_start[k + 1]]`, k = j * nx + i.
    origin_x: f32,
    origin_y: f32,
    cell_m: f32,
    inv_cell: f32,
    nx: i32,
    ny: i32,
    cell_start: Vec<u32>,
    cell_items: Vec<u32>,
}

impl Scene {
    /// Builds a scene over `bounds` with grid cells of `cell_m` metres, or coarser ones where
    /// `cell_m` would need more than [`MAX_GRID_CELLS`] cells (a map kilometres wide): the
    /// index then only narrows less, ray casts stay exact.
    pub fn new(bounds: Aabb, segments: &[[f64; 4]], circles: &[[f64; 3]], cell_m: f64) -> Self {
        let cells_at = |c: f64| ((bounds.width() + 2.0 * c) / c).ceil() * ((bounds.height() + 2.0 * c) / c).ceil();
        let mut cell_m = cell_m;
        while !(cells_at(cell_m) <= MAX_GRID_CELLS as f64) && cell_m.is_finite() {
            cell_m *= 2.0;
        }
        let margin = cell_m; // primitives on the boundary still fall inside the grid
        let origin_x = (bounds.min_x - margin) as f32;
        let origin_y = (bounds.min_y - margin) as f32;
        let nx = (((bounds.width() + 2.0 * margin) / cell_m).ceil() as i32).max(1);
        let ny = (((bounds.height() + 2.0 * margin) / cell_m).ceil() as i32).max(1);
        let mut s = Scene {
            seg_ax: segments.iter().map(|s| s[0] as f32).collect(),
            seg_ay: segments.iter().map(|s| s[1] as f32).collect(),
            seg_bx: segments.iter().map(|s| s[2] as f32).collect(),
            seg_by: segments.iter().map(|s| s[3] as f32).collect(),
            circ_x: circles.iter().map(|c| c[0] as f32).collect(),
            circ_y: circles.iter().map(|c| c[1] as f32).collect(),
            circ_r: circles.iter().map(|c| c[2] as f32).collect(),
            origin_x,
            origin_y,
            cell_m: cell_m as f32,
            inv_cell: (1.0 / cell_m) as f32,
            nx,
            ny,
            cell_start: Vec::new(),
            cell_items: Vec::new(),
        };
        s.index();
        s
    }

    pub fn segment_count(&self) -> usize {
        self.seg_ax.len()
    }
    pub fn circle_count(&self) -> usize {
        self.circ_x.len()
    }

    /// Registers every primitive in each grid cell its (slightly inflated) bounding box touches.
    fn index(&mut self) {
        let ncell = (self.nx * self.ny) as usize;
        let mut buckets: Vec<Vec<u32>> = vec![Vec::new(); ncell];
        let eps = 1e-3f32;
        let add = |buckets: &mut Vec<Vec<u32>>, x0: f32, y0: f32, x1: f32, y1: f32, id: u32| {
            let (i0, j0) = self.cell_of(x0 - eps, y0 - eps);
            let (i1, j1) = self.cell_of(x1 + eps, y1 + eps);
            for j in j0..=j1 {
                for i in i0..=i1 {
                    buckets[(j * self.nx + i) as usize].push(id);
                }
            }
        };
        for k in 0..self.seg_ax.len() {
            let (ax, ay, bx, by) = (self.seg_ax[k], self.seg_ay[k], self.seg_bx[k], self.seg_by[k]);
            // Walk only the cells the segment really crosses, not its whole bounding box, so
            // long diagonal walls do not flood the grid.
            // In f64: the squares of a wall 10^20 m long overflow f32, and an infinite length
            // made this walk endless. Capped at quarter cells along 4 grid half-perimeters: a
            // segment inside the grid is at most one long.
            let len = (f64::from(bx - ax).powi(2) + f64::from(by - ay).powi(2)).sqrt();
            let most = 16.0 * f64::from(self.nx + self.ny);
            let n = (len / (0.25 * f64::from(self.cell_m))).ceil().min(most).max(1.0) as usize;
            let mut last = (-1, -1);
            for t in 0..=n {
                let f = t as f32 / n as f32;
                let (x, y) = (ax + f * (bx - ax), ay + f * (by - ay));
                let c = self.cell_of(x, y);
                if c != last {
                    add(&mut buckets, x - 0.26 * self.cell_m, y - 0.26 * self.cell_m, x + 0.26 * self.cell_m, y + 0.26 * self.cell_m, k as u32);
                    last = c;
                }
            }
        }
        for k in 0..self.circ_x.len() {
            let (x, y, r) = (self.circ_x[k], self.circ_y[k], self.circ_r[k]);
            add(&mut buckets, x - r, y - r, x + r, y + r, k as u32 | CIRCLE_BIT);
        }
        self.cell_start = Vec::with_capacity(ncell + 1);
        self.cell_items.clear();
        for b in &mut buckets {
            b.sort_unstable();
            b.dedup();
            self.cell_start.push(self.cell_items.len() as u32);
            self.cell_items.extend_from_slice(b);
        }
        self.cell_start.push(self.cell_items.len() as u32);
    }

    /// Grid cell of a point, clamped to the grid.
    #[inline]
    fn cell_of(&self, x: f32, y: f32) -> (i32, i32) {
        // Clamping below at 0 first makes truncation equal floor.
        let i = ((x - self.origin_x) * self.inv_cell).max(0.0) as i32;
        let j = ((y - self.origin_y) * self.inv_cell).max(0.0) as i32;
        (i.min(self.nx - 1), j.min(self.ny - 1))
    }

    #[inline]
    fn items(&self, i: i32, j: i32) -> &[u32] {
        let k = (j * self.nx + i) as usize;
        &self.cell_items[self.cell_start[k] as usize..self.cell_start[k + 1] as usize]
    }

    /// Distance along the ray from (ox, oy) in unit direction (dx, dy) to the first surface,
    /// or `max_range` if nothing is hit within it.
    pub fn cast_ray(&self, ox: f32, oy: f32, dx: f32, dy: f32, max_range: f32) -> f32 {
        // Grid traversal (Amanatides & Woo). Invariant: every surface point at parameter
        // t < t_exit(current cell) lies in a cell already visited, so once the best hit is
        // closer than the current cell's exit, no later cell can hold a closer one.
        let gx = (ox - self.origin_x) * self.inv_cell;
        let gy = (oy - self.origin_y) * self.inv_cell;
        // Truncation is floor for the non-negative coordinates inside the grid (and avoids a
        // libm call on baseline x86-64, which has no SSE4.1 round instruction).
        let (mut i, mut j) = (gx as i32, gy as i32);
        if gx < 0.0 || gy < 0.0 || i >= self.nx || j >= self.ny {
            // Origin outside the indexed region (never true for a vehicle inside its map):
            // fall back to testing everything.
            return self.cast_ray_brute(ox, oy, dx, dy, max_range);
        }
        let step_i: i32 = if dx > 0.0 { 1 } else { -1 };
        let step_j: i32 = if dy > 0.0 { 1 } else { -1 };
        let inv_dx = if dx != 0.0 { 1.0 / dx } else { f32::INFINITY };
        let inv_dy = if dy != 0.0 { 1.0 / dy } else { f32::INFINITY };
        let next_bx = if dx > 0.0 { (i + 1) as f32 } else { i as f32 };
        let next_by = if dy > 0.0 { (j + 1) as f32 } else { j as f32 };
        let mut t_max_x = if dx != 0.0 { (next_bx - gx) * inv_dx * self.cell_m } else { f32::INFINITY };
        let mut t_max_y = if dy != 0.0 { (next_by - gy) * inv_dy * self.cell_m } else { f32::INFINITY };
        let t_delta_x = (self.cell_m * inv_dx).abs();
        let t_delta_y = (self.cell_m * inv_dy).abs();
        let mut best = max_range;
        loop {
            for &id in self.items(i, j) {
                let t = self.hit_item(id, ox, oy, dx, dy);
                if t < best {
                    best = t;
                }
            }
            let t_exit = t_max_x.min(t_max_y);
            if best <= t_exit || t_exit >= max_range {
                return best;
            }
            if t_max_x < t_max_y {
                i += step_i;
                t_max_x += t_delta_x;
                if i < 0 || i >= self.nx {
                    return best;
                }
            } else {
                j += step_j;
                t_max_y += t_delta_y;
                if j < 0 || j >= self.ny {
                    return best;
                }
            }
        }
    }

    /// Reference ray cast: every primitive, no index. Used outside the grid and in tests.
    pub fn cast_ray_brute(&self, ox: f32, oy: f32, dx: f32, dy: f32, max_range: f32) -> f32 {
        let mut best = max_range;
        for k in 0..self.seg_ax.len() {
            best = best.min(self.hit_item(k as u32, ox, oy, dx, dy));
        }
        for k in 0..self.circ_x.len() {
            best = best.min(self.hit_item(k as u32 | CIRCLE_BIT, ox, oy, dx, dy));
        }
        best
    }

    /// Ray parameter of the first intersection with item `id`, +inf if none (t ≥ 0 only).
    #[inline(always)]
    fn hit_item(&self, id: u32, ox: f32, oy: f32, dx: f32, dy: f32) -> f32 {
        if id & CIRCLE_BIT == 0 {
            let k = id as usize;
            let (ax, ay) = (self.seg_ax[k], self.seg_ay[k]);
            let (ex, ey) = (self.seg_bx[k] - ax, self.seg_by[k] - ay);
            let (wx, wy) = (ax - ox, ay - oy);
            let den = dx * ey - dy * ex;
            if den == 0.0 {
                return f32::INFINITY; // parallel: a grazing wall is seen by its neighbours
            }
            let t = (wx * ey - wy * ex) / den;
            let s = (wx * dy - wy * dx) / den;
            if t >= 0.0 && (0.0..=1.0).contains(&s) { t } else { f32::INFINITY }
        } else {
            let k = (id & !CIRCLE_BIT) as usize;
            ray_circle(self.circ_x[k] - ox, self.circ_y[k] - oy, self.circ_r[k], dx, dy)
        }
    }

    /// Casts a fan of rays from one origin. `dirs` holds unit directions (x, y) of beams whose
    /// angles are `angle0 + k * step` (k = 0..n, step > 0) in the world frame; results go to
    /// `out` (length n), each the hit distance or `max_range`.
    pub fn cast_fan(&self, ox: f32, oy: f32, angle0: f32, step: f32, dirs_x: &[f32], dirs_y: &[f32], max_range: f32, out: &mut [f32]) {
        let n = out.len();
        debug_assert!(dirs_x.len() == n && dirs_y.len() == n && step > 0.0);
        out.fill(max_range);
        let two_pi = std::f32::consts::TAU;
        let inv_step = 1.0 / step;
        // Beams subtended by the angular interval [lo, lo + width] (world angles), padded by
        // one beam each side because the interval comes from a fast atan2; the exact
        // intersection test rejects the padding.
        let beam_ranges = |lo: f32, width: f32| -> [(usize, usize); 2] {
            let rel = (lo - angle0).rem_euclid(two_pi);
            let mut r = [(1, 0); 2];
            for (w, shift) in [0.0f32, two_pi].into_iter().enumerate() {
                let a = rel - shift;
                let k0 = ((a * inv_step).floor() as i64 - 1).max(0);
                let k1 = (((a + width) * inv_step).ceil() as i64 + 1).min(n as i64 - 1);
                if k0 <= k1 {
                    r[w] = (k0 as usize, k1 as usize);
                }
            }
            r
        };
        let r2max = max_range * max_range;
        for k in 0..self.seg_ax.len() {
            let (ax, ay) = (self.seg_ax[k] - ox, self.seg_ay[k] - oy);
            let (bx, by) = (self.seg_bx[k] - ox, self.seg_by[k] - oy);
            let (ex, ey) = (bx - ax, by - ay);
            // Cull: closest point of the segment to the origin beyond max range.
            let ee = ex * ex + ey * ey;
            let u = if ee > 0.0 { (-(ax * ex + ay * ey) / ee).clamp(0.0, 1.0) } else { 0.0 };
            let (cx, cy) = (ax + u * ex, ay + u * ey);
            if cx * cx + cy * cy > r2max {
                continue;
            }
            let ta = fast_atan2(ay, ax);
            let tb = fast_atan2(by, bx);
            let d = wrap_pi(tb - ta);
            let (lo, width) = if d >= 0.0 { (ta, d) } else { (tb, -d) };
            let num_t = ax * ey - ay * ex;
            for (k0, k1) in beam_ranges(lo, width) {
                for b in k0..=k1 {
                    let (dx, dy) = (dirs_x[b], dirs_y[b]);
                    let den = dx * ey - dy * ex;
                    let t = num_t / den;
                    let s = (ax * dy - ay * dx) / den;
                    if t >= 0.0 && (0.0..=1.0).contains(&s) && t < out[b] {
                        out[b] = t;
                    }
                }
            }
        }
        for k in 0..self.circ_x.len() {
            let (cx, cy, r) = (self.circ_x[k] - ox, self.circ_y[k] - oy, self.circ_r[k]);
            let dist2 = cx * cx + cy * cy;
            let reach = max_range + r;
            if dist2 > reach * reach {
                continue;
            }
            let dist = dist2.sqrt();
            let (lo, width) = if dist <= r {
                (0.0, two_pi) // origin inside: every beam
            } else {
                let half = (r / dist).asin();
                (fast_atan2(cy, cx) - half, 2.0 * half)
            };
            for (k0, k1) in beam_ranges(lo, width.min(two_pi)) {
                for b in k0..=k1 {
                    let t = ray_circle(cx, cy, r, dirs_x[b], dirs_y[b]);
                    if t < out[b] {
                        out[b] = t;
                    }
                }
            }
        }
    }

    /// True if the footprint centred at (x, y) with heading `heading_rad` touches any primitive.
    pub fn footprint_collides(&self, x: f64, y: f64, heading_rad: f64, fp: &Footprint) -> bool {
        let (c, s) = (heading_rad.cos() as f32, heading_rad.sin() as f32);
        let (hl, hw) = (fp.half_length_m as f32, fp.half_width_m as f32);
        let (x, y) = (x as f32, y as f32);
        // Axis-aligned bounds of the rotated rectangle select the grid cells to test.
        let ex = hl * c.abs() + hw * s.abs();
        let ey = hl * s.abs() + hw * c.abs();
        let (i0, j0) = self.cell_of(x - ex, y - ey);
        let (i1, j1) = self.cell_of(x + ex, y + ey);
        for j in j0..=j1 {
            for i in i0..=i1 {
                for &id in self.items(i, j) {
                    if self.item_overlaps_box(id, x, y, c, s, hl, hw) {
                        return true;
                    }
                }
            }
        }
        false
    }

    /// Footprint test against every primitive (reference for tests).
    pub fn footprint_collides_brute(&self, x: f64, y: f64, heading_rad: f64, fp: &Footprint) -> bool {
        let (c, s) = (heading_rad.cos() as f32, heading_rad.sin() as f32);
        let (hl, hw) = (fp.half_length_m as f32, fp.half_width_m as f32);
        let (segs, circs) = (self.seg_ax.len() as u32, self.circ_x.len() as u32);
        (0..segs).chain((0..circs).map(|k| k | CIRCLE_BIT)).any(|id| self.item_overlaps_box(id, x as f32, y as f32, c, s, hl, hw))
    }

    /// Does item `id` overlap the box centred at (x, y), axes (c, s) / (−s, c), half sizes hl, hw?
    #[inline]
    fn item_overlaps_box(&self, id: u32, x: f32, y: f32, c: f32, s: f32, hl: f32, hw: f32) -> bool {
        // Work in the box frame: p' = R(−ψ)(p − centre).
        let to_box = |px: f32, py: f32| {
            let (dx, dy) = (px - x, py - y);
            (c * dx + s * dy, -s * dx + c * dy)
        };
        if id & CIRCLE_BIT == 0 {
            let k = id as usize;
            let (ax, ay) = to_box(self.seg_ax[k], self.seg_ay[k]);
            let (bx, by) = to_box(self.seg_bx[k], self.seg_by[k]);
            segment_hits_aabb(ax, ay, bx, by, hl, hw)
        } else {
            let k = (id & !CIRCLE_BIT) as usize;
            let (px, py) = to_box(self.circ_x[k], self.circ_y[k]);
            let (qx, qy) = (px.clamp(-hl, hl), py.clamp(-hw, hw));
            let r = self.circ_r[k];
            (px - qx).powi(2) + (py - qy).powi(2) <= r * r
        }
    }

    /// Euclidean distance from (x, y) to the nearest primitive surface (brute force: used for
    /// start-pose sampling, not on the hot path). +inf for an empty scene.
    pub fn distance_to_nearest(&self, x: f64, y: f64) -> f64 {
        let (x, y) = (x as f32, y as f32);
        let mut best = f32::INFINITY;
        for k in 0..self.seg_ax.len() {
            let (ax, ay) = (self.seg_ax[k] - x, self.seg_ay[k] - y);
            let (ex, ey) = (self.seg_bx[k] - self.seg_ax[k], self.seg_by[k] - self.seg_ay[k]);
            let ee = ex * ex + ey * ey;
            let u = if ee > 0.0 { (-(ax * ex + ay * ey) / ee).clamp(0.0, 1.0) } else { 0.0 };
            best = best.min(((ax + u * ex).powi(2) + (ay + u * ey).powi(2)).sqrt());
        }
        for k in 0..self.circ_x.len() {
            let d = ((self.circ_x[k] - x).powi(2) + (self.circ_y[k] - y).powi(2)).sqrt();
            best = best.min((d - self.circ_r[k]).abs());
        }
        best as f64
    }
}

/// First t ≥ 0 where the ray from the origin along unit (dx, dy) meets the circle centred at
/// (cx, cy) (relative to the origin) of radius r; +inf if it misses.
#[inline]
fn ray_circle(cx: f32, cy: f32, r: f32, dx: f32, dy: f32) -> f32 {
    let b = cx * dx + cy * dy;
    let c = cx * cx + cy * cy - r * r;
    let disc = b * b - c;
    if disc < 0.0 {
        return f32::INFINITY;
    }
    let sq = disc.sqrt();
    let t0 = b - sq;
    if t0 >= 0.0 {
        t0
    } else if b + sq >= 0.0 && c <= 0.0 {
        b + sq // origin inside the circle: the far wall
    } else {
        f32::INFINITY
    }
}

/// Does the segment (a, b) meet the axis-aligned box [−hl, hl] × [−hw, hw]? (Liang–Barsky clip.)
#[inline]
fn segment_hits_aabb(ax: f32, ay: f32, bx: f32, by: f32, hl: f32, hw: f32) -> bool {
    let (dx, dy) = (bx - ax, by - ay);
    let (mut t0, mut t1) = (0.0f32, 1.0f32);
    for (p, q) in [(-dx, ax + hl), (dx, hl - ax), (-dy, ay + hw), (dy, hw - ay)] {
        if p == 0.0 {
            if q < 0.0 {
                return false;
            }
        } else {
            let r = q / p;
            if p < 0.0 {
                if r > t1 {
                    return false;
                }
                t0 = t0.max(r);
            } else {
                if r < t0 {
                    return false;
                }
                t1 = t1.min(r);
            }
        }
    }
    t0 <= t1
}

/// Wraps an angle to (−π, π].
#[inline]
pub fn wrap_pi(a: f32) -> f32 {
    let two_pi = std::f32::consts::TAU;
    let mut a = a.rem_euclid(two_pi);
    if a > std::f32::consts::PI {
        a -= two_pi;
    }
    a
}

/// atan2 to about 1e-5 rad (odd minimax polynomial on [0, 1] plus octant reduction). Only used to
/// choose which beams a primitive can hit; the hit itself is computed exactly.
#[inline]
fn fast_atan2(y: f32, x: f32) -> f32 {
    use std::f32::consts::{FRAC_PI_2, PI};
    let (ax, ay) = (x.abs(), y.abs());
    let (mn, mx) = if ax < ay { (ax, ay) } else { (ay, ax) };
    if mx == 0.0 {
        return 0.0;
    }
    let a = mn / mx;
    let s = a * a;
    let mut r = ((-0.046_496_473 * s + 0.159_314_22) * s - 0.327_622_77) * s * a + a;
    if ay > ax {
        r = FRAC_PI_2 - r;
    }
    if x < 0.0 {
        r = PI - r;
    }
    if y < 0.0 { -r } else { r }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn square_room(half: f64) -> Scene {
        let h = half;
        let segs = [[-h, -h, h, -h], [h, -h, h, h], [h, h, -h, h], [-h, h, -h, -h]];
        Scene::new(Aabb { min_x: -h, min_y: -h, max_x: h, max_y: h }, &segs, &[], 1.0)
    }

    #[test]
    fn fast_atan2_matches_std_within_beam_padding() {
        let mut worst = 0.0f32;
        for i in 0..3600 {
            let a = i as f32 * 0.1f32.to_radians() - 3.0;
            for r in [0.1f32, 1.0, 30.0] {
                let (y, x) = (r * a.sin(), r * a.cos());
                worst = worst.max(wrap_pi(fast_atan2(y, x) - y.atan2(x)).abs());
            }
        }
        assert!(worst < 2e-4, "worst error {worst}");
    }

    #[test]
    fn ray_to_wall_straight_ahead_reads_the_distance() {
        let s = square_room(5.0);
        // From (1, 0) looking +x: wall at x = 5 is 4 m away.
        assert!((s.cast_ray(1.0, 0.0, 1.0, 0.0, 12.0) - 4.0).abs() < 1e-5);
        // Looking −y from (0, 2): wall y = −5 is 7 m away.
        assert!((s.cast_ray(0.0, 2.0, 0.0, -1.0, 12.0) - 7.0).abs() < 1e-5);
        // 45° from the centre: corner distance 5√2.
        let d = std::f32::consts::FRAC_1_SQRT_2;
        assert!((s.cast_ray(0.0, 0.0, d, d, 12.0) - 5.0 * 2f32.sqrt()).abs() < 1e-4);
    }

    #[test]
    fn ray_beyond_max_range_reads_max_range() {
        let s = square_room(10.0);
        assert_eq!(s.cast_ray(0.0, 0.0, 1.0, 0.0, 3.0), 3.0);
        assert_eq!(s.cast_ray_brute(0.0, 0.0, 1.0, 0.0, 3.0), 3.0);
    }

    #[test]
    fn ray_meets_circle_at_its_near_side() {
        let s = Scene::new(Aabb { min_x: -5.0, min_y: -5.0, max_x: 5.0, max_y: 5.0 }, &[], &[[3.0, 0.0, 0.5]], 1.0);
        assert!((s.cast_ray(0.0, 0.0, 1.0, 0.0, 12.0) - 2.5).abs() < 1e-5);
        // Tangent-missing ray.
        assert_eq!(s.cast_ray(0.0, 1.0, 1.0, 0.0, 12.0), 12.0);
    }

    /// A map kilometres wide gets coarser cells, not 10^10 of them (whose count overflowed an
    /// i32: fuzz/regressions/map_files/grid-cells-overflow).
    #[test]
    fn a_huge_scene_keeps_its_grid_bounded_and_its_rays_exact() {
        let h = 1e5;
        let s = Scene::new(Aabb { min_x: -h, min_y: -h, max_x: h, max_y: h }, &[[-h, -h, h, -h]], &[[3.0, 0.0, 0.5]], 1.0);
        assert!((s.nx as usize) * (s.ny as usize) <= MAX_GRID_CELLS, "{} x {}", s.nx, s.ny);
        assert!((s.cast_ray(0.0, 0.0, 1.0, 0.0, 12.0) - 2.5).abs() < 1e-3);
        assert_eq!(s.cast_ray(0.0, 0.0, 0.0, -1.0, 12.0), s.cast_ray_brute(0.0, 0.0, 0.0, -1.0, 12.0));
    }

    #[test]
    fn segment_box_overlap_cases() {
        assert!(segment_hits_aabb(-2.0, 0.0, 2.0, 0.0, 1.0, 0.5)); // crosses
        assert!(segment_hits_aabb(0.0, 0.0, 0.1, 0.1, 1.0, 0.5)); // inside
        assert!(!segment_hits_aabb(-2.0, 0.6, 2.0, 0.6, 1.0, 0.5)); // passes above
        assert!(!segment_hits_aabb(1.1, -3.0, 1.1, 3.0, 1.0, 0.5)); // passes right
        assert!(segment_hits_aabb(0.9, -3.0, 0.9, 3.0, 1.0, 0.5));
    }

    #[test]
    fn footprint_touching_wall_collides_and_clear_one_does_not() {
        let s = square_room(5.0);
        let fp = Footprint { half_length_m: 0.275, half_width_m: 0.15 };
        assert!(!s.footprint_collides(0.0, 0.0, 0.3, &fp));
        // Facing the x = 5 wall, nose at 4.99 + … : centre 4.8 → nose at 5.075.
        assert!(s.footprint_collides(4.8, 0.0, 0.0, &fp));
        // Sideways to it: half width 0.15 → 4.8 + 0.15 < 5: clear.
        assert!(!s.footprint_collides(4.8, 0.0, std::f64::consts::FRAC_PI_2, &fp));
    }
}
