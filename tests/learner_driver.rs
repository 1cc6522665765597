//! The learner loop end to end in one process: a replay table feeds the driver, which updates,
//! publishes versioned weights a pure-Rust actor can load, checkpoints, and resumes with its
//! weights version intact.

mod common;
use common::in_process::InProcess;

use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use mapless_actor::{ActMode, Policy};
use mapless_learner::algo::Agent;
use mapless_learner::config::{AlgorithmKind, LearnerConfig};
use mapless_learner::driver::{Driver, DriverConfig};
use mapless_learner::weights::WeightsPublisher;
use mapless_proto::{Transition, TransitionBatchBuilder};
use mapless_replay::config::{RateLimiterConfig, SamplerConfig, TableConfig};
use mapless_replay::table::Table;
use rand::{Rng, SeedableRng};

const OBS: usize = 5;
const ACT: usize = 2;

fn config(algorithm: AlgorithmKind) -> LearnerConfig {
    LearnerConfig { algorithm, hidden_width: 32, batch_size: 16, seed: 11, ..LearnerConfig::default() }
}

/// A table holding 400 random transitions (some terminal, some truncated).
fn table() -> Arc<Table> {
    let cfg = TableConfig {
        capacity: 1000,
        obs_dim: OBS,
        act_dim: ACT,
        sampler: SamplerConfig::Uniform,
        rate_limiter: RateLimiterConfig { min_size_to_sample: 1, samples_per_insert: None, error_buffer: 0.0 },
        ..TableConfig::default()
    };
    let table = Table::new(cfg, 5).unwrap();
    let mut rng = rand_pcg::Pcg64::seed_from_u64(3);
    for seq in 1..=4u64 {
        let mut b = TransitionBatchBuilder::new(OBS, ACT);
        for i in 0..100 {
            let obs: Vec<f32> = (0..OBS).map(|_| rng.random_range(-1.0..1.0)).collect();
            let next: Vec<f32> = (0..OBS).map(|_| rng.random_range(-1.0..1.0)).collect();
            let action: Vec<f32> = (0..ACT).map(|_| rng.random_range(-1.0..1.0)).collect();
            b.push(Transition {
                obs: &obs,
                action: &action,
                reward: rng.random_range(-1.0..1.0),
                next_obs: &next,
                terminal: i % 17 == 16,
                truncated: i % 23 == 22,
                episode_id: seq,
                step: i,
                policy_version: 0,
            })
            .unwrap();
        }
        table.insert(&b.finish("actor-test", seq), None).unwrap();
    }
    Arc::new(table)
}

#[test]
fn driver_publishes_every_k_updates_checkpoints_and_a_resumed_driver_continues_the_version_count() {
    let dir = tempfile::tempdir().unwrap();
    let table = table();
    let publisher = WeightsPublisher::new();
    let cfg = DriverConfig { publish_every: 10, metrics_every: 5, ..DriverConfig::default() };
    let agent = Agent::new(&config(AlgorithmKind::Sac), OBS, ACT).unwrap();
    let source = Box::new(InProcess::new(Arc::clone(&table), 16).unwrap());
    let mut driver = Driver::new(agent, source, publisher.clone(), cfg.clone(), 0).unwrap().with_checkpoints(dir.path().join("checkpoints")).with_tensorboard(&dir.path().join("tb")).unwrap();
    let report = driver.run(&AtomicBool::new(false), Some(25)).unwrap();
    // Version 1 before the first update (actors need a policy), then after updates 10 and 20,
    // and the final policy after update 25.
    assert_eq!((report.updates, report.total_updates, report.weights_version), (25, 25, 4));
    assert_eq!(publisher.latest_version(), 4);
    let latest = publisher.latest().unwrap();
    assert_eq!(latest.metadata.get("learner_step").map(String::as_str), Some("25"));
    let scalars = mapless_learner::tensorboard::read_scalars(&std::fs::read_dir(dir.path().join("tb")).unwrap().next().unwrap().unwrap().path()).unwrap();
    assert!(scalars.iter().any(|s| s.tag == "losses/critic" && s.step == 25), "critic loss logged at update 25");
    let checkpoint = report.checkpoint.expect("run ends with a checkpoint");

    // A new learner process: same checkpoint, a fresh publisher (subscribers reconnect with
    // min_version = 5), and the count goes on from 4.
    let publisher = WeightsPublisher::new();
    let source = Box::new(InProcess::new(Arc::clone(&table), 16).unwrap());
    let mut resumed = Driver::resume(&checkpoint, None, source, publisher.clone(), cfg).unwrap();
    assert_eq!((resumed.weights_version(), resumed.agent().updates()), (4, 25));
    let report = resumed.run(&AtomicBool::new(false), Some(5)).unwrap();
    assert_eq!((report.total_updates, report.weights_version), (30, 5));
    assert_eq!(publisher.latest_version(), 5);
}

#[test]
fn pure_rust_actor_matches_the_tch_policy_on_published_weights() {
    let mut rng = rand_pcg::Pcg64::seed_from_u64(9);
    let obs: Vec<f32> = (0..64 * OBS).map(|_| rng.random_range(-3.0..3.0)).collect();
    for kind in [AlgorithmKind::Ddpg, AlgorithmKind::Td3, AlgorithmKind::Sac] {
        let table = table();
        let agent = Agent::new(&config(kind), OBS, ACT).unwrap();
        let source = Box::new(InProcess::new(table, 16).unwrap());
        let mut driver = Driver::new(agent, source, WeightsPublisher::new(), DriverConfig::default(), 0).unwrap();
        // Trained a little, so the weights are not just the initialisation.
        driver.run(&AtomicBool::new(false), Some(20)).unwrap();
        let snapshot = driver.snapshot().unwrap();
        let mut policy = Policy::from_snapshot(&snapshot).unwrap();
        let mut ours = vec![0.0f32; 64 * ACT];
        policy.act(&obs, ActMode::Deterministic, &mut rng, &mut ours).unwrap();
        let theirs = driver.agent_mut().act_slice(&obs, false).unwrap();
        let worst = ours.iter().zip(&theirs).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
        assert!(worst <= 1e-5, "{kind:?}: largest difference {worst}");
        assert!(theirs.iter().any(|a| a.abs() > 1e-3), "{kind:?}: actions are not all zero");
    }
}

/// The names in `dir`, sorted.
fn names(dir: &std::path::Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().file_name().into_string().unwrap()).collect();
    v.sort();
    v
}

/// The learner's checkpoints on a full disk, for real (a 1 MiB tmpfs this test mounts and
/// fills): a periodic checkpoint that cannot be written is counted and training goes on; the
/// previous checkpoint stays whole and named by LATEST, and no temporary directory is left
/// holding space; once space returns, the next checkpoint is written without a restart.
#[test]
fn a_full_disk_costs_only_the_checkpoints_it_refuses_and_the_next_one_after_space_returns_is_written() {
    let disk = common::tmpfs::Tmpfs::mount("1m");
    let root = disk.path().join("checkpoints");
    let cfg = DriverConfig { publish_every: 10, checkpoint_every: 5, checkpoint_keep: 2, ..DriverConfig::default() };
    let agent = Agent::new(&config(AlgorithmKind::Sac), OBS, ACT).unwrap();
    let source = Box::new(InProcess::new(table(), 16).unwrap());
    let mut driver = Driver::new(agent, source, WeightsPublisher::new(), cfg, 0).unwrap().with_checkpoints(&root);
    for _ in 0..10 {
        driver.step().unwrap();
    }
    assert_eq!(names(&root), ["LATEST", "ckpt-000000000005", "ckpt-000000000010"]);

    let filler = disk.path().join("filler");
    assert!(common::tmpfs::fill(&filler) > 0, "the tmpfs had room for the filler");
    for _ in 0..10 {
        driver.step().expect("a full disk does not stop training");
    }
    assert_eq!((driver.agent().updates(), driver.checkpoint_failures()), (20, 2), "the saves at 15 and 20 were refused, and counted");
    let e = driver.checkpoint().expect_err("an explicit checkpoint on a full disk is an error");
    assert!(e.to_string().contains("No space left on device"), "{e}");
    assert_eq!(names(&root), ["LATEST", "ckpt-000000000005", "ckpt-000000000010"], "nothing half-written is left behind");
    let (kept, _) = mapless_learner::checkpoint::load(&root, None).expect("the newest checkpoint is still whole");
    assert_eq!(kept.updates(), 10);

    std::fs::remove_file(&filler).unwrap();
    for _ in 0..5 {
        driver.step().unwrap();
    }
    assert_eq!(driver.checkpoint_failures(), 2);
    assert_eq!(names(&root), ["LATEST", "ckpt-000000000010", "ckpt-000000000025"]);
    let (newest, _) = mapless_learner::checkpoint::load(&root, None).unwrap();
    assert_eq!(newest.updates(), 25);
}
