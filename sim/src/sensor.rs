//! Planar range sensor: beams fanned around the heading, first surface along each beam,
//! Gaussian noise, clipped to [0, r_max]; a miss reads exactly r_max (no noise). With
//! `rays_per_beam` > 1 a beam reads the nearest surface of its rays (its sector's minimum), and
//! the noise is added to that reading.

use rand::Rng;
use rand_distr::StandardNormal;

use crate::config::{RaycastMethod, SensorConfig};
use crate::scene::Scene;
use crate::vehicle::Pose;

/// Ray count from which `RaycastMethod::Auto` switches to the fan sweep (measured with
/// `mapless bench sim`: the sweep wins from a few dozen beams on).
pub const FAN_FROM_BEAMS: usize = 32;

/// Precomputed ray geometry plus per-scan scratch buffers.
#[derive(Clone, Debug)]
pub struct RangeSensor {
    pub cfg: SensorConfig,
    /// Rays per beam (1: each beam is one ray, written straight into the caller's buffer).
    rays_per_beam: usize,
    /// Every ray's range, beam by beam (used only with more than one ray per beam).
    rays: Vec<f32>,
    rel_cos: Vec<f32>,
    rel_sin: Vec<f32>,
    first_rad: f64,
    step_rad: f64,
    use_fan: bool,
    dir_x: Vec<f32>,
    dir_y: Vec<f32>,
}

impl RangeSensor {
    pub fn new(cfg: &SensorConfig) -> Self {
        // The rays are evenly spaced whatever `rays_per_beam` is, so the fan sweep serves them.
        let angles = cfg.ray_angles_rad();
        let rays_per_beam = cfg.rays_per_beam.max(1);
        let step = if angles.len() > 1 { angles[1] - angles[0] } else { 1.0 };
        let use_fan = match cfg.method {
            RaycastMethod::Auto => angles.len() >= FAN_FROM_BEAMS,
            RaycastMethod::PerBeam => false,
            RaycastMethod::Fan => true,
        };
        RangeSensor {
            cfg: cfg.clone(),
            rays_per_beam,
            rays: if rays_per_beam > 1 { vec![0.0; angles.len()] } else { Vec::new() },
            rel_cos: angles.iter().map(|a| a.cos() as f32).collect(),
            rel_sin: angles.iter().map(|a| a.sin() as f32).collect(),
            first_rad: angles[0],
            step_rad: step,
            use_fan,
            dir_x: vec![0.0; angles.len()],
            dir_y: vec![0.0; angles.len()],
        }
    }

    /// Exact (noise-free) ranges from `pose` into `out` (metres), one per beam.
    pub fn scan_exact(&mut self, scene: &Scene, pose: &Pose, out: &mut [f32]) {
        if self.rays_per_beam == 1 {
            self.cast(scene, pose, out);
            return;
        }
        let mut rays = std::mem::take(&mut self.rays);
        self.cast(scene, pose, &mut rays);
        for (o, sector) in out.iter_mut().zip(rays.chunks_exact(self.rays_per_beam)) {
            *o = sector.iter().copied().fold(f32::INFINITY, f32::min);
        }
        self.rays = rays;
    }

    /// Exact range along every ray into `out`.
    fn cast(&mut self, scene: &Scene, pose: &Pose, out: &mut [f32]) {
        let (s, c) = pose.heading_rad.sin_cos();
        let (s, c) = (s as f32, c as f32);
        for k in 0..out.len() {
            // World direction = heading rotated by the beam's relative angle.
            self.dir_x[k] = c * self.rel_cos[k] - s * self.rel_sin[k];
            self.dir_y[k] = s * self.rel_cos[k] + c * self.rel_sin[k];
        }
        let (ox, oy) = (pose.x_m as f32, pose.y_m as f32);
        let r_max = self.cfg.max_range_m as f32;
        if self.use_fan {
            let angle0 = (pose.heading_rad + self.first_rad) as f32;
            scene.cast_fan(ox, oy, angle0, self.step_rad as f32, &self.dir_x, &self.dir_y, r_max, out);
        } else {
            for (k, o) in out.iter_mut().enumerate() {
                *o = scene.cast_ray(ox, oy, self.dir_x[k], self.dir_y[k], r_max);
            }
        }
    }

    /// Measured ranges: exact ranges plus N(0, σ²) noise on every hit, clipped to [0, r_max].
    pub fn scan<R: Rng>(&mut self, scene: &Scene, pose: &Pose, rng: &mut R, out: &mut [f32]) {
        self.scan_exact(scene, pose, out);
        let sigma = self.cfg.noise_std_m as f32;
        if sigma > 0.0 {
            let r_max = self.cfg.max_range_m as f32;
            for o in out.iter_mut() {
                if *o < r_max {
                    let n: f32 = rng.sample(StandardNormal);
                    *o = (*o + sigma * n).clamp(0.0, r_max);
                }
            }
        }
    }
}
