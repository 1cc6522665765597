//! Which index an actor process runs as. The index picks the process's random streams (its
//! simulator and exploration seeds derive from `seed` and the index, see [`crate::run::run`])
//! and its actor-id prefix (`actor-<index>-…`, [`crate::run::incarnation_id`]).
//!
//! ```text
//!   --index N     ─► N                                   (`mapless train` numbers its actors)
//!   --index auto  ─► name (--name, MAPLESS_ACTOR_NAME, or the host name)
//!                    ─► RegisterActor(name) at the replay ─► the name's slot
//! ```
//!
//! `auto` is for replicas started from one command line (`docker-compose up --scale
//! actor=N`): each container has its own host name, the replay gives each name its own slot
//! and keeps it, so replicas draw different seeds and a restarted container gets its slot back.
//! Each incarnation still sends under an actor id of its own (pid and start time after the
//! slot), so the replay's exactly-once bookkeeping never confuses it with its predecessor.

use std::str::FromStr;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use anyhow::{Context as _, bail};
use mapless_net::insert::sleep_unless_stopped;
use mapless_net::register::{is_retryable, register_actor};

use crate::run::{ActorConfig, ReplayTarget};

/// The `--index` of `mapless-actor`: a number, or `auto` (a slot from the replay).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum IndexArg {
    Fixed(usize),
    Auto,
}

impl FromStr for IndexArg {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "auto" => Ok(IndexArg::Auto),
            n => n.parse().map(IndexArg::Fixed).map_err(|_| format!("`{s}` is neither a process index (0, 1, …) nor `auto`")),
        }
    }
}

/// First wait between registration attempts while the replay cannot be reached; doubles up to
/// [`RETRY_MAX`]. Containers of one compose project start together, so the replay may not
/// listen yet when an actor starts.
const RETRY_START: Duration = Duration::from_millis(200);
/// Longest wait between registration attempts.
const RETRY_MAX: Duration = Duration::from_secs(5);

/// This host's name: the container id (or the `hostname:` set in a compose file) inside a
/// container. Read from the kernel, so it works in an image without a shell or `/etc`.
pub fn host_name() -> Option<String> {
    let from_kernel = std::fs::read_to_string("/proc/sys/kernel/hostname").ok().map(|s| s.trim().to_owned());
    from_kernel.filter(|s| !s.is_empty()).or_else(|| std::env::var("HOSTNAME").ok().filter(|s| !s.is_empty()))
}

/// The index this process runs as: `Fixed(n)` is `n`; `Auto` registers `name` (or, without
/// one, [`host_name`]) with the replay of `cfg` and returns its slot, retrying while the replay
/// is unreachable. Returns `None` when `stop` turned true before an answer came.
pub fn resolve_index(cfg: &ActorConfig, index: IndexArg, name: Option<&str>, stop: &AtomicBool) -> anyhow::Result<Option<usize>> {
    let IndexArg::Fixed(n) = index else {
        let name = match name {
            Some(n) => n.to_owned(),
            None => host_name().context("--index auto: no host name to register under; pass --name")?,
        };
        return Ok(register(cfg, &name, stop)?.map(|slot| slot as usize));
    };
    Ok(Some(n))
}

fn register(cfg: &ActorConfig, name: &str, stop: &AtomicBool) -> anyhow::Result<Option<u32>> {
    let uri = match &cfg.replay {
        ReplayTarget::Grpc { uri } | ReplayTarget::Shm { register: Some(uri), .. } => uri,
        ReplayTarget::Shm { register: None, .. } => {
            bail!("--index auto registers with the replay over gRPC, but this actor reaches the replay over shared memory with no `replay.register` address; add it, or pass --index N")
        }
    };
    let endpoint = cfg.security.endpoint(uri)?;
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
    let mut wait = RETRY_START;
    loop {
        if stop.load(Ordering::Relaxed) {
            return Ok(None);
        }
        match rt.block_on(register_actor(&endpoint, name)) {
            Ok(r) => {
                tracing::info!(name, slot = r.slot, known = r.known, registered = r.registered, "registered with the replay");
                return Ok(Some(r.slot));
            }
            Err(e) if is_retryable(&e) => {
                tracing::warn!(name, error = %e, retry_in = ?wait, "cannot register with the replay yet");
                sleep_unless_stopped(wait, stop);
                wait = (wait * 2).min(RETRY_MAX);
            }
            Err(e) => return Err(anyhow::Error::new(e).context(format!("registering actor name {name:?} with the replay"))),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn index_is_a_number_or_auto() {
        assert_eq!("3".parse::<IndexArg>(), Ok(IndexArg::Fixed(3)));
        assert_eq!("auto".parse::<IndexArg>(), Ok(IndexArg::Auto));
        assert!("-1".parse::<IndexArg>().unwrap_err().contains("neither"));
        assert!("Auto".parse::<IndexArg>().is_err());
    }

    #[test]
    fn this_host_has_a_name() {
        let name = host_name().expect("a host name");
        mapless_proto::check_actor_name(&name).expect("a name the replay accepts");
    }
}
