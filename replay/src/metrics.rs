//! The Prometheus metrics of one table at `GET /metrics` (OpenMetrics text, written by
//! `prometheus-client` through `mapless_net::metrics::Exposition`). Every scrape reads the table's counters under its lock once (O(actors)); nothing
//! is cached, so a scrape always shows the current state.
//!
//! Series (all carry `table`; per-actor ones also `actor`):
//!
//! | name                                          | type    | meaning                                  |
//! |-----------------------------------------------|---------|------------------------------------------|
//! | `replay_up`                                   | gauge   | 1 while the service serves               |
//! | `replay_size`, `replay_capacity`              | gauge   | rows stored / most rows kept             |
//! | `replay_inserts_total`, `replay_samples_total`| counter | rows inserted / sampled                  |
//! | `replay_insert_rows_per_s`, `…sample_rows_per_s` | gauge | rates over the last ~10 s               |
//! | `replay_rate_limiter_blocked_seconds_total{side}` | counter | time callers waited on the limiter  |
//! | `replay_sample_streams_refused_total`         | counter | Sample streams refused (RESOURCE_EXHAUSTED: `max_sample_streams` open) |
//! | `replay_storage_refusals_total{op,reason}`    | counter | insert batches / priority updates the log refused: `disk_full` (RESOURCE_EXHAUSTED) or `io_error` |
//! | `replay_actor_{rows,batches,duplicate_batches,rejected_batches}_total` | counter | per actor |
//! | `replay_actor_policy_version_lag`             | gauge   | newest policy seen − this actor's        |
//! | `replay_actor_last_insert_timestamp_seconds`  | gauge   | Unix time of the actor's last stored batch (lag of live actors only: `… and (time() - this < 60)`) |
//! | `replay_actor_slots`                          | gauge   | actor names holding a slot (`RegisterActor`) |
//! | `replay_actor_registrations_total{outcome}`   | counter | registrations: `new` slot, `known` name, `refused` |
//! | `replay_auth_refusals_total{service,method,reason}` | counter | requests the token check refused: `missing_token`, `wrong_token` (UNAUTHENTICATED), `forbidden` (PERMISSION_DENIED: the token's role may not call the method) |
//!
//! The liveness gauge is `replay_up`, not `up`: Prometheus writes its own `up` series for
//! every scrape target, and a scraped sample of that name would collide with it.

use std::future::Future;
use std::sync::Arc;

use mapless_net::AuthRefusals;
use mapless_net::health::Health;
use mapless_net::metrics::{Exposition, Labels, MetricsAccess, labels};
use tokio::net::TcpListener;

use crate::actors::ActorStats;
use crate::grpc::{newest_policy_version, policy_version_lag};
use crate::registry::ActorRegistry;
use crate::table::{StorageRefusal, Table};

/// Serves `GET /metrics` for `table`, the actor slots of `registry` and the gRPC service's
/// token-check `refusals`, and `GET /healthz` for `health`, on `listener` until `shutdown`
/// resolves (`mapless_net::metrics`, the exporter every process uses).
pub async fn serve(
    listener: TcpListener,
    table: Arc<Table>,
    registry: Arc<ActorRegistry>,
    refusals: AuthRefusals,
    health: Health,
    access: MetricsAccess,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> std::io::Result<()> {
    mapless_net::metrics::serve(listener, Arc::new(move || render(&table, &registry, &refusals)), health, access, shutdown).await
}

/// The exposition text for `table`, `registry` and `refusals`.
pub fn render(table: &Table, registry: &ActorRegistry, refusals: &AuthRefusals) -> String {
    let slots = registry.counts();
    let info = table.info();
    let mut actors: Vec<(String, ActorStats)> = table.actors().into_iter().collect();
    actors.sort_by(|a, b| a.0.cmp(&b.0));
    let newest = newest_policy_version(actors.iter().map(|(_, a)| a));
    let t = info.table.as_str();
    let rl = info.rate_limiter.unwrap_or_default();
    let table_only = |v: f64| [(labels([("table", t)]), v)];
    let per_actor = |f: &dyn Fn(&ActorStats) -> f64| -> Vec<(Labels, f64)> { actors.iter().map(|(id, a)| (labels([("table", t), ("actor", id)]), f(a))).collect() };
    let mut x = Exposition::new();
    x.gauges("replay_up", "1 while the replay service is serving.", table_only(1.0))
        .gauges("replay_size", "Rows stored in the table.", table_only(info.size as f64))
        .gauges("replay_capacity", "Most rows the table keeps; the oldest are evicted first.", table_only(info.capacity as f64))
        .counters("replay_inserts", "Rows inserted (duplicates excluded).", table_only(info.inserts_total as f64))
        .counters("replay_samples", "Rows sampled (a minibatch of 128 counts 128).", table_only(info.samples_total as f64))
        .gauges("replay_insert_rows_per_s", "Inserted rows per second over the last ~10 s.", table_only(info.inserts_per_s))
        .gauges("replay_sample_rows_per_s", "Sampled rows per second over the last ~10 s.", table_only(info.samples_per_s))
        .counters(
            "replay_rate_limiter_blocked_seconds",
            "Seconds inserts or samples spent waiting on the rate limiter.",
            [(labels([("table", t), ("side", "insert")]), rl.inserts_blocked_ms as f64 / 1e3), (labels([("table", t), ("side", "sample")]), rl.samples_blocked_ms as f64 / 1e3)],
        )
        .counters("replay_sample_streams_refused", "Sample streams refused with RESOURCE_EXHAUSTED because max_sample_streams were open.", table_only(table.sample_streams_refused() as f64))
        .counters(
            "replay_storage_refusals",
            "Insert batches (op=insert) and priority updates (op=priorities) refused because the log could not store them: reason=disk_full (RESOURCE_EXHAUSTED; accepted again once space is freed) or io_error (a failed write or fsync).",
            [false, true].into_iter().flat_map(|priorities| {
                let op = if priorities { "priorities" } else { "insert" };
                StorageRefusal::ALL.map(|r| (labels([("table", t), ("op", op), ("reason", r.label())]), table.storage_refusals(priorities, r) as f64))
            }),
        )
        .counters("replay_actor_rows", "Rows inserted per actor.", per_actor(&|a| a.rows as f64))
        .counters("replay_actor_batches", "Batches inserted per actor (duplicates excluded).", per_actor(&|a| a.batches as f64))
        .counters("replay_actor_duplicate_batches", "Batches acknowledged as duplicates (retransmissions) per actor.", per_actor(&|a| a.duplicate_batches as f64))
        .counters("replay_actor_rejected_batches", "Batches refused as invalid per actor.", per_actor(&|a| a.rejected_batches as f64))
        .gauges("replay_actor_policy_version_lag", "Newest policy_version seen across actors minus this actor's newest.", per_actor(&|a| policy_version_lag(newest, a) as f64))
        .gauges(
            "replay_actor_last_insert_timestamp_seconds",
            "Unix time of this actor's last stored batch (0 before one): an actor that stopped inserting keeps its lag, so a console filters on this.",
            per_actor(&|a| a.last_insert_unix_ms as f64 / 1000.0),
        )
        .gauges("replay_actor_slots", "Actor names holding a slot (RegisterActor; mapless-actor --index auto).", table_only(slots.registered as f64))
        .counters(
            "replay_actor_registrations",
            "RegisterActor calls: a new slot given out, a known name answered, or refused (bad name, no slot left, slot file not written).",
            [("new", slots.new), ("known", slots.known), ("refused", slots.refused)].map(|(outcome, n)| (labels([("table", t), ("outcome", outcome)]), n as f64)),
        );
    refusals.write(&mut x, "replay_auth_refusals");
    x.text()
}
