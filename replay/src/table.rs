//! A table of transitions: columnar ring storage with FIFO eviction, a sum-tree sampler
//! (uniform or proportional prioritised), the rate limiter, and exactly-once inserts.
//!
//! ```text
//!   key k (u64, assigned in insert order) lives in slot k mod capacity while
//!   next_key − capacity ≤ k < next_key and it has not been removed (max_times_sampled)
//!
//!   columns (slot-major): obs[cap·obs_dim] next_obs[cap·obs_dim] action[cap·act_dim]
//!                         reward terminal truncated episode_id step policy_version actor key
//! ```
//!
//! Threading: one mutex guards everything; every method takes it once and holds it for
//! O(rows × dims) copying or O(rows × log capacity) tree work. Blocked callers park on a
//! condition variable that every insert, sample and close notifies. Memory is the raw payload
//! plus 16 bytes a slot for the sum tree and ~30 bytes of per-row metadata.

use std::collections::HashMap;
use std::sync::{Condvar, Mutex, MutexGuard};
use std::time::{Instant, SystemTime, UNIX_EPOCH};

use mapless_proto::v1::{ActorInfo, InsertAck, ProtocolVersion, RateLimiterInfo, SampledBatch, ServerInfoResponse, TransitionBatch};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64Mcg;

use crate::config::{SamplerConfig, TableConfig};
use crate::error::ReplayError;
use crate::rate_limiter::RateLimiter;
use crate::sum_tree::SumTree;

/// Per-actor bookkeeping: de-duplication and what server info reports.
#[derive(Clone, Debug, Default)]
pub struct ActorStats {
    /// Highest sequence stored; batches at or below it are duplicates.
    pub last_sequence: u64,
    pub batches: u64,
    pub rows: u64,
    pub duplicate_batches: u64,
    pub rejected_batches: u64,
    pub last_rejection: String,
    pub last_policy_version: u64,
    pub last_insert_unix_ms: u64,
}

/// Insert and sample rates over the last few seconds.
#[derive(Debug)]
struct RateMeter {
    window: std::collections::VecDeque<(Instant, u64)>,
}

impl RateMeter {
    const SPAN_S: f64 = 10.0;
    fn new() -> Self {
        RateMeter { window: std::collections::VecDeque::new() }
    }
    fn add(&mut self, now: Instant, n: u64) {
        match self.window.back_mut() {
            // Coalesce into 100 ms buckets so the window stays small.
            Some((t, c)) if now.duration_since(*t).as_secs_f64() < 0.1 => *c += n,
            _ => self.window.push_back((now, n)),
        }
        while self.window.front().is_some_and(|(t, _)| now.duration_since(*t).as_secs_f64() > Self::SPAN_S) {
            self.window.pop_front();
        }
    }
    fn per_second(&self, now: Instant) -> f64 {
        let Some((first, _)) = self.window.front() else { return 0.0 };
        let span = now.duration_since(*first).as_secs_f64().clamp(1.0, Self::SPAN_S);
        self.window.iter().filter(|(t, _)| now.duration_since(*t).as_secs_f64() <= Self::SPAN_S).map(|(_, c)| *c).sum::<u64>() as f64 / span
    }
}

struct State {
    // Columns.
    obs: Vec<f32>,
    next_obs: Vec<f32>,
    action: Vec<f32>,
    reward: Vec<f32>,
    terminal: Vec<bool>,
    truncated: Vec<bool>,
    episode_id: Vec<u64>,
    step: Vec<u32>,
    policy_version: Vec<u64>,
    key: Vec<u64>,
    live: Vec<bool>,
    times_sampled: Vec<u32>,
    // Sampling.
    tree: SumTree,
    /// Largest priority^α seen; new items get it so each is sampled at least once soon.
    max_weight: f64,
    size: u64,
    next_key: u64,
    limiter: RateLimiter,
    actors: HashMap<String, ActorStats>,
    rng: Pcg64Mcg,
    insert_rate: RateMeter,
    sample_rate: RateMeter,
    closed: bool,
}

/// One replay table. Share it with `Arc`; every method takes `&self`.
pub struct Table {
    cfg: TableConfig,
    state: Mutex<State>,
    changed: Condvar,
    started_unix_ms: u64,
}

fn unix_ms() -> u64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map(|d| d.as_millis() as u64).unwrap_or(0)
}

impl Table {
    /// An empty table; `seed` fixes the sampler's random stream.
    pub fn new(cfg: TableConfig, seed: u64) -> Result<Table, ReplayError> {
        cfg.validate()?;
        let c = cfg.capacity;
        let state = State {
            obs: vec![0.0; c * cfg.obs_dim],
            next_obs: vec![0.0; c * cfg.obs_dim],
            action: vec![0.0; c * cfg.act_dim],
            reward: vec![0.0; c],
            terminal: vec![false; c],
            truncated: vec![false; c],
            episode_id: vec![0; c],
            step: vec![0; c],
            policy_version: vec![0; c],
            key: vec![0; c],
            live: vec![false; c],
            times_sampled: vec![0; c],
            tree: SumTree::new(c),
            max_weight: 1.0,
            size: 0,
            next_key: 0,
            limiter: RateLimiter::new(cfg.rate_limiter.clone()),
            actors: HashMap::new(),
            rng: Pcg64Mcg::seed_from_u64(seed),
            insert_rate: RateMeter::new(),
            sample_rate: RateMeter::new(),
            closed: false,
        };
        Ok(Table { cfg, state: Mutex::new(state), changed: Condvar::new(), started_unix_ms: unix_ms() })
    }

    pub fn config(&self) -> &TableConfig {
        &self.cfg
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        // A panic while holding the lock cannot leave columns half-written in a way later
        // calls trip over (each row is written before it becomes live), so keep serving.
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Rows currently stored (live).
    pub fn size(&self) -> u64 {
        self.lock().size
    }

    /// Validates, de-duplicates on (actor_id, sequence), waits for the rate limiter until
    /// `deadline` (None: wait indefinitely), and stores the batch. A duplicate (sequence at or
    /// below the actor's last stored one) is acknowledged with `duplicate = true` and changes
    /// nothing. A rejected batch changes nothing and is counted against its actor.
    pub fn insert(&self, batch: &TransitionBatch, deadline: Option<Instant>) -> Result<InsertAck, ReplayError> {
        let rows = match batch.validate(self.cfg.obs_dim, self.cfg.act_dim, self.cfg.max_batch_rows) {
            Ok(r) => r,
            Err(e) => {
                self.record_rejection(&batch.actor_id, &e.to_string());
                return Err(e.into());
            }
        };
        let mut st = self.lock();
        if let Some(a) = st.actors.get_mut(&batch.actor_id) {
            if batch.sequence <= a.last_sequence {
                a.duplicate_batches += 1;
                return Ok(InsertAck { actor_id: batch.actor_id.clone(), sequence: batch.sequence, accepted_rows: 0, duplicate: true, table_size: st.size });
            }
        }
        st = self.wait(st, deadline, "insert", |s| s.limiter.can_insert())?;
        let d = self.cfg.obs_dim;
        let a = self.cfg.act_dim;
        let cap = self.cfg.capacity as u64;
        let s = &mut *st;
        for r in 0..rows {
            let key = s.next_key;
            let slot = (key % cap) as usize;
            if s.live[slot] {
                s.size -= 1; // FIFO eviction of the oldest row
            }
            s.obs[slot * d..(slot + 1) * d].copy_from_slice(&batch.obs[r * d..(r + 1) * d]);
            s.next_obs[slot * d..(slot + 1) * d].copy_from_slice(&batch.next_obs[r * d..(r + 1) * d]);
            s.action[slot * a..(slot + 1) * a].copy_from_slice(&batch.action[r * a..(r + 1) * a]);
            s.reward[slot] = batch.reward[r];
            s.terminal[slot] = batch.terminal[r];
            s.truncated[slot] = batch.truncated[r];
            s.episode_id[slot] = batch.episode_id[r];
            s.step[slot] = batch.step[r];
            s.policy_version[slot] = batch.policy_version[r];
            s.key[slot] = key;
            s.times_sampled[slot] = 0;
            s.live[slot] = true;
            s.tree.set(slot, s.max_weight);
            s.next_key += 1;
            s.size += 1;
        }
        s.limiter.inserted(rows as u64);
        s.insert_rate.add(Instant::now(), rows as u64);
        let newest_version = batch.policy_version[..rows].iter().copied().max().unwrap_or(0);
        let actor = s.actors.entry(batch.actor_id.clone()).or_default();
        actor.last_sequence = batch.sequence;
        actor.batches += 1;
        actor.rows += rows as u64;
        actor.last_policy_version = actor.last_policy_version.max(newest_version);
        actor.last_insert_unix_ms = unix_ms();
        let ack = InsertAck { actor_id: batch.actor_id.clone(), sequence: batch.sequence, accepted_rows: rows as u32, duplicate: false, table_size: s.size };
        drop(st);
        self.changed.notify_all();
        Ok(ack)
    }

    /// Counts a rejected batch against its actor (any ingest path calls this for input it
    /// could not even decode). Nothing stored is touched.
    pub fn record_rejection(&self, actor_id: &str, why: &str) {
        let id = if actor_id.is_empty() || actor_id.len() > mapless_proto::MAX_ACTOR_ID_BYTES { "<invalid actor id>" } else { actor_id };
        let mut st = self.lock();
        let a = st.actors.entry(id.to_string()).or_default();
        a.rejected_batches += 1;
        a.last_rejection = why.chars().take(200).collect();
        tracing::warn!(table = %self.cfg.name, actor_id = id, reason = why, "batch rejected");
    }

    /// Draws a minibatch of `rows`, waiting for the rate limiter until `deadline`. `beta`
    /// overrides the configured importance-sampling exponent (prioritised sampler only).
    pub fn sample(&self, rows: usize, beta: Option<f64>, deadline: Option<Instant>) -> Result<SampledBatch, ReplayError> {
        if rows == 0 || rows > self.cfg.max_sample_rows {
            return Err(ReplayError::BadRequest(format!("batch_size must be in 1..={}, got {rows}", self.cfg.max_sample_rows)));
        }
        let beta = match (&self.cfg.sampler, beta) {
            (SamplerConfig::Prioritized { beta, .. }, None) => *beta,
            (_, Some(b)) if b.is_finite() && b >= 0.0 => b,
            (_, Some(b)) => return Err(ReplayError::BadRequest(format!("importance beta must be finite and ≥ 0, got {b}"))),
            (SamplerConfig::Uniform, None) => 0.0,
        };
        let st = self.lock();
        let mut st = self.wait(st, deadline, "sample", |s| s.limiter.can_sample(s.size, rows as u64))?;
        let (d, a) = (self.cfg.obs_dim, self.cfg.act_dim);
        let mut out = SampledBatch {
            protocol_version: ProtocolVersion::V1 as i32,
            table: self.cfg.name.clone(),
            obs_dim: d as u32,
            act_dim: a as u32,
            num_rows: rows as u32,
            table_size: st.size,
            keys: Vec::with_capacity(rows),
            probabilities: Vec::with_capacity(rows),
            importance_weights: Vec::with_capacity(rows),
            obs: Vec::with_capacity(rows * d),
            action: Vec::with_capacity(rows * a),
            reward: Vec::with_capacity(rows),
            next_obs: Vec::with_capacity(rows * d),
            terminal: Vec::with_capacity(rows),
            truncated: Vec::with_capacity(rows),
            episode_id: Vec::with_capacity(rows),
            step: Vec::with_capacity(rows),
            policy_version: Vec::with_capacity(rows),
        };
        let s = &mut *st;
        let total = s.tree.total();
        let n = s.size as f64;
        let segment = total / rows as f64;
        let mut max_w = 0.0f64;
        for i in 0..rows {
            // Stratified: one draw from each of `rows` equal slices of the total mass.
            let u = (i as f64 + s.rng.random::<f64>()) * segment;
            let slot = s.tree.find(u.min(total));
            let p = s.tree.get(slot) / total;
            let w = (n * p).powf(-beta);
            max_w = max_w.max(w);
            out.keys.push(s.key[slot]);
            out.probabilities.push(p);
            out.importance_weights.push(w as f32);
            out.obs.extend_from_slice(&s.obs[slot * d..(slot + 1) * d]);
            out.next_obs.extend_from_slice(&s.next_obs[slot * d..(slot + 1) * d]);
            out.action.extend_from_slice(&s.action[slot * a..(slot + 1) * a]);
            out.reward.push(s.reward[slot]);
            out.terminal.push(s.terminal[slot]);
            out.truncated.push(s.truncated[slot]);
            out.episode_id.push(s.episode_id[slot]);
            out.step.push(s.step[slot]);
            out.policy_version.push(s.policy_version[slot]);
            s.times_sampled[slot] += 1;
            if self.cfg.max_times_sampled > 0 && s.times_sampled[slot] >= self.cfg.max_times_sampled && s.live[slot] {
                s.live[slot] = false;
                s.tree.set(slot, 0.0);
                s.size -= 1;
            }
        }
        // Normalise by the minibatch's largest weight (as Acme and Dopamine do), so weights
        // only ever scale updates down.
        for w in &mut out.importance_weights {
            *w = (*w as f64 / max_w) as f32;
        }
        s.limiter.sampled(rows as u64);
        s.sample_rate.add(Instant::now(), rows as u64);
        drop(st);
        self.changed.notify_all();
        Ok(out)
    }

    /// Sets new priorities (e.g. |TD error|) for keys still stored; returns (updated,
    /// unknown) counts. Keys evicted or removed since they were sampled are skipped.
    pub fn update_priorities(&self, keys: &[u64], priorities: &[f64]) -> Result<(u32, u32), ReplayError> {
        if keys.len() != priorities.len() {
            return Err(ReplayError::BadRequest(format!("{} keys but {} priorities", keys.len(), priorities.len())));
        }
        if let Some(i) = priorities.iter().position(|p| !(p.is_finite() && *p >= 0.0)) {
            return Err(ReplayError::BadRequest(format!("priority {i} is {}, must be finite and ≥ 0", priorities[i])));
        }
        let SamplerConfig::Prioritized { alpha, epsilon, .. } = self.cfg.sampler else {
            // Uniform tables accept and ignore updates, so a learner can run either way.
            return Ok((0, 0));
        };
        let cap = self.cfg.capacity as u64;
        let mut st = self.lock();
        let s = &mut *st;
        let (mut updated, mut unknown) = (0u32, 0u32);
        for (&k, &p) in keys.iter().zip(priorities) {
            let slot = (k % cap) as usize;
            if k < s.next_key && s.live[slot] && s.key[slot] == k {
                let w = (p + epsilon).powf(alpha);
                s.tree.set(slot, w);
                s.max_weight = s.max_weight.max(w);
                updated += 1;
            } else {
                unknown += 1;
            }
        }
        Ok((updated, unknown))
    }

    /// Waits on the condition variable until `ready` or the deadline; accounts blocked time.
    fn wait<'a>(
        &self,
        mut st: MutexGuard<'a, State>,
        deadline: Option<Instant>,
        op: &'static str,
        ready: impl Fn(&State) -> bool,
    ) -> Result<MutexGuard<'a, State>, ReplayError> {
        let start = Instant::now();
        let mut blocked = false;
        loop {
            if st.closed {
                return Err(ReplayError::Closed(self.cfg.name.clone()));
            }
            if ready(&st) {
                if blocked {
                    let ns = start.elapsed().as_nanos() as u64;
                    if op == "insert" { st.limiter.insert_blocked(ns) } else { st.limiter.sample_blocked(ns) }
                }
                return Ok(st);
            }
            blocked = true;
            let now = Instant::now();
            match deadline {
                Some(d) if now >= d => {
                    let ns = start.elapsed().as_nanos() as u64;
                    if op == "insert" { st.limiter.insert_blocked(ns) } else { st.limiter.sample_blocked(ns) }
                    let state = serde_json::to_string(&st.limiter.state()).unwrap_or_default();
                    return Err(ReplayError::DeadlineExceeded { op, waited_ms: start.elapsed().as_millis() as u64, state: format!("size {}, {state}", st.size) });
                }
                Some(d) => st = self.changed.wait_timeout(st, d - now).unwrap_or_else(|p| p.into_inner()).0,
                None => st = self.changed.wait(st).unwrap_or_else(|p| p.into_inner()),
            }
        }
    }

    /// Wakes every blocked caller with `Closed`; later calls fail the same way.
    pub fn close(&self) {
        self.lock().closed = true;
        self.changed.notify_all();
    }

    /// Per-actor statistics (clone).
    pub fn actors(&self) -> HashMap<String, ActorStats> {
        self.lock().actors.clone()
    }

    /// Everything `ServerInfo` reports.
    pub fn info(&self) -> ServerInfoResponse {
        use mapless_proto::v1::{RateLimiterState as Rls, Selector};
        let st = self.lock();
        let now = Instant::now();
        let rl = st.limiter.state();
        let batch = self.cfg.max_sample_rows.min(128) as u64;
        let state = if st.size < rl.min_size_to_sample {
            Rls::WarmingUp
        } else if !st.limiter.can_insert() {
            Rls::InsertsBlocked
        } else if !st.limiter.can_sample(st.size, batch) {
            Rls::SamplesBlocked
        } else {
            Rls::Open
        };
        let mut actors: Vec<ActorInfo> = st
            .actors
            .iter()
            .map(|(id, a)| ActorInfo {
                actor_id: id.clone(),
                batches: a.batches,
                rows: a.rows,
                duplicate_batches: a.duplicate_batches,
                last_sequence: a.last_sequence,
                last_policy_version: a.last_policy_version,
                last_insert_unix_ms: a.last_insert_unix_ms,
            })
            .collect();
        actors.sort_by(|a, b| a.actor_id.cmp(&b.actor_id));
        ServerInfoResponse {
            protocol_version: ProtocolVersion::V1 as i32,
            table: self.cfg.name.clone(),
            selector: match self.cfg.sampler {
                SamplerConfig::Uniform => Selector::Uniform as i32,
                SamplerConfig::Prioritized { .. } => Selector::Prioritized as i32,
            },
            obs_dim: self.cfg.obs_dim as u32,
            act_dim: self.cfg.act_dim as u32,
            size: st.size,
            capacity: self.cfg.capacity as u64,
            inserts_total: rl.inserts,
            samples_total: rl.samples,
            inserts_per_s: st.insert_rate.per_second(now),
            samples_per_s: st.sample_rate.per_second(now),
            rate_limiter: Some(RateLimiterInfo {
                state: state as i32,
                min_size_to_sample: rl.min_size_to_sample,
                samples_per_insert: rl.samples_per_insert.unwrap_or(0.0),
                error_buffer: self.cfg.rate_limiter.error_buffer,
                inserts_blocked_ms: (rl.insert_blocked_s * 1e3) as u64,
                samples_blocked_ms: (rl.sample_blocked_s * 1e3) as u64,
            }),
            actors,
            max_rows_per_batch: self.cfg.max_batch_rows as u32,
            started_unix_ms: self.started_unix_ms,
        }
    }

    /// Bytes held by the table's columns and sampler (what the memory target measures).
    pub fn memory_bytes(&self) -> usize {
        let st = self.lock();
        let f = std::mem::size_of::<f32>();
        (st.obs.len() + st.next_obs.len() + st.action.len() + st.reward.len()) * f
            + st.terminal.len() * 3 // terminal, truncated, live
            + (st.episode_id.len() + st.policy_version.len() + st.key.len()) * 8
            + (st.step.len() + st.times_sampled.len()) * 4
            + st.tree.memory_bytes()
    }
}
