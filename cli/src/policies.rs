//! Shipped policies: trained policies kept in the repository's `policies/` folder so that
//! `mapless eval --policy NAME` and `mapless rollout --policy NAME` work right after a clone.
//!
//! ```text
//!   policies/NAME/
//!     config.yaml            the run's resolved configuration (sensor, reward, algorithm …)
//!     policy.safetensors     the deterministic policy (the run's final published weights)
//!     card.json              how it was trained and what it scored (read by `policies check`)
//!     card.md                the same for people, with the env3 contact sheet
//!     sheet-env3.png
//! ```
//!
//! `mapless policies ship --run R --name NAME` makes one from a finished run: it copies the
//! two files, evaluates the policy (its training map, env3, and any `--eval` maps) and writes
//! the card. Every evaluation on the card is deterministic (fixed seeds), so `mapless policies
//! check` reruns the short ones and must get the recorded figures again: a simulator or
//! inference change that alters what a shipped policy does is caught by the test suite.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use serde::{Deserialize, Serialize};

use crate::eval::{self, EvalSummary};
use crate::train::{Summary, read_run_config};
use mapless_sim::EnvConfig;
use mapless_sim::worlds::Split;

/// The card's machine-readable half.
pub const CARD_JSON: &str = "card.json";
/// Episodes, step limit and seed of the short evaluations that `policies check` reruns.
pub const CHECK_EPISODES: u32 = 3;
pub const CHECK_MAX_STEPS: u32 = 1000;
/// The seed of every evaluation on a card (the env3 evaluations of `mapless reproduce` use it too).
pub const CARD_SEED: u64 = 7;
/// Episodes and step limit of a card's full evaluations (env3 as in Table V: 3,000 steps).
pub const FULL_EPISODES: u32 = 10;
pub const ENV3_MAX_STEPS: u32 = 3000;

/// How a shipped policy was made and what it scored.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Card {
    pub name: String,
    pub preset: String,
    pub algorithm: String,
    /// The run's `map` (one map, or a `+`-joined list of maps and families).
    pub trained_on: String,
    pub seed: u64,
    /// The command that trained it.
    pub command: String,
    pub stopped_because: String,
    pub wall_s: f64,
    pub episodes: u64,
    pub env_steps: u64,
    pub updates: u64,
    /// `mapless --version` that shipped it.
    pub shipped_by: String,
    pub evaluations: Vec<CardEval>,
}

/// One deterministic evaluation of a shipped policy.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct CardEval {
    pub map: String,
    pub episodes: u32,
    pub max_steps: u32,
    pub seed: u64,
    /// Rerun by `mapless policies check` (and the test suite).
    pub check: bool,
    pub mean_steps: f64,
    pub collisions: u32,
    /// Episodes that ran to the limit without a collision by stopping
    /// ([`crate::eval::PARKED_SHARE`]); `None` on a card written before it was counted
    /// (`mapless policies update` fills it in).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub parked: Option<u32>,
    pub mean_eqs: f64,
    pub mean_ees: f64,
    pub mean_distance_m: f64,
}

impl CardEval {
    fn from_summary(map: &str, episodes: u32, max_steps: u32, seed: u64, check: bool, s: &EvalSummary) -> CardEval {
        CardEval {
            map: map.to_owned(),
            episodes,
            max_steps,
            seed,
            check,
            mean_steps: s.mean_steps,
            collisions: s.collisions,
            parked: Some(s.parked),
            mean_eqs: s.mean_eqs,
            mean_ees: s.mean_ees,
            mean_distance_m: s.mean_distance_m,
        }
    }

    /// The parked count as a table cell ("–" on a card written before it was counted).
    fn parked_text(&self) -> String {
        self.parked.map_or("–".to_owned(), |p| p.to_string())
    }

    /// What differs between the recorded figures and a rerun (empty when they agree).
    fn differences(&self, now: &CardEval) -> Vec<String> {
        let mut d = Vec::new();
        let close = |a: f64, b: f64| (a - b).abs() <= 1e-6 * a.abs().max(1.0);
        for (what, was, is) in [
            ("mean steps", self.mean_steps, now.mean_steps),
            ("mean EQS", self.mean_eqs, now.mean_eqs),
            ("mean EES", self.mean_ees, now.mean_ees),
            ("mean distance", self.mean_distance_m, now.mean_distance_m),
        ] {
            if !close(was, is) {
                d.push(format!("{what} {was} recorded, {is} now"));
            }
        }
        if self.collisions != now.collisions {
            d.push(format!("collisions {} recorded, {} now", self.collisions, now.collisions));
        }
        // A card written before parked episodes were counted has nothing to hold.
        if let (Some(was), Some(is)) = (self.parked, now.parked)
            && was != is
        {
            d.push(format!("parked {was} recorded, {is} now"));
        }
        d
    }
}

/// The folder that holds the shipped policies: `$MAPLESS_POLICIES`, else the repository's
/// `policies/` (the checkout this binary was built from), else `./policies`.
pub fn policies_dir() -> PathBuf {
    if let Some(d) = std::env::var_os("MAPLESS_POLICIES") {
        return PathBuf::from(d);
    }
    let repo = Path::new(env!("CARGO_MANIFEST_DIR")).join("..").join("policies");
    if repo.is_dir() { repo.canonicalize().unwrap_or(repo) } else { PathBuf::from("policies") }
}

/// A shipped policy's folder by name (or a path to such a folder).
pub fn resolve(name: &str) -> Result<PathBuf> {
    let as_path = Path::new(name);
    let dir = if as_path.join("policy.safetensors").is_file() { as_path.to_path_buf() } else { policies_dir().join(name) };
    if !dir.join("policy.safetensors").is_file() || !dir.join("config.yaml").is_file() {
        let known = list(&policies_dir()).map(|c| c.into_iter().map(|c| c.name).collect::<Vec<_>>().join(", ")).unwrap_or_default();
        bail!("no shipped policy {name:?} (looked in {}; shipped: {})", dir.display(), if known.is_empty() { "none" } else { &known });
    }
    Ok(dir)
}

/// Reads a policy folder's card.
pub fn read_card(dir: &Path) -> Result<Card> {
    let p = dir.join(CARD_JSON);
    let text = std::fs::read_to_string(&p).with_context(|| format!("reading {}", p.display()))?;
    serde_json::from_str(&text).with_context(|| format!("parsing {}", p.display()))
}

/// The cards of every policy under `dir`, by name.
pub fn list(dir: &Path) -> Result<Vec<Card>> {
    let mut cards = Vec::new();
    if !dir.is_dir() {
        return Ok(cards);
    }
    for e in std::fs::read_dir(dir).with_context(|| format!("reading {}", dir.display()))? {
        let e = e?;
        if e.path().join(CARD_JSON).is_file() {
            cards.push(read_card(&e.path())?);
        }
    }
    cards.sort_by(|a, b| a.name.cmp(&b.name));
    Ok(cards)
}

/// The evaluations a card carries for a policy trained on `trained_on`: its training map and
/// env3 in full, the same two short (rerun by `check`), and each of `extra` in full.
fn planned(trained_on: &str, max_steps: u32, extra: &[String]) -> Vec<(String, u32, u32, bool)> {
    let mut v = vec![(trained_on.to_owned(), FULL_EPISODES, max_steps, false), ("env3".to_owned(), FULL_EPISODES, ENV3_MAX_STEPS, false)];
    v.extend(extra.iter().map(|m| (m.clone(), FULL_EPISODES, ENV3_MAX_STEPS, false)));
    v.push((trained_on.to_owned(), CHECK_EPISODES, CHECK_MAX_STEPS, true));
    v.push(("env3".to_owned(), CHECK_EPISODES, CHECK_MAX_STEPS, true));
    v
}

/// One deterministic evaluation of the policy in `dir` under its own simulator settings `env`.
fn run_eval(dir: &Path, env: &EnvConfig, map: &str, episodes: u32, max_steps: u32, seed: u64, out: Option<&Path>) -> Result<EvalSummary> {
    let mut env = env.clone();
    env.episode.max_steps = max_steps;
    eval::evaluate(&dir.join("policy.safetensors"), map, Split::HeldOut, &env, episodes, seed, out)
}

/// Evaluates one row of `name`'s card (the policy in `dir`): prints it, keeps the env3 sheet of a
/// full row as `dir/sheet-env3.png` (`sheets` holds the pictures of row `k`) and returns the row.
#[allow(clippy::too_many_arguments)]
fn evaluate_row(dir: &Path, name: &str, env: &EnvConfig, map: &str, episodes: u32, max_steps: u32, seed: u64, check: bool, sheets: &Path, k: usize) -> Result<CardEval> {
    let out = sheets.join(k.to_string());
    let s = run_eval(dir, env, map, episodes, max_steps, seed, Some(&out))?;
    eprintln!("  {name}: {}{}", s.one_line(), if check { " (check)" } else { "" });
    if map == "env3" && !check {
        std::fs::copy(out.join("sheet.png"), dir.join("sheet-env3.png"))?;
    }
    Ok(CardEval::from_summary(map, episodes, max_steps, seed, check, &s))
}

/// Writes both halves of a card, `card.json` and `card.md`, into `dir`.
fn write_card(dir: &Path, card: &Card) -> Result<()> {
    mapless_proto::atomic_file::write_file_atomically(&dir.join(CARD_JSON), serde_json::to_string_pretty(card)?.as_bytes())?;
    mapless_proto::atomic_file::write_file_atomically(&dir.join("card.md"), card_markdown(card).as_bytes())?;
    Ok(())
}

/// Copies a finished run into `policies/NAME`, evaluates it and writes its card.
pub fn ship(run: &Path, name: &str, into: &Path, extra: &[String], command: Option<&str>, force: bool) -> Result<Card> {
    if name.is_empty() || !name.chars().all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_') {
        bail!("a policy name is letters, digits, '-' and '_' (got {name:?})");
    }
    let summary_path = run.join("summary.json");
    let summary: Summary = serde_json::from_str(&std::fs::read_to_string(&summary_path).with_context(|| format!("reading {} (ship a finished run)", summary_path.display()))?)
        .with_context(|| format!("parsing {}", summary_path.display()))?;
    if summary.stopped_because.starts_with(crate::train::INTERRUPTED) {
        bail!("{} was interrupted ({}); finish it (`mapless train --resume`) before shipping it", run.display(), summary.stopped_because);
    }
    let cfg = read_run_config(run)?;
    let dir = into.join(name);
    if dir.exists() {
        if !force {
            bail!("{} exists (--force replaces it)", dir.display());
        }
        std::fs::remove_dir_all(&dir).with_context(|| format!("removing {}", dir.display()))?;
    }
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    for f in ["config.yaml", "policy.safetensors"] {
        std::fs::copy(run.join(f), dir.join(f)).with_context(|| format!("copying {} into {}", run.join(f).display(), dir.display()))?;
    }
    let sheets = tempfile::tempdir()?;
    let mut evaluations = Vec::new();
    for (k, (map, episodes, max_steps, check)) in planned(&cfg.map, cfg.env.episode.max_steps, extra).into_iter().enumerate() {
        evaluations.push(evaluate_row(&dir, name, &cfg.env, &map, episodes, max_steps, CARD_SEED, check, sheets.path(), k)?);
    }
    let seed = cfg.seed;
    let card = Card {
        name: name.to_owned(),
        preset: summary.preset.clone(),
        algorithm: cfg.learner.algorithm.as_str().to_owned(),
        trained_on: cfg.map.clone(),
        seed,
        command: command.map_or_else(|| format!("mapless train --preset {} --set seed={seed}", summary.preset), str::to_owned),
        stopped_because: summary.stopped_because.clone(),
        wall_s: summary.wall_s,
        episodes: summary.episodes,
        env_steps: summary.env_steps,
        updates: summary.updates,
        shipped_by: format!("mapless {}", env!("CARGO_PKG_VERSION")),
        evaluations,
    };
    write_card(&dir, &card)?;
    Ok(card)
}

/// The model card for people.
pub fn card_markdown(c: &Card) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "# {} — {} trained on {}\n", c.name, c.algorithm.to_uppercase(), c.trained_on);
    let _ = writeln!(s, "A shipped policy of mapless (`policies/{}`). Try it: `mapless eval --policy {} --map env3`, `mapless rollout --policy {} --map env1`.\n", c.name, c.name, c.name);
    let _ = writeln!(s, "## Training\n");
    let _ = writeln!(s, "| | |\n|---|---|");
    let _ = writeln!(s, "| preset | `{}` (config.yaml holds every resolved field) |", c.preset);
    let _ = writeln!(s, "| command | `{}` |", c.command);
    let _ = writeln!(s, "| seed | {} |", c.seed);
    let _ = writeln!(s, "| stopped because | {} |", c.stopped_because);
    let _ = writeln!(s, "| wall time | {:.0} s on the machine that trained it |", c.wall_s);
    let _ = writeln!(s, "| episodes / env steps / updates | {} / {} / {} |", c.episodes, c.env_steps, c.updates);
    let _ = writeln!(s, "| shipped by | {} |\n", c.shipped_by);
    let _ = writeln!(s, "## Evaluation\n");
    let _ = writeln!(
        s,
        "Deterministic policy, random starts (seed {CARD_SEED}), an episode ends in a collision or at the step limit. EQS/EES as docs/simulator.md reads them. Rows marked *check* are rerun by `mapless policies check` and the test suite, which require the same figures.\n"
    );
    let _ = writeln!(
        s,
        "*Parked*: episodes that ran to the limit without a collision because the car stopped (it drove under a third of what its steps cover at full speed; docs/experiments.md, \"Safe, or parked?\").\n"
    );
    let _ = writeln!(s, "| map | episodes × step limit | mean steps | collisions | parked | EQS | EES | distance (m) |");
    let _ = writeln!(s, "|---|---|---|---|---|---|---|---|");
    for e in &c.evaluations {
        let _ = writeln!(
            s,
            "| {}{} | {} × {} | {:.0} | {} | {} | {:.1} | {:.2} | {:.1} |",
            e.map,
            if e.check { " (check)" } else { "" },
            e.episodes,
            e.max_steps,
            e.mean_steps,
            e.collisions,
            e.parked_text(),
            e.mean_eqs,
            e.mean_ees,
            e.mean_distance_m
        );
    }
    let _ = writeln!(s, "\n![env3](sheet-env3.png)\n\n*The first episodes on env3 (never trained on): blue cells are those EQS counts, red ends are collisions.*");
    s
}

/// Rewrites `dir/README.md`: one row per shipped policy, from the cards.
pub fn write_index(dir: &Path) -> Result<()> {
    let cards = list(dir)?;
    let mut s = String::from(
        "# Shipped policies\n\nWritten by `mapless policies ship` from the cards below; `mapless policies list` prints the same. Try one: `mapless eval --policy NAME --map env3 --max-steps 3000`, `mapless rollout --policy NAME --map env1`. `mapless policies check` (run by the test suite) reruns each card's short evaluations and fails if a figure changed.\n\n",
    );
    s.push_str("| policy | algorithm | trained on | training | on its training map: steps, collisions, parked, EQS, EES | env3 (3,000 steps): steps, collisions, parked, EQS, EES |\n|---|---|---|---|---|---|\n");
    let fmt = |e: Option<&CardEval>| e.map_or("–".to_owned(), |e| format!("{:.0}, {}/{}, {}, {:.1}, {:.2}", e.mean_steps, e.collisions, e.episodes, e.parked_text(), e.mean_eqs, e.mean_ees));
    for c in &cards {
        let own = c.evaluations.iter().find(|e| e.map == c.trained_on && !e.check);
        let env3 = c.evaluations.iter().find(|e| e.map == "env3" && !e.check);
        let _ = writeln!(
            s,
            "| [{}]({}/card.md) | {} | {} | {:.0} s, {} env steps, {} updates | {} | {} |",
            c.name,
            c.name,
            c.algorithm,
            c.trained_on,
            c.wall_s,
            c.env_steps,
            c.updates,
            fmt(own),
            fmt(env3)
        );
    }
    mapless_proto::atomic_file::write_file_atomically(&dir.join("README.md"), s.as_bytes())?;
    Ok(())
}

/// Reruns a policy's check evaluations; the differences from its card (empty: it holds).
pub fn check(dir: &Path) -> Result<Vec<String>> {
    let card = read_card(dir)?;
    let mut diffs = Vec::new();
    let checks: Vec<&CardEval> = card.evaluations.iter().filter(|e| e.check).collect();
    if checks.is_empty() {
        bail!("{}: the card has no check evaluation", dir.display());
    }
    let env = read_run_config(dir)?.env;
    for e in checks {
        let s = run_eval(dir, &env, &e.map, e.episodes, e.max_steps, e.seed, None)?;
        let now = CardEval::from_summary(&e.map, e.episodes, e.max_steps, e.seed, true, &s);
        diffs.extend(e.differences(&now).into_iter().map(|d| format!("{} on {}: {d}", card.name, e.map)));
    }
    Ok(diffs)
}

/// Reruns every evaluation on a policy's card (full and check rows, same maps, episodes, step
/// limits and seeds), rewrites `card.json`, `card.md` and the env3 sheet with the new figures and
/// returns what changed. For a simulator change that moves the figures on purpose; the training
/// record (command, seed, wall time, steps) is kept.
pub fn update(dir: &Path) -> Result<Vec<String>> {
    let mut card = read_card(dir)?;
    let env = read_run_config(dir)?.env;
    let sheets = tempfile::tempdir()?;
    let mut changed = Vec::new();
    for (k, e) in card.evaluations.iter_mut().enumerate() {
        let now = evaluate_row(dir, &card.name, &env, &e.map, e.episodes, e.max_steps, e.seed, e.check, sheets.path(), k)?;
        changed.extend(e.differences(&now).into_iter().map(|d| format!("{} on {}: {d}", card.name, e.map)));
        *e = now;
    }
    write_card(dir, &card)?;
    Ok(changed)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_changed_figure_is_a_difference_and_the_same_figures_are_none() {
        let a = CardEval {
            map: "env3".into(),
            episodes: 3,
            max_steps: 1000,
            seed: 7,
            check: true,
            mean_steps: 812.0,
            collisions: 1,
            parked: Some(1),
            mean_eqs: 90.5,
            mean_ees: 2.1,
            mean_distance_m: 40.0,
        };
        assert!(a.differences(&a.clone()).is_empty());
        let mut b = a.clone();
        b.collisions = 2;
        b.parked = Some(0);
        b.mean_eqs = 91.0;
        let d = a.differences(&b);
        assert_eq!(d.len(), 3, "{d:?}");
        assert!(d.iter().any(|x| x.contains("collisions 1 recorded, 2 now")));
        assert!(d.iter().any(|x| x.contains("parked 1 recorded, 0 now")));
        // An older card, without the count, still holds on its other figures.
        let old = CardEval { parked: None, ..a.clone() };
        assert!(old.differences(&a).is_empty());
        let old: CardEval =
            serde_json::from_str(r#"{"map":"env3","episodes":3,"max_steps":1000,"seed":7,"check":true,"mean_steps":812.0,"collisions":1,"mean_eqs":90.5,"mean_ees":2.1,"mean_distance_m":40.0}"#)
                .unwrap();
        assert_eq!(old.parked, None);
    }

    #[test]
    fn a_card_plans_full_and_short_evaluations_of_its_training_map_and_env3() {
        let p = planned("env1", 1000, &["gen:rooms".into()]);
        assert_eq!(p.iter().filter(|e| e.3).map(|e| e.0.as_str()).collect::<Vec<_>>(), ["env1", "env3"]);
        assert!(p.iter().any(|e| e.0 == "env3" && e.2 == ENV3_MAX_STEPS && !e.3));
        assert!(p.iter().any(|e| e.0 == "gen:rooms" && !e.3));
    }

    #[test]
    fn an_unknown_policy_is_a_clear_error() {
        let e = resolve("no-such-policy").unwrap_err().to_string();
        assert!(e.contains("no shipped policy \"no-such-policy\""), "{e}");
    }
}
