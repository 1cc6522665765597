//! Shared by the shm examples and `tests/shm.rs`: a synthetic batch and a writer loop.

#![allow(dead_code)]

use std::time::{Duration, Instant};

use mapless_net::shm::{Ack, ShmConfig, ShmError, ShmWriter};
use mapless_proto::v1::{ProtocolVersion, TransitionBatch};
use mapless_replay::ReplayError;

/// A valid batch of `rows` transitions with `obs_dim`-float observations and 2-float
/// actions; reward i and step i for row i, policy version = sequence.
pub fn synthetic_batch(actor: &str, sequence: u64, rows: usize, obs_dim: usize) -> TransitionBatch {
    TransitionBatch {
        protocol_version: ProtocolVersion::V1 as i32,
        actor_id: actor.to_string(),
        sequence,
        obs_dim: obs_dim as u32,
        act_dim: 2,
        num_rows: rows as u32,
        obs: (0..rows * obs_dim).map(|i| (i % 97) as f32 * 0.01).collect(),
        action: vec![0.25; rows * 2],
        reward: (0..rows).map(|i| i as f32).collect(),
        next_obs: (0..rows * obs_dim).map(|i| (i % 89) as f32 * 0.01).collect(),
        terminal: (0..rows).map(|i| i % 100 == 99).collect(),
        truncated: vec![false; rows],
        episode_id: vec![1; rows],
        step: (0..rows as u32).collect(),
        policy_version: vec![sequence; rows],
        ..TransitionBatch::default()
    }
}

/// What one writer run did.
#[derive(Debug, Default)]
pub struct WriterReport {
    pub stored: u64,
    pub duplicates: u64,
    pub rejected: u64,
    pub reconnects: u64,
    pub rows: u64,
    pub elapsed: Duration,
}

/// What a writer sends: batches `first_seq ..= first_seq + batches - 1` of `rows` rows.
#[derive(Clone, Debug)]
pub struct Plan {
    pub rows: usize,
    pub batches: u64,
    pub obs_dim: usize,
    pub first_seq: u64,
    /// Sleep between batches.
    pub pace: Duration,
    /// How long to keep reconnecting on connection trouble.
    pub patience: Duration,
}

impl Plan {
    /// `batches` batches of `rows` rows with 17-float observations from sequence 1, unpaced.
    pub fn new(rows: usize, batches: u64) -> Plan {
        Plan { rows, batches, obs_dim: 17, first_seq: 1, pace: Duration::ZERO, patience: Duration::from_secs(20) }
    }
}

/// Sends `plan`'s batches and waits for every ack, reconnecting (and so resending) on
/// connection trouble for up to `plan.patience`. `on_ack` sees every ack as it arrives.
pub fn run_writer(cfg: &ShmConfig, actor: &str, plan: &Plan, mut on_ack: impl FnMut(&Ack)) -> Result<WriterReport, ReplayError> {
    let Plan { rows, batches, obs_dim, first_seq, pace, patience } = plan.clone();
    let start = Instant::now();
    let mut w = connect_patiently(cfg, actor, patience)?;
    let mut report = WriterReport::default();
    let mut batch = synthetic_batch(actor, first_seq, rows, obs_dim);
    let mut tally = |acks: Vec<Ack>, report: &mut WriterReport| {
        for a in acks {
            match &a {
                Ack::Stored(s) if s.duplicate => report.duplicates += 1,
                Ack::Stored(s) => {
                    report.stored += 1;
                    report.rows += u64::from(s.accepted_rows);
                }
                Ack::Rejected { .. } => report.rejected += 1,
            }
            on_ack(&a);
        }
    };
    for seq in first_seq..first_seq + batches {
        batch.sequence = seq;
        loop {
            match w.send(&batch) {
                Ok(()) => break,
                Err(ShmError::Closed(_)) if start.elapsed() < patience => {
                    report.reconnects += 1;
                    std::thread::sleep(Duration::from_millis(20));
                    let _ = w.reconnect();
                }
                Err(e) => return Err(e.into()),
            }
        }
        match w.poll_acks() {
            Ok(acks) => tally(acks, &mut report),
            Err(ShmError::Closed(_)) if start.elapsed() < patience => {
                report.reconnects += 1;
                let _ = w.reconnect();
            }
            Err(e) => return Err(e.into()),
        }
        if !pace.is_zero() {
            std::thread::sleep(pace);
        }
    }
    loop {
        match w.wait_acks(start + patience.max(Duration::from_secs(1)) + Duration::from_secs(60)) {
            Ok(acks) => {
                tally(acks, &mut report);
                break;
            }
            Err(ShmError::Closed(_)) if start.elapsed() < patience => {
                report.reconnects += 1;
                std::thread::sleep(Duration::from_millis(20));
                let _ = w.reconnect();
            }
            Err(e) => return Err(e.into()),
        }
    }
    report.elapsed = start.elapsed();
    Ok(report)
}

/// `ShmWriter::connect`, retried while the service is not up yet.
pub fn connect_patiently(cfg: &ShmConfig, actor: &str, patience: Duration) -> Result<ShmWriter, ReplayError> {
    let start = Instant::now();
    loop {
        match ShmWriter::connect(cfg, actor) {
            Ok(w) => return Ok(w),
            Err(ShmError::Closed(_)) if start.elapsed() < patience => std::thread::sleep(Duration::from_millis(20)),
            Err(e) => return Err(e.into()),
        }
    }
}
