//! What a world lets any policy earn: the largest minimum range over every pose the car can
//! stand in, and from it the per-step reward bounds of eq. (1) (`mapless maps stats`).
//!
//! The exploration reward is R = w_r r² + w_v v² − w_ω ω², r the smallest of the scan's
//! readings. No policy can beat w_r r_max² + w_v v_max² per step, and a car that stands still
//! (or turns on the spot: ω only costs) earns at most w_r r_max². In an empty 25 m box r_max is
//! the sensor's 12 m and standing in the middle pays 1.08 per step, three times the paper's
//! trained agents (Table III: 0.32–0.44): a return criterion of 320 then says nothing about
//! driving. A world is faithful to the paper when standing still cannot reach its returns.
//!
//! r_max is found by scanning a grid of poses (every collision-free position on a `grid_m`
//! lattice × `headings` headings) with noiseless ranges; the bounds add 4 σ of the range noise
//! (a reading exceeds its true range by more with probability 3·10⁻⁵). The grid can miss a
//! better pose between its points, so the bound is a measured figure, not a proof: keep the
//! lattice fine (0.1 m, 5° in the docs' figures).

use serde::Serialize;

use crate::env::World;
use crate::sensor::RangeSensor;
use crate::vehicle::Pose;

/// The largest minimum range of a world and the reward bounds it implies.
#[derive(Clone, Debug, Serialize)]
pub struct RewardBounds {
    /// Largest noiseless minimum range over the poses scanned (m).
    pub max_min_range_m: f64,
    /// Where it was found.
    pub at: [f64; 3],
    /// Mean noiseless minimum range over the collision-free poses scanned (m).
    pub mean_min_range_m: f64,
    /// Collision-free poses scanned.
    pub poses: usize,
    /// Per-step reward at most: r_max (+ 4 σ) at full speed, no turn.
    pub per_step: f64,
    /// Per-step reward of a car that does not move, at most.
    pub standing_still_per_step: f64,
}

/// Scans the world on a `grid_m` lattice with `headings` headings per position.
pub fn reward_bounds(world: &World, grid_m: f64, headings: usize) -> RewardBounds {
    assert!(grid_m > 0.0 && headings >= 1);
    let cfg = &world.cfg;
    let mut sensor = RangeSensor::new(&cfg.sensor);
    let mut ranges = vec![0.0f32; cfg.sensor.beams];
    let b = world.map.bounds;
    let nx = (b.width() / grid_m).floor() as usize;
    let ny = (b.height() / grid_m).floor() as usize;
    let (mut best, mut at, mut sum, mut poses) = (0.0f64, [0.0; 3], 0.0f64, 0usize);
    for j in 0..=ny {
        let y = b.min_y + j as f64 * grid_m;
        for i in 0..=nx {
            let x = b.min_x + i as f64 * grid_m;
            if !world.map.is_free(x, y) {
                continue;
            }
            for h in 0..headings {
                let heading = -std::f64::consts::PI + h as f64 * std::f64::consts::TAU / headings as f64;
                if world.collide.footprint_collides(x, y, heading, &world.footprint) {
                    continue;
                }
                let pose = Pose { x_m: x, y_m: y, heading_rad: heading };
                sensor.scan_exact(&world.sense, &pose, &mut ranges);
                let r = ranges.iter().copied().fold(f32::INFINITY, f32::min) as f64;
                sum += r;
                poses += 1;
                if r > best {
                    best = r;
                    at = [x, y, heading];
                }
            }
        }
    }
    let r = (best + 4.0 * cfg.sensor.noise_std_m).min(cfg.sensor.max_range_m);
    RewardBounds {
        max_min_range_m: best,
        at,
        mean_min_range_m: if poses > 0 { sum / poses as f64 } else { 0.0 },
        poses,
        per_step: cfg.reward.reward(r, cfg.vehicle.v_max_mps, 0.0),
        standing_still_per_step: cfg.reward.reward(r, 0.0, 0.0),
    }
}
