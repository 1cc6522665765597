//! Rows per second through the shared-memory ingest into a 1,000,000-row table without
//! rate limiting, with writers as threads or as processes (`shm_writer`), plus the cost of
//! each server-side step measured alone (decode, insert) for the profile.
//!
//! ```text
//! cargo build --release -p mapless-replay --examples
//! target/release/examples/shm_throughput [--writers 4] [--mode thread|process]
//!     [--rows 256] [--batches 4000] [--obs-dim 17] [--no-alone]
//! ```

mod shm_common;

use std::process::{Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use mapless_net::shm::ShmConfig;
use mapless_proto::v1::TransitionBatch;
use mapless_replay::shm::ShmIngest;
use mapless_replay::{RateLimiterConfig, Table, TableConfig};
use prost::Message;

fn table(obs_dim: usize) -> Table {
    let cfg =
        TableConfig { capacity: 1_000_000, obs_dim, rate_limiter: RateLimiterConfig { min_size_to_sample: 1, samples_per_insert: None, ..RateLimiterConfig::default() }, ..TableConfig::default() };
    Table::new(cfg, 7).expect("table config")
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let opt = |name: &str, default: u64| -> u64 { args.iter().position(|a| a == name).and_then(|i| args.get(i + 1)).and_then(|v| v.parse().ok()).unwrap_or(default) };
    let writers = opt("--writers", 4) as usize;
    let rows = opt("--rows", 256) as usize;
    let batches = opt("--batches", 4000);
    let obs_dim = opt("--obs-dim", 17) as usize;
    let mode = args.iter().position(|a| a == "--mode").and_then(|i| args.get(i + 1)).map_or("thread", |s| s.as_str()).to_string();

    // The server-side steps alone, one thread, same batch shape (--no-alone: skip, e.g. to
    // profile only the ingest).
    if !args.iter().any(|a| a == "--no-alone") {
        let n = 2000u64;
        let batch = shm_common::synthetic_batch("baseline", 1, rows, obs_dim);
        let bytes = batch.encode_to_vec();
        let t = Instant::now();
        let mut sink = 0usize;
        for _ in 0..n {
            sink += TransitionBatch::decode(bytes.as_slice()).expect("decode").obs.len();
        }
        let decode = t.elapsed().as_secs_f64();
        let tbl = table(obs_dim);
        let mut b = batch.clone();
        let t = Instant::now();
        for seq in 1..=n {
            b.sequence = seq;
            tbl.insert(&b, None).expect("insert");
        }
        let insert = t.elapsed().as_secs_f64();
        let t = Instant::now();
        for _ in 0..n {
            sink += b.encode_to_vec().len();
        }
        let encode = t.elapsed().as_secs_f64();
        let per = |s: f64| (n as f64 * rows as f64) / s;
        println!(
            "alone, one thread: decode {:.2} M rows/s, Table::insert {:.2} M rows/s, encode {:.2} M rows/s ({} bytes per {rows}-row batch) [{sink}]",
            per(decode) / 1e6,
            per(insert) / 1e6,
            per(encode) / 1e6,
            bytes.len()
        );
    }

    let tbl = Arc::new(table(obs_dim));
    let cfg = ShmConfig { prefix: format!("mapless-bench/{}", std::process::id()), ..ShmConfig::default() };
    let ingest = ShmIngest::spawn(Arc::clone(&tbl), cfg.clone()).expect("ingest");
    let start = Instant::now();
    match mode.as_str() {
        "process" => {
            let exe = std::env::current_exe().expect("current exe").with_file_name("shm_writer");
            let children: Vec<_> = (0..writers)
                .map(|w| {
                    Command::new(&exe)
                        .args([&cfg.prefix, &format!("bench-{w}"), &rows.to_string(), &batches.to_string(), &obs_dim.to_string()])
                        .stdout(Stdio::piped())
                        .spawn()
                        .unwrap_or_else(|e| panic!("cannot start {} (build the examples first): {e}", exe.display()))
                })
                .collect();
            for c in children {
                let out = c.wait_with_output().expect("writer");
                assert!(out.status.success(), "writer failed: {:?}", out.status);
                print!("  writer: {}", String::from_utf8_lossy(&out.stdout));
            }
        }
        _ => {
            let handles: Vec<_> = (0..writers)
                .map(|w| {
                    let cfg = cfg.clone();
                    std::thread::spawn(move || {
                        let plan = shm_common::Plan { obs_dim, patience: Duration::from_secs(30), ..shm_common::Plan::new(rows, batches) };
                        shm_common::run_writer(&cfg, &format!("bench-{w}"), &plan, |_| {}).expect("writer")
                    })
                })
                .collect();
            for h in handles {
                let r = h.join().expect("writer thread");
                println!("  writer: {} batches, {} rows in {:.3} s", r.stored, r.rows, r.elapsed.as_secs_f64());
            }
        }
    }
    let elapsed = start.elapsed().as_secs_f64();
    let stats = ingest.stats();
    ingest.stop();
    let expected = writers as u64 * batches * rows as u64;
    assert_eq!(stats.rows_stored, expected, "every row stored exactly once");
    println!(
        "shm ingest, {writers} writer {mode}(s), {rows}-row batches, obs_dim {obs_dim}: {} rows in {elapsed:.3} s = {:.0} rows/s ({:.0} batches/s); table size {}, stalls {}",
        stats.rows_stored,
        stats.rows_stored as f64 / elapsed,
        stats.batches_stored as f64 / elapsed,
        tbl.size(),
        stats.insert_stalls
    );
}
