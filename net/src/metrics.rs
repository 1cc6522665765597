//! The Prometheus `/metrics` exporter of every mapless process (replay, learner, actors):
//! text exposition format 0.0.4 over plain HTTP/1 (axum), rendered afresh on each scrape.

use std::future::Future;
use std::net::SocketAddr;
use std::sync::Arc;

use axum::extract::State;
use axum::http::header::CONTENT_TYPE;
use axum::response::IntoResponse;
use axum::routing::get;
use tokio::net::TcpListener;
use tokio::sync::watch;

/// Content type of the text exposition format.
pub const CONTENT_TYPE_TEXT: &str = "text/plain; version=0.0.4; charset=utf-8";

/// Renders the exposition text on each scrape.
pub type Render = Arc<dyn Fn() -> String + Send + Sync>;

/// Serves `render()` at `GET /metrics` on `listener` until `shutdown` resolves. `render` runs
/// on the blocking pool, so it may take a std lock (the replay's table).
pub async fn serve(listener: TcpListener, render: Render, shutdown: impl Future<Output = ()> + Send + 'static) -> std::io::Result<()> {
    let app = axum::Router::new().route("/metrics", get(scrape)).with_state(render);
    axum::serve(listener, app).with_graceful_shutdown(shutdown).await
}

async fn scrape(State(render): State<Render>) -> impl IntoResponse {
    let body = tokio::task::spawn_blocking(move || render()).await.unwrap_or_else(|e| format!("# render failed: {e}\n"));
    ([(CONTENT_TYPE, CONTENT_TYPE_TEXT)], body)
}

/// Binds `addr` (port 0: any free port; loopback only), logs the address, and serves `render`
/// on `rt` until `stop` turns true. Returns the bound address. For the actor and learner
/// processes, whose metrics are for the host they run on.
pub fn spawn(rt: &tokio::runtime::Runtime, addr: SocketAddr, render: Render, mut stop: watch::Receiver<bool>) -> std::io::Result<SocketAddr> {
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
        if let Err(e) = serve(listener, render, stopped).await {
            tracing::warn!(error = %e, "metrics endpoint stopped");
        }
    });
    Ok(bound)
}

/// One metric in the text format: `# HELP`, `# TYPE` and the sample.
pub fn line(out: &mut String, name: &str, kind: &str, help: &str, value: f64) {
    use std::fmt::Write as _;
    let _ = write!(out, "# HELP {name} {help}\n# TYPE {name} {kind}\n{name} {value}\n");
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
            let mut s = String::new();
            line(&mut s, "x_total", "counter", "Things.", 3.0);
            s
        });
        assert!(spawn(&rt, "0.0.0.0:0".parse().unwrap(), render.clone(), stop_rx.clone()).is_err(), "non-loopback is refused");
        let addr = spawn(&rt, "127.0.0.1:0".parse().unwrap(), render, stop_rx).unwrap();
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
        assert!(ok.contains("# TYPE x_total counter\nx_total 3\n"), "{ok}");
        assert!(get("/nope").starts_with("HTTP/1.1 404"));
        let _ = stop_tx.send(true);
    }
}
