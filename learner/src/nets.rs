//! Network bodies for the actor and critic networks.
//!
//! Paper §II-B: every network has two hidden layers with ReLU activations. Their width is not
//! given in the paper; 256 is our inferred default (SPEC §2) and is configurable.
//!
//! ```text
//!   x ─► l0: Linear(input→hidden) ─► ReLU ─► l1: Linear(hidden→hidden) ─► ReLU ─► out: Linear(hidden→output) ─► y
//! ```
//!
//! The output is linear; squashing (tanh for deterministic actors, the tanh-Gaussian head for
//! SAC) belongs to the algorithm, not to this body.
//!
//! Parameters live in a `tch::nn::VarStore` under stable names, `{prefix}.l0.weight`,
//! `{prefix}.l0.bias`, `{prefix}.l1.weight`, `{prefix}.l1.bias`, `{prefix}.out.weight`,
//! `{prefix}.out.bias`; weights are `[out_features, in_features]` as in PyTorch. Checkpoints,
//! published weights and the actors' pure-Rust inference all key on these names, so changing
//! them is a wire-format change.

use tch::{Tensor, nn};

use crate::LearnerError;
use crate::cpu::LAYER_NORM_EPS;

pub use mapless_learner_config::DEFAULT_HIDDEN_WIDTH;

/// Parameter path segment of the first hidden layer.
pub const LAYER_0: &str = "l0";
/// Parameter path segment of the second hidden layer.
pub const LAYER_1: &str = "l1";
/// Parameter path segment of the output layer.
pub const LAYER_OUT: &str = "out";

/// A two-hidden-layer ReLU perceptron. Build it with [`Mlp::builder`].
#[derive(Debug)]
pub struct Mlp {
    l0: nn::Linear,
    l1: nn::Linear,
    out: nn::Linear,
    input_dim: i64,
    hidden_width: i64,
    output_dim: i64,
}

/// Sizes for an [`Mlp`]; `hidden_width` defaults to [`DEFAULT_HIDDEN_WIDTH`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MlpBuilder {
    input_dim: i64,
    hidden_width: i64,
    output_dim: i64,
}

impl Mlp {
    /// Starts an `input_dim → hidden → hidden → output_dim` network.
    pub fn builder(input_dim: i64, output_dim: i64) -> MlpBuilder {
        MlpBuilder { input_dim, hidden_width: DEFAULT_HIDDEN_WIDTH, output_dim }
    }

    /// Width of the network's input.
    pub fn input_dim(&self) -> i64 {
        self.input_dim
    }

    /// Width of both hidden layers.
    pub fn hidden_width(&self) -> i64 {
        self.hidden_width
    }

    /// Width of the network's output.
    pub fn output_dim(&self) -> i64 {
        self.output_dim
    }
}

impl MlpBuilder {
    /// Sets the width of both hidden layers.
    pub fn hidden_width(mut self, width: i64) -> Self {
        self.hidden_width = width;
        self
    }

    /// Creates the parameters under `path` (e.g. `&(vs.root() / "critic")`), drawing from
    /// libtorch's global RNG (`tch::manual_seed`).
    ///
    /// Initialisation is tch's `LinearConfig::default()`: weights Kaiming-uniform with the ReLU
    /// gain, U(±√6/√fan_in), which is √6 times wider than PyTorch's `nn.Linear` default
    /// (U(±1/√fan_in)); biases U(±1/√fan_in) as in PyTorch. The paper (MATLAB) does not say;
    /// choosing per-layer initialisers is left to the algorithms.
    pub fn build(self, path: &nn::Path) -> Result<Mlp, LearnerError> {
        for (what, value) in [("input_dim", self.input_dim), ("hidden_width", self.hidden_width), ("output_dim", self.output_dim)] {
            if value < 1 {
                return Err(LearnerError::InvalidNetwork { name: path.components().collect::<Vec<_>>().join("."), reason: format!("{what} must be at least 1, got {value}") });
            }
        }
        let config = nn::LinearConfig::default();
        Ok(Mlp {
            l0: nn::linear(path / LAYER_0, self.input_dim, self.hidden_width, config),
            l1: nn::linear(path / LAYER_1, self.hidden_width, self.hidden_width, config),
            out: nn::linear(path / LAYER_OUT, self.hidden_width, self.output_dim, config),
            input_dim: self.input_dim,
            hidden_width: self.hidden_width,
            output_dim: self.output_dim,
        })
    }
}

impl nn::Module for Mlp {
    /// `[batch, input_dim] → [batch, output_dim]`.
    fn forward(&self, xs: &Tensor) -> Tensor {
        xs.apply(&self.l0).relu().apply(&self.l1).relu().apply(&self.out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn zero_sized_layers_are_an_error_naming_the_network() {
        let vs = nn::VarStore::new(tch::Device::Cpu);
        let err = Mlp::builder(19, 1).hidden_width(0).build(&(vs.root() / "critic")).unwrap_err();
        assert!(err.to_string().contains("`critic`"), "{err}");
        assert!(err.to_string().contains("hidden_width must be at least 1"), "{err}");
        assert!(vs.variables().is_empty(), "nothing is created on error");
    }
}

// ---------------------------------------------------------------------------------------------
// Flat parameter sets: what the algorithms train.
// ---------------------------------------------------------------------------------------------

/// The parameters of one network (or of a stack of twin networks), kept back to back in one
/// contiguous f32 buffer.
///
/// ```text
///   flat: [ l0.weight | l0.bias | l1.weight | l1.bias | out.weight | out.bias ]
///            ▲ params()[0] is a leaf tensor that shares these bytes (requires grad)
/// ```
///
/// Invariant: every tensor of [`ParamSet::params`] is a gradient-requiring leaf whose storage
/// *is* a slice of [`ParamSet::flat`], so an in-place update of the flat buffer (an optimiser
/// step, a soft target update, a checkpoint restore) is an update of the parameters, with one
/// kernel launch for the whole network. Gradients come back per parameter from
/// `Tensor::run_backward` and are concatenated into one flat gradient
/// ([`ParamSet::flat_grad`], or [`ParamSet::flat_grad_into`] a reused buffer).
/// [`ParamSet::frozen`] are the same views without gradient, for evaluating a network
/// inside another network's loss.
///
/// Why not `tch::nn::VarStore`: its optimiser state cannot be checkpointed (see
/// [`crate::optim`]), and one buffer per network keeps an update's launch count low.
#[derive(Debug)]
pub struct ParamSet {
    flat: Tensor,
    names: Vec<String>,
    shapes: Vec<Vec<i64>>,
    params: Vec<Tensor>,
    /// The same views without gradient ([`ParamSet::frozen`]).
    frozen: Vec<Tensor>,
}

impl ParamSet {
    /// Lays out `specs` (name, shape, initial values in row-major order) in one buffer on
    /// `device`. Value counts must match the shapes (checked).
    pub fn new(specs: Vec<(String, Vec<i64>, Vec<f32>)>, device: tch::Device) -> Result<Self, LearnerError> {
        let mut values = Vec::new();
        let mut names = Vec::with_capacity(specs.len());
        let mut shapes = Vec::with_capacity(specs.len());
        for (name, shape, v) in specs {
            let numel: i64 = shape.iter().product();
            if usize::try_from(numel).ok() != Some(v.len()) {
                return Err(LearnerError::InvalidNetwork { name, reason: format!("shape {shape:?} needs {numel} values, got {}", v.len()) });
            }
            values.extend_from_slice(&v);
            names.push(name);
            shapes.push(shape);
        }
        let flat = Tensor::from_slice(&values).to_device(device);
        let mut set = Self { flat, names, shapes, params: Vec::new(), frozen: Vec::new() };
        (set.params, set.frozen) = set.make_views();
        Ok(set)
    }

    /// A set with the same layout and a copy of the values (a target network), its names'
    /// leading `from` replaced by `to` (`critic.l0.weight` → `target_critic.l0.weight`).
    pub fn duplicate_as(&self, from: &str, to: &str) -> Self {
        let names = self
            .names
            .iter()
            .map(|n| match n.strip_prefix(from) {
                Some(rest) => format!("{to}{rest}"),
                None => n.clone(),
            })
            .collect();
        let mut set = Self { flat: self.flat.detach().copy(), names, shapes: self.shapes.clone(), params: Vec::new(), frozen: Vec::new() };
        (set.params, set.frozen) = set.make_views();
        set
    }

    /// `(params, frozen)`: per-parameter views of `flat`, the first requiring gradient.
    fn make_views(&self) -> (Vec<Tensor>, Vec<Tensor>) {
        let mut offset = 0;
        self.shapes
            .iter()
            .map(|shape| {
                let numel: i64 = shape.iter().product();
                let view = self.flat.narrow(0, offset, numel).view(shape.as_slice());
                offset += numel;
                // Two `detach`es: two tensor objects on the same bytes, so that setting
                // `requires_grad` on one leaves the other without.
                (view.detach().set_requires_grad(true), view.detach())
            })
            .unzip()
    }

    /// The parameters in layout order, for forward passes and `run_backward`.
    pub fn params(&self) -> &[Tensor] {
        &self.params
    }

    /// The parameters as views that do not require gradient: a forward pass through them
    /// records no weight-gradient work, while gradients still flow to the inputs (a critic
    /// evaluated inside the actor's loss). They share storage with [`ParamSet::params`], so
    /// they always hold the current values.
    pub fn frozen(&self) -> &[Tensor] {
        &self.frozen
    }

    /// The flat buffer (no gradient). Modify it only under `no_grad`.
    pub fn flat(&self) -> &Tensor {
        &self.flat
    }

    /// The flat buffer as host memory, for the fused CPU updates; `None` unless it is a CPU
    /// f32 buffer. The slice borrows this set, so nothing can write the buffer while it lives:
    /// every write goes through `&mut self` (an optimiser step through the owning
    /// `algo::Trained`, a soft update, a restore), and the set never hands out an owning handle
    /// to its storage.
    pub fn host(&self) -> Option<&[f32]> {
        // SAFETY: see above; a shared borrow of the set excludes every writer.
        unsafe { crate::cpu::host_slice(&self.flat) }
    }

    /// [`ParamSet::host`], writable: the set is borrowed exclusively for the slice's life.
    pub fn host_mut(&mut self) -> Option<&mut [f32]> {
        // SAFETY: the exclusive borrow of the set excludes every other view of the buffer
        // made through it (the per-parameter views are not used while the slice lives: that
        // would need the set).
        unsafe { crate::cpu::host_slice_mut(&mut self.flat) }
    }

    /// Total number of parameters.
    pub fn numel(&self) -> i64 {
        self.flat.size()[0]
    }

    /// Names in layout order.
    pub fn names(&self) -> &[String] {
        &self.names
    }

    /// Shapes in layout order.
    pub fn shapes(&self) -> &[Vec<i64>] {
        &self.shapes
    }

    /// Concatenates per-parameter gradients (as returned by `run_backward` on
    /// [`ParamSet::params`]) into one flat gradient.
    pub fn flat_grad(grads: &[Tensor]) -> Tensor {
        let flat: Vec<Tensor> = grads.iter().map(|g| g.reshape([-1])).collect();
        Tensor::cat(&flat, 0)
    }

    /// [`ParamSet::flat_grad`] written into `out` (flat, [`ParamSet::numel`] values), which
    /// saves allocating a network-sized buffer per step.
    pub fn flat_grad_into(grads: &[Tensor], out: &Tensor) {
        let flat: Vec<Tensor> = grads.iter().map(|g| g.reshape([-1])).collect();
        let _ = Tensor::cat_out(out, &flat, 0);
    }

    /// θ_t ← θ (a hard copy, e.g. initialising a target network).
    pub fn copy_from(&mut self, src: &ParamSet) {
        let _guard = tch::no_grad_guard();
        self.flat.copy_(&src.flat);
    }

    /// θ_t ← (1 − τ)·θ_t + τ·θ, the soft target update (paper §II-A; SPEC τ). One kernel
    /// (`lerp_`: θ_t + τ(θ − θ_t)).
    pub fn soft_update_from(&mut self, src: &ParamSet, tau: f64) {
        let _guard = tch::no_grad_guard();
        let _ = self.flat.lerp_(&src.flat, tau);
    }

    /// `(name, CPU f32 copy)` for every parameter.
    pub fn named_cpu(&self) -> Vec<(String, Tensor)> {
        self.names.iter().zip(&self.params).map(|(n, p)| (n.clone(), p.detach().to(tch::Device::Cpu).copy())).collect()
    }

    /// Overwrites the parameter called `name` with `value` (same shape). `Ok(false)` when
    /// this set has no such name.
    pub fn set(&mut self, name: &str, value: &Tensor) -> Result<bool, String> {
        let Some(i) = self.names.iter().position(|n| n == name) else {
            return Ok(false);
        };
        if value.size() != self.shapes[i] {
            return Err(format!("tensor `{name}` has shape {:?}, this network needs {:?}", value.size(), self.shapes[i]));
        }
        let _guard = tch::no_grad_guard();
        let mut p = self.params[i].shallow_clone();
        p.copy_(&value.to_kind(tch::Kind::Float).to_device(self.flat.device()));
        Ok(true)
    }

    /// Overwrites every parameter with the tensor of the same name from `lookup`; a missing
    /// name or another shape is an error naming it, and then nothing was changed.
    pub fn load_named(&mut self, lookup: &dyn Fn(&str) -> Option<Tensor>) -> Result<(), String> {
        let mut found = Vec::with_capacity(self.names.len());
        for (name, shape) in self.names.iter().zip(&self.shapes) {
            let t = lookup(name).ok_or_else(|| format!("tensor `{name}` is missing"))?;
            if &t.size() != shape {
                return Err(format!("tensor `{name}` has shape {:?}, this network needs {shape:?}", t.size()));
            }
            found.push(t);
        }
        let _guard = tch::no_grad_guard();
        for (p, t) in self.params.iter().zip(&found) {
            let mut p = p.shallow_clone();
            p.copy_(t);
        }
        Ok(())
    }
}

/// PyTorch's `nn.Linear` default initialisation, drawn from a Rust PRNG so that it is
/// reproducible and independent of libtorch's global RNG: weight and bias both
/// U(−1/√fan_in, 1/√fan_in) (`kaiming_uniform_(a=√5)` reduces to this bound).
fn linear_init(rng: &mut impl rand::Rng, fan_in: i64, count: i64) -> Vec<f32> {
    let bound = 1.0 / (fan_in as f64).sqrt();
    (0..count).map(|_| rng.random_range(-bound..bound) as f32).collect()
}

/// Parameter specs of one `input → hidden → hidden → output` ReLU MLP under `prefix`, in
/// PyTorch layout (weights `[out, in]`): `{prefix}.l0.weight`, `{prefix}.l0.bias`, … — the
/// names of the module docs. Initialised as PyTorch's `nn.Linear`.
pub fn mlp_specs(prefix: &str, input: i64, hidden: i64, output: i64, rng: &mut impl rand::Rng) -> Vec<(String, Vec<i64>, Vec<f32>)> {
    let mut specs = Vec::with_capacity(6);
    for (layer, fan_in, fan_out) in [(LAYER_0, input, hidden), (LAYER_1, hidden, hidden), (LAYER_OUT, hidden, output)] {
        specs.push((format!("{prefix}.{layer}.weight"), vec![fan_out, fan_in], linear_init(rng, fan_in, fan_out * fan_in)));
        specs.push((format!("{prefix}.{layer}.bias"), vec![fan_out], linear_init(rng, fan_in, fan_out)));
    }
    specs
}

/// Parameter specs of `k` MLPs of the same shape stacked along a leading axis, for
/// [`stacked_mlp_forward`]. Layout is *input-major* so a batched matmul needs no transpose:
/// `{prefix}.l0.weight [k, input, hidden]`, `{prefix}.l0.bias [k, 1, hidden]`, … ,
/// `{prefix}.out.weight [k, hidden, output]`, `{prefix}.out.bias [k, 1, output]`.
/// Network j is initialised exactly as an `nn.Linear` stack would be (j = 0 first).
/// Used for the critics, which are never published, so this layout is internal to
/// checkpoints.
pub fn stacked_mlp_specs(prefix: &str, k: i64, input: i64, hidden: i64, output: i64, rng: &mut impl rand::Rng) -> Vec<(String, Vec<i64>, Vec<f32>)> {
    let layers = [(LAYER_0, input, hidden), (LAYER_1, hidden, hidden), (LAYER_OUT, hidden, output)];
    let mut w: Vec<Vec<f32>> = vec![Vec::new(); 3];
    let mut b: Vec<Vec<f32>> = vec![Vec::new(); 3];
    for _ in 0..k {
        for (i, &(_, fan_in, fan_out)) in layers.iter().enumerate() {
            // Drawn as [out, in] like nn.Linear, stored transposed as [in, out].
            let wt = linear_init(rng, fan_in, fan_out * fan_in);
            let (fi, fo) = (fan_in as usize, fan_out as usize);
            let mut t = vec![0.0f32; fi * fo];
            for o in 0..fo {
                for j in 0..fi {
                    t[j * fo + o] = wt[o * fi + j];
                }
            }
            w[i].extend(t);
            b[i].extend(linear_init(rng, fan_in, fan_out));
        }
    }
    let mut specs = Vec::with_capacity(6);
    for (i, (layer, fan_in, fan_out)) in layers.into_iter().enumerate() {
        specs.push((format!("{prefix}.{layer}.weight"), vec![k, fan_in, fan_out], std::mem::take(&mut w[i])));
        specs.push((format!("{prefix}.{layer}.bias"), vec![k, 1, fan_out], std::mem::take(&mut b[i])));
    }
    specs
}

/// Forward pass of an [`mlp_specs`] network: `[B, input] → [B, output]`
/// (`relu(x·W0ᵀ + b0)`, `relu(h·W1ᵀ + b1)`, `h·Woutᵀ + bout`).
pub fn mlp_forward(p: &[Tensor], x: &Tensor) -> Tensor {
    let mut h = x.linear(&p[0], Some(&p[1]));
    let _ = h.relu_();
    let mut h = h.linear(&p[2], Some(&p[3]));
    let _ = h.relu_();
    h.linear(&p[4], Some(&p[5]))
}

/// Forward pass of a [`stacked_mlp_specs`] stack of `k` networks on the same input:
/// `[B, input] → [k, B, output]`.
///
/// `fused`: each layer is one `baddbmm` over all `k` networks (3 matmul launches in all);
/// otherwise each network runs on its own (`3k` `addmm` launches, then a `stack`). Same
/// parameters and the same result up to float rounding.
///
/// `norm`: each hidden layer's pre-activations are normalised per sample over the layer's
/// units (layer normalisation without gain or bias, ε [`LAYER_NORM_EPS`]) before the ReLU
/// (`LearnerConfig::critic_layer_norm`).
pub fn stacked_mlp_forward(p: &[Tensor], x: &Tensor, fused: bool, norm: bool) -> Tensor {
    let k = p[0].size()[0];
    let hidden = p[0].size()[2];
    let act = |h: Tensor| {
        let mut h = if norm { h.layer_norm([hidden], None::<Tensor>, None::<Tensor>, LAYER_NORM_EPS, false) } else { h };
        let _ = h.relu_();
        h
    };
    if fused {
        let size = x.size();
        let xs = x.unsqueeze(0).expand([k, size[0], size[1]], false);
        let h = act(p[1].baddbmm(&xs, &p[0], 1.0, 1.0));
        let h = act(p[3].baddbmm(&h, &p[2], 1.0, 1.0));
        p[5].baddbmm(&h, &p[4], 1.0, 1.0)
    } else {
        let outs: Vec<Tensor> = (0..k)
            .map(|j| {
                let layer = |i: usize, h: &Tensor| p[i + 1].get(j).addmm(h, &p[i].get(j));
                let h = act(layer(0, x));
                let h = act(layer(2, &h));
                layer(4, &h)
            })
            .collect();
        Tensor::stack(&outs, 0)
    }
}

#[cfg(test)]
mod param_tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn flat_buffer_updates_are_parameter_updates_and_grads_flatten_in_layout_order() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(1);
        let set = ParamSet::new(mlp_specs("actor", 3, 4, 2, &mut rng), tch::Device::Cpu).unwrap();
        assert_eq!(set.numel(), 3 * 4 + 4 + 4 * 4 + 4 + 4 * 2 + 2);
        assert!(set.params().iter().all(|p| p.requires_grad()));
        assert!(set.frozen().iter().all(|p| !p.requires_grad()));
        {
            let _g = tch::no_grad_guard();
            let _ = set.flat().shallow_clone().fill_(0.5);
        }
        assert_eq!(set.params()[2].double_value(&[1, 1]), 0.5);
        assert_eq!(set.frozen()[2].double_value(&[1, 1]), 0.5);
        let x = Tensor::ones([5, 3], (tch::Kind::Float, tch::Device::Cpu));
        let loss = mlp_forward(set.params(), &x).sum(None);
        let grads = Tensor::run_backward(&[loss], set.params(), false, false);
        let flat = ParamSet::flat_grad(&grads);
        assert_eq!(flat.size(), vec![set.numel()]);
        // out.bias is last: d(sum)/d(bias) = batch size.
        assert_eq!(flat.double_value(&[set.numel() - 1]), 5.0);
        let into = set.flat().zeros_like();
        ParamSet::flat_grad_into(&grads, &into);
        assert!(into.equal(&flat));
        // Through the frozen views, gradient reaches the input only.
        let x = x.set_requires_grad(true);
        let loss = mlp_forward(set.frozen(), &x).sum(None);
        let gx = Tensor::run_backward(&[&loss], &[&x], false, false);
        let gp = Tensor::run_backward(&[&mlp_forward(set.params(), &x).sum(None)], &[&x], false, false);
        assert!(gx[0].allclose(&gp[0], 1e-6, 1e-6, false));
    }

    #[test]
    fn fused_and_sequential_stacked_forwards_agree() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(2);
        let set = ParamSet::new(stacked_mlp_specs("critic", 2, 5, 8, 1, &mut rng), tch::Device::Cpu).unwrap();
        let x = Tensor::from_slice(&(0..15).map(|i| i as f32 / 7.0 - 1.0).collect::<Vec<_>>()).view([3, 5]);
        for norm in [false, true] {
            let a = stacked_mlp_forward(set.params(), &x, true, norm);
            let b = stacked_mlp_forward(set.params(), &x, false, norm);
            assert_eq!(a.size(), vec![2, 3, 1]);
            assert!(a.allclose(&b, 1e-6, 1e-6, false));
        }
        // Normalisation changes the result (so the flag is not ignored).
        assert!(!stacked_mlp_forward(set.params(), &x, true, true).allclose(&stacked_mlp_forward(set.params(), &x, true, false), 1e-4, 1e-4, false));
    }
}
