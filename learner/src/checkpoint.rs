//! Checkpoints: everything needed to resume an [`Agent`] exactly, written atomically, and the
//! policy alone for deployment.
//!
//! A checkpoint is a directory:
//!
//! ```text
//!   <root>/LATEST                      "ckpt-000000012000\n"  (replaced atomically)
//!   <root>/ckpt-000000012000/
//!       manifest.json                  format + version, algorithm, dims, updates, and
//!                                      {bytes, crc32} of each file below
//!       state.json                     config, counters, Adam step counts, PCG64 states,
//!                                      exploration state, the caller's `extra` JSON value
//!       tensors.safetensors            every network, target, Adam moment and log α (f32)
//!       policy.safetensors             the actor alone + __metadata__ (see export_policy)
//! ```
//!
//! **Atomic.** A checkpoint is written into `<root>/.ckpt-….tmp` (each file fsynced, then the
//! directory), renamed to its final name (the parent fsynced), and only then does `LATEST`
//! move to it (written as a temporary file, fsynced, renamed over the old one, parent
//! fsynced). A crash at any point leaves `LATEST` naming a complete checkpoint (or absent,
//! before the first one); a stale `.tmp` directory is removed by the next save. Older
//! checkpoints beyond `keep` are pruned after `LATEST` has moved. One writer per root.
//!
//! **Checked on load.** The manifest's format and version, every file's length (a short file
//! is "truncated") and CRC-32, the algorithm and dimensions against what the caller expects,
//! and every tensor's name and shape against the agent. Each failure is a
//! [`LearnerError`] (`CheckpointIo`, `CheckpointCorrupt`, `CheckpointMismatch`) saying what
//! and where; nothing on this path panics.

use std::collections::{BTreeMap, HashMap};
use std::fs::{self, File};
use std::io::Write;
use std::path::{Path, PathBuf};

use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use serde::{Deserialize, Serialize};
use tch::Tensor;

use crate::LearnerError;
use crate::algo::{Agent, AgentMeta};
use crate::config::{AlgorithmKind, LearnerConfig};

/// Written into every manifest; anything else is not ours.
pub const FORMAT: &str = "mapless-learner-checkpoint";
/// Version of the layout above. A checkpoint of another version is refused.
pub const FORMAT_VERSION: u32 = 1;
/// Name of the pointer file in a checkpoint root.
pub const LATEST: &str = "LATEST";
/// The manifest's file name.
pub const MANIFEST: &str = "manifest.json";
/// The scalar state's file name.
pub const STATE: &str = "state.json";
/// The tensors' file name.
pub const TENSORS: &str = "tensors.safetensors";
/// The deployable policy's file name.
pub const POLICY: &str = "policy.safetensors";
/// `format` value in a policy file's metadata.
pub const POLICY_FORMAT: &str = "mapless-policy";
pub use mapless_learner_config::DEFAULT_CHECKPOINT_KEEP as DEFAULT_KEEP;

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Manifest {
    format: String,
    format_version: u32,
    algorithm: AlgorithmKind,
    obs_dim: usize,
    act_dim: usize,
    updates: u64,
    files: BTreeMap<String, FileSum>,
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Eq)]
#[serde(deny_unknown_fields)]
struct FileSum {
    bytes: u64,
    crc32: u32,
}

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct StateFile {
    config: LearnerConfig,
    agent: AgentMeta,
    extra: serde_json::Value,
}

fn io_err(path: &Path, what: &str, e: impl std::fmt::Display) -> LearnerError {
    LearnerError::CheckpointIo { path: path.to_path_buf(), reason: format!("{what}: {e}") }
}

fn corrupt(path: &Path, reason: impl Into<String>) -> LearnerError {
    LearnerError::CheckpointCorrupt { path: path.to_path_buf(), reason: reason.into() }
}

fn mismatch(path: &Path, what: &str, expected: impl ToString, found: impl ToString) -> LearnerError {
    LearnerError::CheckpointMismatch { path: path.to_path_buf(), what: what.into(), expected: expected.to_string(), found: found.to_string() }
}

/// Writes `bytes` to `path` and fsyncs the file.
fn write_synced(path: &Path, bytes: &[u8]) -> Result<(), LearnerError> {
    let mut f = File::create(path).map_err(|e| io_err(path, "create", e))?;
    f.write_all(bytes).map_err(|e| io_err(path, "write", e))?;
    f.sync_all().map_err(|e| io_err(path, "fsync", e))
}

fn sync_dir(dir: &Path) -> Result<(), LearnerError> {
    File::open(dir).and_then(|d| d.sync_all()).map_err(|e| io_err(dir, "fsync directory", e))
}

fn parent_of(path: &Path) -> PathBuf {
    match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    }
}

/// Named f32 tensors (any device) as safetensors bytes with optional `__metadata__`.
fn encode_tensors(tensors: &[(String, Tensor)], metadata: Option<HashMap<String, String>>) -> Result<Vec<u8>, LearnerError> {
    let mut bytes: Vec<(String, Vec<usize>, Vec<u8>)> = Vec::with_capacity(tensors.len());
    for (name, t) in tensors {
        let t = t.to(tch::Device::Cpu).to_kind(tch::Kind::Float).contiguous();
        let values = Vec::<f32>::try_from(&t.reshape([-1]))?;
        let shape = t.size().iter().map(|&d| d as usize).collect();
        bytes.push((name.clone(), shape, values.iter().flat_map(|v| v.to_le_bytes()).collect()));
    }
    let views = bytes
        .iter()
        .map(|(n, s, b)| TensorView::new(Dtype::F32, s.clone(), b).map(|v| (n.as_str(), v)))
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| LearnerError::InvalidNetwork { name: "checkpoint".into(), reason: e.to_string() })?;
    safetensors::serialize(views, metadata).map_err(|e| LearnerError::InvalidNetwork { name: "checkpoint".into(), reason: e.to_string() })
}

/// Parses safetensors bytes into CPU f32 tensors; anything but F32 is corruption.
fn decode_tensors(path: &Path, bytes: &[u8]) -> Result<HashMap<String, Tensor>, LearnerError> {
    let st = SafeTensors::deserialize(bytes).map_err(|e| corrupt(path, format!("safetensors: {e}")))?;
    let mut out = HashMap::new();
    for (name, view) in st.tensors() {
        if view.dtype() != Dtype::F32 {
            return Err(corrupt(path, format!("tensor `{name}` is {:?}, expected F32", view.dtype())));
        }
        let values: Vec<f32> = view.data().chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
        let shape: Vec<i64> = view.shape().iter().map(|&d| d as i64).collect();
        out.insert(name, Tensor::from_slice(&values).view(shape.as_slice()));
    }
    Ok(out)
}

/// The policy file's bytes: [`Agent::policy_tensors`] with [`Agent::policy_metadata`] plus
/// `format` = `mapless-policy` and `format_version` as `__metadata__`.
fn policy_bytes(agent: &Agent) -> Result<Vec<u8>, LearnerError> {
    let mut meta: HashMap<String, String> = agent.policy_metadata().into_iter().collect();
    meta.insert("format".into(), POLICY_FORMAT.into());
    meta.insert("format_version".into(), FORMAT_VERSION.to_string());
    encode_tensors(&agent.policy_tensors(), Some(meta))
}

/// Writes the policy alone to `path` (atomically): `actor.*` tensors as documented in
/// [`crate::algo`], `__metadata__` with `algorithm`, `obs_dim`, `act_dim`, `hidden_width`,
/// `version` (update counter), `format`, `format_version` and, for SAC, `sac.log_std_min` /
/// `sac.log_std_max`.
pub fn export_policy(agent: &Agent, path: &Path) -> Result<(), LearnerError> {
    Ok(mapless_proto::atomic_file::write_file_atomically(path, &policy_bytes(agent)?)?)
}

/// A policy file read back: tensors `(name, shape, values)` sorted by name, and the metadata.
#[derive(Debug, Clone, PartialEq)]
pub struct PolicyFile {
    /// `(name, shape, row-major values)`.
    pub tensors: Vec<(String, Vec<usize>, Vec<f32>)>,
    /// `__metadata__`.
    pub metadata: BTreeMap<String, String>,
}

/// Reads a file written by [`export_policy`] (or a checkpoint's `policy.safetensors`).
pub fn read_policy(path: &Path) -> Result<PolicyFile, LearnerError> {
    let bytes = fs::read(path).map_err(|e| io_err(path, "read", e))?;
    let (_, header) = SafeTensors::read_metadata(&bytes).map_err(|e| corrupt(path, format!("safetensors: {e}")))?;
    let metadata: BTreeMap<String, String> = header.metadata().clone().unwrap_or_default().into_iter().collect();
    if metadata.get("format").map(String::as_str) != Some(POLICY_FORMAT) {
        return Err(corrupt(path, "no `format: mapless-policy` metadata"));
    }
    let mut tensors: Vec<_> = decode_tensors(path, &bytes)?
        .into_iter()
        .map(|(n, t)| {
            let shape = t.size().iter().map(|&d| d as usize).collect();
            let values = Vec::<f32>::try_from(&t.reshape([-1])).unwrap_or_default();
            (n, shape, values)
        })
        .collect();
    tensors.sort_by(|a, b| a.0.cmp(&b.0));
    Ok(PolicyFile { tensors, metadata })
}

/// Writes a complete checkpoint of `agent` (plus the caller's `extra` JSON, e.g. its
/// training loop's state) to the new directory `dir`, atomically: it appears complete or
/// not at all. `dir` must not exist yet.
///
/// `extra` is a `serde_json::Value`, which cannot hold integers beyond 64 bits: state with
/// u128s in it (a `rand_pcg::Pcg64`) should go in as a JSON *string*
/// (`Value::String(serde_json::to_string(&state)?)`).
pub fn write_checkpoint(dir: &Path, agent: &Agent, extra: &serde_json::Value) -> Result<(), LearnerError> {
    if dir.exists() {
        return Err(io_err(dir, "create", "already exists"));
    }
    let parent = parent_of(dir);
    let name = dir.file_name().and_then(|n| n.to_str()).ok_or_else(|| io_err(dir, "create", "no directory name"))?;
    let tmp = parent.join(format!(".{name}.tmp"));
    if tmp.exists() {
        fs::remove_dir_all(&tmp).map_err(|e| io_err(&tmp, "remove stale temporary", e))?;
    }
    fs::create_dir_all(&tmp).map_err(|e| io_err(&tmp, "create", e))?;
    // A save that fails (a full disk, an I/O error) takes its temporary directory with it: the
    // space it held is what the next save needs.
    let written = write_into(&tmp, dir, agent, extra).and_then(|()| fs::rename(&tmp, dir).map_err(|e| io_err(dir, "rename into place", e)));
    if let Err(e) = written {
        let _ = fs::remove_dir_all(&tmp);
        return Err(e);
    }
    sync_dir(&parent)
}

/// The checkpoint's files, written and synced in `tmp` (which becomes `dir`).
fn write_into(tmp: &Path, dir: &Path, agent: &Agent, extra: &serde_json::Value) -> Result<(), LearnerError> {
    let state = StateFile { config: agent.config().clone(), agent: agent.state_meta(), extra: extra.clone() };
    let state = serde_json::to_vec_pretty(&state).map_err(|e| io_err(dir, "encode state", e))?;
    let tensors = encode_tensors(&agent.state_tensors(), None)?;
    let policy = policy_bytes(agent)?;
    let mut files = BTreeMap::new();
    for (file, bytes) in [(STATE, &state), (TENSORS, &tensors), (POLICY, &policy)] {
        write_synced(&tmp.join(file), bytes)?;
        files.insert(file.to_string(), FileSum { bytes: bytes.len() as u64, crc32: crc32fast::hash(bytes) });
    }
    let manifest =
        Manifest { format: FORMAT.into(), format_version: FORMAT_VERSION, algorithm: agent.config().algorithm, obs_dim: agent.obs_dim(), act_dim: agent.act_dim(), updates: agent.updates(), files };
    let manifest = serde_json::to_vec_pretty(&manifest).map_err(|e| io_err(dir, "encode manifest", e))?;
    write_synced(&tmp.join(MANIFEST), &manifest)?;
    sync_dir(tmp)
}

/// Saves a checkpoint under `root` as `ckpt-<updates>` (see the module docs), points
/// `LATEST` at it, and prunes all but the newest `keep` (≥ 1) checkpoints. Returns its path.
pub fn save(root: &Path, agent: &Agent, extra: &serde_json::Value, keep: usize) -> Result<PathBuf, LearnerError> {
    fs::create_dir_all(root).map_err(|e| io_err(root, "create", e))?;
    // Leftovers of a save that crashed before its rename (one writer per root).
    for entry in fs::read_dir(root).map_err(|e| io_err(root, "list", e))?.flatten() {
        let name = entry.file_name();
        let name = name.to_string_lossy();
        if name.starts_with(".ckpt-") && name.ends_with(".tmp") {
            fs::remove_dir_all(entry.path()).map_err(|e| io_err(&entry.path(), "remove stale temporary", e))?;
        }
    }
    let base = format!("ckpt-{:012}", agent.updates());
    let mut name = base.clone();
    let mut k = 1;
    while root.join(&name).exists() {
        name = format!("{base}.{k}");
        k += 1;
    }
    let dir = root.join(&name);
    write_checkpoint(&dir, agent, extra)?;
    if let Err(e) = mapless_proto::atomic_file::write_file_atomically(&root.join(LATEST), format!("{name}\n").as_bytes()) {
        // Up to the rename, LATEST still names the previous checkpoint, and this one, which
        // nothing names, would only hold the space a full disk lacks. A failed fsync of the
        // directory comes after the rename: LATEST may name this one, which must stay.
        if e.step != mapless_proto::atomic_file::AtomicWriteStep::SyncDir {
            let _ = fs::remove_dir_all(&dir);
        }
        return Err(e.into());
    }

    let mut all: Vec<String> = fs::read_dir(root).map_err(|e| io_err(root, "list", e))?.filter_map(|e| e.ok()?.file_name().into_string().ok()).filter(|n| n.starts_with("ckpt-")).collect();
    all.sort();
    let keep = keep.max(1);
    for old in all.iter().take(all.len().saturating_sub(keep)) {
        if *old != name {
            fs::remove_dir_all(root.join(old)).map_err(|e| io_err(&root.join(old), "prune", e))?;
        }
    }
    Ok(dir)
}

/// The checkpoint directory `path` names: `path` itself when it holds a manifest, otherwise
/// the one its `LATEST` names.
pub fn resolve(path: &Path) -> Result<PathBuf, LearnerError> {
    if path.join(MANIFEST).is_file() {
        return Ok(path.to_path_buf());
    }
    let latest = path.join(LATEST);
    match fs::read_to_string(&latest) {
        Ok(s) => {
            let name = s.trim();
            if name.is_empty() || name.contains('/') || name.contains("..") {
                return Err(corrupt(&latest, format!("names {name:?}")));
            }
            Ok(path.join(name))
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Err(corrupt(path, format!("neither `{MANIFEST}` nor `{LATEST}`: not a checkpoint, or one never completed"))),
        Err(e) => Err(io_err(&latest, "read", e)),
    }
}

/// A checkpoint read and verified, not yet turned into an agent.
struct Loaded {
    dir: PathBuf,
    manifest: Manifest,
    state: StateFile,
    tensors: HashMap<String, Tensor>,
}

fn read_verified(path: &Path) -> Result<Loaded, LearnerError> {
    let dir = resolve(path)?;
    let mpath = dir.join(MANIFEST);
    let raw = fs::read(&mpath).map_err(|e| match e.kind() {
        std::io::ErrorKind::NotFound => corrupt(&dir, format!("no `{MANIFEST}`")),
        _ => io_err(&mpath, "read", e),
    })?;
    // Format and version first, leniently, so a future layout reads as a version mismatch
    // rather than as corruption.
    let head: serde_json::Value = serde_json::from_slice(&raw).map_err(|e| corrupt(&mpath, format!("not JSON: {e}")))?;
    if head.get("format").and_then(|f| f.as_str()) != Some(FORMAT) {
        return Err(corrupt(&mpath, format!("`format` is not `{FORMAT}`")));
    }
    let version = head.get("format_version").and_then(|v| v.as_u64());
    if version != Some(u64::from(FORMAT_VERSION)) {
        return Err(mismatch(&dir, "format version", FORMAT_VERSION, version.map_or("missing".into(), |v| v.to_string())));
    }
    let manifest: Manifest = serde_json::from_value(head).map_err(|e| corrupt(&mpath, format!("manifest: {e}")))?;
    let mut contents = HashMap::new();
    for file in [STATE, TENSORS, POLICY] {
        let sum = manifest.files.get(file).ok_or_else(|| corrupt(&mpath, format!("lists no `{file}`")))?;
        let fpath = dir.join(file);
        let bytes = fs::read(&fpath).map_err(|e| match e.kind() {
            std::io::ErrorKind::NotFound => corrupt(&fpath, "missing"),
            _ => io_err(&fpath, "read", e),
        })?;
        if bytes.len() as u64 != sum.bytes {
            let how = if (bytes.len() as u64) < sum.bytes { "truncated: " } else { "" };
            return Err(corrupt(&fpath, format!("{how}{} bytes, the manifest says {}", bytes.len(), sum.bytes)));
        }
        let crc = crc32fast::hash(&bytes);
        if crc != sum.crc32 {
            return Err(corrupt(&fpath, format!("checksum mismatch (stored {:#010x}, computed {crc:#010x})", sum.crc32)));
        }
        contents.insert(file, bytes);
    }
    let spath = dir.join(STATE);
    let state: StateFile = serde_json::from_slice(&contents[STATE]).map_err(|e| corrupt(&spath, format!("state: {e}")))?;
    if state.config.algorithm != manifest.algorithm {
        return Err(corrupt(&spath, "config's algorithm differs from the manifest's"));
    }
    let tensors = decode_tensors(&dir.join(TENSORS), &contents[TENSORS])?;
    Ok(Loaded { dir, manifest, state, tensors })
}

/// Loads the checkpoint at `path` (a checkpoint directory, or a root with `LATEST`) into a
/// new agent built from the stored config, with `device` overriding the stored device when
/// given. Returns the agent and the caller's `extra` JSON.
pub fn load(path: &Path, device: Option<&str>) -> Result<(Agent, serde_json::Value), LearnerError> {
    let l = read_verified(path)?;
    let mut cfg = l.state.config.clone();
    if let Some(d) = device {
        cfg.device = d.to_string();
    }
    // The agent is built from the stored sizes before its tensors are checked against it, so
    // sizes that no stored tensor could fill (a manifest's digits damaged, a forged state) are
    // refused first, not handed to libtorch as an allocation it cannot make. The actor alone
    // holds a hidden × (obs_dim + act_dim) and a hidden × hidden matrix.
    let stored: i64 = l.tensors.values().map(Tensor::numel).map(|n| i64::try_from(n).unwrap_or(i64::MAX)).fold(0, i64::saturating_add);
    let (obs, act) = (i64::try_from(l.manifest.obs_dim).unwrap_or(i64::MAX), i64::try_from(l.manifest.act_dim).unwrap_or(i64::MAX));
    let needed = cfg.hidden_width.saturating_mul(cfg.hidden_width.max(obs.saturating_add(act)));
    if needed > stored {
        return Err(corrupt(&l.dir, format!("hidden_width {}, obs_dim {obs} and act_dim {act} need at least {needed} parameters; `{TENSORS}` holds {stored}", cfg.hidden_width)));
    }
    let mut agent = Agent::new(&cfg, l.manifest.obs_dim, l.manifest.act_dim)?;
    agent.restore_state(&l.tensors, l.state.agent).map_err(|reason| corrupt(&l.dir, reason))?;
    Ok((agent, l.state.extra))
}

/// Restores the checkpoint at `path` into `agent`, which must have the same algorithm,
/// dimensions, hidden width and critic normalisation (`critic_layer_norm` changes no
/// tensor's shape, only what the stored critics compute), and must keep a running average of
/// its actor if the checkpoint does (`policy_average`; its τ̄ may differ); the agent keeps its own config
/// otherwise (e.g. a changed learning rate or device). Returns the caller's `extra` JSON. On error `agent` may be
/// partly overwritten: discard it.
pub fn restore(agent: &mut Agent, path: &Path) -> Result<serde_json::Value, LearnerError> {
    let l = read_verified(path)?;
    let (m, have) = (&l.manifest, agent.config());
    if m.algorithm != have.algorithm {
        return Err(mismatch(&l.dir, "algorithm", have.algorithm.as_str(), m.algorithm.as_str()));
    }
    if m.obs_dim != agent.obs_dim() {
        return Err(mismatch(&l.dir, "obs_dim", agent.obs_dim(), m.obs_dim));
    }
    if m.act_dim != agent.act_dim() {
        return Err(mismatch(&l.dir, "act_dim", agent.act_dim(), m.act_dim));
    }
    if l.state.config.hidden_width != have.hidden_width {
        return Err(mismatch(&l.dir, "hidden_width", have.hidden_width, l.state.config.hidden_width));
    }
    if l.state.config.critic_layer_norm != have.critic_layer_norm {
        return Err(mismatch(&l.dir, "critic_layer_norm", have.critic_layer_norm, l.state.config.critic_layer_norm));
    }
    // Whether the actor's running average is kept decides whether its tensors are stored.
    let (stored, kept) = (l.state.config.policy_average.is_some(), have.policy_average.is_some());
    if stored != kept {
        return Err(mismatch(&l.dir, "policy_average (kept)", kept, stored));
    }
    agent.restore_state(&l.tensors, l.state.agent).map_err(|reason| mismatch(&l.dir, "tensors", "this agent's layout", reason))?;
    Ok(l.state.extra)
}
