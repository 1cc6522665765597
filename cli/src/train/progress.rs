//! What the supervisor tells the person who started it: the opening lines, the progress line
//! (an `indicatif` spinner redrawn in place on a terminal; a plain line every 10 s to a log or
//! a pipe), and the closing report.

use std::io::IsTerminal;
use std::path::Path;
use std::time::{Duration, Instant};

use indicatif::{ProgressBar, ProgressStyle};

use super::config::TrainConfig;
use super::summary::Summary;

/// `1234567` → `1,234,567`.
pub(crate) fn fmt_int(n: u64) -> String {
    let s = n.to_string();
    let mut out = String::new();
    for (i, c) in s.chars().enumerate() {
        if i > 0 && (s.len() - i).is_multiple_of(3) {
            out.push(',');
        }
        out.push(c);
    }
    out
}

/// `[hh:mm:ss]`.
fn clock(elapsed: Duration) -> String {
    let s = elapsed.as_secs();
    format!("[{:02}:{:02}:{:02}]", s / 3600, s / 60 % 60, s % 60)
}

/// What the progress line shows.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Figures {
    /// Training episodes of the run.
    pub(crate) episodes: u64,
    /// Order of the moving averages, and their values.
    pub(crate) window: usize,
    pub(crate) average_return: f64,
    pub(crate) average_steps: f64,
    pub(crate) updates: u64,
    pub(crate) updates_per_s: f64,
    pub(crate) env_steps_per_s: f64,
    pub(crate) replay_size: u64,
    pub(crate) policy_version: u64,
    pub(crate) actors_alive: usize,
    pub(crate) actors: usize,
    /// Restarts of all children.
    pub(crate) restarts: u32,
}

impl Figures {
    /// The line without its clock.
    pub(crate) fn message(&self) -> String {
        format!(
            "ep {} | avg{} return {:.1} steps {:.0} | updates {} ({:.0}/s) | env {:.0} steps/s | replay {} | policy v{} | actors {}/{}{}",
            fmt_int(self.episodes),
            self.window,
            self.average_return,
            self.average_steps,
            fmt_int(self.updates),
            self.updates_per_s,
            self.env_steps_per_s,
            fmt_int(self.replay_size),
            self.policy_version,
            self.actors_alive,
            self.actors,
            if self.restarts > 0 { format!(" ({} restarts)", self.restarts) } else { String::new() }
        )
    }
}

/// The progress line of a session.
pub(crate) struct Progress {
    /// Drawn on a terminal; hidden otherwise (then `above` a hidden bar just prints).
    bar: ProgressBar,
    terminal: bool,
    /// When the last plain line was printed (off a terminal).
    printed: Option<Instant>,
    /// What the line shows now, and the session's time then.
    last: Option<(Figures, Duration)>,
}

impl Progress {
    /// A progress line for a session that began `elapsed` ago: a spinner on stderr when it is
    /// a terminal.
    pub(crate) fn new(elapsed: Duration) -> Progress {
        Progress::to(std::io::stderr().is_terminal(), elapsed)
    }

    fn to(terminal: bool, elapsed: Duration) -> Progress {
        let bar = if terminal {
            let bar = ProgressBar::new_spinner().with_elapsed(elapsed);
            // The whole message, wrapped onto a second row on a narrow terminal.
            bar.set_style(ProgressStyle::with_template("[{elapsed_precise}] {spinner} {msg}").expect("template"));
            bar.enable_steady_tick(Duration::from_millis(200));
            bar
        } else {
            ProgressBar::hidden()
        };
        Progress { bar, terminal, printed: None, last: None }
    }

    /// Where other output goes while the line is drawn: `above.suspend(|| …)` prints above it.
    pub(crate) fn above(&self) -> &ProgressBar {
        &self.bar
    }

    /// Shows `f` (the session has run for `elapsed`): the line redrawn in place on a terminal;
    /// elsewhere a plain line, at most one every 10 s (logs and pipes).
    pub(crate) fn show(&mut self, f: &Figures, elapsed: Duration) {
        self.last = Some((f.clone(), elapsed));
        if self.terminal {
            self.bar.set_message(f.message());
        } else if self.printed.is_none_or(|t| t.elapsed() >= Duration::from_secs(10)) {
            eprintln!("{}", plain_line(f, elapsed));
            self.printed = Some(Instant::now());
        }
    }

    /// Ends the line: on a terminal the spinner gives way to the last figures as a plain line
    /// that stays; what follows goes below it.
    pub(crate) fn finish(&self) {
        if self.terminal {
            self.bar.finish_and_clear();
            if let Some((f, elapsed)) = &self.last {
                eprintln!("{}", plain_line(f, *elapsed));
            }
        }
    }
}

/// The progress line off a terminal: `[hh:mm:ss] ep … | … | actors n/m`.
fn plain_line(f: &Figures, elapsed: Duration) -> String {
    format!("{} {}", clock(elapsed), f.message())
}

/// The opening lines: the run and where to look.
pub(crate) fn opening(cfg: &TrainConfig, run: &Path, logs: &Path) {
    eprintln!("mapless train: {} — {} ({} actors × {} vehicles); run folder {}", cfg.name, cfg.description, cfg.actors.count, cfg.actors.vehicles, run.display());
    eprintln!("  logs: {}/  TensorBoard: tensorboard --logdir {}/tensorboard", logs.display(), run.display());
}

/// The closing report.
pub(crate) fn closing(s: &Summary, run: &Path) {
    eprintln!(
        "done: {} episodes, {} env steps, {} updates in {:.0} s; avg{} return {:.1}, steps {:.0}; convergence episode {}",
        s.episodes,
        fmt_int(s.env_steps),
        fmt_int(s.updates),
        s.wall_s,
        s.window,
        s.average_return,
        s.average_steps,
        s.convergence_episode.map_or("-".to_owned(), |e| e.to_string())
    );
    eprintln!("  pictures: {}/curves.png, {}/eval/; summary: {}/summary.json", run.display(), run.display(), run.display());
}

#[cfg(test)]
mod tests {
    use super::*;

    fn figures() -> Figures {
        Figures {
            episodes: 1234,
            window: 50,
            average_return: 312.44,
            average_steps: 998.2,
            updates: 65_143,
            updates_per_s: 318.4,
            env_steps_per_s: 1273.0,
            replay_size: 1_000_000,
            policy_version: 52,
            actors_alive: 2,
            actors: 2,
            restarts: 0,
        }
    }

    #[test]
    fn the_progress_line_reads_as_before() {
        assert_eq!((fmt_int(0), fmt_int(999), fmt_int(1000), fmt_int(1_234_567)), ("0".into(), "999".into(), "1,000".into(), "1,234,567".into()));
        let f = figures();
        assert_eq!(
            plain_line(&f, Duration::from_secs(3 * 3600 + 25 * 60 + 7)),
            "[03:25:07] ep 1,234 | avg50 return 312.4 steps 998 | updates 65,143 (318/s) | env 1273 steps/s | replay 1,000,000 | policy v52 | actors 2/2"
        );
        let f = Figures { actors_alive: 1, restarts: 3, average_return: f64::NAN, ..f };
        assert!(f.message().contains("return NaN") && f.message().ends_with("actors 1/2 (3 restarts)"), "{}", f.message());
    }

    #[test]
    fn off_a_terminal_a_plain_line_every_ten_seconds() {
        let mut p = Progress::to(false, Duration::ZERO);
        assert!(p.above().is_hidden());
        p.show(&figures(), Duration::ZERO);
        let first = p.printed.expect("the first figures are printed at once");
        p.show(&figures(), Duration::ZERO);
        assert_eq!(p.printed, Some(first), "not again within 10 s");
        p.printed = Some(first - Duration::from_secs(10));
        p.show(&figures(), Duration::ZERO);
        assert!(p.printed.unwrap() > first);
        p.finish();
    }
}
