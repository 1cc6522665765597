//! Prometheus text exposition (format 0.0.4) of one table at `GET /metrics`, over plain
//! HTTP/1. Every scrape reads the table's counters under its lock once (O(actors)); nothing
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
//! | `replay_actor_{rows,batches,duplicate_batches,rejected_batches}_total` | counter | per actor |
//! | `replay_actor_policy_version_lag`             | gauge   | newest policy seen − this actor's        |
//!
//! The liveness gauge is `replay_up`, not `up`: Prometheus writes its own `up` series for
//! every scrape target, and a scraped sample of that name would collide with it.

use std::fmt::Write as _;
use std::future::Future;
use std::sync::Arc;

use tokio::net::TcpListener;

use crate::actors::ActorStats;
use crate::grpc::{newest_policy_version, policy_version_lag};
use crate::table::Table;

/// Serves `GET /metrics` for `table` on `listener` until `shutdown` resolves
/// (`mapless_net::metrics`, the exporter every process uses).
pub async fn serve(listener: TcpListener, table: Arc<Table>, shutdown: impl Future<Output = ()> + Send + 'static) -> std::io::Result<()> {
    mapless_net::metrics::serve(listener, Arc::new(move || render(&table)), shutdown).await
}

/// The exposition text for `table`.
pub fn render(table: &Table) -> String {
    let info = table.info();
    let mut actors: Vec<(String, ActorStats)> = table.actors().into_iter().collect();
    actors.sort_by(|a, b| a.0.cmp(&b.0));
    let newest = newest_policy_version(actors.iter().map(|(_, a)| a));
    let t = escape(&info.table);
    let rl = info.rate_limiter.unwrap_or_default();
    let mut out = String::with_capacity(2048 + actors.len() * 600);
    let mut family = |name: &str, kind: &str, help: &str, samples: &[(String, f64)]| {
        let _ = writeln!(out, "# HELP {name} {help}");
        let _ = writeln!(out, "# TYPE {name} {kind}");
        for (labels, value) in samples {
            let _ = writeln!(out, "{name}{{{labels}}} {}", number(*value));
        }
    };
    let table_only = |v: f64| vec![(format!("table=\"{t}\""), v)];
    family("replay_up", "gauge", "1 while the replay service is serving.", &table_only(1.0));
    family("replay_size", "gauge", "Rows stored in the table.", &table_only(info.size as f64));
    family("replay_capacity", "gauge", "Most rows the table keeps; the oldest are evicted first.", &table_only(info.capacity as f64));
    family("replay_inserts_total", "counter", "Rows inserted (duplicates excluded).", &table_only(info.inserts_total as f64));
    family("replay_samples_total", "counter", "Rows sampled (a minibatch of 128 counts 128).", &table_only(info.samples_total as f64));
    family("replay_insert_rows_per_s", "gauge", "Inserted rows per second over the last ~10 s.", &table_only(info.inserts_per_s));
    family("replay_sample_rows_per_s", "gauge", "Sampled rows per second over the last ~10 s.", &table_only(info.samples_per_s));
    family(
        "replay_rate_limiter_blocked_seconds_total",
        "counter",
        "Seconds inserts or samples spent waiting on the rate limiter.",
        &[(format!("table=\"{t}\",side=\"insert\""), rl.inserts_blocked_ms as f64 / 1e3), (format!("table=\"{t}\",side=\"sample\""), rl.samples_blocked_ms as f64 / 1e3)],
    );
    let per_actor = |f: &dyn Fn(&ActorStats) -> f64| -> Vec<(String, f64)> { actors.iter().map(|(id, a)| (format!("table=\"{t}\",actor=\"{}\"", escape(id)), f(a))).collect() };
    family("replay_actor_rows_total", "counter", "Rows inserted per actor.", &per_actor(&|a| a.rows as f64));
    family("replay_actor_batches_total", "counter", "Batches inserted per actor (duplicates excluded).", &per_actor(&|a| a.batches as f64));
    family("replay_actor_duplicate_batches_total", "counter", "Batches acknowledged as duplicates (retransmissions) per actor.", &per_actor(&|a| a.duplicate_batches as f64));
    family("replay_actor_rejected_batches_total", "counter", "Batches refused as invalid per actor.", &per_actor(&|a| a.rejected_batches as f64));
    family("replay_actor_policy_version_lag", "gauge", "Newest policy_version seen across actors minus this actor's newest.", &per_actor(&|a| policy_version_lag(newest, a) as f64));
    out
}

/// A label value as the text format wants it: backslash, double quote and newline escaped.
fn escape(value: &str) -> String {
    value.replace('\\', r"\\").replace('"', "\\\"").replace('\n', r"\n")
}

/// Integers without a fraction, everything else in Rust's shortest round-trip form.
fn number(v: f64) -> String {
    if v.is_finite() && v.fract() == 0.0 && v.abs() < 9.0e15 { format!("{}", v as i64) } else { format!("{v}") }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn label_values_are_escaped() {
        assert_eq!(escape(r#"a"b\c"#), r#"a\"b\\c"#);
        assert_eq!(escape("x\ny"), r"x\ny");
    }

    #[test]
    fn numbers_print_as_prometheus_reads_them() {
        assert_eq!(number(3.0), "3");
        assert_eq!(number(0.25), "0.25");
        assert_eq!(number(f64::NAN), "NaN");
    }
}
