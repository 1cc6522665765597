//! The Prometheus `/metrics` exporter of every mapless process (replay, learner, actors):
//! OpenMetrics text written by `prometheus-client` from an [`Exposition`] built afresh on each
//! scrape (the values are read where they live — the replay's table, a process's counters — so
//! nothing is cached), served over plain HTTP/1 by axum; beside it `GET /healthz`, the
//! process's [`Health`]: 200 `SERVING`, else 503 `NOT_SERVING`.

use std::future::Future;
use std::net::SocketAddr;
use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use axum::extract::State;
use axum::http::header::{AUTHORIZATION, CONTENT_TYPE, WWW_AUTHENTICATE};
use axum::http::{HeaderMap, StatusCode};
use axum::response::IntoResponse;
use axum::routing::get;
use prometheus_client::encoding::{EncodeLabelValue, LabelValueEncoder};
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::registry::Registry;
use subtle::ConstantTimeEq;
use tokio::net::TcpListener;
use tokio::sync::watch;

use crate::health::Health;

/// Content type of the OpenMetrics text format (what Prometheus asks for first).
pub const CONTENT_TYPE_TEXT: &str = "application/openmetrics-text; version=1.0.0; charset=utf-8";

/// Renders the exposition text on each scrape.
pub type Render = Arc<dyn Fn() -> String + Send + Sync>;

/// Who may read `/metrics`. On loopback, anyone on the host (the default, with no token). Beyond
/// loopback — a Prometheus in another container or on another host — only a scraper that sends
/// `authorization: Bearer <token>` with the token of the process's `metrics_token_file`: the
/// exposition names actors and shows the replay's state. The endpoint is plain HTTP, so the
/// token crosses the network in the clear: keep such an endpoint on a private network (the
/// compose file's). `/healthz` stays open (a probe learns SERVING or NOT_SERVING, nothing else).
/// Refused scrapes are counted and shown as `metrics_scrape_refusals_total`.
#[derive(Clone, Debug, Default)]
pub struct MetricsAccess {
    bearer: Option<Arc<[u8]>>,
    refusals: Arc<AtomicU64>,
}

impl MetricsAccess {
    /// Open to whoever reaches the address (loopback only).
    pub fn open() -> Self {
        Self::default()
    }

    /// The token in `path` (trimmed; an empty file is an error), or open without a path.
    pub fn from_token_file(path: Option<&Path>) -> std::io::Result<Self> {
        let Some(path) = path else { return Ok(Self::open()) };
        let raw = std::fs::read_to_string(path).map_err(|e| std::io::Error::new(e.kind(), format!("metrics token file {}: {e}", path.display())))?;
        let token = raw.trim();
        if token.is_empty() {
            return Err(std::io::Error::new(std::io::ErrorKind::InvalidData, format!("metrics token file {}: the file is empty", path.display())));
        }
        Ok(Self { bearer: Some(format!("Bearer {token}").into_bytes().into()), refusals: Arc::default() })
    }

    /// Whether `/metrics` may listen on `addr`: loopback, or anywhere with a token.
    pub fn allows(&self, addr: &SocketAddr) -> bool {
        addr.ip().is_loopback() || self.bearer.is_some()
    }

    /// Scrapes refused for a missing or wrong token.
    pub fn refusals(&self) -> u64 {
        self.refusals.load(Ordering::Relaxed)
    }

    fn admits(&self, headers: &HeaderMap) -> bool {
        let Some(bearer) = &self.bearer else { return true };
        let got = headers.get(AUTHORIZATION).map(|v| v.as_bytes()).unwrap_or_default();
        if got.ct_eq(bearer).into() {
            return true;
        }
        if self.refusals.fetch_add(1, Ordering::Relaxed) == 0 {
            tracing::warn!("a /metrics scrape without the metrics token was refused (401); further refusals are counted in metrics_scrape_refusals_total");
        }
        false
    }
}

/// Serves `render()` at `GET /metrics` (to scrapers `access` admits) and `health` at
/// `GET /healthz` on `listener` until `shutdown` resolves. `render` runs on the blocking pool,
/// so it may take a std lock (the replay's table).
pub async fn serve(listener: TcpListener, render: Render, health: Health, access: MetricsAccess, shutdown: impl Future<Output = ()> + Send + 'static) -> std::io::Result<()> {
    let app = axum::Router::new().route("/metrics", get(scrape)).with_state((render, access)).route("/healthz", get(healthz)).with_state(health);
    axum::serve(listener, app).with_graceful_shutdown(shutdown).await
}

async fn healthz(State(health): State<Health>) -> impl IntoResponse {
    if health.is_serving() { (StatusCode::OK, "SERVING\n") } else { (StatusCode::SERVICE_UNAVAILABLE, "NOT_SERVING\n") }
}

async fn scrape(State((render, access)): State<(Render, MetricsAccess)>, headers: HeaderMap) -> axum::response::Response {
    if !access.admits(&headers) {
        return (StatusCode::UNAUTHORIZED, [(WWW_AUTHENTICATE, "Bearer")], "a bearer token is required (the process's metrics_token_file)\n").into_response();
    }
    let body = tokio::task::spawn_blocking(move || render()).await.unwrap_or_else(|e| format!("# render failed: {e}\n"));
    // The endpoint's own family, before the process's end-of-exposition line.
    let mut own = Exposition::new();
    own.counter("metrics_scrape_refusals", "Scrapes of /metrics refused for a missing or wrong bearer token.", access.refusals() as f64);
    let own = own.text();
    let own = own.strip_suffix("# EOF\n").unwrap_or(&own);
    let body = match body.strip_suffix("# EOF\n") {
        Some(families) => format!("{families}{own}# EOF\n"),
        None => format!("{body}{own}"),
    };
    ([(CONTENT_TYPE, CONTENT_TYPE_TEXT)], body).into_response()
}

/// Binds `addr` (port 0: any free port; beyond loopback only when `access` holds a token), logs
/// the address, and serves `render` and `health` on `rt` until `stop` turns true. Returns the
/// bound address. For the actor and learner processes.
pub fn spawn(rt: &tokio::runtime::Runtime, addr: SocketAddr, render: Render, health: Health, access: MetricsAccess, mut stop: watch::Receiver<bool>) -> std::io::Result<SocketAddr> {
    if !access.allows(&addr) {
        return Err(std::io::Error::new(std::io::ErrorKind::PermissionDenied, format!("metrics: refusing non-loopback address {addr} without a metrics_token_file")));
    }
    let listener = rt.block_on(TcpListener::bind(addr))?;
    let bound = listener.local_addr()?;
    tracing::info!(addr = %bound, "metrics on /metrics");
    rt.spawn(async move {
        let stopped = async move {
            let _ = stop.wait_for(|s| *s).await;
        };
        if let Err(e) = serve(listener, render, health, access, stopped).await {
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

    /// The whole HTTP/1.1 response to `GET path` with the `headers` lines (each ending "\r\n").
    fn http_get(rt: &tokio::runtime::Runtime, addr: SocketAddr, path: &str, headers: &str) -> String {
        rt.block_on(async move {
            let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
            s.write_all(format!("GET {path} HTTP/1.1\r\nHost: x\r\n{headers}Connection: close\r\n\r\n").as_bytes()).await.unwrap();
            let mut out = String::new();
            s.read_to_string(&mut out).await.unwrap();
            out
        })
    }

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
        assert!(spawn(&rt, "0.0.0.0:0".parse().unwrap(), render.clone(), health.clone(), MetricsAccess::open(), stop_rx.clone()).is_err(), "non-loopback is refused");
        let addr = spawn(&rt, "127.0.0.1:0".parse().unwrap(), render, health.clone(), MetricsAccess::open(), stop_rx).unwrap();
        let get = |path: &str| http_get(&rt, addr, path, "");
        let ok = get("/metrics");
        assert!(ok.starts_with("HTTP/1.1 200"), "{ok}");
        assert!(ok.to_ascii_lowercase().contains("content-type: application/openmetrics-text"), "{ok}");
        assert!(ok.contains("# HELP x Things.\n# TYPE x counter\nx_total 3.0\n"), "{ok}");
        assert!(ok.contains(r#"y{actor="a\"b\\c\nd"} 0.5"#), "label values are escaped: {ok}");
        assert!(ok.contains("metrics_scrape_refusals_total 0"), "{ok}");
        assert!(ok.trim_end().ends_with("# EOF") && ok.matches("# EOF").count() == 1, "{ok}");
        assert!(get("/nope").starts_with("HTTP/1.1 404"));
        let _ = stop_tx.send(true);
    }

    #[test]
    fn healthz_answers_the_phase_and_the_probe_reads_it() {
        let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build().unwrap();
        let (stop_tx, stop_rx) = watch::channel(false);
        let health = Health::new();
        let addr = spawn(&rt, "127.0.0.1:0".parse().unwrap(), Arc::new(String::new), health.clone(), MetricsAccess::open(), stop_rx).unwrap();
        let status = || rt.block_on(crate::health::get_healthz(addr)).unwrap();
        assert_eq!(status(), 503, "starting");
        health.serve();
        assert_eq!(status(), 200, "serving");
        health.drain();
        assert_eq!(status(), 503, "draining");
        let _ = stop_tx.send(true);
    }

    #[test]
    fn beyond_loopback_a_scrape_needs_the_token_and_refusals_are_counted() {
        let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build().unwrap();
        let (stop_tx, stop_rx) = watch::channel(false);
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("metrics-token");
        std::fs::write(&file, "s3cret\n").unwrap();
        std::fs::write(dir.path().join("empty"), " \n").unwrap();
        assert!(MetricsAccess::from_token_file(Some(&dir.path().join("empty"))).is_err(), "an empty token file is an error");
        let access = MetricsAccess::from_token_file(Some(&file)).unwrap();
        let render: Render = Arc::new(|| {
            let mut x = Exposition::new();
            x.counter("x", "Things.", 3.0);
            x.text()
        });
        // Any address, here 0.0.0.0, is allowed with a token; scraped on loopback below.
        let addr = spawn(&rt, "0.0.0.0:0".parse().unwrap(), render, Health::new(), access.clone(), stop_rx).unwrap();
        let addr = SocketAddr::from(([127, 0, 0, 1], addr.port()));
        let get = |path: &str, auth: &str| http_get(&rt, addr, path, auth);
        assert!(get("/metrics", "").starts_with("HTTP/1.1 401"), "no token");
        assert!(get("/metrics", "Authorization: Bearer wrong\r\n").starts_with("HTTP/1.1 401"), "a wrong token");
        assert!(get("/metrics", "Authorization: Bearer s3cret-and-more\r\n").starts_with("HTTP/1.1 401"), "a longer token");
        assert!(get("/healthz", "").starts_with("HTTP/1.1 503"), "health stays open");
        let ok = get("/metrics", "Authorization: Bearer s3cret\r\n");
        assert!(ok.starts_with("HTTP/1.1 200") && ok.contains("x_total 3.0"), "{ok}");
        assert!(ok.contains("metrics_scrape_refusals_total 3.0") || ok.contains("metrics_scrape_refusals_total 3\n"), "{ok}");
        assert_eq!(access.refusals(), 3);
        let _ = stop_tx.send(true);
    }
}
