//! Evaluation: the deterministic policy on any map, with the paper's exploration figures and
//! a trajectory picture per episode (like Figs. 10 and 12). Pure Rust inference (the actor's
//! `Policy`), no training traffic.

use std::path::Path;
use std::sync::Arc;

use anyhow::{Context, Result, bail};
use mapless_actor::{ActMode, Policy};
use mapless_plots::{Canvas, default_px_per_m};
use mapless_proto::weights_file::read_safetensors_file;
use mapless_sim::worlds::{Family, MapItem, Split, generate, parse_map_list, resolve};
use mapless_sim::{Env, EnvConfig, World};
use rand::SeedableRng;
use serde::{Deserialize, Serialize};

/// One evaluation episode.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct EvalEpisode {
    pub episode: u32,
    /// The world it ran in.
    #[serde(default)]
    pub map: String,
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

/// The worlds of an evaluation: one map, or a list of maps and families whose episodes take
/// the items in turn, a family's in its held-out worlds, one after the other.
struct EvalWorlds {
    slots: Vec<Slot>,
    env: EnvConfig,
}

enum Slot {
    Fixed(Arc<World>),
    Family(Family),
}

impl EvalWorlds {
    fn new(map: &str, env: &EnvConfig) -> Result<EvalWorlds> {
        let slots = parse_map_list(map)?
            .into_iter()
            .map(|i| match i {
                MapItem::Map(name) => resolve(&name).and_then(|m| World::new(m, env.clone())).map(Slot::Fixed),
                MapItem::Family(f) => Ok(Slot::Family(f)),
            })
            .collect::<Result<_, _>>()?;
        Ok(EvalWorlds { slots, env: env.clone() })
    }

    /// The world of episode `k` (from 0): item k mod n; a family's (k / n)-th held-out world.
    fn world(&self, k: usize) -> Result<Arc<World>> {
        match &self.slots[k % self.slots.len()] {
            Slot::Fixed(w) => Ok(Arc::clone(w)),
            Slot::Family(f) => Ok(World::new(generate(*f, Split::HeldOut.seed((k / self.slots.len()) as u64)?)?, self.env.clone())?),
        }
    }

    /// What the summary calls the evaluation: the map's own name for one map, else `map`.
    fn label(&self, map: &str) -> String {
        if let [Slot::Fixed(w)] = self.slots.as_slice() { w.map.name.clone() } else { map.to_owned() }
    }
}

/// Runs `episodes` deterministic episodes of the policy in `policy_file` (a published weights
/// snapshot, `.safetensors`) on `map` with `env`; draws `episode-K.png` into `out_dir`. `map`
/// may be a list (`env3+gen:cave`): the episodes take its items in turn, a family's in its
/// held-out worlds (seeds from `worlds::HELD_OUT_FIRST_SEED`).
pub fn evaluate(policy_file: &Path, map: &str, env: &EnvConfig, episodes: u32, seed: u64, out_dir: Option<&Path>) -> Result<EvalSummary> {
    if episodes == 0 {
        bail!("--episodes must be >= 1");
    }
    let snapshot = read_safetensors_file(policy_file).with_context(|| format!("reading the policy {}", policy_file.display()))?;
    let mut policy = Policy::from_snapshot(&snapshot).with_context(|| format!("loading the policy {}", policy_file.display()))?;
    // One map, or a list of maps and families: episode k runs in item k mod n, a family's
    // episodes each in the next of its held-out worlds (never a training world).
    let worlds = EvalWorlds::new(map, env)?;
    let world_for = |k: usize| worlds.world(k);
    let first = world_for(0)?;
    if policy.obs_dim() != first.obs_dim() {
        bail!("the policy reads {} observation values, this map's sensor gives {} (the run's sensor config must match)", policy.obs_dim(), first.obs_dim());
    }
    let label = worlds.label(map);
    if let Some(d) = out_dir {
        std::fs::create_dir_all(d).with_context(|| format!("creating {}", d.display()))?;
    }
    let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
    let mut obs = vec![0.0f32; first.obs_dim()];
    let mut next = obs.clone();
    let mut action = [0.0f32; 2];
    let mut out = Vec::new();
    for k in 1..=episodes {
        let world = if k == 1 { Arc::clone(&first) } else { world_for(k as usize - 1)? };
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
        out.push(EvalEpisode {
            episode: k,
            map: world.map.name.clone(),
            steps: s.steps,
            episode_return: s.return_,
            collided: s.terminal,
            eqs: s.eqs,
            ees: s.ees,
            distance_m: s.distance_m,
            shaded_time_s: s.shaded_time_s,
        });
    }
    let n = out.len() as f64;
    let mean = |f: &dyn Fn(&EvalEpisode) -> f64| out.iter().map(f).sum::<f64>() / n;
    let summary = EvalSummary {
        map: label,
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_list_is_evaluated_item_by_item_and_families_only_on_held_out_worlds() {
        let env = EnvConfig::default();
        let w = EvalWorlds::new("env1+gen:forest+gen:rooms", &env).unwrap();
        let names: Vec<String> = (0..7).map(|k| w.world(k).unwrap().map.name.clone()).collect();
        assert_eq!(names, ["env1", "forest-1000000", "rooms-1000000", "env1", "forest-1000001", "rooms-1000001", "env1"]);
        assert_eq!(w.label("env1+gen:forest+gen:rooms"), "env1+gen:forest+gen:rooms");
        let one = EvalWorlds::new("env3", &env).unwrap();
        assert_eq!((one.world(5).unwrap().map.name.as_str(), one.label("env3").as_str()), ("env3", "env3"));
        assert!(EvalWorlds::new("env1+gen:lava", &env).is_err());
    }
}
