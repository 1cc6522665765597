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
use std::fs;
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use indicatif::{ProgressBar, ProgressStyle};
use mapless_sim::paper;
use mapless_sim::worlds::Split;
use serde::{Deserialize, Serialize};

use crate::eval::{self, EvalSummary};
use crate::train::{INTERRUPTED, Summary, read_run_config};

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
    /// Where the run folders go (kept: rerunning resumes and skips what is done)
    /// [default: runs/reproduce-quick or runs/reproduce-full].
    #[arg(long)]
    pub runs: Option<PathBuf>,
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

    fn runs(&self) -> PathBuf {
        self.runs.clone().unwrap_or_else(|| PathBuf::from(format!("runs/reproduce-{}", self.mode())))
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
        env3_dir(&self.dir)
    }
}

/// Where this command evaluates a run on env3 (not `eval-env3/`, which a hand-run `mapless
/// eval --map env3` fills with its own settings).
fn env3_dir(run: &Path) -> PathBuf {
    run.join("reproduce-env3")
}

/// The finished run in `dir`, if it is one: None when it has no summary yet or was interrupted
/// before it met its criteria (then it is resumed); an error when a summary is there but cannot
/// be read (a run is never trained further on a guess).
fn finished_summary(dir: &Path) -> Result<Option<Summary>> {
    let path = dir.join("summary.json");
    let text = match fs::read_to_string(&path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(e).with_context(|| format!("reading {}", path.display())),
    };
    let s: Summary = serde_json::from_str(&text).with_context(|| format!("{} is not a run summary; move the run folder away to train it again", path.display()))?;
    Ok((!s.stopped_because.starts_with(INTERRUPTED) || s.criteria_met_at.is_some()).then_some(s))
}

/// This command's env3 evaluation of a run, if it is there and is what the page says it is.
fn read_env3(dir: &Path) -> Option<EvalSummary> {
    let e: EvalSummary = serde_json::from_str(&fs::read_to_string(dir.join("eval.json")).ok()?).ok()?;
    let limit = paper::ENV3_EVAL_STEPS;
    let ok = e.map == "env3" && e.episodes.len() == ENV3_EPISODES as usize && e.episodes.iter().all(|x| x.steps <= limit && (x.collided || x.steps == limit));
    ok.then_some(e)
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
    if let Some(kv) = args.set.iter().find(|kv| kv.split('=').next().is_some_and(|k| k.trim() == "seed")) {
        bail!("--set {kv}: each run's seed is its seed number (seed-K); use --seeds");
    }
    let experiments = args.experiments()?;
    let runs = args.runs();
    let jobs: Vec<Job> = experiments.iter().flat_map(|e| (1..=args.seeds).map(|k| Job { exp: *e, seed: k, dir: runs.join(e.preset).join(format!("seed-{k}")) }).collect::<Vec<_>>()).collect();
    // The page is written from whatever finished, also when some runs failed or were stopped.
    let ran = if args.report_only { Ok(()) } else { run_jobs(args, &runs, &jobs) };
    let page = report(args, &runs, &experiments)?;
    eprintln!("reproduce: wrote {}", page.display());
    ran
}

fn run_jobs(args: &ReproduceArgs, runs: &Path, jobs: &[Job]) -> Result<()> {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let parallel = args.jobs.unwrap_or((cores / CORES_PER_EXPERIMENT).max(1)).max(1);
    let exe = std::env::current_exe().context("finding the mapless binary")?;
    let mut todo = Vec::new();
    for j in jobs {
        // An unreadable summary is this job's failure (reported by `run_one`), not the command's.
        if !matches!(finished_summary(&j.dir), Ok(Some(_))) || (j.exp.on_env3 && read_env3(&j.env3_dir()).is_none()) {
            todo.push(j.clone());
        }
    }
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
        runs.display()
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
    let children = Arc::new(Mutex::new(Children::default()));
    {
        let (queue, children) = (Arc::clone(&queue), Arc::clone(&children));
        std::thread::spawn(move || {
            let Ok(rt) = tokio::runtime::Builder::new_current_thread().enable_all().build() else { return };
            rt.block_on(crate::signals::termination());
            queue.lock().unwrap_or_else(|e| e.into_inner()).clear();
            // Under the lock that spawning holds: a child is either in the list now, or is
            // never started.
            let mut c = children.lock().unwrap_or_else(|e| e.into_inner());
            c.stopping = true;
            for pid in &c.pids {
                crate::signals::terminate(*pid);
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
                let _ = tx.send((job, r));
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
                // The other runs go on; the page shows what finished.
                bar.suspend(|| eprintln!("  {}: FAILED: {e:#}", job.label()));
                failed.push(job.label());
            }
        }
        show_running(&bar, &running);
    }
    for w in workers {
        if w.join().is_err() {
            failed.push("a worker thread (panicked)".into());
        }
    }
    bar.finish_and_clear();
    if !failed.is_empty() {
        bail!("{} run(s) did not finish: {}; run the same command again to resume (logs: {}/PRESET/seed-K.log)", failed.len(), failed.join(", "), runs.display());
    }
    Ok(())
}

/// The `mapless train` children now running, and whether a signal has stopped new ones.
#[derive(Default)]
struct Children {
    pids: Vec<u32>,
    stopping: bool,
}

fn show_running(bar: &ProgressBar, running: &Mutex<Vec<(String, Instant)>>) {
    let r = running.lock().unwrap_or_else(|e| e.into_inner());
    bar.set_message(r.iter().map(|(l, t)| format!("{l} ({:.0} s)", t.elapsed().as_secs_f64())).collect::<Vec<_>>().join(", "));
}

/// Trains (or resumes, or skips) one run, then evaluates it on env3; a one-line result.
fn run_one(exe: &Path, job: &Job, minutes: Option<f64>, set: &[String], children: &Mutex<Children>) -> Result<String> {
    let parent = job.dir.parent().expect("run folders have a parent");
    fs::create_dir_all(parent).with_context(|| format!("creating {}", parent.display()))?;
    if finished_summary(&job.dir)?.is_none() {
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
        let mut child = {
            let mut c = children.lock().unwrap_or_else(|e| e.into_inner());
            if c.stopping {
                bail!("stopped before it started");
            }
            let child = cmd.stdin(Stdio::null()).stdout(log.try_clone()?).stderr(log).spawn().with_context(|| format!("starting {}", exe.display()))?;
            c.pids.push(child.id());
            child
        };
        let status = child.wait();
        children.lock().unwrap_or_else(|e| e.into_inner()).pids.retain(|p| *p != child.id());
        let status = status?;
        if !status.success() {
            bail!("mapless train exited with {status} (log: {})", log_path.display());
        }
    }
    let Some(s) = finished_summary(&job.dir)? else {
        bail!("interrupted (log: {}/seed-{}.log)", parent.display(), job.seed);
    };
    let own = s.evaluation.as_ref().map_or("no evaluation".to_owned(), |e| format!("EQS {:.1}, EES {:.2}, {} collisions", e.mean_eqs, e.mean_ees, e.collisions));
    let mut line = format!("{} episodes in {:.0} s, avg return {:.1}, steps {:.0}; {own}", s.episodes, s.wall_s, s.average_return, s.average_steps);
    if job.exp.on_env3 {
        let e3 = match read_env3(&job.env3_dir()) {
            Some(e) => e,
            None => {
                let mut env = read_run_config(&job.dir)?.env;
                env.episode.max_steps = paper::ENV3_EVAL_STEPS;
                eval::evaluate(&job.dir.join("policy.safetensors"), "env3", Split::HeldOut, &env, ENV3_EPISODES, ENV3_SEED, Some(&job.env3_dir()))?
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

    /// "m ± s" (one value: "m"); "–" for none.
    fn fmt(s: Option<Stat>, decimals: usize) -> String {
        match s {
            None => "–".into(),
            Some(s) if s.n == 1 => format!("{:.*}", decimals, s.mean),
            Some(s) => format!("{:.*} ± {:.*}", decimals, s.mean, decimals, s.std),
        }
    }
}

/// One run as the page uses it: its summary, what its `config.yaml` says of its caps and its
/// update-to-data ratio, and its env3 evaluation.
#[derive(Debug, Serialize)]
struct RunResult {
    seed: u32,
    #[serde(flatten)]
    summary: Summary,
    minutes_cap: Option<f64>,
    episodes_cap: Option<u64>,
    samples_per_insert: Option<f64>,
    batch_size: usize,
    /// What the run's preset adds to the paper's set-up (`actors.start_clearance_m`,
    /// `actors.mirror_share`, `stop.min_episodes`), as the page's words; empty for none.
    aids: Vec<String>,
    env3: Option<EvalSummary>,
}

/// The training aids a run's config holds beyond the paper's set-up, each as the page says it.
fn training_aids(cfg: &crate::train::config::TrainConfig) -> Vec<String> {
    let mut aids = Vec::new();
    if let Some(c) = cfg.actors.start_clearance_m {
        aids.push(format!("training starts {c} m from obstacles (evaluations {} m; `actors.start_clearance_m`)", cfg.env.episode.start_clearance_m));
    }
    if cfg.actors.mirror_share > 0.0 {
        aids.push(format!("{} % of its transitions stored as their mirror image (`actors.mirror_share`)", cfg.actors.mirror_share * 100.0));
    }
    if let Some(k) = cfg.stop.min_episodes {
        aids.push(format!("its criteria judged from episode {k} on (`stop.min_episodes`)"));
    }
    aids
}

impl RunResult {
    /// Environment steps per learner update, as the run's rate limiter held them.
    fn steps_per_update(&self) -> Option<f64> {
        self.samples_per_insert.map(|spi| self.batch_size as f64 / spi)
    }
}

fn collect(runs: &Path, seeds: u32, e: &Experiment) -> Vec<RunResult> {
    (1..=seeds)
        .filter_map(|k| {
            let dir = runs.join(e.preset).join(format!("seed-{k}"));
            let summary = finished_summary(&dir).ok()??;
            let cfg = read_run_config(&dir).ok()?;
            Some(RunResult {
                seed: k,
                summary,
                minutes_cap: cfg.stop.minutes,
                episodes_cap: cfg.stop.episodes,
                samples_per_insert: cfg.replay.rate_limiter.samples_per_insert,
                batch_size: cfg.learner.batch_size,
                aids: training_aids(&cfg),
                env3: read_env3(&env3_dir(&dir)),
            })
        })
        .collect()
}

/// The distinct values, in order of first appearance, joined with " or "; "–" for none.
fn distinct(values: impl Iterator<Item = String>) -> String {
    let mut seen: Vec<String> = Vec::new();
    for v in values {
        if !seen.contains(&v) {
            seen.push(v);
        }
    }
    if seen.is_empty() { "–".into() } else { seen.join(" or ") }
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
fn figures(args: &ReproduceArgs, root: &Path, e: &Experiment, runs: &[RunResult]) -> Result<Vec<(String, String)>> {
    let Some(first) = runs.first() else { return Ok(Vec::new()) };
    let dir = root.join(e.preset).join(format!("seed-{}", first.seed));
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
    copy(
        dir.join("curves.png"),
        format!("{curves}-{}.png", e.preset),
        format!("{alg} on {}: return and steps per episode with their order-{} averages (seed {})", e.world, first.summary.window, first.seed),
    )?;
    if first.summary.evaluation.is_some() {
        copy(dir.join("eval").join("episode-1.png"), format!("{traj}-{}.png", e.preset), format!("{alg} on {}: evaluation trajectory 1 of the final policy (seed {})", e.world, first.seed))?;
    }
    if first.env3.is_some() {
        copy(env3_dir(&dir).join("episode-1.png"), format!("fig14-env3-{}.png", e.preset), format!("{alg} trained on {}, on env3: evaluation trajectory 1 (seed {})", e.world, first.seed))?;
    }
    Ok(out)
}

/// Writes `OUT/README.md`, `OUT/results.json` and the figures; returns the page's path.
fn report(args: &ReproduceArgs, root: &Path, experiments: &[Experiment]) -> Result<PathBuf> {
    fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let results: Vec<(Experiment, Vec<RunResult>)> = experiments.iter().map(|e| (*e, collect(root, args.seeds, e))).collect();
    let all: Vec<&RunResult> = results.iter().flat_map(|(_, r)| r.iter()).collect();
    let seeds = args.seeds as usize;
    let cell = |s: Option<Stat>, decimals: usize| match s {
        Some(st) if st.n < seeds => format!("{} (n = {})", Stat::fmt(s, decimals), st.n),
        _ => Stat::fmt(s, decimals),
    };
    let mut page = String::new();
    let total_s: f64 = all.iter().map(|x| x.summary.wall_s).sum();
    // What the runs did, read from their own configs and summaries (not from this command's flags).
    let caps = distinct(all.iter().map(|r| match (r.minutes_cap, r.episodes_cap) {
        (Some(m), _) => format!("capped at {m} minutes"),
        (None, Some(k)) => format!("up to {k} episodes (the preset's schedule)"),
        (None, None) => "uncapped".to_owned(),
    }));
    let ratios = distinct(all.iter().map(|r| r.steps_per_update().map_or("no update-to-data ratio".to_owned(), |k| format!("one update per {k} env steps"))));
    let eval_eps = distinct(all.iter().filter_map(|r| r.summary.evaluation.as_ref().map(|e| e.episodes.len().to_string())));
    let windows = distinct(all.iter().map(|r| r.summary.window.to_string()));
    let overrides = if args.set.is_empty() { String::new() } else { format!(" with {}", args.set.iter().map(|s| format!("`--set {s}`")).collect::<Vec<_>>().join(" ")) };
    let _ = writeln!(page, "# The paper's experiments, reproduced by `mapless reproduce`\n");
    let _ = writeln!(
        page,
        "Written by `mapless reproduce --{}{overrides} --seeds {}` from {} finished runs in `{}` ({:.0} minutes of training in all). \
         The runs: training {caps} (the paper trains 5,000–20,000 episodes over 66–204 hours); {ratios} (the paper: one per step). \
         Every number below comes from those runs; the paper's are from its Tables II–V (`sim/src/paper.rs`). \
         Ours are mean ± standard deviation over the seeds that finished (cells with fewer are marked n). \
         The paper reports one post-training trajectory per agent; our EQS and EES are the means of {eval_eps} deterministic evaluation episodes per run \
         (the final evaluation of `mapless train` on the training map), and of {ENV3_EPISODES} episodes of at most {} steps on env3. \
         Moving averages are of order {windows}. \
         EQS is read as docs/simulator.md settles it (linear inner sum, 2.5 m rings, 2 m cells; `mapless analyze eqs`, docs/results/eqs-reading.md).\n",
        args.mode(),
        args.seeds,
        all.len(),
        root.display(),
        total_s / 60.0,
        paper::ENV3_EVAL_STEPS
    );

    // Table II.
    let _ = writeln!(page, "## Table II — training time\n");
    let _ = writeln!(page, "| experiment | paper (hours, MATLAB, i7-11700K + RTX 3070 Ti) | ours: wall time per run | episodes | env steps | updates | stopped because (first seed) |");
    let _ = writeln!(page, "|---|---|---|---|---|---|---|");
    for (e, runs) in &results {
        let paper_h = paper::TABLE_III.iter().chain(paper::TABLE_IV.iter()).find(|t| t.world == e.world && t.algorithm == e.algorithm).map_or("–".to_owned(), |t| format!("{:.1}", t.hours));
        let why = runs.first().map_or("–".to_owned(), |r| format!("seed {}: {}", r.seed, r.summary.stopped_because));
        let _ = writeln!(
            page,
            "| {} | {paper_h} | {} min | {} | {} | {} | {why} |",
            e.preset,
            cell(stat(runs, |r| Some(r.summary.wall_s / 60.0)), 1),
            cell(stat(runs, |r| Some(r.summary.episodes as f64)), 0),
            cell(stat(runs, |r| Some(r.summary.env_steps as f64)), 0),
            cell(stat(runs, |r| Some(r.summary.updates as f64)), 0)
        );
    }

    // Tables III and IV.
    for (table, world, rows) in [("III", "env1", &paper::TABLE_III[..]), ("IV", "env2", &paper::TABLE_IV[..])] {
        if !results.iter().any(|(e, r)| e.world == world && !r.is_empty()) {
            continue;
        }
        let _ = writeln!(page, "\n## Table {table} — training on {world}\n");
        let _ = writeln!(
            page,
            "Paper / ours. Average return and steps are the moving averages at the end of training; the convergence episode is ours by the rule of `protocol::convergence_episode` (the paper states none).\n"
        );
        let _ = writeln!(page, "| algorithm | convergence episode | average return | average steps | EQS | EES | eval collisions per run (of {eval_eps}) |");
        let _ = writeln!(page, "|---|---|---|---|---|---|---|");
        for t in rows {
            let Some((_, runs)) = results.iter().find(|(e, _)| e.world == world && e.algorithm == t.algorithm) else { continue };
            let _ = writeln!(
                page,
                "| {} | {} / {} | {:.0} / {} | {:.0} / {} | {:.0} / {} | {:.2} / {} | {} |",
                t.algorithm.to_uppercase(),
                t.convergence_episode.map_or("–".to_owned(), |c| c.to_string()),
                cell(stat(runs, |r| r.summary.convergence_episode.map(|c| c as f64)), 0),
                t.average_return,
                cell(stat(runs, |r| Some(r.summary.average_return)), 1),
                t.average_steps,
                cell(stat(runs, |r| Some(r.summary.average_steps)), 0),
                t.eqs,
                cell(stat(runs, |r| r.summary.evaluation.as_ref().map(|e| e.mean_eqs)), 1),
                t.ees,
                cell(stat(runs, |r| r.summary.evaluation.as_ref().map(|e| e.mean_ees)), 2),
                cell(stat(runs, |r| r.summary.evaluation.as_ref().map(|e| f64::from(e.collisions))), 1),
            );
        }
    }

    // Table V.
    if results.iter().any(|(e, r)| e.on_env3 && r.iter().any(|x| x.env3.is_some())) {
        let _ = writeln!(page, "\n## Table V — the six agents on env3 (never trained on)\n");
        let _ = writeln!(page, "Paper / ours: steps before a collision or the {}-step limit, EQS, EES; collisions of our {ENV3_EPISODES} episodes per seed.\n", paper::ENV3_EVAL_STEPS);
        let _ = writeln!(page, "| agent | steps | EQS | EES | collisions per run (of {ENV3_EPISODES}) |");
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
                cell(env3(|e| e.mean_steps), 0),
                t.eqs,
                cell(env3(|e| e.mean_eqs), 1),
                t.ees,
                cell(env3(|e| e.mean_ees), 2),
                cell(env3(|e| f64::from(e.collisions)), 1),
            );
        }
    }

    // Outdoor.
    if let Some((_, runs)) = results.iter().find(|(e, _)| e.world == "outdoor20") {
        let _ = writeln!(page, "\n## Outdoor20 — SAC with the search-and-rescue reward (eq. 2)\n");
        let _ = writeln!(page, "| | paper | ours |\n|---|---|---|");
        let _ = writeln!(page, "| average return (order 50, end of training) | {:.0} | {} |", paper::OUTDOOR_SAC_RETURN, cell(stat(runs, |r| Some(r.summary.average_return)), 1));
        let _ = writeln!(page, "| evaluation: time in shade per episode (s) | – | {} |", cell(stat(runs, |r| r.summary.evaluation.as_ref().map(|e| e.mean_shaded_time_s)), 1));
        let _ = writeln!(page, "| evaluation: steps | – | {} |", cell(stat(runs, |r| r.summary.evaluation.as_ref().map(|e| e.mean_steps)), 0));
    }

    // Ranking.
    let _ = writeln!(page, "\n## The ranking of the algorithms\n");
    let rank = |pairs: Vec<(String, f64)>| -> String {
        let mut p = pairs;
        p.sort_by(|a, b| b.1.total_cmp(&a.1));
        p.iter().map(|(a, v)| format!("{a} ({v:.1})")).collect::<Vec<_>>().join(" > ")
    };
    for (world, rows) in [("env1", &paper::TABLE_III[..]), ("env2", &paper::TABLE_IV[..])] {
        let ours: Vec<(String, f64)> = results
            .iter()
            .filter(|(e, _)| e.world == world)
            .filter_map(|(e, r)| stat(r, |x| x.summary.evaluation.as_ref().map(|v| v.mean_eqs)).map(|s| (agent_name(e.algorithm, None), s.mean)))
            .collect();
        if ours.is_empty() {
            continue;
        }
        let theirs: Vec<(String, f64)> = rows.iter().map(|t| (agent_name(t.algorithm, None), t.eqs)).collect();
        let _ = writeln!(page, "- EQS on {world}: ours {}; paper {}.", rank(ours), rank(theirs));
    }
    let ours3: Vec<(String, f64)> =
        results.iter().filter(|(e, _)| e.on_env3).filter_map(|(e, r)| stat(r, |x| x.env3.as_ref().map(|v| v.mean_steps)).map(|s| (agent_name(e.algorithm, Some(e.world)), s.mean))).collect();
    if !ours3.is_empty() {
        let theirs3: Vec<(String, f64)> = paper::TABLE_V.iter().map(|t| (agent_name(t.algorithm, Some(t.trained_on)), f64::from(t.steps))).collect();
        let _ = writeln!(page, "- Steps on env3: ours {}; paper {}.", rank(ours3), rank(theirs3));
    }

    // Where we differ and why.
    let _ = writeln!(page, "\n## Where we match, where we differ, and why\n");
    let _ = writeln!(
        page,
        "- **Schedules.** {}",
        if all.iter().all(|r| r.minutes_cap.is_none()) {
            "The runs followed the presets' schedules: the paper's episode counts, stopping early when the paper-quality criteria (order-50 averages and an evaluation at the paper's EQS/EES) hold."
        } else {
            "These runs were capped at minutes where the paper trains for days: a run that has not met its preset's criteria by then is compared as it stands, so low returns and short episodes here are schedules cut short, not a verdict on the algorithm. `--full` runs the paper's schedules."
        }
    );
    let _ = writeln!(
        page,
        "- **Worlds.** The paper's figures are not in its text; our env1, env2 and env3 are layouts built to satisfy its numbers (docs/simulator.md, \"What the paper's numbers imply\"): env1 is a walled 25 m box with a central block and env2 a walled 40 m square of four lanes round medians, so a car that stands still earns less per step of eq. (1) than the paper's agents (Tables III and IV). env3 is held to Table V's remark that it resembles env1 more than env2: an island in each room makes it a loop of aisles, so 99 % of its poses show a nearest obstacle no farther than env1's farthest (`mapless maps stats env3`). Walls in env1 and env3 are 1 m thick, as on the occupancy grid of 1 m cells that the paper's MathWorks template uses: drawn as lines (before 2026-11-26), a wall's end was invisible end-on to seven beams and our agents clipped env3's door jambs."
    );
    let _ = writeln!(
        page,
        "- **Inferred parameters.** Where the paper is silent (network width, exploration noise, the update-to-data ratio, the EQS reading) the presets say what we chose and why; these runs took {ratios} (the paper: every step)."
    );
    let aided: Vec<String> = results
        .iter()
        .filter_map(|(e, runs)| {
            let per_run: Vec<String> = runs.iter().filter(|r| !r.aids.is_empty()).map(|r| r.aids.join(", ")).collect();
            (!per_run.is_empty()).then(|| format!("{}: {}", e.preset, distinct(per_run.into_iter())))
        })
        .collect();
    if !aided.is_empty() {
        let _ = writeln!(
            page,
            "- **Beyond the paper, in training only.** Reward, hyperparameters and the evaluation stay the paper's; in training, on points its text leaves open, these runs add (a preset that holds one says why and what it was measured against; one set by `--set` is named in the first line): {}.",
            aided.join("; ")
        );
    }
    let _ = writeln!(
        page,
        "- **Evaluation.** The paper scores one trajectory per agent; ours average {eval_eps} deterministic episodes per run from random starts, so a lucky or unlucky start weighs less."
    );

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
        let collisions: f64 = runs.iter().filter_map(|r| r.summary.evaluation.as_ref().map(|e| f64::from(e.collisions))).sum();
        let episodes: usize = runs.iter().filter_map(|r| r.summary.evaluation.as_ref().map(|e| e.episodes.len())).sum();
        let _ = writeln!(
            page,
            "- {} on {}: EQS {}, EES {}, average steps {}; {collisions:.0} collisions in {episodes} evaluation episodes.",
            agent_name(t.algorithm, None),
            t.world,
            verdict(stat(runs, |r| r.summary.evaluation.as_ref().map(|e| e.mean_eqs)), t.eqs, 1),
            verdict(stat(runs, |r| r.summary.evaluation.as_ref().map(|e| e.mean_ees)), t.ees, 2),
            verdict(stat(runs, |r| Some(r.summary.average_steps)), t.average_steps, 0),
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
    // Pictures of an earlier page go; those of these runs are copied afresh.
    if let Ok(dir) = fs::read_dir(&args.out) {
        for f in dir.flatten() {
            let name = f.file_name().to_string_lossy().into_owned();
            if name.starts_with("fig") && name.ends_with(".png") {
                let _ = fs::remove_file(f.path());
            }
        }
    }
    let mut all_figs = Vec::new();
    for (e, runs) in &results {
        all_figs.extend(figures(args, root, e, runs)?);
    }
    let _ = writeln!(
        page,
        "The paper's numbering: Figs. 8–9 env1 curves, 10 env1 trajectories, 11–12 env2 curves, 13 env2 trajectories, 14 env3, 15 outdoor return curve, 16 outdoor trajectory (shaded regions marked).\n"
    );
    for (name, caption) in &all_figs {
        let _ = writeln!(page, "**{name}** — {caption}\n\n![{caption}]({name})\n");
    }

    let json: Vec<serde_json::Value> = results.iter().map(|(e, r)| serde_json::json!({"preset": e.preset, "world": e.world, "algorithm": e.algorithm, "runs": r})).collect();
    fs::write(
        args.out.join("results.json"),
        serde_json::to_string_pretty(&serde_json::json!({"command_mode": args.mode(), "seeds": args.seeds, "runs": root.display().to_string(), "experiments": json}))?,
    )?;
    let path = args.out.join("README.md");
    fs::write(&path, page).with_context(|| format!("writing {}", path.display()))?;
    Ok(path)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_page_names_what_a_preset_adds_in_training() {
        use crate::train::config::{preset_config, preset_with_sets};
        let aids = training_aids(&preset_config("env1-sac").unwrap());
        assert_eq!(aids.len(), 3, "{aids:?}");
        assert!(aids[0].starts_with("training starts 0.1 m from obstacles (evaluations 0.5 m"), "{aids:?}");
        assert!(aids[1].starts_with("50 % of its transitions stored as their mirror image"), "{aids:?}");
        assert!(aids[2].contains("from episode 1000 on"), "{aids:?}");
        // The paper's other presets add none; a --set that adds one is named.
        assert!(training_aids(&preset_config("env2-td3").unwrap()).is_empty());
        let set = training_aids(&preset_with_sets("env2-td3", &["actors.mirror_share=0.25".into()]).unwrap());
        assert_eq!(set, ["25 % of its transitions stored as their mirror image (`actors.mirror_share`)"]);
    }

    #[test]
    fn stat_is_mean_and_sample_std_over_finite_values() {
        let s = Stat::of(&[1.0, 2.0, 3.0, f64::NAN]).unwrap();
        assert_eq!((s.mean, s.n), (2.0, 3));
        assert!((s.std - 1.0).abs() < 1e-12);
        assert_eq!(Stat::of(&[]), None);
        assert_eq!(Stat::fmt(Stat::of(&[5.0]), 1), "5.0");
        assert_eq!(Stat::fmt(Stat::of(&[1.0, 3.0]), 1), "2.0 ± 1.4");
    }

    fn summary_json(stopped_because: &str, criteria_met: bool) -> serde_json::Value {
        serde_json::json!({
            "run": "r", "preset": "env1-sac", "stopped_because": stopped_because, "wall_s": 1.0, "episodes": 0,
            "env_steps": 0, "updates": 0, "weights_version": 0,
            // No episode yet: NaN averages, which serde_json writes as null.
            "average_return": null, "average_steps": null, "window": 50,
            "criteria_met_at": if criteria_met { serde_json::json!({"wall_s": 1.0, "episode": 1, "env_steps": 1, "updates": 1}) } else { serde_json::Value::Null },
            "criteria_evaluation": null, "convergence_episode": null, "actor_restarts": 0, "steady": null, "evaluation": null
        })
    }

    #[test]
    fn a_run_is_finished_resumed_or_refused_by_what_its_summary_says() {
        let dir = tempfile::tempdir().unwrap();
        let write = |v: serde_json::Value| fs::write(dir.path().join("summary.json"), v.to_string()).unwrap();
        assert!(finished_summary(dir.path()).unwrap().is_none(), "no summary: not finished");
        write(summary_json("2 minutes", false));
        let s = finished_summary(dir.path()).unwrap().expect("a summary with null averages reads back");
        assert!(s.average_return.is_nan());
        write(summary_json("interrupted (Ctrl-C or SIGTERM)", false));
        assert!(finished_summary(dir.path()).unwrap().is_none(), "interrupted: resumed");
        write(summary_json("interrupted (Ctrl-C or SIGTERM); meanwhile the criteria were met", true));
        assert!(finished_summary(dir.path()).unwrap().is_some(), "met its criteria before the interruption: finished");
        fs::write(dir.path().join("summary.json"), "{ torn").unwrap();
        assert!(finished_summary(dir.path()).is_err(), "an unreadable summary is an error, not a resume");
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
