//! The Prometheus `/metrics` exporter of every mapless process (replay, learner, actors):
//! OpenMetrics text written by `prometheus-client` from an [`Exposition`] built afresh on each
//! scrape (the values are read where they live — the replay's table, a process's counters — so
//! nothing is cached), served over plain HTTP/1 by axum; beside it `GET /healthz`, the
//! process's [`Health`]: 200 `SERVING`, else 503 `NOT_SERVING`.

use std::future::Future;
use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::AtomicU64;

use axum::extract::State;
use axum::http::StatusCode;
use axum::http::header::CONTENT_TYPE;
use axum::response::IntoResponse;
use axum::routing::get;
use prometheus_client::encoding::{EncodeLabelValue, LabelValueEncoder};
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::registry::Registry;
use tokio::net::TcpListener;
use tokio::sync::watch;

use crate::health::Health;

/// Content type of the OpenMetrics text format (what Prometheus asks for first).
pub const CONTENT_TYPE_TEXT: &str = "application/openmetrics-text; version=1.0.0; charset=utf-8";

/// Renders the exposition text on each scrape.
pub type Render = Arc<dyn Fn() -> String + Send + Sync>;

/// Serves `render()` at `GET /metrics` and `health` at `GET /healthz` on `listener` until
/// `shutdown` resolves. `render` runs on the blocking pool, so it may take a std lock (the
/// replay's table).
pub async fn serve(listener: TcpListener, render: Render, health: Health, shutdown: impl Future<Output = ()> + Send + 'static) -> std::io::Result<()> {
    let app = axum::Router::new().route("/metrics", get(scrape)).with_state(render).route("/healthz", get(healthz)).with_state(health);
    axum::serve(listener, app).with_graceful_shutdown(shutdown).await
}

async fn healthz(State(health): State<Health>) -> impl IntoResponse {
    if health.is_serving() { (StatusCode::OK, "SERVING\n") } else { (StatusCode::SERVICE_UNAVAILABLE, "NOT_SERVING\n") }
}

async fn scrape(State(render): State<Render>) -> impl IntoResponse {
    let body = tokio::task::spawn_blocking(move || render()).await.unwrap_or_else(|e| format!("# render failed: {e}\n"));
    ([(CONTENT_TYPE, CONTENT_TYPE_TEXT)], body)
}

/// Binds `addr` (port 0: any free port; loopback only), logs the address, and serves `render`
/// and `health` on `rt` until `stop` turns true. Returns the bound address. For the actor and
/// learner processes, whose metrics are for the host they run on.
pub fn spawn(rt: &tokio::runtime::Runtime, addr: SocketAddr, render: Render, health: Health, mut stop: watch::Receiver<bool>) -> std::io::Result<SocketAddr> {
    if !addr.ip().is_loopback() {
        return Err(std::io::Error::new(std::io::ErrorKind::PermissionDenied, format!("metrics: refusing non-loopback address {addr}")));
    }
    let listener = rt.block_on(TcpListener::bind(addr))?;
    let bound = listener.local_addr()?;
    tracing::info!(addr = %bound, "metrics on /metrics");
    rt.spawn(async move {
        let stopped = async move {
            let _ = stop.wait_for(|s| *s).await;
        };
        if let Err(e) = serve(listener, render, health, stopped).await {
            tracing::warn!(error = %e, "metrics endpoint stopped");
        }
    });
    Ok(bound)
}

/// A label value, escaped as the text format requires (backslash, double quote, newline):
/// label values such as actor ids come from peers, and `prometheus-client` writes values as
/// they are.
#[derive(Clone, Debug, Hash, PartialEq, Eq)]
pub struct LabelValue(pub String);

impl EncodeLabelValue for LabelValue {
    fn encode(&self, encoder: &mut LabelValueEncoder) -> std::fmt::Result {
        use std::fmt::Write as _;
        encoder.write_str(&self.0.replace('\\', r"\\").replace('"', "\\\"").replace('\n', r"\n"))
    }
}

/// A series' labels: `(name, value)` pairs.
pub type Labels = Vec<(&'static str, LabelValue)>;

/// `[(name, value)]` as [`Labels`].
pub fn labels<const N: usize>(pairs: [(&'static str, &str); N]) -> Labels {
    pairs.into_iter().map(|(k, v)| (k, LabelValue(v.to_owned()))).collect()
}

/// `prometheus-client` ends every help text with a period of its own.
fn help_text(help: &str) -> &str {
    help.strip_suffix('.').unwrap_or(help)
}

/// The metrics of one scrape: families of gauges and counters with their samples, encoded as
/// OpenMetrics text by `prometheus-client`.
#[derive(Default)]
pub struct Exposition {
    registry: Registry,
}

impl Exposition {
    pub fn new() -> Self {
        Self::default()
    }

    /// A gauge family `name` with one sample per `(labels, value)`.
    pub fn gauges(&mut self, name: &str, help: &str, samples: impl IntoIterator<Item = (Labels, f64)>) -> &mut Self {
        let family = Family::<Labels, Gauge<f64, AtomicU64>>::default();
        for (l, v) in samples {
            family.get_or_create(&l).set(v);
        }
        self.registry.register(name, help_text(help), family);
        self
    }

    /// A counter family; `name` is the family's, without the `_total` the samples carry
    /// (`replay_inserts` → `replay_inserts_total`).
    pub fn counters(&mut self, name: &str, help: &str, samples: impl IntoIterator<Item = (Labels, f64)>) -> &mut Self {
        let family = Family::<Labels, Counter<f64, AtomicU64>>::default();
        for (l, v) in samples {
            family.get_or_create(&l).inc_by(v);
        }
        self.registry.register(name, help_text(help), family);
        self
    }

    /// One unlabelled gauge.
    pub fn gauge(&mut self, name: &str, help: &str, value: f64) -> &mut Self {
        let g = Gauge::<f64, AtomicU64>::default();
        g.set(value);
        self.registry.register(name, help_text(help), g);
        self
    }

    /// One unlabelled counter (`name` without `_total`).
    pub fn counter(&mut self, name: &str, help: &str, value: f64) -> &mut Self {
        let c = Counter::<f64, AtomicU64>::default();
        c.inc_by(value);
        self.registry.register(name, help_text(help), c);
        self
    }

    /// The OpenMetrics text, `# EOF` included.
    pub fn text(&self) -> String {
        let mut out = String::new();
        // Writing into a String cannot fail.
        let _ = prometheus_client::encoding::text::encode(&mut out, &self.registry);
        out
    }
}

/// One benchmark figure on stdout, as every `mapless bench …` prints it: a JSON object
/// `{"bench", "config", "value", "unit"}` per line with `json`, else an aligned text line.
pub fn bench_report(json: bool, bench: &str, config: serde_json::Value, value: f64, unit: &str) {
    if json {
        println!("{}", serde_json::json!({"bench": bench, "config": config, "value": (value * 100.0).round() / 100.0, "unit": unit}));
    } else {
        println!("  {bench:<34} {:<58} {value:>14.1} {unit}", config.to_string());
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};

    #[test]
    fn a_scrape_gets_the_rendered_text_and_other_paths_404() {
        let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build().unwrap();
        let (stop_tx, stop_rx) = watch::channel(false);
        let render: Render = Arc::new(|| {
            let mut x = Exposition::new();
            x.counter("x", "Things.", 3.0).gauges("y", "Levels.", [(labels([("actor", "a\"b\\c\nd")]), 0.5)]);
            x.text()
        });
        let health = Health::new();
        assert!(spawn(&rt, "0.0.0.0:0".parse().unwrap(), render.clone(), health.clone(), stop_rx.clone()).is_err(), "non-loopback is refused");
        let addr = spawn(&rt, "127.0.0.1:0".parse().unwrap(), render, health.clone(), stop_rx).unwrap();
        let get = |path: &'static str| {
            rt.block_on(async move {
                let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
                s.write_all(format!("GET {path} HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n").as_bytes()).await.unwrap();
                let mut out = String::new();
                s.read_to_string(&mut out).await.unwrap();
                out
            })
        };
        let ok = get("/metrics");
        assert!(ok.starts_with("HTTP/1.1 200"), "{ok}");
        assert!(ok.to_ascii_lowercase().contains("content-type: application/openmetrics-text"), "{ok}");
        assert!(ok.contains("# HELP x Things.\n# TYPE x counter\nx_total 3.0\n"), "{ok}");
        assert!(ok.contains(r#"y{actor="a\"b\\c\nd"} 0.5"#), "label values are escaped: {ok}");
        assert!(ok.trim_end().ends_with("# EOF"), "{ok}");
        assert!(get("/nope").starts_with("HTTP/1.1 404"));
        let _ = stop_tx.send(true);
    }

    #[test]
    fn healthz_answers_the_phase_and_the_probe_reads_it() {
        let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build().unwrap();
        let (stop_tx, stop_rx) = watch::channel(false);
        let health = Health::new();
        let addr = spawn(&rt, "127.0.0.1:0".parse().unwrap(), Arc::new(String::new), health.clone(), stop_rx).unwrap();
        let status = || rt.block_on(crate::health::get_healthz(addr)).unwrap();
        assert_eq!(status(), 503, "starting");
        health.serve();
        assert_eq!(status(), 200, "serving");
        health.drain();
        assert_eq!(status(), 503, "draining");
        let _ = stop_tx.send(true);
    }
}
