//! The harness of the `checkpoint_files` fuzz target (`fuzz/fuzz_targets/checkpoint_files.rs`),
//! here so that the same code runs on stable (`tests/fuzz_corpora.rs` replays the committed
//! inputs): a valid checkpoint written by [`checkpoint::save`], edited as a damaged or forged
//! one would be, then read back by [`checkpoint::load`] and [`checkpoint::restore`], as
//! `mapless-learner` does when it resumes.
//!
//! Input: `base u8 | edit*`. The base picks the algorithm (DDPG, TD3, SAC: `base % 3`) of a
//! small agent (17 observations, 2 actions, 8 hidden units) whose checkpoint is written once
//! per base and kept in memory; each input lays its files out in a fresh directory and applies
//! its edits ([`op`]) to them. Checked after every input:
//! - nothing panics (and nothing aborts on an absurd allocation);
//! - an unedited checkpoint loads and, written again, gives back the same tensors byte for byte
//!   and the same policy (tensors and metadata; the metadata map is written in no fixed order);
//! - a checkpoint whose state, tensors or policy file was changed without the manifest's sums
//!   being recomputed ([`op::FIX_SUMS`]) is refused: a damaged file is never loaded;
//! - whatever loads restores into a fresh agent of its own configuration too, or is refused.

use std::collections::BTreeMap;
use std::fs;
use std::path::PathBuf;
use std::sync::OnceLock;
use std::sync::atomic::{AtomicU64, Ordering};

use mapless_learner_config::{AlgorithmKind, LearnerConfig};

use crate::algo::Agent;
use crate::checkpoint::{self, LATEST, MANIFEST, POLICY, STATE, TENSORS};

/// Observation and action sizes of the harness's agents.
pub const OBS_DIM: usize = 17;
pub const ACT_DIM: usize = 2;
const HIDDEN: i64 = 8;

/// The files an edit can name (`file % FILES.len()`): the checkpoint's four and `LATEST`.
pub const FILES: [&str; 5] = [MANIFEST, STATE, TENSORS, POLICY, LATEST];

/// Edit codes (`code % 7`), each followed by its operands.
pub mod op {
    /// file u8, offset u16 LE, xor u8: flips bits of one byte.
    pub const FLIP: u8 = 0;
    /// file u8, length u16 LE: cuts the file to `length % (len + 1)` bytes.
    pub const TRUNCATE: u8 = 1;
    /// file u8, offset u16 LE, n u8, n bytes: overwrites bytes (extending the file if need be).
    pub const OVERWRITE: u8 = 2;
    /// file u8, offset u16 LE, n u8, n bytes: inserts bytes.
    pub const INSERT: u8 = 3;
    /// file u8: deletes the file.
    pub const DELETE: u8 = 4;
    /// file u8, n u8, n bytes: replaces the file's contents.
    pub const REPLACE: u8 = 5;
    /// (no operand): recomputes the manifest's byte counts and CRCs of the state, tensors and
    /// policy files, when the manifest still parses as JSON, so that the edits before it pass
    /// them (a forged checkpoint, contents its writer never wrote).
    pub const FIX_SUMS: u8 = 6;
}

/// A small agent of `algorithm` with a fixed seed.
pub fn seed_agent(algorithm: AlgorithmKind) -> Agent {
    let cfg = LearnerConfig { algorithm, hidden_width: HIDDEN, device: "cpu".into(), batch_size: 4, ..LearnerConfig::default() };
    Agent::new(&cfg, OBS_DIM, ACT_DIM).expect("the harness's agent")
}

/// Where the harness writes its scratch files: `/dev/shm` where it is a directory (memory; on
/// a disk-backed temp dir each input's mkdir, writes and unlinks made the fuzzer 1.7 times
/// slower, docs/reliability.md), else the temp dir.
fn scratch_root() -> PathBuf {
    let shm = std::path::Path::new("/dev/shm");
    if shm.is_dir() { shm.to_path_buf() } else { std::env::temp_dir() }
}

/// A fresh, empty directory under [`scratch_root`] (removed by [`Scratch`]'s drop).
struct Scratch(PathBuf);

impl Scratch {
    fn new() -> Scratch {
        static N: AtomicU64 = AtomicU64::new(0);
        let p = scratch_root().join(format!("mapless-fuzz-ckpt-{}-{}", std::process::id(), N.fetch_add(1, Ordering::Relaxed)));
        let _ = fs::remove_dir_all(&p);
        fs::create_dir_all(&p).expect("scratch directory");
        Scratch(p)
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = fs::remove_dir_all(&self.0);
    }
}

/// The files of a checkpoint of [`seed_agent`] for `base`: name → bytes, `LATEST` included
/// (it names the directory `ckpt`).
fn base_files(base: u8) -> &'static BTreeMap<&'static str, Vec<u8>> {
    static BASES: OnceLock<[BTreeMap<&'static str, Vec<u8>>; 3]> = OnceLock::new();
    &BASES.get_or_init(|| {
        [AlgorithmKind::Ddpg, AlgorithmKind::Td3, AlgorithmKind::Sac].map(|algorithm| {
            let scratch = Scratch::new();
            let dir = checkpoint::save(&scratch.0, &seed_agent(algorithm), &serde_json::json!({"episodes": 3}), 1).expect("save");
            let mut files: BTreeMap<&'static str, Vec<u8>> = [MANIFEST, STATE, TENSORS, POLICY].into_iter().map(|f| (f, fs::read(dir.join(f)).expect("read back"))).collect();
            files.insert(LATEST, b"ckpt\n".to_vec());
            files
        })
    })[usize::from(base % 3)]
}

/// Little-endian u16 at the front of `data`, or 0.
fn take_u16(data: &mut &[u8]) -> usize {
    let v = match data {
        [a, b, ..] => u16::from_le_bytes([*a, *b]),
        _ => 0,
    };
    *data = data.get(2..).unwrap_or(&[]);
    usize::from(v)
}

fn take_u8(data: &mut &[u8]) -> u8 {
    let v = data.first().copied().unwrap_or(0);
    *data = data.get(1..).unwrap_or(&[]);
    v
}

fn take_bytes<'a>(data: &mut &'a [u8]) -> &'a [u8] {
    let n = usize::from(take_u8(data)).min(data.len());
    let (head, tail) = data.split_at(n);
    *data = tail;
    head
}

/// Recomputes the manifest's sums for the files present; false when the manifest is not a
/// JSON object with a `files` object.
fn fix_sums(files: &mut BTreeMap<&'static str, Vec<u8>>) -> bool {
    let Some(Ok(mut manifest)) = files.get(MANIFEST).map(|m| serde_json::from_slice::<serde_json::Value>(m)) else { return false };
    let Some(sums) = manifest.get_mut("files").and_then(|f| f.as_object_mut()) else { return false };
    for name in [STATE, TENSORS, POLICY] {
        if let Some(bytes) = files.get(name) {
            sums.insert(name.into(), serde_json::json!({"bytes": bytes.len(), "crc32": crc32fast::hash(bytes)}));
        }
    }
    files.insert(MANIFEST, serde_json::to_vec_pretty(&manifest).expect("JSON"));
    true
}

/// The harness: see the module doc.
pub fn checkpoint_files(data: &[u8]) {
    let Some((&base, mut data)) = data.split_first() else { return };
    let original = base_files(base);
    let mut files = original.clone();
    let mut forged = false;
    while let Some(&code) = data.first() {
        data = &data[1..];
        let code = code % 7;
        if code == op::FIX_SUMS {
            forged |= fix_sums(&mut files);
            continue;
        }
        let name = FILES[usize::from(take_u8(&mut data)) % FILES.len()];
        match code {
            op::DELETE => {
                files.remove(name);
            }
            op::REPLACE => {
                files.insert(name, take_bytes(&mut data).to_vec());
            }
            _ => {
                let Some(bytes) = files.get_mut(name) else { continue };
                let at = take_u16(&mut data);
                match code {
                    op::FLIP => {
                        let xor = take_u8(&mut data);
                        if !bytes.is_empty() {
                            let i = at % bytes.len();
                            bytes[i] ^= xor;
                        }
                    }
                    op::TRUNCATE => bytes.truncate(at % (bytes.len() + 1)),
                    op::OVERWRITE => {
                        let new = take_bytes(&mut data);
                        let at = at.min(bytes.len());
                        if bytes.len() < at + new.len() {
                            bytes.resize(at + new.len(), 0);
                        }
                        bytes[at..at + new.len()].copy_from_slice(new);
                    }
                    _ => {
                        let new = take_bytes(&mut data);
                        let at = at.min(bytes.len());
                        bytes.splice(at..at, new.iter().copied());
                    }
                }
            }
        }
    }

    let scratch = Scratch::new();
    let dir = scratch.0.join("ckpt");
    fs::create_dir_all(&dir).expect("checkpoint directory");
    for (name, bytes) in &files {
        let path = if *name == LATEST { scratch.0.join(name) } else { dir.join(name) };
        fs::write(path, bytes).expect("write a file");
    }
    let unedited = files == *original;
    let damaged = !forged && [STATE, TENSORS, POLICY].iter().any(|f| files.get(f) != original.get(f));
    match checkpoint::load(&scratch.0, None) {
        Ok((agent, _)) => {
            assert!(!damaged, "loaded a checkpoint whose data files differ from what was written, without forged sums");
            if unedited {
                let again = Scratch::new();
                let dir2 = checkpoint::save(&again.0, &agent, &serde_json::json!({"episodes": 3}), 1).expect("save again");
                assert_eq!(fs::read(dir2.join(TENSORS)).expect("read"), original[TENSORS], "tensors changed in a load and save");
                // The policy file's metadata is a map written in no fixed order: compare contents.
                let (a, b) = (checkpoint::read_policy(&dir2.join(POLICY)).expect("policy written"), checkpoint::read_policy(&dir.join(POLICY)).expect("policy loaded"));
                assert_eq!(a, b, "policy changed in a load and save");
            }
            let mut fresh = Agent::new(agent.config(), agent.obs_dim(), agent.act_dim()).expect("an agent like the loaded one");
            let _ = checkpoint::restore(&mut fresh, &scratch.0);
        }
        Err(e) => assert!(!unedited, "the unedited checkpoint did not load: {e}"),
    }
}

/// `base u8 | edit*` as bytes, for seeds.
pub fn input(base: u8, edits: &[&[u8]]) -> Vec<u8> {
    let mut out = vec![base];
    for e in edits {
        out.extend_from_slice(e);
    }
    out
}
