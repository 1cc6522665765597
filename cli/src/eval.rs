//! Evaluation: the deterministic policy on any map, with the paper's exploration figures and
//! a trajectory picture per episode (like Figs. 10 and 12). Pure Rust inference (the actor's
//! `Policy`), no training traffic.

use std::path::Path;
use std::sync::Arc;

use anyhow::{Context, Result, bail};
use mapless_actor::{ActMode, Policy};
use mapless_plots::{Canvas, contact_sheet_png, default_px_per_m};
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
    /// Ran to the step limit without a collision but drove less than [`PARKED_SHARE`] of what
    /// its steps cover at full speed: safe because it stopped, not because it explored.
    #[serde(default)]
    pub parked: bool,
    /// The pose it ended in, x and y in the map's frame (m) and the heading (rad): after a
    /// collision, where the car hit something. Older eval.json files have none.
    #[serde(default)]
    pub end_pose: Option<[f64; 3]>,
}

/// An episode that ends without a collision is *parked* when it drove less than this share
/// of `steps × v_max × dt` [ours (issue 18): a third. Driving policies cover 0.57–0.97 of it
/// on every family of generated worlds (85–145 m in 3,000 steps of at most 150 m); those
/// that stop in clutter or open ground cover under 0.33 (5–50 m)].
pub const PARKED_SHARE: f64 = 1.0 / 3.0;

/// Is an episode that ended this way parked ([`PARKED_SHARE`])?
pub fn is_parked(collided: bool, steps: u32, distance_m: f64, env: &EnvConfig) -> bool {
    !collided && distance_m < PARKED_SHARE * f64::from(steps) * env.vehicle.v_max_mps * env.vehicle.dt_s
}

/// One world's rows of an evaluation.
#[derive(Clone, Debug, PartialEq)]
pub struct MapRow {
    pub map: String,
    pub episodes: usize,
    pub mean_steps: f64,
    pub collisions: u32,
    pub parked: u32,
    pub mean_eqs: f64,
    pub mean_ees: f64,
    pub mean_distance_m: f64,
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
    /// Episodes that ran to the limit without a collision by stopping ([`EvalEpisode::parked`]).
    #[serde(default)]
    pub parked: u32,
}

impl EvalSummary {
    /// Per world, in the order first met.
    pub fn per_map(&self) -> Vec<MapRow> {
        let mut rows: Vec<(String, Vec<&EvalEpisode>)> = Vec::new();
        for e in &self.episodes {
            match rows.iter_mut().find(|(m, _)| *m == e.map) {
                Some((_, v)) => v.push(e),
                None => rows.push((e.map.clone(), vec![e])),
            }
        }
        rows.into_iter()
            .map(|(m, v)| {
                let n = v.len() as f64;
                let mean = |f: &dyn Fn(&EvalEpisode) -> f64| v.iter().map(|e| f(e)).sum::<f64>() / n;
                let count = |f: &dyn Fn(&EvalEpisode) -> bool| v.iter().filter(|e| f(e)).count() as u32;
                MapRow {
                    episodes: v.len(),
                    mean_steps: mean(&|e| f64::from(e.steps)),
                    collisions: count(&|e| e.collided),
                    parked: count(&|e| e.parked),
                    mean_eqs: mean(&|e| e.eqs as f64),
                    mean_ees: mean(&|e| e.ees),
                    mean_distance_m: mean(&|e| e.distance_m),
                    map: m,
                }
            })
            .collect()
    }

    /// The means on one line.
    pub fn one_line(&self) -> String {
        format!(
            "{}: {} episodes, mean steps {:.0}, return {:.1}, EQS {:.1}, EES {:.2}, distance {:.1} m, shaded {:.1} s, collisions {}, parked {}",
            self.map,
            self.episodes.len(),
            self.mean_steps,
            self.mean_return,
            self.mean_eqs,
            self.mean_ees,
            self.mean_distance_m,
            self.mean_shaded_time_s,
            self.collisions,
            self.parked
        )
    }
}

/// Episodes on the contact sheet (`sheet.png`) at most.
const SHEET_EPISODES: usize = 24;

/// The worlds of an evaluation: one map, or a list of maps and families whose episodes take
/// the items in turn, a family's in the worlds of one split (held-out or validation), one after
/// the other.
struct EvalWorlds {
    slots: Vec<Slot>,
    split: Split,
    env: EnvConfig,
}

enum Slot {
    Fixed(Arc<World>),
    Family(Family),
}

impl EvalWorlds {
    fn new(map: &str, split: Split, env: &EnvConfig) -> Result<EvalWorlds> {
        if split == Split::Train {
            bail!("an evaluation runs on held-out or validation worlds, never on training ones");
        }
        let slots = parse_map_list(map)?
            .into_iter()
            .map(|i| match i {
                MapItem::Map(name) => resolve(&name).and_then(|m| World::new(m, env.clone())).map(Slot::Fixed),
                MapItem::Family(f) => Ok(Slot::Family(f)),
            })
            .collect::<Result<_, _>>()?;
        Ok(EvalWorlds { slots, split, env: env.clone() })
    }

    /// The world of episode `k` (from 0): item k mod n; a family's (k / n)-th world of the split.
    fn world(&self, k: usize) -> Result<Arc<World>> {
        match &self.slots[k % self.slots.len()] {
            Slot::Fixed(w) => Ok(Arc::clone(w)),
            Slot::Family(f) => Ok(World::new(generate(*f, self.split.seed((k / self.slots.len()) as u64)?)?, self.env.clone())?),
        }
    }

    /// What the summary calls the evaluation: the map's own name for one map, else `map`.
    fn label(&self, map: &str) -> String {
        if let [Slot::Fixed(w)] = self.slots.as_slice() { w.map.name.clone() } else { map.to_owned() }
    }
}

/// The deterministic policy in a published weights snapshot (`.safetensors`).
pub fn load_policy(policy_file: &Path) -> Result<Policy> {
    let snapshot = read_safetensors_file(policy_file).with_context(|| format!("reading the policy {}", policy_file.display()))?;
    Policy::from_snapshot(&snapshot).with_context(|| format!("loading the policy {}", policy_file.display()))
}

/// Runs `episodes` deterministic episodes of the policy in `policy_file` (a published weights
/// snapshot, `.safetensors`) on `map` with `env`; draws `episode-K.png` into `out_dir`. `map`
/// may be a list (`env3+gen:cave`): the episodes take its items in turn, a family's in the
/// worlds of `worlds`: [`Split::HeldOut`] for what is reported (seeds from
/// `worlds::HELD_OUT_FIRST_SEED`), [`Split::Validation`] for what a run judges itself by while
/// it trains (seeds from `worlds::VALIDATION_FIRST_SEED`).
pub fn evaluate(policy_file: &Path, map: &str, worlds: Split, env: &EnvConfig, episodes: u32, seed: u64, out_dir: Option<&Path>) -> Result<EvalSummary> {
    if episodes == 0 {
        bail!("--episodes must be >= 1");
    }
    let mut policy = load_policy(policy_file)?;
    // One map, or a list of maps and families: episode k runs in item k mod n, a family's
    // episodes each in the next of its worlds of the split (never a training world).
    let worlds = EvalWorlds::new(map, worlds, env)?;
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
    let mut sheet = Vec::new();
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
            if sheet.len() < SHEET_EPISODES {
                sheet.push(c);
            }
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
            parked: is_parked(s.terminal, s.steps, s.distance_m, &world.cfg),
            end_pose: Some({
                let p = e.pose();
                [p.x_m, p.y_m, p.heading_rad]
            }),
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
        parked: out.iter().filter(|e| e.parked).count() as u32,
        episodes: out,
    };
    if let Some(d) = out_dir {
        std::fs::write(d.join("eval.json"), serde_json::to_string_pretty(&summary)?)?;
        // A long list (`--family F --seeds A..B`) is cut short in the title; eval.json keeps it.
        let name: String = if summary.map.chars().count() > 90 { summary.map.chars().take(89).chain(['…']).collect() } else { summary.map.clone() };
        let title = format!(
            "{} — policy v{}, {} episodes{}",
            name,
            summary.policy_version,
            episodes,
            if episodes as usize > SHEET_EPISODES { format!(" (the first {SHEET_EPISODES})") } else { String::new() }
        );
        contact_sheet_png(&sheet, 4, 0.4, &title, &d.join("sheet.png"))?;
    }
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_list_is_evaluated_item_by_item_and_families_only_on_held_out_or_validation_worlds() {
        let env = EnvConfig::default();
        let w = EvalWorlds::new("env1+gen:forest+gen:rooms", Split::HeldOut, &env).unwrap();
        let names: Vec<String> = (0..7).map(|k| w.world(k).unwrap().map.name.clone()).collect();
        assert_eq!(names, ["env1", "forest-1000000", "rooms-1000000", "env1", "forest-1000001", "rooms-1000001", "env1"]);
        assert_eq!(w.label("env1+gen:forest+gen:rooms"), "env1+gen:forest+gen:rooms");
        let v = EvalWorlds::new("env1+gen:forest", Split::Validation, &env).unwrap();
        let names: Vec<String> = (0..4).map(|k| v.world(k).unwrap().map.name.clone()).collect();
        assert_eq!(names, ["env1", "forest-2000000", "env1", "forest-2000001"]);
        let one = EvalWorlds::new("env3", Split::HeldOut, &env).unwrap();
        assert_eq!((one.world(5).unwrap().map.name.as_str(), one.label("env3").as_str()), ("env3", "env3"));
        assert!(EvalWorlds::new("env1+gen:lava", Split::HeldOut, &env).is_err());
        let e = EvalWorlds::new("gen:forest", Split::Train, &env).err().unwrap().to_string();
        assert!(e.contains("never on training ones"), "{e}");
    }

    #[test]
    fn the_per_map_table_groups_episodes_by_world_in_the_order_met() {
        let ep = |k: u32, map: &str, steps: u32, collided: bool| EvalEpisode {
            episode: k,
            map: map.into(),
            steps,
            episode_return: 0.0,
            collided,
            eqs: 10 * u64::from(k),
            ees: 1.0,
            distance_m: 5.0,
            shaded_time_s: 0.0,
            parked: !collided && k == 3,
            end_pose: None,
        };
        let s = EvalSummary {
            map: "a+b".into(),
            policy_version: 1,
            episodes: vec![ep(1, "b", 100, true), ep(2, "a", 300, false), ep(3, "b", 300, false)],
            mean_steps: 0.0,
            mean_return: 0.0,
            mean_eqs: 0.0,
            mean_ees: 0.0,
            mean_distance_m: 0.0,
            mean_shaded_time_s: 0.0,
            collisions: 1,
            parked: 1,
        };
        let rows = s.per_map();
        assert_eq!(rows.iter().map(|r| (r.map.as_str(), r.episodes, r.mean_steps, r.collisions, r.parked, r.mean_eqs)).collect::<Vec<_>>(), [("b", 2, 200.0, 1, 1, 20.0), ("a", 1, 300.0, 0, 0, 20.0)]);
    }

    #[test]
    fn an_episode_is_parked_when_it_survives_by_stopping() {
        // The default car: 0.5 m/s × 0.1 s, so 3,000 steps reach at most 150 m; a third is 50 m.
        let env = EnvConfig::default();
        assert!(is_parked(false, 3000, 49.9, &env));
        assert!(!is_parked(false, 3000, 50.1, &env));
        assert!(!is_parked(true, 3000, 5.0, &env), "a collision is a collision, not parking");
        // Scaled by the steps it ran: 300 steps at 10 m is not parked.
        assert!(!is_parked(false, 300, 10.0, &env));
        // Older eval.json files (without the field) still read.
        let old = r#"{"episode":1,"map":"env3","steps":3000,"return":1.0,"collided":false,"eqs":3,"ees":0.1,"distance_m":4.0,"shaded_time_s":0.0}"#;
        let old = serde_json::from_str::<EvalEpisode>(old).unwrap();
        assert!(!old.parked && old.end_pose.is_none());
    }
}
