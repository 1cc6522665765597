//! Proof that tch links, loads libtorch (via the rpath from build.rs, no LD_LIBRARY_PATH) and
//! trains: a SAC-critic-sized network takes real Adam steps on the CPU.

use mapless_learner::{Device, LearnerError, Mlp, TorchThreads};
use tch::nn::{self, Module, OptimizerConfig};
use tch::{Kind, Tensor};

/// Critic input: the default observation (7 beams: 2·7 + 3 = 17 floats, SPEC "Observation")
/// plus the 2 action floats.
const CRITIC_INPUT: i64 = 17 + 2;
/// Paper Table I minibatch.
const BATCH: i64 = 128;
/// Paper Table I critic learning rate.
const CRITIC_LR: f64 = 5e-4;
const STEPS: usize = 50;

/// A smooth, bounded target of all 19 inputs, with a non-linear part an MLP has to learn:
/// y = sin(x·a) + 0.5·tanh(x·b), with `a`, `b` fixed random directions of unit norm.
fn smooth_target(xs: &Tensor) -> Tensor {
    let a = Tensor::randn([CRITIC_INPUT, 1], (Kind::Float, tch::Device::Cpu));
    let b = Tensor::randn([CRITIC_INPUT, 1], (Kind::Float, tch::Device::Cpu));
    let a = &a / a.norm();
    let b = &b / b.norm();
    xs.matmul(&a).sin() + 0.5 * xs.matmul(&b).tanh()
}

fn mse(net: &Mlp, xs: &Tensor, ys: &Tensor) -> Tensor {
    net.forward(xs).mse_loss(ys, tch::Reduction::Mean)
}

fn value(t: &Tensor) -> f64 {
    t.double_value(&[])
}

#[test]
fn sac_sized_gradient_step_reduces_loss_on_fixed_target() {
    TorchThreads::default().apply().unwrap();
    tch::manual_seed(0);

    let vs = nn::VarStore::new(tch::Device::Cpu);
    let critic = Mlp::builder(CRITIC_INPUT, 1).build(&(vs.root() / "critic")).unwrap();
    let xs = Tensor::randn([BATCH, CRITIC_INPUT], (Kind::Float, tch::Device::Cpu));
    let ys = smooth_target(&xs);
    let mut adam = nn::Adam::default().build(&vs, CRITIC_LR).unwrap();

    let initial = tch::no_grad(|| value(&mse(&critic, &xs, &ys)));
    assert!(initial.is_finite() && initial > 0.1, "initial loss {initial} should be sizeable");

    let mut losses = Vec::with_capacity(STEPS);
    for _ in 0..STEPS {
        let loss = mse(&critic, &xs, &ys);
        adam.backward_step(&loss);
        losses.push(tch::no_grad(|| value(&mse(&critic, &xs, &ys))));
    }

    let last = losses[STEPS - 1];
    eprintln!("critic MSE: initial {initial:.4}, 1 step {:.4}, {STEPS} steps {last:.4}", losses[0]);
    assert!(losses[0] < initial, "one Adam step should lower the loss: {initial} -> {}", losses[0]);
    assert!(last < 0.5 * initial, "after {STEPS} steps the loss should at least halve: {initial} -> {last} ({losses:?})");
}

#[test]
fn mlp_parameters_have_the_stable_names_and_pytorch_shapes() {
    let vs = nn::VarStore::new(tch::Device::Cpu);
    let net = Mlp::builder(CRITIC_INPUT, 1).build(&(vs.root() / "critic")).unwrap();
    assert_eq!((net.input_dim(), net.hidden_width(), net.output_dim()), (19, 256, 1));

    let mut shapes: Vec<(String, Vec<i64>)> = vs.variables().into_iter().map(|(name, t)| (name, t.size())).collect();
    shapes.sort();
    let expected = [
        ("critic.l0.bias", vec![256]),
        ("critic.l0.weight", vec![256, 19]),
        ("critic.l1.bias", vec![256]),
        ("critic.l1.weight", vec![256, 256]),
        ("critic.out.bias", vec![1]),
        ("critic.out.weight", vec![1, 256]),
    ];
    let expected: Vec<(String, Vec<i64>)> = expected.into_iter().map(|(n, s)| (n.to_owned(), s)).collect();
    assert_eq!(shapes, expected);

    let out = net.forward(&Tensor::zeros([BATCH, CRITIC_INPUT], (Kind::Float, tch::Device::Cpu)));
    assert_eq!(out.size(), [BATCH, 1]);
}

#[test]
fn mlp_hidden_width_is_configurable() {
    let vs = nn::VarStore::new(tch::Device::Cpu);
    Mlp::builder(17, 2).hidden_width(64).build(&(vs.root() / "actor")).unwrap();
    let vars = vs.variables();
    assert_eq!(vars["actor.l0.weight"].size(), [64, 17]);
    assert_eq!(vars["actor.l1.weight"].size(), [64, 64]);
    assert_eq!(vars["actor.out.weight"].size(), [2, 64]);
}

#[test]
fn cuda_device_is_a_clear_error_when_libtorch_sees_no_gpu() {
    let parsed = mapless_learner::device::available("cuda");
    if tch::Cuda::is_available() {
        assert_eq!(parsed.unwrap(), Device::Cuda(0));
        eprintln!("CUDA is available here; the no-GPU error path was not exercised");
        return;
    }
    let err = parsed.unwrap_err();
    assert!(matches!(err, LearnerError::CudaUnavailable { ref spec } if spec == "cuda"), "{err:?}");
    let message = err.to_string();
    assert!(message.contains("no CUDA device") && message.contains("use `cpu`"), "{message}");
    // And an explicit ordinal fails the same way, before any tensor is created.
    assert!(matches!(mapless_learner::device::available("cuda:1"), Err(LearnerError::CudaUnavailable { .. })));
}

/// build.rs must keep libtorch_cuda.so in the link (see there); without it CUDA is never
/// available, silently. Checked by looking at what this test process has loaded.
#[cfg(target_os = "linux")]
#[test]
fn cuda_backend_is_loaded_whenever_libtorch_ships_one() {
    let lib_dir = std::path::Path::new(env!("MAPLESS_LIBTORCH_LIB"));
    let maps = std::fs::read_to_string("/proc/self/maps").unwrap();
    let loaded = |name: &str| maps.lines().any(|l| l.ends_with(&format!("/{name}")));
    assert!(loaded("libtorch_cpu.so"), "libtorch_cpu.so should be mapped");
    if lib_dir.join("libtorch_cuda.so").exists() {
        assert!(loaded("libtorch_cuda.so"), "libtorch_cuda.so is in {lib_dir:?} but not loaded");
    } else {
        eprintln!("CPU-only libtorch in {lib_dir:?}; nothing to check");
    }
}
