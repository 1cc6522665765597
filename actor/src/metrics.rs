//! A minimal Prometheus text endpoint (`GET /metrics`, HTTP/1.1, one response per connection)
//! for the actor and learner processes; the replay service has its own.

use std::sync::Arc;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpListener;
use tokio::sync::watch;

/// Renders the exposition text on each scrape.
pub type Render = Arc<dyn Fn() -> String + Send + Sync>;

/// Serves `render()` at `/metrics` on `listener` (loopback only) until `stop` turns true.
pub async fn serve(listener: TcpListener, render: Render, mut stop: watch::Receiver<bool>) -> Result<(), String> {
    let addr = listener.local_addr().map_err(|e| e.to_string())?;
    if !addr.ip().is_loopback() {
        return Err(format!("metrics: refusing non-loopback address {addr}"));
    }
    loop {
        let accepted = tokio::select! {
            a = listener.accept() => a,
            _ = stop.wait_for(|s| *s) => return Ok(()),
        };
        let Ok((mut sock, _)) = accepted else { continue };
        let render = Arc::clone(&render);
        tokio::spawn(async move {
            let mut buf = [0u8; 2048];
            let n = match tokio::time::timeout(std::time::Duration::from_secs(5), sock.read(&mut buf)).await {
                Ok(Ok(n)) => n,
                _ => return,
            };
            let head = String::from_utf8_lossy(&buf[..n]);
            let (status, body) = if head.starts_with("GET /metrics") { ("200 OK", render()) } else { ("404 Not Found", "try /metrics\n".to_owned()) };
            let resp = format!("HTTP/1.1 {status}\r\nContent-Type: text/plain; version=0.0.4\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}", body.len());
            let _ = sock.write_all(resp.as_bytes()).await;
            let _ = sock.shutdown().await;
        });
    }
}

/// Binds `addr` (port 0: any free port), logs the address, and serves `render` on `rt` until
/// `stop` turns true. Returns the bound address.
pub fn spawn(rt: &tokio::runtime::Runtime, addr: std::net::SocketAddr, render: Render, stop: watch::Receiver<bool>) -> std::io::Result<std::net::SocketAddr> {
    let listener = rt.block_on(TcpListener::bind(addr))?;
    let bound = listener.local_addr()?;
    tracing::info!(addr = %bound, "metrics on /metrics");
    rt.spawn(async move {
        if let Err(e) = serve(listener, render, stop).await {
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
