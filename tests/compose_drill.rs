//! The compose cluster as its users launch it: `deploy/smoke.sh` builds the images (debug
//! binaries here, layers reused on a rerun) and drills `docker-compose up --scale actor=4`:
//! health-ordered start of non-root containers, learner updates reaching the actors, four
//! distinct actor ids, Prometheus scraping every replica with the metrics token, a killed actor
//! restarted on its slot, scaling to 6 (Prometheus finds the new replicas) and back to 2, a
//! replay restart that keeps its rows, an actor cut off the network and reconnected,
//! exactly-once delivery per actor, a final checkpoint and a teardown that leaves nothing
//! behind. Then `deploy/swarm.sh` drills the Swarm stack (deploy/stack.yaml) on the same images
//! in a single-node swarm: `docker stack deploy`, healthy non-root tasks, replicas named by task
//! slot, `docker service scale` to 4 with Prometheus finding them, a killed task replaced on its
//! slot, and `docker stack rm` leaving nothing (the swarm is left again if the drill made it).
//! It needs a Docker engine, root (it kills an actor's process and reads the replay's
//! unpublished `/metrics` from inside its container's network namespace) and apt-get (the
//! Prometheus image is Debian's package); where no engine answers `docker info` it says so and
//! skips.

use std::path::Path;
use std::process::Command;

#[test]
fn the_compose_cluster_and_the_swarm_stack_scale_survive_faults_and_deliver_exactly_once() {
    match Command::new("docker").args(["info", "--format", "{{.ServerVersion}}"]).output() {
        Ok(out) if out.status.success() => {}
        Ok(out) => {
            eprintln!("skipped: no Docker engine answers `docker info` ({}); the compose drill (deploy/smoke.sh) needs one", String::from_utf8_lossy(&out.stderr).trim());
            return;
        }
        Err(e) => {
            eprintln!("skipped: no `docker` command ({e}); the compose drill (deploy/smoke.sh) needs a Docker engine");
            return;
        }
    }
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).parent().expect("the workspace root");
    // The drills write why they failed here (deploy/lib.sh's `failed`), for the panic message:
    // the failure must not be only somewhere above the cluster's log tail.
    let failures = tempfile::NamedTempFile::new().expect("a temporary file");
    let status = Command::new("bash")
        .arg(root.join("deploy/smoke.sh"))
        // The suite's own (debug) binaries: no release build just for the images.
        .env("MAPLESS_PROFILE", "dev")
        .env("MAPLESS_TAG", "suite")
        .env("MAPLESS_DRILL_FAILURE_FILE", failures.path())
        .status()
        .expect("bash runs deploy/smoke.sh");
    assert!(status.success(), "deploy/smoke.sh failed:\n{}(its steps and the cluster's last log lines are above)", why(failures.path()));
    let status = Command::new("bash")
        .arg(root.join("deploy/swarm.sh"))
        // The images deploy/smoke.sh has just built.
        .env("SKIP_IMAGES", "1")
        .env("MAPLESS_TAG", "suite")
        .env("MAPLESS_DRILL_FAILURE_FILE", failures.path())
        .status()
        .expect("bash runs deploy/swarm.sh");
    assert!(status.success(), "deploy/swarm.sh failed:\n{}(its steps and the services' last log lines are above)", why(failures.path()));
}

/// What a drill recorded as its failures, or a line saying it recorded none.
fn why(path: &Path) -> String {
    match std::fs::read_to_string(path) {
        Ok(text) if !text.trim().is_empty() => text,
        _ => "(no failure recorded: the drill ended before its checks)\n".to_owned(),
    }
}
