//! A supervised child process: spawning it into its own process group with its log file, its
//! stdout lines forwarded, the address a service says it bound, stopping it (SIGTERM, then
//! SIGKILL). What happens when one exits is `restart.rs`'s.

use std::fs;
use std::io::{BufRead, BufReader};
use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc as std_mpsc;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};

/// A supervised child process. Dropping it stops the process (so an error in the supervisor
/// never leaves a cluster behind).
pub(crate) struct Proc {
    pub(crate) role: String,
    pub(crate) cmd: Vec<String>,
    pub(crate) child: Option<Child>,
    /// Forwards the child's stdout lines; ends at the child's exit.
    pub(crate) reader: Option<std::thread::JoinHandle<()>>,
    pub(crate) restarts: u32,
    /// Restarts in a row of a child that died within 10 s of starting, and when it may start again.
    pub(crate) quick_failures: u32,
    pub(crate) not_before: Option<Instant>,
    pub(crate) started_at: Instant,
    pub(crate) log: PathBuf,
}

impl Drop for Proc {
    fn drop(&mut self) {
        self.stop(Duration::from_secs(10));
    }
}

impl Proc {
    pub(crate) fn spawn(role: &str, cmd: Vec<String>, log: PathBuf, on_line: Option<std_mpsc::Sender<(String, String)>>) -> Result<Proc> {
        let mut p = Proc { role: role.to_owned(), cmd, child: None, reader: None, restarts: 0, quick_failures: 0, not_before: None, started_at: Instant::now(), log };
        p.start(on_line)?;
        Ok(p)
    }

    pub(crate) fn start(&mut self, on_line: Option<std_mpsc::Sender<(String, String)>>) -> Result<()> {
        let log = fs::OpenOptions::new().create(true).append(true).open(&self.log).with_context(|| format!("opening {}", self.log.display()))?;
        let mut c = Command::new(&self.cmd[0]);
        c.args(&self.cmd[1..]).stdin(Stdio::null()).stdout(Stdio::piped()).stderr(log);
        // Children without a --run flag (the replay) take the run name for their log lines from here.
        if let Some(run) = mapless_net::logging::field("run") {
            c.env("MAPLESS_RUN", run);
        }
        // Its own process group: a Ctrl-C at the terminal reaches the supervisor only, which
        // then stops the children in order (actors, learner, replay).
        std::os::unix::process::CommandExt::process_group(&mut c, 0);
        let mut child = c.spawn().with_context(|| format!("starting {} ({})", self.role, self.cmd[0]))?;
        let out = child.stdout.take().expect("piped stdout");
        let role = self.role.clone();
        self.reader = Some(std::thread::spawn(move || {
            for line in BufReader::new(out).lines().map_while(std::result::Result::ok) {
                if let Some(tx) = &on_line {
                    let _ = tx.send((role.clone(), line));
                }
            }
        }));
        self.child = Some(child);
        self.started_at = Instant::now();
        Ok(())
    }

    /// Exit status if it has exited.
    pub(crate) fn exited(&mut self) -> Option<std::process::ExitStatus> {
        self.child.as_mut().and_then(|c| c.try_wait().ok().flatten())
    }

    pub(crate) fn pid(&self) -> Option<u32> {
        self.child.as_ref().map(Child::id)
    }

    /// SIGTERM, then wait up to `grace`, then SIGKILL.
    pub(crate) fn stop(&mut self, grace: Duration) {
        let Some(c) = self.child.as_mut() else { return };
        if c.try_wait().ok().flatten().is_none() {
            crate::signals::terminate(c.id());
            let end = Instant::now() + grace;
            while Instant::now() < end {
                if c.try_wait().ok().flatten().is_some() {
                    break;
                }
                std::thread::sleep(Duration::from_millis(50));
            }
            if c.try_wait().ok().flatten().is_none() {
                tracing::warn!(child = %self.role, "did not stop within {grace:?}; killing");
                let _ = c.kill();
                let _ = c.wait();
            }
        }
        self.child = None;
        // Every line it printed has been forwarded once its stdout closed.
        if let Some(r) = self.reader.take() {
            let _ = r.join();
        }
    }
}

/// Waits for a line from `role` that starts with `prefix`; returns every line `role` printed
/// until then, that one last.
pub(crate) fn wait_line(rx: &std_mpsc::Receiver<(String, String)>, role: &str, prefix: &str, timeout: Duration, proc_: &mut Proc) -> Result<Vec<String>> {
    let end = Instant::now() + timeout;
    let mut said = Vec::new();
    loop {
        if let Some(st) = proc_.exited() {
            bail!("{role} exited ({st}) before it was ready; see {}", proc_.log.display());
        }
        match rx.recv_timeout(Duration::from_millis(100)) {
            Ok((r, l)) if r == role => {
                let done = l.starts_with(prefix);
                said.push(l);
                if done {
                    return Ok(said);
                }
            }
            Ok(_) => {}
            Err(std_mpsc::RecvTimeoutError::Timeout) => {}
            Err(e) => bail!("{role}: {e}"),
        }
        if Instant::now() > end {
            bail!("{role} not ready after {timeout:?}; see {}", proc_.log.display());
        }
    }
}

/// Starts a service child and waits until it prints `ready` followed by its address; returns
/// it with that address and the one of its `metrics on http://ADDR/metrics` line.
pub(crate) fn start_service(
    role: &str,
    cmd: Vec<String>,
    log: PathBuf,
    ready: &str,
    rx: &std_mpsc::Receiver<(String, String)>,
    tx: &std_mpsc::Sender<(String, String)>,
) -> Result<(Proc, SocketAddr, SocketAddr)> {
    let mut proc_ = Proc::spawn(role, cmd, log, Some(tx.clone()))?;
    let said = wait_line(rx, role, ready, Duration::from_secs(120), &mut proc_)?;
    let addr = said_addr(&said, ready)?;
    let metrics = said_addr(&said, "metrics on http://")?;
    Ok((proc_, addr, metrics))
}

/// The address in the line of `said` that starts with `prefix` (`listening on ADDR`,
/// `metrics on http://ADDR/metrics`).
pub(crate) fn said_addr(said: &[String], prefix: &str) -> Result<SocketAddr> {
    let line = said.iter().find(|l| l.starts_with(prefix)).with_context(|| format!("no `{prefix}…` line in {said:?}"))?;
    let rest = &line[prefix.len()..];
    let addr = rest.split(['/', ' ']).next().unwrap_or(rest);
    addr.parse().with_context(|| format!("bad address in `{line}`"))
}

/// `mapless-replay`, `mapless-learner` and `mapless-actor` live next to this executable.
pub fn sibling(name: &str) -> Result<PathBuf> {
    let exe = std::env::current_exe()?;
    let p = exe.with_file_name(name);
    if p.exists() {
        return Ok(p);
    }
    bail!("{} not found next to {} — build all binaries: `cargo build --release --bins` (run.sh does)", name, exe.display())
}
