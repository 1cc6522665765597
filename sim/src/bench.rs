//! Throughput measurement shared by `mapless bench sim` and the criterion benches.
//!
//! One thread steps a [`VecEnv`] with pre-drawn uniform random actions (so vehicles crash and
//! episodes reset at a realistic rate, and the policy costs nothing), for a fixed wall time.

use std::time::{Duration, Instant};

use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64Mcg;

use crate::config::{EnvConfig, RaycastMethod};
use crate::env::{VecEnv, VecStep, World};
use crate::error::Result;

/// A sensor set-up to measure: the paper's template and the two dense scans SPEC §1 names.
#[derive(Clone, Copy, Debug)]
pub struct ScanPreset {
    pub beams: usize,
    pub fov_rad: f64,
    pub label: &'static str,
}

pub const SCAN_PRESETS: [ScanPreset; 3] = [
    ScanPreset { beams: 7, fov_rad: 3.0 * std::f64::consts::FRAC_PI_4, label: "7 beams over 135° (paper template)" },
    ScanPreset { beams: 100, fov_rad: std::f64::consts::FRAC_PI_2, label: "100 beams over 90° (AutoVRL)" },
    ScanPreset { beams: 1080, fov_rad: 1.5 * std::f64::consts::PI, label: "1080 beams over 270° (Hokuyo UST-10LX)" },
];

/// Result of one measurement.
#[derive(Clone, Debug)]
pub struct SimThroughput {
    pub steps: u64,
    pub seconds: f64,
    pub episodes: u64,
}

impl SimThroughput {
    pub fn steps_per_s(&self) -> f64 {
        self.steps as f64 / self.seconds
    }
}

/// Builds the benchmark's vectorised environment.
pub fn bench_env(map: &str, preset: ScanPreset, method: RaycastMethod, vehicles: usize) -> Result<VecEnv> {
    let mut cfg = EnvConfig::default();
    cfg.sensor.beams = preset.beams;
    cfg.sensor.fov_rad = preset.fov_rad;
    cfg.sensor.method = method;
    let world = World::new(crate::worlds::resolve(map)?, cfg)?;
    VecEnv::new(world, vehicles, 0xBE7C4)
}

/// Random actions for `vehicles`, `rows` steps' worth, cycled through during a run.
pub fn random_actions(vehicles: usize, rows: usize, seed: u64) -> Vec<f32> {
    let mut rng = Pcg64Mcg::seed_from_u64(seed);
    (0..vehicles * 2 * rows).map(|_| rng.random_range(-1.0f32..1.0)).collect()
}

/// Steps `env` for about `duration` on the calling thread.
pub fn measure(env: &mut VecEnv, duration: Duration) -> Result<SimThroughput> {
    let n = env.len();
    let actions = random_actions(n, 64, 1);
    let mut out = VecStep::default();
    let (mut steps, mut episodes, mut k) = (0u64, 0u64, 0usize);
    let start = Instant::now();
    // Check the clock every few batches only.
    while start.elapsed() < duration {
        for _ in 0..8 {
            let a = &actions[k * 2 * n..(k + 1) * 2 * n];
            env.step(a, &mut out)?;
            k = (k + 1) % 64;
            steps += n as u64;
            episodes += out.finished.len() as u64;
        }
    }
    Ok(SimThroughput { steps, seconds: start.elapsed().as_secs_f64(), episodes })
}
