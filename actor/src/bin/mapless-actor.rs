//! `mapless-actor`: one actor process (no libtorch). Started by `mapless train` on this host,
//! or by hand / by an orchestrator on other hosts with a config file that points at the
//! replay and the learner.
//!
//! ```text
//!   mapless-actor --config run/actor.yaml --index 3 [--max-steps N] [--log-json]
//!   mapless-actor --config actor.yaml --index auto [--name NAME]   # a slot from the replay
//!   mapless-actor health 127.0.0.1:9466        # exit 0 when the actor at that /metrics acts
//! ```
//! Runs until SIGINT/SIGTERM (then sends what it holds and waits for the acknowledgements),
//! or until `--max-steps` vehicle-steps; prints its final counters as one JSON line.

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use anyhow::Context as _;
use clap::{Parser, Subcommand};
use mapless_actor::identity::{IndexArg, resolve_index};
use mapless_actor::run::{ActorConfig, incarnation_id, run};
use mapless_net::health::{HttpProbeArgs, http_probe};

#[derive(Parser)]
#[command(
    name = "mapless-actor",
    version,
    about = "A mapless actor process: vehicles, policy inference, transitions to the replay",
    args_conflicts_with_subcommands = true,
    subcommand_negates_reqs = true
)]
struct Cli {
    #[command(subcommand)]
    cmd: Option<Cmd>,
    /// Actor config (YAML; `mapless train` writes one into the run folder).
    #[arg(long, required = true)]
    config: Option<PathBuf>,
    /// This process's index (seeds and the actor id derive from it), or `auto`: register
    /// `--name` with the replay (gRPC) and take the slot it gives that name — the same slot
    /// every time, also after a restart — so identical replicas need no per-replica config.
    #[arg(long, default_value = "0")]
    index: IndexArg,
    /// The name `--index auto` registers under; stable across restarts of this actor (one
    /// name, one slot) [default: the host name, i.e. the container's].
    #[arg(long, env = "MAPLESS_ACTOR_NAME")]
    name: Option<String>,
    /// Stop after this many vehicle-steps.
    #[arg(long)]
    max_steps: Option<u64>,
    /// Run name, shown on every log line.
    #[arg(long, default_value = "")]
    run: String,
    /// Log as JSON lines.
    #[arg(long)]
    log_json: bool,
}

#[derive(Subcommand)]
enum Cmd {
    /// Asks the actor whose `metrics_listen` is ADDR whether it is acting (`GET /healthz`; an
    /// actor serves no gRPC): exit 0 if so, else 1 with the reason. For a container's
    /// HEALTHCHECK.
    Health(HttpProbeArgs),
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    if let Some(Cmd::Health(args)) = &cli.cmd {
        return http_probe("mapless-actor", args);
    }
    mapless_net::logging::init(cli.log_json, "info,iceoryx2=warn");
    mapless_net::logging::identify(&[("run", &cli.run), ("role", "actor")]);
    match main_inner(&cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            tracing::error!("{e:#}");
            ExitCode::FAILURE
        }
    }
}

fn main_inner(cli: &Cli) -> anyhow::Result<()> {
    let config = cli.config.as_ref().context("--config is required")?;
    let text = std::fs::read_to_string(config).with_context(|| format!("reading {}", config.display()))?;
    let cfg: ActorConfig = serde_yaml::from_str(&text).with_context(|| format!("parsing {}", config.display()))?;
    let stop = Arc::new(AtomicBool::new(false));
    let on_signal = Arc::clone(&stop);
    std::thread::Builder::new().name("signals".into()).spawn(move || {
        let Ok(rt) = tokio::runtime::Builder::new_current_thread().enable_all().build() else { return };
        rt.block_on(mapless_net::signals::termination());
        tracing::info!("signal received; stopping");
        on_signal.store(true, Ordering::Relaxed);
    })?;
    let Some(index) = resolve_index(&cfg, cli.index, cli.name.as_deref(), &stop)? else {
        tracing::info!("stopped before the replay gave this actor a slot");
        return Ok(());
    };
    let actor_id = incarnation_id(index);
    mapless_net::logging::identify(&[("run", &cli.run), ("role", "actor"), ("actor_id", &actor_id)]);
    tracing::info!(map = %cfg.map, vehicles = cfg.vehicles, index, "actor starting");
    let report = run(&cfg, index, &actor_id, stop, cli.max_steps)?;
    println!("{}", serde_json::to_string(&report)?);
    Ok(())
}
