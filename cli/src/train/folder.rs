//! The run folder: making it ready for a new or a resumed run (its `config.yaml`, `logs/`),
//! where it is, and writing its files whole or not at all.

use std::fs;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};

use super::config::TrainConfig;

/// A run's folder, ready for a session.
pub(crate) struct RunFolder {
    /// As given (`runs/NAME`): what messages and `summary.json` show.
    pub(crate) dir: PathBuf,
    /// Absolute: what the children's configs name.
    pub(crate) abs: PathBuf,
    /// The children's logs.
    pub(crate) logs: PathBuf,
    /// The folder's name: the run's name in every process's log lines.
    pub(crate) name: String,
}

impl RunFolder {
    /// Makes `dir` ready: a new run refuses a folder that holds a run (unless `force`, which
    /// empties it first); then `logs/` and the resolved `config.yaml`.
    pub(crate) fn prepare(dir: &Path, cfg: &TrainConfig, resuming: bool, force: bool) -> Result<RunFolder> {
        if !resuming && dir.join("config.yaml").exists() {
            if !force {
                bail!("{} already holds a run; continue it with `--resume {}`, pick another `--run`, or pass --force to start over", dir.display(), dir.display());
            }
            fs::remove_dir_all(dir).with_context(|| format!("removing {}", dir.display()))?;
        }
        let logs = dir.join("logs");
        fs::create_dir_all(&logs)?;
        write_atomic(&dir.join("config.yaml"), &serde_yaml::to_string(cfg)?)?;
        let name = dir.file_name().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "run".into());
        let abs = fs::canonicalize(dir)?;
        Ok(RunFolder { dir: dir.to_owned(), abs, logs, name })
    }

    /// A file of the run folder.
    pub(crate) fn join(&self, file: &str) -> PathBuf {
        self.dir.join(file)
    }
}

/// Writes `path` whole or not at all (a temporary file beside it, then a rename), so a run
/// killed mid-write leaves the old file, never a torn one.
pub fn write_atomic(path: &Path, contents: &str) -> Result<()> {
    mapless_proto::atomic_file::write_file_atomically(path, contents.as_bytes()).with_context(|| format!("writing {}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_folder_that_holds_a_run_is_refused_unless_resumed_or_forced() {
        let root = tempfile::tempdir().unwrap();
        let dir = root.path().join("r");
        let cfg = super::super::config::preset_config("env1-sac").unwrap();
        let f = RunFolder::prepare(&dir, &cfg, false, false).unwrap();
        assert_eq!((f.name.as_str(), f.logs.is_dir(), f.abs.is_absolute()), ("r", true, true));
        std::fs::write(f.join("episodes.csv"), "x").unwrap();
        let e = format!("{:#}", RunFolder::prepare(&dir, &cfg, false, false).err().expect("refused"));
        assert!(e.contains("already holds a run") && e.contains("--resume"), "{e}");
        RunFolder::prepare(&dir, &cfg, true, false).unwrap();
        assert!(dir.join("episodes.csv").exists(), "a resume keeps the run");
        RunFolder::prepare(&dir, &cfg, false, true).unwrap();
        assert!(!dir.join("episodes.csv").exists() && dir.join("config.yaml").exists(), "--force starts over");
    }
}
