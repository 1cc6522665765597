//! `mapless-actor health ADDR`, the probe a container's HEALTHCHECK runs against an actor's
//! `/healthz` (an actor serves no gRPC; `/healthz` sits beside its `/metrics`): exit 0 only
//! while the process is serving, 1 with the reason while it starts or drains, or when nothing
//! answers.

use std::net::SocketAddr;
use std::process::{Command, Output};
use std::sync::Arc;

use mapless_net::health::Health;
use mapless_net::metrics;
use tokio::sync::watch;

/// `mapless-actor health ADDR`, with no `MAPLESS_HEALTH_*` from the environment.
fn probe(addr: SocketAddr) -> Output {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_mapless-actor"));
    cmd.arg("health").arg(addr.to_string());
    for (k, _) in std::env::vars() {
        if k.starts_with("MAPLESS_HEALTH_") {
            cmd.env_remove(k);
        }
    }
    cmd.output().expect("run mapless-actor health")
}

fn text(o: &Output) -> String {
    format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr))
}

#[test]
fn the_probe_exits_0_only_while_the_actor_serves() {
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build().expect("runtime");
    let (stop_tx, stop_rx) = watch::channel(false);
    let health = Health::new();
    let addr = metrics::spawn(&rt, "127.0.0.1:0".parse().expect("address"), Arc::new(String::new), health.clone(), metrics::MetricsAccess::open(), stop_rx).expect("metrics endpoint");

    let starting = probe(addr);
    assert_eq!(starting.status.code(), Some(1), "{}", text(&starting));
    assert!(text(&starting).contains("NOT_SERVING"), "{}", text(&starting));

    health.serve();
    let serving = probe(addr);
    assert!(serving.status.success(), "{}", text(&serving));
    assert!(String::from_utf8_lossy(&serving.stdout).starts_with("SERVING"), "{}", text(&serving));

    health.drain();
    let draining = probe(addr);
    assert_eq!(draining.status.code(), Some(1), "{}", text(&draining));
    assert!(text(&draining).contains("NOT_SERVING"), "{}", text(&draining));

    let _ = stop_tx.send(true);
    rt.shutdown_timeout(std::time::Duration::from_secs(5));
    let gone = probe(addr);
    assert_eq!(gone.status.code(), Some(1), "{}", text(&gone));
    assert!(text(&gone).contains("unreachable"), "{}", text(&gone));
}
