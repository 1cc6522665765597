//! The restart policies: what the supervisor does when a child exits. Two, one per kind of
//! child:
//!
//! - **An actor** ([`actor`]) holds nothing that a restart loses (it comes back under a new
//!   incarnation id, so the replay's exactly-once bookkeeping stays right, and fetches the
//!   newest weights). It is restarted at once when it had run for [`QUICK`] or more; one that
//!   exits sooner waits first ([`backoff`]: 1 s, doubling to 30 s), and [`MAX_QUICK_FAILURES`]
//!   such exits in a row fail the run. Every exit counts in `summary.json`'s `actor_restarts`.
//! - **A service**, the learner or the replay ([`service`]), is restarted at once — the
//!   learner from its newest checkpoint, the replay from its log — at most
//!   [`MAX_SERVICE_RESTARTS`] times; its next exit fails the run.

use std::process::ExitStatus;
use std::sync::mpsc as std_mpsc;
use std::time::{Duration, Instant};

use anyhow::{Result, bail};
use indicatif::ProgressBar;

use super::children::Proc;

/// An actor that exits within this time of starting waits before it starts again.
pub(crate) const QUICK: Duration = Duration::from_secs(10);
/// Quick exits in a row of one actor that fail the run.
pub(crate) const MAX_QUICK_FAILURES: u32 = 10;
/// Restarts of the learner, or of the replay, in one session.
pub(crate) const MAX_SERVICE_RESTARTS: u32 = 3;

/// The wait before an actor's restart after its `quick_failures`-th quick exit in a row
/// (from 1): 1, 2, 4, 8, 16 s, then 30 s.
pub(crate) fn backoff(quick_failures: u32) -> Duration {
    Duration::from_secs(1 << quick_failures.saturating_sub(1).min(5)).min(Duration::from_secs(30))
}

/// The actor policy for actor `index`: called at every turn of the supervision; restarts it
/// when it has exited (or when the pause after a quick exit is over). Returns whether it was
/// started again. What it logs goes `above` the progress line.
pub(crate) fn actor(index: usize, a: &mut Proc, on_line: &std_mpsc::Sender<(String, String)>, above: &ProgressBar) -> Result<bool> {
    if let Some(t) = a.not_before {
        if Instant::now() < t {
            return Ok(false);
        }
        a.not_before = None;
        a.start(Some(on_line.clone()))?;
        return Ok(true);
    }
    let Some(st) = a.exited() else { return Ok(false) };
    a.restarts += 1;
    above.suspend(|| tracing::warn!(actor = index, status = %st, "actor exited; restarting it"));
    if a.started_at.elapsed() < QUICK {
        a.quick_failures += 1;
        if a.quick_failures >= MAX_QUICK_FAILURES {
            bail!("{} failed within 10 s of starting 10 times in a row; see {}", a.role, a.log.display());
        }
        let wait = backoff(a.quick_failures);
        a.not_before = Some(Instant::now() + wait);
        above.suspend(|| tracing::warn!(child = %a.role, retry_in_s = wait.as_secs(), "exited soon after starting; restarting after a pause"));
        return Ok(false);
    }
    a.quick_failures = 0;
    a.start(Some(on_line.clone()))?;
    Ok(true)
}

/// The service policy: restarts a service child (learner, replay) that exited with `st`, `how`
/// it comes back saying how it recovers its state; fails after [`MAX_SERVICE_RESTARTS`]. What
/// it logs goes `above` the progress line.
pub(crate) fn service(p: &mut Proc, st: ExitStatus, how: &str, on_line: &std_mpsc::Sender<(String, String)>, above: &ProgressBar) -> Result<()> {
    if p.restarts >= MAX_SERVICE_RESTARTS {
        bail!("the {} exited ({st}) for the 4th time; see {}", p.role, p.log.display());
    }
    above.suspend(|| tracing::warn!(status = %st, "{} exited; restarting it {how}", p.role));
    p.restarts += 1;
    p.start(Some(on_line.clone()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_pause_after_a_quick_exit_doubles_up_to_30_s() {
        let waits: Vec<u64> = (1..=8).map(|n| backoff(n).as_secs()).collect();
        assert_eq!(waits, [1, 2, 4, 8, 16, 30, 30, 30]);
    }

    /// A child that exits at once (`true`), logging into `dir`.
    fn quitter(dir: &std::path::Path, role: &str) -> Proc {
        let mut p = Proc::spawn(role, vec!["true".into()], dir.join(format!("{role}.log")), None).unwrap();
        let end = Instant::now() + Duration::from_secs(10);
        while p.exited().is_none() {
            assert!(Instant::now() < end, "`true` did not exit");
            std::thread::sleep(Duration::from_millis(10));
        }
        p
    }

    #[test]
    fn an_actor_that_exits_quickly_waits_and_ten_in_a_row_fail_the_run() {
        let dir = tempfile::tempdir().unwrap();
        let (tx, _rx) = std_mpsc::channel();
        let hidden = ProgressBar::hidden();
        let mut a = quitter(dir.path(), "actor-0");
        assert!(!actor(0, &mut a, &tx, &hidden).unwrap(), "a quick exit: not at once");
        assert_eq!((a.restarts, a.quick_failures), (1, 1));
        let due = a.not_before.expect("a pause");
        assert!(due > Instant::now() + Duration::from_millis(500) && due <= Instant::now() + Duration::from_secs(1));
        assert!(!actor(0, &mut a, &tx, &hidden).unwrap(), "still pausing");
        a.not_before = Some(Instant::now());
        assert!(actor(0, &mut a, &tx, &hidden).unwrap(), "the pause is over: started again");
        assert!(a.not_before.is_none() && a.child.is_some());
        while a.exited().is_none() {
            std::thread::sleep(Duration::from_millis(10));
        }
        a.quick_failures = MAX_QUICK_FAILURES - 1;
        let e = actor(0, &mut a, &tx, &hidden).unwrap_err().to_string();
        assert!(e.contains("actor-0 failed within 10 s of starting 10 times in a row"), "{e}");
    }

    #[test]
    fn an_actor_that_ran_a_while_comes_back_at_once() {
        let dir = tempfile::tempdir().unwrap();
        let (tx, _rx) = std_mpsc::channel();
        let mut a = quitter(dir.path(), "actor-1");
        a.started_at = Instant::now() - QUICK;
        a.quick_failures = 4;
        assert!(actor(1, &mut a, &tx, &ProgressBar::hidden()).unwrap());
        assert_eq!((a.restarts, a.quick_failures, a.not_before), (1, 0, None), "a long run clears the quick exits");
    }

    #[test]
    fn a_service_comes_back_three_times_and_its_fourth_exit_fails_the_run() {
        let dir = tempfile::tempdir().unwrap();
        let (tx, _rx) = std_mpsc::channel();
        let mut p = quitter(dir.path(), "learner");
        for n in 1..=MAX_SERVICE_RESTARTS {
            let st = p.exited().expect("exited");
            service(&mut p, st, "from its newest checkpoint", &tx, &ProgressBar::hidden()).unwrap();
            assert_eq!(p.restarts, n);
            while p.exited().is_none() {
                std::thread::sleep(Duration::from_millis(10));
            }
        }
        let st = p.exited().unwrap();
        let e = service(&mut p, st, "from its newest checkpoint", &tx, &ProgressBar::hidden()).unwrap_err().to_string();
        assert!(e.contains("the learner exited") && e.contains("for the 4th time"), "{e}");
    }
}
