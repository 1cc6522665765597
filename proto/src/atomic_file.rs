//! The workspace's one atomic file write: the policy, checkpoints' `LATEST`, the run's config,
//! summary and pictures, the learner's weights-version file, and the replay's snapshots and
//! log segments all go through [`write_file_atomically_with`] (most through
//! [`write_file_atomically`]).
//!
//! ```text
//!   <dir>/.XXXXXX.tmp   created beside the target (0644 less the umask), written, [fsync]
//!      ── rename ──►  <dir>/<name>   [fsync <dir>]          [..]: Durability::Synced only
//! ```
//!
//! A reader of `<name>`, and the writer after a crash of its own process, sees the old file or
//! the whole new one, never a torn one. Leftovers of a crash before the rename keep the
//! temporary name ([`is_temp_file_name`]), so an owner of a directory can remove them.

use std::fs::{self, File};
use std::io::{self, Write as _};
use std::path::{Path, PathBuf};

/// Random characters in a temporary file's name (`.XXXXXX.tmp`).
const TEMP_RANDOM_CHARS: usize = 6;
/// Temporary files start with this (hidden from `ls`)…
const TEMP_PREFIX: &str = ".";
/// …and end with this.
const TEMP_SUFFIX: &str = ".tmp";

/// What an atomic write makes durable before it returns.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Durability {
    /// fsync of the new file before the rename and of its directory after it: once the write
    /// returns, the new file survives a power loss.
    Synced,
    /// No fsync. Readers, and the writer after a crash of its process, still see the old file
    /// or the whole new one; after a power loss the name may hold a file whose data never
    /// reached the disk. For files that are only hints (the learner's weights-version file,
    /// rewritten every second) or whose owner syncs them by its own policy (the replay's log
    /// segments, which its recovery checks).
    Unsynced,
}

/// The step of an atomic write that failed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AtomicWriteStep {
    /// Creating the temporary file in the target's directory.
    CreateTemp,
    /// The caller's writes into the temporary file.
    Write,
    /// fsync of the temporary file.
    SyncFile,
    /// Renaming the temporary file over the target.
    Rename,
    /// fsync of the directory after the rename.
    SyncDir,
}

impl std::fmt::Display for AtomicWriteStep {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            AtomicWriteStep::CreateTemp => "create a temporary file",
            AtomicWriteStep::Write => "write",
            AtomicWriteStep::SyncFile => "fsync",
            AtomicWriteStep::Rename => "rename into place",
            AtomicWriteStep::SyncDir => "fsync directory",
        })
    }
}

/// An atomic write that failed. Up to and including [`AtomicWriteStep::Rename`], the target
/// is untouched and the temporary file removed; a failed [`AtomicWriteStep::SyncDir`] comes
/// after the rename: the new file is in place, but not known to be durable.
#[derive(Debug, thiserror::Error)]
#[error("{path}: {step}: {error}")]
pub struct AtomicWriteError {
    /// What the failed step acted on: the directory (creating the temporary file, its fsync),
    /// the temporary file (writes, fsync) or the target (the rename).
    pub path: PathBuf,
    /// The step that failed.
    pub step: AtomicWriteStep,
    /// What the OS (or the caller's writer) said.
    pub error: io::Error,
}

/// Writes `bytes` to `path` atomically and durably ([`Durability::Synced`]): a crash leaves
/// either the old file or the new one, never a torn one, and once this returns the new one
/// survives a power loss. The one atomic write of the workspace (module docs).
pub fn write_file_atomically(path: &Path, bytes: &[u8]) -> Result<(), AtomicWriteError> {
    write_file_atomically_with(path, Durability::Synced, |f| f.write_all(bytes)).map(drop)
}

/// Writes `path` atomically (module docs) with what `write` writes into the temporary file
/// (from its start; it may also seek, read or write at offsets), to the given `durability`.
/// Returns the file, open for reading and writing, now under its final name (a log segment
/// keeps appending to it). The caller's own I/O errors come back as [`AtomicWriteStep::Write`].
pub fn write_file_atomically_with(path: &Path, durability: Durability, write: impl FnOnce(&mut File) -> io::Result<()>) -> Result<File, AtomicWriteError> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    // rw-r--r-- (less the umask) as `fs::write` makes them, not tempfile's private 0600: a
    // policy or a run folder is read by other users and containers.
    let mode = <fs::Permissions as std::os::unix::fs::PermissionsExt>::from_mode(0o644);
    let mut tmp = tempfile::Builder::new().prefix(TEMP_PREFIX).suffix(TEMP_SUFFIX).rand_bytes(TEMP_RANDOM_CHARS).permissions(mode).tempfile_in(dir).map_err(fail(dir, AtomicWriteStep::CreateTemp))?;
    // On any error below before the rename, dropping `tmp` removes the temporary file.
    write(tmp.as_file_mut()).map_err(fail(tmp.path(), AtomicWriteStep::Write))?;
    if durability == Durability::Synced {
        tmp.as_file().sync_all().map_err(fail(tmp.path(), AtomicWriteStep::SyncFile))?;
    }
    let file = tmp.persist(path).map_err(|e| fail(path, AtomicWriteStep::Rename)(e.error))?;
    if durability == Durability::Synced {
        // The rename itself is durable only once the directory is.
        File::open(dir).and_then(|d| d.sync_all()).map_err(fail(dir, AtomicWriteStep::SyncDir))?;
    }
    Ok(file)
}

/// The error of `step` on `path`, for `map_err`.
fn fail(path: &Path, step: AtomicWriteStep) -> impl FnOnce(io::Error) -> AtomicWriteError + '_ {
    move |error| AtomicWriteError { path: path.to_owned(), step, error }
}

/// Whether `name` (a file name, no directory) is that of an atomic write's temporary file
/// (`.XXXXXX.tmp`), which only a crash before the rename leaves behind. The owner of a
/// directory that nobody else writes into may remove such files when it opens it.
pub fn is_temp_file_name(name: &str) -> bool {
    name.strip_prefix(TEMP_PREFIX).and_then(|n| n.strip_suffix(TEMP_SUFFIX)).is_some_and(|random| random.len() == TEMP_RANDOM_CHARS && random.bytes().all(|b| b.is_ascii_alphanumeric()))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The names in `dir`, sorted.
    fn names(dir: &Path) -> Vec<String> {
        let mut v: Vec<String> = fs::read_dir(dir).unwrap().map(|e| e.unwrap().file_name().into_string().unwrap()).collect();
        v.sort();
        v
    }

    #[test]
    fn a_write_replaces_the_file_whole_and_leaves_no_temporary_file() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("LATEST");
        write_file_atomically(&p, b"old").unwrap();
        write_file_atomically(&p, b"new").unwrap();
        assert_eq!(fs::read(&p).unwrap(), b"new");
        assert_eq!(names(d.path()), ["LATEST"]);
    }

    #[test]
    fn a_failed_write_leaves_the_old_file_and_no_temporary_file() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("policy.safetensors");
        write_file_atomically(&p, b"old").unwrap();
        for durability in [Durability::Synced, Durability::Unsynced] {
            let e = write_file_atomically_with(&p, durability, |f| {
                f.write_all(b"half of the new")?;
                Err(io::Error::other("disk full"))
            })
            .unwrap_err();
            assert_eq!(e.step, AtomicWriteStep::Write);
            assert!(is_temp_file_name(e.path.file_name().unwrap().to_str().unwrap()), "names the temporary file: {}", e.path.display());
            assert!(e.to_string().ends_with(": write: disk full"), "{e}");
            assert_eq!(fs::read(&p).unwrap(), b"old");
            assert_eq!(names(d.path()), ["policy.safetensors"]);
        }
    }

    #[test]
    fn a_rename_that_fails_leaves_the_target_and_no_temporary_file() {
        let d = tempfile::tempdir().unwrap();
        // A non-empty directory under the target's name: rename(2) refuses to replace it.
        let p = d.path().join("summary.json");
        fs::create_dir(&p).unwrap();
        fs::write(p.join("inside"), b"x").unwrap();
        let e = write_file_atomically(&p, b"{}").unwrap_err();
        assert_eq!((e.step, e.path.as_path()), (AtomicWriteStep::Rename, p.as_path()));
        assert_eq!(names(d.path()), ["summary.json"]);
        assert!(p.join("inside").exists());
    }

    #[test]
    fn a_missing_directory_fails_at_the_temporary_file() {
        let d = tempfile::tempdir().unwrap();
        let e = write_file_atomically(&d.path().join("no/such/dir/file"), b"x").unwrap_err();
        assert_eq!((e.step, e.path.as_path()), (AtomicWriteStep::CreateTemp, d.path().join("no/such/dir").as_path()));
    }

    #[test]
    fn the_written_file_comes_back_open_under_its_name() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("seg.log");
        let mut f = write_file_atomically_with(&p, Durability::Unsynced, |f| f.write_all(b"header|")).unwrap();
        f.write_all(b"record").unwrap();
        assert_eq!(fs::read(&p).unwrap(), b"header|record");
        // rw-r--r-- less the umask, as fs::write makes files (tempfile alone makes them 0600).
        let mode = std::os::unix::fs::PermissionsExt::mode(&fs::metadata(&p).unwrap().permissions());
        assert_eq!(mode & 0o444, 0o444, "readable by all: {mode:o}");
    }

    #[test]
    fn temporary_file_names_are_recognised_and_nothing_else() {
        let d = tempfile::tempdir().unwrap();
        let tmp = tempfile::Builder::new().prefix(TEMP_PREFIX).suffix(TEMP_SUFFIX).rand_bytes(TEMP_RANDOM_CHARS).tempfile_in(d.path()).unwrap();
        assert!(is_temp_file_name(tmp.path().file_name().unwrap().to_str().unwrap()));
        for other in ["snap-00000000000000000005.snap", "snap-00000000000000000005.snap.tmp", ".ckpt-000000000002.tmp", ".abc.tmp", ".abcdef.tmp.1", "abcdefg.tmp", ".ab-def.tmp"] {
            assert!(!is_temp_file_name(other), "{other}");
        }
    }
}
