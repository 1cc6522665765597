//! The fuzz targets' committed inputs, for the stable test suites that replay them
//! (`sim`, `actor`, `replay`, `learner` and `cli` `tests/fuzz_corpora.rs`, which include this file
//! by `#[path]`):
//! `fuzz/corpus/<target>/` (seeds and what `cargo fuzz cmin` kept) and
//! `fuzz/regressions/<target>/` (inputs that once found a bug).

#![allow(dead_code)]

use std::path::{Path, PathBuf};

/// The repository's `fuzz/` folder.
pub fn fuzz_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../fuzz")
}

/// Runs every committed input of `target` through `harness`, in name order, printing each
/// path first (a failing input is the last one printed); returns how many there were.
pub fn replay_inputs(target: &str, harness: impl Fn(&[u8])) -> usize {
    let mut n = 0;
    for kind in ["corpus", "regressions"] {
        let Ok(entries) = std::fs::read_dir(fuzz_dir().join(kind).join(target)) else { continue };
        let mut paths: Vec<PathBuf> = entries.flatten().map(|e| e.path()).filter(|p| p.is_file()).collect();
        paths.sort();
        for path in paths {
            eprintln!("{}", path.display());
            harness(&std::fs::read(&path).unwrap());
            n += 1;
        }
    }
    n
}

/// Writes `seeds` as `fuzz/corpus/<target>/seed-<name>`, when `MAPLESS_WRITE_FUZZ_SEEDS` is
/// set (the seed writers are `#[ignore]`d tests run by hand; docs/reliability.md, "Fuzzing").
pub fn write_seeds(target: &str, seeds: impl IntoIterator<Item = (String, Vec<u8>)>) {
    if std::env::var_os("MAPLESS_WRITE_FUZZ_SEEDS").is_none() {
        return;
    }
    let dir = fuzz_dir().join("corpus").join(target);
    std::fs::create_dir_all(&dir).unwrap();
    for (name, data) in seeds {
        std::fs::write(dir.join(format!("seed-{name}")), data).unwrap();
    }
}
