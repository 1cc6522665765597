//! Harnesses of the coverage-guided fuzz targets (`fuzz/` at the repository root, run with
//! `cargo +nightly fuzz run <target>`; docs/reliability.md, "Fuzzing"). Each takes arbitrary
//! bytes, drives the code that meets outside bytes exactly as the server does, and panics only
//! when an invariant breaks, never on the input's account. `replay/tests/fuzz_corpora.rs`
//! replays the committed corpora and regression inputs through the same functions on stable.
//!
//! ```text
//!   replay_ingest  [config byte] frame*        frame = len u16 | prost TransitionBatch
//!                  decode (as tonic does) ─► Table::insert          (the gRPC Insert path)
//!   shm_wire       [config byte] frame*        frame = len u16 | sequence u64 | id_len u8
//!                                                      | id bytes | prost TransitionBatch
//!                  BatchHeader::actor_id ─► shm::decode_payload ─► Table::insert_encoded
//!                                                                   (the shared-memory path)
//!   replay_requests [config byte] frame*       frame = len u16 | kind u8 | prost message
//!                  kind % 3 = 0: TransitionBatch ─► Table::insert           (Insert)
//!                             1: SampleRequest ─► validate ─► Table::sample_as (Sample)
//!                             2: PriorityUpdate ─► validate ─► Table::update_priorities
//!                  (the config byte also picks the priority exponent α and ε)
//!   wal_recovery   [base byte] op*             a valid directory written by DurableTable,
//!                  then flipped, truncated, swapped, deleted, copied bytes and files
//!                  ─► persist::recovery::recover, twice
//!   actor_slots    [max byte] frame*           the first frame: an actor-slots.json; then
//!                  prost RegisterActorRequest ─► protocol version ─► ActorRegistry::register
//!                  (the RegisterActor path), and the file reopened
//! ```
//!
//! After every frame the ingest harnesses compare the table with a model of what it must
//! hold: the newest `capacity` rows accepted, bit for bit, under the keys they were given; a
//! rejected batch or a duplicate (actor, sequence) changes nothing; every sampled row is a
//! stored row and every minibatch passes `SampledBatch::validate`. The recovery harness checks
//! that recovery never panics, never loads a row that was not written (unless the input forged
//! records with valid checksums), leaves a table whose bookkeeping is consistent and whose
//! minibatches validate, and that a second recovery of what the first left finds a clean log
//! and the same rows.

use std::collections::{BTreeMap, HashMap, HashSet, VecDeque};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::Instant;

use mapless_net::shm::BatchHeader;
use mapless_proto::v1::{PriorityUpdate, RegisterActorRequest, SampleRequest, SampledBatch, TransitionBatch};
use mapless_proto::{FloatColumn, FloatEncoding, MAX_ACTOR_ID_BYTES, Transition, TransitionBatchBuilder, check_actor_name, check_protocol_version};
use prost::Message;
use prost::bytes::Bytes;

use crate::config::{FsyncPolicy, PersistenceConfig, RateLimiterConfig, SamplerConfig, TableConfig};
use crate::error::ReplayError;
use crate::persist::DurableTable;
use crate::registry::{ActorRegistry, RegistryCounts, SLOTS_FILE};
use crate::snapshot::SnapshotStore;
use crate::table::{Journal, StoredRow, Table};

/// Dims of every fuzzed table (seeds are written for them).
pub const OBS_DIM: usize = 3;
pub const ACT_DIM: usize = 2;
const MAX_BATCH_ROWS: usize = 16;
const MAX_SAMPLE_ROWS: usize = 8;

/// The table a config byte picks: uniform or prioritised, ring of 8 or 5 rows.
fn ingest_config(byte: u8) -> TableConfig {
    TableConfig {
        name: "fuzz".into(),
        capacity: if byte & 2 == 0 { 8 } else { 5 },
        obs_dim: OBS_DIM,
        act_dim: ACT_DIM,
        sampler: if byte & 1 == 0 { SamplerConfig::Uniform } else { SamplerConfig::Prioritized { alpha: 0.6, beta: 0.4, epsilon: 1e-6 } },
        max_times_sampled: 0,
        rate_limiter: RateLimiterConfig { min_size_to_sample: 1, samples_per_insert: None, error_buffer: 100.0 },
        max_batch_rows: MAX_BATCH_ROWS,
        max_sample_rows: MAX_SAMPLE_ROWS,
    }
}

/// Splits `data` into frames of `len u16 (LE) | len bytes` (the last one cut short if the data
/// ends early).
fn frames(mut data: &[u8]) -> impl Iterator<Item = &[u8]> {
    std::iter::from_fn(move || {
        if data.len() < 2 {
            return None;
        }
        let len = (u16::from_le_bytes([data[0], data[1]]) as usize).min(data.len() - 2);
        let (frame, rest) = data[2..].split_at(len);
        data = rest;
        Some(frame)
    })
}

/// Frames `chunks` as [`frames`] reads them, after a config byte (for writing seeds).
pub fn frame_all(config: u8, chunks: &[Vec<u8>]) -> Vec<u8> {
    let mut out = vec![config];
    for c in chunks {
        out.extend_from_slice(&(c.len().min(u16::MAX as usize) as u16).to_le_bytes());
        out.extend_from_slice(&c[..c.len().min(u16::MAX as usize)]);
    }
    out
}

/// Floats `i*w..(i+1)*w` of a validated column.
fn floats(c: FloatColumn<'_>, i: usize, w: usize) -> Vec<f32> {
    c.slice(i * w, (i + 1) * w).expect("validated column holds the row").to_vec()
}

/// Row `i` of a validated batch, stored under `key`.
fn batch_row(b: &TransitionBatch, i: usize, key: u64) -> StoredRow {
    StoredRow {
        key,
        obs: floats(b.obs_column(), i, OBS_DIM),
        action: floats(b.action_column(), i, ACT_DIM),
        reward: b.reward_column().get(i).expect("validated reward"),
        next_obs: floats(b.next_obs_column(), i, OBS_DIM),
        terminal: b.terminal[i],
        truncated: b.truncated[i],
        episode_id: b.episode_id[i],
        step: b.step[i],
        policy_version: b.policy_version[i],
    }
}

/// Row `i` of a minibatch (validated by the caller), with its key.
fn sampled_row(b: &SampledBatch, i: usize) -> StoredRow {
    StoredRow {
        key: b.keys[i],
        obs: floats(b.obs_column(), i, OBS_DIM),
        action: floats(b.action_column(), i, ACT_DIM),
        reward: b.reward_column().get(i).expect("validated reward"),
        next_obs: floats(b.next_obs_column(), i, OBS_DIM),
        terminal: b.terminal[i],
        truncated: b.truncated[i],
        episode_id: b.episode_id[i],
        step: b.step[i],
        policy_version: b.policy_version[i],
    }
}

/// Bit-for-bit equality (so -0.0 ≠ 0.0 and a NaN never matches).
fn same_row(a: &StoredRow, b: &StoredRow) -> bool {
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    (a.key, a.terminal, a.truncated, a.episode_id, a.step, a.policy_version) == (b.key, b.terminal, b.truncated, b.episode_id, b.step, b.policy_version)
        && a.reward.to_bits() == b.reward.to_bits()
        && bits(&a.obs) == bits(&b.obs)
        && bits(&a.action) == bits(&b.action)
        && bits(&a.next_obs) == bits(&b.next_obs)
}

/// Draws minibatches in both encodings (when the table holds rows) and checks each against
/// `lookup`: it validates, and each of its rows is the stored row of its key.
fn check_samples(table: &Table, lookup: impl Fn(u64) -> Option<StoredRow>) {
    let size = table.size() as usize;
    if size == 0 {
        return;
    }
    for floats in [FloatEncoding::Packed, FloatEncoding::F32Le] {
        let rows = size.min(MAX_SAMPLE_ROWS);
        let batch = match table.sample_as(rows, None, Some(Instant::now()), floats) {
            Ok(b) => b,
            Err(ReplayError::DeadlineExceeded { .. }) => return, // the rate limiter's call
            Err(e) => panic!("sampling {rows} of {size} rows failed: {e}"),
        };
        if let Err(e) = batch.validate(OBS_DIM, ACT_DIM, MAX_SAMPLE_ROWS) {
            panic!("the table served a minibatch that does not validate: {e}; probabilities {:?} weights {:?}", batch.probabilities, batch.importance_weights);
        }
        assert_eq!(batch.num_rows as usize, rows, "asked for {rows} rows");
        for i in 0..rows {
            let got = sampled_row(&batch, i);
            match lookup(got.key) {
                Some(want) => assert!(same_row(&got, &want), "sampled key {} is {got:?}, stored {want:?}", got.key),
                None => panic!("sampled key {} is not a stored row", got.key),
            }
        }
    }
}

/// What an ingest-fed table must hold.
struct Model {
    cap: usize,
    rows: VecDeque<StoredRow>,
    next_key: u64,
    last_sequence: HashMap<String, u64>,
    rejected: HashMap<String, u64>,
}

impl Model {
    fn new(cap: usize) -> Model {
        Model { cap, rows: VecDeque::new(), next_key: 0, last_sequence: HashMap::new(), rejected: HashMap::new() }
    }

    fn store(&mut self, b: &TransitionBatch, rows: usize) {
        for i in 0..rows {
            self.rows.push_back(batch_row(b, i, self.next_key));
            self.next_key += 1;
            if self.rows.len() > self.cap {
                self.rows.pop_front();
            }
        }
        self.last_sequence.insert(b.actor_id.clone(), b.sequence);
    }

    /// The key of the oldest row stored.
    fn first_key(&self) -> u64 {
        self.next_key - self.rows.len() as u64
    }

    fn reject(&mut self, actor_id: &str) {
        let id = if actor_id.is_empty() || actor_id.len() > MAX_ACTOR_ID_BYTES { "<invalid actor id>" } else { actor_id };
        *self.rejected.entry(id.to_string()).or_default() += 1;
    }

    /// The table holds exactly what the model says, and samples from it.
    fn check(&self, table: &Table) {
        let stored = table.stored_rows().unwrap_or_else(|e| panic!("table bookkeeping broken: {e}"));
        assert!(stored.len() <= self.cap, "{} rows in a table of capacity {}", stored.len(), self.cap);
        assert_eq!((table.size() as usize, table.next_key()), (self.rows.len(), self.next_key), "size and next key");
        assert_eq!(stored.len(), self.rows.len(), "rows stored");
        for (got, want) in stored.iter().zip(&self.rows) {
            assert!(same_row(got, want), "stored {got:?}, expected {want:?}");
        }
        let actors = table.actors();
        for (id, a) in &actors {
            assert_eq!(a.last_sequence, self.last_sequence.get(id).copied().unwrap_or(0), "last sequence of `{id}`");
            assert_eq!(a.rejected_batches, self.rejected.get(id).copied().unwrap_or(0), "rejections of `{id}`");
        }
        for id in self.last_sequence.keys().chain(self.rejected.keys()) {
            assert!(actors.contains_key(id), "actor `{id}` is missing from the table's statistics");
        }
        let first = self.first_key();
        check_samples(table, |k| k.checked_sub(first).and_then(|i| self.rows.get(i as usize)).cloned());
    }

    /// Applies the table's answer to a decoded `batch` to the model, checking it is the right
    /// answer; returns the rows stored.
    fn apply(&mut self, batch: &TransitionBatch, result: Result<mapless_proto::v1::InsertAck, ReplayError>) -> usize {
        let valid = batch.validate(OBS_DIM, ACT_DIM, MAX_BATCH_ROWS);
        match result {
            Err(e @ (ReplayError::Invalid(_) | ReplayError::BadRequest(_))) => {
                assert!(valid.is_err(), "the table rejected a valid batch: {e}");
                self.reject(&batch.actor_id);
                0
            }
            Err(e) => panic!("insert into a memory table failed: {e}"),
            Ok(ack) => {
                let rows = valid.unwrap_or_else(|e| panic!("the table accepted an invalid batch ({e})"));
                let last = self.last_sequence.get(&batch.actor_id).copied();
                assert_eq!((ack.actor_id.as_str(), ack.sequence), (batch.actor_id.as_str(), batch.sequence), "ack names another batch");
                if ack.duplicate {
                    assert!(last.is_some_and(|l| batch.sequence <= l), "sequence {} of `{}` acked as a duplicate; last stored {last:?}", batch.sequence, batch.actor_id);
                    assert_eq!(ack.accepted_rows, 0);
                    0
                } else {
                    assert!(last.is_none_or(|l| batch.sequence > l), "sequence {} of `{}` stored again (last stored {last:?})", batch.sequence, batch.actor_id);
                    assert_eq!(ack.accepted_rows as usize, rows);
                    self.store(batch, rows);
                    assert_eq!(ack.table_size as usize, self.rows.len(), "ack's table size");
                    rows
                }
            }
        }
    }
}

/// The gRPC Insert path on arbitrary bytes: each frame is decoded with prost as tonic decodes
/// a request message (an undecodable one is counted against the stream as
/// `grpc::InsertSession` counts it), then handed to [`Table::insert`].
pub fn replay_ingest(data: &[u8]) {
    let Some((&config, rest)) = data.split_first() else { return };
    let cfg = ingest_config(config);
    let table = Table::new(cfg.clone(), u64::from(config)).expect("valid config");
    let mut model = Model::new(cfg.capacity);
    for frame in frames(rest) {
        insert_frame(&table, &mut model, frame);
        model.check(&table);
    }
}

/// One Insert message: decoded with prost as tonic decodes it (an undecodable one is counted
/// against the stream as `grpc::InsertSession` counts it), then handed to [`Table::insert`];
/// the model checks the answer.
fn insert_frame(table: &Table, model: &mut Model, bytes: &[u8]) {
    match TransitionBatch::decode(Bytes::copy_from_slice(bytes)) {
        Err(e) => {
            table.record_rejection("", &format!("malformed TransitionBatch: {e}"));
            model.reject("");
        }
        Ok(batch) => {
            let result = table.insert(&batch, Some(Instant::now()));
            model.apply(&batch, result);
        }
    }
}

/// The table a `replay_requests` config byte picks: [`ingest_config`]'s (bits 0–1), with the
/// prioritised sampler's α from bits 2–3 (0.6 as the presets, 1, 3: weights (p + ε)^α that
/// overflow for large priorities, 0: every row alike) and ε from bit 4 (1e-6, or 0: rows of
/// priority 0 have no mass).
fn requests_config(byte: u8) -> TableConfig {
    let mut cfg = ingest_config(byte);
    if let SamplerConfig::Prioritized { alpha, epsilon, .. } = &mut cfg.sampler {
        *alpha = [0.6, 1.0, 3.0, 0.0][usize::from((byte >> 2) & 3)];
        *epsilon = if byte & 16 == 0 { 1e-6 } else { 0.0 };
    }
    cfg
}

/// The replay's other requests on arbitrary bytes, between inserts: each frame's first byte
/// picks the message, the rest is decoded with prost as tonic decodes it and checked as
/// `grpc::ReplayService` checks it before the table sees it. A Sample request that passes is
/// answered with a minibatch of stored rows whose probabilities and importance weights are in
/// (0, 1] (an empty table: the rate limiter's deadline); a priority update that passes is
/// applied to exactly the keys still stored and changes no row. After every frame the table
/// holds what the model says (as in [`replay_ingest`]).
pub fn replay_requests(data: &[u8]) {
    let Some((&config, rest)) = data.split_first() else { return };
    let cfg = requests_config(config);
    let table = Table::new(cfg.clone(), u64::from(config)).expect("valid config");
    let mut model = Model::new(cfg.capacity);
    for frame in frames(rest) {
        let Some((&kind, msg)) = frame.split_first() else { continue };
        match kind % 3 {
            0 => insert_frame(&table, &mut model, msg),
            1 => {
                let Ok(req) = SampleRequest::decode(Bytes::copy_from_slice(msg)) else { continue };
                let Ok(rows) = req.validate(cfg.max_sample_rows) else { continue };
                let floats = if req.float_columns_as_bytes { FloatEncoding::F32Le } else { FloatEncoding::Packed };
                let first = model.first_key();
                match table.sample_as(rows, req.importance_beta.map(f64::from), Some(Instant::now()), floats) {
                    Ok(batch) => {
                        if let Err(e) = batch.validate(OBS_DIM, ACT_DIM, cfg.max_sample_rows) {
                            panic!("a minibatch that does not validate: {e}; probabilities {:?} weights {:?}", batch.probabilities, batch.importance_weights);
                        }
                        assert_eq!(batch.num_rows as usize, rows, "asked for {rows} rows");
                        for i in 0..rows {
                            let got = sampled_row(&batch, i);
                            let want = got.key.checked_sub(first).and_then(|j| model.rows.get(j as usize));
                            assert!(want.is_some_and(|w| same_row(&got, w)), "sampled key {} is {got:?}, stored {want:?}", got.key);
                        }
                        let unit = |x: f64| x > 0.0 && x <= 1.0;
                        assert!(batch.probabilities.iter().all(|&p| unit(p)), "probabilities outside (0, 1]: {:?}", batch.probabilities);
                        assert!(batch.importance_weights.iter().all(|&w| unit(f64::from(w))), "importance weights outside (0, 1]: {:?} (β {:?})", batch.importance_weights, req.importance_beta);
                    }
                    Err(ReplayError::DeadlineExceeded { .. }) => assert_eq!(table.size(), 0, "a table of {} rows refused to sample {rows}", table.size()),
                    Err(e) => panic!("a Sample request that validates ({req:?}) failed: {e}"),
                }
            }
            _ => {
                let Ok(update) = PriorityUpdate::decode(Bytes::copy_from_slice(msg)) else { continue };
                // The server answers FAILED_PRECONDITION for a uniform table, and refuses what
                // does not validate, before the table sees either.
                if cfg.sampler == SamplerConfig::Uniform || update.validate(crate::grpc::MAX_PRIORITY_KEYS).is_err() {
                    continue;
                }
                let first = model.first_key();
                let held = update.keys.iter().filter(|&&k| k >= first && k < model.next_key).count();
                match table.update_priorities(&update.keys, &update.priorities) {
                    Ok((updated, unknown)) => {
                        assert_eq!((updated as usize, unknown as usize), (held, update.keys.len() - held), "(updated, unknown) for keys {:?}; stored keys {first}..{}", update.keys, model.next_key)
                    }
                    Err(e) => panic!("a priority update that validates failed: {e}"),
                }
            }
        }
        model.check(&table);
    }
}

/// A journal that keeps every insert record in memory.
#[derive(Default)]
struct MemJournal {
    inserts: Mutex<Vec<(u64, u64, Vec<u8>)>>,
}

impl Journal for MemJournal {
    fn insert(&self, first_key: u64, rows: u64, _unix_ms: u64, batch_bytes: &[u8]) -> Result<(), ReplayError> {
        self.inserts.lock().unwrap_or_else(|p| p.into_inner()).push((first_key, rows, batch_bytes.to_vec()));
        Ok(())
    }
    fn priorities(&self, _pairs: &[(u64, f64)]) -> Result<(), ReplayError> {
        Ok(())
    }
    fn position(&self) -> u64 {
        self.inserts.lock().unwrap_or_else(|p| p.into_inner()).len() as u64
    }
}

/// One shared-memory request as `shm_wire` frames it: sequence, header actor id (its length
/// byte may exceed the bytes given and [`MAX_ACTOR_ID_BYTES`]), payload.
pub fn shm_frame(sequence: u64, actor_id: &[u8], payload: &[u8]) -> Vec<u8> {
    let mut out = sequence.to_le_bytes().to_vec();
    out.push(actor_id.len().min(255) as u8);
    out.extend_from_slice(&actor_id[..actor_id.len().min(255)]);
    out.extend_from_slice(payload);
    out
}

/// The shared-memory ingest path on arbitrary bytes: each frame is a request header and its
/// payload; the header's actor id is checked (`BatchHeader::actor_id`), the payload decoded
/// and matched to the header (`shm::decode_payload`), and the batch inserted with its payload
/// as the journaled bytes (`Table::insert_encoded`), as `shm::Ingest` does. Besides the
/// model's checks: the journal gets exactly the received bytes, once per stored batch.
pub fn shm_wire(data: &[u8]) {
    let Some((&config, rest)) = data.split_first() else { return };
    let cfg = ingest_config(config);
    let mut table = Table::new(cfg.clone(), u64::from(config)).expect("valid config");
    let journal = Arc::new(MemJournal::default());
    table.set_journal(Arc::clone(&journal) as Arc<dyn Journal>);
    let mut model = Model::new(cfg.capacity);
    for frame in frames(rest) {
        if frame.len() < 9 {
            continue; // no whole header: the transport never delivers one
        }
        let sequence = u64::from_le_bytes(frame[..8].try_into().expect("8 bytes"));
        let id_len = frame[8] as usize;
        let given = id_len.min(MAX_ACTOR_ID_BYTES).min(frame.len() - 9);
        let mut id = [0u8; MAX_ACTOR_ID_BYTES];
        id[..given].copy_from_slice(&frame[9..9 + given]);
        let payload = &frame[9 + given..];
        let header = BatchHeader::from_raw_parts(sequence, id_len as u32, id);
        let journaled = journal.inserts.lock().unwrap_or_else(|p| p.into_inner()).len();
        let next_key = table.next_key();
        let actor = match header.actor_id() {
            Ok(a) => a.to_string(),
            Err(why) => {
                table.record_rejection("", &why);
                model.reject("");
                model.check(&table);
                continue;
            }
        };
        let payload = Bytes::copy_from_slice(payload);
        match crate::shm::decode_payload(&actor, sequence, payload.clone()) {
            Err(why) => {
                table.record_rejection(&actor, &why);
                model.reject(&actor);
            }
            Ok(batch) => {
                assert_eq!((batch.actor_id.as_str(), batch.sequence), (actor.as_str(), sequence), "decode_payload let a mismatched header through");
                let result = table.insert_encoded(&batch, Some(&payload), Some(Instant::now()));
                let stored = model.apply(&batch, result);
                let log = journal.inserts.lock().unwrap_or_else(|p| p.into_inner());
                if stored > 0 {
                    assert_eq!(log.len(), journaled + 1, "one journal record per stored batch");
                    let (first_key, rows, bytes) = &log[journaled];
                    assert_eq!((*first_key, *rows), (next_key, stored as u64), "journaled keys");
                    assert_eq!(bytes.as_slice(), &payload[..], "the journal holds the received bytes");
                    let again = TransitionBatch::decode(bytes.as_slice()).expect("journaled bytes decode");
                    assert_eq!(again, batch, "journaled bytes decode to the stored batch");
                } else {
                    assert_eq!(log.len(), journaled, "nothing journaled for a batch not stored");
                }
            }
        }
        model.check(&table);
    }
}

// ---------------------------------------------------------------------------------------------
// Recovery

/// A valid table directory written by [`DurableTable`], kept in memory, with every row it
/// ever wrote.
struct Base {
    cfg: TableConfig,
    persistence: PersistenceConfig,
    /// Paths relative to the table directory (`wal/…`, `snapshots/…`), sorted, and contents.
    files: Vec<(String, Vec<u8>)>,
    /// Every row inserted, by key.
    written: HashMap<u64, StoredRow>,
    /// Highest sequence inserted per actor.
    sequences: HashMap<String, u64>,
    /// The rows the table held when it was closed, and its next key.
    final_rows: Vec<StoredRow>,
    final_next_key: u64,
}

static SCRATCH: AtomicU64 = AtomicU64::new(0);

/// A fresh, empty directory for one run (under /dev/shm when there is one: recovery fsyncs).
fn scratch_dir() -> PathBuf {
    let root = if Path::new("/dev/shm").is_dir() { PathBuf::from("/dev/shm") } else { std::env::temp_dir() };
    let dir = root.join(format!("mapless-fuzz-{}-{}", std::process::id(), SCRATCH.fetch_add(1, Ordering::Relaxed)));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("create a scratch directory");
    dir
}

/// A batch of `rows` rows of `actor` whose values say where they come from.
fn seed_batch(actor: &str, sequence: u64, rows: usize) -> TransitionBatch {
    let mut b = TransitionBatchBuilder::new(OBS_DIM, ACT_DIM);
    for i in 0..rows {
        let v = sequence as f32 * 10.0 + i as f32;
        let obs = [v, -v, 0.5];
        let next_obs = [v + 1.0, -v - 1.0, -0.0];
        let action = [0.25 * v, 1.0];
        let terminal = i + 1 == rows && sequence.is_multiple_of(3);
        let truncated = i + 1 == rows && sequence % 3 == 1;
        b.push(Transition { obs: &obs, action: &action, reward: -v, next_obs: &next_obs, terminal, truncated, episode_id: sequence, step: i as u32, policy_version: sequence / 2 })
            .expect("seed row fits the dims");
    }
    b.finish(actor, sequence)
}

/// Valid batches for seeds: packed and `*_f32le` encodings, both actors.
pub fn seed_batches() -> Vec<TransitionBatch> {
    (1..=6u64)
        .map(|s| {
            let mut b = seed_batch(if s.is_multiple_of(2) { "actor-b" } else { "actor-a" }, s, 1 + (s as usize * 2) % 5);
            if s % 2 == 1 {
                b.convert_float_columns(FloatEncoding::F32Le);
            }
            b
        })
        .collect()
}

/// Writes one base: `kind` 0 = log only (uniform, capacity 16, several segments); 1 =
/// prioritised with priority updates, removals by `max_times_sampled` and the final snapshot;
/// 2 = prioritised, a snapshot half-way and the log after it (no final snapshot).
fn build_base(kind: u8) -> Base {
    let prioritized = SamplerConfig::Prioritized { alpha: 0.6, beta: 0.4, epsilon: 1e-6 };
    let cfg = TableConfig {
        name: "fuzz".into(),
        capacity: if kind == 0 { 16 } else { 8 },
        obs_dim: OBS_DIM,
        act_dim: ACT_DIM,
        sampler: if kind == 0 { SamplerConfig::Uniform } else { prioritized },
        max_times_sampled: if kind == 1 { 3 } else { 0 },
        rate_limiter: RateLimiterConfig { min_size_to_sample: 1, samples_per_insert: None, error_buffer: 100.0 },
        max_batch_rows: MAX_BATCH_ROWS,
        max_sample_rows: MAX_SAMPLE_ROWS,
    };
    let dir = scratch_dir();
    let persistence = PersistenceConfig { dir: Some(dir.clone()), segment_bytes: 4096, fsync: FsyncPolicy::Never, snapshot_interval_s: 0.0 };
    let (dt, _) = DurableTable::open(cfg.clone(), persistence.clone(), 7).expect("open a fresh durable table");
    let mut written = HashMap::new();
    let mut sequences = HashMap::new();
    let batches: u64 = if kind == 0 { 40 } else { 14 };
    let mut mid_snapshot = None;
    for s in 1..=batches {
        let actor = if s.is_multiple_of(3) { "actor-b" } else { "actor-a" };
        let mut b = seed_batch(actor, s, 1 + (s as usize * 7) % 6);
        if s.is_multiple_of(2) {
            b.convert_float_columns(FloatEncoding::F32Le);
        }
        let first = dt.next_key();
        let ack = dt.insert(&b, None).expect("insert into the base table");
        for i in 0..ack.accepted_rows as usize {
            written.insert(first + i as u64, batch_row(&b, i, first + i as u64));
        }
        sequences.insert(actor.to_string(), s);
        if s.is_multiple_of(4) {
            dt.insert(&b, None).expect("a resend is acknowledged"); // a duplicate: logged nowhere
        }
        if kind > 0 && s.is_multiple_of(2) {
            let m = dt.sample(4.min(dt.size() as usize), None, None).expect("sample the base table");
            let p: Vec<f64> = m.keys.iter().map(|k| (k % 5) as f64 * 0.5).collect();
            dt.update_priorities(&m.keys, &p).expect("update priorities");
        }
        if kind == 2 && s == batches / 2 {
            mid_snapshot = dt.snapshot().expect("snapshot").map(|i| i.path);
        }
    }
    let final_rows = dt.table().stored_rows().expect("base table consistent");
    let final_next_key = dt.next_key();
    dt.close();
    drop(dt);
    let mut files = Vec::new();
    for sub in ["wal", "snapshots"] {
        for entry in std::fs::read_dir(dir.join(sub)).expect("list the base directory").flatten() {
            let path = entry.path();
            if !path.is_file() {
                continue;
            }
            let keep = match kind {
                0 => sub == "wal",
                2 => sub == "wal" || Some(&path) == mid_snapshot.as_ref(),
                _ => true,
            };
            if keep {
                let name = format!("{sub}/{}", entry.file_name().to_string_lossy());
                files.push((name, std::fs::read(&path).expect("read a base file")));
            }
        }
    }
    files.sort();
    let _ = std::fs::remove_dir_all(&dir);
    Base { cfg, persistence, files, written, sequences, final_rows, final_next_key }
}

fn base(kind: u8) -> &'static Base {
    static BASES: [OnceLock<Base>; 3] = [OnceLock::new(), OnceLock::new(), OnceLock::new()];
    let k = kind % 3;
    BASES[k as usize].get_or_init(|| build_base(k))
}

/// The files of base `kind` (for writing seeds and tests).
pub fn base_files(kind: u8) -> Vec<(String, Vec<u8>)> {
    base(kind).files.clone()
}

/// Reads the ops of a `wal_recovery` input.
struct Ops<'a>(&'a [u8]);

impl Ops<'_> {
    fn u8(&mut self) -> Option<u8> {
        let (&b, rest) = self.0.split_first()?;
        self.0 = rest;
        Some(b)
    }
    fn u16(&mut self) -> Option<usize> {
        Some(u16::from_le_bytes([self.u8()?, self.u8()?]) as usize)
    }
    fn bytes(&mut self, n: usize) -> &[u8] {
        let (a, b) = self.0.split_at(n.min(self.0.len()));
        self.0 = b;
        a
    }
}

/// Op codes of a `wal_recovery` input (after its base byte), each followed by its operands.
pub mod op {
    /// file u8, offset u16, xor u8: flips bits of one byte.
    pub const FLIP: u8 = 0;
    /// file u8, length u16: cuts the file to `length % (len + 1)` bytes.
    pub const TRUNCATE: u8 = 1;
    /// file u8, file u8: swaps two files' contents.
    pub const SWAP: u8 = 2;
    /// file u8: deletes the file.
    pub const DELETE: u8 = 3;
    /// file u8, offset u16, n u8, n bytes: overwrites bytes (extending the file if need be).
    pub const OVERWRITE: u8 = 4;
    /// file u8, offset u16, n u8, n bytes: inserts bytes.
    pub const INSERT: u8 = 5;
    /// file u8, number u8: copies the file under the name of another LSN.
    pub const COPY_AS: u8 = 6;
    /// file u8: recomputes the checksums of every whole record (a segment) or of the file (a
    /// snapshot), so that the changes before it pass them (content the writer never wrote).
    pub const FIX_CHECKSUMS: u8 = 7;
}

/// Recomputes the CRCs a segment's records or a snapshot carry.
fn fix_checksums(name: &str, data: &mut [u8]) {
    if name.starts_with("snapshots/") {
        if data.len() >= 4 {
            let n = data.len() - 4;
            let crc = crc32fast::hash(&data[..n]);
            data[n..].copy_from_slice(&crc.to_le_bytes());
        }
        return;
    }
    let mut pos = crate::wal::SEGMENT_HEADER_BYTES;
    while pos + 8 <= data.len() {
        let len = u32::from_le_bytes(data[pos..pos + 4].try_into().expect("4 bytes")) as usize;
        let Some(end) = (pos + 8).checked_add(len).filter(|&e| e <= data.len()) else { break };
        let crc = crc32fast::hash(&data[pos + 8..end]);
        data[pos + 4..pos + 8].copy_from_slice(&crc.to_le_bytes());
        pos = end;
    }
}

/// The checksummed pieces of a directory: each snapshot file whose checksum holds, and each
/// segment record whose checksum holds, walking the framing from the header until it breaks.
fn checksummed_pieces(files: &[(String, Vec<u8>)]) -> Vec<&[u8]> {
    let mut out = Vec::new();
    for (name, data) in files {
        if name.starts_with("snapshots/") {
            if data.len() >= 4 && crc32fast::hash(&data[..data.len() - 4]).to_le_bytes() == data[data.len() - 4..] {
                out.push(data.as_slice());
            }
            continue;
        }
        let mut pos = crate::wal::SEGMENT_HEADER_BYTES;
        while pos + 8 <= data.len() {
            let len = u32::from_le_bytes(data[pos..pos + 4].try_into().expect("4 bytes")) as usize;
            let Some(end) = (pos + 8).checked_add(len).filter(|&e| e <= data.len()) else { break };
            let body = &data[pos + 8..end];
            if crc32fast::hash(body).to_le_bytes() != data[pos + 4..pos + 8] {
                break;
            }
            out.push(body);
            pos = end;
        }
    }
    out
}

/// Whether `files` hold checksummed content the writer never wrote: a record or snapshot
/// whose checksum holds but which is not one of the base's (the ops may have recomputed a
/// checksum, or the fuzzer may have learnt one from the comparison that checks it). Only then
/// may recovery restore rows that were not written.
fn forges(files: &[(String, Vec<u8>)], base: &[(String, Vec<u8>)]) -> bool {
    let written: std::collections::HashSet<&[u8]> = checksummed_pieces(base).into_iter().collect();
    checksummed_pieces(files).iter().any(|p| !written.contains(p))
}

/// Applies the ops to the files.
fn apply_ops(files: &mut Vec<(String, Vec<u8>)>, mut ops: Ops<'_>) {
    while let Some(code) = ops.u8() {
        if files.is_empty() {
            break;
        }
        let Some(f) = ops.u8().map(|i| i as usize % files.len()) else { break };
        match code % 8 {
            op::FLIP => {
                let (Some(off), Some(x)) = (ops.u16(), ops.u8()) else { break };
                let data = &mut files[f].1;
                if !data.is_empty() {
                    let n = data.len();
                    data[off % n] ^= x.max(1);
                }
            }
            op::TRUNCATE => {
                let Some(len) = ops.u16() else { break };
                let data = &mut files[f].1;
                data.truncate(len % (data.len() + 1));
            }
            op::SWAP => {
                let Some(g) = ops.u8().map(|i| i as usize % files.len()) else { break };
                if f != g {
                    let tmp = std::mem::take(&mut files[f].1);
                    files[f].1 = std::mem::replace(&mut files[g].1, tmp);
                }
            }
            op::DELETE => {
                files.remove(f);
            }
            op::OVERWRITE | op::INSERT => {
                let (Some(off), Some(n)) = (ops.u16(), ops.u8()) else { break };
                let bytes = ops.bytes(n as usize).to_vec();
                let data = &mut files[f].1;
                let at = off % (data.len() + 1);
                if code % 8 == op::INSERT {
                    data.splice(at..at, bytes);
                } else {
                    let end = at + bytes.len();
                    if data.len() < end {
                        data.resize(end, 0);
                    }
                    data[at..end].copy_from_slice(&bytes);
                }
            }
            op::COPY_AS => {
                let Some(lsn) = ops.u8() else { break };
                let (name, data) = files[f].clone();
                let new_name =
                    if name.starts_with("wal/") { format!("wal/{}", crate::wal::segment_name(u64::from(lsn))) } else { format!("snapshots/{}", crate::snapshot::snapshot_name(u64::from(lsn))) };
                if let Some(existing) = files.iter_mut().find(|(n, _)| *n == new_name) {
                    existing.1 = data;
                } else {
                    files.push((new_name, data));
                }
            }
            _ => {
                let (name, data) = &mut files[f];
                fix_checksums(name, data);
            }
        }
    }
}

/// What one recovery of `dir` left: its report's essentials and the table's rows.
struct Recovered {
    rows: Vec<StoredRow>,
    next_key: u64,
    fault: bool,
    skipped: usize,
}

fn recover_dir(b: &Base, dir: &Path, lookup_forged: bool) -> Result<Recovered, ReplayError> {
    let fresh = || Table::new(b.cfg.clone(), 11);
    let store = SnapshotStore::open(dir.join("snapshots"), 2)?;
    let p = PersistenceConfig { dir: Some(dir.to_path_buf()), ..b.persistence.clone() };
    let (table, wal, report) = crate::persist::recovery::recover(fresh()?, fresh, &store, &dir.join("wal"), &p)?;
    drop(wal);
    let rows = table.stored_rows().unwrap_or_else(|e| panic!("recovered table bookkeeping broken: {e}"));
    assert_eq!((report.rows, report.next_key), (rows.len() as u64, table.next_key()), "the report's counts");
    assert!(rows.len() <= b.cfg.capacity);
    for r in &rows {
        assert!(r.obs.iter().chain(&r.action).chain(&r.next_obs).chain([&r.reward]).all(|x| x.is_finite()), "recovered row {} is not finite", r.key);
        assert!(!(r.terminal && r.truncated), "recovered row {} is terminal and truncated", r.key);
        if !lookup_forged {
            match b.written.get(&r.key) {
                Some(w) => assert!(same_row(r, w), "recovered row {} is {r:?}; written {w:?}", r.key),
                None => panic!("recovered row {} was never written", r.key),
            }
        }
    }
    if !lookup_forged {
        for (id, a) in table.actors() {
            let written = b.sequences.get(&id).copied().unwrap_or(0);
            assert!(a.last_sequence <= written, "actor `{id}` recovered at sequence {}, above the {written} written", a.last_sequence);
        }
    }
    let by_key: HashMap<u64, StoredRow> = rows.iter().map(|r| (r.key, r.clone())).collect();
    check_samples(&table, |k| by_key.get(&k).cloned());
    Ok(Recovered { rows, next_key: table.next_key(), fault: report.fault.is_some(), skipped: report.skipped_snapshots.len() })
}

/// Recovery on a damaged copy of a valid directory: byte 0 picks the base, the rest are ops
/// ([`op`]). Recovery must not panic, must restore only rows that were written (unless the
/// input forged checksums) into a consistent table, and must leave a directory that a second
/// recovery reads without a fault, to the same rows. An undamaged directory comes back whole.
pub fn wal_recovery(data: &[u8]) {
    let Some((&kind, rest)) = data.split_first() else { return };
    let b = base(kind);
    let mut files = b.files.clone();
    apply_ops(&mut files, Ops(rest));
    files.sort();
    let changed = files != b.files;
    let forged = changed && forges(&files, &b.files);
    let dir = scratch_dir();
    for sub in ["wal", "snapshots"] {
        std::fs::create_dir_all(dir.join(sub)).expect("create a scratch directory");
    }
    for (name, bytes) in &files {
        std::fs::write(dir.join(name), bytes).expect("write a scratch file");
    }
    let first = recover_dir(b, &dir, forged);
    match &first {
        Ok(r) => {
            if !changed {
                assert!(!r.fault && r.skipped == 0, "an undamaged directory reported a fault");
                assert_eq!(r.next_key, b.final_next_key, "undamaged: next key");
                assert_eq!(r.rows.len(), b.final_rows.len(), "undamaged: rows");
                assert!(r.rows.iter().zip(&b.final_rows).all(|(x, y)| same_row(x, y)), "undamaged: rows differ");
            }
            let again = recover_dir(b, &dir, forged).unwrap_or_else(|e| panic!("a second recovery failed: {e}"));
            assert!(!again.fault, "the second recovery found a fault the first left behind");
            assert_eq!((again.next_key, again.rows.len()), (r.next_key, r.rows.len()), "the second recovery restored another table");
            assert!(again.rows.iter().zip(&r.rows).all(|(x, y)| same_row(x, y)), "the second recovery restored other rows");
        }
        Err(ReplayError::Storage { .. } | ReplayError::InvalidConfig(_)) => assert!(changed, "an undamaged directory failed to recover: {:?}", first.as_ref().err()),
        Err(e) => panic!("recovery failed with an unexpected error: {e}"),
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// What a registration must answer, from the slots given out so far.
#[derive(Debug)]
enum Expected {
    BadName,
    Known(u32),
    New(u32),
    Exhausted,
}

fn expected_registration(model: &BTreeMap<String, u32>, max_slots: u32, name: &str) -> Expected {
    if check_actor_name(name).is_err() {
        return Expected::BadName;
    }
    if let Some(&slot) = model.get(name) {
        return Expected::Known(slot);
    }
    let held: HashSet<u32> = model.values().copied().collect();
    let lowest = (0..=u32::MAX).find(|s| !held.contains(s)).expect("fewer slots held than u32 values");
    if lowest >= max_slots { Expected::Exhausted } else { Expected::New(lowest) }
}

/// `actor_slots`: `[max byte] frame*` (frames as [`replay_ingest`]'s). The first frame is the
/// bytes of a replay's `actor-slots.json` (empty: no file), each further frame a prost
/// `RegisterActorRequest`, handled as `ReplayService::register_actor` handles it (protocol
/// version, then [`ActorRegistry::register`]); `max_actor_slots` is 1 + max byte % 8.
///
/// Checked: a file that does not load is an error naming it and is left unchanged; a file that
/// loads holds valid names on distinct slots; every registration answers what a model of the
/// table says (a bad name refused, a known name its slot, a new one the lowest free slot, none
/// left past `max_actor_slots`), the table and its counters match the model after each, and
/// the file the registry leaves loads back to the same table.
pub fn actor_slots(data: &[u8]) {
    let Some((&max_byte, rest)) = data.split_first() else { return };
    let max_slots = u32::from(max_byte % 8) + 1;
    let mut input = frames(rest);
    let file = input.next().unwrap_or_default();
    let dir = scratch_dir();
    let path = dir.join(SLOTS_FILE);
    if !file.is_empty() {
        std::fs::write(&path, file).expect("write a scratch file");
    }
    let registry = match ActorRegistry::open(Some(&dir), max_slots) {
        Ok(r) => r,
        Err(e) => {
            let message = e.to_string();
            assert!(matches!(e, ReplayError::Storage { .. }) && message.contains(SLOTS_FILE) && message.contains("not a valid actor-slot file"), "unclear refusal: {message}");
            assert_eq!(std::fs::read(&path).ok().as_deref(), Some(file), "a refused slot file was changed");
            let _ = std::fs::remove_dir_all(&dir);
            return;
        }
    };
    let mut model = registry.slots();
    let mut held = HashSet::new();
    for (name, &slot) in &model {
        assert!(check_actor_name(name).is_ok(), "loaded a bad name {name:?}");
        assert!(held.insert(slot), "loaded slot {slot} twice");
    }
    let mut counts = RegistryCounts { registered: model.len() as u64, ..RegistryCounts::default() };
    for frame in input {
        // An undecodable request never reaches the service (tonic answers it).
        let Ok(request) = RegisterActorRequest::decode(frame) else { continue };
        if check_protocol_version(request.protocol_version).is_err() {
            registry.record_refused();
            counts.refused += 1;
            continue;
        }
        let expected = expected_registration(&model, max_slots, &request.name);
        match (registry.register(&request.name), &expected) {
            (Err(ReplayError::BadRequest(_)), Expected::BadName) | (Err(ReplayError::SlotsExhausted { .. }), Expected::Exhausted) => counts.refused += 1,
            (Ok(r), &Expected::Known(slot)) => {
                assert!(r.known && r.slot == slot && r.registered as usize == model.len(), "{:?} answered {r:?}, expected {expected:?}", request.name);
                counts.known += 1;
            }
            (Ok(r), &Expected::New(slot)) => {
                model.insert(request.name.clone(), slot);
                assert!(!r.known && r.slot == slot && r.registered as usize == model.len(), "{:?} answered {r:?}, expected {expected:?}", request.name);
                counts.new += 1;
            }
            // The scratch file system is full: nothing is given out (the table checks below).
            (Err(ReplayError::Storage { .. }), Expected::New(_)) => counts.refused += 1,
            (got, _) => panic!("{:?} answered {got:?}, expected {expected:?}", request.name),
        }
        counts.registered = model.len() as u64;
        assert_eq!(registry.slots(), model, "after registering {:?}", request.name);
        assert_eq!(registry.counts(), counts);
    }
    drop(registry);
    let again = ActorRegistry::open(Some(&dir), max_slots).expect("the registry's own file loads");
    assert_eq!(again.slots(), model, "the file holds what was given out");
    drop(again);
    let _ = std::fs::remove_dir_all(&dir);
}
