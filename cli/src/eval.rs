//! Evaluation: the deterministic policy on any map, with the paper's exploration figures and
//! a trajectory picture per episode (like Figs. 10 and 12). Pure Rust inference (the actor's
//! `Policy`), no training traffic.

use std::path::Path;
use std::sync::Arc;

use anyhow::{Context, Result, bail};
use mapless_actor::{ActMode, Policy};
use mapless_plots::{Canvas, default_px_per_m};
use mapless_proto::weights_file::read_safetensors_file;
use mapless_sim::{Env, EnvConfig, Map, World};
use rand::SeedableRng;
use serde::{Deserialize, Serialize};

/// One evaluation episode.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct EvalEpisode {
    pub episode: u32,
    pub steps: u32,
    #[serde(rename = "return")]
    pub episode_return: f64,
    pub collided: bool,
    pub eqs: u64,
    pub ees: f64,
    pub distance_m: f64,
    pub shaded_time_s: f64,
}

/// Episodes and their means.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct EvalSummary {
    pub map: String,
    pub policy_version: u64,
    pub episodes: Vec<EvalEpisode>,
    pub mean_steps: f64,
    pub mean_return: f64,
    pub mean_eqs: f64,
    pub mean_ees: f64,
    pub mean_distance_m: f64,
    pub mean_shaded_time_s: f64,
    pub collisions: u32,
}

impl EvalSummary {
    /// The means on one line.
    pub fn one_line(&self) -> String {
        format!(
            "{}: {} episodes, mean steps {:.0}, return {:.1}, EQS {:.1}, EES {:.2}, distance {:.1} m, shaded {:.1} s, collisions {}",
            self.map,
            self.episodes.len(),
            self.mean_steps,
            self.mean_return,
            self.mean_eqs,
            self.mean_ees,
            self.mean_distance_m,
            self.mean_shaded_time_s,
            self.collisions
        )
    }
}

/// Runs `episodes` deterministic episodes of the policy in `policy_file` (a published weights
/// snapshot, `.safetensors`) on `map` with `env`; draws `episode-K.png` into `out_dir`.
pub fn evaluate(policy_file: &Path, map: &str, env: &EnvConfig, episodes: u32, seed: u64, out_dir: Option<&Path>) -> Result<EvalSummary> {
    if episodes == 0 {
        bail!("--episodes must be >= 1");
    }
    let snapshot = read_safetensors_file(policy_file).with_context(|| format!("reading the policy {}", policy_file.display()))?;
    let mut policy = Policy::from_snapshot(&snapshot).with_context(|| format!("loading the policy {}", policy_file.display()))?;
    let world = World::new(Map::resolve(map)?, env.clone())?;
    if policy.obs_dim() != world.obs_dim() {
        bail!("the policy reads {} observation values, this map's sensor gives {} (the run's sensor config must match)", policy.obs_dim(), world.obs_dim());
    }
    if let Some(d) = out_dir {
        std::fs::create_dir_all(d).with_context(|| format!("creating {}", d.display()))?;
    }
    let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
    let mut obs = vec![0.0f32; world.obs_dim()];
    let mut next = obs.clone();
    let mut action = [0.0f32; 2];
    let mut out = Vec::new();
    for k in 1..=episodes {
        let mut e = Env::new(Arc::clone(&world), seed.wrapping_add(u64::from(k)).wrapping_mul(0x9E37_79B9_7F4A_7C15));
        e.record_trajectory(true);
        e.reset(&mut obs)?;
        let last = loop {
            policy.act(&obs, ActMode::Deterministic, &mut rng, &mut action)?;
            let o = e.step(action, &mut next)?;
            std::mem::swap(&mut obs, &mut next);
            if o.done() {
                break o;
            }
        };
        let s = e.summary(Some(last));
        if let Some(d) = out_dir {
            let mut c = Canvas::map(&world.map, default_px_per_m(&world.map), &format!("{} — evaluation {k}, policy v{}", world.map.name, policy.version()))?;
            c.episode(&world.map, e.trajectory().unwrap_or(&[]), e.tracker(), world.cfg.exploration.ring_width_m, s.terminal)?;
            c.footer(&crate::episode_footer(&s, !world.map.shaded.is_empty()))?;
            c.save_png(&d.join(format!("episode-{k}.png")))?;
        }
        out.push(EvalEpisode { episode: k, steps: s.steps, episode_return: s.return_, collided: s.terminal, eqs: s.eqs, ees: s.ees, distance_m: s.distance_m, shaded_time_s: s.shaded_time_s });
    }
    let n = out.len() as f64;
    let mean = |f: &dyn Fn(&EvalEpisode) -> f64| out.iter().map(f).sum::<f64>() / n;
    let summary = EvalSummary {
        map: world.map.name.clone(),
        policy_version: policy.version(),
        mean_steps: mean(&|e| f64::from(e.steps)),
        mean_return: mean(&|e| e.episode_return),
        mean_eqs: mean(&|e| e.eqs as f64),
        mean_ees: mean(&|e| e.ees),
        mean_distance_m: mean(&|e| e.distance_m),
        mean_shaded_time_s: mean(&|e| e.shaded_time_s),
        collisions: out.iter().filter(|e| e.collided).count() as u32,
        episodes: out,
    };
    if let Some(d) = out_dir {
        std::fs::write(d.join("eval.json"), serde_json::to_string_pretty(&summary)?)?;
    }
    Ok(summary)
}
