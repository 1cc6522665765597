//! Checkpoints: exact round trips, the deployable policy file, every way loading can fail,
//! and a mid-run resume of the Pendulum loop that ends bit-identical to an uninterrupted run.

mod common;

use std::collections::HashMap;
use std::fs;
use std::path::Path;

use common::{Harness, LoopState, pendulum_config};
use mapless_learner::LearnerError;
use mapless_learner::algo::Agent;
use mapless_learner::batch::Minibatch;
use mapless_learner::checkpoint::{self, DEFAULT_KEEP, LATEST, MANIFEST, POLICY, TENSORS};
use mapless_learner::config::{AlgorithmKind, LearnerConfig};
use rand::SeedableRng;

const ALL: [AlgorithmKind; 3] = [AlgorithmKind::Ddpg, AlgorithmKind::Td3, AlgorithmKind::Sac];

fn cfg(algorithm: AlgorithmKind) -> LearnerConfig {
    LearnerConfig { algorithm, hidden_width: 16, seed: 11, ..LearnerConfig::default() }
}

fn batches(n: usize) -> Vec<Minibatch> {
    let mut rng = rand_pcg::Pcg64::seed_from_u64(4);
    (0..n).map(|_| Minibatch::random(32, 5, 2, &mut rng, tch::Device::Cpu).unwrap()).collect()
}

fn state(agent: &Agent) -> HashMap<String, Vec<f32>> {
    agent.state_tensors().into_iter().map(|(n, t)| (n, Vec::<f32>::try_from(&t.reshape([-1])).unwrap())).collect()
}

fn trained(algorithm: AlgorithmKind, updates: usize) -> Agent {
    let mut agent = Agent::new(&cfg(algorithm), 5, 2).unwrap();
    for b in batches(updates) {
        agent.update(&b).unwrap();
    }
    agent
}

#[test]
fn a_loaded_checkpoint_continues_exactly_like_the_original() {
    for algorithm in ALL {
        let dir = tempfile::tempdir().unwrap();
        let mut original = trained(algorithm, 3);
        // Exploration state is part of it too.
        original.act_slice(&[0.1; 5], true).unwrap();
        let extra = serde_json::json!({"env": "state", "step": 42});
        let path = checkpoint::save(dir.path(), &original, &extra, DEFAULT_KEEP).unwrap();
        assert!(path.ends_with("ckpt-000000000003"));

        let (mut restored, got_extra) = checkpoint::load(dir.path(), None).unwrap();
        assert_eq!(got_extra, extra);
        assert_eq!(restored.updates(), 3);
        assert_eq!(restored.algorithm(), original.algorithm());
        assert_eq!(state(&restored), state(&original), "{algorithm:?}");

        let more = batches(6);
        for b in &more[3..] {
            let a = original.update(b).unwrap();
            let r = restored.update(b).unwrap();
            assert_eq!(a, r, "{algorithm:?}: stats differ after resume");
        }
        assert_eq!(state(&restored), state(&original), "{algorithm:?} after 3 more updates");
        assert_eq!(restored.act_slice(&[0.2; 5], true).unwrap(), original.act_slice(&[0.2; 5], true).unwrap(), "{algorithm:?}: exploration noise resumes too");

        // restore() into an agent built from the same config does the same.
        let mut fresh = Agent::new(&cfg(algorithm), 5, 2).unwrap();
        checkpoint::restore(&mut fresh, &path).unwrap();
        assert_eq!(fresh.updates(), 3);
    }
}

#[test]
fn the_policy_file_holds_the_actor_alone_with_its_metadata() {
    let dir = tempfile::tempdir().unwrap();
    let agent = trained(AlgorithmKind::Sac, 2);
    let path = checkpoint::save(dir.path(), &agent, &serde_json::Value::Null, 1).unwrap();
    let exported = dir.path().join("exported.safetensors");
    checkpoint::export_policy(&agent, &exported).unwrap();
    for file in [path.join(POLICY), exported] {
        let p = checkpoint::read_policy(&file).unwrap();
        let m = &p.metadata;
        assert_eq!(m["algorithm"], "sac");
        assert_eq!((m["obs_dim"].as_str(), m["act_dim"].as_str(), m["version"].as_str()), ("5", "2", "2"));
        assert_eq!((m["sac.log_std_min"].as_str(), m["sac.log_std_max"].as_str()), ("-20", "2"));
        assert_eq!(m["format"], "mapless-policy");
        let names: Vec<&str> = p.tensors.iter().map(|t| t.0.as_str()).collect();
        assert_eq!(names, ["actor.l0.bias", "actor.l0.weight", "actor.l1.bias", "actor.l1.weight", "actor.out.bias", "actor.out.weight"]);
        let want: HashMap<String, Vec<f32>> = agent.policy_tensors().into_iter().map(|(n, t)| (n, Vec::<f32>::try_from(&t.reshape([-1])).unwrap())).collect();
        for (name, shape, values) in &p.tensors {
            assert_eq!(values, &want[name], "{name}");
            if name == "actor.out.weight" {
                assert_eq!(shape, &vec![4, 16], "SAC head: 2·act_dim rows");
            }
        }
    }
}

/// `policy_average`: the policy published (and exported) is θ̄ after n updates, θ̄ ← θ̄ +
/// max(τ̄, 1/n)(θ − θ̄) over the trained actors θ, on both update paths and for every
/// algorithm; the trained actor is unchanged by it; a checkpoint keeps θ̄ exactly; and τ̄
/// outside (0, 1] is refused.
#[test]
fn a_running_average_of_the_actor_is_what_is_published_and_checkpointed() {
    const TAU: f64 = 0.3;
    let actor = |agent: &Agent| -> Vec<(String, Vec<f64>)> {
        let mut s: Vec<_> = state(agent).into_iter().filter(|(n, _)| n.starts_with("actor.")).map(|(n, v)| (n, v.into_iter().map(f64::from).collect())).collect();
        s.sort_by(|a, b| a.0.cmp(&b.0));
        s
    };
    let published = |agent: &Agent| -> HashMap<String, Vec<f32>> { agent.policy_tensors().into_iter().map(|(n, t)| (n, Vec::<f32>::try_from(&t.reshape([-1])).unwrap())).collect() };
    for algorithm in ALL {
        for fused in [true, false] {
            let c = LearnerConfig { policy_average: Some(TAU), fused_update: fused, ..cfg(algorithm) };
            let mut agent = Agent::new(&c, 5, 2).unwrap();
            let mut plain = Agent::new(&LearnerConfig { policy_average: None, ..c.clone() }, 5, 2).unwrap();
            let mut want: Vec<(String, Vec<f64>)> = Vec::new();
            for (n, b) in batches(6).iter().enumerate() {
                agent.update(b).unwrap();
                plain.update(b).unwrap();
                let now = actor(&agent);
                assert_eq!(now, actor(&plain), "{algorithm:?}: averaging changed training");
                let step = TAU.max(1.0 / (n + 1) as f64);
                want =
                    if want.is_empty() { now } else { want.into_iter().zip(now).map(|((name, avg), (_, theta))| (name, avg.iter().zip(&theta).map(|(a, t)| a + step * (t - a)).collect())).collect() };
            }
            let got = published(&agent);
            assert_eq!(got.len(), want.len());
            for (name, values) in &want {
                let g = &got[name];
                let worst = g.iter().zip(values).map(|(g, w)| (f64::from(*g) - w).abs()).fold(0.0, f64::max);
                assert!(worst < 1e-6, "{algorithm:?} fused {fused}: {name} is {worst} from the average");
            }
            assert_ne!(got, published(&plain), "{algorithm:?}: the average is the last actor");

            let dir = tempfile::tempdir().unwrap();
            checkpoint::save(dir.path(), &agent, &serde_json::Value::Null, 1).unwrap();
            let (mut restored, _) = checkpoint::load(dir.path(), None).unwrap();
            assert_eq!(state(&restored), state(&agent));
            assert_eq!(published(&restored), got);
            let next = &batches(7)[6];
            agent.update(next).unwrap();
            restored.update(next).unwrap();
            assert_eq!(published(&restored), published(&agent), "{algorithm:?}: resumed average");
            let exported = dir.path().join("exported.safetensors");
            checkpoint::export_policy(&agent, &exported).unwrap();
            let file: HashMap<String, Vec<f32>> = checkpoint::read_policy(&exported).unwrap().tensors.into_iter().map(|(n, _, v)| (n, v)).collect();
            assert_eq!(file, published(&agent));
        }
    }
    for bad in [0.0, -0.1, 1.5, f64::NAN] {
        let c = LearnerConfig { policy_average: Some(bad), ..cfg(AlgorithmKind::Sac) };
        let e = Agent::new(&c, 5, 2).unwrap_err();
        assert!(e.to_string().contains("policy_average"), "{bad}: {e}");
    }
}

fn saved(algorithm: AlgorithmKind) -> (tempfile::TempDir, std::path::PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let path = checkpoint::save(dir.path(), &trained(algorithm, 1), &serde_json::Value::Null, 1).unwrap();
    (dir, path)
}

fn modify(path: &Path, f: impl FnOnce(&mut Vec<u8>)) {
    let mut bytes = fs::read(path).unwrap();
    f(&mut bytes);
    fs::write(path, bytes).unwrap();
}

#[test]
fn a_flipped_byte_is_a_checksum_error() {
    let (_d, path) = saved(AlgorithmKind::Sac);
    modify(&path.join(TENSORS), |b| {
        let i = b.len() / 2;
        b[i] ^= 0x40;
    });
    let e = checkpoint::load(&path, None).unwrap_err();
    assert!(matches!(e, LearnerError::CheckpointCorrupt { .. }), "{e}");
    assert!(e.to_string().contains("checksum mismatch"), "{e}");
}

#[test]
fn a_truncated_file_is_reported_as_truncated() {
    let (_d, path) = saved(AlgorithmKind::Td3);
    modify(&path.join(TENSORS), |b| b.truncate(b.len() - 100));
    let e = checkpoint::load(&path, None).unwrap_err();
    assert!(matches!(e, LearnerError::CheckpointCorrupt { .. }), "{e}");
    assert!(e.to_string().contains("truncated"), "{e}");
    // An unparsable manifest (torn) is corrupt too, not a panic.
    modify(&path.join(MANIFEST), |b| b.truncate(b.len() / 2));
    let e = checkpoint::load(&path, None).unwrap_err();
    assert!(matches!(e, LearnerError::CheckpointCorrupt { .. }), "{e}");
}

/// The manifest carries no checksum of its own: damaged sizes in it (or a forged state) must be
/// refused before an agent of that size is built, not become an allocation libtorch cannot make.
#[test]
fn sizes_no_stored_tensor_could_fill_are_refused_before_building_the_agent() {
    let (_d, path) = saved(AlgorithmKind::Ddpg);
    let manifest = path.join(MANIFEST);
    let good = fs::read_to_string(&manifest).unwrap();
    assert!(good.contains("\"obs_dim\": 5"), "{good}");
    for forged in ["\"obs_dim\": 500000000000", "\"obs_dim\": 18446744073709551615"] {
        fs::write(&manifest, good.replace("\"obs_dim\": 5", forged)).unwrap();
        let e = checkpoint::load(&path, None).unwrap_err();
        assert!(matches!(e, LearnerError::CheckpointCorrupt { .. }), "{e}");
        assert!(e.to_string().contains("parameters"), "{e}");
    }
}

#[test]
fn other_algorithms_dimensions_and_format_versions_are_mismatches() {
    let (_d, path) = saved(AlgorithmKind::Sac);
    let mut td3 = Agent::new(&cfg(AlgorithmKind::Td3), 5, 2).unwrap();
    let e = checkpoint::restore(&mut td3, &path).unwrap_err();
    assert!(matches!(&e, LearnerError::CheckpointMismatch { what, .. } if what == "algorithm"), "{e}");
    assert!(e.to_string().contains("algorithm is sac, expected td3"), "{e}");

    let mut wide = Agent::new(&cfg(AlgorithmKind::Sac), 6, 2).unwrap();
    let e = checkpoint::restore(&mut wide, &path).unwrap_err();
    assert!(matches!(&e, LearnerError::CheckpointMismatch { what, .. } if what == "obs_dim"), "{e}");

    let mut c = cfg(AlgorithmKind::Sac);
    c.hidden_width = 32;
    let mut bigger = Agent::new(&c, 5, 2).unwrap();
    let e = checkpoint::restore(&mut bigger, &path).unwrap_err();
    assert!(matches!(&e, LearnerError::CheckpointMismatch { what, .. } if what == "hidden_width"), "{e}");

    // Same tensors, different critics: resuming would silently change what they compute.
    let mut c = cfg(AlgorithmKind::Sac);
    c.critic_layer_norm = true;
    let mut normed = Agent::new(&c, 5, 2).unwrap();
    let e = checkpoint::restore(&mut normed, &path).unwrap_err();
    assert!(matches!(&e, LearnerError::CheckpointMismatch { what, .. } if what == "critic_layer_norm"), "{e}");
    assert!(e.to_string().contains("critic_layer_norm is false, expected true"), "{e}");

    // A running average of the actor is stored only where it is kept.
    let mut c = cfg(AlgorithmKind::Sac);
    c.policy_average = Some(0.01);
    let mut averaging = Agent::new(&c, 5, 2).unwrap();
    let e = checkpoint::restore(&mut averaging, &path).unwrap_err();
    assert!(matches!(&e, LearnerError::CheckpointMismatch { what, .. } if what == "policy_average (kept)"), "{e}");

    let manifest = path.join(MANIFEST);
    let text = fs::read_to_string(&manifest).unwrap().replace("\"format_version\": 1", "\"format_version\": 2");
    fs::write(&manifest, text).unwrap();
    let e = checkpoint::load(&path, None).unwrap_err();
    assert!(matches!(&e, LearnerError::CheckpointMismatch { what, .. } if what == "format version"), "{e}");
}

#[test]
fn missing_pieces_are_errors_and_latest_always_names_a_complete_checkpoint() {
    let root = tempfile::tempdir().unwrap();
    let e = checkpoint::load(root.path(), None).unwrap_err();
    assert!(e.to_string().contains("not a checkpoint"), "{e}");

    let mut agent = trained(AlgorithmKind::Ddpg, 1);
    let first = checkpoint::save(root.path(), &agent, &serde_json::Value::Null, 2).unwrap();
    // A crash while writing the next one leaves only a temporary directory behind.
    fs::create_dir_all(root.path().join(".ckpt-000000000002.tmp")).unwrap();
    fs::write(root.path().join(".ckpt-000000000002.tmp").join(TENSORS), b"half").unwrap();
    assert_eq!(checkpoint::resolve(root.path()).unwrap(), first);
    assert_eq!(checkpoint::load(root.path(), None).unwrap().0.updates(), 1);

    for b in batches(3) {
        agent.update(&b).unwrap();
        checkpoint::save(root.path(), &agent, &serde_json::Value::Null, 2).unwrap();
    }
    let mut kept: Vec<String> = fs::read_dir(root.path()).unwrap().map(|e| e.unwrap().file_name().into_string().unwrap()).filter(|n| n.starts_with("ckpt-")).collect();
    kept.sort();
    assert_eq!(kept, ["ckpt-000000000003", "ckpt-000000000004"], "pruned to the newest 2");
    assert_eq!(fs::read_to_string(root.path().join(LATEST)).unwrap().trim(), "ckpt-000000000004");
    assert!(!root.path().join(".ckpt-000000000002.tmp").exists(), "stale temporary removed");

    // Writing over an existing directory is refused; a missing file is corrupt.
    let e = checkpoint::write_checkpoint(&root.path().join("ckpt-000000000004"), &agent, &serde_json::Value::Null).unwrap_err();
    assert!(matches!(e, LearnerError::CheckpointIo { .. }), "{e}");
    fs::remove_file(root.path().join("ckpt-000000000004").join(POLICY)).unwrap();
    let e = checkpoint::load(root.path(), None).unwrap_err();
    assert!(e.to_string().contains("missing"), "{e}");
}

// ---------------------------------------------------------------------------------------------
// Resume of the whole Pendulum loop.
// ---------------------------------------------------------------------------------------------

const TOTAL: u64 = 1_500;
const SPLIT: u64 = 750;
const LEARNING_STARTS: u64 = 500;
const SEED: u64 = 5;

/// Runs the loop to TOTAL steps. `resume_at`: stop there, checkpoint the learner (with the
/// loop state as `extra`), snapshot and close the replay table, drop everything, then reopen
/// the table from its directory (rows, and the sampler's random stream, come back from its
/// snapshot and log), load the checkpoint, and carry on.
fn run(algorithm: AlgorithmKind, resume_at: Option<u64>) -> (HashMap<String, Vec<f32>>, Vec<f64>) {
    let cfg = pendulum_config(algorithm, SEED);
    let table_dir = tempfile::tempdir().unwrap();
    let ckpt_dir = tempfile::tempdir().unwrap();
    let table = Harness::persistent_table(&cfg, table_dir.path(), SEED);
    let mut h = Harness::new(&cfg, table, SEED, LEARNING_STARTS);
    while h.s.steps < TOTAL {
        if Some(h.s.steps) == resume_at {
            // Pcg64 holds u128s, which serde_json::Value cannot: stash the loop as a string.
            let extra = serde_json::Value::String(serde_json::to_string(&h.s).unwrap());
            checkpoint::save(ckpt_dir.path(), &h.agent, &extra, 1).unwrap();
            h.table.snapshot().unwrap();
            h.table.close();
            drop(h);
            let table = Harness::persistent_table(&cfg, table_dir.path(), SEED);
            let (agent, extra) = checkpoint::load(ckpt_dir.path(), None).unwrap();
            let s: LoopState = serde_json::from_str(extra.as_str().unwrap()).unwrap();
            h = Harness { agent, table, s, learning_starts: LEARNING_STARTS, batch: cfg.batch_size };
        }
        h.step();
    }
    let returns = h.s.returns.clone();
    (state(&h.agent), returns)
}

fn assert_same(a: &(HashMap<String, Vec<f32>>, Vec<f64>), b: &(HashMap<String, Vec<f32>>, Vec<f64>), what: &str) {
    assert_eq!(a.1, b.1, "{what}: episode returns differ");
    assert_eq!(a.0.len(), b.0.len());
    for (name, v) in &a.0 {
        assert!(v == &b.0[name], "{what}: `{name}` differs after resume");
    }
}

/// Learner, loop and replay table all resume exactly: networks, targets, Adam moments, α,
/// counters, every random stream and the episode returns end bit-identical to a run that
/// was never interrupted.
#[test]
fn a_resumed_pendulum_run_is_bit_identical_to_an_uninterrupted_one() {
    mapless_learner::TorchThreads::default().apply().unwrap();
    for algorithm in ALL {
        let reference = run(algorithm, None);
        let resumed = run(algorithm, Some(SPLIT));
        assert_eq!(reference.1.len(), (TOTAL / 200) as usize);
        assert_same(&reference, &resumed, algorithm.as_str());
    }
}

#[test]
fn atomic_writes_replace_the_file_and_others_can_read_it() {
    use std::os::unix::fs::PermissionsExt;
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("policy.safetensors");
    mapless_proto::atomic_file::write_file_atomically(&p, b"old").unwrap();
    mapless_proto::atomic_file::write_file_atomically(&p, b"new").unwrap();
    assert_eq!(std::fs::read(&p).unwrap(), b"new");
    // rw-r--r-- less the umask, as fs::write makes files (tempfile alone makes them 0600).
    assert_eq!(std::fs::metadata(&p).unwrap().permissions().mode() & 0o044, 0o044);
    let left: Vec<_> = std::fs::read_dir(d.path()).unwrap().flatten().map(|e| e.file_name()).collect();
    assert_eq!(left, [std::ffi::OsString::from("policy.safetensors")], "no temporary file left");
}
