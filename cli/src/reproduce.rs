//! `mapless reproduce`: the paper's experiment matrix on this machine, and the page that holds
//! our numbers beside the paper's.
//!
//! ```text
//!   env1 × {DDPG, TD3, SAC}  ─┐  mapless train --preset envW-ALGO --set seed=K   (× seeds)
//!   env2 × {DDPG, TD3, SAC}  ─┤    └─ the final evaluation on its own map (Table III/IV EQS, EES)
//!   outdoor20 × SAC (eq. 2)  ─┘  the six env1/env2 agents on env3, 3,000 steps (Table V)
//!                                 └─► OUT/README.md, results.json, fig*.png
//! ```
//!
//! Every experiment is a run folder under `--runs` (`PRESET/seed-K`). A run whose
//! `summary.json` says it finished is not run again; one that was interrupted (Ctrl-C, a
//! killed session) is resumed with `mapless train --resume`, so the command can be stopped
//! and started again at will. Experiments run as child processes, as many at once as the cores
//! allow (a local cluster is a replay, a learner and two actors: about three cores).
//!
//! `--quick` (the default) caps each training run at [`QUICK_MINUTES`] minutes (the presets'
//! stop criteria still apply, so a run that meets them stops sooner); `--full` runs the
//! presets' own schedules (the paper's episode counts, stopping early only on the paper-quality
//! criteria). The page says which, and every figure on it comes from the runs in `--runs`.

use std::fmt::Write as _;
use std::io::Write as _;
use std::fs;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use indicatif::{ProgressBar, ProgressStyle};
use mapless_sim::paper;
use serde::{Deserialize, Serialize};

use crate::eval::{self, EvalSummary};
use crate::train::{INTERRUPTED, Summary, TrainConfig};

/// Minutes of training per experiment under `--quick`: 7 experiments × 3 seeds × (2 min + start,
/// final evaluation and env3 evaluation) fit in an hour on 2 cores, one experiment at a time.
pub const QUICK_MINUTES: f64 = 2.0;
/// Episodes of each env3 evaluation (deterministic, from the evaluation seed's random starts).
pub const ENV3_EPISODES: u32 = 10;
/// The evaluation seed of the env3 evaluations (the same starts for every agent).
pub const ENV3_SEED: u64 = 7;
/// Cores one local cluster keeps busy (replay, learner with one libtorch thread, 2 actors).
const CORES_PER_EXPERIMENT: usize = 3;

/// One experiment of the paper's matrix.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Experiment {
    pub preset: &'static str,
    pub world: &'static str,
    pub algorithm: &'static str,
    /// Evaluated on env3 afterwards (Table V: the env1 and env2 agents).
    pub on_env3: bool,
}

/// The paper's matrix (§IV–V): env1 and env2 × DDPG, TD3, SAC, then SAC with eq. (2) on outdoor20.
pub const MATRIX: [Experiment; 7] = [
    Experiment { preset: "env1-ddpg", world: "env1", algorithm: "ddpg", on_env3: true },
    Experiment { preset: "env1-td3", world: "env1", algorithm: "td3", on_env3: true },
    Experiment { preset: "env1-sac", world: "env1", algorithm: "sac", on_env3: true },
    Experiment { preset: "env2-ddpg", world: "env2", algorithm: "ddpg", on_env3: true },
    Experiment { preset: "env2-td3", world: "env2", algorithm: "td3", on_env3: true },
    Experiment { preset: "env2-sac", world: "env2", algorithm: "sac", on_env3: true },
    Experiment { preset: "outdoor20-sac", world: "outdoor20", algorithm: "sac", on_env3: false },
];

#[derive(clap::Args, Clone, Debug)]
pub struct ReproduceArgs {
    /// Each training run capped at 2 minutes (the default mode; about an hour on 2 cores).
    #[arg(long, conflicts_with = "full")]
    pub quick: bool,
    /// The presets' own schedules (the paper's episode counts; hours to days).
    #[arg(long)]
    pub full: bool,
    /// Seeds per experiment (mean ± std over them).
    #[arg(long, default_value_t = 3)]
    pub seeds: u32,
    /// Where the page, the tables and the figures go.
    #[arg(long, default_value = "docs/results")]
    pub out: PathBuf,
    /// Where the run folders go (kept: rerunning resumes and skips what is done).
    #[arg(long, default_value = "runs/reproduce")]
    pub runs: PathBuf,
    /// Experiments at once [default: cores / 3, at least 1].
    #[arg(long)]
    pub jobs: Option<usize>,
    /// Cap each training run at this many minutes (overrides the mode's cap).
    #[arg(long)]
    pub minutes: Option<f64>,
    /// Only these presets of the matrix (comma-separated), e.g. `--only env1-sac,env1-td3`.
    #[arg(long, value_delimiter = ',')]
    pub only: Vec<String>,
    /// Override a config field of every new training run, as `mapless train --set` (e.g.
    /// `--set replay.rate_limiter.samples_per_insert=128` for the paper's update ratio); the
    /// page lists them.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub set: Vec<String>,
    /// Write the page from the run folders that exist, without training anything.
    #[arg(long)]
    pub report_only: bool,
}

impl ReproduceArgs {
    fn mode(&self) -> &'static str {
        if self.full { "full" } else { "quick" }
    }

    fn minutes(&self) -> Option<f64> {
        self.minutes.or(if self.full { None } else { Some(QUICK_MINUTES) })
    }

    fn experiments(&self) -> Result<Vec<Experiment>> {
        for name in &self.only {
            if !MATRIX.iter().any(|e| e.preset == name) {
                bail!("--only {name}: not in the matrix ({})", MATRIX.iter().map(|e| e.preset).collect::<Vec<_>>().join(", "));
            }
        }
        Ok(MATRIX.iter().copied().filter(|e| self.only.is_empty() || self.only.iter().any(|o| o == e.preset)).collect())
    }
}

/// One (experiment, seed) and its folder.
#[derive(Clone, Debug)]
struct Job {
    exp: Experiment,
    seed: u32,
    dir: PathBuf,
}

impl Job {
    fn label(&self) -> String {
        format!("{} seed {}", self.exp.preset, self.seed)
    }
    fn env3_dir(&self) -> PathBuf {
        self.dir.join("eval-env3")
    }
}

/// What a run folder says about itself.
fn finished_summary(dir: &Path) -> Option<Summary> {
    let text = fs::read_to_string(dir.join("summary.json")).ok()?;
    let s: Summary = serde_json::from_str(&text).ok()?;
    (!s.stopped_because.starts_with(INTERRUPTED)).then_some(s)
}

fn read_env3(dir: &Path) -> Option<EvalSummary> {
    serde_json::from_str(&fs::read_to_string(dir.join("eval.json")).ok()?).ok()
}

/// Runs `mapless reproduce`.
pub fn reproduce(args: &ReproduceArgs) -> Result<()> {
    if args.seeds == 0 {
        bail!("--seeds must be >= 1");
    }
    if let Some(m) = args.minutes
        && !(m > 0.0)
    {
        bail!("--minutes must be > 0");
    }
    let experiments = args.experiments()?;
    let jobs: Vec<Job> = experiments
        .iter()
        .flat_map(|e| (1..=args.seeds).map(move |k| Job { exp: *e, seed: k, dir: args.runs.join(e.preset).join(format!("seed-{k}")) }))
        .collect();
    if !args.report_only {
        run_jobs(args, &jobs)?;
    }
    let page = report(args, &experiments)?;
    eprintln!("reproduce: wrote {}", page.display());
    Ok(())
}

fn run_jobs(args: &ReproduceArgs, jobs: &[Job]) -> Result<()> {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let parallel = args.jobs.unwrap_or((cores / CORES_PER_EXPERIMENT).max(1)).max(1);
    let exe = std::env::current_exe().context("finding the mapless binary")?;
    let todo: Vec<Job> = jobs.iter().filter(|j| finished_summary(&j.dir).is_none() || (j.exp.on_env3 && read_env3(&j.env3_dir()).is_none())).cloned().collect();
    eprintln!(
        "reproduce ({}): {} experiments × {} seeds = {} runs, {} to do ({} done); {} at once; training capped at {}; runs in {}",
        args.mode(),
        jobs.len() / args.seeds as usize,
        args.seeds,
        jobs.len(),
        todo.len(),
        jobs.len() - todo.len(),
        parallel,
        args.minutes().map_or("the presets' schedules".to_owned(), |m| format!("{m} min per run")),
        args.runs.display()
    );
    if todo.is_empty() {
        return Ok(());
    }
    let bar = ProgressBar::new(todo.len() as u64);
    bar.set_style(ProgressStyle::with_template("[{elapsed_precise}] {bar:30} {pos}/{len} runs  {wide_msg}").expect("template"));
    bar.enable_steady_tick(Duration::from_secs(1));
    let queue = Arc::new(Mutex::new(todo.into_iter().collect::<std::collections::VecDeque<_>>()));
    // Ctrl-C or SIGTERM: nothing new starts, and every running `mapless train` gets SIGTERM
    // (it stops its cluster in order and writes an "interrupted" summary that a rerun resumes).
    let children = Arc::new(Mutex::new(Vec::<u32>::new()));
    {
        let (queue, children) = (Arc::clone(&queue), Arc::clone(&children));
        std::thread::spawn(move || {
            let Ok(rt) = tokio::runtime::Builder::new_current_thread().enable_all().build() else { return };
            rt.block_on(crate::signals::termination());
            queue.lock().unwrap_or_else(|e| e.into_inner()).clear();
            for pid in children.lock().unwrap_or_else(|e| e.into_inner()).iter() {
                let _ = Command::new("kill").arg("-TERM").arg(pid.to_string()).status();
            }
        });
    }
    let running = Arc::new(Mutex::new(Vec::<(String, Instant)>::new()));
    let (tx, rx) = mpsc::channel::<(Job, Result<String>)>();
    let mut workers = Vec::new();
    for _ in 0..parallel {
        let (queue, running, tx, exe, bar, children) = (Arc::clone(&queue), Arc::clone(&running), tx.clone(), exe.clone(), bar.clone(), Arc::clone(&children));
        let (minutes, set) = (args.minutes(), args.set.clone());
        workers.push(std::thread::spawn(move || {
            loop {
                let Some(job) = queue.lock().unwrap_or_else(|e| e.into_inner()).pop_front() else { break };
                running.lock().unwrap_or_else(|e| e.into_inner()).push((job.label(), Instant::now()));
                show_running(&bar, &running);
                let r = run_one(&exe, &job, minutes, &set, &children);
                running.lock().unwrap_or_else(|e| e.into_inner()).retain(|(l, _)| *l != job.label());
                let stop = r.is_err();
                let _ = tx.send((job, r));
                if stop {
                    break;
                }
            }
        }));
    }
    drop(tx);
    let mut failed = Vec::new();
    for (job, r) in rx {
        bar.inc(1);
        match r {
            Ok(line) => bar.suspend(|| eprintln!("  {}: {line}", job.label())),
            Err(e) => {
                bar.suspend(|| eprintln!("  {}: FAILED: {e:#}", job.label()));
                failed.push(job.label());
                // Nothing new starts after a failure (an interrupted run lands here too).
                queue.lock().unwrap_or_else(|e| e.into_inner()).clear();
            }
        }
        show_running(&bar, &running);
    }
    for w in workers {
        let _ = w.join();
    }
    bar.finish_and_clear();
    if !failed.is_empty() {
        bail!("{} run(s) did not finish: {}; run the same command again to resume (logs: {}/PRESET/seed-K.log)", failed.len(), failed.join(", "), args.runs.display());
    }
    Ok(())
}

fn show_running(bar: &ProgressBar, running: &Mutex<Vec<(String, Instant)>>) {
    let r = running.lock().unwrap_or_else(|e| e.into_inner());
    bar.set_message(r.iter().map(|(l, t)| format!("{l} ({:.0} s)", t.elapsed().as_secs_f64())).collect::<Vec<_>>().join(", "));
}

/// Trains (or resumes, or skips) one run, then evaluates it on env3; a one-line result.
fn run_one(exe: &Path, job: &Job, minutes: Option<f64>, set: &[String], children: &Mutex<Vec<u32>>) -> Result<String> {
    let parent = job.dir.parent().expect("run folders have a parent");
    fs::create_dir_all(parent).with_context(|| format!("creating {}", parent.display()))?;
    if finished_summary(&job.dir).is_none() {
        let log_path = parent.join(format!("seed-{}.log", job.seed));
        let log = fs::OpenOptions::new().create(true).append(true).open(&log_path).with_context(|| format!("opening {}", log_path.display()))?;
        let mut cmd = Command::new(exe);
        cmd.arg("train");
        let resuming = job.dir.join("config.yaml").exists();
        writeln!(&log, "=== mapless reproduce: {} {} ===", if resuming { "resuming" } else { "starting" }, job.dir.display()).with_context(|| format!("writing {}", log_path.display()))?;
        if resuming {
            cmd.arg("--resume").arg(&job.dir);
        } else {
            // A folder without a config is what a run killed before it started leaves.
            cmd.args(["--preset", job.exp.preset, "--force", "--set", &format!("seed={}", job.seed)]).arg("--run").arg(&job.dir);
            for kv in set {
                cmd.arg("--set").arg(kv);
            }
        }
        if let Some(m) = minutes {
            cmd.arg("--minutes").arg(m.to_string());
        }
        let mut child = cmd.stdin(Stdio::null()).stdout(log.try_clone()?).stderr(log).spawn().with_context(|| format!("starting {}", exe.display()))?;
        children.lock().unwrap_or_else(|e| e.into_inner()).push(child.id());
        let status = child.wait();
        children.lock().unwrap_or_else(|e| e.into_inner()).retain(|p| *p != child.id());
        let status = status?;
        if !status.success() {
            bail!("mapless train exited with {status} (log: {})", log_path.display());
        }
        if finished_summary(&job.dir).is_none() {
            bail!("interrupted (log: {})", log_path.display());
        }
    }
    let s = finished_summary(&job.dir).expect("checked");
    let own = s.evaluation.as_ref().map_or("no evaluation".to_owned(), |e| format!("EQS {:.1}, EES {:.2}, {} collisions", e.mean_eqs, e.mean_ees, e.collisions));
    let mut line = format!("{} episodes in {:.0} s, avg return {:.1}, steps {:.0}; {own}", s.episodes, s.wall_s, s.average_return, s.average_steps);
    if job.exp.on_env3 {
        let e3 = match read_env3(&job.env3_dir()) {
            Some(e) => e,
            None => {
                let cfg: TrainConfig = serde_yaml::from_str(&fs::read_to_string(job.dir.join("config.yaml"))?).context("the run's config.yaml")?;
                let mut env = cfg.env.clone();
                env.episode.max_steps = paper::ENV3_EVAL_STEPS;
                eval::evaluate(&job.dir.join("policy.safetensors"), "env3", &env, ENV3_EPISODES, ENV3_SEED, Some(&job.env3_dir()))?
            }
        };
        let _ = write!(line, "; env3: steps {:.0}, EQS {:.1}, EES {:.2}, {} collisions", e3.mean_steps, e3.mean_eqs, e3.mean_ees, e3.collisions);
    }
    Ok(line)
}

// ---------------------------------------------------------------------------------------------
// The page.

/// Mean and sample standard deviation of what the seeds gave.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq)]
pub struct Stat {
    pub mean: f64,
    pub std: f64,
    pub n: usize,
}

impl Stat {
    pub fn of(values: &[f64]) -> Option<Stat> {
        let v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
        if v.is_empty() {
            return None;
        }
        let n = v.len();
        let mean = v.iter().sum::<f64>() / n as f64;
        let std = if n > 1 { (v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1) as f64).sqrt() } else { 0.0 };
        Some(Stat { mean, std, n })
    }

    fn fmt(s: Option<Stat>, decimals: usize) -> String {
        match s {
            None => "–".into(),
            Some(s) if s.n == 1 => format!("{:.*}", decimals, s.mean),
            Some(s) => format!("{:.*} ± {:.*}", decimals, s.mean, decimals, s.std),
        }
    }
}

/// One run as the page uses it.
#[derive(Clone, Debug, Serialize)]
struct RunResult {
    preset: String,
    seed: u32,
    stopped_because: String,
    wall_s: f64,
    episodes: u64,
    env_steps: u64,
    updates: u64,
    average_return: f64,
    average_steps: f64,
    convergence_episode: Option<u64>,
    criteria_met_at_s: Option<f64>,
    eval: Option<EvalSummary>,
    env3: Option<EvalSummary>,
}

fn collect(args: &ReproduceArgs, e: &Experiment) -> Vec<RunResult> {
    (1..=args.seeds)
        .filter_map(|k| {
            let dir = args.runs.join(e.preset).join(format!("seed-{k}"));
            let s = finished_summary(&dir)?;
            Some(RunResult {
                preset: e.preset.into(),
                seed: k,
                stopped_because: s.stopped_because.clone(),
                wall_s: s.wall_s,
                episodes: s.episodes,
                env_steps: s.env_steps,
                updates: s.updates,
                average_return: s.average_return,
                average_steps: s.average_steps,
                convergence_episode: s.convergence_episode,
                criteria_met_at_s: s.criteria_met_at.as_ref().map(|m| m.wall_s),
                eval: s.evaluation,
                env3: read_env3(&dir.join("eval-env3")),
            })
        })
        .collect()
}

/// `SAC` or `SAC-env1`.
fn agent_name(algorithm: &str, world: Option<&str>) -> String {
    match world {
        Some(w) => format!("{}-{w}", algorithm.to_uppercase()),
        None => algorithm.to_uppercase(),
    }
}

fn stat(runs: &[RunResult], f: impl Fn(&RunResult) -> Option<f64>) -> Option<Stat> {
    Stat::of(&runs.iter().filter_map(f).collect::<Vec<_>>())
}

/// The figures of one run: the paper's number for each, the file it came from.
fn figures(args: &ReproduceArgs, e: &Experiment, runs: &[RunResult]) -> Result<Vec<(String, String)>> {
    let Some(first) = runs.first() else { return Ok(Vec::new()) };
    let dir = args.runs.join(e.preset).join(format!("seed-{}", first.seed));
    let (curves, traj) = match e.world {
        "env1" => ("fig08-09", "fig10"),
        "env2" => ("fig11-12", "fig13"),
        _ => ("fig15", "fig16"),
    };
    let mut out = Vec::new();
    let mut copy = |from: PathBuf, name: String, caption: String| -> Result<()> {
        if from.exists() {
            fs::copy(&from, args.out.join(&name)).with_context(|| format!("copying {}", from.display()))?;
            out.push((name, caption));
        }
        Ok(())
    };
    let alg = e.algorithm.to_uppercase();
    copy(dir.join("curves.png"), format!("{curves}-{}.png", e.preset), format!("{alg} on {}: return and steps per episode with their order-50 averages (seed {})", e.world, first.seed))?;
    copy(dir.join("eval").join("episode-1.png"), format!("{traj}-{}.png", e.preset), format!("{alg} on {}: evaluation trajectory 1 of the final policy (seed {})", e.world, first.seed))?;
    if e.on_env3 {
        copy(dir.join("eval-env3").join("episode-1.png"), format!("fig14-env3-{}.png", e.preset), format!("{alg} trained on {}, on env3: evaluation trajectory 1 (seed {})", e.world, first.seed))?;
    }
    Ok(out)
}

/// Writes `OUT/README.md`, `OUT/results.json` and the figures; returns the page's path.
fn report(args: &ReproduceArgs, experiments: &[Experiment]) -> Result<PathBuf> {
    fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let results: Vec<(Experiment, Vec<RunResult>)> = experiments.iter().map(|e| (*e, collect(args, e))).collect();
    let mut page = String::new();
    let total_runs: usize = results.iter().map(|(_, r)| r.len()).sum();
    let total_s: f64 = results.iter().flat_map(|(_, r)| r.iter().map(|x| x.wall_s)).sum();
    let cap = args.minutes().map_or("the presets' own schedules (the paper's episode counts, stopping early on the paper-quality criteria)".to_owned(), |m| format!("each training run capped at {m} minutes (the paper trains 5,000–20,000 episodes over 66–204 hours)"));
    let _ = writeln!(page, "# The paper's experiments, reproduced by `mapless reproduce --{}`\n", args.mode());
    let overrides = if args.set.is_empty() { String::new() } else { format!(" The presets ran with {}.", args.set.iter().map(|s| format!("`--set {s}`")).collect::<Vec<_>>().join(", ")) };
    let _ = writeln!(
        page,
        "Written by `mapless reproduce --{} --seeds {} --out {}` from {total_runs} runs in `{}` ({:.0} minutes of training in all); {cap}. \
         Every number below comes from those runs; the paper's are from its Tables II–V (`sim/src/paper.rs`). \
         Ours are mean ± standard deviation over the seeds (n per cell in `results.json`). \
         The paper reports one post-training trajectory per agent; our EQS and EES are the means of {} deterministic evaluation episodes per seed \
         (the final evaluation of `mapless train` on the training map; {ENV3_EPISODES} episodes of at most {} steps on env3). \
         EQS is read as docs/simulator.md settles it (linear inner sum, 2.5 m rings, 2 m cells; [eqs-reading.md](eqs-reading.md)).{overrides}\n",
        args.mode(),
        args.seeds,
        args.out.display(),
        args.runs.display(),
        total_s / 60.0,
        10,
        paper::ENV3_EVAL_STEPS
    );

    // Table II.
    let _ = writeln!(page, "## Table II — training time\n");
    let _ = writeln!(page, "| experiment | paper (hours, MATLAB, i7-11700K + RTX 3070 Ti) | ours: wall time per run | episodes | env steps | updates | stopped because (seed 1) |");
    let _ = writeln!(page, "|---|---|---|---|---|---|---|");
    for (e, runs) in &results {
        let paper_h = paper::TABLE_III.iter().chain(paper::TABLE_IV.iter()).find(|t| t.world == e.world && t.algorithm == e.algorithm).map_or("–".to_owned(), |t| format!("{:.1}", t.hours));
        let why = runs.first().map_or("–".to_owned(), |r| r.stopped_because.clone());
        let _ = writeln!(
            page,
            "| {} | {paper_h} | {} min | {} | {} | {} | {why} |",
            e.preset,
            Stat::fmt(stat(runs, |r| Some(r.wall_s / 60.0)), 1),
            Stat::fmt(stat(runs, |r| Some(r.episodes as f64)), 0),
            Stat::fmt(stat(runs, |r| Some(r.env_steps as f64)), 0),
            Stat::fmt(stat(runs, |r| Some(r.updates as f64)), 0)
        );
    }

    // Tables III and IV.
    for (table, world, rows) in [("III", "env1", &paper::TABLE_III[..]), ("IV", "env2", &paper::TABLE_IV[..])] {
        if !results.iter().any(|(e, r)| e.world == world && !r.is_empty()) {
            continue;
        }
        let _ = writeln!(page, "\n## Table {table} — training on {world}\n");
        let _ = writeln!(page, "Paper / ours. Average return and steps are the order-50 moving averages at the end of training; the convergence episode is ours by the rule of `protocol::convergence_episode` (the paper states none).\n");
        let _ = writeln!(page, "| algorithm | convergence episode | average return | average steps | EQS | EES | eval collisions (of 10 per seed) |");
        let _ = writeln!(page, "|---|---|---|---|---|---|---|");
        for t in rows {
            let Some((_, runs)) = results.iter().find(|(e, _)| e.world == world && e.algorithm == t.algorithm) else { continue };
            let _ = writeln!(
                page,
                "| {} | {} / {} | {:.0} / {} | {:.0} / {} | {:.0} / {} | {:.2} / {} | {} |",
                t.algorithm.to_uppercase(),
                t.convergence_episode.map_or("–".to_owned(), |c| c.to_string()),
                Stat::fmt(stat(runs, |r| r.convergence_episode.map(|c| c as f64)), 0),
                t.average_return,
                Stat::fmt(stat(runs, |r| Some(r.average_return)), 1),
                t.average_steps,
                Stat::fmt(stat(runs, |r| Some(r.average_steps)), 0),
                t.eqs,
                Stat::fmt(stat(runs, |r| r.eval.as_ref().map(|e| e.mean_eqs)), 1),
                t.ees,
                Stat::fmt(stat(runs, |r| r.eval.as_ref().map(|e| e.mean_ees)), 2),
                Stat::fmt(stat(runs, |r| r.eval.as_ref().map(|e| f64::from(e.collisions))), 1),
            );
        }
    }

    // Table V.
    if results.iter().any(|(e, r)| e.on_env3 && r.iter().any(|x| x.env3.is_some())) {
    let _ = writeln!(page, "\n## Table V — the six agents on env3 (never trained on)\n");
    let _ = writeln!(page, "Paper / ours: steps before a collision or the {}-step limit, EQS, EES; collisions of our {ENV3_EPISODES} episodes per seed.\n", paper::ENV3_EVAL_STEPS);
    let _ = writeln!(page, "| agent | steps | EQS | EES | collisions (of {ENV3_EPISODES} per seed) |");
    let _ = writeln!(page, "|---|---|---|---|---|");
    for t in &paper::TABLE_V {
        let Some((_, runs)) = results.iter().find(|(e, _)| e.world == t.trained_on && e.algorithm == t.algorithm) else { continue };
        let env3 = |f: fn(&EvalSummary) -> f64| stat(runs, move |r| r.env3.as_ref().map(f));
        let _ = writeln!(
            page,
            "| {}-{} | {} / {} | {:.0} / {} | {:.2} / {} | {} |",
            t.algorithm.to_uppercase(),
            t.trained_on,
            t.steps,
            Stat::fmt(env3(|e| e.mean_steps), 0),
            t.eqs,
            Stat::fmt(env3(|e| e.mean_eqs), 1),
            t.ees,
            Stat::fmt(env3(|e| e.mean_ees), 2),
            Stat::fmt(env3(|e| f64::from(e.collisions)), 1),
        );
    }
    }

    // Outdoor.
    if let Some((_, runs)) = results.iter().find(|(e, _)| e.world == "outdoor20") {
        let _ = writeln!(page, "\n## Outdoor20 — SAC with the search-and-rescue reward (eq. 2)\n");
        let _ = writeln!(page, "| | paper | ours |\n|---|---|---|");
        let _ = writeln!(page, "| average return (order 50, end of training) | {:.0} | {} |", paper::OUTDOOR_SAC_RETURN, Stat::fmt(stat(runs, |r| Some(r.average_return)), 1));
        let _ = writeln!(page, "| evaluation: time in shade per episode (s) | – | {} |", Stat::fmt(stat(runs, |r| r.eval.as_ref().map(|e| e.mean_shaded_time_s)), 1));
        let _ = writeln!(page, "| evaluation: steps | – | {} |", Stat::fmt(stat(runs, |r| r.eval.as_ref().map(|e| e.mean_steps)), 0));
    }

    // Ranking.
    let _ = writeln!(page, "\n## The ranking of the algorithms\n");
    let rank = |pairs: Vec<(String, f64)>| -> String {
        let mut p = pairs;
        p.sort_by(|a, b| b.1.total_cmp(&a.1));
        p.iter().map(|(a, v)| format!("{a} ({v:.1})")).collect::<Vec<_>>().join(" > ")
    };
    for (world, rows) in [("env1", &paper::TABLE_III[..]), ("env2", &paper::TABLE_IV[..])] {
        let ours: Vec<(String, f64)> = results.iter().filter(|(e, _)| e.world == world).filter_map(|(e, r)| stat(r, |x| x.eval.as_ref().map(|v| v.mean_eqs)).map(|s| (agent_name(e.algorithm, None), s.mean))).collect();
        if ours.is_empty() {
            continue;
        }
        let theirs: Vec<(String, f64)> = rows.iter().map(|t| (agent_name(t.algorithm, None), t.eqs)).collect();
        let _ = writeln!(page, "- EQS on {world}: ours {}; paper {}.", rank(ours), rank(theirs));
    }
    let ours3: Vec<(String, f64)> = results.iter().filter(|(e, _)| e.on_env3).filter_map(|(e, r)| stat(r, |x| x.env3.as_ref().map(|v| v.mean_steps)).map(|s| (agent_name(e.algorithm, Some(e.world)), s.mean))).collect();
    if !ours3.is_empty() {
        let theirs3: Vec<(String, f64)> = paper::TABLE_V.iter().map(|t| (agent_name(t.algorithm, Some(t.trained_on)), f64::from(t.steps))).collect();
        let _ = writeln!(page, "- Steps on env3: ours {}; paper {}.", rank(ours3), rank(theirs3));
    }

    // Where we differ and why.
    let _ = writeln!(page, "\n## Where we match, where we differ, and why\n");
    let _ = writeln!(page, "- **Schedules.** {}", if args.full { "`--full` follows the presets' schedules: the paper's episode counts, stopping early when the paper-quality criteria (order-50 averages and an evaluation at the paper's EQS/EES) hold." } else { "`--quick` caps every run at a few minutes where the paper trains for days: a run that has not met its preset's criteria by then is compared as it stands, so low returns and short episodes here are schedules cut short, not a verdict on the algorithm. `--full` runs the paper's schedules." });
    let _ = writeln!(page, "- **Worlds.** The paper's figures are not in its text; our env1, env2 and env3 are layouts built to satisfy its numbers (docs/simulator.md, \"What the paper's numbers imply\"): env1 is a walled 25 m box with a central block, so the per-step return of eq. (1) is bounded as the paper's Table III implies.");
    let _ = writeln!(page, "- **Inferred parameters.** Where the paper is silent (network width, exploration noise, the update-to-data ratio, the EQS reading) the presets say what we chose and why; the update-to-data ratio is one update per 4 env steps (the paper: every step).");
    let _ = writeln!(page, "- **Evaluation.** The paper scores one trajectory per agent; ours average {} deterministic episodes per seed from random starts, so a lucky or unlucky start weighs less.", 10);

    // Row by row, as the data says.
    let verdict = |ours: Option<Stat>, theirs: f64, decimals: usize| -> String {
        match ours {
            None => format!("– (paper {theirs:.decimals$})"),
            Some(o) => format!("{:.decimals$} ({} the paper's {theirs:.decimals$})", o.mean, if o.mean >= theirs { "reaches" } else { "below" }),
        }
    };
    let _ = writeln!(page, "\nRow by row (our mean over seeds against the paper's figure):\n");
    for t in paper::TABLE_III.iter().chain(paper::TABLE_IV.iter()) {
        let Some((_, runs)) = results.iter().find(|(e, r)| e.world == t.world && e.algorithm == t.algorithm && !r.is_empty()) else { continue };
        let collisions: f64 = runs.iter().filter_map(|r| r.eval.as_ref().map(|e| f64::from(e.collisions))).sum();
        let episodes: usize = runs.iter().filter_map(|r| r.eval.as_ref().map(|e| e.episodes.len())).sum();
        let _ = writeln!(
            page,
            "- {} on {}: EQS {}, EES {}, average steps {}; {collisions:.0} collisions in {episodes} evaluation episodes.",
            agent_name(t.algorithm, None),
            t.world,
            verdict(stat(runs, |r| r.eval.as_ref().map(|e| e.mean_eqs)), t.eqs, 1),
            verdict(stat(runs, |r| r.eval.as_ref().map(|e| e.mean_ees)), t.ees, 2),
            verdict(stat(runs, |r| Some(r.average_steps)), t.average_steps, 0),
        );
    }
    for t in &paper::TABLE_V {
        let Some((_, runs)) = results.iter().find(|(e, r)| e.world == t.trained_on && e.algorithm == t.algorithm && r.iter().any(|x| x.env3.is_some())) else { continue };
        let _ = writeln!(
            page,
            "- {} on env3: steps {}, EQS {}.",
            agent_name(t.algorithm, Some(t.trained_on)),
            verdict(stat(runs, |r| r.env3.as_ref().map(|e| e.mean_steps)), f64::from(t.steps), 0),
            verdict(stat(runs, |r| r.env3.as_ref().map(|e| e.mean_eqs)), t.eqs, 1),
        );
    }

    // Figures.
    let _ = writeln!(page, "\n## Figures\n");
    let mut all_figs = Vec::new();
    for (e, runs) in &results {
        all_figs.extend(figures(args, e, runs)?);
    }
    let _ = writeln!(page, "The paper's numbering: Figs. 8–9 env1 curves, 10 env1 trajectories, 11–12 env2 curves, 13 env2 trajectories, 14 env3, 15 outdoor return curve, 16 outdoor trajectory (shaded regions marked).\n");
    for (name, caption) in &all_figs {
        let _ = writeln!(page, "**{name}** — {caption}\n\n![{caption}]({name})\n");
    }

    let json: Vec<serde_json::Value> = results.iter().map(|(e, r)| serde_json::json!({"preset": e.preset, "world": e.world, "algorithm": e.algorithm, "runs": r})).collect();
    fs::write(args.out.join("results.json"), serde_json::to_string_pretty(&serde_json::json!({"mode": args.mode(), "seeds": args.seeds, "minutes_per_run": args.minutes(), "experiments": json}))?)?;
    let path = args.out.join("README.md");
    fs::write(&path, page).with_context(|| format!("writing {}", path.display()))?;
    Ok(path)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stat_is_mean_and_sample_std_over_finite_values() {
        let s = Stat::of(&[1.0, 2.0, 3.0, f64::NAN]).unwrap();
        assert_eq!((s.mean, s.n), (2.0, 3));
        assert!((s.std - 1.0).abs() < 1e-12);
        assert_eq!(Stat::of(&[]), None);
        assert_eq!(Stat::fmt(Stat::of(&[5.0]), 1), "5.0");
        assert_eq!(Stat::fmt(Stat::of(&[1.0, 3.0]), 1), "2.0 ± 1.4");
    }

    #[test]
    fn the_matrix_is_the_papers_and_every_preset_exists() {
        assert_eq!(MATRIX.iter().filter(|e| e.on_env3).count(), paper::TABLE_V.len());
        for e in &MATRIX {
            assert!(crate::train::PRESETS.iter().any(|(n, _)| *n == e.preset), "{}", e.preset);
        }
        for t in &paper::TABLE_V {
            assert!(MATRIX.iter().any(|e| e.world == t.trained_on && e.algorithm == t.algorithm));
        }
    }
}
