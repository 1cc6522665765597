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
//! lattice fine (0.1 m, 5° in the docs' figures). With eq. (2)'s bands the bounds are the
//! reward's supremum over every minimum range up to r_max.

use serde::Serialize;

use crate::config::RewardConfig;
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
    /// The 50th, 90th and 99th percentiles of the noiseless minimum range over those poses (m,
    /// to the 0.01 m of a histogram): what the scans a policy meets there look like.
    pub min_range_percentiles_m: [f64; 3],
    /// Collision-free poses scanned.
    pub poses: usize,
    /// Per-step reward at most: r_max (+ 4 σ) at full speed, no turn.
    pub per_step: f64,
    /// Per-step reward of a car that does not move, at most.
    pub standing_still_per_step: f64,
}

/// The least upper bound of the reward over minimum ranges in [0, r_max] at speed v and no turn.
/// Eq. (1)'s r² term grows with r, so its best is at r_max; a positive band of eq. (2) pays most
/// just inside its upper edge, so each band's edge (or r_max, if lower) is a candidate too.
fn sup_reward(reward: &RewardConfig, r_max_m: f64, v_mps: f64) -> f64 {
    let at = |r: f64| {
        let bands: f64 = reward.bands.iter().filter(|b| b.min_m < r && r <= b.max_m).map(|b| b.value).sum();
        reward.range_weight * r * r + reward.speed_weight * v_mps * v_mps + bands
    };
    reward.bands.iter().filter(|b| b.min_m < r_max_m).map(|b| at(b.max_m.min(r_max_m))).fold(at(r_max_m), f64::max)
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
    // Minimum ranges in 0.01 m bins, for the percentiles.
    const BIN_M: f64 = 0.01;
    let mut hist = vec![0u64; (cfg.sensor.max_range_m / BIN_M).ceil() as usize + 1];
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
                let last = hist.len() - 1;
                hist[((r / BIN_M) as usize).min(last)] += 1;
                if r > best {
                    best = r;
                    at = [x, y, heading];
                }
            }
        }
    }
    let percentile = |q: f64| {
        let rank = (q * poses as f64).ceil().max(1.0) as u64;
        let mut seen = 0;
        hist.iter()
            .position(|&c| {
                seen += c;
                seen >= rank
            })
            .map_or(0.0, |i| (i as f64 + 1.0) * BIN_M)
            .min(best)
    };
    let min_range_percentiles_m = [percentile(0.5), percentile(0.9), percentile(0.99)];
    let r = (best + 4.0 * cfg.sensor.noise_std_m).min(cfg.sensor.max_range_m);
    let reward = &cfg.reward;
    RewardBounds {
        max_min_range_m: best,
        at,
        mean_min_range_m: if poses > 0 { sum / poses as f64 } else { 0.0 },
        min_range_percentiles_m,
        poses,
        per_step: sup_reward(reward, r, cfg.vehicle.v_max_mps),
        standing_still_per_step: sup_reward(reward, r, 0.0),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bands_count_where_they_can_be_reached() {
        let eq1 = RewardConfig::exploration();
        // Eq. (1): the r² term at r_max: 0.0075 · 36 + 1.5 · 0.25 = 0.645.
        assert!((sup_reward(&eq1, 6.0, 0.5) - 0.645).abs() < 1e-12);
        // Eq. (2): +2 just inside 2.5 m beats r_max = 6 m: 0.0075 · 6.25 + 2 = 2.046875
        // (the −50 band below 1 m never helps).
        let eq2 = RewardConfig::search_and_rescue();
        assert!((sup_reward(&eq2, 6.0, 0.0) - 2.046875).abs() < 1e-12);
        // Below 2.5 m the band's best is at r_max itself; below 2 m it cannot be reached.
        assert!((sup_reward(&eq2, 2.2, 0.0) - (0.0075 * 2.2 * 2.2 + 2.0)).abs() < 1e-12);
        assert!((sup_reward(&eq2, 1.5, 0.0) - 0.0075 * 2.25).abs() < 1e-12);
    }
}
