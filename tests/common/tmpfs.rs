//! A small tmpfs that a test mounts to fill (a full disk, for real). It needs root or
//! CAP_SYS_ADMIN and panics, saying so, without them. Shared by the replay's disk-full test
//! (which includes this file by path) and the learner's.

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::process::Command;

/// A tmpfs of `size` mounted on a fresh directory; unmounted and removed on drop.
pub struct Tmpfs(PathBuf);

impl Tmpfs {
    /// Where it is mounted.
    pub fn path(&self) -> &Path {
        &self.0
    }

    pub fn mount(size: &str) -> Tmpfs {
        let nanos = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_nanos();
        let dir = std::env::temp_dir().join(format!("mapless-diskfull-{}-{nanos}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let out = Command::new("mount").args(["-t", "tmpfs", "-o", &format!("size={size},mode=0700"), "mapless-diskfull"]).arg(&dir).output();
        let why = match out {
            Ok(o) if o.status.success() => return Tmpfs(dir),
            Ok(o) => String::from_utf8_lossy(&o.stderr).trim().to_string(),
            Err(e) => format!("cannot run `mount`: {e}"),
        };
        let _ = std::fs::remove_dir(&dir);
        panic!("this test needs to mount a small tmpfs to fill it (root or CAP_SYS_ADMIN): `mount -t tmpfs -o size={size} … {}` failed: {why}", dir.display());
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg(&self.0).status();
        let _ = std::fs::remove_dir(&self.0);
    }
}

/// Writes `path` until the disk is full (ENOSPC); the bytes written.
pub fn fill(path: &Path) -> u64 {
    let mut f = std::fs::File::create(path).unwrap();
    let chunk = vec![0xA5u8; 4096];
    let mut written = 0;
    loop {
        match f.write(&chunk) {
            Ok(0) => break,
            Ok(n) => written += n as u64,
            Err(e) if e.raw_os_error() == Some(28) => break, // ENOSPC
            Err(e) => panic!("filling {}: {e}", path.display()),
        }
    }
    written
}
