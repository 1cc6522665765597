//! The shared-memory ingest: every batch acknowledged and stored exactly once, resends after
//! reconnecting acknowledged as duplicates, writers and servers killed with SIGKILL leave
//! nothing that blocks the others or a fresh ingest, bad input is counted and answered.
//!
//! Writer and server processes are the `shm_writer` and `shm_ingest` examples, built by a
//! nested `cargo build` the first time a test needs them. The tests run one at a time (they
//! kill processes and count dead-node cleanups, which any other iceoryx2 node in this
//! process could do for them).

#[path = "../../tests/common/workspace_build.rs"]
mod workspace_build;

#[path = "../examples/shm_common/mod.rs"]
mod shm_common;

use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::mpsc::{Receiver, channel};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use mapless_net::insert::ShmInsertClient;
use mapless_net::shm::{Ack, ShmConfig, ShmError, ShmWriter};
use mapless_proto::FloatEncoding;
use mapless_replay::shm::ShmIngest;
use mapless_replay::{RateLimiterConfig, Table, TableConfig};
use prost::Message;
use shm_common::{Plan, run_writer, synthetic_batch};

const OBS: usize = 17;

static DOMAINS: Mutex<Vec<String>> = Mutex::new(Vec::new());

/// Runs tests one at a time; at the end of each, removes the one file iceoryx2 keeps per
/// domain (its global management segment), so test runs leave nothing in /dev/shm.
struct Serial(#[allow(dead_code)] MutexGuard<'static, ()>);

fn serial() -> Serial {
    static SERIAL: Mutex<()> = Mutex::new(());
    Serial(SERIAL.lock().unwrap_or_else(|p| p.into_inner()))
}

impl Drop for Serial {
    fn drop(&mut self) {
        for d in DOMAINS.lock().unwrap_or_else(|p| p.into_inner()).drain(..) {
            for f in files_of(&d) {
                if f.ends_with(".global_mgmt") {
                    let _ = std::fs::remove_file(f);
                }
            }
        }
    }
}

/// Every file of an iceoryx2 domain in /dev/shm and under /tmp/iceoryx2.
fn files_of(domain: &str) -> Vec<String> {
    fn walk(dir: &std::path::Path, domain: &str, out: &mut Vec<String>) {
        for e in std::fs::read_dir(dir).into_iter().flatten().flatten() {
            let path = e.path();
            if path.is_dir() {
                walk(&path, domain, out);
            } else if e.file_name().to_string_lossy().starts_with(domain) {
                out.push(path.display().to_string());
            }
        }
    }
    let mut out = Vec::new();
    walk(std::path::Path::new("/dev/shm"), domain, &mut out);
    walk(std::path::Path::new("/tmp/iceoryx2"), domain, &mut out);
    out
}

/// Files of the domain left behind, apart from the management segment iceoryx2 keeps.
fn leftovers(domain: &str) -> Vec<String> {
    files_of(domain).into_iter().filter(|f| !f.ends_with(".global_mgmt")).collect()
}

/// A service in an iceoryx2 domain of its own: no other test, test run or process on this
/// host sees (or cleans up) its nodes.
fn cfg(tag: &str) -> ShmConfig {
    static N: AtomicU32 = AtomicU32::new(0);
    let n = N.fetch_add(1, Ordering::Relaxed);
    let domain = format!("mlt{}x{n}_", std::process::id());
    DOMAINS.lock().unwrap_or_else(|p| p.into_inner()).push(domain.clone());
    ShmConfig { prefix: format!("mapless-test/{tag}"), domain, dead_node_scan_ms: 100, ..ShmConfig::default() }
}

/// samples_per_insert 1, error_buffer 100: inserts wait once 110 rows are unsampled, so the
/// third batch of 100 rows waits for sampling.
fn rate_limited_table() -> Arc<Table> {
    let c = TableConfig {
        capacity: 10_000,
        obs_dim: OBS,
        rate_limiter: RateLimiterConfig { min_size_to_sample: 10, samples_per_insert: Some(1.0), error_buffer: 100.0 },
        max_batch_rows: 100,
        max_sample_rows: 100,
        ..TableConfig::default()
    };
    Arc::new(Table::new(c, 1).unwrap())
}

fn table() -> Arc<Table> {
    let c =
        TableConfig { capacity: 100_000, obs_dim: OBS, rate_limiter: RateLimiterConfig { min_size_to_sample: 1, samples_per_insert: None, ..RateLimiterConfig::default() }, ..TableConfig::default() };
    Arc::new(Table::new(c, 1).unwrap())
}

fn in_secs(s: u64) -> Instant {
    Instant::now() + Duration::from_secs(s)
}

/// Path of an example binary, brought up to date once with the profile this test runs under.
fn example(name: &str) -> PathBuf {
    let exe = std::env::current_exe().unwrap();
    let profile_dir = exe.parent().and_then(|deps| deps.parent()).unwrap().to_path_buf();
    workspace_build::build_workspace_once(&profile_dir);
    profile_dir.join("examples").join(name)
}

/// A child process whose stdout lines arrive on a channel; killed (SIGKILL) when dropped.
struct Proc {
    child: Child,
    lines: Receiver<String>,
}

impl Proc {
    fn spawn(example_name: &str, args: &[&str]) -> Proc {
        let mut child = Command::new(example(example_name)).args(args).stdout(Stdio::piped()).spawn().unwrap();
        let stdout = child.stdout.take().unwrap();
        let (tx, lines) = channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        Proc { child, lines }
    }

    /// Waits for a line satisfying `want`; panics after `secs`.
    fn wait_for(&self, secs: u64, want: impl Fn(&str) -> bool) -> String {
        let deadline = in_secs(secs);
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.lines.recv_timeout(left) {
                Ok(l) if want(&l) => return l,
                Ok(_) => {}
                Err(e) => panic!("child did not print the expected line within {secs} s: {e}"),
            }
        }
    }

    fn sigkill(&mut self) {
        self.child.kill().unwrap(); // SIGKILL on Unix
        self.child.wait().unwrap();
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn acked_at_least(n: u64) -> impl Fn(&str) -> bool {
    move |l: &str| l.strip_prefix("acked ").and_then(|s| s.parse::<u64>().ok()).is_some_and(|s| s >= n)
}

fn stored(acks: &[Ack]) -> Vec<(u64, bool)> {
    acks.iter()
        .map(|a| match a {
            Ack::Stored(s) => (s.sequence, s.duplicate),
            Ack::Rejected { sequence, reason } => panic!("batch {sequence} rejected: {reason}"),
        })
        .collect()
}

#[test]
fn shm_writer_can_move_to_another_thread() {
    fn is_send<T: Send>() {}
    is_send::<ShmWriter>();
    is_send::<ShmIngest>();
}

#[test]
fn config_defaults_name_the_table_and_bad_values_are_refused() {
    let c = ShmConfig::default();
    assert_eq!(c.prefix, "mapless/replay/transitions");
    assert_eq!(c.service_name(), "mapless/replay/transitions/insert");
    assert_eq!(c.max_payload_bytes, mapless_proto::MAX_MESSAGE_BYTES);
    c.validate().unwrap();
    let parsed: ShmConfig = serde_yaml::from_str("prefix: mapless/replay/other\nmax_in_flight: 4\n").unwrap();
    assert_eq!(parsed, ShmConfig { prefix: "mapless/replay/other".into(), max_in_flight: 4, ..ShmConfig::default() });
    for bad in [
        ShmConfig { prefix: String::new(), ..ShmConfig::default() },
        ShmConfig { max_payload_bytes: mapless_proto::MAX_MESSAGE_BYTES + 1, ..ShmConfig::default() },
        ShmConfig { max_in_flight: 0, ..ShmConfig::default() },
    ] {
        assert!(matches!(bad.validate(), Err(ShmError::InvalidConfig(_))), "{bad:?}");
    }
}

#[test]
fn writer_without_a_running_ingest_is_told_the_service_is_closed() {
    let _g = serial();
    let e = ShmWriter::connect(&cfg("nobody"), "a").err().unwrap();
    assert!(matches!(e, ShmError::Closed(_)), "{e}");
    assert_eq!(mapless_replay::ReplayError::from(e).to_status().code(), tonic::Code::Unavailable);
}

#[test]
fn every_batch_from_a_writer_thread_is_acked_and_stored_exactly_once() {
    let _g = serial();
    let (t, c) = (table(), cfg("once"));
    let ingest = ShmIngest::spawn(Arc::clone(&t), c.clone()).unwrap();
    let writer = {
        let c = c.clone();
        std::thread::spawn(move || run_writer(&c, "w", &Plan::new(64, 100), |_| {}))
    };
    let report = writer.join().unwrap().unwrap();
    assert_eq!((report.stored, report.duplicates, report.rejected, report.rows), (100, 0, 0, 6400));
    assert_eq!(t.size(), 6400);
    let a = &t.actors()["w"];
    assert_eq!((a.batches, a.rows, a.last_sequence, a.duplicate_batches), (100, 6400, 100, 0));
    let s = ingest.stats();
    assert_eq!((s.batches_stored, s.rows_stored, s.rejected_batches), (100, 6400, 0));
    ingest.stop();
}

#[test]
fn resending_after_reconnect_is_acked_as_duplicate_and_never_stored_twice() {
    let _g = serial();
    let (t, c) = (table(), cfg("resend"));
    let ingest = ShmIngest::spawn(Arc::clone(&t), c.clone()).unwrap();
    let mut w = ShmWriter::connect(&c, "r").unwrap();
    for seq in 1..=5 {
        w.send(&synthetic_batch("r", seq, 10, OBS)).unwrap();
    }
    assert_eq!(stored(&w.wait_acks(in_secs(20)).unwrap()), [(1, false), (2, false), (3, false), (4, false), (5, false)]);
    // 6..=8 reach the table but their acks are never read: as if the connection broke.
    for seq in 6..=8 {
        w.send(&synthetic_batch("r", seq, 10, OBS)).unwrap();
    }
    let deadline = in_secs(20);
    while t.size() < 80 {
        assert!(Instant::now() < deadline, "batches 6..=8 never stored");
        std::thread::sleep(Duration::from_millis(5));
    }
    assert_eq!(w.unacked(), 3);
    w.reconnect().unwrap(); // resends 6, 7, 8
    w.send(&synthetic_batch("r", 9, 10, OBS)).unwrap();
    assert_eq!(stored(&w.wait_acks(in_secs(20)).unwrap()), [(6, true), (7, true), (8, true), (9, false)]);
    assert_eq!(t.size(), 90);
    let a = &t.actors()["r"];
    assert_eq!((a.batches, a.rows, a.duplicate_batches), (9, 90, 3));
    assert_eq!(ingest.stats().duplicate_batches, 3);
    // A sequence at or below the last one sent is the caller's mistake, not a resend.
    assert!(matches!(w.send(&synthetic_batch("r", 9, 10, OBS)), Err(ShmError::BadRequest(_))));
    ingest.stop();
}

#[test]
fn de_duplication_spans_transports_because_both_feed_one_table() {
    let _g = serial();
    let (t, c) = (table(), cfg("transports"));
    let ingest = ShmIngest::spawn(Arc::clone(&t), c.clone()).unwrap();
    // Batches 1..=5 arrive the way the gRPC Insert stream stores them.
    for seq in 1..=5 {
        t.insert(&synthetic_batch("both", seq, 10, OBS), None).unwrap();
    }
    // The actor moves to shared memory and resends from 4 (it never saw those acks).
    let mut w = ShmWriter::connect(&c, "both").unwrap();
    for seq in 4..=7 {
        w.send(&synthetic_batch("both", seq, 10, OBS)).unwrap();
    }
    assert_eq!(stored(&w.wait_acks(in_secs(20)).unwrap()), [(4, true), (5, true), (6, false), (7, false)]);
    let a = &t.actors()["both"];
    assert_eq!((a.batches, a.rows, a.duplicate_batches), (7, 70, 2));
    ingest.stop();
}

#[test]
fn killed_writer_process_blocks_nobody_and_a_fresh_ingest_cleans_up_after_it() {
    let _g = serial();
    let (t, c) = (table(), cfg("killwriter"));
    // No janitor help while the first ingest runs: it must keep serving with a dead writer's
    // resources still in place, and leave them for the fresh ingest below.
    let ingest = ShmIngest::spawn(Arc::clone(&t), ShmConfig { dead_node_scan_ms: 600_000, ..c.clone() }).unwrap();

    // A writer process streams and is killed mid-stream.
    let mut victim = Proc::spawn("shm_writer", &[&c.prefix, "victim", "64", "1000000", "17", "--pace-us", "1000", "--progress", "--domain", &c.domain]);
    victim.wait_for(30, acked_at_least(20));
    victim.sigkill();

    // Another writer is served as if nothing happened.
    let report = run_writer(&c, "survivor", &Plan::new(64, 200), |_| {}).unwrap();
    assert_eq!((report.stored, report.rows), (200, 12_800));

    // The victim's rows are all there, each batch once, without gaps.
    let v = t.actors()["victim"].clone();
    assert!(v.last_sequence >= 20);
    assert_eq!((v.batches, v.rows), (v.last_sequence, 64 * v.last_sequence));

    // The actor restarts: the dead writer's claim on its actor id is dropped, and batches it
    // may not have seen acknowledged are resent and recognised as duplicates.
    // (Requests the victim left queued may still be stored meanwhile, hence "at least".)
    let first = v.last_sequence - 1;
    let report = run_writer(&c, "victim", &Plan { first_seq: first, ..Plan::new(64, 10) }, |_| {}).unwrap();
    assert!(report.duplicates >= 2 && report.duplicates + report.stored == 10, "{report:?}");
    let v = t.actors()["victim"].clone();
    assert_eq!((v.last_sequence, v.batches, v.rows), (first + 9, first + 9, 64 * (first + 9)));

    // A second writer process is killed and the ingest stopped before anyone cleans up: its
    // resources are stale until a fresh ingest removes them on start.
    let mut victim2 = Proc::spawn("shm_writer", &[&c.prefix, "victim2", "64", "1000000", "17", "--pace-us", "1000", "--progress", "--domain", &c.domain]);
    victim2.wait_for(30, acked_at_least(5));
    victim2.sigkill();
    ingest.stop();

    let fresh = ShmIngest::spawn(Arc::clone(&t), c.clone()).unwrap();
    assert!(fresh.stats().dead_nodes_cleaned >= 1, "{:?}", fresh.stats());
    let report = run_writer(&c, "after", &Plan::new(64, 50), |_| {}).unwrap();
    assert_eq!(report.stored, 50);
    fresh.stop();
    // Nothing of the two killed writers is left in shared memory or on disk.
    assert_eq!(leftovers(&c.domain), Vec::<String>::new());
}

#[test]
fn killed_ingest_process_is_cleaned_up_by_a_fresh_ingest_and_writers_resend_to_it() {
    let _g = serial();
    let c = cfg("killserver");
    let mut server = Proc::spawn("shm_ingest", &[&c.prefix, "17", &c.domain]);
    server.wait_for(30, |l| l == "ready");
    let mut w = ShmWriter::connect(&c, "k").unwrap();
    for seq in 1..=5 {
        w.send(&synthetic_batch("k", seq, 32, OBS)).unwrap();
    }
    assert_eq!(w.wait_acks(in_secs(20)).unwrap().len(), 5);

    server.sigkill();
    // Sent into the dead server's queue: never answered. The writer notices the dead server.
    w.send(&synthetic_batch("k", 6, 32, OBS)).unwrap();
    let e = w.wait_acks(in_secs(20)).unwrap_err();
    assert!(matches!(e, ShmError::Closed(_)), "{e}");

    // The dead server still holds the service's one server slot until a fresh ingest cleans up.
    let t = table();
    let fresh = ShmIngest::spawn(Arc::clone(&t), c.clone()).unwrap();
    assert!(fresh.stats().dead_nodes_cleaned >= 1, "{:?}", fresh.stats());
    w.reconnect().unwrap();
    w.send(&synthetic_batch("k", 7, 32, OBS)).unwrap();
    assert_eq!(stored(&w.wait_acks(in_secs(20)).unwrap()), [(6, false), (7, false)]);
    assert_eq!(t.actors()["k"].batches, 2);
    drop(w);
    fresh.stop();
    // Nothing of the killed server is left in shared memory or on disk.
    assert_eq!(leftovers(&c.domain), Vec::<String>::new());
}

#[test]
fn stopped_ingest_makes_writers_reconnect_and_resend_to_the_next_one() {
    let _g = serial();
    let (t, c) = (table(), cfg("restart"));
    let first = ShmIngest::spawn(Arc::clone(&t), c.clone()).unwrap();
    let mut w = ShmWriter::connect(&c, "s").unwrap();
    w.send(&synthetic_batch("s", 1, 8, OBS)).unwrap();
    w.wait_acks(in_secs(20)).unwrap();
    first.stop();
    w.send(&synthetic_batch("s", 2, 8, OBS)).unwrap(); // taken; nobody serves it
    assert!(matches!(w.poll_acks(), Err(ShmError::Closed(_))));
    assert_eq!(w.unacked(), 1);
    let second = ShmIngest::spawn(Arc::clone(&t), c.clone()).unwrap();
    w.reconnect().unwrap();
    assert_eq!(stored(&w.wait_acks(in_secs(20)).unwrap()), [(2, false)]);
    assert_eq!(t.actors()["s"].batches, 2);
    second.stop();
}

#[test]
fn malformed_and_invalid_payloads_are_counted_as_rejected_and_the_ingest_keeps_serving() {
    let _g = serial();
    let (t, c) = (table(), cfg("malformed"));
    let ingest = ShmIngest::spawn(Arc::clone(&t), c.clone()).unwrap();
    let mut w = ShmWriter::connect(&c, "m").unwrap();
    // 1: not a protobuf at all.
    w.send_encoded(1, vec![0xff; 100]).unwrap();
    // 2: decodes but breaks the contract (NaN observation).
    let mut nan = synthetic_batch("m", 2, 4, OBS);
    nan.obs[5] = f32::NAN;
    w.send(&nan).unwrap();
    // 3: a valid batch.
    w.send(&synthetic_batch("m", 3, 4, OBS)).unwrap();
    // 4: the payload claims another actor than the connection.
    w.send_encoded(4, synthetic_batch("someone-else", 4, 4, OBS).encode_to_vec()).unwrap();
    // 5: wrong observation width for this table.
    w.send(&synthetic_batch("m", 5, 4, OBS + 1)).unwrap();
    // 6: valid again.
    w.send(&synthetic_batch("m", 6, 4, OBS)).unwrap();
    // 7: rewards as bytes that are not a whole number of floats.
    let mut ragged = synthetic_batch("m", 7, 4, OBS);
    ragged.convert_float_columns(FloatEncoding::F32Le);
    ragged.reward_f32le = ragged.reward_f32le.slice(..15);
    w.send(&ragged).unwrap();
    let acks = w.wait_acks(in_secs(20)).unwrap();
    let summary: Vec<_> = acks
        .iter()
        .map(|a| match a {
            Ack::Stored(s) => (s.sequence, format!("stored {}", s.accepted_rows)),
            Ack::Rejected { sequence, reason } => (*sequence, reason.clone()),
        })
        .collect();
    assert_eq!(summary.len(), 7, "{summary:?}");
    assert!(summary[0].1.contains("undecodable"), "{summary:?}");
    assert!(summary[1].1.contains("obs"), "{summary:?}");
    assert_eq!(summary[2].1, "stored 4");
    assert!(summary[3].1.contains("someone-else"), "{summary:?}");
    assert!(summary[4].1.contains("obs_dim") || summary[4].1.contains("18"), "{summary:?}");
    assert_eq!(summary[5].1, "stored 4");
    assert!(summary[6].1.contains("reward_f32le") && summary[6].1.contains("15 bytes"), "{summary:?}");
    assert_eq!(t.size(), 8);
    let m = &t.actors()["m"];
    assert_eq!((m.batches, m.rejected_batches), (2, 5));
    assert_eq!(ingest.stats().rejected_batches, 5);
    ingest.stop();
}

#[test]
fn oversized_batch_is_refused_by_the_writer_with_the_limit_in_the_message() {
    let _g = serial();
    let (t, c) = (table(), cfg("oversized"));
    let ingest = ShmIngest::spawn(Arc::clone(&t), c.clone()).unwrap();
    let small = ShmConfig { max_payload_bytes: 8192, initial_payload_bytes: 8192, ..c.clone() };
    let mut w = ShmWriter::connect(&small, "o").unwrap();
    let e = w.send(&synthetic_batch("o", 1, 100, OBS)).unwrap_err();
    assert!(matches!(&e, ShmError::BadRequest(m) if m.contains("max_payload_bytes = 8192")), "{e}");
    assert_eq!(w.unacked(), 0);
    w.send(&synthetic_batch("o", 1, 10, OBS)).unwrap();
    assert_eq!(w.wait_acks(in_secs(20)).unwrap().len(), 1);
    ingest.stop();
}

#[test]
fn second_writer_for_an_actor_is_refused_until_the_first_disconnects() {
    let _g = serial();
    let (t, c) = (table(), cfg("owner"));
    let ingest = ShmIngest::spawn(Arc::clone(&t), c.clone()).unwrap();
    let mut first = ShmWriter::connect(&c, "x").unwrap();
    first.send(&synthetic_batch("x", 1, 8, OBS)).unwrap();
    first.wait_acks(in_secs(20)).unwrap();
    let mut second = ShmWriter::connect(&c, "x").unwrap();
    second.send(&synthetic_batch("x", 2, 8, OBS)).unwrap();
    let e = second.wait_acks(in_secs(20)).unwrap_err();
    assert!(matches!(&e, ShmError::BadRequest(m) if m.contains("another connected ShmWriter")), "{e}");
    assert_eq!(second.unacked(), 1);
    assert_eq!(ingest.stats().aborted_batches, 1);
    drop(first);
    second.reconnect().unwrap();
    assert_eq!(stored(&second.wait_acks(in_secs(20)).unwrap()), [(2, false)]);
    assert_eq!(t.actors()["x"].batches, 2);
    ingest.stop();
}

/// iceoryx2 routes an answer by the server's connection slot, channel and request id, all of
/// which a killed writer's successor can reuse (and both number their batches from 1): the
/// ingest's late answer to the dead writer's batch 1 could reach the new writer's batch 1. A
/// writer takes only answers that echo its connection's nonce; another one's "stored" breaks
/// the connection, and reconnecting resends the batch.
#[test]
fn an_answer_addressed_to_another_writer_connection_is_refused_and_the_batch_resent() {
    use iceoryx2::prelude::*;
    use mapless_net::shm::{WireAck, rr_builder};
    use mapless_proto::v1::InsertAck;
    let _g = serial();
    let (t, c) = (table(), cfg("foreign"));
    // A stand-in server with the ingest's service settings answers batch 1 with a "stored"
    // addressed to another connection.
    let node = NodeBuilder::new().config(&c.iceoryx2_config()).create::<ipc::Service>().unwrap();
    let name = ServiceName::new(&c.service_name()).unwrap();
    let service = rr_builder(&node, &name)
        .enable_safe_overflow_for_requests(false)
        .max_active_requests_per_client(c.max_in_flight)
        .max_servers(1)
        .max_clients(c.max_writers)
        .max_nodes(c.max_writers + 8)
        .open_or_create()
        .unwrap();
    let server = service.server_builder().create().unwrap();
    let mut w = ShmWriter::connect(&c, "f").unwrap();
    w.send(&synthetic_batch("f", 1, 10, OBS)).unwrap();
    let deadline = in_secs(20);
    let request = loop {
        if let Some(r) = server.receive().unwrap() {
            break r;
        }
        assert!(Instant::now() < deadline, "the stand-in server never received batch 1");
        std::thread::sleep(Duration::from_millis(1));
    };
    let header = *request.user_header();
    assert_eq!(header.sequence(), 1);
    assert_ne!(header.writer(), 0, "a writer's header carries its connection's nonce");
    let ack = InsertAck { actor_id: "f".into(), sequence: 1, accepted_rows: 10, duplicate: false, table_size: 10 };
    request.send_copy(WireAck::stored(&ack).for_writer(header.writer() ^ 1)).unwrap();
    let e = loop {
        match w.poll_acks() {
            Ok(acks) => assert!(acks.is_empty(), "took another connection's answer: {acks:?}"),
            Err(e) => break e,
        }
        assert!(Instant::now() < deadline, "the writer never noticed the foreign answer");
        std::thread::sleep(Duration::from_millis(1));
    };
    assert!(matches!(&e, ShmError::Closed(m) if m.contains("addressed to another shm writer connection")), "{e}");
    assert_eq!(w.unacked(), 1, "batch 1 stays in the window");
    drop((request, server, service, node));
    // The real ingest gets it on the resend, once.
    let ingest = ShmIngest::spawn(Arc::clone(&t), c.clone()).unwrap();
    w.reconnect().unwrap();
    assert_eq!(stored(&w.wait_acks(in_secs(20)).unwrap()), [(1, false)]);
    assert_eq!((t.size(), t.actors()["f"].batches), (10, 1));
    ingest.stop();
}

#[test]
fn insert_blocked_by_the_rate_limiter_delays_the_ack_without_dropping_it() {
    let _g = serial();
    let t = rate_limited_table();
    let c = cfg("ratelimit");
    let ingest = ShmIngest::spawn(Arc::clone(&t), c.clone()).unwrap();
    let mut w = ShmWriter::connect(&c, "rl").unwrap();
    for seq in 1..=3 {
        w.send(&synthetic_batch("rl", seq, 100, OBS)).unwrap();
    }
    // Batch 3 waits for a sample that never comes: 3 s leaves the first two time to be stored
    // (and the third to stall) on a loaded machine.
    let e = w.wait_acks(Instant::now() + Duration::from_secs(3)).unwrap_err();
    assert!(matches!(e, ShmError::DeadlineExceeded { .. }), "{e}");
    assert_eq!(stored(&w.poll_acks().unwrap()), [(1, false), (2, false)]);
    assert!(ingest.stats().insert_stalls >= 2, "{:?}", ingest.stats());
    // Other writers are not wedged either: their batches queue behind the limiter too, but
    // a dead one would still be cleaned (the janitor does not wait for inserts).
    t.sample(100, None, Some(in_secs(5))).unwrap();
    assert_eq!(stored(&w.wait_acks(in_secs(20)).unwrap()), [(3, false)]);
    assert_eq!(t.actors()["rl"].batches, 3);
    ingest.stop();
}

/// A batch handed to the actor's client while the writer's window is full (the replay's rate
/// limiter holds inserts back) and the actor is told to stop is not lost: `send` returns
/// `Stopped` with the batch still held, and `flush` delivers it once inserts flow again, so
/// the rows the actor reports handing over are exactly the rows stored under its id. (Before,
/// the shared-memory client counted that batch and dropped it: a clean-clone compose drill
/// once found an `actor-shm` replica one batch short after a stop.)
#[test]
fn a_batch_handed_over_as_the_actor_stops_is_held_and_flushed_not_lost() {
    let _g = serial();
    let t = rate_limited_table();
    let c = ShmConfig { max_in_flight: 1, send_timeout_ms: 200, ..cfg("stopheld") };
    let ingest = ShmIngest::spawn(Arc::clone(&t), c.clone()).unwrap();
    let (running, stopping) = (AtomicBool::new(false), AtomicBool::new(true));
    let mut client = ShmInsertClient::connect(c, "held", &running).unwrap();
    for seq in 1..=3 {
        client.send(synthetic_batch("held", seq, 100, OBS), &running).unwrap();
    }
    // Batch 3 fills the one-batch window, stalled at the limiter; batch 4 cannot be taken.
    let e = client.send(synthetic_batch("held", 4, 100, OBS), &stopping).unwrap_err();
    assert!(e.to_string().contains("take a batch"), "{e}");
    assert_eq!(client.held(), 1);
    assert_eq!(t.actors()["held"].batches, 2);
    // Sampling lets inserts through again; the flush hands batch 4 over and waits for both.
    let sampler = {
        let t = Arc::clone(&t);
        std::thread::spawn(move || {
            for _ in 0..3 {
                t.sample(100, None, Some(in_secs(10))).unwrap();
                std::thread::sleep(Duration::from_millis(100));
            }
        })
    };
    assert!(client.flush(in_secs(20)), "{:?}", client.stats());
    sampler.join().unwrap();
    assert_eq!(client.held(), 0);
    let s = client.stats();
    assert_eq!((s.batches, s.rows, s.acked, s.duplicates), (4, 400, 4, 0), "{s:?}");
    assert_eq!((t.actors()["held"].batches, t.actors()["held"].rows), (4, 400));
    ingest.stop();
}
