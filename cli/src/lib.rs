//! `mapless` — the command (its binary, `src/main.rs`, calls [`main`]).
//!
//! ```text
//!   mapless maps list                      built-in maps and what they hold
//!   mapless maps show env2 --out env2.png  a map as a picture
//!   mapless maps rasterize env2 --out DIR  a map as a ROS map_server map (YAML + PGM)
//!   mapless worlds generate --family cave --seed 7 --out DIR   a generated world (ROS map + picture)
//!   mapless worlds show --family rooms --out sheet.png         a contact sheet of a family
//!   mapless rollout --map env1 --out DIR   one simulated episode: trajectory picture + JSON
//!   mapless bench sim [--json]             simulator throughput (vehicle-steps/s)
//!   mapless train --preset env1-sac        a local actor–learner cluster, supervised
//!   mapless eval --run runs/NAME --map env3  the trained policy on any map, with pictures
//!   mapless analyze eqs                    which EQS reading the paper's tables support
//!   mapless reproduce [--quick|--full]     the paper's matrix; Tables II–V and figures in docs/results
//! ```
//!
//! `mapless` never links libtorch: `train` starts the `mapless-learner` binary beside it (the
//! learner crate's, the one executable that does), and `bench learner` runs its bench.
//!
//! A library beside the binary so that the fuzz targets (`fuzz/`, [`fuzzing`]) and the corpus
//! tests reach the run configuration's parser; nothing else is meant to link it.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Duration;

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand, ValueEnum};
use mapless_net::metrics::bench_report;
use mapless_plots::{Canvas, default_px_per_m};
use mapless_sim::{Env, EnvConfig, Map, RaycastMethod, RewardConfig, World};
use rand::{Rng, SeedableRng};

mod eval;
pub mod fuzzing;
mod policies;
mod protocol;
mod reproduce;
mod scrape;
mod signals;
mod soak;
pub mod train;
mod worlds;

#[derive(Parser)]
#[command(name = "mapless", version, about = "Map-free exploration by deep RL: simulator, training cluster, tools")]
struct Cli {
    /// Log as JSON lines instead of human-readable text.
    #[arg(long, global = true)]
    log_json: bool,
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Built-in and user maps.
    Maps {
        #[command(subcommand)]
        cmd: MapsCmd,
    },
    /// Procedural worlds: five seeded families (rooms, cave, hall, forest, field), as ROS maps
    /// and pictures; name one anywhere a map is named as gen:FAMILY:SEED.
    Worlds {
        #[command(subcommand)]
        cmd: worlds::WorldsCmd,
    },
    /// Drive one simulated episode and draw it.
    Rollout(RolloutArgs),
    /// Train: replay, learner and N actor processes on this machine, supervised, with a live
    /// progress line, curves and trajectories in the run folder.
    Train(train::TrainArgs),
    /// The run folder of a cluster `mapless train` did not start (the compose cluster): episodes
    /// from the actors, curves, evaluations of the learner's policy, summary.json on SIGTERM.
    Monitor(train::MonitorArgs),
    /// Evaluate a run's policy (deterministic) on any map: steps, EQS, EES, distance, shaded
    /// time per episode and their means; a trajectory picture per episode.
    Eval(EvalArgs),
    /// Trained policies shipped in the repository (`policies/`), each with a model card:
    /// list them, check that their recorded figures still hold, or ship a finished run.
    Policies {
        #[command(subcommand)]
        cmd: PoliciesCmd,
    },
    /// Measure throughput.
    Bench {
        #[command(subcommand)]
        cmd: BenchCmd,
    },
    /// The paper's experiment matrix (env1/env2 × DDPG/TD3/SAC, the six agents on env3, SAC on
    /// outdoor20) over several seeds, then a page with Tables II–V and the figures beside the
    /// paper's. Resumes after an interruption; runs as many experiments at once as the cores allow.
    Reproduce(reproduce::ReproduceArgs),
    /// Analyses of the paper's own numbers.
    Analyze {
        #[command(subcommand)]
        cmd: AnalyzeCmd,
    },
}

#[derive(Subcommand)]
enum PoliciesCmd {
    /// The shipped policies: what each was trained on and how it does on env3.
    List,
    /// Rerun every shipped policy's short check evaluations (or those named) and compare them
    /// with its card; fails on any difference.
    Check {
        names: Vec<String>,
        /// Rerun every evaluation on the cards (full ones too) and write the new figures into
        /// them, printing what changed: after a simulator change that moves them on purpose.
        #[arg(long)]
        update: bool,
    },
    /// Copy a finished run's policy into `policies/NAME`, evaluate it (its training map and
    /// env3, 10 episodes each; env3 and `--eval` maps at 3,000 steps) and write its model card.
    Ship {
        #[arg(long)]
        run: PathBuf,
        #[arg(long)]
        name: String,
        /// More maps to evaluate on (names, files, `gen:FAMILY` for held-out worlds).
        #[arg(long = "eval", num_args = 1..)]
        eval: Vec<String>,
        /// The training command for the card [default: `mapless train --preset P --set seed=S`].
        #[arg(long)]
        command: Option<String>,
        /// Replace an existing `policies/NAME`.
        #[arg(long)]
        force: bool,
    },
}

#[derive(Subcommand)]
enum AnalyzeCmd {
    /// Which reading of the paper's EQS formula fits every row of its Tables III–V: a Monte
    /// Carlo of trajectories of each row's length (d = EQS/EES) under the car's kinematics,
    /// scored under each candidate reading (docs/simulator.md, "EQS and EES — the reading the paper's tables support").
    Eqs {
        /// Simulated trajectories per paper row.
        #[arg(long, default_value_t = 2000)]
        trajectories: usize,
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Also write the table as Markdown to this file.
        #[arg(long)]
        out: Option<PathBuf>,
        /// Print the whole analysis as one JSON object instead of the table.
        #[arg(long)]
        json: bool,
    },
}

#[derive(Subcommand)]
enum MapsCmd {
    /// List the built-in maps.
    List,
    /// Draw a map (built-in name or path to a vector / ROS map YAML) to PNG.
    Show {
        map: String,
        #[arg(long)]
        out: PathBuf,
        /// Pixels per metre (default: about 900 px across).
        #[arg(long)]
        px_per_m: Option<f32>,
    },
    /// What a map lets any policy earn under eq. (1): the largest minimum range over every
    /// pose the car can stand in (a lattice of positions × headings), the per-step reward
    /// bound it implies, and the bound for a car that stands still.
    Stats {
        map: String,
        /// Lattice spacing (m).
        #[arg(long, default_value_t = 0.1)]
        grid: f64,
        /// Headings per position.
        #[arg(long, default_value_t = 72)]
        headings: usize,
        #[arg(long)]
        json: bool,
    },
    /// Write a map as a ROS map_server map (NAME.yaml + NAME.pgm) for ROS tools and peers.
    Rasterize {
        map: String,
        /// Metres per pixel.
        #[arg(long, default_value_t = 0.05)]
        resolution: f64,
        /// Output folder.
        #[arg(long)]
        out: PathBuf,
    },
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum Driver {
    /// Hand-written reactive driver (turn towards open space); not learned.
    Wander,
    /// Uniform random actions.
    Random,
}

#[derive(clap::Args)]
struct RolloutArgs {
    /// Built-in map name or path to a map YAML.
    #[arg(long, default_value = "env1")]
    map: String,
    /// Who drives.
    #[arg(long, value_enum, default_value = "wander", conflicts_with = "policy")]
    driver: Driver,
    /// A shipped policy drives (`mapless policies list`; or a run folder), deterministic, with
    /// the sensor and reward it was trained with.
    #[arg(long, conflicts_with = "reward")]
    policy: Option<String>,
    /// Step limit (the episode may end earlier in a collision).
    #[arg(long, default_value_t = 1000)]
    steps: u32,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Reward preset: exploration (eq. 1) or search_and_rescue (eq. 2) [default: exploration,
    /// or the policy's].
    #[arg(long)]
    reward: Option<String>,
    /// Output folder: trajectory.png and episode.json.
    #[arg(long, default_value = "runs/rollout")]
    out: PathBuf,
    /// Print the episode summary as one JSON object.
    #[arg(long)]
    json: bool,
}

#[derive(clap::Args)]
struct EvalArgs {
    /// Run folder (its config.yaml and policy.safetensors).
    #[arg(long, required_unless_present = "policy", conflicts_with = "policy")]
    run: Option<PathBuf>,
    /// A shipped policy by name (`mapless policies list`) instead of a run.
    #[arg(long)]
    policy: Option<String>,
    /// Map [default: the run's training map]: a name, a file, gen:FAMILY:SEED, or a list
    /// joined by `+` (episodes take the items in turn; gen:FAMILY: its held-out worlds).
    #[arg(long, conflicts_with_all = ["maps", "family"])]
    map: Option<String>,
    /// Several maps; `--episodes` episodes on each.
    #[arg(long, num_args = 1.., conflicts_with = "family")]
    maps: Vec<String>,
    /// A family of generated worlds (rooms, cave, hall, forest, field), with `--seeds`;
    /// `--episodes` episodes on each world.
    #[arg(long, requires = "seeds")]
    family: Option<String>,
    /// Seeds A..B of `--family` (held-out worlds are 1000000..2000000; a run judges itself
    /// while training on validation worlds, from 2000000).
    #[arg(long, value_parser = worlds::parse_seeds, requires = "family")]
    seeds: Option<std::ops::Range<u64>>,
    /// Episodes (per map with `--maps` or `--family`).
    #[arg(long, default_value_t = 10)]
    episodes: u32,
    /// Step limit per episode [default: the run's].
    #[arg(long)]
    max_steps: Option<u32>,
    #[arg(long, default_value_t = 7)]
    seed: u64,
    /// Pictures and eval.json go here [default: RUN/eval-MAP].
    #[arg(long)]
    out: Option<PathBuf>,
    /// Print the result as one JSON object.
    #[arg(long)]
    json: bool,
}

#[derive(Subcommand)]
enum BenchCmd {
    /// Vehicle-steps per second on one core, per scan preset (7, 100, 1080 beams).
    Sim {
        #[arg(long, default_value = "env2")]
        map: String,
        /// Seconds per configuration.
        #[arg(long, default_value_t = 3.0)]
        seconds: f64,
        /// Vehicles per vectorised step.
        #[arg(long, default_value_t = 64)]
        vehicles: usize,
        /// One JSON object per line: {"bench", "config", "value", "unit"}.
        #[arg(long)]
        json: bool,
    },
    /// Replay service: ingest over iceoryx2 and gRPC (1, 4, 16 writers), sampling rate and
    /// latency (minibatches of 128), resident memory of a full table; 17- and 203-float obs.
    Replay {
        /// Seconds per configuration.
        #[arg(long, default_value_t = 2.0)]
        seconds: f64,
        /// Rows for the memory measurement (the paper's capacity by default).
        #[arg(long, default_value_t = 1_000_000)]
        memory_rows: usize,
        /// Only the write-ahead log's cost per fsync policy (never, interval_ms 100, always)
        /// with 1, 4 and 16 writers: rows/s, insert latency p50/p99, rows per fsync.
        #[arg(long)]
        durability: bool,
        /// Where `--durability` puts its log (the disk it measures; the temp dir by default).
        #[arg(long, requires = "durability")]
        dir: Option<std::path::PathBuf>,
        #[arg(long)]
        json: bool,
    },
    /// Learner gradient updates per second for DDPG, TD3 and SAC at the paper's sizes
    /// (17-float observations, 2 actions, 2×256 hidden, minibatch 128), with 1 and 2 threads.
    Learner {
        /// Its flags, handed on as they are: `--seconds`, `--device`, `--threads`, `--algos`,
        /// `--unfused`, `--autograd`, `--json` (`mapless-learner bench --help` says more).
        #[arg(trailing_var_arg = true, allow_hyphen_values = true, value_name = "FLAGS")]
        args: Vec<String>,
    },
    /// The whole local cluster (`mapless train --preset env1-sac`): environment steps/s and
    /// learner updates/s after start-up, with 1, 2 and 4 actor processes.
    E2e {
        /// Actor process counts to measure.
        #[arg(long, value_delimiter = ',', default_value = "1,2,4")]
        actors: Vec<usize>,
        /// Wall seconds per configuration (the first 20 s are start-up and not counted).
        #[arg(long, default_value_t = 60.0)]
        seconds: f64,
        /// Vehicles per actor process.
        #[arg(long, default_value_t = 4)]
        vehicles: usize,
        /// Extra config overrides for every run (`--set KEY=VALUE`, as for `train`).
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
        #[arg(long)]
        json: bool,
    },
    /// Many streams for a long time: the replay (persistence on) and the learner under S paced
    /// insert streams, K samplers with priority updates and W weights subscribers; rows/s,
    /// latency p50/p99, each process's memory, threads and open files every few seconds.
    /// Fails if a stream stalls, a request fails or a resource grows after the warm-up.
    Soak(soak::SoakArgs),
}

/// `mapless`: parses the command line, runs the command, and prints an error's causes.
pub fn main() -> ExitCode {
    let cli = Cli::parse();
    // Benchmarks run services in-process; their per-stream info lines would drown the figures.
    let quiet = matches!(cli.cmd, Cmd::Bench { .. });
    mapless_net::logging::init(cli.log_json, if quiet { "warn" } else { "info" });
    let role = match &cli.cmd {
        Cmd::Train(_) => "supervisor",
        Cmd::Eval(_) => "eval",
        Cmd::Reproduce(_) => "reproduce",
        Cmd::Monitor(_) => "monitor",
        _ => "cli",
    };
    mapless_net::logging::identify(&[("role", role)]);
    match run(cli) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> Result<ExitCode> {
    let log_json = cli.log_json;
    let done: Result<()> = match cli.cmd {
        // A probe's verdict is its exit code.
        Cmd::Monitor(a) => return train::monitor(&a),
        Cmd::Maps { cmd: MapsCmd::List } => maps_list(),
        Cmd::Maps { cmd: MapsCmd::Show { map, out, px_per_m } } => maps_show(&map, &out, px_per_m),
        Cmd::Maps { cmd: MapsCmd::Stats { map, grid, headings, json } } => maps_stats(&map, grid, headings, json),
        Cmd::Maps { cmd: MapsCmd::Rasterize { map, resolution, out } } => maps_rasterize(&map, resolution, &out),
        Cmd::Worlds { cmd } => worlds::run(cmd),
        Cmd::Rollout(a) => rollout(a),
        Cmd::Train(a) => train::train(&a, log_json),
        Cmd::Eval(a) => eval_cmd(&a),
        Cmd::Policies { cmd } => policies_cmd(cmd),
        Cmd::Reproduce(a) => reproduce::reproduce(&a),
        Cmd::Analyze { cmd: AnalyzeCmd::Eqs { trajectories, seed, out, json } } => analyze_eqs(trajectories, seed, out.as_deref(), json),
        Cmd::Bench { cmd: BenchCmd::Sim { map, seconds, vehicles, json } } => bench_sim(&map, seconds, vehicles, json),
        Cmd::Bench { cmd: BenchCmd::Replay { seconds, durability: true, dir, json, .. } } => bench_durability(seconds, dir, json),
        Cmd::Bench { cmd: BenchCmd::Replay { seconds, memory_rows, json, .. } } => bench_replay(seconds, memory_rows, json),
        Cmd::Bench { cmd: BenchCmd::Learner { args } } => bench_learner(&args),
        Cmd::Bench { cmd: BenchCmd::E2e { actors, seconds, vehicles, set, json } } => bench_e2e(&actors, seconds, vehicles, &set, json),
        Cmd::Bench { cmd: BenchCmd::Soak(args) } => soak::soak(args),
    };
    done.map(|()| ExitCode::SUCCESS)
}

fn policies_cmd(cmd: PoliciesCmd) -> Result<()> {
    let dir = policies::policies_dir();
    match cmd {
        PoliciesCmd::List => {
            let cards = policies::list(&dir)?;
            if cards.is_empty() {
                println!("no shipped policies in {}", dir.display());
                return Ok(());
            }
            println!("{:<16} {:<5} {:<34} {:>7} {:>13} {:>8}", "name", "algo", "trained on", "train s", "env3 steps", "env3 EQS");
            for c in &cards {
                let env3 = c.evaluations.iter().find(|e| e.map == "env3" && !e.check);
                let (steps, eqs) = env3.map_or(("–".to_owned(), "–".to_owned()), |e| (format!("{:.0} ({}/{})", e.mean_steps, e.collisions, e.episodes), format!("{:.1}", e.mean_eqs)));
                println!("{:<16} {:<5} {:<34} {:>7.0} {:>13} {:>8}", c.name, c.algorithm, c.trained_on, c.wall_s, steps, eqs);
            }
            println!("(env3 steps: mean of the card's 3,000-step episodes, (collisions/episodes); cards: {}/NAME/card.md)", dir.display());
        }
        PoliciesCmd::Check { names, update } => {
            let names = if names.is_empty() { policies::list(&dir)?.into_iter().map(|c| c.name).collect() } else { names };
            if names.is_empty() {
                bail!("no shipped policies in {}", dir.display());
            }
            if update {
                for n in &names {
                    let d = policies::update(&policies::resolve(n)?)?;
                    println!("{n}: {}", if d.is_empty() { "unchanged".to_owned() } else { format!("updated: {}", d.join("; ")) });
                }
                policies::write_index(&dir)?;
                return Ok(());
            }
            let mut failed = Vec::new();
            for n in &names {
                let d = policies::check(&policies::resolve(n)?)?;
                println!("{n}: {}", if d.is_empty() { "holds".to_owned() } else { d.join("; ") });
                failed.extend(d);
            }
            if !failed.is_empty() {
                bail!("{} recorded figure(s) no longer hold", failed.len());
            }
        }
        PoliciesCmd::Ship { run, name, eval, command, force } => {
            let card = policies::ship(&run, &name, &dir, &eval, command.as_deref(), force)?;
            policies::write_index(&dir)?;
            println!("shipped {} into {} (card.md, card.json, sheet-env3.png)", card.name, dir.join(&card.name).display());
        }
    }
    Ok(())
}

fn eval_cmd(a: &EvalArgs) -> Result<()> {
    let run = match (&a.run, &a.policy) {
        (Some(r), _) => r.clone(),
        (None, Some(p)) => policies::resolve(p)?,
        (None, None) => bail!("--run or --policy"),
    };
    let cfg = train::read_run_config(&run)?;
    let mut env = cfg.env.clone();
    if let Some(m) = a.max_steps {
        env.episode.max_steps = m;
    }
    // --maps and --family name several maps: the episodes take them in turn, --episodes each.
    let several: Vec<String> = match (&a.family, &a.seeds) {
        (Some(f), Some(seeds)) => {
            mapless_sim::worlds::Family::parse(f)?;
            seeds.clone().map(|s| format!("gen:{f}:{s}")).collect()
        }
        _ => a.maps.clone(),
    };
    let (map, episodes) = if several.is_empty() { (a.map.clone().unwrap_or_else(|| cfg.map.clone()), a.episodes) } else { (several.join("+"), a.episodes * several.len() as u32) };
    let label = match (&a.family, &a.seeds) {
        (Some(f), Some(s)) => format!("{f}-{}-{}", s.start, s.end),
        _ => map.replace(['/', '.', '+', ':'], "_"),
    };
    // A shipped policy's folder is part of the checkout: its pictures go under runs/.
    let out = a.out.clone().unwrap_or_else(|| match &a.policy {
        Some(p) => PathBuf::from("runs").join(format!("eval-{p}-{label}")),
        None => run.join(format!("eval-{label}")),
    });
    let s = eval::evaluate(&run.join("policy.safetensors"), &map, mapless_sim::worlds::Split::HeldOut, &env, episodes, a.seed, Some(&out))?;
    if a.json {
        println!("{}", serde_json::to_string(&s)?);
    } else {
        println!("{:>3} {:>6} {:>9} {:>5} {:>6} {:>9} {:>8}", "ep", "steps", "return", "EQS", "EES", "dist m", "shade s");
        for e in &s.episodes {
            println!(
                "{:>3} {:>6} {:>9.1} {:>5} {:>6.2} {:>9.1} {:>8.1}{}",
                e.episode,
                e.steps,
                e.episode_return,
                e.eqs,
                e.ees,
                e.distance_m,
                e.shaded_time_s,
                match (e.collided, e.end_pose) {
                    (true, Some([x, y, _])) => format!("  collision at ({x:.1}, {y:.1}) m"),
                    (true, None) => "  collision".to_owned(),
                    (false, _) if e.parked => "  parked".to_owned(),
                    _ => String::new(),
                }
            );
        }
        println!(
            "mean {:>6.0} {:>9.1} {:>5.1} {:>6.2} {:>9.1} {:>8.1}  ({} collisions, {} parked: no collision, under a third of full speed's distance)",
            s.mean_steps, s.mean_return, s.mean_eqs, s.mean_ees, s.mean_distance_m, s.mean_shaded_time_s, s.collisions, s.parked
        );
        let per_map = s.per_map();
        if per_map.len() > 1 {
            println!("\n{:<24} {:>4} {:>6} {:>10} {:>6} {:>6} {:>5} {:>7}", "map", "eps", "steps", "collisions", "parked", "EQS", "EES", "dist m");
            for r in &per_map {
                println!("{:<24} {:>4} {:>6.0} {:>10} {:>6} {:>6.1} {:>5.2} {:>7.1}", r.map, r.episodes, r.mean_steps, r.collisions, r.parked, r.mean_eqs, r.mean_ees, r.mean_distance_m);
            }
        }
        println!("pictures (episode-K.png, sheet.png) and eval.json in {}", out.display());
    }
    Ok(())
}

fn analyze_eqs(trajectories: usize, seed: u64, out: Option<&std::path::Path>, json: bool) -> Result<()> {
    if trajectories == 0 {
        bail!("--trajectories must be >= 1");
    }
    let readings = mapless_sim::eqs_analysis::candidate_readings();
    let t0 = std::time::Instant::now();
    let a = mapless_sim::eqs_analysis::analyze(&readings, trajectories, seed, |done, all| {
        eprintln!("analyze eqs: {done}/{all} paper rows simulated ({:.1} s)", t0.elapsed().as_secs_f64());
    })?;
    let md = a.markdown();
    if let Some(p) = out {
        std::fs::write(p, &md).with_context(|| format!("writing {}", p.display()))?;
    }
    if json {
        println!("{}", serde_json::to_string(&a)?);
        return Ok(());
    }
    println!("{md}");
    let default = mapless_sim::ExplorationConfig::default();
    match a.supported() {
        Some(best) => println!("Supported by every row: {} (worst row {:.1} % from a tail).", best.label, best.worst_tail),
        None => println!("No candidate reading fits every row; best: {}.", a.readings[0].label),
    }
    if let Some(d) = a.readings.iter().find(|r| r.reading == default) {
        println!("The simulator's default ({}): {}/{} rows fit, worst row {:.1} % from a tail.", d.label, d.rows_fitting, d.rows.len(), d.worst_tail);
    }
    Ok(())
}

fn maps_stats(map: &str, grid: f64, headings: usize, json: bool) -> Result<()> {
    if !(grid > 0.0) || headings == 0 {
        bail!("--grid must be > 0 and --headings >= 1");
    }
    let world = World::new(mapless_sim::worlds::resolve(map)?, EnvConfig::default())?;
    let b = mapless_sim::bounds::reward_bounds(&world, grid, headings);
    if json {
        println!("{}", serde_json::json!({ "map": world.map.name, "grid_m": grid, "headings": headings, "bounds": b }));
        return Ok(());
    }
    let steps = world.cfg.episode.max_steps;
    println!("{}: {} collision-free poses scanned ({grid} m × {headings} headings)", world.map.name, b.poses);
    println!("  largest minimum range {:.2} m at ({:.1}, {:.1}, {:.0}°); mean {:.2} m", b.max_min_range_m, b.at[0], b.at[1], b.at[2].to_degrees(), b.mean_min_range_m);
    let [p50, p90, p99] = b.min_range_percentiles_m;
    println!("  minimum range over the poses: 50th percentile {p50:.2} m, 90th {p90:.2} m, 99th {p99:.2} m");
    println!(
        "  eq. (1) per step at most {:.3} ({:.0} over {steps} steps); standing still at most {:.3} ({:.0})",
        b.per_step,
        b.per_step * f64::from(steps),
        b.standing_still_per_step,
        b.standing_still_per_step * f64::from(steps)
    );
    Ok(())
}

fn maps_list() -> Result<()> {
    for name in mapless_sim::map::BUILTIN_MAPS {
        let m = Map::builtin(name)?;
        println!("{name:<10} {:>3.0} m x {:<3.0} m  {:>2} obstacles  {} shaded  {}", m.bounds.width(), m.bounds.height(), m.obstacles.len(), m.shaded.len(), m.description);
    }
    Ok(())
}

fn maps_show(map: &str, out: &Path, px_per_m: Option<f32>) -> Result<()> {
    let m = mapless_sim::worlds::resolve(map)?;
    let ppm = px_per_m.unwrap_or_else(|| default_px_per_m(&m));
    let title = format!("{} — {:.0} m × {:.0} m", m.name, m.bounds.width(), m.bounds.height());
    let mut c = Canvas::map(&m, ppm, &title)?;
    c.footer(&format!("{} obstacles, {} shaded regions", m.obstacles.len(), m.shaded.len()))?;
    c.save_png(out)?;
    println!("wrote {}", out.display());
    Ok(())
}

fn maps_rasterize(map: &str, resolution: f64, out: &Path) -> Result<()> {
    let m = mapless_sim::worlds::resolve(map)?;
    let yaml_path = m.write_ros(out, resolution)?;
    println!("wrote {} and {} ({resolution} m per pixel)", yaml_path.with_extension("pgm").display(), yaml_path.display());
    Ok(())
}

/// The footer line of an episode picture (`mapless rollout`, evaluations).
fn episode_footer(s: &mapless_sim::EpisodeSummary, shaded_map: bool) -> String {
    let mut parts = vec![format!("{} steps", s.steps), format!("return {:.1}", s.return_), format!("EQS {}", s.eqs), format!("EES {:.2}", s.ees), format!("{:.1} m driven", s.distance_m)];
    if shaded_map {
        parts.push(format!("{:.0} s in shade", s.shaded_time_s));
    }
    if s.terminal {
        parts.push("collision".into());
    }
    parts.join("  ·  ")
}

fn rollout(a: RolloutArgs) -> Result<()> {
    let map = mapless_sim::worlds::resolve(&a.map)?;
    let mut policy = None;
    let mut cfg = match &a.policy {
        Some(name) => {
            let dir = policies::resolve(name)?;
            policy = Some(eval::load_policy(&dir.join("policy.safetensors"))?);
            train::read_run_config(&dir)?.env
        }
        None => EnvConfig { reward: RewardConfig::preset(a.reward.as_deref().unwrap_or("exploration"))?, ..EnvConfig::default() },
    };
    cfg.episode.max_steps = a.steps;
    let world = World::new(map, cfg)?;
    let mut env = Env::new(Arc::clone(&world), a.seed);
    env.record_trajectory(true);
    let mut obs = vec![0.0; world.obs_dim()];
    if let Some(p) = &policy
        && p.obs_dim() != world.obs_dim()
    {
        bail!("the policy reads {} observation values, this map's sensor gives {}", p.obs_dim(), world.obs_dim());
    }
    env.reset(&mut obs)?;
    let angles = world.cfg.sensor.beam_angles_rad();
    let mut rng = rand_pcg::Pcg64Mcg::seed_from_u64(a.seed ^ 0x5EED);
    let mut last = None;
    tracing::info!(map = %world.map.name, steps = a.steps, seed = a.seed, "rollout started");
    for _ in 0..a.steps {
        let action = match (&mut policy, a.driver) {
            (Some(p), _) => {
                let mut act = [0.0f32; 2];
                p.act(&obs, mapless_actor::ActMode::Deterministic, &mut rng, &mut act)?;
                act
            }
            (None, Driver::Wander) => mapless_sim::baseline::wander(env.ranges_m(), &angles, world.cfg.sensor.max_range_m),
            (None, Driver::Random) => [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)],
        };
        let o = env.step(action, &mut obs)?;
        last = Some(o);
        if o.done() {
            break;
        }
    }
    let s = env.summary(last);
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let png = a.out.join("trajectory.png");
    let who = a.policy.as_deref().map_or_else(|| format!("{:?}", a.driver).to_lowercase(), |p| format!("policy {p}"));
    let mut c = Canvas::map(&world.map, default_px_per_m(&world.map), &format!("{} — rollout ({who}), seed {}", world.map.name, a.seed))?;
    let traj = env.trajectory().unwrap_or(&[]);
    c.episode(&world.map, traj, env.tracker(), world.cfg.exploration.ring_width_m, s.terminal)?;
    c.footer(&episode_footer(&s, !world.map.shaded.is_empty()))?;
    c.save_png(&png)?;
    let mut json = serde_json::to_value(&s)?;
    json["map"] = world.map.name.clone().into();
    json["seed"] = a.seed.into();
    std::fs::write(a.out.join("episode.json"), serde_json::to_string_pretty(&json)?)?;
    if a.json {
        println!("{json}");
    } else {
        println!(
            "{}: {} steps ({}), return {:.1}, EQS {}, EES {:.2}, distance {:.1} m, shaded {:.1} s",
            world.map.name,
            s.steps,
            if s.terminal {
                "collision"
            } else if s.truncated {
                "step limit"
            } else {
                "stopped"
            },
            s.return_,
            s.eqs,
            s.ees,
            s.distance_m,
            s.shaded_time_s
        );
        println!("wrote {} and {}", png.display(), a.out.join("episode.json").display());
    }
    Ok(())
}

fn bench_sim(map: &str, seconds: f64, vehicles: usize, json: bool) -> Result<()> {
    use mapless_sim::bench::{SCAN_PRESETS, bench_env, measure};
    if !(seconds > 0.0) || vehicles == 0 {
        bail!("--seconds must be > 0 and --vehicles ≥ 1");
    }
    if !json {
        println!("simulator throughput, one thread, {vehicles} vehicles per step, map {map}, {seconds} s each");
    }
    for preset in SCAN_PRESETS {
        let mut env = bench_env(map, preset, RaycastMethod::Auto, vehicles)?;
        let r = measure(&mut env, Duration::from_secs_f64(seconds))?;
        if json {
            let config =
                serde_json::json!({"map": map, "beams": preset.beams, "fov_deg": preset.fov_rad.to_degrees().round(), "vehicles": vehicles, "threads": 1, "method": "auto", "seconds": r.seconds});
            bench_report(true, "sim.vehicle_steps_per_s", config, r.steps_per_s().round(), "steps/s");
        } else {
            println!("  {:<40} {:>12.0} steps/s   ({} steps, {} episodes)", preset.label, r.steps_per_s(), r.steps, r.episodes);
        }
    }
    Ok(())
}

fn bench_e2e(actors: &[usize], seconds: f64, vehicles: usize, set: &[String], json: bool) -> Result<()> {
    if !(seconds > 25.0) || actors.is_empty() || actors.contains(&0) || vehicles == 0 {
        bail!("--seconds must be > 25 (20 s of start-up are not counted), --actors and --vehicles >= 1");
    }
    let exe = std::env::current_exe()?;
    let dir = tempfile::tempdir()?;
    if !json {
        println!("local cluster (env1-sac preset, replay + learner + N actors × {vehicles} vehicles), {seconds} s each, counted after 20 s of start-up");
    }
    for &n in actors {
        let run = dir.path().join(format!("e2e-{n}"));
        eprintln!("bench e2e: {n} actor(s), {seconds} s ...");
        let mut cmd = std::process::Command::new(&exe);
        cmd.args(["train", "--preset", "env1-sac", "--force", "--actors", &n.to_string(), "--vehicles", &vehicles.to_string(), "--minutes", &(seconds / 60.0).to_string()]);
        cmd.arg("--run").arg(&run);
        for s in ["eval.episodes=0", "stop.average_return=null", "stop.average_steps=null", "replay_persistence=false"].iter().map(|s| s.to_string()).chain(set.iter().cloned()) {
            cmd.args(["--set", &s]);
        }
        let out = cmd.stdin(std::process::Stdio::null()).stderr(std::process::Stdio::null()).status()?;
        if !out.success() {
            bail!("mapless train with {n} actors failed ({out}); run it by hand to see why");
        }
        let summary: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(run.join("summary.json"))?)?;
        let steady = &summary["steady"];
        let config = serde_json::json!({"preset": "env1-sac", "actors": n, "vehicles_per_actor": vehicles, "seconds": steady["seconds"], "cores": std::thread::available_parallelism().map(|c| c.get()).unwrap_or(0)});
        bench_report(json, "e2e.env_steps_per_s", config.clone(), steady["env_steps_per_s"].as_f64().unwrap_or(f64::NAN), "steps/s");
        bench_report(json, "e2e.learner_updates_per_s", config, steady["updates_per_s"].as_f64().unwrap_or(f64::NAN), "updates/s");
    }
    Ok(())
}

fn bench_replay(seconds: f64, memory_rows: usize, json: bool) -> Result<()> {
    use mapless_replay::bench as rb;
    if !(seconds > 0.0) || memory_rows == 0 {
        bail!("--seconds must be > 0 and --memory-rows ≥ 1");
    }
    let d = Duration::from_secs_f64(seconds);
    if !json {
        println!("replay service, in-process on loopback, {} rows per insert batch, {seconds} s each", rb::BATCH_ROWS);
    }
    // Memory first: later benchmarks leave freed pages the allocator would reuse, hiding growth.
    let (rss, raw) = rb::memory(memory_rows, 17);
    let cfg = serde_json::json!({"obs_dim": 17, "rows": memory_rows, "raw_payload_bytes": raw, "resident_bytes": rss});
    bench_report(json, "replay.memory_over_raw_payload", cfg, rss as f64 / raw as f64, "ratio");
    let (lock_ms, insert_ms) = rb::snapshot_stall_ms(memory_rows)?;
    let cfg = serde_json::json!({"obs_dim": 17, "rows": memory_rows, "snapshots": 3, "insert_rows": 100});
    bench_report(json, "replay.snapshot_lock_ms", cfg.clone(), lock_ms, "ms");
    bench_report(json, "replay.insert_worst_ms_during_snapshots", cfg, insert_ms, "ms");
    for obs_dim in [17usize, 203] {
        let v = rb::first_fill_rows_per_s(obs_dim)?;
        bench_report(json, "replay.first_fill_rows_per_s", serde_json::json!({"obs_dim": obs_dim, "rows": rb::INGEST_TABLE_ROWS, "batch_rows": rb::BATCH_ROWS, "transport": "none"}), v, "rows/s");
    }
    // Ingest into a full table (every insert evicts), as in a long run.
    for obs_dim in [17usize, 203] {
        for writers in [1usize, 4, 16] {
            let v = rb::shm_ingest_rows_per_s(writers, obs_dim, d)?;
            bench_report(json, "replay.ingest_shm_rows_per_s", serde_json::json!({"obs_dim": obs_dim, "writers": writers, "batch_rows": rb::BATCH_ROWS, "writer": "thread"}), v, "rows/s");
        }
    }
    for obs_dim in [17usize, 203] {
        for writers in [1usize, 4, 16] {
            let v = rb::grpc_ingest_rows_per_s(writers, obs_dim, d);
            bench_report(json, "replay.ingest_grpc_rows_per_s", serde_json::json!({"obs_dim": obs_dim, "writers": writers, "batch_rows": rb::BATCH_ROWS}), v, "rows/s");
        }
    }
    for obs_dim in [17usize, 203] {
        let s = rb::grpc_sample(100_000, obs_dim, 128, 4, d);
        let cfg = serde_json::json!({"obs_dim": obs_dim, "batch_size": 128, "prefetch": 4, "table_rows": 100_000, "transport": "grpc"});
        bench_report(json, "replay.sample_minibatches_per_s", cfg.clone(), s.minibatches_per_s, "minibatches/s");
        bench_report(json, "replay.sample_latency_p50_us", cfg.clone(), s.p50_us, "us");
        bench_report(json, "replay.sample_latency_p99_us", cfg, s.p99_us, "us");
    }
    Ok(())
}

/// `mapless bench replay --durability`: the write-ahead log's cost under each fsync policy.
fn bench_durability(seconds: f64, dir: Option<std::path::PathBuf>, json: bool) -> Result<()> {
    use mapless_replay::FsyncPolicy;
    use mapless_replay::bench as rb;
    if !(seconds > 0.0) {
        bail!("--seconds must be > 0");
    }
    let dir = dir.unwrap_or_else(std::env::temp_dir);
    if !json {
        println!("replay write-ahead log in {}, in-process, {} rows (17-float obs) per insert, {seconds} s each", dir.display(), rb::BATCH_ROWS);
    }
    for (name, policy) in [("never", FsyncPolicy::Never), ("interval_ms_100", FsyncPolicy::IntervalMs(100)), ("always", FsyncPolicy::Always)] {
        for writers in [1usize, 4, 16] {
            let f = rb::durable_insert(policy, writers, &dir, Duration::from_secs_f64(seconds))?;
            let cfg = serde_json::json!({"fsync": name, "writers": writers, "batch_rows": rb::BATCH_ROWS, "obs_dim": 17, "dir": dir});
            bench_report(json, "replay.durable_insert_rows_per_s", cfg.clone(), f.rows_per_s.round(), "rows/s");
            bench_report(json, "replay.durable_insert_latency_p50_us", cfg.clone(), f.p50_us.round(), "us");
            bench_report(json, "replay.durable_insert_latency_p99_us", cfg.clone(), f.p99_us.round(), "us");
            bench_report(json, "replay.durable_insert_rows_per_fsync", cfg, f.rows_per_fsync.round(), "rows");
        }
    }
    Ok(())
}

/// `mapless bench learner` is the learner binary's bench (`mapless-learner bench`, the one
/// executable that links libtorch), with the same flags.
fn bench_learner(args: &[String]) -> Result<()> {
    let bin = train::sibling("mapless-learner")?;
    let status = std::process::Command::new(&bin).arg("bench").args(args).status().with_context(|| format!("running {}", bin.display()))?;
    if !status.success() {
        bail!("{} bench failed ({status})", bin.display());
    }
    Ok(())
}
