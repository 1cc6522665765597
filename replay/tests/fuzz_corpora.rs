//! The fuzz targets' committed inputs on stable: every file of `fuzz/corpus/<target>/` (seeds
//! and what `cargo fuzz cmin` kept) and of `fuzz/regressions/<target>/` (inputs that once
//! found a bug) goes through the same harness the fuzzer runs (`mapless_replay::fuzzing`).
//!
//! The seeds are written by the project's own encoders:
//! `MAPLESS_WRITE_FUZZ_SEEDS=1 cargo test -p mapless-replay --test fuzz_corpora -- --ignored`
//! (docs/reliability.md, "Fuzzing").

use mapless_proto::v1::{PriorityUpdate, ProtocolVersion, RegisterActorRequest, SampleRequest, TransitionBatch};
use mapless_replay::fuzzing::{self, frame_all, op, seed_batches, shm_frame};
use prost::Message;

#[path = "../../tests/common/fuzz_corpus.rs"]
mod fuzz_corpus;
use fuzz_corpus::replay_inputs;

#[test]
fn replay_ingest_corpus_and_regressions() {
    assert!(replay_inputs("replay_ingest", fuzzing::replay_ingest) > 0, "no committed inputs for replay_ingest");
}

#[test]
fn shm_wire_corpus_and_regressions() {
    assert!(replay_inputs("shm_wire", fuzzing::shm_wire) > 0, "no committed inputs for shm_wire");
}

#[test]
fn replay_requests_corpus_and_regressions() {
    assert!(replay_inputs("replay_requests", fuzzing::replay_requests) > 0, "no committed inputs for replay_requests");
}

#[test]
fn wal_recovery_corpus_and_regressions() {
    assert!(replay_inputs("wal_recovery", fuzzing::wal_recovery) > 0, "no committed inputs for wal_recovery");
}

#[test]
fn actor_slots_corpus_and_regressions() {
    assert!(replay_inputs("actor_slots", fuzzing::actor_slots) > 0, "no committed inputs for actor_slots");
}

#[test]
fn the_seeds_pass_their_harnesses() {
    for (target, _, data) in seeds() {
        match target {
            "replay_ingest" => fuzzing::replay_ingest(&data),
            "shm_wire" => fuzzing::shm_wire(&data),
            "replay_requests" => fuzzing::replay_requests(&data),
            "actor_slots" => fuzzing::actor_slots(&data),
            _ => fuzzing::wal_recovery(&data),
        }
    }
}

/// Valid and broken batches, as encoded bytes.
fn batch_bytes() -> (Vec<Vec<u8>>, Vec<Vec<u8>>) {
    let valid: Vec<Vec<u8>> = seed_batches().iter().map(|b| b.encode_to_vec()).collect();
    let base = seed_batches()[1].clone(); // packed floats
    let mut broken = Vec::new();
    let mut push = |f: &dyn Fn(&mut TransitionBatch)| {
        let mut b = base.clone();
        f(&mut b);
        broken.push(b.encode_to_vec());
    };
    push(&|b| b.obs_dim = 4);
    push(&|b| b.obs[1] = f32::NAN);
    push(&|b| b.reward[0] = f32::INFINITY);
    push(&|b| {
        b.terminal[0] = true;
        b.truncated[0] = true
    });
    push(&|b| b.sequence = 0);
    push(&|b| b.actor_id.clear());
    push(&|b| b.actor_id = "x".repeat(200));
    push(&|b| b.num_rows = 17);
    push(&|b| b.protocol_version = 2);
    push(&|b| b.obs_f32le = vec![0u8; 4 * b.obs.len()].into());
    push(&|b| {
        b.obs.clear();
        b.obs_f32le = vec![0u8; 5].into()
    });
    push(&|b| {
        b.step.pop();
    });
    broken.push(vec![0x0a, 0xff, 0xff, 0xff, 0xff, 0x0f]); // a length past the end
    broken.push(b"not a protobuf message at all".to_vec());
    (valid, broken)
}

/// Every seed: (target, file name, bytes).
fn seeds() -> Vec<(&'static str, String, Vec<u8>)> {
    let (valid, broken) = batch_bytes();
    let mut out = Vec::new();

    // replay_ingest: config byte, frames of prost bytes.
    out.push(("replay_ingest", "valid-uniform".into(), frame_all(0, &valid)));
    let mut resend = valid.clone();
    resend.extend([valid[2].clone(), valid[0].clone(), valid[5].clone()]);
    out.push(("replay_ingest", "resends-prioritized".into(), frame_all(1, &resend)));
    let big = seed_batches().into_iter().map(|mut b| {
        b.sequence += 100;
        b.encode_to_vec()
    });
    out.push(("replay_ingest", "wraps-capacity-5".into(), frame_all(2, &valid.iter().cloned().chain(big).collect::<Vec<_>>())));
    let mut mixed = Vec::new();
    for (i, b) in broken.iter().enumerate() {
        mixed.push(b.clone());
        mixed.push(valid[i % valid.len()].clone());
    }
    out.push(("replay_ingest", "broken-between-valid".into(), frame_all(3, &mixed)));

    // shm_wire: config byte, frames of header + payload.
    let shm_valid: Vec<Vec<u8>> = seed_batches().iter().zip(&valid).map(|(b, bytes)| shm_frame(b.sequence, b.actor_id.as_bytes(), bytes)).collect();
    out.push(("shm_wire", "valid".into(), frame_all(0, &shm_valid)));
    let b0 = &seed_batches()[0];
    let bad_headers = vec![
        shm_frame(b0.sequence + 1, b0.actor_id.as_bytes(), &valid[0]), // sequence disagrees
        shm_frame(b0.sequence, b"someone-else", &valid[0]),            // actor disagrees
        shm_frame(b0.sequence, b"", &valid[0]),                        // no actor id
        shm_frame(b0.sequence, &[0xff, 0xfe, 0x00], &valid[0]),        // not UTF-8
        shm_frame(b0.sequence, &[b'a'; 200], &valid[0]),               // longer than the limit
        shm_frame(b0.sequence, b0.actor_id.as_bytes(), &broken[13]),   // undecodable payload
        shm_valid[0].clone(),
        shm_valid[0].clone(), // a resend
    ];
    out.push(("shm_wire", "bad-headers".into(), frame_all(1, &bad_headers)));
    let shm_broken: Vec<Vec<u8>> = broken
        .iter()
        .map(|bytes| {
            let b = TransitionBatch::decode(bytes.as_slice()).unwrap_or_default();
            shm_frame(b.sequence, b.actor_id.as_bytes(), bytes)
        })
        .collect();
    out.push(("shm_wire", "broken-batches".into(), frame_all(2, &shm_broken)));

    // replay_requests: config byte, frames of kind byte + prost bytes.
    let tagged = |kind: u8, bytes: Vec<u8>| [vec![kind], bytes].concat();
    let v1 = ProtocolVersion::V1 as i32;
    let sample = |batch_size: u32, importance_beta: f32, float_columns_as_bytes: bool| {
        tagged(1, SampleRequest { protocol_version: v1, batch_size, importance_beta: Some(importance_beta), float_columns_as_bytes, ..Default::default() }.encode_to_vec())
    };
    let priorities = |keys: Vec<u64>, priorities: Vec<f64>| tagged(2, PriorityUpdate { protocol_version: v1, keys, priorities, ..Default::default() }.encode_to_vec());
    let mut session = vec![sample(4, 0.4, false)]; // an empty table: the rate limiter's deadline
    session.extend(valid.iter().cloned().map(|b| tagged(0, b)));
    session.extend([
        sample(4, 0.4, false),
        sample(8, 1.0, true),
        priorities(vec![0, 1, 2, 3], vec![0.5, 2.0, 0.0, 1e3]),
        priorities(vec![3, 3, 1000], vec![1.0, 7.0, 1.0]), // a repeated and an unknown key
        sample(8, 0.0, false),
        priorities(vec![1, 2], vec![1e200, 0.0]), // far apart
        sample(5, 1.0, true),
        priorities(vec![1], vec![f64::NAN]), // refused
        priorities(vec![1, 2], vec![1.0]),   // refused
        sample(0, 0.4, false),               // refused
        sample(9, 0.4, false),               // refused: above max_sample_rows
        sample(2, 1.5, false),               // refused
        tagged(1, b"not a protobuf message".to_vec()),
        tagged(2, vec![0x0a, 0xff, 0xff, 0xff, 0xff, 0x0f]),
    ]);
    // config bytes: 1: prioritised α 0.6; 9 (8|1): α 3; 13 (12|1): α 0; 17 (16|1): ε 0; 0: uniform.
    for config in [1u8, 9, 13, 17, 0, 3] {
        out.push(("replay_requests", format!("session-config-{config}"), frame_all(config, &session)));
    }

    // wal_recovery: base byte, ops.
    // Files are sorted by path: the snapshot (if any) first, then the segments in LSN order.
    let seg = |kind: u8, i: usize| (fuzzing::base_files(kind).iter().position(|(n, _)| n.starts_with("wal/")).unwrap() + i) as u8;
    let last_seg = |kind: u8| fuzzing::base_files(kind).iter().rposition(|(n, _)| n.starts_with("wal/")).unwrap() as u8;
    let snap = |kind: u8| fuzzing::base_files(kind).iter().position(|(n, _)| n.starts_with("snapshots/")).unwrap_or(0) as u8;
    for kind in 0..3u8 {
        out.push(("wal_recovery", format!("base-{kind}-undamaged"), vec![kind]));
        out.push(("wal_recovery", format!("base-{kind}-torn-tail"), vec![kind, op::TRUNCATE, last_seg(kind), 0xf0, 0x0f]));
        out.push(("wal_recovery", format!("base-{kind}-flip-first-segment"), vec![kind, op::FLIP, seg(kind, 0), 100, 0, 0x40]));
        out.push(("wal_recovery", format!("base-{kind}-middle-segment-deleted"), vec![kind, op::DELETE, seg(kind, 1)]));
        out.push(("wal_recovery", format!("base-{kind}-segments-swapped"), vec![kind, op::SWAP, seg(kind, 0), seg(kind, 1)]));
        out.push(("wal_recovery", format!("base-{kind}-segment-copied-ahead"), vec![kind, op::COPY_AS, seg(kind, 0), 200]));
    }
    for kind in 1..3u8 {
        out.push(("wal_recovery", format!("base-{kind}-snapshot-flipped"), vec![kind, op::FLIP, snap(kind), 40, 0, 0x01]));
        out.push(("wal_recovery", format!("base-{kind}-snapshot-forged"), vec![kind, op::OVERWRITE, snap(kind), 20, 0, 3, b'9', b'9', b'9', op::FIX_CHECKSUMS, snap(kind)]));
        out.push(("wal_recovery", format!("base-{kind}-snapshot-deleted"), vec![kind, op::DELETE, snap(kind)]));
    }
    // actor_slots: max byte (max_actor_slots = 1 + byte % 8), the slot file, registrations.
    let register = |name: &str| RegisterActorRequest { protocol_version: v1, name: name.to_owned() }.encode_to_vec();
    let file = |text: &str| text.as_bytes().to_vec();
    let names = |list: &[&str]| list.iter().map(|n| register(n)).collect::<Vec<_>>();
    let mut fresh = vec![Vec::new()]; // no file yet
    fresh.extend(names(&["mapless-actor-1", "mapless-actor-2", "mapless-actor-1", "", "tab\there", &"x".repeat(129), "ünïcödé", "mapless-actor-3"]));
    fresh.push(RegisterActorRequest { protocol_version: 0, name: "old-client".into() }.encode_to_vec());
    fresh.push(b"not a protobuf message".to_vec());
    out.push(("actor_slots", "fresh-then-full".into(), frame_all(2, &fresh)));
    let mut known = vec![file(r#"{"version": 1, "slots": {"a": 0, "c": 2, "far": 40}}"#)];
    known.extend(names(&["c", "b", "d", "a", "e"]));
    out.push(("actor_slots", "file-with-a-gap".into(), frame_all(5, &known)));
    for (name, text) in [
        ("file-torn", r#"{"version": 1, "slots": {"a": 0"#),
        ("file-two-names-one-slot", r#"{"version": 1, "slots": {"a": 0, "b": 0}}"#),
        ("file-other-version", r#"{"version": 2, "slots": {}}"#),
        ("file-bad-name", r#"{"version": 1, "slots": {"": 3}}"#),
        ("file-negative-slot", r#"{"version": 1, "slots": {"a": -1}}"#),
        ("file-unknown-field", r#"{"version": 1, "slots": {}, "extra": true}"#),
    ] {
        out.push(("actor_slots", name.into(), frame_all(7, &[file(text), register("a")])));
    }
    out.push(("wal_recovery", "base-1-record-forged".into(), vec![1, op::OVERWRITE, seg(1, 0), 60, 0, 8, 0, 0, 0, 0, 0, 0, 0xf8, 0x7f, op::FIX_CHECKSUMS, seg(1, 0)]));
    out
}

/// Writes the seeds into `fuzz/corpus/<target>/seed-<name>` (run by hand; see the module doc).
#[test]
#[ignore]
fn write_seed_corpora() {
    for target in ["replay_ingest", "shm_wire", "replay_requests", "wal_recovery", "actor_slots"] {
        fuzz_corpus::write_seeds(target, seeds().into_iter().filter(|(t, _, _)| *t == target).map(|(_, name, data)| (name, data)));
    }
}
