//! Every number the simulator uses, with its symbol and source.
//!
//! Sources: **[paper]** Sivashangaran & Eskandarian 2023 (equation numbers as there);
//! **[inferred]** the paper is silent, the value follows SPEC §1 (the MathWorks template the
//! paper's set-up follows, AutoVRL, F1TENTH, or what the paper's figures imply).

use serde::{Deserialize, Serialize};

use crate::error::{Result, SimError};

/// XTENTH-CAR kinematics and actuation (paper §IV-C, eqs. 13–16).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct VehicleConfig {
    /// L, wheelbase [paper: 0.32 m].
    pub wheelbase_m: f64,
    /// l_r, centre of mass to rear axle [inferred: L/2]; l_f = L − l_r.
    pub lr_m: f64,
    /// Footprint length (bumper to bumper) [inferred: 0.55 m].
    pub length_m: f64,
    /// Footprint width [inferred: 0.30 m].
    pub width_m: f64,
    /// δ_max, steering limit [inferred: 0.40 rad; F1TENTH 0.419, AutoVRL 0.36].
    pub max_steer_rad: f64,
    /// v_max: a₁ ∈ [−1, 1] maps to v = v_max (a₁ + 1) / 2 [inferred: 0.5 m/s].
    pub v_max_mps: f64,
    /// ω_max: a₂ ∈ [−1, 1] maps to ω = ω_max a₂ [inferred: 0.6 rad/s].
    pub omega_max_radps: f64,
    /// Control period (one environment step) [inferred: 0.1 s; 1000-step episodes = 100 s].
    pub dt_s: f64,
    /// Longest distance travelled between two collision checks; a step is cut into sub-steps
    /// so that no obstacle thinner than this can be jumped [inferred: 0.05 m].
    pub max_substep_m: f64,
}

impl Default for VehicleConfig {
    fn default() -> Self {
        VehicleConfig { wheelbase_m: 0.32, lr_m: 0.16, length_m: 0.55, width_m: 0.30, max_steer_rad: 0.40, v_max_mps: 0.5, omega_max_radps: 0.6, dt_s: 0.1, max_substep_m: 0.05 }
    }
}

/// Which ray caster answers a scan (see `scene`): both give the same ranges.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq, Eq, Default)]
#[serde(rename_all = "snake_case")]
pub enum RaycastMethod {
    /// Per-beam grid walk below 32 rays, fan sweep from 32 up.
    #[default]
    Auto,
    PerBeam,
    Fan,
}

/// Planar range sensor (LiDAR or RGB-D ranges), paper §III-A.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct SensorConfig {
    /// Number of beams [inferred, template: 7].
    pub beams: usize,
    /// Field of view, beams spread evenly over [−fov/2, +fov/2] [inferred, template: 3π/4].
    /// With fov ≥ 2π the last beam does not repeat the first.
    pub fov_rad: f64,
    /// r_max; a miss reads r_max [inferred, template: 12 m].
    pub max_range_m: f64,
    /// σ of additive Gaussian range noise; readings are clipped to [0, r_max] [inferred: 0.1 m].
    pub noise_std_m: f64,
    /// Mounting height: obstacles not taller than this are invisible (tree canopies are not
    /// obstacles at all) [inferred, AutoVRL: 0.15 m].
    pub height_m: f64,
    /// Rays per beam: each beam reads the nearest of this many rays spread evenly across its
    /// sector (the beam's direction ± half the spacing between beams; with one beam, the whole
    /// field of view), as LiDAR navigation stacks down-sample a dense scan by taking each bin's
    /// minimum. 1 (the default, and the paper's set-up) is a single ray per beam. More rays keep
    /// a post or a wall end between two beams from going unseen (at 7 beams over 135° the rays
    /// are 22.5° apart, 1.2 m at 3 m) without changing the observation's length [beyond the
    /// paper, issue 18; docs/simulator.md, "Beams that see their sector"].
    pub rays_per_beam: usize,
    /// Ray caster; does not change results.
    pub method: RaycastMethod,
}

impl Default for SensorConfig {
    fn default() -> Self {
        SensorConfig { beams: 7, fov_rad: 3.0 * std::f64::consts::FRAC_PI_4, max_range_m: 12.0, noise_std_m: 0.1, height_m: 0.15, rays_per_beam: 1, method: RaycastMethod::Auto }
    }
}

impl SensorConfig {
    /// Beam angles relative to the heading, ascending.
    pub fn beam_angles_rad(&self) -> Vec<f64> {
        let n = self.beams;
        if n == 1 {
            return vec![0.0];
        }
        let step = self.sector_rad();
        (0..n).map(|k| -self.fov_rad / 2.0 + k as f64 * step).collect()
    }

    /// The angle one beam's sector spans: the spacing between beams, or the field of view for
    /// a single beam. Its `rays_per_beam` rays lie `sector / rays_per_beam` apart, centred on
    /// the beam.
    pub fn sector_rad(&self) -> f64 {
        let n = self.beams;
        if n == 1 {
            self.fov_rad
        } else if self.is_full_circle() {
            self.fov_rad / n as f64
        } else {
            self.fov_rad / (n - 1) as f64
        }
    }

    /// Whether the field of view is a full circle (fov ≥ 2π), where the last beam does not
    /// repeat the first and beam 0 looks straight back.
    pub fn is_full_circle(&self) -> bool {
        self.fov_rad >= std::f64::consts::TAU - 1e-9
    }

    /// The beam that sees beam `k`'s direction in a mirror (left ↔ right, the heading's line
    /// the axis): beam angles are symmetric about the heading, so it is `n − 1 − k`, or
    /// `(n − k) mod n` for a full circle (whose beam 0 looks straight back).
    pub fn mirrored_beam(&self, k: usize) -> usize {
        let n = self.beams;
        if self.is_full_circle() { (n - k) % n } else { n - 1 - k }
    }

    /// Every ray's angle relative to the heading, ascending: `rays_per_beam` per beam, beam by
    /// beam. With one ray per beam these are [`SensorConfig::beam_angles_rad`].
    pub fn ray_angles_rad(&self) -> Vec<f64> {
        let m = self.rays_per_beam.max(1);
        if m == 1 {
            return self.beam_angles_rad();
        }
        let w = self.sector_rad();
        self.beam_angles_rad().iter().flat_map(|a| (0..m).map(move |j| a + w * ((j as f64 + 0.5) / m as f64 - 0.5))).collect()
    }
}

/// A reward band: `value` is added when `min_m < r < max_m` (r = minimum range).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct RewardBand {
    pub min_m: f64,
    pub max_m: f64,
    pub value: f64,
}

/// R = w_r r² + w_v v² − w_ω ω² + Σ bands (+ `collision` on a step that ends in one, +
/// `novelty` + `novelty_eqs`·[min(ΔEQS, c) + s·max(ΔEQS − c, 0)] on a step that enters a cell the
/// episode has not visited, ΔEQS what the cell adds to the EQS, c = `novelty_eqs_cap`, s =
/// `novelty_eqs_past_cap`; ΔEQS itself when c = 0, no cap), r the smallest range reading (metres),
/// v and ω the commanded action (m/s, rad/s). Eq. (1) and eq. (2) are presets.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct RewardConfig {
    /// Weight of r² [paper eq. 1: 0.0075].
    pub range_weight: f64,
    /// Weight of v² [paper eq. 1: 1.5].
    pub speed_weight: f64,
    /// Penalty weight of ω² [paper eq. 1: 0.6].
    pub turn_penalty: f64,
    /// Distance bands [paper eq. 2: +2.0 for 2.0 < r < 2.5, −50 for r < 1.0; none in eq. 1. A
    /// run may add one to eq. 1, beyond the paper (issue 18): a price on every step that comes
    /// close; −2 under 0.6 m in `explore-sac`, docs/simulator.md, "A price on coming close"].
    pub bands: Vec<RewardBand>,
    /// Added to the reward of a step that ends in a collision, ≤ 0 [ours, beyond the paper
    /// (issue 18): 0 in eq. 1 and eq. 2, where a collision costs only the value it ends].
    pub collision: f64,
    /// Added to the reward of a step whose pose enters an EQS cell (`exploration.cell_area_m2`)
    /// the episode has not visited before, ≥ 0 [ours, beyond the paper (issue 18): 0 in eq. 1
    /// and eq. 2. A count-based novelty bonus (the cells, not the EQS rings, so the metric
    /// itself is not what is paid): eq. (1) pays a car as much for a lap of one room's island as
    /// for a tour of the building]. At most one cell per step at v_max·dt ≤ one cell side, so
    /// it adds at most `novelty`·v_max·dt·√2/side per step on average (0.35 at 10 and 2 m cells).
    pub novelty: f64,
    /// Added, times what the step adds to the EQS, to the reward of a step that enters a new
    /// cell, ≥ 0 [ours, beyond the paper (issue 18): 0 in eq. 1 and eq. 2, 1.5 in the
    /// `explore-sac` preset (docs/experiments.md, "A bonus on the EQS"). The metric itself
    /// paid: over an episode the term sums to `novelty_eqs`·(EQS − 1), the start's cell not
    /// being entered, so a cell in ring n pays n times one beside the start, and a car that
    /// leaves the room it started in is paid for it; `novelty` pays every cell alike].
    pub novelty_eqs: f64,
    /// The most ΔEQS one new cell is paid for by `novelty_eqs`, > 0, or 0 for no cap [ours,
    /// beyond the paper (issue 18): 4 in `explore-sac`, 0 in the other presets. With the linear inner
    /// sum a cell pays its ring, so the bonus grows without end with the distance from the
    /// start and a car that knows where the start is (`observation.start_offset_m`) is paid
    /// most for the farthest place, in a cave a pocket's end; capped at c, every cell beyond
    /// ring c pays as one in ring c (c = 4: 7.5–10 m at 2.5 m rings), so leaving the start's
    /// neighbourhood pays and going farther does not. The EQS itself is not changed].
    pub novelty_eqs_cap: f64,
    /// The share s ∈ [0, 1] of what a new cell adds to the EQS past `novelty_eqs_cap` that is
    /// still paid: the cell pays min(ΔEQS, c) + s·(ΔEQS − c)⁺; 0 is the flat cap, 1 no cap; only
    /// with a cap [ours, beyond the paper (issue 18): 0.5 in `explore-sac`, 0 in the other presets. A flat
    /// cap pays every cell past ring c alike, so a memoryless car no longer gains by going on
    /// to the next room and laps the first one (env3, c = 4); s > 0 keeps a slope outward,
    /// shallower than the uncapped one that drives cars into a cave's far pockets].
    pub novelty_eqs_past_cap: f64,
}

impl Default for RewardConfig {
    fn default() -> Self {
        Self::exploration()
    }
}

impl RewardConfig {
    /// Paper eq. (1): exploration.
    pub fn exploration() -> Self {
        RewardConfig { range_weight: 0.0075, speed_weight: 1.5, turn_penalty: 0.6, bands: Vec::new(), collision: 0.0, novelty: 0.0, novelty_eqs: 0.0, novelty_eqs_cap: 0.0, novelty_eqs_past_cap: 0.0 }
    }
    /// Paper eq. (2): search and rescue — eq. (1) plus +2.0 for 2.0 < r < 2.5 m and −50 for r < 1.0 m.
    pub fn search_and_rescue() -> Self {
        RewardConfig { bands: vec![RewardBand { min_m: 2.0, max_m: 2.5, value: 2.0 }, RewardBand { min_m: f64::NEG_INFINITY, max_m: 1.0, value: -50.0 }], ..Self::exploration() }
    }
    /// A preset by name: `exploration` (eq. 1) or `search_and_rescue` (eq. 2).
    pub fn preset(name: &str) -> Result<Self> {
        match name {
            "exploration" | "eq1" => Ok(Self::exploration()),
            "search_and_rescue" | "sar" | "eq2" => Ok(Self::search_and_rescue()),
            _ => Err(SimError::InvalidConfig(format!("unknown reward preset `{name}` (exploration, search_and_rescue)"))),
        }
    }
    /// What `novelty_eqs` multiplies on a step that adds `eqs_gained` to the EQS: the gain,
    /// capped at `novelty_eqs_cap` when that is > 0, plus `novelty_eqs_past_cap` times what lies
    /// past the cap.
    #[inline]
    pub fn novelty_eqs_paid(&self, eqs_gained: u64) -> f64 {
        let (gained, cap) = (eqs_gained as f64, self.novelty_eqs_cap);
        if cap > 0.0 && gained > cap { cap + self.novelty_eqs_past_cap * (gained - cap) } else { gained }
    }
    /// Reward for minimum range `r_m` and commanded (v, ω).
    #[inline]
    pub fn reward(&self, r_m: f64, v_mps: f64, omega_radps: f64) -> f64 {
        let mut rew = self.range_weight * r_m * r_m + self.speed_weight * v_mps * v_mps - self.turn_penalty * omega_radps * omega_radps;
        for b in &self.bands {
            if b.min_m < r_m && r_m < b.max_m {
                rew += b.value;
            }
        }
        rew
    }
}

/// Episode rules (paper §IV-D).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct EpisodeConfig {
    /// Truncation limit [paper: 1000 in env1 and outdoor, 2000 in env2].
    pub max_steps: u32,
    /// Minimum distance from the footprint to any obstacle at the start [inferred: 0.5 m].
    pub start_clearance_m: f64,
    /// Keep a start only if some sequence of actions never collides from it — witnessed by up
    /// to 2 m straight, then a full-lock circle, left or right
    /// ([`crate::env::World::can_circle_from`]) [inferred: the paper starts at random poses and
    /// is silent on this; the car has no reverse and a 0.76 m minimum turn radius, so the
    /// clearance rule alone admits poses, facing a wall 0.81–0.85 m away or tucked into a
    /// corner, from which every action collides].
    pub start_escapable: bool,
    /// Rejection-sampling attempts before a map is declared to have no valid start.
    pub start_attempts: usize,
    /// Share of starts drawn hard: valid and escapable as every start, and facing a surface
    /// within `hard_start_within_m` ([`crate::env::World::faces_surface_within`]). Drawn per
    /// episode; at 0 no random number is spent on it, so every seed's starts stay as they were
    /// [ours: 0, the paper's uniform random starts. Training may raise it through
    /// `actors.hard_start_share` (evaluations keep this value); 30 % on env1 did not make the
    /// policies carry better to env3 over five seeds (docs/simulator.md, "Hard starts")].
    pub hard_start_share: f64,
    /// How near the surface a hard start faces: the nearest hit of the rays from the car's
    /// centre across its front, heading ± 45° every 15°, is at most this far [ours: 1.5 m,
    /// about twice the car's 0.76 m minimum turn radius — a start the car must turn away from
    /// at once, as from env3's corners].
    pub hard_start_within_m: f64,
    /// Share of episodes that run to `long_max_steps` in place of `max_steps`. Drawn per
    /// episode; at 0 no random number is spent on it, so every seed's episodes stay as they
    /// were [ours: 0, the paper's one limit. Training may raise it through
    /// `actors.long_share` (evaluations keep this value): a policy trained on 1,000-step
    /// episodes and evaluated on 3,000 meets states, such as a second lap over its own
    /// track, that no training episode reached (docs/experiments.md, "A share of long
    /// training episodes")].
    pub long_share: f64,
    /// The limit of those long episodes [ours: 3,000, the length issue 18 evaluates on].
    pub long_max_steps: u32,
}

impl Default for EpisodeConfig {
    fn default() -> Self {
        EpisodeConfig {
            max_steps: 1000,
            start_clearance_m: 0.5,
            start_escapable: true,
            start_attempts: 100_000,
            hard_start_share: 0.0,
            hard_start_within_m: 1.5,
            long_share: 0.0,
            long_max_steps: 3000,
        }
    }
}

/// How the cells k_n counted in ring n enter the EQS (paper §IV-B).
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq, Eq, Default)]
#[serde(rename_all = "snake_case")]
pub enum InnerSum {
    /// EQS = Σₙ n·k_n: each covered cell of ring n is worth n.
    #[default]
    Linear,
    /// EQS = Σₙ n·(1 + 2 + … + k_n), the printed Σ_{k=1}^{k_max} k taken literally.
    Triangular,
}

/// EQS / EES scoring grid (paper §IV-B). The reading — cell size, ring width, inner sum — is
/// the one `mapless analyze eqs` finds consistent with every row of the paper's Tables III–V
/// (docs/simulator.md, "EQS and EES — the reading the paper's tables support"); the others stay selectable.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct ExplorationConfig {
    /// Area of one scoring cell; cells are squares of side √area [paper: "2 m² segments", read
    /// as squares 2 m on a side (4 m²): with side √2 m the circling DDPG-env2 row (EQS 3 over
    /// ~150 m) is a 1 % event for this car's tightest circle, with 2 m it is ordinary].
    pub cell_area_m2: f64,
    /// Width of the rings around the start [paper: "radius 10n"; 10 m rings reject 10 of the
    /// 12 rows (SAC-env1's 91 over 34.6 m is above every simulated trajectory), 2–3 m rings fit
    /// all 12 and 2.5 m fits best].
    pub ring_width_m: f64,
    /// Inner sum [paper: Σ_{k=1}^{k_max} k; read as the count k_n (linear): taken literally
    /// (triangular) it leaves TD3-env1 on env3 below the 2nd percentile with 2 m cells and
    /// 9 or more rows in the tails with √2 m cells].
    pub inner_sum: InnerSum,
}

impl Default for ExplorationConfig {
    fn default() -> Self {
        ExplorationConfig { cell_area_m2: 4.0, ring_width_m: 2.5, inner_sum: InnerSum::Linear }
    }
}

/// What the observation carries besides the scans and the last action and reward.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq, Default)]
#[serde(default, deny_unknown_fields)]
pub struct ObservationConfig {
    /// S > 0 appends one value, min(k, S)/S ∈ [0, 1], k the steps since the car last entered an
    /// EQS cell (`exploration.cell_area_m2`) the episode had not visited; 0 leaves it out [ours,
    /// beyond the paper (issue 18): 0 in every preset. A memoryless policy cannot tell a
    /// lap over its own track from new ground, and `explore-sac`'s policies end most env3
    /// episodes lapping one room's island; the value is what wheel odometry knows, no map].
    pub staleness_steps: u32,
    /// L > 0 appends two values, tanh(d/L)·(cos β, sin β), where the episode's start lies d
    /// metres from the car at bearing β from its heading (0 ahead, positive to the left); 0
    /// leaves them out [ours, beyond the paper (issue 18): 10 in `explore-sac`, 0 in the other
    /// presets. The EQS pays a
    /// cell by its ring around the start (§IV-B), and `env.reward.novelty_eqs` pays the same,
    /// but without this a memoryless policy cannot tell how far from the start it is: a lap of
    /// the room it started in and a tour of the building look alike. It is what wheel odometry
    /// and a heading sensor know, no map; L sets the distance at which the value is tanh(1) ≈ 0.76].
    pub start_offset_m: f64,
}

/// Everything one environment needs besides its map.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq, Default)]
#[serde(default, deny_unknown_fields)]
pub struct EnvConfig {
    pub vehicle: VehicleConfig,
    pub sensor: SensorConfig,
    pub reward: RewardConfig,
    pub episode: EpisodeConfig,
    pub exploration: ExplorationConfig,
    pub observation: ObservationConfig,
}

impl EnvConfig {
    /// Length of the observation vector: [ranges_t, ranges_{t−1}, v_{t−1}, ω_{t−1}, R_{t−1}],
    /// then the staleness when `observation.staleness_steps` > 0, then the start's offset (two
    /// values) when `observation.start_offset_m` > 0.
    pub fn obs_dim(&self) -> usize {
        2 * self.sensor.beams + 3 + usize::from(self.observation.staleness_steps > 0) + 2 * usize::from(self.observation.start_offset_m > 0.0)
    }

    /// The observation the car would read in the mirror image of its world, at the mirror
    /// image of its pose, after the mirror image of its history: each beam's range moves to
    /// its [`SensorConfig::mirrored_beam`], ω_{t−1} changes sign, v_{t−1} and R_{t−1} stay (eq. (1)
    /// and (2) depend on ω only through ω², and the mirror image of a map is a map), and so does
    /// the staleness (exactly where the EQS grid is its own mirror image, as in
    /// sim/tests/mirror.rs; elsewhere a cell edge may fall a step earlier or later); the start's
    /// bearing changes sign (its sine, the last value). `obs` and `out` are `obs_dim` long.
    pub fn mirror_obs(&self, obs: &[f32], out: &mut [f32]) {
        let n = self.sensor.beams;
        debug_assert!(obs.len() == self.obs_dim() && out.len() == obs.len());
        for k in 0..n {
            let m = self.sensor.mirrored_beam(k);
            out[m] = obs[k];
            out[n + m] = obs[n + k];
        }
        out[2 * n..].copy_from_slice(&obs[2 * n..]);
        out[2 * n + 1] = -obs[2 * n + 1];
        if self.observation.start_offset_m > 0.0 {
            let last = obs.len() - 1;
            out[last] = -obs[last];
        }
    }

    /// The action (a_speed, a_turn) mirrored: the turn changes sign.
    pub fn mirror_action(action: [f32; 2]) -> [f32; 2] {
        [action[0], -action[1]]
    }

    /// Checks every field's domain.
    pub fn validate(&self) -> Result<()> {
        let v = &self.vehicle;
        let s = &self.sensor;
        let checks: [(bool, &str); 26] = [
            (v.wheelbase_m > 0.0, "vehicle.wheelbase_m must be > 0"),
            (v.lr_m > 0.0 && v.lr_m <= v.wheelbase_m, "vehicle.lr_m must be in (0, wheelbase_m]"),
            (v.length_m > 0.0 && v.width_m > 0.0, "vehicle footprint must be > 0"),
            (v.max_steer_rad > 0.0 && v.max_steer_rad < std::f64::consts::FRAC_PI_2, "vehicle.max_steer_rad must be in (0, π/2)"),
            (v.v_max_mps > 0.0 && v.omega_max_radps >= 0.0, "vehicle.v_max_mps must be > 0 and omega_max_radps ≥ 0"),
            (v.dt_s > 0.0 && v.max_substep_m > 0.0, "vehicle.dt_s and max_substep_m must be > 0"),
            (s.beams >= 1 && s.beams <= 8192, "sensor.beams must be in 1..=8192"),
            (s.rays_per_beam >= 1 && s.rays_per_beam <= 64 && s.beams.saturating_mul(s.rays_per_beam) <= 8192, "sensor.rays_per_beam must be in 1..=64, with beams × rays_per_beam ≤ 8192"),
            (s.fov_rad > 0.0 && s.fov_rad <= std::f64::consts::TAU + 1e-9, "sensor.fov_rad must be in (0, 2π]"),
            (s.max_range_m > 0.0, "sensor.max_range_m must be > 0"),
            (s.noise_std_m >= 0.0, "sensor.noise_std_m must be ≥ 0"),
            (self.episode.max_steps >= 1, "episode.max_steps must be ≥ 1"),
            (self.episode.start_clearance_m >= 0.0, "episode.start_clearance_m must be ≥ 0"),
            ((0.0..=1.0).contains(&self.episode.hard_start_share), "episode.hard_start_share must be in [0, 1]"),
            ((0.0..=1.0).contains(&self.episode.long_share), "episode.long_share must be in [0, 1]"),
            (self.episode.long_share == 0.0 || self.episode.long_max_steps > self.episode.max_steps, "episode.long_max_steps must be > max_steps where episode.long_share > 0"),
            (self.episode.hard_start_within_m > 0.0 && self.episode.hard_start_within_m.is_finite(), "episode.hard_start_within_m must be a finite number > 0 (metres)"),
            (self.exploration.cell_area_m2 > 0.0, "exploration.cell_area_m2 must be > 0"),
            (self.exploration.ring_width_m > 0.0, "exploration.ring_width_m must be > 0"),
            (self.reward.collision.is_finite() && self.reward.collision <= 0.0, "reward.collision must be a finite number ≤ 0"),
            (self.reward.novelty.is_finite() && self.reward.novelty >= 0.0, "reward.novelty must be a finite number ≥ 0"),
            (self.reward.novelty_eqs.is_finite() && self.reward.novelty_eqs >= 0.0, "reward.novelty_eqs must be a finite number ≥ 0"),
            (self.reward.novelty_eqs_cap.is_finite() && self.reward.novelty_eqs_cap >= 0.0, "reward.novelty_eqs_cap must be a finite number ≥ 0 (0: no cap)"),
            ((0.0..=1.0).contains(&self.reward.novelty_eqs_past_cap), "reward.novelty_eqs_past_cap must be in [0, 1]"),
            (self.reward.novelty_eqs_past_cap == 0.0 || self.reward.novelty_eqs_cap > 0.0, "reward.novelty_eqs_past_cap needs reward.novelty_eqs_cap > 0 (without a cap nothing lies past it)"),
            (self.observation.start_offset_m.is_finite() && self.observation.start_offset_m >= 0.0, "observation.start_offset_m must be a finite number ≥ 0 (metres; 0 leaves the start's offset out)"),
        ];
        let all_finite = [v.wheelbase_m, v.lr_m, v.length_m, v.width_m, v.max_steer_rad, v.v_max_mps, v.omega_max_radps, v.dt_s, s.fov_rad, s.max_range_m, s.noise_std_m].iter().all(|x| x.is_finite());
        if !all_finite {
            return Err(SimError::InvalidConfig("every vehicle and sensor value must be finite".into()));
        }
        match checks.iter().find(|(ok, _)| !ok) {
            Some((_, msg)) => Err(SimError::InvalidConfig((*msg).into())),
            None => Ok(()),
        }
    }
}
