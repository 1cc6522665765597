//! DDPG, TD3 and SAC against values worked out by hand.
//!
//! The networks are set to weights whose outputs have a closed form (hidden width 4):
//!
//! ```text
//!   critic k:  h = relu(a + 10) = a + 10 → relu(h) → Q_k(s, a) = h − 10 + k_k = a + k_k
//!   actor:     y = s₀ + bias (the +10 / −10 trick again), so π(s) = tanh(s₀ + bias)
//!   SAC actor: μ = s₀, log σ = c (a constant bias)
//! ```
//!
//! valid while |a| ≤ 1 and |s₀| < 10, so every TD target below is arithmetic on a few numbers.

use std::collections::HashMap;

use mapless_learner::algo::{Agent, metric, sac::tanh_gaussian};
use mapless_learner::batch::Minibatch;
use mapless_learner::config::{AlgorithmKind, LearnerConfig};
use mapless_proto::v1::SampledBatch;
use rand::SeedableRng;
use tch::Tensor;

const OBS: usize = 2;
const ACT: usize = 1;
const H: usize = 4;
const GAMMA: f64 = 0.9;

fn cfg(kind: AlgorithmKind) -> LearnerConfig {
    let mut c = LearnerConfig { algorithm: kind, hidden_width: H as i64, gamma: GAMMA, seed: 3, ..LearnerConfig::default() };
    c.sac.initial_alpha = 0.5;
    c
}

fn t(values: Vec<f32>, shape: &[i64]) -> Tensor {
    Tensor::from_slice(&values).view(shape)
}

/// Stacked critic weights giving Q_k(s, a) = a + ks[k] (input [s₀, s₁, a]).
fn linear_critics(prefix: &str, ks: &[f64]) -> Vec<(String, Tensor)> {
    let k = ks.len();
    let inp = OBS + ACT;
    let mut w0 = vec![0.0f32; k * inp * H];
    let mut b0 = vec![0.0f32; k * H];
    let mut w1 = vec![0.0f32; k * H * H];
    let mut wo = vec![0.0f32; k * H];
    let mut bo = vec![0.0f32; k];
    for j in 0..k {
        w0[j * inp * H + OBS * H] = 1.0; // [j, in = a, out = 0]
        b0[j * H] = 10.0;
        w1[j * H * H] = 1.0;
        wo[j * H] = 1.0;
        bo[j] = (ks[j] - 10.0) as f32;
    }
    let (k, inp, h) = (k as i64, inp as i64, H as i64);
    vec![
        (format!("{prefix}.l0.weight"), t(w0, &[k, inp, h])),
        (format!("{prefix}.l0.bias"), t(b0, &[k, 1, h])),
        (format!("{prefix}.l1.weight"), t(w1, &[k, h, h])),
        (format!("{prefix}.l1.bias"), Tensor::zeros([k, 1, h], tch::kind::FLOAT_CPU)),
        (format!("{prefix}.out.weight"), t(wo, &[k, h, 1])),
        (format!("{prefix}.out.bias"), t(bo, &[k, 1, 1])),
    ]
}

/// Actor weights (PyTorch layout) giving output 0 = s₀ + out_bias[0]; further outputs are
/// the constants out_bias[i].
fn linear_actor(prefix: &str, out_bias: &[f64]) -> Vec<(String, Tensor)> {
    let outs = out_bias.len();
    let mut w0 = vec![0.0f32; H * OBS];
    w0[0] = 1.0; // [0][s₀]
    let mut b0 = vec![0.0f32; H];
    b0[0] = 10.0;
    let mut w1 = vec![0.0f32; H * H];
    w1[0] = 1.0;
    let mut wo = vec![0.0f32; outs * H];
    wo[0] = 1.0;
    let mut bo: Vec<f32> = out_bias.iter().map(|&b| b as f32).collect();
    bo[0] -= 10.0;
    let (h, o, n) = (H as i64, OBS as i64, outs as i64);
    vec![
        (format!("{prefix}.l0.weight"), t(w0, &[h, o])),
        (format!("{prefix}.l0.bias"), t(b0, &[h])),
        (format!("{prefix}.l1.weight"), t(w1, &[h, h])),
        (format!("{prefix}.l1.bias"), Tensor::zeros([h], tch::kind::FLOAT_CPU)),
        (format!("{prefix}.out.weight"), t(wo, &[n, h])),
        (format!("{prefix}.out.bias"), t(bo, &[n])),
    ]
}

fn set(agent: &mut Agent, named: Vec<(String, Tensor)>) {
    let refs: Vec<(&str, Tensor)> = named.iter().map(|(n, t)| (n.as_str(), t.shallow_clone())).collect();
    agent.set_tensors(&refs).unwrap();
}

// The three-row batch: a normal row, a terminal row, a truncated row.
const S0_NEXT: [f64; 3] = [2.0, 0.1, -0.4];
const REWARD: [f64; 3] = [1.0, -2.0, 0.5];
const ACTION: [f64; 3] = [0.2, -0.7, 0.9];
const WEIGHTS: [f32; 3] = [1.0, 0.5, 0.25];

fn batch() -> Minibatch {
    let sampled = SampledBatch {
        obs_dim: OBS as u32,
        act_dim: ACT as u32,
        num_rows: 3,
        obs: vec![0.5, 0.0, -0.3, 1.0, 1.0, -1.0],
        action: ACTION.iter().map(|&a| a as f32).collect(),
        reward: REWARD.iter().map(|&r| r as f32).collect(),
        next_obs: S0_NEXT.iter().flat_map(|&s| [s as f32, 0.0]).collect(),
        terminal: vec![false, true, false],
        truncated: vec![false, false, true],
        importance_weights: WEIGHTS.to_vec(),
        keys: vec![10, 11, 12],
        ..SampledBatch::default()
    };
    Minibatch::from_sampled(&sampled, tch::Device::Cpu).unwrap()
}

fn column(t: &Tensor) -> Vec<f64> {
    Vec::<f32>::try_from(&t.reshape([-1])).unwrap().into_iter().map(f64::from).collect()
}

fn assert_close(got: &[f64], want: &[f64], tol: f64) {
    assert_eq!(got.len(), want.len());
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        assert!((g - w).abs() <= tol, "row {i}: got {g}, want {w} (all: {got:?} vs {want:?})");
    }
}

/// 1 − terminal, row by row: the truncated row bootstraps.
const NOT_DONE: [f64; 3] = [1.0, 0.0, 1.0];

#[test]
fn ddpg_target_uses_the_target_actor_and_critic_and_cuts_only_terminal_rows() {
    let mut agent = Agent::new(&cfg(AlgorithmKind::Ddpg), OBS, ACT).unwrap();
    // Online networks deliberately different from the targets: they must not be used.
    set(&mut agent, linear_actor("actor", &[5.0]));
    set(&mut agent, linear_critics("critic", &[100.0]));
    set(&mut agent, linear_actor("target_actor", &[0.0]));
    set(&mut agent, linear_critics("target_critic", &[0.25]));
    let Agent::Ddpg(ddpg) = &agent else { unreachable!() };
    let b = batch();
    let y = column(&ddpg.td_target(&b));
    let want: Vec<f64> = (0..3).map(|i| REWARD[i] + GAMMA * NOT_DONE[i] * (S0_NEXT[i].tanh() + 0.25)).collect();
    assert_close(&y, &want, 1e-5);
    assert_eq!(y[1], -2.0, "terminal row: y = r exactly");
}

#[test]
fn weighted_critic_loss_and_td_errors_match_hand_values() {
    let mut agent = Agent::new(&cfg(AlgorithmKind::Ddpg), OBS, ACT).unwrap();
    set(&mut agent, linear_actor("target_actor", &[0.0]));
    set(&mut agent, linear_critics("target_critic", &[0.25]));
    set(&mut agent, linear_critics("critic", &[-1.0])); // Q(s, a) = a − 1
    let b = batch();
    let stats = agent.update(&b).unwrap();
    let y: Vec<f64> = (0..3).map(|i| REWARD[i] + GAMMA * NOT_DONE[i] * (S0_NEXT[i].tanh() + 0.25)).collect();
    let td: Vec<f64> = (0..3).map(|i| (y[i] - (ACTION[i] - 1.0)).abs()).collect();
    let loss: f64 = (0..3).map(|i| f64::from(WEIGHTS[i]) * td[i] * td[i]).sum::<f64>() / 3.0;
    let got_td: Vec<f64> = stats.td_errors.iter().map(|&v| f64::from(v)).collect();
    assert_close(&got_td, &td, 1e-5);
    let got = stats.get(metric::CRITIC_LOSS).unwrap();
    assert!((got - loss).abs() < 1e-5 * loss.max(1.0), "{got} vs {loss}");
    assert!((stats.get(metric::Q_MEAN).unwrap() - (0.4 / 3.0 - 1.0)).abs() < 1e-5);
    assert_eq!(agent.updates(), 1);
}

#[test]
fn td3_target_takes_the_min_of_twin_target_critics_at_the_clipped_smoothed_action() {
    let mut agent = Agent::new(&cfg(AlgorithmKind::Td3), OBS, ACT).unwrap();
    set(&mut agent, linear_actor("target_actor", &[0.0]));
    set(&mut agent, linear_critics("target_critic", &[0.25, -0.5]));
    set(&mut agent, linear_critics("critic", &[100.0, 100.0]));
    let Agent::Td3(td3) = &agent else { unreachable!() };
    let eps = [0.5, -0.5, 0.3];
    let y = column(&td3.td_target(&batch(), &t(eps.iter().map(|&e| e as f32).collect(), &[3, 1])));
    let want: Vec<f64> = (0..3)
        .map(|i| {
            let a = (S0_NEXT[i].tanh() + eps[i]).clamp(-1.0, 1.0);
            REWARD[i] + GAMMA * NOT_DONE[i] * (a + 0.25f64.min(-0.5))
        })
        .collect();
    // Row 0's smoothed action tanh(2) + 0.5 > 1 is clipped to the action box.
    assert!(S0_NEXT[0].tanh() + eps[0] > 1.0);
    assert_close(&y, &want, 1e-5);
}

/// `td_target_max` caps every algorithm's targets and changes nothing else: each row is the
/// uncapped target or the cap, whichever is smaller, and a cap between the rows' targets bites
/// on some rows and not on others.
#[test]
fn td_target_max_caps_the_targets_of_every_algorithm() {
    let eps = t(vec![0.3, -1.2, 0.8], &[3, 1]);
    let targets = |kind: AlgorithmKind, max: Option<f64>| {
        let mut c = cfg(kind);
        c.td_target_max = max;
        let mut agent = Agent::new(&c, OBS, ACT).unwrap();
        match kind {
            AlgorithmKind::Sac => set(&mut agent, linear_actor("actor", &[0.0, -1.0])),
            _ => set(&mut agent, linear_actor("target_actor", &[0.0])),
        }
        set(&mut agent, linear_critics("target_critic", if kind == AlgorithmKind::Ddpg { &[0.25] } else { &[0.25, -0.5] }));
        let b = batch();
        column(&match &agent {
            Agent::Ddpg(a) => a.td_target(&b),
            Agent::Td3(a) => a.td_target(&b, &eps),
            Agent::Sac(a) => a.td_target(&b, &eps),
        })
    };
    for kind in [AlgorithmKind::Ddpg, AlgorithmKind::Td3, AlgorithmKind::Sac] {
        let free = targets(kind, None);
        let mut sorted = free.clone();
        sorted.sort_by(f64::total_cmp);
        let cap = (sorted[0] + sorted[2]) / 2.0;
        let capped = targets(kind, Some(cap));
        let want: Vec<f64> = free.iter().map(|&y| y.min(cap)).collect();
        assert_close(&capped, &want, 1e-6);
        assert!(free.iter().any(|&y| y > cap) && free.iter().any(|&y| y < cap), "{kind:?}: the cap {cap} bites on some rows only: {free:?}");
    }
    let mut c = cfg(AlgorithmKind::Sac);
    c.td_target_max = Some(f64::INFINITY);
    assert!(c.validate().is_err(), "an infinite cap is refused");
}

/// `n_step` bootstraps with γⁿ on both update paths of every algorithm: the same networks,
/// noise and minibatch give a first update whose targets' mean, less the rewards' mean, is γⁿ⁻¹
/// times the one-step agent's (y = r + γⁿ(1 − terminal)·v, v unchanged).
#[test]
fn n_step_targets_bootstrap_with_gamma_to_the_n_on_both_paths() {
    let mut rng = rand_pcg::Pcg64::seed_from_u64(8);
    let b = Minibatch::random(32, OBS, ACT, &mut rng, tch::Device::Cpu).unwrap();
    let reward_mean = column(&b.reward).iter().sum::<f64>() / 32.0;
    for kind in [AlgorithmKind::Ddpg, AlgorithmKind::Td3, AlgorithmKind::Sac] {
        for fused in [true, false] {
            let target_mean = |n_step: usize| {
                let c = LearnerConfig { n_step, fused_update: fused, ..cfg(kind) };
                let stats = Agent::new(&c, OBS, ACT).unwrap().update(&b).unwrap();
                stats.scalars.iter().find(|(n, _)| *n == metric::TARGET_MEAN).unwrap().1
            };
            let (one, three) = (target_mean(1) - reward_mean, target_mean(3) - reward_mean);
            assert!(one.abs() > 1e-3, "{kind:?}: the bootstrapped part is not negligible ({one})");
            assert!((three - GAMMA * GAMMA * one).abs() < 1e-5, "{kind:?} fused {fused}: {three} vs γ²·{one}");
        }
    }
    let c = LearnerConfig { n_step: 0, ..cfg(AlgorithmKind::Sac) };
    assert!(c.validate().unwrap_err().to_string().contains("n_step"));
}

#[test]
fn td3_smoothing_noise_is_gaussian_with_sigma_0_45_clipped_to_half() {
    let mut agent = Agent::new(&cfg(AlgorithmKind::Td3), OBS, ACT).unwrap();
    let Agent::Td3(td3) = &mut agent else { unreachable!() };
    let eps = column(&td3.smoothing_noise(20_000));
    assert!(eps.iter().all(|e| e.abs() <= 0.5 + 1e-7));
    // P(|N(0, 0.45²)| > 0.5) = 2(1 − Φ(1.111)) ≈ 0.2666: that share sits exactly on ±0.5.
    let clipped = eps.iter().filter(|e| (e.abs() - 0.5).abs() < 1e-7).count() as f64 / eps.len() as f64;
    assert!((clipped - 0.2666).abs() < 0.015, "clipped share {clipped}");
    let inside: Vec<f64> = eps.iter().copied().filter(|e| e.abs() < 0.5).collect();
    let mean = inside.iter().sum::<f64>() / inside.len() as f64;
    assert!(mean.abs() < 0.01, "mean {mean}");
    // Different draws each call.
    assert_ne!(column(&td3.smoothing_noise(4)), column(&td3.smoothing_noise(4)));
}

fn state(agent: &Agent) -> HashMap<String, Vec<f64>> {
    agent.state_tensors().into_iter().map(|(n, t)| (n, column(&t))).collect()
}

fn prefixed<'a>(s: &'a HashMap<String, Vec<f64>>, prefix: &str) -> Vec<(&'a String, &'a Vec<f64>)> {
    let mut v: Vec<_> = s.iter().filter(|(n, _)| n.starts_with(prefix)).collect();
    v.sort_by(|a, b| a.0.cmp(b.0));
    assert!(!v.is_empty());
    v
}

/// θ_t after == θ_t before + τ(θ after − θ_t before), for every parameter of `net`.
fn assert_soft_updated(before: &HashMap<String, Vec<f64>>, after: &HashMap<String, Vec<f64>>, net: &str, tau: f64) {
    for (name, online) in prefixed(after, &format!("{net}.")) {
        let target_name = format!("target_{name}");
        let old = &before[&target_name];
        let new = &after[&target_name];
        for i in 0..old.len() {
            let want = old[i] + tau * (online[i] - old[i]);
            assert!((new[i] - want).abs() < 1e-6, "{target_name}[{i}]: {} vs {want}", new[i]);
        }
    }
}

fn random_batch(seed: u64) -> Minibatch {
    let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
    Minibatch::random(16, OBS, ACT, &mut rng, tch::Device::Cpu).unwrap()
}

#[test]
fn ddpg_soft_updates_both_targets_after_every_step() {
    let mut c = cfg(AlgorithmKind::Ddpg);
    c.tau = 0.1;
    let mut agent = Agent::new(&c, OBS, ACT).unwrap();
    // Make targets differ from the online networks first.
    set(&mut agent, linear_actor("target_actor", &[0.3]));
    set(&mut agent, linear_critics("target_critic", &[0.1]));
    let before = state(&agent);
    agent.update(&random_batch(1)).unwrap();
    let after = state(&agent);
    assert_soft_updated(&before, &after, "actor", 0.1);
    assert_soft_updated(&before, &after, "critic", 0.1);
}

#[test]
fn td3_updates_actor_and_targets_only_every_second_step() {
    let mut c = cfg(AlgorithmKind::Td3);
    c.tau = 0.1;
    let mut agent = Agent::new(&c, OBS, ACT).unwrap();
    set(&mut agent, linear_actor("target_actor", &[0.3]));
    let s0 = state(&agent);
    let st1 = agent.update(&random_batch(1)).unwrap();
    let s1 = state(&agent);
    assert!(st1.get(metric::ACTOR_LOSS).is_none());
    for prefix in ["actor.", "target_actor.", "target_critic."] {
        for (name, v) in prefixed(&s1, prefix) {
            assert_eq!(v, &s0[name], "{name} moved on update 1");
        }
    }
    assert_ne!(s1["critic.l0.weight"], s0["critic.l0.weight"], "critics learn every update");

    let st2 = agent.update(&random_batch(2)).unwrap();
    let s2 = state(&agent);
    assert!(st2.get(metric::ACTOR_LOSS).is_some());
    assert_ne!(s2["actor.l0.weight"], s1["actor.l0.weight"], "actor learns on update 2");
    assert_soft_updated(&s1, &s2, "actor", 0.1);
    assert_soft_updated(&s1, &s2, "critic", 0.1);

    let st3 = agent.update(&random_batch(3)).unwrap();
    assert!(st3.get(metric::ACTOR_LOSS).is_none());
    assert_eq!(state(&agent)["actor.out.bias"], s2["actor.out.bias"]);
    assert!(agent.update(&random_batch(4)).unwrap().get(metric::ACTOR_LOSS).is_some());
}

/// ln π(a|s) by the textbook formula in f64: Gaussian density of u minus ln(1 − tanh²u).
fn log_prob_closed_form(mean: &[f64], log_std: &[f64], eps: &[f64]) -> f64 {
    (0..mean.len())
        .map(|j| {
            let sigma = log_std[j].exp();
            let u = mean[j] + sigma * eps[j];
            let gauss = -((u - mean[j]) / sigma).powi(2) / 2.0 - sigma.ln() - (2.0 * std::f64::consts::PI).sqrt().ln();
            // 1 − tanh² = sech², computed without cancellation.
            let log_sech2 = 2.0 * (2.0 / (u.exp() + (-u).exp())).ln();
            gauss - log_sech2
        })
        .sum()
}

#[test]
fn sac_log_prob_includes_the_tanh_correction_and_matches_the_closed_form() {
    let cases: [([f64; 2], [f64; 2], [f64; 2]); 3] = [
        ([0.3, -1.0], [-0.5, 0.2], [0.7, -1.3]),
        ([0.0, 0.0], [0.0, 0.0], [0.0, 0.0]),
        // |u| = 12: 1 − tanh²(u) underflows in f32; the stable form must not.
        ([11.0, -9.0], [0.0, 0.0], [1.0, -3.0]),
    ];
    for (mean, log_std, eps) in cases {
        let f = |v: [f64; 2]| t(v.iter().map(|&x| x as f32).collect(), &[1, 2]);
        let s = tanh_gaussian(&f(mean), &f(log_std), &f(eps));
        let got = s.log_prob.double_value(&[0, 0]);
        let want = log_prob_closed_form(&mean, &log_std, &eps);
        assert!((got - want).abs() < 1e-4 * want.abs().max(1.0), "{mean:?}: {got} vs {want}");
        let a = column(&s.action);
        for j in 0..2 {
            assert!((a[j] - (mean[j] + log_std[j].exp() * eps[j]).tanh()).abs() < 1e-6);
        }
    }
    // At μ = 0, σ = 1, ε = 0 the correction is zero: ln π = 2 × (−½ ln 2π).
    let z = Tensor::zeros([1, 2], tch::kind::FLOAT_CPU);
    let lp = tanh_gaussian(&z, &z, &z).log_prob.double_value(&[0, 0]);
    assert!((lp + (2.0 * std::f64::consts::PI).ln()).abs() < 1e-6);
}

#[test]
fn sac_target_is_the_entropy_regularised_min_over_target_critics() {
    let mut agent = Agent::new(&cfg(AlgorithmKind::Sac), OBS, ACT).unwrap();
    let c = -1.0; // log σ
    set(&mut agent, linear_actor("actor", &[0.0, c]));
    set(&mut agent, linear_critics("target_critic", &[0.25, -0.5]));
    set(&mut agent, linear_critics("critic", &[100.0, 100.0]));
    let Agent::Sac(sac) = &agent else { unreachable!() };
    assert!((sac.alpha() - 0.5).abs() < 1e-7);
    assert_eq!(sac.target_entropy(), -1.0, "default H = −act_dim");
    let eps = [0.3, -1.2, 0.8];
    let y = column(&sac.td_target(&batch(), &t(eps.iter().map(|&e| e as f32).collect(), &[3, 1])));
    let want: Vec<f64> = (0..3)
        .map(|i| {
            let u = S0_NEXT[i] + c.exp() * eps[i];
            let a = u.tanh();
            let logp = log_prob_closed_form(&[S0_NEXT[i]], &[c], &[eps[i]]);
            REWARD[i] + GAMMA * NOT_DONE[i] * ((a + 0.25f64.min(-0.5)) - 0.5 * logp)
        })
        .collect();
    assert_close(&y, &want, 1e-4);
}

fn alpha_after_one_update(log_std: f64) -> (f64, f64, f64) {
    let mut agent = Agent::new(&cfg(AlgorithmKind::Sac), OBS, ACT).unwrap();
    set(&mut agent, linear_actor("actor", &[0.0, log_std]));
    let before = agent.alpha().unwrap();
    let stats = agent.update(&random_batch(5)).unwrap();
    (before, agent.alpha().unwrap(), stats.get(metric::ENTROPY).unwrap())
}

#[test]
fn alpha_grows_when_entropy_is_below_target_and_shrinks_when_above() {
    let lr = LearnerConfig::default().sac.alpha_lr;
    // σ = e⁻⁵: entropy ≈ −5 + 1.42 ≪ H = −1.
    let (before, after, entropy) = alpha_after_one_update(-5.0);
    assert!(entropy < -1.0, "entropy {entropy}");
    assert!(after > before, "α {before} → {after}");
    // Adam's first step moves log α by exactly lr.
    assert!(((after / before).ln() - lr).abs() < 1e-6);
    // σ = 1 around μ ≈ 0: entropy ≈ 0.4 > H.
    let (before, after, entropy) = alpha_after_one_update(0.0);
    assert!(entropy > -1.0, "entropy {entropy}");
    assert!(after < before, "α {before} → {after}");
}

#[test]
fn fixed_alpha_stays_fixed() {
    let mut c = cfg(AlgorithmKind::Sac);
    c.sac.autotune_alpha = false;
    let mut agent = Agent::new(&c, OBS, ACT).unwrap();
    agent.update(&random_batch(5)).unwrap();
    assert!((agent.alpha().unwrap() - 0.5).abs() < 1e-7);
}

/// The documented pure-Rust inference (algo module docs), from `policy_tensors` alone.
fn infer(policy: &[(String, Tensor)], obs: &[f32], act: usize, sac: bool) -> Vec<f64> {
    let get = |n: &str| -> (Vec<i64>, Vec<f64>) {
        let t = &policy.iter().find(|(m, _)| m == n).unwrap().1;
        (t.size(), column(t))
    };
    let mut x: Vec<f64> = obs.iter().map(|&v| f64::from(v)).collect();
    for (i, layer) in ["l0", "l1", "out"].iter().enumerate() {
        let (shape, w) = get(&format!("actor.{layer}.weight"));
        let (_, b) = get(&format!("actor.{layer}.bias"));
        let (o, n) = (shape[0] as usize, shape[1] as usize);
        x = (0..o)
            .map(|r| {
                let y = b[r] + (0..n).map(|c| w[r * n + c] * x[c]).sum::<f64>();
                if i < 2 { y.max(0.0) } else { y }
            })
            .collect();
    }
    if sac {
        assert_eq!(x.len(), 2 * act);
    }
    x[..act].iter().map(|y| y.tanh()).collect()
}

#[test]
fn published_policy_layout_reproduces_deterministic_actions() {
    for kind in [AlgorithmKind::Ddpg, AlgorithmKind::Td3, AlgorithmKind::Sac] {
        let mut c = cfg(kind);
        c.hidden_width = 8;
        let mut agent = Agent::new(&c, 3, 2).unwrap();
        agent
            .update(&{
                let mut rng = rand_pcg::Pcg64::seed_from_u64(9);
                Minibatch::random(8, 3, 2, &mut rng, tch::Device::Cpu).unwrap()
            })
            .unwrap();
        let policy = agent.policy_tensors();
        let names: Vec<(&str, Vec<i64>)> = policy.iter().map(|(n, t)| (n.as_str(), t.size())).collect();
        let k = if kind == AlgorithmKind::Sac { 4 } else { 2 };
        assert_eq!(
            names,
            vec![
                ("actor.l0.weight", vec![8, 3]),
                ("actor.l0.bias", vec![8]),
                ("actor.l1.weight", vec![8, 8]),
                ("actor.l1.bias", vec![8]),
                ("actor.out.weight", vec![k, 8]),
                ("actor.out.bias", vec![k]),
            ],
            "{kind:?}"
        );
        assert!(policy.iter().all(|(_, t)| t.device() == tch::Device::Cpu && t.kind() == tch::Kind::Float));
        let obs = [0.3f32, -0.8, 1.5];
        let got = agent.act_slice(&obs, false).unwrap();
        let want = infer(&policy, &obs, 2, kind == AlgorithmKind::Sac);
        for j in 0..2 {
            assert!((f64::from(got[j]) - want[j]).abs() < 1e-5, "{kind:?}: {got:?} vs {want:?}");
        }
        // Exploring actions stay in the box and differ from the greedy ones.
        let explored = agent.act_slice(&obs, true).unwrap();
        assert!(explored.iter().all(|a| (-1.0..=1.0).contains(a)));
        assert_ne!(explored, got);
        let meta = agent.policy_metadata();
        assert_eq!(meta["algorithm"], kind.as_str());
        assert_eq!((meta["obs_dim"].as_str(), meta["act_dim"].as_str(), meta["version"].as_str()), ("3", "2", "1"));
        assert_eq!(meta.contains_key("sac.log_std_min"), kind == AlgorithmKind::Sac);
    }
}

#[test]
fn same_seed_same_updates_bit_for_bit_and_other_seeds_differ() {
    for kind in [AlgorithmKind::Ddpg, AlgorithmKind::Td3, AlgorithmKind::Sac] {
        let run = |seed: u64| {
            let mut c = cfg(kind);
            c.seed = seed;
            let mut agent = Agent::new(&c, OBS, ACT).unwrap();
            for i in 0..4 {
                agent.update(&random_batch(i)).unwrap();
            }
            state(&agent)
        };
        assert_eq!(run(1), run(1), "{kind:?}");
        assert_ne!(run(1)["actor.l0.weight"], run(2)["actor.l0.weight"], "{kind:?}");
    }
}

#[test]
fn bad_batches_and_observations_are_errors_not_panics() {
    let mut agent = Agent::new(&cfg(AlgorithmKind::Sac), OBS, ACT).unwrap();
    let mut rng = rand_pcg::Pcg64::seed_from_u64(1);
    let wrong = Minibatch::random(4, OBS + 1, ACT, &mut rng, tch::Device::Cpu).unwrap();
    let e = agent.update(&wrong).unwrap_err();
    assert!(e.to_string().contains("obs_dim 3"), "{e}");
    assert!(agent.act_slice(&[0.1, f32::NAN], false).is_err());
    assert!(agent.act_slice(&[0.1, 0.2, 0.3], false).is_err());
    assert!(agent.act(&Tensor::zeros([2, 5], tch::kind::FLOAT_CPU), false).is_err());
    assert!(agent.set_tensors(&[("actor.nope", Tensor::zeros([1], tch::kind::FLOAT_CPU))]).is_err());
    assert!(agent.set_tensors(&[("actor.l0.bias", Tensor::zeros([1], tch::kind::FLOAT_CPU))]).is_err());
    assert_eq!(agent.updates(), 0);
    // A diverged critic (an infinite weight) is reported, not applied.
    let mut c = cfg(AlgorithmKind::Ddpg);
    c.grad_clip_norm = None;
    let mut agent = Agent::new(&c, OBS, ACT).unwrap();
    let mut named = linear_critics("critic", &[0.0]);
    named[5].1 = Tensor::from_slice(&[f32::INFINITY]).view([1, 1, 1]);
    set(&mut agent, named);
    let before = state(&agent);
    let e = agent.update(&random_batch(1)).unwrap_err();
    assert!(e.to_string().contains("losses/critic"), "{e}");
    assert_eq!(state(&agent)["actor.l0.weight"], before["actor.l0.weight"]);
    assert_eq!(agent.updates(), 0);
}

/// Each algorithm's fused CPU update (`fused_update`, hand-written backward passes) against
/// the libtorch autograd path: same seeds, same batches (terminal rows, prioritised-replay
/// weights), six updates (three of TD3's delayed actor steps); every network, target, Adam
/// moment, log α, the reported scalars and the TD errors agree up to float rounding. SAC runs
/// once with the default log σ clamp and once with a clamp narrow enough that some rows hit
/// it (its gradient is cut). Each algorithm runs again with layer-normalised critics
/// (`critic_layer_norm`).
#[test]
fn fused_updates_match_autograd() {
    let cases = [
        (AlgorithmKind::Sac, 2.0, false),
        (AlgorithmKind::Sac, 0.02, false),
        (AlgorithmKind::Td3, 2.0, false),
        (AlgorithmKind::Ddpg, 2.0, false),
        (AlgorithmKind::Sac, 2.0, true),
        (AlgorithmKind::Td3, 2.0, true),
        (AlgorithmKind::Ddpg, 2.0, true),
    ];
    // Each case again with targets capped where the cap bites on some rows (rewards and
    // early Q-values lie around ±1).
    let cases = cases.into_iter().flat_map(|(k, l, n)| [(k, l, n, None), (k, l, n, Some(0.25))]);
    for (kind, log_std_max, norm, cap) in cases {
        // Normalising divides by each row's σ, which magnifies the two paths' rounding of the
        // pre-activations (libtorch's moments against the fused path's eight-lane f32 sums,
        // which add in another order).
        let tol = if norm { 2e-5 } else { 1e-6 };
        let (obs, act, rows) = (5usize, 2usize, 24usize);
        let make = |fused: bool, cap: Option<f64>| {
            let mut c = LearnerConfig {
                algorithm: kind,
                hidden_width: 32,
                seed: 11,
                tau: 0.05,
                actor_lr: 1e-3,
                critic_lr: 1e-3,
                fused_update: fused,
                grad_clip_norm: Some(0.5),
                critic_layer_norm: norm,
                td_target_max: cap,
                ..LearnerConfig::default()
            };
            c.sac.log_std_max = log_std_max;
            c.sac.alpha_lr = 1e-2;
            Agent::new(&c, obs, act).unwrap()
        };
        let (mut fused, mut autograd) = (make(true, cap), make(false, cap));
        let mut rng = rand_pcg::Pcg64::seed_from_u64(5);
        let mut last = None;
        for step in 0..6 {
            let mut u = |n: usize, lo: f32, hi: f32| -> Vec<f32> { (0..n).map(|_| rand::Rng::random_range(&mut rng, lo..hi)).collect() };
            let (o, o2, a, r, w) = (u(rows * obs, -1.0, 1.0), u(rows * obs, -1.0, 1.0), u(rows * act, -1.0, 1.0), u(rows, -1.0, 1.0), u(rows, 0.2, 1.0));
            let terminal: Vec<bool> = (0..rows).map(|i| i % 5 == 0).collect();
            let b = Minibatch::from_columns(
                mapless_learner::batch::BatchColumns { rows, obs_dim: obs, act_dim: act, obs: &o, action: &a, reward: &r, next_obs: &o2, terminal: &terminal, importance_weights: &w, keys: &[] },
                tch::Device::Cpu,
            )
            .unwrap();
            let sf = fused.update(&b).unwrap();
            let sa = autograd.update(&b).unwrap();
            if let (0, Some(c)) = (step, cap) {
                // The cap bites: the same first update uncapped has a higher target mean.
                let mean = |s: &mapless_learner::algo::UpdateStats| s.scalars.iter().find(|(n, _)| *n == metric::TARGET_MEAN).unwrap().1;
                let free = make(true, None).update(&b).unwrap();
                assert!(mean(&sf) <= c && mean(&sf) < mean(&free) - 1e-3, "{kind:?}: capped target mean {} vs uncapped {}", mean(&sf), mean(&free));
            }
            last = Some(b);
            assert_eq!(sf.scalars.len(), sa.scalars.len());
            for ((nf, vf), (na, va)) in sf.scalars.iter().zip(&sa.scalars) {
                assert_eq!(nf, na);
                assert!((vf - va).abs() <= tol * (1.0 + va.abs()), "{kind:?} step {step} {nf}: {vf} vs {va}");
            }
            let (tf, ta): (Vec<f64>, Vec<f64>) = (sf.td_errors.iter().map(|&v| f64::from(v)).collect(), sa.td_errors.iter().map(|&v| f64::from(v)).collect());
            assert_close(&tf, &ta, tol);
        }
        let (sf, sa) = (state(&fused), state(&autograd));
        assert_eq!(sf.len(), sa.len());
        let mut worst = (0.0f64, String::new());
        for (name, want) in &sa {
            let got = &sf[name];
            for (i, (g, w)) in got.iter().zip(want).enumerate() {
                let d = (g - w).abs() / (1.0 + w.abs());
                if d > worst.0 {
                    worst = (d, format!("{name}[{i}]"));
                }
                assert!(d <= tol, "{kind:?} {name}[{i}]: {g} vs {w} (log σ max {log_std_max}, critic layer norm {norm}, target cap {cap:?})");
            }
        }
        eprintln!("{kind:?} (log σ max {log_std_max}, critic layer norm {norm}, target cap {cap:?}): largest relative difference {:.2e} at {}", worst.0, worst.1);
        // Rounding differs somewhere, so the fused path did run (it falls back to autograd
        // on batches it cannot read, which would make the two agents bit-identical).
        assert!(worst.0 > 0.0, "{kind:?}: the two paths are bit-identical");
        // A diverged critic: both paths refuse the update with the same error and counter.
        let shape = fused.state_tensors().into_iter().find(|(n, _)| n == "critic.out.bias").unwrap().1.size();
        let n: i64 = shape.iter().product();
        let nan = Tensor::from_slice(&vec![f32::NAN; n as usize]).view(shape.as_slice());
        let b = last.unwrap();
        let mut errors = Vec::new();
        for agent in [&mut fused, &mut autograd] {
            agent.set_tensors(&[("critic.out.bias", nan.shallow_clone())]).unwrap();
            errors.push(agent.update(&b).unwrap_err().to_string());
        }
        assert_eq!(errors[0], errors[1], "{kind:?}");
        assert!(errors[0].contains("losses/critic"), "{}", errors[0]);
        // The updates moved the networks: the comparison is not of two untouched copies.
        let fresh = state(&make(true, cap));
        assert!(fresh["actor.l1.weight"] != sf["actor.l1.weight"]);
        assert!(fresh["critic.l0.weight"] != sf["critic.l0.weight"]);
    }
}
