//! A writer process for the shared-memory ingest: sends synthetic batches and waits for
//! every ack. Used by `tests/shm.rs` (killed with SIGKILL mid-stream) and by
//! `shm_throughput --mode process`.
//!
//! ```text
//! shm_writer <prefix> <actor id> <rows per batch> <batches> <obs dim>
//!            [--first-seq N] [--pace-us N] [--progress] [--domain D]
//! ```
//!
//! With `--progress` it prints `acked <sequence>` per ack; at the end always
//! `done <batches stored> <rows stored> <duplicates> <rejected> <seconds>`.

mod shm_common;

use std::io::Write;
use std::time::Duration;

use mapless_net::shm::{Ack, ShmConfig};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let usage = "usage: shm_writer <prefix> <actor id> <rows> <batches> <obs dim> [--first-seq N] [--pace-us N] [--progress] [--domain D]";
    if args.len() < 6 {
        eprintln!("{usage}");
        std::process::exit(2);
    }
    let num = |s: &str| -> u64 {
        s.parse().unwrap_or_else(|_| {
            eprintln!("not a number: {s}\n{usage}");
            std::process::exit(2)
        })
    };
    let (prefix, actor) = (&args[1], &args[2]);
    let (rows, batches, obs_dim) = (num(&args[3]) as usize, num(&args[4]), num(&args[5]) as usize);
    let (mut first_seq, mut pace_us, mut progress, mut domain) = (1, 0, false, String::new());
    let mut rest = args[6..].iter();
    while let Some(a) = rest.next() {
        match a.as_str() {
            "--first-seq" => first_seq = num(rest.next().map_or("", |s| s.as_str())),
            "--pace-us" => pace_us = num(rest.next().map_or("", |s| s.as_str())),
            "--progress" => progress = true,
            "--domain" => domain = rest.next().cloned().unwrap_or_default(),
            other => {
                eprintln!("unknown argument {other}\n{usage}");
                std::process::exit(2);
            }
        }
    }
    let cfg = ShmConfig { prefix: prefix.clone(), domain, ..ShmConfig::default() };
    let stdout = std::io::stdout();
    let plan = shm_common::Plan { obs_dim, first_seq, pace: Duration::from_micros(pace_us), patience: Duration::from_secs(30), ..shm_common::Plan::new(rows, batches) };
    let report = shm_common::run_writer(&cfg, actor, &plan, |a: &Ack| {
        if progress {
            let mut out = stdout.lock();
            let _ = writeln!(out, "acked {}", a.sequence());
            let _ = out.flush();
        }
    });
    match report {
        Ok(r) => {
            println!("done {} {} {} {} {:.3}", r.stored, r.rows, r.duplicates, r.rejected, r.elapsed.as_secs_f64());
        }
        Err(e) => {
            eprintln!("shm_writer {actor}: {e}");
            std::process::exit(1);
        }
    }
}
