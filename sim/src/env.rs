//! Episodes: one vehicle ([`Env`]) and many at once ([`VecEnv`], what actors use).
//!
//! Observation (paper §III-A), with n beams, 2n + 3 floats:
//!
//! ```text
//!   [ ranges_t (n) | ranges_{t−1} (n) | v_{t−1} | ω_{t−1} | R_{t−1} ]
//! ```
//!
//! ranges normalised to [−1, 1] as 2r/r_max − 1; v (m/s) and ω (rad/s) are the last commanded
//! action and R the last reward, in physical units. At a reset both scans are the first scan
//! and the last action and reward are 0. Beyond the paper, and only when asked for
//! ([`crate::ObservationConfig`]), the staleness (one value) and then the start's offset (two)
//! follow.
//!
//! An episode ends either by **collision** (`terminal`: the value of what follows is 0, no
//! bootstrapping) or by reaching `max_steps` (`truncated`: the task goes on, bootstrapping
//! continues). A collision on the last step is terminal; the two flags are never both set.

use std::sync::Arc;

use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64Mcg;

use crate::config::EnvConfig;
use crate::error::{Result, SimError};
use crate::explore::ExplorationTracker;
use crate::map::Map;
use crate::scene::{Footprint, Scene};
use crate::sensor::RangeSensor;
use crate::vehicle::Pose;

/// Grid cell size of the scene index [measured with `mapless bench sim` in env2: 2 m beat
/// 0.5 m and 1 m for 7- and 100-beam scans; a 12 m beam crosses at most ~12 cells].
const SCENE_CELL_M: f64 = 2.0;

/// A map with a configuration, ready to host vehicles. Immutable and shared (`Arc`).
#[derive(Debug)]
pub struct World {
    pub map: Map,
    pub cfg: EnvConfig,
    /// Everything the car can hit.
    pub collide: Scene,
    /// Everything the sensor can see (obstacles taller than the sensor).
    pub sense: Scene,
    pub footprint: Footprint,
}

impl World {
    pub fn new(map: Map, cfg: EnvConfig) -> Result<Arc<World>> {
        cfg.validate()?;
        let collide = map.scene(0.0, SCENE_CELL_M);
        let sense = map.scene(cfg.sensor.height_m, SCENE_CELL_M);
        let footprint = Footprint { half_length_m: cfg.vehicle.length_m / 2.0, half_width_m: cfg.vehicle.width_m / 2.0 };
        Ok(Arc::new(World { map, cfg, collide, sense, footprint }))
    }

    pub fn obs_dim(&self) -> usize {
        self.cfg.obs_dim()
    }

    /// Can the car stand here with `clearance_m` to spare? Conservative: the centre must be at
    /// least clearance + the footprint's circumradius from every surface, whatever the heading.
    pub fn is_valid_start(&self, x: f64, y: f64, clearance_m: f64) -> bool {
        self.map.is_free(x, y) && self.collide.distance_to_nearest(x, y) >= clearance_m + self.cfg.vehicle.circumradius_m()
    }

    /// Does the car at `pose` face a surface within `within_m`? Rays from its centre across its
    /// front — the heading and ± 15°, 30°, 45° — and the nearest hit counts (a hard start,
    /// `episode.hard_start_share`).
    pub fn faces_surface_within(&self, pose: Pose, within_m: f64) -> bool {
        let reach = within_m as f32;
        (-3..=3).any(|k| {
            let a = pose.heading_rad + f64::from(k) * 15f64.to_radians();
            self.collide.cast_ray(pose.x_m as f32, pose.y_m as f32, a.cos() as f32, a.sin() as f32, reach) < reach
        })
    }

    /// Can the car, started at `pose`, drive on for ever? The car has no reverse and turns no
    /// tighter than L / tan δ_max (0.76 m at the rear axle), so a pose 0.83 m from a wall and
    /// facing it collides whatever the policy does. The witness used here: after driving
    /// straight for 0, 0.5, 1, 1.5 or 2 m, the car steers to full lock, left or right, and drives
    /// a whole circle without touching anything — a loop it could repeat for ever. Sufficient,
    /// not necessary (a pose in a corridor too narrow to turn in, heading along it, fails it and
    /// is merely not used as a start).
    pub fn can_circle_from(&self, pose: Pose) -> bool {
        let vc = &self.cfg.vehicle;
        let hits = |p: &Pose| self.collide.footprint_collides(p.x_m, p.y_m, p.heading_rad, &self.footprint);
        // Walk in pieces no longer than the simulator's own sub-step.
        let piece_m = vc.max_substep_m.min(0.05);
        let circle_m = std::f64::consts::TAU * vc.min_turning_radius_m();
        let n_circle = (circle_m / piece_m).ceil() as usize;
        let circle_t = circle_m / n_circle as f64 / vc.v_max_mps;
        let circles = |from: Pose| {
            [vc.max_steer_rad, -vc.max_steer_rad].into_iter().any(|steer| {
                let mut p = from;
                (0..n_circle).all(|_| {
                    p = vc.advance(p, vc.v_max_mps, steer, circle_t);
                    !hits(&p)
                })
            })
        };
        // Four straight legs of 0.5 m; a circle is tried before the first and after each.
        const LEG_M: f64 = 0.5;
        const LEGS: usize = 4;
        let per_leg = (LEG_M / piece_m).ceil() as usize;
        let leg_t = LEG_M / per_leg as f64 / vc.v_max_mps;
        let mut p = pose;
        for leg in 0..=LEGS {
            if leg > 0 {
                for _ in 0..per_leg {
                    p = vc.advance(p, vc.v_max_mps, 0.0, leg_t);
                    if hits(&p) {
                        return false;
                    }
                }
            }
            if circles(p) {
                return true;
            }
        }
        false
    }
}

/// Result of one step of one vehicle.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StepOutcome {
    pub reward: f32,
    /// Collision: no bootstrapping.
    pub terminal: bool,
    /// Step limit reached: bootstrapping continues.
    pub truncated: bool,
}

impl StepOutcome {
    pub fn done(&self) -> bool {
        self.terminal || self.truncated
    }
}

/// What an episode achieved, reported when it ends.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct EpisodeSummary {
    /// The world it ran in (its map's name).
    pub map: String,
    pub episode_id: u64,
    #[serde(rename = "return")]
    pub return_: f64,
    pub steps: u32,
    pub terminal: bool,
    pub truncated: bool,
    pub eqs: u64,
    pub ees: f64,
    pub distance_m: f64,
    pub shaded_time_s: f64,
}

/// One vehicle in a world.
#[derive(Clone, Debug)]
pub struct Env {
    world: Arc<World>,
    sensor: RangeSensor,
    rng: Pcg64Mcg,
    pose: Pose,
    ranges: Vec<f32>,
    prev_ranges: Vec<f32>,
    prev_v: f32,
    prev_omega: f32,
    prev_reward: f32,
    /// Steps since the pose last entered a cell the episode had not visited.
    stale_steps: u32,
    steps: u32,
    /// This episode's limit: `episode.max_steps`, or `episode.long_max_steps` for a long one.
    max_steps: u32,
    return_: f64,
    episode_id: u64,
    episodes_started: u64,
    tracker: ExplorationTracker,
    trajectory: Option<Vec<[f64; 2]>>,
}

/// SplitMix64: decorrelates seeds of neighbouring vehicles.
fn splitmix64(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

impl Env {
    /// A vehicle with its own random stream. Call [`Env::reset`] before stepping.
    pub fn new(world: Arc<World>, seed: u64) -> Self {
        let n = world.cfg.sensor.beams;
        let tracker = ExplorationTracker::new(world.map.bounds, &world.cfg.exploration);
        let max_steps = world.cfg.episode.max_steps;
        Env {
            sensor: RangeSensor::new(&world.cfg.sensor),
            rng: Pcg64Mcg::seed_from_u64(splitmix64(seed)),
            world,
            pose: Pose { x_m: 0.0, y_m: 0.0, heading_rad: 0.0 },
            ranges: vec![0.0; n],
            prev_ranges: vec![0.0; n],
            prev_v: 0.0,
            prev_omega: 0.0,
            prev_reward: 0.0,
            stale_steps: 0,
            steps: 0,
            max_steps,
            return_: 0.0,
            episode_id: 0,
            episodes_started: 0,
            tracker,
            trajectory: None,
        }
    }

    pub fn world(&self) -> &Arc<World> {
        &self.world
    }

    /// Moves the vehicle to another world for its next episode (call [`Env::reset`] next). The
    /// world must give observations of the same length (the same sensor).
    pub fn set_world(&mut self, world: Arc<World>) -> Result<()> {
        if world.obs_dim() != self.world.obs_dim() {
            return Err(SimError::InvalidConfig(format!("world `{}` gives {} observation values, `{}` gave {}", world.map.name, world.obs_dim(), self.world.map.name, self.world.obs_dim())));
        }
        if world.map.bounds != self.world.map.bounds || world.cfg.exploration != self.world.cfg.exploration {
            self.tracker = ExplorationTracker::new(world.map.bounds, &world.cfg.exploration);
        }
        self.world = world;
        Ok(())
    }
    pub fn pose(&self) -> Pose {
        self.pose
    }
    pub fn steps(&self) -> u32 {
        self.steps
    }
    pub fn episode_id(&self) -> u64 {
        self.episode_id
    }
    /// Latest measured ranges in metres.
    pub fn ranges_m(&self) -> &[f32] {
        &self.ranges
    }
    pub fn tracker(&self) -> &ExplorationTracker {
        &self.tracker
    }
    /// Keep every pose of the current episode (for pictures). Off by default.
    pub fn record_trajectory(&mut self, on: bool) {
        self.trajectory = on.then(Vec::new);
    }
    pub fn trajectory(&self) -> Option<&[[f64; 2]]> {
        self.trajectory.as_deref()
    }

    /// Starts an episode at a uniformly random collision-free pose (with `episode.start_escapable`,
    /// one the car can drive on from: [`World::can_circle_from`]) and writes its observation.
    pub fn reset(&mut self, obs: &mut [f32]) -> Result<()> {
        let w = Arc::clone(&self.world);
        let b = w.map.bounds;
        let ep = &w.cfg.episode;
        // Drawn only when asked for, so that shares of 0 leave every seed's starts unchanged.
        let facing = (ep.hard_start_share > 0.0 && self.rng.random::<f64>() < ep.hard_start_share).then_some(ep.hard_start_within_m);
        let long = ep.long_share > 0.0 && self.rng.random::<f64>() < ep.long_share;
        for _ in 0..ep.start_attempts {
            let x = self.rng.random_range(b.min_x..b.max_x);
            let y = self.rng.random_range(b.min_y..b.max_y);
            let heading = self.rng.random_range(-std::f64::consts::PI..std::f64::consts::PI);
            let pose = Pose { x_m: x, y_m: y, heading_rad: heading };
            if w.is_valid_start(x, y, ep.start_clearance_m) && facing.is_none_or(|d| w.faces_surface_within(pose, d)) && (!ep.start_escapable || w.can_circle_from(pose)) {
                self.reset_to(pose, obs);
                if long {
                    self.max_steps = ep.long_max_steps;
                }
                return Ok(());
            }
        }
        Err(SimError::NoFreeStart { map: w.map.name.clone(), clearance_m: ep.start_clearance_m, escapable: ep.start_escapable, facing_within_m: facing, attempts: ep.start_attempts })
    }

    /// Starts an episode at a given pose (evaluation, tests). The pose is not checked.
    pub fn reset_to(&mut self, pose: Pose, obs: &mut [f32]) {
        self.pose = pose;
        self.steps = 0;
        self.max_steps = self.world.cfg.episode.max_steps;
        self.return_ = 0.0;
        self.episodes_started += 1;
        self.episode_id = self.episodes_started;
        self.prev_v = 0.0;
        self.prev_omega = 0.0;
        self.prev_reward = 0.0;
        self.stale_steps = 0;
        let w = Arc::clone(&self.world);
        self.sensor.scan(&w.sense, &pose, &mut self.rng, &mut self.ranges);
        self.prev_ranges.copy_from_slice(&self.ranges);
        self.tracker.reset(pose.x_m, pose.y_m);
        if let Some(t) = &mut self.trajectory {
            t.clear();
            t.push([pose.x_m, pose.y_m]);
        }
        self.write_obs(obs);
    }

    /// Applies action a ∈ [−1, 1]² (clipped) for one control period and writes the next
    /// observation. Errors (and changes nothing) if the action is not finite.
    pub fn step(&mut self, action: [f32; 2], next_obs: &mut [f32]) -> Result<StepOutcome> {
        if !(action[0].is_finite() && action[1].is_finite()) {
            return Err(SimError::InvalidAction { vehicle: 0, problem: format!("not finite: {action:?}") });
        }
        let w = Arc::clone(&self.world);
        let vc = &w.cfg.vehicle;
        let cmd = vc.command(action[0], action[1]);
        let n = vc.substeps(cmd.v_mps);
        let h = vc.dt_s / n as f64;
        let mut collided = false;
        for _ in 0..n {
            self.pose = vc.advance(self.pose, cmd.v_mps, cmd.steer_rad, h);
            if w.collide.footprint_collides(self.pose.x_m, self.pose.y_m, self.pose.heading_rad, &w.footprint) {
                collided = true;
                break;
            }
        }
        std::mem::swap(&mut self.ranges, &mut self.prev_ranges);
        self.sensor.scan(&w.sense, &self.pose, &mut self.rng, &mut self.ranges);
        let r_min = self.ranges.iter().copied().fold(f32::INFINITY, f32::min) as f64;
        let shade = if w.map.in_shade(self.pose.x_m, self.pose.y_m) { vc.dt_s } else { 0.0 };
        let eqs_gained = self.tracker.visit(self.pose.x_m, self.pose.y_m, shade);
        let new_cell = eqs_gained > 0;
        self.stale_steps = if new_cell { 0 } else { self.stale_steps.saturating_add(1) };
        let rc = &w.cfg.reward;
        let mut reward = rc.reward(r_min, cmd.v_mps, cmd.omega_radps);
        if collided {
            reward += rc.collision;
        }
        if new_cell {
            reward += rc.novelty + rc.novelty_eqs * rc.novelty_eqs_paid(eqs_gained);
        }
        if let Some(t) = &mut self.trajectory {
            t.push([self.pose.x_m, self.pose.y_m]);
        }
        self.steps += 1;
        self.return_ += reward;
        self.prev_v = cmd.v_mps as f32;
        self.prev_omega = cmd.omega_radps as f32;
        self.prev_reward = reward as f32;
        self.write_obs(next_obs);
        let terminal = collided;
        let truncated = !terminal && self.steps >= self.max_steps;
        Ok(StepOutcome { reward: reward as f32, terminal, truncated })
    }

    /// Statistics of the episode so far.
    pub fn summary(&self, outcome: Option<StepOutcome>) -> EpisodeSummary {
        EpisodeSummary {
            map: self.world.map.name.clone(),
            episode_id: self.episode_id,
            return_: self.return_,
            steps: self.steps,
            terminal: outcome.is_some_and(|o| o.terminal),
            truncated: outcome.is_some_and(|o| o.truncated),
            eqs: self.tracker.eqs(),
            ees: self.tracker.ees(),
            distance_m: self.tracker.distance_m(),
            shaded_time_s: self.tracker.shaded_time_s(),
        }
    }

    fn write_obs(&self, obs: &mut [f32]) {
        let n = self.ranges.len();
        debug_assert_eq!(obs.len(), self.world.cfg.obs_dim());
        let scale = 2.0 / self.world.cfg.sensor.max_range_m as f32;
        for k in 0..n {
            obs[k] = self.ranges[k] * scale - 1.0;
            obs[n + k] = self.prev_ranges[k] * scale - 1.0;
        }
        obs[2 * n] = self.prev_v;
        obs[2 * n + 1] = self.prev_omega;
        obs[2 * n + 2] = self.prev_reward;
        let s = self.world.cfg.observation.staleness_steps;
        if s > 0 {
            obs[2 * n + 3] = self.stale_steps.min(s) as f32 / s as f32;
        }
        let l = self.world.cfg.observation.start_offset_m;
        if l > 0.0 {
            // The start is the EQS rings' centre, which the tracker keeps.
            let (sx, sy) = self.tracker.start();
            let (dx, dy) = (sx - self.pose.x_m, sy - self.pose.y_m);
            let d = dx.hypot(dy);
            let scale = if d > 0.0 { (d / l).tanh() / d } else { 0.0 };
            // The start in the car's frame: x ahead, y to the left.
            let (s_h, c_h) = self.pose.heading_rad.sin_cos();
            let len = obs.len();
            obs[len - 2] = ((dx * c_h + dy * s_h) * scale) as f32;
            obs[len - 1] = ((-dx * s_h + dy * c_h) * scale) as f32;
        }
    }
}

/// Outputs of one [`VecEnv::step`], columnar (row i = vehicle i).
#[derive(Clone, Debug, Default)]
pub struct VecStep {
    /// Observation after the step, before any reset (what the transition stores).
    pub next_obs: Vec<f32>,
    pub reward: Vec<f32>,
    pub terminal: Vec<bool>,
    pub truncated: Vec<bool>,
    /// Episodes that ended in this step: (vehicle index, summary). Those vehicles have been
    /// reset; [`VecEnv::obs`] holds their new first observation.
    pub finished: Vec<(usize, EpisodeSummary)>,
}

/// Many vehicles in one world (or a pool of worlds, one drawn per episode), stepped with one
/// call; episodes reset automatically.
pub struct VecEnv {
    envs: Vec<Env>,
    obs: Vec<f32>,
    obs_dim: usize,
    /// Where each episode's world is drawn from (one world: never redrawn).
    worlds: Vec<Arc<World>>,
    /// The stream that picks worlds (separate from the vehicles', so one world gives the same
    /// episodes as before pools existed).
    pick: Pcg64Mcg,
}

impl VecEnv {
    /// `n` vehicles; vehicle i draws from stream (seed, i). All are reset.
    pub fn new(world: Arc<World>, n: usize, seed: u64) -> Result<Self> {
        Self::with_worlds(vec![world], n, seed)
    }

    /// `n` vehicles, each episode in a world drawn uniformly from `worlds` (e.g. a
    /// [`crate::worlds::WorldPool`]'s).
    pub fn with_worlds(worlds: Vec<Arc<World>>, n: usize, seed: u64) -> Result<Self> {
        let first = worlds.first().ok_or_else(|| SimError::InvalidConfig("no world to drive in".into()))?;
        let d = first.obs_dim();
        if let Some(w) = worlds.iter().find(|w| w.obs_dim() != d) {
            return Err(SimError::InvalidConfig(format!("world `{}` gives {} observation values, `{}` gives {d}", w.map.name, w.obs_dim(), first.map.name)));
        }
        let mut pick = Pcg64Mcg::seed_from_u64(splitmix64(seed ^ 0x5EED_0F30_17D5));
        let mut envs = Vec::with_capacity(n);
        for i in 0..n {
            let w = if worlds.len() > 1 { &worlds[pick.random_range(0..worlds.len())] } else { first };
            envs.push(Env::new(Arc::clone(w), splitmix64(seed) ^ (i as u64).wrapping_mul(0xA24B_AED4_963E_E407)));
        }
        let mut obs = vec![0.0; n * d];
        for (e, o) in envs.iter_mut().zip(obs.chunks_exact_mut(d)) {
            e.reset(o)?;
        }
        Ok(VecEnv { envs, obs, obs_dim: d, worlds, pick })
    }

    /// The worlds episodes are drawn from.
    pub fn worlds(&self) -> &[Arc<World>] {
        &self.worlds
    }

    pub fn len(&self) -> usize {
        self.envs.len()
    }
    pub fn is_empty(&self) -> bool {
        self.envs.is_empty()
    }
    pub fn obs_dim(&self) -> usize {
        self.obs_dim
    }
    /// Current observations (n × obs_dim), what the policy acts on.
    pub fn obs(&self) -> &[f32] {
        &self.obs
    }
    pub fn envs(&self) -> &[Env] {
        &self.envs
    }
    pub fn envs_mut(&mut self) -> &mut [Env] {
        &mut self.envs
    }

    /// Steps every vehicle with `actions` (n × 2, row-major). Validates the whole batch first:
    /// on error nothing moves.
    pub fn step(&mut self, actions: &[f32], out: &mut VecStep) -> Result<()> {
        let n = self.envs.len();
        if actions.len() != 2 * n {
            return Err(SimError::InvalidAction { vehicle: 0, problem: format!("expected {} action values for {n} vehicles, got {}", 2 * n, actions.len()) });
        }
        if let Some(i) = actions.iter().position(|a| !a.is_finite()) {
            return Err(SimError::InvalidAction { vehicle: i / 2, problem: format!("component {} is {}", i % 2, actions[i]) });
        }
        let d = self.obs_dim;
        out.next_obs.resize(n * d, 0.0);
        out.reward.resize(n, 0.0);
        out.terminal.resize(n, false);
        out.truncated.resize(n, false);
        out.finished.clear();
        for (i, env) in self.envs.iter_mut().enumerate() {
            let next = &mut out.next_obs[i * d..(i + 1) * d];
            let o = env.step([actions[2 * i], actions[2 * i + 1]], next)?;
            out.reward[i] = o.reward;
            out.terminal[i] = o.terminal;
            out.truncated[i] = o.truncated;
            let cur = &mut self.obs[i * d..(i + 1) * d];
            if o.done() {
                out.finished.push((i, env.summary(Some(o))));
                if self.worlds.len() > 1 {
                    env.set_world(Arc::clone(&self.worlds[self.pick.random_range(0..self.worlds.len())]))?;
                }
                env.reset(cur)?;
            } else {
                cur.copy_from_slice(next);
            }
        }
        Ok(())
    }
}
