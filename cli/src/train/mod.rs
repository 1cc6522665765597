//! `mapless train`: a whole actor–learner cluster on this machine, supervised.
//!
//! ```text
//!   mapless train ─┬─ mapless-replay  (run/replay.yaml; persists to run/replay/)
//!   (supervisor,   ├─ mapless-learner (run/learner.yaml; checkpoints, TensorBoard, policy file)
//!    stats         └─ mapless-actor × N (run/actor.yaml) ──iceoryx2──► replay
//!    collector)         ▲ weights (gRPC) ── learner        └─ episodes (gRPC) ──► supervisor
//! ```
//!
//! The supervisor restarts a child that dies (actors at once; the learner from its newest
//! checkpoint; the replay from its log), prints a progress line, writes `episodes.csv` and
//! `curves.png` as the run goes, stops on the preset's criteria (order-W moving averages of
//! return and steps, or K episodes, or a time limit) or Ctrl-C, then stops the children in
//! order (actors, learner with a final checkpoint, replay), keeps the policy that met the
//! criteria or, clearly safer than the last (or with `stop.keep_best_when: safer`, safer),
//! the best one their evaluations judged (`stop.keep_best`), evaluates it and writes `summary.json`.
//!
//! One file a concept: `config.rs` (presets, `--set`, resolution), `folder.rs` (the run
//! folder), `children.rs` (one child process), `restart.rs` (the restart policies),
//! `cluster.rs` (the children together: start, supervise, stop), `episodes.rs`
//! (`episodes.csv`), `status.rs` (what the supervisor knows of the run now), `progress.rs`
//! (what it prints), `evaluate.rs` (evaluations, `evals.csv`), `curves.rs` (`curves.png`),
//! `stop.rs` (the stop rules), `summary.rs` (`summary.json`); this file runs them in order.
//! `monitor.rs` runs the same pieces beside a cluster it did not start (`mapless monitor`).

use std::time::{Duration, Instant};

use anyhow::Result;

mod average;
mod children;
mod cluster;
pub mod config;
mod curves;
pub(crate) mod episodes;
mod evaluate;
mod folder;
mod monitor;
mod progress;
mod restart;
mod status;
mod stop;
mod summary;

pub(crate) use children::{sibling, start_service};
#[cfg(test)]
pub(crate) use config::PRESETS;
pub(crate) use config::{TrainArgs, preset_config, read_run_config};
pub(crate) use monitor::{MonitorArgs, monitor};
pub(crate) use stop::INTERRUPTED;
pub(crate) use summary::Summary;

use cluster::{Binaries, Cluster};
use config::{TrainConfig, load_config};
use curves::{Curves, draw_curves};
use episodes::Episodes;
use evaluate::Evaluations;
use folder::RunFolder;
use progress::{Figures, Progress};
use status::Status;
use stop::{Interrupt, StopRules};
use summary::End;

/// Runs `mapless train`.
pub fn train(args: &TrainArgs, log_json: bool) -> Result<()> {
    let (cfg, dir, resuming) = load_config(args)?;
    if args.print_config {
        print!("{}", serde_yaml::to_string(&cfg)?);
        return Ok(());
    }
    let run = RunFolder::prepare(&dir, &cfg, resuming, args.force)?;
    mapless_net::logging::identify(&[("run", &run.name), ("role", "supervisor")]);
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).thread_name("train-io").enable_all().build()?;
    let interrupt = Interrupt::listen(&rt);
    let bins = Binaries::find()?;
    progress::opening(&cfg, &run.dir, &run.logs);
    let mut cluster = Cluster::start(&cfg, &run, resuming, log_json, &bins, rt)?;

    let mut episodes = Episodes::open(&run.dir)?;
    let mut status = Status::new(episodes.offset_s, cfg.stop.minutes);
    let mut rules = StopRules::new(&cfg.stop, episodes.before, cfg.env.episode.max_steps);
    let mut evals = Evaluations::new(&cfg, &run.dir);
    let mut curves = Curves::new(&run.dir, episodes.rows.len());
    let mut progress = Progress::new(status.elapsed());
    let mut polled: Option<Instant> = None;
    loop {
        for event in cluster.learner_said() {
            status.learner_said(&event);
        }
        for e in cluster.episodes() {
            episodes.record(e, status.wall_s())?;
        }
        // The replay's counts and the progress line, once a second.
        if polled.is_none_or(|t| t.elapsed() >= Duration::from_secs(1)) {
            status.replay_said(cluster.replay_info().as_ref());
            progress.show(&figures(&cfg, &status, &episodes, &mut cluster), status.elapsed());
            polled = Some(Instant::now());
        }
        evals.progress_tick(&status, progress.above())?;
        curves.tick(&cfg, &episodes.rows);
        // Stop rules: the moving averages, backed (when the preset asks) by an evaluation of the
        // newest policy that reaches the paper's exploration figures; a signal; the limits.
        if let Some((at, s)) = evals.gate_ended(&status, progress.above())? {
            progress.above().suspend(|| rules.judge(at, s));
        }
        let at = || status.milestone(episodes.count());
        evals.start_due(rules.averages(&episodes.rows, at), at)?;
        if rules.stops(interrupt.came(), episodes.count(), status.wall_s()) {
            break;
        }
        cluster.supervise(progress.above())?;
        std::thread::sleep(Duration::from_millis(100));
    }
    progress.finish();
    let stopped_at = status.counters();
    eprintln!("stopping: {}", rules.stopped_because());

    let actor_restarts = cluster.actor_restarts();
    let late = cluster.stop(|e| episodes.record(e, status.wall_s()))?;
    draw_curves(&run.dir, &cfg, &episodes.rows);
    evals.finish_progress()?;
    if let Some((at, s)) = evals.gate_after_stop(&status)? {
        rules.judge_after_stop(at, s);
    }
    let kept_policy = if rules.met_by_evaluation() {
        evals.keep_the_policy_that_met_the_criteria()?;
        "the one that met the criteria (criteria_evaluation)".to_owned()
    } else if cfg.stop.keep_best {
        evals.keep_the_best_policy(&status)?
    } else {
        evaluate::LAST.to_owned()
    };
    let evaluation = evals.final_evaluation(&status)?;
    let learner = status.learner_end(&late);
    let end = End { wall_s: status.wall_s(), env_steps: status.env_steps, learner, actor_restarts, steady: status.steady_rates(stopped_at), evaluation, kept_policy: Some(kept_policy) };
    let summary = Summary::new(&run.dir, &cfg, &episodes, rules.outcome(), end);
    summary.write(&run.dir)?;
    progress::closing(&summary, &run.dir);
    Ok(())
}

/// What the progress line shows now.
fn figures(cfg: &TrainConfig, status: &Status, episodes: &Episodes, cluster: &mut Cluster) -> Figures {
    let (average_return, average_steps) = episodes.averages(cfg.stop.window);
    let (actors_alive, actors) = cluster.actors_alive();
    Figures {
        episodes: episodes.count(),
        window: cfg.stop.window,
        average_return,
        average_steps,
        updates: status.learner.updates,
        updates_per_s: status.learner.updates_per_s,
        env_steps_per_s: status.env_rate.per_s,
        replay_size: status.replay_size,
        policy_version: status.learner.weights_version,
        actors_alive,
        actors,
        restarts: cluster.restarts(),
    }
}
