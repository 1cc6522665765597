//! The mapless learner: off-policy actor–critic updates (DDPG, TD3, SAC; SPEC §2) on libtorch
//! through tch, on CPU or CUDA.
//!
//! - [`Device`]: `cpu` / `cuda` / `cuda:N`, checked against what libtorch can see
//!   ([`device::available`]);
//! - [`TorchThreads`]: libtorch's CPU thread pools, set explicitly (default 1 each, because
//!   the learner shares cores with actors and libtorch's threads spin);
//! - [`Mlp`]: the paper's two-hidden-layer ReLU network body with stable parameter names.
//!
//! Building needs libtorch 2.13.0: run `scripts/setup-torch.sh` once; `.cargo/config.toml`
//! points torch-sys at it and `build.rs` bakes its path into test binaries as an rpath.

// `Lanes::ONE` is a const with a `Cell` on purpose: each use is a fresh one-lane value.
#![allow(clippy::borrow_interior_mutable_const)]

pub mod device;
mod error;
mod malloc;
pub mod nets;
mod threads;

// Algorithms and everything they need to learn and resume.
pub mod algo;
pub mod batch;
pub mod ceiling;
pub mod checkpoint;
/// The harness of the `checkpoint_files` fuzz target (fuzz/), run on stable by tests/fuzz_corpora.rs.
pub mod fuzzing;
/// The learner's configuration (`mapless-learner-config`, readable without libtorch).
pub use mapless_learner_config as config;
mod cpu;
pub mod driver;
pub mod envs;
pub mod lanes;
pub mod optim;

// Around the algorithms: replay sources, published weights, metrics files.
pub mod source;
pub mod tensorboard;
pub mod weights;

pub use device::Device;
pub use error::LearnerError;
pub use nets::{Mlp, MlpBuilder};
pub use threads::{DEFAULT_TORCH_THREADS, TorchThreads};
