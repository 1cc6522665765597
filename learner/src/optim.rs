//! Adam over one flat parameter buffer, with state that checkpoints exactly, and global-norm
//! gradient clipping.
//!
//! Why not `tch::nn::Optimizer`: it wraps libtorch's C++ optimiser, whose per-parameter
//! state (Adam's first and second moments and step count) tch does not expose, so a
//! checkpoint could hold the weights but not the optimiser, and a resumed run would restart
//! Adam's moments from zero — not an exact resume. Here the moments are two plain tensors and
//! the step a `u64`, all saved by [`crate::checkpoint`].
//!
//! Why one flat buffer: every network keeps all its parameters back to back in one
//! contiguous tensor (see [`crate::nets::ParamSet`]), so one Adam step is 8 kernel launches
//! for the whole network instead of 8 per parameter tensor — at the paper's sizes (batch 128,
//! 256-wide layers) launches, not arithmetic, dominate a CPU update.
//!
//! The update is PyTorch's `torch.optim.Adam` (single-tensor path, no weight decay, no
//! AMSGrad), with bias correction:
//!
//! ```text
//!   t ← t + 1
//!   m ← m + (1 − β₁)(g − m)                  (= β₁m + (1 − β₁)g; PyTorch: exp_avg.lerp_)
//!   v ← v + (1 − β₂)(g² − v)                 (= β₂v + (1 − β₂)g²)
//!   θ ← θ − (lr / (1 − β₁ᵗ)) · m / (√v / √(1 − β₂ᵗ) + ε)
//! ```
//!
//! The bias corrections are computed in f64 on the host as PyTorch does. Results agree with
//! PyTorch to float rounding (the order of a few f32 multiplications differs, because tch's
//! `addcmul_`/`addcdiv_` take no scale factor).
//!
//! The host step of the fused CPU update (`Adam::step_host`) also stores a moment below
//! f32's smallest normal number as 0, which moves no parameter differently and spares Intel
//! CPUs a microcode assist per such moment per step (`normal_or_zero`). The tensor step
//! ([`Adam::step`], on CUDA and on the autograd path) is PyTorch's as it stands: on a GPU
//! subnormals cost nothing, and the flush would be six more kernel launches per step.

use tch::Tensor;

use crate::config::AdamConfig;

/// Adam state for one flat parameter buffer. See the module docs for the update.
#[derive(Debug)]
pub struct Adam {
    lr: f64,
    cfg: AdamConfig,
    /// First moment, same shape as the parameters.
    exp_avg: Tensor,
    /// Second moment, same shape as the parameters.
    exp_avg_sq: Tensor,
    /// Steps taken (t).
    step: u64,
    /// Work buffer for g² and the denominator (not state).
    scratch: Tensor,
}

impl Adam {
    /// Zero moments for `numel` parameters on `device`.
    pub fn new(numel: i64, device: tch::Device, lr: f64, cfg: AdamConfig) -> Self {
        let opts = (tch::Kind::Float, device);
        Self { lr, cfg, exp_avg: Tensor::zeros([numel], opts), exp_avg_sq: Tensor::zeros([numel], opts), step: 0, scratch: Tensor::zeros([numel], opts) }
    }

    /// The learning rate.
    pub fn lr(&self) -> f64 {
        self.lr
    }

    /// Steps taken so far.
    pub fn steps(&self) -> u64 {
        self.step
    }

    /// One Adam step: `params` (flat, updated in place) along `grad` (same shape).
    pub fn step(&mut self, params: &Tensor, grad: &Tensor) {
        let _guard = tch::no_grad_guard();
        self.step += 1;
        let AdamConfig { beta1, beta2, eps } = self.cfg;
        // i32 is plenty: after 2^31 steps both corrections are 1 to double precision.
        let t = i32::try_from(self.step).unwrap_or(i32::MAX);
        let bias_correction1 = 1.0 - beta1.powi(t);
        let bias_correction2 = 1.0 - beta2.powi(t);
        let step_size = self.lr / bias_correction1;
        let _ = self.exp_avg.lerp_(grad, 1.0 - beta1);
        // g² and then the denominator go to the reused work buffer: no per-step allocation
        // of a network-sized tensor (same kernels, same values as grad.square() / v.sqrt()).
        let _ = grad.square_out(&self.scratch);
        let _ = self.exp_avg_sq.lerp_(&self.scratch, 1.0 - beta2);
        // denom = (√v / √bc2 + ε) · (−1/step_size), so that θ + m/denom = θ − step_size·m/(…).
        let mut denom = self.exp_avg_sq.sqrt_out(&self.scratch);
        let _ = denom.divide_scalar_(bias_correction2.sqrt());
        let _ = denom.g_add_scalar_(eps);
        let _ = denom.g_mul_scalar_(-1.0 / step_size);
        let mut p = params.shallow_clone();
        let _ = p.addcdiv_(&self.exp_avg, &denom);
    }

    /// [`Adam::step`] on host memory, one fused pass: `params` and `grad` are the network's
    /// flat buffers as slices (CPU only; the moments must be CPU tensors, which they are
    /// whenever the parameters are). Same arithmetic in f32 as the tensor version, which
    /// `lerp`s with weight 1 − β < ½ (m + (1 − β)(g − m)).
    /// Each half of the buffer on its own lane (the step is elementwise: same result).
    pub(crate) fn step_host(&mut self, params: &mut [f32], grad: &[f32], lanes: &crate::lanes::Lanes) {
        // SAFETY: the moments are this optimiser's own tensors, never handed out (the
        // checkpoint reads them through `&self`), and `self` is borrowed exclusively here.
        let m = unsafe { crate::cpu::host_slice_mut(&mut self.exp_avg) }.expect("Adam moments on the host");
        let v = unsafe { crate::cpu::host_slice_mut(&mut self.exp_avg_sq) }.expect("Adam moments on the host");
        assert!(m.len() == params.len() && v.len() == params.len() && grad.len() == params.len(), "Adam sizes");
        self.step += 1;
        let AdamConfig { beta1, beta2, eps } = self.cfg;
        let t = i32::try_from(self.step).unwrap_or(i32::MAX);
        let step_size = (self.lr / (1.0 - beta1.powi(t))) as f32;
        let sqrt_bc2 = (1.0 - beta2.powi(t)).sqrt() as f32;
        let (w1, w2, eps) = ((1.0 - beta1) as f32, (1.0 - beta2) as f32, eps as f32);
        let run = |params: &mut [f32], grad: &[f32], m: &mut [f32], v: &mut [f32]| {
            crate::cpu::wide(|| {
                for (((p, &g), m), v) in params.iter_mut().zip(grad).zip(m.iter_mut()).zip(v.iter_mut()) {
                    *m = normal_or_zero(*m + w1 * (g - *m));
                    *v = normal_or_zero(*v + w2 * (g * g - *v));
                    let denom = v.sqrt() / sqrt_bc2 + eps;
                    *p -= step_size * *m / denom;
                }
            })
        };
        let half = params.len() / 2;
        let (p0, p1) = params.split_at_mut(half);
        let (g0, g1) = grad.split_at(half);
        let (m0, m1) = m.split_at_mut(half);
        let (v0, v1) = v.split_at_mut(half);
        lanes.join(|| run(p0, g0, m0, v0), || run(p1, g1, m1, v1));
    }

    /// The moments, for checkpoints: `(exp_avg, exp_avg_sq)`.
    pub fn moments(&self) -> (&Tensor, &Tensor) {
        (&self.exp_avg, &self.exp_avg_sq)
    }

    /// Restores the state written by [`Adam::moments`] and [`Adam::steps`]. The caller
    /// checks shapes.
    pub fn restore(&mut self, exp_avg: &Tensor, exp_avg_sq: &Tensor, step: u64) {
        let _guard = tch::no_grad_guard();
        self.exp_avg.copy_(exp_avg);
        self.exp_avg_sq.copy_(exp_avg_sq);
        self.step = step;
    }
}

/// `x`, or 0 when `x` is subnormal (|x| < 2⁻¹²⁶ ≈ 1.2·10⁻³⁸): [`Adam::step_host`]'s moments.
///
/// Why: a parameter whose gradient is exactly 0 from some step on (a ReLU unit that no row of
/// the minibatches activates) has its first moment shrink by β₁ per step into the subnormal
/// range, where `m + (1 − β₁)(0 − m)` rounds back to `m`: it stays subnormal for good (the
/// second moment follows after ~7·10⁴ steps). Every Adam step then does arithmetic on it, and
/// on Intel CPUs each such operation is a microcode assist of ~100 cycles: SAC at the paper's
/// sizes ran at 0.8× its speed on an Intel Xeon core (AVX-512) (`mapless bench learner`; ~12,700 of the
/// critics' 142,000 first moments subnormal after 1,000 updates). Zeroing them moves nothing
/// else: a subnormal m changes θ by at most lr·2⁻¹²⁶/((1 − β₁)·ε) (the bias correction
/// 1/(1 − β₁ᵗ) is largest at t = 1), ≈ lr·1.2·10⁻²⁹ with the defaults β₁ = 0.9, ε = 10⁻⁸: below
/// half an ulp of any |θ| > 10⁻²¹ for lr ≤ 1; a subnormal v changes the denominator
/// √v/√(1 − β₂ᵗ) + ε by less than 10⁻¹⁷ (β₂ = 0.999), below half an ulp of ε = 10⁻⁸. A larger β₁
/// or a smaller ε scales the first bound up (β₁ = 0.999: ×100). This is what flush-to-zero mode
/// (TensorFlow's and XLA's default on CPU, PyTorch's `torch.set_flush_denormal(True)`) does to
/// these two values, written out (Rust code may not run with the CPU's FTZ/DAZ flags set).
/// The branch-free select vectorises.
#[inline(always)]
fn normal_or_zero(x: f32) -> f32 {
    if x.abs() < f32::MIN_POSITIVE { 0.0 } else { x }
}

/// Scales `grad` in place so that its L2 norm is at most `max_norm`, as
/// `torch.nn.utils.clip_grad_norm_` does for the parameters of one network: coefficient
/// `max_norm / (‖g‖ + 1e-6)`, applied only when below 1. Returns the norm before clipping.
pub fn clip_grad_norm(grad: &mut Tensor, max_norm: f64) -> f64 {
    let _guard = tch::no_grad_guard();
    let norm = grad.norm().double_value(&[]);
    let coef = max_norm / (norm + 1e-6);
    if coef < 1.0 {
        let _ = grad.g_mul_scalar_(coef);
    }
    norm
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Adam by hand in f64 for one scalar parameter.
    fn reference(grads: &[f64], lr: f64, p0: f64) -> f64 {
        let (b1, b2, eps) = (0.9f64, 0.999f64, 1e-8);
        let (mut m, mut v, mut p) = (0.0, 0.0, p0);
        for (i, g) in grads.iter().enumerate() {
            let t = (i + 1) as i32;
            m = b1 * m + (1.0 - b1) * g;
            v = b2 * v + (1.0 - b2) * g * g;
            let mhat = m / (1.0 - b1.powi(t));
            let vhat = v / (1.0 - b2.powi(t));
            p -= lr * mhat / (vhat.sqrt() + eps);
        }
        p
    }

    #[test]
    fn adam_matches_the_textbook_update_with_bias_correction() {
        let p = Tensor::from_slice(&[1.0f32, -2.0]);
        let mut adam = Adam::new(2, tch::Device::Cpu, 0.1, AdamConfig::default());
        let grads = [[0.5f32, -3.0], [0.25, 1.0], [-1.0, 0.1]];
        for g in grads {
            adam.step(&p, &Tensor::from_slice(&g));
        }
        assert_eq!(adam.steps(), 3);
        for (i, p0) in [1.0, -2.0].into_iter().enumerate() {
            let gs: Vec<f64> = grads.iter().map(|g| g[i] as f64).collect();
            let want = reference(&gs, 0.1, p0);
            let got = p.double_value(&[i as i64]);
            assert!((got - want).abs() < 1e-6, "param {i}: {got} vs {want}");
        }
        // First step moves each parameter by exactly lr against the gradient's sign.
        let q = Tensor::from_slice(&[0.0f32]);
        let mut adam = Adam::new(1, tch::Device::Cpu, 0.01, AdamConfig::default());
        adam.step(&q, &Tensor::from_slice(&[-7.0f32]));
        assert!((q.double_value(&[0]) - 0.01).abs() < 1e-7);
    }

    #[test]
    fn host_step_equals_the_tensor_step() {
        let g = [[0.5f32, -3.0, 1e-3], [0.25, 1.0, -2.0], [-1.0, 0.1, 0.0]];
        let p = Tensor::from_slice(&[1.0f32, -2.0, 0.3]);
        let mut a = Adam::new(3, tch::Device::Cpu, 0.1, AdamConfig::default());
        let mut host = vec![1.0f32, -2.0, 0.3];
        let mut b = Adam::new(3, tch::Device::Cpu, 0.1, AdamConfig::default());
        for g in g {
            a.step(&p, &Tensor::from_slice(&g));
            b.step_host(&mut host, &g, &crate::lanes::Lanes::started());
        }
        let want = Vec::<f32>::try_from(&p).unwrap();
        for (x, y) in host.iter().zip(&want) {
            assert!((x - y).abs() <= 1e-6 * (1.0 + y.abs()), "{host:?} vs {want:?}");
        }
        assert_eq!(b.steps(), 3);
        assert!(b.moments().0.allclose(a.moments().0, 1e-6, 1e-7, false));
        assert!(b.moments().1.allclose(a.moments().1, 1e-6, 1e-7, false));
    }

    /// [`Adam::step_host`]'s arithmetic without the flush, element by element in f32: what the
    /// host step would store and do if it kept subnormal moments.
    fn unflushed_host_step(p: &mut [f32], m: &mut [f32], v: &mut [f32], g: &[f32], t: i32, lr: f64) {
        let AdamConfig { beta1, beta2, eps } = AdamConfig::default();
        let step_size = (lr / (1.0 - beta1.powi(t))) as f32;
        let sqrt_bc2 = (1.0 - beta2.powi(t)).sqrt() as f32;
        let (w1, w2, eps) = ((1.0 - beta1) as f32, (1.0 - beta2) as f32, eps as f32);
        for i in 0..p.len() {
            m[i] += w1 * (g[i] - m[i]);
            v[i] += w2 * (g[i] * g[i] - v[i]);
            p[i] -= step_size * m[i] / (v[i].sqrt() / sqrt_bc2 + eps);
        }
    }

    /// Dead ReLU units: one gradient, then exact zeros. The moments shrink by β₁ (β₂) per step
    /// into the subnormal range, where the tensor step and an unflushed replay leave them for
    /// good; the host step stores 0 there, and its parameters stay bit-equal to the replay's
    /// (and within rounding of the tensor step's). 38 elements: `step_host` splits the buffer in
    /// halves even on one lane, and each half (19) runs the vectorised body and a scalar tail.
    #[test]
    fn host_step_stores_no_subnormal_moment_and_moves_parameters_as_the_tensor_step() {
        const N: usize = 38;
        let subnormal = |x: &[f32]| x.iter().filter(|v| v.is_subnormal()).count();
        let moments = |adam: &Adam| {
            let (m, v) = adam.moments();
            (Vec::<f32>::try_from(m).unwrap(), Vec::<f32>::try_from(v).unwrap())
        };
        let p0: Vec<f32> = (0..N).map(|i| (i as f32 - 17.5) * 0.03).collect();
        let first: Vec<f32> = (0..N).map(|i| [1e-3f32, -2.0, 0.37, -4e-5][i % 4] * (1.0 + i as f32 / 8.0)).collect();
        let zero = [0.0f32; N];
        let lr = 1e-3;
        let p = Tensor::from_slice(&p0);
        let mut host = p0.clone();
        let (mut replay, mut rm, mut rv) = (p0.clone(), vec![0.0f32; N], vec![0.0f32; N]);
        let mut a = Adam::new(N as i64, tch::Device::Cpu, lr, AdamConfig::default());
        let mut b = Adam::new(N as i64, tch::Device::Cpu, lr, AdamConfig::default());
        let one = crate::lanes::Lanes::ONE;
        a.step(&p, &Tensor::from_slice(&first));
        b.step_host(&mut host, &first, &one);
        unflushed_host_step(&mut replay, &mut rm, &mut rv, &first, 1, lr);
        let zeros = Tensor::zeros([N as i64], (tch::Kind::Float, tch::Device::Cpu));
        let mut tensor_went_subnormal = false;
        for t in 2..=1_001 {
            a.step(&p, &zeros);
            b.step_host(&mut host, &zero, &one);
            unflushed_host_step(&mut replay, &mut rm, &mut rv, &zero, t, lr);
            let (m, v) = moments(&b);
            assert_eq!(subnormal(&m) + subnormal(&v), 0, "step {t}");
            tensor_went_subnormal |= subnormal(&moments(&a).0) > 0;
        }
        assert!(tensor_went_subnormal, "the tensor step's first moments never went subnormal: the test misses its case");
        assert_eq!(subnormal(&rm), N, "the unflushed replay's first moments all stay subnormal");
        assert_eq!(moments(&b).0, vec![0.0; N]);
        assert_eq!(host, replay, "the flush moved a parameter");
        let want = Vec::<f32>::try_from(&p).unwrap();
        for (x, y) in host.iter().zip(&want) {
            assert!((x - y).abs() <= 1e-6 * (1.0 + y.abs()), "{host:?} vs {want:?}");
        }
        // The second moments (β₂ = 0.999) reach the subnormal range 60,000–90,000 steps later.
        for t in 1_002..=121_001 {
            b.step_host(&mut host, &zero, &one);
            unflushed_host_step(&mut replay, &mut rm, &mut rv, &zero, t, lr);
        }
        assert!(subnormal(&rv) > 0, "the replay's second moments never went subnormal: {rv:?}");
        let (m, v) = moments(&b);
        assert_eq!((m, v), (vec![0.0; N], vec![0.0; N]));
        assert_eq!(host, replay, "the flush moved a parameter");
    }

    #[test]
    fn restored_state_continues_identically() {
        let run = |split: bool| {
            let p = Tensor::from_slice(&[0.3f32, 0.7, -0.1]);
            let mut adam = Adam::new(3, tch::Device::Cpu, 0.05, AdamConfig::default());
            for k in 0..6 {
                if split && k == 3 {
                    let (m, v) = adam.moments();
                    let (m, v, s) = (m.copy(), v.copy(), adam.steps());
                    adam = Adam::new(3, tch::Device::Cpu, 0.05, AdamConfig::default());
                    adam.restore(&m, &v, s);
                }
                let g = Tensor::from_slice(&[k as f32 - 2.0, 1.0 / (k as f32 + 1.0), 0.5]);
                adam.step(&p, &g);
            }
            Vec::<f32>::try_from(&p).unwrap()
        };
        assert_eq!(run(false), run(true));
    }

    #[test]
    fn clipping_scales_only_gradients_above_the_norm() {
        let mut g = Tensor::from_slice(&[3.0f32, 4.0]);
        let norm = clip_grad_norm(&mut g, 1.0);
        assert!((norm - 5.0).abs() < 1e-6);
        let v = Vec::<f32>::try_from(&g).unwrap();
        assert!((v[0] - 0.6).abs() < 1e-5 && (v[1] - 0.8).abs() < 1e-5, "{v:?}");
        let mut small = Tensor::from_slice(&[0.3f32, 0.4]);
        clip_grad_norm(&mut small, 1.0);
        assert_eq!(Vec::<f32>::try_from(&small).unwrap(), vec![0.3, 0.4]);
    }
}
