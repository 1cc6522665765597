//! A run's configuration: the presets, the sections a run holds with their defaults and
//! sources, `--set` paths, and resolution into one checked [`TrainConfig`].

use std::fs;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{Context, Result, bail};
use mapless_learner_config::{AlgorithmKind, DriverConfig, ExplorationNoise, LearnerConfig};
use mapless_replay::TableConfig;
use mapless_sim::{EnvConfig, RewardConfig};
use serde::{Deserialize, Serialize};

use super::episodes::{EpisodeRow, trailing_mean};
use crate::protocol;

/// Built-in presets: name → YAML (the files under `presets/`).
pub const PRESETS: &[(&str, &str)] = &[
    ("env1-sac", include_str!("../../../presets/env1-sac.yaml")),
    ("env1-td3", include_str!("../../../presets/env1-td3.yaml")),
    ("env1-ddpg", include_str!("../../../presets/env1-ddpg.yaml")),
    ("env2-sac", include_str!("../../../presets/env2-sac.yaml")),
    ("env2-td3", include_str!("../../../presets/env2-td3.yaml")),
    ("env2-ddpg", include_str!("../../../presets/env2-ddpg.yaml")),
    ("outdoor20-sac", include_str!("../../../presets/outdoor20-sac.yaml")),
];

/// When a run stops by itself (whichever comes first). Moving averages are over the last
/// `window` training episodes and are only compared once `window` episodes exist.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct StopCriteria {
    /// Stop after this many training episodes.
    pub episodes: Option<u64>,
    /// Order of the moving averages.
    pub window: usize,
    /// Stop when the moving average of episode return reaches this ...
    pub average_return: Option<f64>,
    /// ... and (when both are set) the moving average of episode steps reaches this.
    pub average_steps: Option<f64>,
    /// Stop after this many minutes of wall time (of the whole run: a resumed run counts its
    /// earlier sessions).
    pub minutes: Option<f64>,
    /// With the moving averages (it only backs them: without `average_return` or
    /// `average_steps` it is not used): whenever they hold, the newest policy is evaluated
    /// (deterministic, `eval.map`, `eval_episodes` episodes, the evaluation seed), and the run
    /// stops only when that evaluation's mean EQS reaches this ... [paper Table III: the
    /// algorithm's post-training EQS]
    pub eval_eqs: Option<f64>,
    /// ... and its mean EES this ... [paper Table III]
    pub eval_ees: Option<f64>,
    /// ... with at most this many collisions [paper §V-A1: "each algorithm achieved 1000
    /// episode steps without collision"].
    pub eval_max_collisions: u32,
    /// Episodes of that evaluation [ours: 10, as the final evaluation].
    pub eval_episodes: u32,
    /// The convergence episode reported by every run (not a stop): the first episode from which
    /// the order-`window` averages of return and steps stay within this fraction of their
    /// final values [ours; the paper states no rule, see `protocol::convergence_episode`].
    pub convergence_tolerance: f64,
}

impl Default for StopCriteria {
    fn default() -> Self {
        StopCriteria {
            episodes: None,
            window: 50,
            average_return: None,
            average_steps: None,
            minutes: None,
            eval_eqs: None,
            eval_ees: None,
            eval_max_collisions: 0,
            eval_episodes: 10,
            convergence_tolerance: 0.1,
        }
    }
}

impl StopCriteria {
    /// The evaluation that must back the moving averages, if any.
    pub fn eval_goal(&self) -> Option<protocol::EvalGoal> {
        (self.eval_eqs.is_some() || self.eval_ees.is_some()).then_some(protocol::EvalGoal { eqs: self.eval_eqs, ees: self.eval_ees, max_collisions: self.eval_max_collisions })
    }
}

/// Have the stop criteria on moving averages been met?
pub fn averages_met(rows: &[EpisodeRow], stop: &StopCriteria) -> bool {
    if stop.average_return.is_none() && stop.average_steps.is_none() {
        return false;
    }
    if rows.len() < stop.window {
        return false;
    }
    let r = trailing_mean(rows.iter().map(|e| e.episode_return), stop.window);
    let s = trailing_mean(rows.iter().map(|e| f64::from(e.steps)), stop.window);
    stop.average_return.is_none_or(|g| r >= g) && stop.average_steps.is_none_or(|g| s >= g)
}

/// Shortest time between two evaluations of the stop criterion (they run while training goes
/// on; 10 episodes of 1000 steps take about a second).
pub(crate) const GATE_EVAL_COOLDOWN: Duration = Duration::from_secs(20);

/// Actor processes.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct ActorsSettings {
    /// Actor processes.
    pub count: usize,
    /// Vehicles per process.
    pub vehicles: usize,
    /// Transitions per batch sent to the replay.
    pub batch_rows: usize,
    /// Uniform random vehicle-steps at the start of each actor process.
    pub warmup_steps: u64,
    // Exploration noise has one home, the algorithm's section (`learner.ddpg.exploration`,
    // `learner.td3.exploration`, with their sources); the actors are handed it. SAC samples.
}

impl Default for ActorsSettings {
    fn default() -> Self {
        ActorsSettings { count: 2, vehicles: 4, batch_rows: 64, warmup_steps: 2_500 }
    }
}

/// Evaluation: of the newest policy as the run goes, and of the final policy.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct EvalSettings {
    /// Episodes of the final policy (deterministic); 0 skips it.
    pub episodes: u32,
    /// Map (default: the training map).
    pub map: Option<String>,
    /// Evaluate the newest policy this often while training (pictures in `eval/`, a line in
    /// `evals.csv`); none: only at the end.
    pub every_minutes: Option<f64>,
    /// Episodes of each evaluation while training.
    pub progress_episodes: u32,
}

impl Default for EvalSettings {
    fn default() -> Self {
        EvalSettings { episodes: 10, map: None, every_minutes: Some(5.0), progress_episodes: 2 }
    }
}

/// Threads: libtorch's for the learner (actors are single-threaded each).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct ThreadSettings {
    pub learner: usize,
}

impl Default for ThreadSettings {
    fn default() -> Self {
        ThreadSettings { learner: 1 }
    }
}

/// A training run, as a preset file writes it and as `run/config.yaml` keeps it (resolved).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct TrainConfig {
    pub name: String,
    #[serde(default)]
    pub description: String,
    /// Built-in map name or path to a map YAML.
    pub map: String,
    /// Simulator settings (vehicle, sensor, reward, episode, EQS grid). The reward lives here
    /// only (`env.reward`); a document may name a reward preset with the shorthand `reward:`
    /// (`exploration`: eq. 1, `search_and_rescue`: eq. 2) and the step limit with
    /// `max_steps:`, which [`expand_shorthands`] writes into `env` before any `--set`.
    #[serde(default)]
    pub env: EnvConfig,
    /// Algorithm and hyperparameters (paper Table I defaults).
    #[serde(default)]
    pub learner: LearnerConfig,
    /// Publishing / checkpoint / metrics cadence of the learner.
    #[serde(default)]
    pub driver: DriverConfig,
    /// The replay table (capacity, sampler, rate limiter); dims are set from `env`.
    #[serde(default = "default_table")]
    pub replay: TableConfig,
    /// Persist the replay (write-ahead log + snapshots in `run/replay/`), so a restarted
    /// replay or a resumed run keeps its transitions.
    #[serde(default = "yes")]
    pub replay_persistence: bool,
    #[serde(default)]
    pub actors: ActorsSettings,
    #[serde(default)]
    pub stop: StopCriteria,
    #[serde(default)]
    pub eval: EvalSettings,
    #[serde(default)]
    pub threads: ThreadSettings,
    #[serde(default)]
    pub seed: u64,
}

pub(crate) fn yes() -> bool {
    true
}

pub(crate) fn default_table() -> TableConfig {
    let mut t = TableConfig::default();
    // Set from the sensor by `resolve` (0: not stated).
    (t.obs_dim, t.act_dim) = (0, 0);
    // One 128-row minibatch per 4 environment steps at most: the learner keeps pace with the
    // actors instead of the actors racing ahead on a stale policy.
    t.rate_limiter.samples_per_insert = Some(32.0);
    t.rate_limiter.min_size_to_sample = 2_500;
    t.rate_limiter.error_buffer = 20_000.0;
    // The limiter's slack must cover the largest insert batch × the ratio (see
    // RateLimiterConfig); actors send `actors.batch_rows` (+ up to `actors.vehicles`) rows at a
    // time. 128 rows × the paper's ratio of 128 (one update per step) = 16,384 ≤ 20,000, so
    // either ratio runs with this slack.
    t.max_batch_rows = 128;
    t.max_sample_rows = 4096;
    t
}

impl TrainConfig {
    /// Sets the table's dims from the sensor, checks everything.
    pub fn resolve(mut self) -> Result<TrainConfig> {
        self.env.validate()?;
        // The table's row shape follows the sensor; a document may state it (a run's
        // config.yaml does) but not contradict it.
        for (name, set, derived) in [("replay.obs_dim", &mut self.replay.obs_dim, self.env.obs_dim()), ("replay.act_dim", &mut self.replay.act_dim, 2)] {
            if *set != 0 && *set != derived {
                bail!("{name} is {set}, but the sensor and the action give {derived}: it follows env.sensor, leave it out");
            }
            *set = derived;
        }
        // The run's seed seeds the learner too (and the actors, the replay's sampler).
        if self.learner.seed != 0 && self.learner.seed != self.seed {
            bail!("learner.seed is {}, the run's seed {}: the learner takes the run's `seed`, set that", self.learner.seed, self.seed);
        }
        self.learner.seed = self.seed;
        // An actor sends up to `batch_rows` + one row per vehicle at a time: the table takes
        // at least that (more vehicles than the default covers raise it, and the rate
        // limiter's check below then says if `error_buffer` must grow with it).
        self.replay.max_batch_rows = self.replay.max_batch_rows.max(self.actors.batch_rows + self.actors.vehicles);
        self.replay.validate()?;
        self.learner.validate()?;
        if self.actors.count == 0 || self.actors.vehicles == 0 || self.actors.batch_rows == 0 {
            bail!("actors.count, actors.vehicles and actors.batch_rows must be >= 1");
        }
        if self.stop.window == 0 {
            bail!("stop.window must be >= 1");
        }
        if self.stop.eval_episodes == 0 || !(self.stop.convergence_tolerance > 0.0) {
            bail!("stop.eval_episodes must be >= 1 and stop.convergence_tolerance > 0");
        }
        mapless_sim::Map::resolve(&self.map).with_context(|| format!("map `{}`", self.map))?;
        Ok(self)
    }

    /// The actors' exploration noise: the algorithm's own (`learner.{ddpg,td3}.exploration`);
    /// none for SAC, which samples its policy.
    pub(crate) fn noise(&self) -> Option<ExplorationNoise> {
        match self.learner.algorithm {
            AlgorithmKind::Ddpg => Some(self.learner.ddpg.exploration),
            AlgorithmKind::Td3 => Some(self.learner.td3.exploration),
            AlgorithmKind::Sac => None,
        }
    }
}

/// Sets `path` (dotted, e.g. `learner.actor_lr`) in a YAML document to `value` (parsed as YAML).
pub fn set_path(doc: &mut serde_yaml::Value, path: &str, value: &str) -> Result<()> {
    let v: serde_yaml::Value = serde_yaml::from_str(value).with_context(|| format!("--set {path}={value}: not a YAML value"))?;
    let mut cur = doc;
    let parts: Vec<&str> = path.split('.').collect();
    for (i, p) in parts.iter().enumerate() {
        if p.is_empty() {
            bail!("--set {path}: empty key");
        }
        if !cur.is_mapping() {
            if cur.is_null() {
                *cur = serde_yaml::Value::Mapping(Default::default());
            } else {
                bail!("--set {path}: `{}` is not a section", parts[..i].join("."));
            }
        }
        let map = cur.as_mapping_mut().expect("mapping");
        let key = serde_yaml::Value::String((*p).to_owned());
        if i + 1 == parts.len() {
            map.insert(key, v);
            return Ok(());
        }
        cur = map.entry(key).or_insert(serde_yaml::Value::Null);
    }
    Ok(())
}

/// A config document (a preset, `--set` applied, or a run's `config.yaml`) as a `TrainConfig`,
/// unresolved. This command's defaults for the replay table and the learner's cadence lie
/// under what the document says, field by field: a preset that sets
/// `replay.rate_limiter.samples_per_insert` keeps every other field of `default_table()`, and
/// `--set replay.capacity=…` changes one field instead of replacing the section.
pub fn parse_config(mut doc: serde_yaml::Value) -> Result<TrainConfig> {
    expand_shorthands(&mut doc, false)?;
    let mut defaults = serde_yaml::Mapping::new();
    defaults.insert("env".into(), serde_yaml::to_value(EnvConfig::default())?);
    defaults.insert("learner".into(), serde_yaml::to_value(LearnerConfig::default())?);
    defaults.insert("driver".into(), serde_yaml::to_value(DriverConfig::default())?);
    defaults.insert("replay".into(), serde_yaml::to_value(default_table())?);
    defaults.insert("actors".into(), serde_yaml::to_value(ActorsSettings::default())?);
    defaults.insert("stop".into(), serde_yaml::to_value(StopCriteria::default())?);
    defaults.insert("eval".into(), serde_yaml::to_value(EvalSettings::default())?);
    defaults.insert("threads".into(), serde_yaml::to_value(ThreadSettings::default())?);
    // Errors name the field: `learner.ddpg.exploration.kind: unknown variant …`.
    serde_path_to_error::deserialize(overlay(serde_yaml::Value::Mapping(defaults), doc)).map_err(|e| {
        let path = e.path().to_string();
        anyhow::anyhow!("config: {}{}", if path == "." { String::new() } else { format!("{path}: ") }, e.into_inner())
    })
}

/// A run folder's `config.yaml` (what `mapless eval` and `mapless reproduce` read back),
/// unresolved: the values `resolve` derives are left out (see [`run_document`]).
pub fn read_run_config(run: &Path) -> Result<TrainConfig> {
    read_run_document(run).and_then(parse_config).with_context(|| format!("reading {}", run.join("config.yaml").display()))
}

/// A run folder's `config.yaml` as a document ([`run_document`]): what `--resume` starts from.
pub(crate) fn read_run_document(run: &Path) -> Result<serde_yaml::Value> {
    let path = run.join("config.yaml");
    let text = fs::read_to_string(&path).with_context(|| format!("{} is not a run folder (no config.yaml)", run.display()))?;
    run_document(&text).with_context(|| format!("reading {}", path.display()))
}

/// A run's `config.yaml` as a document to resume from: the values `resolve` derives (the
/// learner's seed, the table's row shape) are left out so that a `--set` of what they follow
/// (`seed`, `env.sensor.…`) carries to them, and fields that older versions wrote are read
/// the way they meant (`learner.replay_capacity`, read by nothing, dropped; `actors.noise`, now
/// the algorithm's `learner.{ddpg,td3}.exploration`, dropped when empty).
pub(crate) fn run_document(text: &str) -> Result<serde_yaml::Value> {
    let mut doc: serde_yaml::Value = serde_yaml::from_str(text).context("not YAML")?;
    for (section, field) in [("learner", "seed"), ("replay", "obs_dim"), ("replay", "act_dim"), ("learner", "replay_capacity")] {
        if let Some(m) = doc.get_mut(section).and_then(|v| v.as_mapping_mut()) {
            m.remove(field);
        }
    }
    if let Some(m) = doc.get_mut("actors").and_then(|v| v.as_mapping_mut())
        && let Some(noise) = m.remove("noise")
        && !noise.is_null()
    {
        bail!("actors.noise is set ({noise:?}): exploration noise now lives in learner.ddpg.exploration / learner.td3.exploration; move it there");
    }
    Ok(doc)
}

/// The document's shorthands written where their values live: `reward: NAME` becomes
/// `env.reward` (the preset's weights, eq. 1 or 2) and `max_steps: N` becomes
/// `env.episode.max_steps`. In a document (a preset, a run's config.yaml) fields it states under
/// `env` win over its shorthand; a shorthand given by `--set` (`later_wins`) replaces what the
/// document said, as any later `--set` does.
pub(crate) fn expand_shorthands(doc: &mut serde_yaml::Value, later_wins: bool) -> Result<()> {
    let Some(map) = doc.as_mapping_mut() else { return Ok(()) };
    if let Some(r) = map.remove("reward").filter(|v| !v.is_null()) {
        let name = r.as_str().with_context(|| format!("reward: expected a preset name (exploration, search_and_rescue), got {r:?}"))?;
        let preset = serde_yaml::to_value(RewardConfig::preset(name)?)?;
        let slot = section_entry(map, &["env", "reward"])?;
        let stated = std::mem::take(slot);
        *slot = if later_wins || stated.is_null() { preset } else { overlay(preset, stated) };
    }
    if let Some(m) = map.remove("max_steps").filter(|v| !v.is_null()) {
        let slot = section_entry(map, &["env", "episode", "max_steps"])?;
        if later_wins || slot.is_null() {
            *slot = m;
        }
    }
    Ok(())
}

/// The value at `path` under `map`, made (as null) where missing; every step but the last must
/// be a section.
pub(crate) fn section_entry<'a>(map: &'a mut serde_yaml::Mapping, path: &[&str]) -> Result<&'a mut serde_yaml::Value> {
    let (last, parents) = path.split_last().expect("a path");
    let mut cur = map;
    for (i, p) in parents.iter().enumerate() {
        let v = cur.entry((*p).into()).or_insert(serde_yaml::Value::Null);
        if v.is_null() {
            *v = serde_yaml::Value::Mapping(Default::default());
        }
        cur = v.as_mapping_mut().with_context(|| format!("`{}` must be a section", path[..=i].join(".")))?;
    }
    Ok(cur.entry((*last).into()).or_insert(serde_yaml::Value::Null))
}

/// A built-in preset (or a preset file) as a `TrainConfig`, unresolved.
#[cfg(test)]
pub fn preset_config(preset: &str) -> Result<TrainConfig> {
    parse_config(serde_yaml::from_str(&preset_text(preset)?).context("preset YAML")?)
}

/// `over` laid over `base`: mappings merge key by key (recursively), anything else replaces.
/// A tagged value of another kind (`{kind: gaussian, …}` over `{kind: ornstein_uhlenbeck, …}`)
/// replaces too: the old kind's fields mean nothing to the new one.
pub(crate) fn overlay(base: serde_yaml::Value, over: serde_yaml::Value) -> serde_yaml::Value {
    let kind = |m: &serde_yaml::Mapping| m.get("kind").cloned();
    match (base, over) {
        (serde_yaml::Value::Mapping(b), serde_yaml::Value::Mapping(o)) if kind(&o).is_some() && kind(&b) != kind(&o) => serde_yaml::Value::Mapping(o),
        (serde_yaml::Value::Mapping(mut b), serde_yaml::Value::Mapping(o)) => {
            for (k, v) in o {
                let merged = match b.remove(&k) {
                    Some(old) => overlay(old, v),
                    None => v,
                };
                b.insert(k, merged);
            }
            serde_yaml::Value::Mapping(b)
        }
        (_, over) => over,
    }
}

/// A preset's YAML: a built-in name or a file path.
pub fn preset_text(preset: &str) -> Result<String> {
    if let Some((_, text)) = PRESETS.iter().find(|(n, _)| *n == preset) {
        return Ok((*text).to_owned());
    }
    let p = Path::new(preset);
    if p.exists() {
        return fs::read_to_string(p).with_context(|| format!("reading {}", p.display()));
    }
    bail!("unknown preset `{preset}`: built-in ones are {}; or give a path to a YAML file", PRESETS.iter().map(|p| p.0).collect::<Vec<_>>().join(", "))
}

#[derive(clap::Args, Clone, Debug)]
pub struct TrainArgs {
    /// Built-in preset (env1-sac, env1-td3, env1-ddpg, env2-*, outdoor20-sac) or a YAML file.
    #[arg(long, default_value = "env1-sac", conflicts_with = "resume")]
    pub preset: String,
    /// Actor processes (overrides the preset).
    #[arg(long, overrides_with = "actors")]
    pub actors: Option<usize>,
    /// Vehicles per actor process (overrides the preset).
    #[arg(long, overrides_with = "vehicles")]
    pub vehicles: Option<usize>,
    /// Stop after K training episodes of the run, earlier sessions included (overrides the preset).
    #[arg(long, overrides_with = "episodes")]
    pub episodes: Option<u64>,
    /// Stop after this many minutes of the run, earlier sessions included (overrides the preset).
    #[arg(long, overrides_with = "minutes")]
    pub minutes: Option<f64>,
    /// Run folder [default: runs/<preset name>].
    #[arg(long, overrides_with = "run")]
    pub run: Option<PathBuf>,
    /// Continue the run in this folder (its config, checkpoint, replay and curves).
    #[arg(long, value_name = "RUN")]
    pub resume: Option<PathBuf>,
    /// Override any config field: --set learner.actor_lr=1e-4 --set actors.vehicles=8.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub set: Vec<String>,
    /// Overwrite an existing run folder that is not being resumed.
    #[arg(long)]
    pub force: bool,
    /// Print the resolved config as YAML and exit.
    #[arg(long)]
    pub print_config: bool,
}

pub(crate) fn load_config(args: &TrainArgs) -> Result<(TrainConfig, PathBuf, bool)> {
    let (mut doc, run, resuming): (serde_yaml::Value, PathBuf, bool) = match &args.resume {
        Some(run) => (read_run_document(run)?, run.clone(), true),
        None => {
            let doc: serde_yaml::Value = serde_yaml::from_str(&preset_text(&args.preset)?).context("preset YAML")?;
            let name = doc.get("name").and_then(|v| v.as_str()).unwrap_or("run").to_owned();
            (doc, args.run.clone().unwrap_or_else(|| PathBuf::from("runs").join(name)), false)
        }
    };
    expand_shorthands(&mut doc, false)?;
    if let Some(n) = args.actors {
        set_path(&mut doc, "actors.count", &n.to_string())?;
    }
    if let Some(n) = args.vehicles {
        set_path(&mut doc, "actors.vehicles", &n.to_string())?;
    }
    if let Some(k) = args.episodes {
        set_path(&mut doc, "stop.episodes", &k.to_string())?;
    }
    if let Some(m) = args.minutes {
        set_path(&mut doc, "stop.minutes", &m.to_string())?;
    }
    for kv in &args.set {
        let (k, v) = kv.split_once('=').with_context(|| format!("--set {kv}: expected KEY=VALUE"))?;
        set_path(&mut doc, k.trim(), v.trim())?;
        expand_shorthands(&mut doc, true)?;
    }
    Ok((parse_config(doc)?.resolve()?, run, resuming))
}
