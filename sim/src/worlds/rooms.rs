//! `rooms`: rooms and corridors by binary space partition. Each split wall has a doorway (two
//! when it is long), so every room is reachable; walls never end inside an earlier doorway;
//! larger rooms get a piece or two of furniture away from the doorways.

use rand::Rng;
use rand_pcg::Pcg64Mcg;

use super::{cm, vector_map};
use crate::error::Result;
use crate::map::{Map, Obstacle};

/// Keep furniture this far from a doorway's centre (m).
const DOOR_KEEP_OUT_M: f64 = 2.5;
/// A new wall may not end this close to an earlier doorway (m).
const WALL_END_KEEP_OUT_M: f64 = 1.0;

#[derive(Clone, Copy)]
struct Rect {
    x0: f64,
    y0: f64,
    x1: f64,
    y1: f64,
}

struct Layout {
    min_room: f64,
    walls: Vec<[f64; 4]>,
    /// Doorway centres.
    doors: Vec<[f64; 2]>,
    /// Doorway openings as segments, to keep wall ends out of them.
    openings: Vec<[f64; 4]>,
    furniture: Vec<Obstacle>,
}

fn near_opening(l: &Layout, p: [f64; 2]) -> bool {
    l.openings.iter().any(|o| point_segment(p, o) < WALL_END_KEEP_OUT_M)
}

fn point_segment(p: [f64; 2], s: &[f64; 4]) -> f64 {
    let (dx, dy) = (s[2] - s[0], s[3] - s[1]);
    let len2 = dx * dx + dy * dy;
    let t = if len2 > 0.0 { (((p[0] - s[0]) * dx + (p[1] - s[1]) * dy) / len2).clamp(0.0, 1.0) } else { 0.0 };
    (p[0] - s[0] - t * dx).hypot(p[1] - s[1] - t * dy)
}

/// A wall from `a` to `b` along one axis with one or two doorways.
fn wall_with_doors(rng: &mut Pcg64Mcg, l: &mut Layout, a: [f64; 2], b: [f64; 2]) {
    let len = (b[0] - a[0]).hypot(b[1] - a[1]);
    let at = |t: f64| [a[0] + (b[0] - a[0]) * t / len, a[1] + (b[1] - a[1]) * t / len];
    let n_doors = if len > 16.0 { 2 } else { 1 };
    let mut cuts = Vec::new();
    for k in 0..n_doors {
        // Door k lies in its share of the wall, 0.6 m from the share's ends.
        let (s0, s1) = (len * k as f64 / n_doors as f64, len * (k + 1) as f64 / n_doors as f64);
        let w = rng.random_range(2.2..3.5f64).min(s1 - s0 - 1.2);
        let d0 = rng.random_range(s0 + 0.6..=s1 - 0.6 - w);
        cuts.push((d0, d0 + w));
    }
    let mut from = 0.0;
    for (d0, d1) in cuts {
        if d0 - from > 0.05 {
            let (p, q) = (at(from), at(d0));
            l.walls.push([cm(p[0]), cm(p[1]), cm(q[0]), cm(q[1])]);
        }
        let (p, q) = (at(d0), at(d1));
        l.openings.push([p[0], p[1], q[0], q[1]]);
        l.doors.push([(p[0] + q[0]) / 2.0, (p[1] + q[1]) / 2.0]);
        from = d1;
    }
    if len - from > 0.05 {
        let (p, q) = (at(from), at(len));
        l.walls.push([cm(p[0]), cm(p[1]), cm(q[0]), cm(q[1])]);
    }
}

fn split(rng: &mut Pcg64Mcg, l: &mut Layout, r: Rect, depth: u32) {
    let (w, h) = (r.x1 - r.x0, r.y1 - r.y0);
    let (can_x, can_y) = (w >= 2.0 * l.min_room, h >= 2.0 * l.min_room);
    let stop = !(can_x || can_y) || (depth >= 2 && rng.random_bool(0.2));
    if !stop {
        // Split across the longer side (a vertical wall when the room is wide).
        let vertical = if can_x && can_y { w > h || (w == h && rng.random_bool(0.5)) } else { can_x };
        for _ in 0..16 {
            if vertical {
                let x = cm(rng.random_range(r.x0 + l.min_room..=r.x1 - l.min_room));
                if near_opening(l, [x, r.y0]) || near_opening(l, [x, r.y1]) {
                    continue;
                }
                wall_with_doors(rng, l, [x, r.y0], [x, r.y1]);
                split(rng, l, Rect { x1: x, ..r }, depth + 1);
                split(rng, l, Rect { x0: x, ..r }, depth + 1);
            } else {
                let y = cm(rng.random_range(r.y0 + l.min_room..=r.y1 - l.min_room));
                if near_opening(l, [r.x0, y]) || near_opening(l, [r.x1, y]) {
                    continue;
                }
                wall_with_doors(rng, l, [r.x0, y], [r.x1, y]);
                split(rng, l, Rect { y1: y, ..r }, depth + 1);
                split(rng, l, Rect { y0: y, ..r }, depth + 1);
            }
            return;
        }
    }
    furnish(rng, l, r);
}

/// Up to two pieces of furniture, 1.3 m clear of the walls and away from the doorways.
fn furnish(rng: &mut Pcg64Mcg, l: &mut Layout, r: Rect) {
    let (w, h) = (r.x1 - r.x0, r.y1 - r.y0);
    if w * h < 25.0 {
        return;
    }
    let items = rng.random_range(0..=2);
    let mut placed: Vec<[f64; 3]> = Vec::new();
    for _ in 0..items {
        for _ in 0..8 {
            let round = rng.random_bool(0.35);
            let (sx, sy) = if round {
                let d: f64 = rng.random_range(0.6..1.6);
                (d, d)
            } else {
                (rng.random_range(0.8..2.5f64), rng.random_range(0.6..1.5f64))
            };
            let reach = 0.5 * sx.hypot(sy);
            let margin = 1.3 + reach;
            if w < 2.0 * margin + 0.5 || h < 2.0 * margin + 0.5 {
                break;
            }
            let c = [rng.random_range(r.x0 + margin..r.x1 - margin), rng.random_range(r.y0 + margin..r.y1 - margin)];
            let clear_of_doors = l.doors.iter().all(|d| (d[0] - c[0]).hypot(d[1] - c[1]) > DOOR_KEEP_OUT_M + reach);
            let clear_of_others = placed.iter().all(|p| (p[0] - c[0]).hypot(p[1] - c[1]) > p[2] + reach + 1.3);
            if !(clear_of_doors && clear_of_others) {
                continue;
            }
            placed.push([c[0], c[1], reach]);
            let center = [cm(c[0]), cm(c[1])];
            l.furniture.push(if round {
                Obstacle::Circle { center, radius: cm(sx / 2.0), height_m: 1.0 }
            } else {
                let angle_deg = if rng.random_bool(0.5) { 0.0 } else { 90.0 };
                Obstacle::Box { center, size: [cm(sx), cm(sy)], angle_deg, height_m: 1.0 }
            });
            break;
        }
    }
}

pub(super) fn rooms(rng: &mut Pcg64Mcg, size: f64, name: &str) -> Result<Map> {
    let h = size / 2.0;
    let mut l = Layout { min_room: rng.random_range(4.5..7.0), walls: Vec::new(), doors: Vec::new(), openings: Vec::new(), furniture: Vec::new() };
    split(rng, &mut l, Rect { x0: -h, y0: -h, x1: h, y1: h }, 0);
    let mut obstacles: Vec<Obstacle> = l.walls.iter().map(|w| Obstacle::Wall { from: [w[0], w[1]], to: [w[2], w[3]], height_m: 1.0 }).collect();
    obstacles.append(&mut l.furniture);
    vector_map(name, size, obstacles, Vec::new())
}
