//! The table's behaviour: rate limiting, prioritised sampling, FIFO eviction, exactly-once
//! inserts and untouched state on bad input.

use std::sync::Arc;
use std::time::{Duration, Instant};

use mapless_proto::v1::TransitionBatch;
use mapless_proto::{FloatEncoding, Transition, TransitionBatchBuilder};
use mapless_replay::{RateLimiterConfig, ReplayError, SamplerConfig, Table, TableConfig};

const D: usize = 3;

fn cfg(capacity: usize) -> TableConfig {
    TableConfig {
        capacity,
        obs_dim: D,
        act_dim: 2,
        rate_limiter: RateLimiterConfig { min_size_to_sample: 1, samples_per_insert: None, error_buffer: 0.0 },
        max_batch_rows: 1000,
        max_sample_rows: 1000,
        ..TableConfig::default()
    }
}

/// `rows` transitions whose reward (and obs[0]) is `first_reward + i`.
fn batch(actor: &str, seq: u64, first_reward: f32, rows: usize) -> TransitionBatch {
    let mut b = TransitionBatchBuilder::new(D, 2);
    for i in 0..rows {
        let r = first_reward + i as f32;
        b.push(Transition { obs: &[r, 0.0, 0.0], action: &[0.1, -0.1], reward: r, next_obs: &[r, 1.0, 0.0], terminal: i % 7 == 6, truncated: false, episode_id: 1, step: i as u32, policy_version: 3 })
            .unwrap();
    }
    b.finish(actor, seq)
}

fn soon() -> Option<Instant> {
    Some(Instant::now() + Duration::from_millis(50))
}

#[test]
fn blocks_samples_until_min_size_reached() {
    let mut c = cfg(100);
    c.rate_limiter.min_size_to_sample = 10;
    let t = Table::new(c, 1).unwrap();
    t.insert(&batch("a", 1, 0.0, 9), None).unwrap();
    let e = t.sample(1, None, soon()).unwrap_err();
    assert!(matches!(e, ReplayError::DeadlineExceeded { op: "sample", .. }), "{e}");
    assert_eq!(e.to_status().code(), tonic::Code::DeadlineExceeded);
    t.insert(&batch("a", 2, 9.0, 1), None).unwrap();
    assert_eq!(t.sample(4, None, soon()).unwrap().num_rows, 4);
}

#[test]
fn blocked_sampler_wakes_when_an_insert_arrives() {
    let mut c = cfg(100);
    c.rate_limiter.min_size_to_sample = 5;
    let t = Arc::new(Table::new(c, 1).unwrap());
    let t2 = Arc::clone(&t);
    let waiter = std::thread::spawn(move || t2.sample(2, None, Some(Instant::now() + Duration::from_secs(10))));
    // Time for the waiter to start and block, even on a loaded machine.
    std::thread::sleep(Duration::from_millis(300));
    t.insert(&batch("a", 1, 0.0, 5), None).unwrap();
    assert_eq!(waiter.join().unwrap().unwrap().num_rows, 2);
    assert!(t.info().rate_limiter.unwrap().samples_blocked_ms > 0, "the wait is accounted as blocked time");
}

#[test]
fn ratio_is_held_within_its_band_under_concurrent_insert_and_sample() {
    // 4 sampled rows per inserted row, min size 20, buffer 200: diff stays in
    // [4·20 − 200, 4·20 + 200] give or take one batch.
    let mut c = cfg(10_000);
    c.rate_limiter = RateLimiterConfig { min_size_to_sample: 20, samples_per_insert: Some(4.0), error_buffer: 200.0 };
    c.max_batch_rows = 10;
    c.max_sample_rows = 32;
    let t = Arc::new(Table::new(c, 2).unwrap());
    let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let inserter = {
        let (t, stop) = (Arc::clone(&t), Arc::clone(&stop));
        std::thread::spawn(move || {
            let mut seq = 0;
            while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                seq += 1;
                match t.insert(&batch("w", seq, 0.0, 10), Some(Instant::now() + Duration::from_millis(20))) {
                    Ok(_) | Err(ReplayError::DeadlineExceeded { .. }) => {}
                    Err(e) => panic!("{e}"),
                }
            }
        })
    };
    // Before any sampling the inserter must hit the top of the band and wait there: let it
    // (whether it later runs ahead again depends on scheduling, so this part is made certain).
    let end = Instant::now() + Duration::from_secs(30);
    while t.info().inserts_total < 70 {
        assert!(Instant::now() < end, "the inserter never filled the band: {:?}", t.info());
        std::thread::sleep(Duration::from_millis(1));
    }
    std::thread::sleep(Duration::from_millis(100));
    let mut worst = (f64::INFINITY, f64::NEG_INFINITY);
    let mut sampled = 0;
    while sampled < 3000 {
        if t.sample(32, None, Some(Instant::now() + Duration::from_secs(5))).is_ok() {
            sampled += 1;
        }
        let info = t.info();
        let diff = info.inserts_total as f64 * 4.0 - info.samples_total as f64;
        worst = (worst.0.min(diff), worst.1.max(diff));
    }
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    inserter.join().unwrap();
    // Band [−120, 280]; an insert batch may overshoot by 10 × 4 = 40.
    assert!(worst.0 >= -120.0 && worst.1 <= 280.0 + 40.0, "diff left its band: {worst:?}");
    let rl = t.info().rate_limiter.unwrap();
    assert!(rl.inserts_blocked_ms > 0, "the inserter ran ahead and was held back");
}

#[test]
fn inserts_wait_for_the_learner_when_the_ratio_runs_ahead() {
    let mut c = cfg(1000);
    c.rate_limiter = RateLimiterConfig { min_size_to_sample: 10, samples_per_insert: Some(1.0), error_buffer: 20.0 };
    c.max_batch_rows = 10;
    c.max_sample_rows = 10;
    let t = Table::new(c, 3).unwrap();
    // max_diff = 10 + 20 = 30 rows ahead of sampling.
    for seq in 1..=4 {
        t.insert(&batch("a", seq, 0.0, 10), soon()).unwrap();
    }
    let e = t.insert(&batch("a", 5, 0.0, 10), soon()).unwrap_err();
    assert!(matches!(e, ReplayError::DeadlineExceeded { op: "insert", .. }), "{e}");
    t.sample(10, None, soon()).unwrap();
    t.insert(&batch("a", 5, 0.0, 10), soon()).unwrap();
}

#[test]
fn eviction_is_fifo() {
    let t = Table::new(cfg(5), 4).unwrap();
    t.insert(&batch("a", 1, 0.0, 8), None).unwrap(); // rewards 0..7; 0, 1, 2 evicted
    assert_eq!(t.size(), 5);
    let s = t.sample(500, None, None).unwrap();
    let mut seen: Vec<u64> = s.keys.clone();
    seen.sort();
    seen.dedup();
    assert_eq!(seen, vec![3, 4, 5, 6, 7]);
    for (k, r) in s.keys.iter().zip(&s.reward) {
        assert_eq!(*r, *k as f32, "row with key {k} holds its own data");
    }
    // The obs and next_obs columns moved with their rows.
    for i in 0..s.num_rows as usize {
        assert_eq!(s.obs[i * D], s.reward[i]);
        assert_eq!(s.next_obs[i * D + 1], 1.0);
    }
}

#[test]
fn resent_batches_are_deduplicated_per_actor() {
    let t = Table::new(cfg(100), 5).unwrap();
    let first = t.insert(&batch("a", 1, 0.0, 4), None).unwrap();
    assert!(!first.duplicate && first.accepted_rows == 4);
    let again = t.insert(&batch("a", 1, 0.0, 4), None).unwrap();
    assert!(again.duplicate && again.accepted_rows == 0);
    assert_eq!(t.size(), 4);
    t.insert(&batch("a", 3, 0.0, 2), None).unwrap(); // gaps are fine
    assert!(t.insert(&batch("a", 2, 0.0, 2), None).unwrap().duplicate, "older than the last stored");
    assert!(!t.insert(&batch("b", 1, 0.0, 2), None).unwrap().duplicate, "sequences are per actor");
    assert_eq!(t.size(), 8);
    let a = &t.actors()["a"];
    assert_eq!((a.batches, a.rows, a.duplicate_batches, a.last_sequence), (2, 6, 2, 3));
}

#[test]
fn bad_input_gets_its_status_is_counted_and_leaves_the_table_intact() {
    let t = Table::new(cfg(100), 6).unwrap();
    t.insert(&batch("good", 1, 0.0, 5), None).unwrap();
    let before = t.sample(100, None, None).unwrap();
    let mut wrong_dim = batch("bad", 1, 0.0, 2);
    wrong_dim.obs_dim = 4;
    let mut nan = batch("bad", 2, 0.0, 2);
    nan.reward[1] = f32::NAN;
    let mut version = batch("bad", 3, 0.0, 2);
    version.protocol_version = 9;
    let mut short = batch("bad", 4, 0.0, 2);
    short.next_obs.pop();
    let too_big = batch("bad", 5, 0.0, 1001);
    for (b, code) in [
        (wrong_dim, tonic::Code::InvalidArgument),
        (nan, tonic::Code::InvalidArgument),
        (version, tonic::Code::FailedPrecondition),
        (short, tonic::Code::InvalidArgument),
        (too_big, tonic::Code::ResourceExhausted),
    ] {
        let e = t.insert(&b, None).unwrap_err();
        assert_eq!(e.to_status().code(), code, "{e}");
    }
    assert_eq!(t.size(), 5);
    assert_eq!(t.actors()["bad"].rejected_batches, 5);
    assert!(t.actors()["bad"].last_rejection.contains("rows"), "{}", t.actors()["bad"].last_rejection);
    let mut after = t.sample(100, None, None).unwrap();
    let mut b = before;
    // Same content (sampling is random: compare the sets of stored rows).
    let sorted = |s: &mut mapless_proto::v1::SampledBatch| {
        let mut v: Vec<(u64, u32)> = s.keys.iter().zip(&s.reward).map(|(k, r)| (*k, r.to_bits())).collect();
        v.sort();
        v.dedup();
        v
    };
    assert_eq!(sorted(&mut b), sorted(&mut after));
}

#[test]
fn prioritized_sampling_frequencies_match_priorities() {
    let mut c = cfg(4);
    c.sampler = SamplerConfig::Prioritized { alpha: 1.0, beta: 1.0, epsilon: 0.0 };
    let t = Table::new(c, 7).unwrap();
    t.insert(&batch("a", 1, 0.0, 4), None).unwrap();
    let (updated, unknown) = t.update_priorities(&[0, 1, 2, 3, 99], &[1.0, 2.0, 3.0, 4.0, 5.0]).unwrap();
    assert_eq!((updated, unknown), (4, 1));
    let mut counts = [0u64; 4];
    let draws = 200_000usize;
    for _ in 0..draws / 100 {
        for k in t.sample(100, None, None).unwrap().keys {
            counts[k as usize] += 1;
        }
    }
    // Expected shares 0.1, 0.2, 0.3, 0.4; Pearson χ² with 3 degrees of freedom must stay
    // below 16.27 (p = 0.001). Stratified sampling makes it far smaller in practice.
    let chi2: f64 = counts
        .iter()
        .enumerate()
        .map(|(i, &c)| {
            let e = draws as f64 * (i + 1) as f64 / 10.0;
            (c as f64 - e).powi(2) / e
        })
        .sum();
    assert!(chi2 < 16.27, "counts {counts:?}, chi2 {chi2}");
}

#[test]
fn importance_weights_and_probabilities_are_exact() {
    let mut c = cfg(2);
    c.sampler = SamplerConfig::Prioritized { alpha: 1.0, beta: 0.5, epsilon: 0.0 };
    let t = Table::new(c, 8).unwrap();
    t.insert(&batch("a", 1, 0.0, 2), None).unwrap();
    t.update_priorities(&[0, 1], &[1.0, 3.0]).unwrap();
    let s = t.sample(200, None, None).unwrap();
    // P = (0.25, 0.75); w = (N P)^−β = (0.5^−0.5, 1.5^−0.5) = (1.41421, 0.81650); ÷ max → (1, 0.57735).
    for ((k, p), w) in s.keys.iter().zip(&s.probabilities).zip(&s.importance_weights) {
        let (ep, ew) = if *k == 0 { (0.25, 1.0) } else { (0.75, 0.577_350_3) };
        assert!((p - ep).abs() < 1e-12 && (*w - ew).abs() < 1e-6, "key {k}: p {p} w {w}");
    }
}

#[test]
fn importance_weights_stay_finite_and_positive_when_n_p_to_the_minus_beta_overflows() {
    // (N·P)^−β leaves f32's range when β is large (a request may set any finite β ≥ 0) or
    // when priorities lie many orders of magnitude apart; the normalised weights then came
    // out inf or 0, which `SampledBatch::validate` refuses at the learner (found by the
    // wal_recovery fuzz target on a recovered table).
    let mut c = cfg(4);
    c.sampler = SamplerConfig::Prioritized { alpha: 1.0, beta: 0.4, epsilon: 0.0 };
    let t = Table::new(c, 3).unwrap();
    t.insert(&batch("a", 1, 0.0, 4), None).unwrap();
    t.update_priorities(&[0, 1, 2, 3], &[4.0, 1.0, 1.0, 1.0]).unwrap();
    for beta in [200.0, 0.4, 0.0] {
        let s = t.sample(4, Some(beta), None).unwrap();
        s.validate(D, 2, 8).unwrap();
        assert!(s.importance_weights.iter().all(|w| *w > 0.0 && *w <= 1.0), "β {beta}: {:?}", s.importance_weights);
        assert!(s.keys.contains(&0) && s.keys.iter().any(|&k| k != 0), "β {beta}: draws {:?}", s.keys);
    }
}

#[test]
fn priorities_whose_weights_overflow_or_vanish_still_give_finite_minibatches() {
    // α > 1 and a large finite priority: (p + ε)^α was inf in f64, the tree's total inf and
    // every probability NaN.
    let mut c = cfg(4);
    c.sampler = SamplerConfig::Prioritized { alpha: 2.0, beta: 0.4, epsilon: 0.0 };
    let t = Table::new(c, 3).unwrap();
    t.insert(&batch("a", 1, 0.0, 4), None).unwrap();
    t.update_priorities(&[0, 1, 2, 3], &[1e200, 1e300, 1.0, 1.0]).unwrap();
    let s = t.sample(64, None, None).unwrap();
    s.validate(D, 2, 400).unwrap();
    assert!(s.probabilities.iter().all(|p| p.is_finite() && *p >= 0.0), "{:?}", s.probabilities);
    assert!(s.importance_weights.iter().all(|w| *w > 0.0 && *w <= 1.0), "{:?}", s.importance_weights);
    // Both huge priorities are clamped to one ceiling: they share the mass; the others have
    // none to speak of.
    assert!(s.keys.iter().all(|&k| k < 2) && s.keys.contains(&0) && s.keys.contains(&1), "{:?}", s.keys);

    // ε = 0 and every priority 0: the total was 0 and every draw 0/0. Now each row keeps the
    // floor weight, so the draws are uniform over the stored rows.
    let mut c = cfg(4);
    c.sampler = SamplerConfig::Prioritized { alpha: 0.6, beta: 0.4, epsilon: 0.0 };
    let t = Table::new(c, 4).unwrap();
    t.insert(&batch("a", 1, 0.0, 4), None).unwrap();
    t.update_priorities(&[0, 1, 2, 3], &[0.0; 4]).unwrap();
    let s = t.sample(400, None, None).unwrap();
    s.validate(D, 2, 400).unwrap();
    for k in 0..4 {
        let n = s.keys.iter().filter(|&&x| x == k).count();
        assert!((80..=120).contains(&n), "key {k} drawn {n} times of 400: {:?}", s.keys);
    }
    assert!(s.probabilities.iter().all(|p| (p - 0.25).abs() < 1e-9), "{:?}", &s.probabilities[..4]);
    assert!(s.importance_weights.iter().all(|w| *w == 1.0));
}

#[test]
fn a_minibatch_larger_than_what_max_times_sampled_leaves_draws_only_rows_that_were_stored() {
    // One row that may be sampled once, a minibatch of 3: rows removed as they were drawn left
    // the later draws an empty tree, which returned a never-written slot with probability 0
    // (found by the wal_recovery fuzz target on a recovered table).
    let mut c = cfg(4);
    c.max_times_sampled = 1;
    c.sampler = SamplerConfig::Prioritized { alpha: 0.6, beta: 0.4, epsilon: 1e-6 };
    let t = Table::new(c, 5).unwrap();
    t.insert(&batch("a", 1, 7.0, 1), None).unwrap();
    let s = t.sample(3, None, None).unwrap();
    s.validate(D, 2, 8).unwrap();
    assert_eq!((s.keys.as_slice(), s.reward.as_slice()), (&[0, 0, 0][..], &[7.0, 7.0, 7.0][..]));
    assert_eq!(t.size(), 0, "the row left after the minibatch");
}

#[test]
fn items_leave_after_max_times_sampled() {
    let mut c = cfg(10);
    c.max_times_sampled = 2;
    let t = Table::new(c, 9).unwrap();
    t.insert(&batch("a", 1, 0.0, 3), None).unwrap();
    let mut drawn = 0;
    while t.size() > 0 {
        drawn += t.sample(1, None, soon()).unwrap().num_rows;
        assert!(drawn <= 6);
    }
    assert_eq!(drawn, 6, "each of 3 items sampled exactly twice");
    assert!(t.sample(1, None, soon()).is_err());
}

#[test]
fn close_wakes_blocked_callers() {
    let mut c = cfg(10);
    c.rate_limiter.min_size_to_sample = 5;
    let t = Arc::new(Table::new(c, 10).unwrap());
    let t2 = Arc::clone(&t);
    let h = std::thread::spawn(move || t2.sample(1, None, None));
    std::thread::sleep(Duration::from_millis(30));
    t.close();
    assert!(matches!(h.join().unwrap(), Err(ReplayError::Closed(_))));
}

/// `b` with its float columns as `*_f32le` bytes.
fn as_bytes(mut b: TransitionBatch) -> TransitionBatch {
    b.convert_float_columns(FloatEncoding::F32Le);
    b
}

#[test]
fn float_columns_travel_as_bytes_in_and_out_with_the_same_rows() {
    // Two tables with the same seed: one fed packed columns and read packed, the other fed
    // and read as bytes. The draws and the data must agree exactly.
    let packed = Table::new(cfg(50), 11).unwrap();
    let bytes = Table::new(cfg(50), 11).unwrap();
    for seq in 1..=4 {
        let b = batch("a", seq, seq as f32 * 100.0, 20); // 80 rows into 50 slots: the ring wraps
        packed.insert(&b, None).unwrap();
        bytes.insert(&as_bytes(b), None).unwrap();
    }
    for _ in 0..5 {
        let p = packed.sample(64, None, None).unwrap();
        let b = bytes.sample_as(64, None, None, FloatEncoding::F32Le).unwrap();
        assert!(b.obs.is_empty() && b.reward.is_empty(), "the bytes encoding replaces the packed fields");
        assert_eq!(b.obs_column().encoding(), FloatEncoding::F32Le);
        assert_eq!(b.validate(D, 2, 1000), Ok(64));
        assert_eq!((&p.keys, &p.probabilities, &p.importance_weights), (&b.keys, &b.probabilities, &b.importance_weights));
        assert_eq!(p.obs, b.obs_column().to_vec());
        assert_eq!(p.next_obs, b.next_obs_column().to_vec());
        assert_eq!(p.action, b.action_column().to_vec());
        assert_eq!(p.reward, b.reward_column().to_vec());
        assert_eq!((&p.terminal, &p.step, &p.episode_id), (&b.terminal, &b.step, &b.episode_id));
        let mut back = b.clone();
        back.convert_float_columns(FloatEncoding::Packed);
        assert_eq!(back, p, "converted back, the minibatch is the packed one");
    }
}

#[test]
fn malformed_bytes_columns_are_refused_naming_the_column_and_counted() {
    let t = Table::new(cfg(100), 12).unwrap();
    t.insert(&as_bytes(batch("good", 1, 0.0, 5)), None).unwrap();
    let mut ragged = as_bytes(batch("bad", 1, 0.0, 2));
    ragged.obs_f32le = ragged.obs_f32le.slice(..ragged.obs_f32le.len() - 1); // not a multiple of 4
    let mut short = as_bytes(batch("bad", 2, 0.0, 2));
    short.next_obs_f32le = short.next_obs_f32le.slice(..short.next_obs_f32le.len() - 4); // one float short
    let mut both = as_bytes(batch("bad", 3, 0.0, 2));
    both.reward = vec![0.0, 1.0]; // and reward_f32le
    let mut nan = as_bytes(batch("bad", 4, 0.0, 2));
    let mut action = nan.action_f32le.to_vec();
    action[8..12].copy_from_slice(&f32::NAN.to_le_bytes()); // float 2: row 1, element 0 (act_dim 2)
    nan.action_f32le = action.into();
    for (b, column) in [(ragged, "obs_f32le"), (short, "next_obs_f32le"), (both, "reward_f32le"), (nan, "action_f32le")] {
        let e = t.insert(&b, None).unwrap_err();
        let status = e.to_status();
        assert_eq!(status.code(), tonic::Code::InvalidArgument, "{e}");
        assert!(status.message().contains(column), "{column}: {}", status.message());
    }
    assert_eq!(t.actors()["bad"].rejected_batches, 4);
    assert!(t.actors()["bad"].last_rejection.contains("row 1 element 0"), "{}", t.actors()["bad"].last_rejection);
    assert_eq!(t.size(), 5, "nothing of the refused batches was stored");
}

#[test]
fn uniform_sampling_draws_every_stored_row_equally_often_after_the_ring_wraps() {
    let t = Table::new(cfg(8), 13).unwrap();
    t.insert(&batch("a", 1, 0.0, 13), None).unwrap(); // keys 5..13 stored, slots wrapped
    let mut counts = [0u64; 8];
    let draws = 80_000usize;
    for _ in 0..draws / 100 {
        let s = t.sample(100, None, None).unwrap();
        assert!(s.probabilities.iter().all(|&p| p == 1.0 / 8.0) && s.importance_weights.iter().all(|&w| w == 1.0));
        for (k, r) in s.keys.iter().zip(&s.reward) {
            assert_eq!(*r, *k as f32, "row with key {k} holds its own data");
            counts[(*k - 5) as usize] += 1;
        }
    }
    // Pearson χ² with 7 degrees of freedom below 24.32 (p = 0.001).
    let e = draws as f64 / 8.0;
    let chi2: f64 = counts.iter().map(|&c| (c as f64 - e).powi(2) / e).sum();
    assert!(chi2 < 24.32, "counts {counts:?}, chi2 {chi2}");
}

/// A journal that records what it is handed, and refuses while `refuse` is set.
#[derive(Default)]
struct Recorder {
    events: std::sync::Mutex<Vec<String>>,
    refuse: std::sync::atomic::AtomicBool,
}

impl mapless_replay::Journal for Recorder {
    fn insert(&self, first_key: u64, rows: u64, _unix_ms: u64, batch_bytes: &[u8]) -> Result<(), ReplayError> {
        if self.refuse.load(std::sync::atomic::Ordering::SeqCst) {
            return Err(ReplayError::Storage { path: "journal".into(), problem: "refused".into() });
        }
        let b = <TransitionBatch as prost::Message>::decode(batch_bytes).unwrap();
        self.events.lock().unwrap().push(format!("insert {first_key}+{rows} {}#{}", b.actor_id, b.sequence));
        Ok(())
    }
    fn priorities(&self, pairs: &[(u64, f64)]) -> Result<(), ReplayError> {
        if self.refuse.load(std::sync::atomic::Ordering::SeqCst) {
            return Err(ReplayError::Storage { path: "journal".into(), problem: "refused".into() });
        }
        self.events.lock().unwrap().push(format!("priorities {pairs:?}"));
        Ok(())
    }
    fn position(&self) -> u64 {
        self.events.lock().unwrap().len() as u64
    }
}

#[test]
fn the_journal_gets_every_accepted_change_first_and_a_refused_one_changes_nothing() {
    let mut t = Table::new(TableConfig { sampler: SamplerConfig::Prioritized { alpha: 1.0, beta: 0.0, epsilon: 0.0 }, ..cfg(10) }, 1).unwrap();
    let journal = Arc::new(Recorder::default());
    t.set_journal(Arc::clone(&journal) as Arc<dyn mapless_replay::Journal>);
    t.insert(&batch("a", 1, 0.0, 4), None).unwrap();
    assert!(t.insert(&batch("a", 1, 0.0, 4), None).unwrap().duplicate, "a resend is acknowledged, not journaled");
    t.insert(&batch("b", 1, 0.0, 8), None).unwrap(); // evicts keys 0 and 1
    assert_eq!(t.update_priorities(&[0, 5, 11], &[2.0, 3.0, 4.0]).unwrap(), (2, 1));
    let cp = t.checkpoint();
    assert_eq!((cp.journal_position, cp.next_key, cp.size), (3, 12, 10));

    // A journal that refuses: nothing stored, nothing acknowledged, no de-duplication mark.
    journal.refuse.store(true, std::sync::atomic::Ordering::SeqCst);
    let e = t.insert(&batch("a", 2, 0.0, 3), None).unwrap_err();
    assert!(matches!(e, ReplayError::Storage { .. }), "{e}");
    assert!(t.update_priorities(&[5], &[9.0]).is_err());
    let after = t.checkpoint();
    assert_eq!((after.next_key, after.size, after.weights.clone(), after.actors["a"].last_sequence), (cp.next_key, cp.size, cp.weights.clone(), 1));
    journal.refuse.store(false, std::sync::atomic::Ordering::SeqCst);
    assert!(!t.insert(&batch("a", 2, 0.0, 3), None).unwrap().duplicate, "the refused batch is taken when resent");

    assert_eq!(*journal.events.lock().unwrap(), ["insert 0+4 a#1", "insert 4+8 b#1", "priorities [(5, 3.0), (11, 4.0)]", "insert 12+3 a#2"].map(String::from));
    assert_eq!(t.checkpoint().mark(), mapless_replay::CheckpointMark { journal_position: 4, samples: 0 });
}

#[test]
fn try_sample_never_waits_and_async_waiters_wake_on_insert() {
    let mut c = cfg(100);
    c.rate_limiter.min_size_to_sample = 5;
    let t = Arc::new(Table::new(c, 1).unwrap());
    let started = Instant::now();
    assert!(t.try_sample_as(2, None, FloatEncoding::Packed).unwrap().is_none(), "below min size: no, at once");
    assert!(started.elapsed() < Duration::from_secs(1));
    let rt = tokio::runtime::Builder::new_current_thread().enable_time().build().unwrap();
    rt.block_on(async {
        let mut changed = std::pin::pin!(t.changed());
        changed.as_mut().enable();
        let t2 = Arc::clone(&t);
        std::thread::spawn(move || t2.insert(&batch("a", 1, 0.0, 5), None).unwrap());
        tokio::time::timeout(Duration::from_secs(10), changed).await.expect("an insert wakes async waiters");
    });
    assert_eq!(t.try_sample_as(2, None, FloatEncoding::Packed).unwrap().expect("allowed now").num_rows, 2);
    t.record_sample_blocked(Duration::from_millis(250));
    assert!(t.info().rate_limiter.unwrap().samples_blocked_ms >= 250);
    let e = t.sample_deadline_exceeded(Duration::from_millis(7));
    assert!(matches!(e, ReplayError::DeadlineExceeded { op: "sample", waited_ms: 7, .. }), "{e}");
    assert!(e.to_string().contains("rate limiter"), "{e}");
    t.close();
    assert!(matches!(t.try_sample_as(2, None, FloatEncoding::Packed), Err(ReplayError::Closed(_))));
}
