//! Reading a mapless process's Prometheus text exposition (`GET /metrics`): how the soak bench
//! and `mapless monitor` follow a replay and a learner they did not start.

use std::io::{Read, Write};
use std::net::{TcpStream, ToSocketAddrs};
use std::time::Duration;

/// The exposition at `http://addr/metrics` (`addr`: `host:port`, a name resolved each call, so a
/// restarted container's new address is found), sending `authorization: Bearer <token>` when
/// one is given; `Err` says why not (unreachable, refused, not 200).
pub(crate) fn metrics(addr: &str, token: Option<&str>) -> Result<String, String> {
    let timeout = Duration::from_secs(2);
    let target = addr.to_socket_addrs().map_err(|e| format!("{addr}: {e}"))?.next().ok_or_else(|| format!("{addr}: no address"))?;
    let mut s = TcpStream::connect_timeout(&target, timeout).map_err(|e| format!("{addr}: {e}"))?;
    s.set_read_timeout(Some(timeout)).map_err(|e| e.to_string())?;
    let auth = token.map(|t| format!("Authorization: Bearer {t}\r\n")).unwrap_or_default();
    let request = format!("GET /metrics HTTP/1.0\r\nHost: {addr}\r\n{auth}\r\n");
    s.write_all(request.as_bytes()).map_err(|e| format!("{addr}: {e}"))?;
    let mut text = String::new();
    s.read_to_string(&mut text).map_err(|e| format!("{addr}: {e}"))?;
    let (head, body) = text.split_once("\r\n\r\n").ok_or_else(|| format!("{addr}: not an HTTP answer"))?;
    let status = head.lines().next().unwrap_or_default();
    if status.split_whitespace().nth(1) != Some("200") {
        return Err(format!("{addr}/metrics: {status}"));
    }
    Ok(body.to_owned())
}

/// The value of the series `name` (or `name_total`, as OpenMetrics names counters) in an
/// exposition: its first sample, whatever its labels.
pub(crate) fn value(text: &str, name: &str) -> Option<f64> {
    text.lines().filter(|l| !l.starts_with('#')).find_map(|l| {
        let (metric, value) = l.rsplit_once(' ')?;
        let metric = metric.split('{').next()?;
        (metric == name || metric.strip_suffix("_total") == Some(name)).then(|| value.parse().ok())?
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn values_by_name_whatever_the_labels_and_the_total_suffix() {
        let text = "# HELP replay_size Rows stored.\n# TYPE replay_size gauge\nreplay_size{table=\"t\"} 1234\nreplay_inserts_total{table=\"t\"} 5e3\nmapless_learner_updates_total 77\n# EOF\n";
        assert_eq!(value(text, "replay_size"), Some(1234.0));
        assert_eq!(value(text, "replay_inserts_total"), Some(5000.0));
        assert_eq!(value(text, "replay_inserts"), Some(5000.0), "a counter by its OpenMetrics family name");
        assert_eq!(value(text, "mapless_learner_updates"), Some(77.0));
        assert_eq!(value(text, "replay"), None, "a prefix is not a name");
    }

    #[test]
    fn a_refused_scrape_is_an_error_that_says_so() {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = l.local_addr().unwrap().to_string();
        let server = std::thread::spawn(move || {
            for answer in ["HTTP/1.1 401 Unauthorized\r\ncontent-length: 0\r\n\r\n", "HTTP/1.1 200 OK\r\n\r\nreplay_size 3\n"] {
                let (mut c, _) = l.accept().unwrap();
                let mut req = String::new();
                let mut buf = [0u8; 1024];
                while !req.ends_with("\r\n\r\n") {
                    let n = c.read(&mut buf).unwrap();
                    assert!(n > 0, "the request ended early: {req:?}");
                    req.push_str(&String::from_utf8_lossy(&buf[..n]));
                }
                c.write_all(answer.as_bytes()).unwrap();
                drop(c);
                if answer.contains("200") {
                    return req;
                }
            }
            unreachable!()
        });
        let e = metrics(&addr, None).unwrap_err();
        assert!(e.contains("401"), "{e}");
        assert_eq!(value(&metrics(&addr, Some("s3cret")).unwrap(), "replay_size"), Some(3.0));
        assert!(server.join().unwrap().contains("Authorization: Bearer s3cret\r\n"));
    }
}
