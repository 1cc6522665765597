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

/// Hidden-layer width when none is given ([inferred], SPEC §2).
pub const DEFAULT_HIDDEN_WIDTH: i64 = 256;

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
        MlpBuilder {
            input_dim,
            hidden_width: DEFAULT_HIDDEN_WIDTH,
            output_dim,
        }
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
        for (what, value) in [
            ("input_dim", self.input_dim),
            ("hidden_width", self.hidden_width),
            ("output_dim", self.output_dim),
        ] {
            if value < 1 {
                return Err(LearnerError::InvalidNetwork {
                    name: path.components().collect::<Vec<_>>().join("."),
                    reason: format!("{what} must be at least 1, got {value}"),
                });
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
        xs.apply(&self.l0)
            .relu()
            .apply(&self.l1)
            .relu()
            .apply(&self.out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn zero_sized_layers_are_an_error_naming_the_network() {
        let vs = nn::VarStore::new(tch::Device::Cpu);
        let err = Mlp::builder(19, 1)
            .hidden_width(0)
            .build(&(vs.root() / "critic"))
            .unwrap_err();
        assert!(err.to_string().contains("`critic`"), "{err}");
        assert!(
            err.to_string().contains("hidden_width must be at least 1"),
            "{err}"
        );
        assert!(vs.variables().is_empty(), "nothing is created on error");
    }
}
