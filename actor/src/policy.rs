//! The policy network, evaluated in pure Rust from a published [`WeightsSnapshot`].
//!
//! The learner publishes only the policy's parameters, under stable names (see
//! `learner/src/nets.rs` and `learner/src/algo/mod.rs`):
//!
//! ```text
//!   actor.l0.weight [H, obs]   actor.l0.bias [H]
//!   actor.l1.weight [H, H]     actor.l1.bias [H]
//!   actor.out.weight [K, H]    actor.out.bias [K]
//!
//!   h = relu(W0·s + b0);  h = relu(W1·h + b1);  y = Wout·h + bout          (weights [out, in])
//!
//!   DDPG, TD3 (K = act):   a = tanh(y)
//!   SAC       (K = 2·act): μ = y[..act], log σ = clamp(y[act..], log_std_min, log_std_max)
//!                          acting: a = tanh(μ + σ·ε), ε ~ N(0, I);  deterministic: a = tanh(μ)
//! ```
//!
//! The log σ clamp bounds come from the snapshot's metadata (`sac.log_std_min`,
//! `sac.log_std_max`); a SAC snapshot without them is refused, so the actor can never disagree
//! with the learner about them.
//!
//! One forward pass handles all of a process's vehicles at once (row-major `[n, obs]` in,
//! `[n, act]` out) without allocating after the first call.

use mapless_proto::v1::{Algorithm, WeightsSnapshot};
use rand::Rng;
use rand_distr::StandardNormal;

use crate::ActorError;

/// Parameter name prefix of the policy network.
pub const POLICY_PREFIX: &str = "actor";
/// Layer names in order, as in the learner's `Mlp`.
pub const LAYERS: [&str; 3] = ["l0", "l1", "out"];
/// Snapshot metadata keys for SAC's log σ clamp.
pub const META_LOG_STD_MIN: &str = "sac.log_std_min";
/// See [`META_LOG_STD_MIN`].
pub const META_LOG_STD_MAX: &str = "sac.log_std_max";

/// One fully connected layer, `[out, in]` row-major as PyTorch stores it.
#[derive(Debug, Clone)]
struct Dense {
    weight: Vec<f32>,
    bias: Vec<f32>,
    inputs: usize,
    outputs: usize,
}

impl Dense {
    /// `y[r] = W·x[r] + b` for every row r, optionally followed by ReLU.
    fn forward(&self, x: &[f32], rows: usize, relu: bool, y: &mut Vec<f32>) {
        y.clear();
        y.resize(rows * self.outputs, 0.0);
        for (xr, yr) in x.chunks_exact(self.inputs).zip(y.chunks_exact_mut(self.outputs)).take(rows) {
            for ((yo, wo), bo) in yr.iter_mut().zip(self.weight.chunks_exact(self.inputs)).zip(&self.bias) {
                let v = bo + dot(wo, xr);
                *yo = if relu { v.max(0.0) } else { v };
            }
        }
    }
}

/// Dot product with eight independent accumulators, so the compiler vectorises it.
fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0.0f32; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for k in 0..8 {
            acc[k] += x[k] * y[k];
        }
    }
    let mut s = ((acc[0] + acc[4]) + (acc[1] + acc[5])) + ((acc[2] + acc[6]) + (acc[3] + acc[7]));
    for (x, y) in ra.iter().zip(rb) {
        s += x * y;
    }
    s
}

/// How the network's output becomes an action.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Head {
    /// DDPG and TD3: `a = tanh(y)`.
    Deterministic,
    /// SAC: `y = [μ | log σ]`, log σ clamped to `[log_std_min, log_std_max]`.
    TanhGaussian {
        /// Lower clamp of log σ.
        log_std_min: f32,
        /// Upper clamp of log σ.
        log_std_max: f32,
    },
}

/// How to act.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ActMode {
    /// The policy's own exploration: SAC samples from its distribution; deterministic policies
    /// act greedily (their exploration noise is added by the caller, see `noise`).
    Sample,
    /// Greedy: tanh of the output (DDPG/TD3) or of the mean (SAC). For evaluation.
    Deterministic,
}

/// A policy network loaded from published weights.
#[derive(Debug, Clone)]
pub struct Policy {
    version: u64,
    algorithm: Algorithm,
    obs_dim: usize,
    act_dim: usize,
    layers: [Dense; 3],
    head: Head,
    // Scratch buffers for forward passes.
    h0: Vec<f32>,
    h1: Vec<f32>,
    y: Vec<f32>,
}

impl Policy {
    /// Loads a snapshot, checking names, shapes, dtypes and the algorithm's head.
    pub fn from_snapshot(snapshot: &WeightsSnapshot) -> Result<Self, ActorError> {
        snapshot.validate().map_err(|e| ActorError::BadWeights(e.to_string()))?;
        let algorithm = Algorithm::try_from(snapshot.algorithm).map_err(|_| ActorError::BadWeights(format!("unknown algorithm {}", snapshot.algorithm)))?;
        let (obs_dim, act_dim) = (snapshot.obs_dim as usize, snapshot.act_dim as usize);
        let (head, out_width) = match algorithm {
            Algorithm::Ddpg | Algorithm::Td3 => (Head::Deterministic, act_dim),
            Algorithm::Sac => {
                let bound = |key: &str| -> Result<f32, ActorError> {
                    let raw = snapshot.metadata.get(key).ok_or_else(|| ActorError::BadWeights(format!("SAC snapshot lacks metadata `{key}`")))?;
                    raw.parse::<f32>().ok().filter(|v| v.is_finite()).ok_or_else(|| ActorError::BadWeights(format!("metadata `{key}` = {raw:?} is not a finite number")))
                };
                let (lo, hi) = (bound(META_LOG_STD_MIN)?, bound(META_LOG_STD_MAX)?);
                if lo > hi {
                    return Err(ActorError::BadWeights(format!("log σ clamp [{lo}, {hi}] is empty")));
                }
                (Head::TanhGaussian { log_std_min: lo, log_std_max: hi }, 2 * act_dim)
            }
            Algorithm::Unspecified => return Err(ActorError::BadWeights("algorithm is unspecified".into())),
        };
        let load = |layer: &str, inputs: Option<usize>, outputs: Option<usize>| -> Result<Dense, ActorError> {
            let name = |part: &str| format!("{POLICY_PREFIX}.{layer}.{part}");
            let get = |part: &str| {
                let n = name(part);
                snapshot.tensor(&n).ok_or_else(|| ActorError::BadWeights(format!("tensor `{n}` is missing")))
            };
            let (w, b) = (get("weight")?, get("bias")?);
            let (o, i) = match w.shape.as_slice() {
                [o, i] => (*o as usize, *i as usize),
                s => return Err(ActorError::BadWeights(format!("`{}` has shape {s:?}, expected [out, in]", name("weight")))),
            };
            if inputs.is_some_and(|want| want != i) || outputs.is_some_and(|want| want != o) {
                return Err(ActorError::BadWeights(format!(
                    "`{}` is [{o}, {i}], expected [{}, {}]",
                    name("weight"),
                    outputs.map_or("any".into(), |v| v.to_string()),
                    inputs.map_or("any".into(), |v| v.to_string())
                )));
            }
            if b.shape.as_slice() != [o as u64] {
                return Err(ActorError::BadWeights(format!("`{}` has shape {:?}, expected [{o}]", name("bias"), b.shape)));
            }
            let weight = w.to_f32_vec().map_err(|e| ActorError::BadWeights(e.to_string()))?;
            let bias = b.to_f32_vec().map_err(|e| ActorError::BadWeights(e.to_string()))?;
            if weight.iter().chain(&bias).any(|v| !v.is_finite()) {
                return Err(ActorError::BadWeights(format!("layer `{layer}` holds a non-finite value")));
            }
            Ok(Dense { weight, bias, inputs: i, outputs: o })
        };
        let l0 = load(LAYERS[0], Some(obs_dim), None)?;
        let l1 = load(LAYERS[1], Some(l0.outputs), None)?;
        let out = load(LAYERS[2], Some(l1.outputs), Some(out_width))?;
        Ok(Policy { version: snapshot.version, algorithm, obs_dim, act_dim, layers: [l0, l1, out], head, h0: Vec::new(), h1: Vec::new(), y: Vec::new() })
    }

    /// Version of the weights (copied into every transition's `policy_version`).
    pub fn version(&self) -> u64 {
        self.version
    }
    /// Algorithm that trained the weights.
    pub fn algorithm(&self) -> Algorithm {
        self.algorithm
    }
    /// Observation length.
    pub fn obs_dim(&self) -> usize {
        self.obs_dim
    }
    /// Action length.
    pub fn act_dim(&self) -> usize {
        self.act_dim
    }
    /// The output head.
    pub fn head(&self) -> Head {
        self.head
    }

    /// The network's raw output for `rows` observations (`[rows, obs]` row-major): `[rows, K]`
    /// with K = act (DDPG/TD3) or 2·act (SAC, log σ not yet clamped). Used by parity tests.
    pub fn raw_output(&mut self, obs: &[f32]) -> Result<&[f32], ActorError> {
        let rows = self.check_rows(obs)?;
        let [l0, l1, out] = &self.layers;
        l0.forward(obs, rows, true, &mut self.h0);
        l1.forward(&self.h0, rows, true, &mut self.h1);
        out.forward(&self.h1, rows, false, &mut self.y);
        Ok(&self.y)
    }

    /// Actions in [−1, 1] for `rows` observations, written to `actions` (`[rows, act]`).
    pub fn act<R: Rng + ?Sized>(&mut self, obs: &[f32], mode: ActMode, rng: &mut R, actions: &mut [f32]) -> Result<(), ActorError> {
        let rows = self.check_rows(obs)?;
        let a = self.act_dim;
        if actions.len() != rows * a {
            return Err(ActorError::Dimension(format!("action buffer holds {} values, {rows} rows need {}", actions.len(), rows * a)));
        }
        let head = self.head;
        let y = self.raw_output(obs)?;
        // Finite weights can still overflow f32 on a finite observation (inf − inf in a dot
        // product): the output is NaN and tanh keeps it NaN, an action no vehicle can take.
        // Refused here rather than handed to the simulator (found by the policy_safetensors
        // fuzz harness's seed of large but finite weights).
        if let Some(i) = y.iter().position(|v| v.is_nan()) {
            let width = y.len() / rows;
            return Err(ActorError::BadWeights(format!("output {} of row {} is NaN for a finite observation: the weights overflow f32", i % width, i / width)));
        }
        match head {
            Head::Deterministic => {
                for (dst, v) in actions.iter_mut().zip(y) {
                    *dst = v.tanh();
                }
            }
            Head::TanhGaussian { log_std_min, log_std_max } => {
                for (ar, yr) in actions.chunks_exact_mut(a).zip(y.chunks_exact(2 * a)) {
                    let (mean, log_std) = yr.split_at(a);
                    for ((dst, m), ls) in ar.iter_mut().zip(mean).zip(log_std) {
                        *dst = match mode {
                            ActMode::Deterministic => m.tanh(),
                            ActMode::Sample => {
                                let eps: f32 = rng.sample(StandardNormal);
                                (m + ls.clamp(log_std_min, log_std_max).exp() * eps).tanh()
                            }
                        };
                    }
                }
            }
        }
        Ok(())
    }

    fn check_rows(&self, obs: &[f32]) -> Result<usize, ActorError> {
        if !obs.len().is_multiple_of(self.obs_dim) || obs.is_empty() {
            return Err(ActorError::Dimension(format!("{} observation values are not whole rows of {}", obs.len(), self.obs_dim)));
        }
        if let Some(i) = obs.iter().position(|v| !v.is_finite()) {
            return Err(ActorError::Dimension(format!("observation value {} (row {}) is {}", i % self.obs_dim, i / self.obs_dim, obs[i])));
        }
        Ok(obs.len() / self.obs_dim)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mapless_proto::v1::{NamedTensor, ProtocolVersion};
    use rand::SeedableRng;

    fn tensor(name: &str, shape: &[u64], values: &[f32]) -> NamedTensor {
        NamedTensor::from_f32(name, shape.to_vec(), values).unwrap()
    }

    /// obs 2 → hidden 2 → hidden 2 → K, with weights chosen so the output is easy by hand.
    fn snapshot(algorithm: Algorithm, k: u64) -> WeightsSnapshot {
        let mut s = WeightsSnapshot {
            protocol_version: ProtocolVersion::V1 as i32,
            version: 7,
            algorithm: algorithm as i32,
            created_unix_ms: 0,
            obs_dim: 2,
            act_dim: 1,
            tensors: vec![
                // h0 = relu([x0 + x1, x0 − x1])
                tensor("actor.l0.weight", &[2, 2], &[1.0, 1.0, 1.0, -1.0]),
                tensor("actor.l0.bias", &[2], &[0.0, 0.0]),
                // h1 = relu([2·h0_0, h0_1 + 1])
                tensor("actor.l1.weight", &[2, 2], &[2.0, 0.0, 0.0, 1.0]),
                tensor("actor.l1.bias", &[2], &[0.0, 1.0]),
            ],
            metadata: Default::default(),
        };
        // y_0 = h1_0 − h1_1 (+ for SAC: y_1 = log σ = 0.5·h1_1 − 3)
        let (w, b): (Vec<f32>, Vec<f32>) = if k == 1 { (vec![1.0, -1.0], vec![0.0]) } else { (vec![1.0, -1.0, 0.0, 0.5], vec![0.0, -3.0]) };
        s.tensors.push(tensor("actor.out.weight", &[k, 2], &w));
        s.tensors.push(tensor("actor.out.bias", &[k], &b));
        s
    }

    #[test]
    fn deterministic_policy_matches_the_hand_computed_forward_pass() {
        let mut p = Policy::from_snapshot(&snapshot(Algorithm::Td3, 1)).unwrap();
        // x = (1, 2): h0 = relu(3, −1) = (3, 0); h1 = (6, 1); y = 5.  x = (0.5, 0): h0 = (.5, .5); h1 = (1, 1.5); y = −.5.
        let mut rng = rand_pcg::Pcg64::seed_from_u64(0);
        let mut a = [0.0f32; 2];
        p.act(&[1.0, 2.0, 0.5, 0.0], ActMode::Sample, &mut rng, &mut a).unwrap();
        assert_eq!(a, [5.0f32.tanh(), (-0.5f32).tanh()]);
        assert_eq!(p.version(), 7);
    }

    #[test]
    fn sac_acts_with_tanh_of_the_mean_when_deterministic_and_samples_around_it_otherwise() {
        let mut s = snapshot(Algorithm::Sac, 2);
        s.metadata.insert(META_LOG_STD_MIN.into(), "-20".into());
        s.metadata.insert(META_LOG_STD_MAX.into(), "2".into());
        let mut p = Policy::from_snapshot(&s).unwrap();
        let mut rng = rand_pcg::Pcg64::seed_from_u64(1);
        let mut a = [0.0f32; 1];
        // x = (1, 2): μ = 5, log σ = 0.5 − 3 = −2.5.
        p.act(&[1.0, 2.0], ActMode::Deterministic, &mut rng, &mut a).unwrap();
        assert_eq!(a[0], 5.0f32.tanh());
        // Sampled pre-tanh values have mean 5 and std e^−2.5.
        let n = 20_000;
        let (mut sum, mut sq) = (0.0f64, 0.0f64);
        for _ in 0..n {
            p.act(&[1.0, 2.0], ActMode::Sample, &mut rng, &mut a).unwrap();
            let u = f64::from(a[0]).atanh();
            sum += u;
            sq += u * u;
        }
        let mean = sum / n as f64;
        let std = (sq / n as f64 - mean * mean).sqrt();
        assert!((mean - 5.0).abs() < 0.01, "mean {mean}");
        assert!((std - (-2.5f64).exp()).abs() < 0.005, "std {std}");
    }

    #[test]
    fn sac_log_std_is_clamped_to_the_published_bounds() {
        let mut s = snapshot(Algorithm::Sac, 2);
        s.metadata.insert(META_LOG_STD_MIN.into(), "-1".into());
        s.metadata.insert(META_LOG_STD_MAX.into(), "2".into());
        let mut p = Policy::from_snapshot(&s).unwrap();
        // x = (1, 2): raw log σ = −2.5, clamped to −1 → pre-tanh std e^−1.
        let mut rng = rand_pcg::Pcg64::seed_from_u64(2);
        let mut a = [0.0f32; 1];
        let n = 20_000;
        let (mut sum, mut sq) = (0.0f64, 0.0f64);
        for _ in 0..n {
            p.act(&[0.1, 0.0], ActMode::Sample, &mut rng, &mut a).unwrap();
            // x = (0.1, 0): h0 = (.1, .1), h1 = (.2, 1.1), μ = −0.9.
            let u = f64::from(a[0]).atanh() + 0.9;
            sum += u;
            sq += u * u;
        }
        let std = (sq / n as f64 - (sum / n as f64).powi(2)).sqrt();
        assert!((std - (-1.0f64).exp()).abs() < 0.01, "std {std}");
    }

    #[test]
    fn malformed_snapshots_are_refused_with_the_reason() {
        let cases: Vec<(WeightsSnapshot, &str)> = vec![
            (
                {
                    let mut s = snapshot(Algorithm::Td3, 1);
                    s.tensors.retain(|t| t.name != "actor.l1.bias");
                    s
                },
                "`actor.l1.bias` is missing",
            ),
            (snapshot(Algorithm::Td3, 2), "expected [1, 2]"),
            (snapshot(Algorithm::Sac, 2), "lacks metadata `sac.log_std_min`"),
            (
                {
                    let mut s = snapshot(Algorithm::Td3, 1);
                    s.obs_dim = 3;
                    s
                },
                "`actor.l0.weight` is [2, 2], expected [any, 3]",
            ),
            (
                {
                    let mut s = snapshot(Algorithm::Ddpg, 1);
                    s.tensors[0] = tensor("actor.l0.weight", &[2, 2], &[1.0, f32::NAN, 0.0, 0.0]);
                    s
                },
                "non-finite",
            ),
            (
                {
                    let mut s = snapshot(Algorithm::Td3, 1);
                    s.algorithm = 0;
                    s
                },
                "not a known algorithm",
            ),
        ];
        for (s, want) in cases {
            let err = Policy::from_snapshot(&s).unwrap_err().to_string();
            assert!(err.contains(want), "expected `{want}` in `{err}`");
        }
    }

    #[test]
    fn wrong_observation_shapes_and_nan_are_errors() {
        let mut p = Policy::from_snapshot(&snapshot(Algorithm::Td3, 1)).unwrap();
        let mut rng = rand_pcg::Pcg64::seed_from_u64(0);
        let mut a = [0.0f32; 1];
        assert!(p.act(&[1.0, 2.0, 3.0], ActMode::Sample, &mut rng, &mut a).is_err());
        assert!(p.act(&[1.0, f32::NAN], ActMode::Sample, &mut rng, &mut a).unwrap_err().to_string().contains("NaN"));
        assert!(p.act(&[1.0, 2.0], ActMode::Sample, &mut rng, &mut [0.0; 2]).is_err());
    }
}
