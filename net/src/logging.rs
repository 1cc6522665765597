//! Process-wide log setup shared by every mapless process (replay, learner, actors, the
//! supervisor): `tracing` to stderr, human-readable or JSON lines, and the process's identity
//! — run name, role, actor id — on **every** line, whichever thread or task logs it.
//!
//! Spans carry the identity only where they are entered, which misses background threads and
//! tasks (sinks, weights followers, the shm ingest thread); so the identity is a process-wide
//! value that the formatter appends to each line instead: ` run=… role=… actor_id=…` at the end
//! of a text line, `"run":…,"role":…,"actor_id":…` as top-level keys of a JSON line.
//!
//! ```no_run
//! mapless_net::logging::init(false, "info");
//! mapless_net::logging::identify(&[("run", "env1-sac"), ("role", "replay")]);
//! tracing::info!("listening");   // … INFO mapless_net: listening run=env1-sac role=replay
//! ```

use std::fmt;
use std::sync::RwLock;

use tracing::{Event, Subscriber};
use tracing_subscriber::fmt::format::{self, Format, Writer};
use tracing_subscriber::fmt::{FmtContext, FormatEvent, FormatFields};
use tracing_subscriber::registry::LookupSpan;

/// The identity fields, in order; empty values are left out.
static IDENTITY: RwLock<Vec<(String, String)>> = RwLock::new(Vec::new());

/// Sets the identity every later log line carries (replaces any earlier one). The run name
/// defaults to the `MAPLESS_RUN` environment variable when `fields` has none.
pub fn identify(fields: &[(&str, &str)]) {
    let mut v: Vec<(String, String)> = fields.iter().filter(|(_, val)| !val.is_empty()).map(|(k, val)| ((*k).to_owned(), (*val).to_owned())).collect();
    if !v.iter().any(|(k, _)| k == "run")
        && let Ok(run) = std::env::var("MAPLESS_RUN")
        && !run.is_empty()
    {
        v.insert(0, ("run".to_owned(), run));
    }
    *IDENTITY.write().unwrap_or_else(std::sync::PoisonError::into_inner) = v;
}

/// The value of identity field `key`, if set.
pub fn field(key: &str) -> Option<String> {
    IDENTITY.read().unwrap_or_else(std::sync::PoisonError::into_inner).iter().find(|(k, _)| k == key).map(|(_, v)| v.clone())
}

/// Installs the process's subscriber: stderr, `RUST_LOG` or `default_filter`, colours only on a
/// terminal, JSON lines when `json`. Call once, early; later calls are ignored.
pub fn init(json: bool, default_filter: &str) {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default_filter));
    // No colour codes when stderr is a file (a run folder's logs/).
    let ansi = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let b = tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr).with_ansi(ansi);
    let _ = if json {
        b.event_format(Tagged { inner: format().json().with_current_span(true).with_span_list(false), json: true }).fmt_fields(format::JsonFields::new()).try_init()
    } else {
        b.event_format(Tagged { inner: format().with_ansi(ansi), json: false }).try_init()
    };
}

fn format() -> Format {
    Format::default()
}

/// An event formatter that appends the process identity to what `inner` writes.
struct Tagged<F> {
    inner: F,
    json: bool,
}

impl<S, N, F> FormatEvent<S, N> for Tagged<F>
where
    S: Subscriber + for<'a> LookupSpan<'a>,
    N: for<'a> FormatFields<'a> + 'static,
    F: FormatEvent<S, N>,
{
    fn format_event(&self, ctx: &FmtContext<'_, S, N>, mut writer: Writer<'_>, event: &Event<'_>) -> fmt::Result {
        let mut line = String::with_capacity(256);
        self.inner.format_event(ctx, Writer::new(&mut line), event)?;
        let identity = IDENTITY.read().unwrap_or_else(std::sync::PoisonError::into_inner);
        writer.write_str(&tag(&line, &identity, self.json))
    }
}

/// `line` (one formatted event, newline-terminated) with the identity added.
fn tag(line: &str, identity: &[(String, String)], json: bool) -> String {
    if identity.is_empty() {
        return line.to_owned();
    }
    let body = line.strip_suffix('\n').unwrap_or(line);
    let mut out = String::with_capacity(line.len() + 64);
    if json {
        let Some(rest) = body.strip_prefix('{') else { return line.to_owned() };
        out.push('{');
        for (k, v) in identity {
            out.push_str(&serde_json::to_string(k).unwrap_or_default());
            out.push(':');
            out.push_str(&serde_json::to_string(v).unwrap_or_default());
            out.push(',');
        }
        if rest.starts_with('}') {
            out.pop();
        }
        out.push_str(rest);
    } else {
        // On the first line: a multi-line message continues below it.
        let (first, rest) = body.split_at(body.find('\n').unwrap_or(body.len()));
        out.push_str(first);
        for (k, v) in identity {
            out.push(' ');
            out.push_str(k);
            out.push('=');
            if v.contains(|c: char| c.is_whitespace() || c == '=' || c == '"') {
                out.push_str(&format!("{v:?}"));
            } else {
                out.push_str(v);
            }
        }
        out.push_str(rest);
    }
    out.push('\n');
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn id() -> Vec<(String, String)> {
        vec![("run".into(), "env1 \"sac\"".into()), ("role".into(), "actor".into())]
    }

    #[test]
    fn text_lines_end_with_the_identity() {
        assert_eq!(tag("2026 INFO x: hello\n", &id(), false), "2026 INFO x: hello run=\"env1 \\\"sac\\\"\" role=actor\n");
        // A multi-line message: the identity ends its first line.
        assert_eq!(tag("2026 WARN x: a\nb\n", &id()[1..], false), "2026 WARN x: a role=actor\nb\n");
    }

    #[test]
    fn json_lines_get_top_level_keys_and_stay_valid_json() {
        let out = tag("{\"level\":\"INFO\",\"fields\":{\"message\":\"hi\"}}\n", &id(), true);
        let v: serde_json::Value = serde_json::from_str(&out).unwrap();
        assert_eq!(v["run"], "env1 \"sac\"");
        assert_eq!(v["role"], "actor");
        assert_eq!(v["fields"]["message"], "hi");
        assert!(out.ends_with("}\n"));
        let empty = tag("{}\n", &id(), true);
        assert_eq!(serde_json::from_str::<serde_json::Value>(&empty).unwrap()["role"], "actor");
    }

    #[test]
    fn no_identity_leaves_the_line_alone() {
        assert_eq!(tag("a\n", &[], false), "a\n");
    }

    #[test]
    fn identify_skips_empty_values() {
        identify(&[("run", "r1"), ("role", "replay"), ("actor_id", "")]);
        let got = IDENTITY.read().unwrap().clone();
        assert_eq!(got, vec![("run".to_owned(), "r1".to_owned()), ("role".to_owned(), "replay".to_owned())]);
    }
}
