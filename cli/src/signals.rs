//! Shutdown signals.

pub use mapless_net::signals::termination;

/// Asks process `pid` to stop (SIGTERM); a process that is already gone is not an error.
pub fn terminate(pid: u32) {
    let Ok(pid) = i32::try_from(pid) else { return };
    let _ = nix::sys::signal::kill(nix::unistd::Pid::from_raw(pid), nix::sys::signal::Signal::SIGTERM);
}
