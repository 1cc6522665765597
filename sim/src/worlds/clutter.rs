//! `hall`, `forest` and `field`: fenced spaces filled with things to steer round.
//!
//! - **hall**: shelf rows across the hall with gaps, aisles 2.4–4 m, a clear lane along the
//!   walls; crates in the aisles; pillars on a grid in large halls.
//! - **forest**: trunks (0.12–0.45 m radius, 5 m tall) and boulders (irregular, 0.4–1.2 m,
//!   1 m tall) by dart throwing, each pair at least a gap of 1.4–3 m apart (drawn per world).
//! - **field**: sparse trees (trunks 0.2–0.3 m) with canopies of 2–4.5 m that shade the ground
//!   (eq. (2)'s regions), often in groves, and boulders; gaps of 3 m at the least.

use rand::Rng;
use rand_pcg::Pcg64Mcg;

use super::{cm, vector_map};
use crate::error::Result;
use crate::map::{Map, Obstacle, Region};

/// Things are kept this far inside the fence (m).
const FENCE_MARGIN_M: f64 = 1.2;

pub(super) fn hall(rng: &mut Pcg64Mcg, size: f64, name: &str) -> Result<Map> {
    let h = size / 2.0;
    let aisle: f64 = rng.random_range(2.4..4.0);
    let depth = rng.random_range(0.6..1.2);
    let lane = aisle.max(2.5);
    let horizontal = rng.random_bool(0.5);
    let mut obstacles = Vec::new();
    // Rows of shelves (in "row space": u along the row, v across), each broken into runs.
    let mut v = -h + lane + depth / 2.0;
    while v + depth / 2.0 <= h - lane {
        let mut u = -h + lane;
        while u < h - lane {
            let run = rng.random_range(3.0..8.0f64).min(h - lane - u);
            if run >= 1.0 {
                let (c, s) = ([u + run / 2.0, v], [run, depth]);
                let (center, size_) = if horizontal { (c, s) } else { ([c[1], c[0]], [s[1], s[0]]) };
                obstacles.push(Obstacle::Box { center: [cm(center[0]), cm(center[1])], size: [cm(size_[0]), cm(size_[1])], angle_deg: 0.0, height_m: 2.0 });
            }
            u += run + rng.random_range(2.5..4.0);
        }
        v += depth + aisle;
    }
    // Crates in the aisles (small enough to pass: at most 1 m across an aisle ≥ 2.4 m... with
    // the gaps in the rows, a blocked aisle still has a way round; the drivable check decides).
    let crates = (size * size / 120.0).round() as usize;
    for _ in 0..crates {
        let s = rng.random_range(0.5..0.9);
        let c = [rng.random_range(-h + FENCE_MARGIN_M..h - FENCE_MARGIN_M), rng.random_range(-h + FENCE_MARGIN_M..h - FENCE_MARGIN_M)];
        let probe = Obstacle::Box { center: [cm(c[0]), cm(c[1])], size: [cm(s), cm(s)], angle_deg: cm(rng.random_range(0.0..90.0)), height_m: 0.8 };
        if obstacles.iter().all(|o| gap(o, &probe) > 1.6) {
            obstacles.push(probe);
        }
    }
    // Pillars on a grid in large halls, where they do not touch anything.
    if size > 25.0 {
        let step = rng.random_range(8.0..12.0);
        let mut y = -h + step;
        while y < h - 2.0 {
            let mut x = -h + step;
            while x < h - 2.0 {
                let p = Obstacle::Circle { center: [cm(x), cm(y)], radius: 0.25, height_m: 3.0 };
                if obstacles.iter().all(|o| gap(o, &p) > 1.6) {
                    obstacles.push(p);
                }
                x += step;
            }
            y += step;
        }
    }
    vector_map(name, size, obstacles, Vec::new())
}

pub(super) fn forest(rng: &mut Pcg64Mcg, size: f64, name: &str) -> Result<Map> {
    let h = size / 2.0 - FENCE_MARGIN_M;
    let min_gap = rng.random_range(1.4..3.0);
    let boulder_share = rng.random_range(0.1..0.3);
    let mut obstacles: Vec<Obstacle> = Vec::new();
    let darts = (size * size / 1.5) as usize;
    for _ in 0..darts {
        let c = [rng.random_range(-h..h), rng.random_range(-h..h)];
        let o = if rng.random_bool(boulder_share) { boulder(rng, c, 0.4, 1.2) } else { Obstacle::Circle { center: [cm(c[0]), cm(c[1])], radius: cm(rng.random_range(0.12..0.45)), height_m: 5.0 } };
        if inside_fence(&o, size) && obstacles.iter().all(|p| gap(p, &o) >= min_gap) {
            obstacles.push(o);
        }
    }
    vector_map(name, size, obstacles, Vec::new())
}

pub(super) fn field(rng: &mut Pcg64Mcg, size: f64, name: &str) -> Result<Map> {
    let h = size / 2.0 - FENCE_MARGIN_M;
    let (mut obstacles, mut shaded) = (Vec::new(), Vec::new());
    let groves = 1 + (size * size / 600.0) as usize;
    let mut tries = 0;
    while shaded.len() < groves * 4 && tries < 400 {
        tries += 1;
        // A grove: a centre, then trees around it.
        let g = [rng.random_range(-h..h), rng.random_range(-h..h)];
        let trees = rng.random_range(1..=5);
        for _ in 0..trees {
            let c = [(g[0] + rng.random_range(-5.0..5.0)).clamp(-h, h), (g[1] + rng.random_range(-5.0..5.0)).clamp(-h, h)];
            let trunk = Obstacle::Circle { center: [cm(c[0]), cm(c[1])], radius: cm(rng.random_range(0.2..0.3)), height_m: 5.0 };
            if obstacles.iter().all(|p| gap(p, &trunk) >= 3.0) {
                obstacles.push(trunk);
                shaded.push(Region::Circle { center: [cm(c[0]), cm(c[1])], radius: cm(rng.random_range(2.0..4.5)) });
            }
        }
    }
    let boulders = (size * size / 150.0) as usize;
    for _ in 0..boulders {
        let c = [rng.random_range(-h..h), rng.random_range(-h..h)];
        let b = boulder(rng, c, 0.5, 1.5);
        if inside_fence(&b, size) && obstacles.iter().all(|p| gap(p, &b) >= 3.0) {
            obstacles.push(b);
        }
    }
    vector_map(name, size, obstacles, shaded)
}

/// Whether `o` lies within the fence of a world of side `size` centred on the origin. A
/// boulder drawn near the fence can reach past it (a field's, up to 1.5 m across a 1.2 m
/// margin), and a map with an obstacle outside its bounds does not load: such a draw is
/// skipped, after its random numbers are spent, so every other world stays as it was.
fn inside_fence(o: &Obstacle, size: f64) -> bool {
    let h = size / 2.0;
    o.outline().iter().all(|p| p[0].abs() <= h && p[1].abs() <= h)
}

/// An irregular convex-ish boulder: 5–8 points at radii within [0.7 r, r] of `c`.
fn boulder(rng: &mut Pcg64Mcg, c: [f64; 2], r_min: f64, r_max: f64) -> Obstacle {
    let r = rng.random_range(r_min..r_max);
    let n = rng.random_range(5..=8);
    let turn = rng.random_range(0.0..std::f64::consts::TAU);
    let points = (0..n)
        .map(|k| {
            let a = turn + std::f64::consts::TAU * k as f64 / n as f64;
            let rr = r * rng.random_range(0.7..1.0);
            [cm(c[0] + rr * a.cos()), cm(c[1] + rr * a.sin())]
        })
        .collect();
    Obstacle::Polygon { points, height_m: 1.0 }
}

/// Centre and bounding radius of an obstacle.
fn disc(o: &Obstacle) -> ([f64; 2], f64) {
    match o {
        Obstacle::Circle { center, radius, .. } => (*center, *radius),
        _ => {
            let pts = o.outline();
            let n = pts.len() as f64;
            let c = [pts.iter().map(|p| p[0]).sum::<f64>() / n, pts.iter().map(|p| p[1]).sum::<f64>() / n];
            (c, pts.iter().map(|p| (p[0] - c[0]).hypot(p[1] - c[1])).fold(0.0, f64::max))
        }
    }
}

/// A lower bound on the free gap between two obstacles (their bounding discs), except for two
/// axis-aligned boxes, whose gap is exact.
fn gap(a: &Obstacle, b: &Obstacle) -> f64 {
    if let (Obstacle::Box { center: ca, size: sa, angle_deg: 0.0, .. }, Obstacle::Box { center: cb, size: sb, angle_deg: 0.0, .. }) = (a, b) {
        let dx = (ca[0] - cb[0]).abs() - (sa[0] + sb[0]) / 2.0;
        let dy = (ca[1] - cb[1]).abs() - (sa[1] + sb[1]) / 2.0;
        return if dx > 0.0 && dy > 0.0 { dx.hypot(dy) } else { dx.max(dy) };
    }
    let ((ca, ra), (cb, rb)) = (disc(a), disc(b));
    (ca[0] - cb[0]).hypot(ca[1] - cb[1]) - ra - rb
}
