//! A replay process that only serves the shared-memory ingest, until killed. Used by
//! `tests/shm.rs` to kill a server with SIGKILL and check that a fresh one starts cleanly.
//!
//! ```text
//! shm_ingest <prefix> <obs dim> [<iceoryx2 domain>]
//! ```
//!
//! Prints `ready` once writers can connect, then `size <rows>` every 100 ms.

use std::sync::Arc;
use std::time::Duration;

use mapless_net::shm::ShmConfig;
use mapless_replay::shm::ShmIngest;
use mapless_replay::{RateLimiterConfig, Table, TableConfig};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if !(3..=4).contains(&args.len()) {
        eprintln!("usage: shm_ingest <prefix> <obs dim> [<iceoryx2 domain>]");
        std::process::exit(2);
    }
    let obs_dim = args[2].parse().unwrap_or(17);
    let table_cfg =
        TableConfig { capacity: 100_000, obs_dim, rate_limiter: RateLimiterConfig { min_size_to_sample: 1, samples_per_insert: None, ..RateLimiterConfig::default() }, ..TableConfig::default() };
    let table = Arc::new(Table::new(table_cfg, 1).expect("table config"));
    let cfg = ShmConfig { prefix: args[1].clone(), domain: args.get(3).cloned().unwrap_or_default(), ..ShmConfig::default() };
    let _ingest = match ShmIngest::spawn(Arc::clone(&table), cfg) {
        Ok(i) => i,
        Err(e) => {
            eprintln!("shm_ingest: {e}");
            std::process::exit(1);
        }
    };
    println!("ready");
    loop {
        std::thread::sleep(Duration::from_millis(100));
        println!("size {}", table.size());
    }
}
