//! Hand-written CPU kernels for the fused update of all three algorithms
//! ([`crate::config::LearnerConfig::fused_update`]): row-major matrix products through the
//! BLAS that libtorch itself calls (`sgemm_`, MKL in the PyPI wheels), two-hidden-layer ReLU
//! bodies with their backward passes written out, and global-norm clipping on raw slices
//! (Adam's host step is [`crate::optim::Adam::step_host`]).
//!
//! Why: at the paper's sizes a SAC update is 267 MFLOP of products, but through autograd each
//! of its many small operations also pays dispatch, allocation and graph bookkeeping; that path
//! reaches 0.5–0.6 of the products' f32 ceiling, this one about 0.8 (`mapless bench learner`
//! prints both; docs/learner.md). Here every layer is one `sgemm` into a reused buffer, and
//! bias, ReLU, its mask and the optimiser are single loops.
//!
//! Layouts are those of [`crate::nets`]: PyTorch's `[out, in]` for [`mlp_specs`] networks
//! (the actor) and input-major `[k, in, out]` stacks for [`stacked_mlp_specs`] (the critics).
//!
//! [`mlp_specs`]: crate::nets::mlp_specs
//! [`stacked_mlp_specs`]: crate::nets::stacked_mlp_specs

use std::os::raw::{c_char, c_int};

use tch::Tensor;

use crate::lanes::Lanes;

unsafe extern "C" {
    /// BLAS single-precision GEMM, Fortran (column-major) interface, LP64 integers; exported
    /// by `libtorch_cpu.so` (MKL) and resolved at link time like every libtorch symbol.
    fn sgemm_(
        transa: *const c_char,
        transb: *const c_char,
        m: *const c_int,
        n: *const c_int,
        k: *const c_int,
        alpha: *const f32,
        a: *const f32,
        lda: *const c_int,
        b: *const f32,
        ldb: *const c_int,
        beta: *const f32,
        c: *mut f32,
        ldc: *const c_int,
    );
}

/// Row-major `C[m, n] = op(A)·op(B) + beta·C`, `op(A)` `[m, k]` (A stored `[k, m]` when
/// `ta`), `op(B)` `[k, n]` (B stored `[n, k]` when `tb`). Panics if a slice is too short —
/// a bug in the caller's sizes, never a data-dependent condition.
#[allow(clippy::too_many_arguments)]
pub fn gemm(ta: bool, tb: bool, m: usize, n: usize, k: usize, a: &[f32], b: &[f32], beta: f32, c: &mut [f32]) {
    assert!(a.len() >= m * k && b.len() >= k * n && c.len() >= m * n, "gemm sizes");
    if m == 0 || n == 0 {
        return;
    }
    if k == 0 {
        c[..m * n].iter_mut().for_each(|v| *v *= beta);
        return;
    }
    // Row-major C is column-major Cᵀ = op(B)ᵀ·op(A)ᵀ: swap the operands.
    let (ta_f, lda_f) = if tb { (b'T', k) } else { (b'N', n) };
    let (tb_f, ldb_f) = if ta { (b'T', m) } else { (b'N', k) };
    let dims = [n, m, k, lda_f, ldb_f, n].map(|v| c_int::try_from(v).expect("gemm dimension fits in i32"));
    let alpha = 1.0f32;
    // SAFETY: the pointers come from slices at least as long as the asserted sizes, the
    // scalars live on this stack frame, and sgemm_ reads/writes only within those bounds.
    unsafe {
        sgemm_((&ta_f as *const u8).cast(), (&tb_f as *const u8).cast(), &dims[0], &dims[1], &dims[2], &alpha, b.as_ptr(), &dims[3], a.as_ptr(), &dims[4], &beta, c.as_mut_ptr(), &dims[5]);
    }
}

/// Where a network's tensors sit in its flat buffer, and how its weights are laid out.
#[derive(Debug, Clone, Copy)]
pub struct Body {
    /// (weight offset, bias offset) of l0, l1, out.
    off: [(usize, usize); 3],
    dims: [(usize, usize); 3],
    /// `[out, in]` (PyTorch, the actor) rather than `[in, out]` (the critic stacks).
    out_major: bool,
    /// Layer normalisation (no gain or bias) of both hidden layers' pre-activations, before
    /// the ReLU, as [`crate::nets::stacked_mlp_forward`]'s `norm`.
    norm: bool,
}

impl Body {
    /// Network `j` of a [`crate::nets::stacked_mlp_specs`] stack of `k`.
    pub fn stacked(j: usize, k: usize, input: usize, hidden: usize, output: usize) -> Self {
        let dims = [(input, hidden), (hidden, hidden), (hidden, output)];
        let mut off = [(0, 0); 3];
        let mut at = 0;
        for (l, &(i, o)) in dims.iter().enumerate() {
            off[l].0 = at + j * i * o;
            at += k * i * o;
            off[l].1 = at + j * o;
            at += k * o;
        }
        Self { off, dims, out_major: false, norm: false }
    }

    /// A [`crate::nets::mlp_specs`] network.
    pub fn single(input: usize, hidden: usize, output: usize) -> Self {
        let dims = [(input, hidden), (hidden, hidden), (hidden, output)];
        let mut off = [(0, 0); 3];
        let mut at = 0;
        for (l, &(i, o)) in dims.iter().enumerate() {
            off[l] = (at, at + i * o);
            at += i * o + o;
        }
        Self { off, dims, out_major: true, norm: false }
    }

    /// The same network with its hidden layers layer-normalised when `norm`.
    pub fn normed(mut self, norm: bool) -> Self {
        self.norm = norm;
        self
    }

    pub fn hidden(&self) -> usize {
        self.dims[1].0
    }

    pub fn output(&self) -> usize {
        self.dims[2].1
    }

    /// `z[rows, o] = x·W + b` for layer `l`.
    fn layer(&self, l: usize, p: &[f32], x: &[f32], rows: usize, z: &mut [f32]) {
        let ((wo, bo), (i, o)) = (self.off[l], self.dims[l]);
        let (w, b) = (&p[wo..wo + i * o], &p[bo..bo + o]);
        for r in z[..rows * o].chunks_exact_mut(o) {
            r.copy_from_slice(b);
        }
        gemm(false, self.out_major, rows, o, i, x, w, 1.0, z);
    }

    /// Forward pass over `rows` rows of `x` (`[rows, input]`), keeping the activations.
    pub fn forward(&self, p: &[f32], x: &[f32], rows: usize, act: &mut Acts) {
        act.resize(rows, self);
        let h = self.hidden();
        self.layer(0, p, x, rows, &mut act.h1);
        if self.norm {
            layer_norm(&mut act.h1, &mut act.n1, &mut act.r1, h);
        }
        relu(&mut act.h1);
        self.layer(1, p, &act.h1, rows, &mut act.h2);
        if self.norm {
            layer_norm(&mut act.h2, &mut act.n2, &mut act.r2, h);
        }
        relu(&mut act.h2);
        self.layer(2, p, &act.h2, rows, &mut act.y);
    }

    /// Backward pass from `dy` (`[rows, output]`, ∂L/∂y) through the activations of the
    /// last [`Body::forward`] on `x`. Weight and bias gradients are *added* to `grad` (same
    /// layout as the parameters) when it is given; with `dx = Some((buf, from))`, ∂L/∂x of
    /// inputs `from..` is written to `buf` (`[rows, input − from]`; `from` > 0 only for stacked
    /// networks). `x` is read only for weight gradients. `scratch` holds the hidden-layer
    /// gradients. With two `lanes`, the hidden layer's weight gradient and input gradient (the
    /// two hidden-by-hidden products) run side by side.
    #[allow(clippy::too_many_arguments)]
    pub fn backward(&self, p: &[f32], x: &[f32], act: &Acts, dy: &[f32], grad: Option<&mut [f32]>, dx: Option<(&mut [f32], usize)>, scratch: &mut Scratch, lanes: &Lanes) {
        let rows = act.rows;
        let h = self.hidden();
        scratch.d2.resize(rows * h, 0.0);
        scratch.d1.resize(rows * h, 0.0);
        let mut grad = grad;
        // out: dh2 = dy·Woutᵀ, masked by ReLU(h2) > 0.
        self.weight_grads(2, &act.h2, dy, rows, grad.as_deref_mut());
        self.input_grad(2, p, dy, rows, &mut scratch.d2, 0);
        mask(&mut scratch.d2, &act.h2);
        if self.norm {
            layer_norm_backward(&mut scratch.d2, &act.n2, &act.r2, h);
        }
        let (d2, d1) = (&scratch.d2, &mut scratch.d1);
        match grad.as_deref_mut() {
            Some(g) => {
                lanes.join(|| self.weight_grads(1, &act.h1, d2, rows, Some(g)), || self.input_grad(1, p, d2, rows, d1, 0));
            }
            None => self.input_grad(1, p, d2, rows, d1, 0),
        }
        mask(&mut scratch.d1, &act.h1);
        if self.norm {
            layer_norm_backward(&mut scratch.d1, &act.n1, &act.r1, h);
        }
        self.weight_grads(0, x, &scratch.d1, rows, grad);
        if let Some((dx, from)) = dx {
            self.input_grad(0, p, &scratch.d1, rows, dx, from);
        }
    }

    /// Adds ∂L/∂W and ∂L/∂b of layer `l` (input `x`, output gradient `dz`) into `grad`.
    fn weight_grads(&self, l: usize, x: &[f32], dz: &[f32], rows: usize, grad: Option<&mut [f32]>) {
        let Some(grad) = grad else { return };
        let ((wo, bo), (i, o)) = (self.off[l], self.dims[l]);
        if self.out_major {
            gemm(true, false, o, i, rows, dz, x, 1.0, &mut grad[wo..wo + i * o]);
        } else {
            gemm(true, false, i, o, rows, x, dz, 1.0, &mut grad[wo..wo + i * o]);
        }
        let gb = &mut grad[bo..bo + o];
        for r in dz[..rows * o].chunks_exact(o) {
            for (g, d) in gb.iter_mut().zip(r) {
                *g += d;
            }
        }
    }

    /// `dx[rows, in − from] = dz·Wᵀ` for layer `l`, inputs `from..` only (`from` > 0 needs the
    /// input-major layout, where those inputs' weights are contiguous rows).
    fn input_grad(&self, l: usize, p: &[f32], dz: &[f32], rows: usize, dx: &mut [f32], from: usize) {
        let (wo, (i, o)) = (self.off[l].0, self.dims[l]);
        assert!(from == 0 || !self.out_major, "input gradients from column {from} need the input-major layout");
        gemm(false, !self.out_major, rows, i - from, o, dz, &p[wo + from * o..wo + i * o], 0.0, dx);
    }
}

/// Activations of one forward pass: `h1`, `h2` after ReLU, the output `y`; with layer
/// normalisation also the normalised pre-activations `n1`, `n2` and each row's 1/σ `r1`, `r2`
/// (empty without it).
#[derive(Debug, Default)]
pub struct Acts {
    pub rows: usize,
    pub h1: Vec<f32>,
    pub h2: Vec<f32>,
    pub y: Vec<f32>,
    pub n1: Vec<f32>,
    pub n2: Vec<f32>,
    pub r1: Vec<f32>,
    pub r2: Vec<f32>,
}

impl Acts {
    fn resize(&mut self, rows: usize, body: &Body) {
        self.rows = rows;
        self.h1.resize(rows * body.hidden(), 0.0);
        self.h2.resize(rows * body.hidden(), 0.0);
        self.y.resize(rows * body.output(), 0.0);
        let (normed, per_row) = if body.norm { (rows * body.hidden(), rows) } else { (0, 0) };
        for v in [&mut self.n1, &mut self.n2] {
            v.resize(normed, 0.0);
        }
        for v in [&mut self.r1, &mut self.r2] {
            v.resize(per_row, 0.0);
        }
    }
}

/// ε of the critics' layer normalisation (here and in [`crate::nets::stacked_mlp_forward`]'s
/// `norm`), PyTorch's `nn.LayerNorm` default.
pub const LAYER_NORM_EPS: f64 = 1e-5;

/// Layer normalisation without gain or bias, row by row over `width` units, in place on `z`:
/// z ← (z − mean)/σ, σ = √(biased variance + ε) ([`LAYER_NORM_EPS`]), the
/// variance of the centred values (two passes). The result is also kept in `n` and each row's
/// 1/σ in `rstd`, for [`layer_norm_backward`]. f32 throughout, with the sums split over 8
/// lanes so that they vectorise.
fn layer_norm(z: &mut [f32], n: &mut [f32], rstd: &mut [f32], width: usize) {
    let eps = LAYER_NORM_EPS as f32;
    let w = width as f32;
    for ((row, out), r) in z.chunks_exact_mut(width).zip(n.chunks_exact_mut(width)).zip(rstd.iter_mut()) {
        let mean = lane_sum(row, |v| v) / w;
        let var = lane_sum(row, |v| (v - mean) * (v - mean)) / w;
        let inv = 1.0 / (var + eps).sqrt();
        for (v, o) in row.iter_mut().zip(out.iter_mut()) {
            *v = (*v - mean) * inv;
            *o = *v;
        }
        *r = inv;
    }
}

/// [`layer_norm`]'s backward, in place on `d` (∂L/∂n in, ∂L/∂z out), row by row:
/// ∂L/∂z = (1/σ)·(∂L/∂n − mean(∂L/∂n) − n·mean(∂L/∂n ⊙ n)).
fn layer_norm_backward(d: &mut [f32], n: &[f32], rstd: &[f32], width: usize) {
    let w = width as f32;
    for ((row, nr), &r) in d.chunks_exact_mut(width).zip(n.chunks_exact(width)).zip(rstd) {
        let mean_d = lane_sum(row, |v| v) / w;
        let mean_dn = lane_sum2(row, nr, |v, x| v * x) / w;
        for (v, &x) in row.iter_mut().zip(nr) {
            *v = r * (*v - mean_d - x * mean_dn);
        }
    }
}

/// Σ f(v) over `values`, in 8 interleaved partial sums (which stay in one vector register; a
/// single running f32 sum cannot be reordered, so it would not vectorise).
#[inline(always)]
fn lane_sum(values: &[f32], f: impl Fn(f32) -> f32) -> f32 {
    lane_sum2(values, values, |v, _| f(v))
}

/// Σ f(a, b) over two equally long slices, pairwise, in the same 8 partial sums as `lane_sum`.
#[inline(always)]
fn lane_sum2(a: &[f32], b: &[f32], f: impl Fn(f32, f32) -> f32) -> f32 {
    debug_assert_eq!(a.len(), b.len());
    let mut acc = [0.0f32; 8];
    let (ac, bc) = (a.chunks_exact(8), b.chunks_exact(8));
    let tail: f32 = ac.remainder().iter().zip(bc.remainder()).map(|(&x, &y)| f(x, y)).sum();
    for (ca, cb) in ac.zip(bc) {
        for ((s, &x), &y) in acc.iter_mut().zip(ca).zip(cb) {
            *s += f(x, y);
        }
    }
    acc.iter().sum::<f32>() + tail
}

/// Reused hidden-layer gradient buffers.
#[derive(Debug, Default)]
pub struct Scratch {
    d1: Vec<f32>,
    d2: Vec<f32>,
}

/// ReLU that keeps NaN (as libtorch's does), so a diverged network still fails the finite-loss
/// check instead of being masked to zero.
fn relu(v: &mut [f32]) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx") {
        // SAFETY: the CPU supports AVX, checked just above.
        unsafe { x86::relu(v) };
        return;
    }
    relu_scalar(v);
}

fn relu_scalar(v: &mut [f32]) {
    for x in v {
        *x = if *x < 0.0 { 0.0 } else { *x };
    }
}

/// ReLU's backward (`threshold_backward`): zero the gradient where the output was ≤ 0.
fn mask(d: &mut [f32], out: &[f32]) {
    assert_eq!(d.len(), out.len(), "mask sizes");
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx") {
        // SAFETY: the CPU supports AVX, checked just above; the lengths are equal.
        unsafe { x86::mask(d, out) };
        return;
    }
    mask_scalar(d, out);
}

fn mask_scalar(d: &mut [f32], out: &[f32]) {
    for (g, &o) in d.iter_mut().zip(out) {
        *g = if o <= 0.0 { 0.0 } else { *g };
    }
}

/// ReLU and its mask in AVX, written out: as plain loops LLVM turns their in-place selects into
/// AVX masked stores, which are microcoded and several times slower on AMD cores.
#[cfg(target_arch = "x86_64")]
mod x86 {
    use std::arch::x86_64::*;

    /// `max(0, x)` with x second: `maxps` returns its second operand when either is NaN, and
    /// for −0.0 — exactly `if x < 0 { 0 } else { x }`.
    #[target_feature(enable = "avx")]
    pub unsafe fn relu(v: &mut [f32]) {
        let zero = _mm256_setzero_ps();
        let mut chunks = v.chunks_exact_mut(8);
        for c in &mut chunks {
            let p = c.as_mut_ptr();
            // SAFETY: `c` holds 8 floats; unaligned loads/stores.
            unsafe { _mm256_storeu_ps(p, _mm256_max_ps(zero, _mm256_loadu_ps(p))) };
        }
        super::relu_scalar(chunks.into_remainder());
    }

    /// `g & (o > 0 or o is NaN)`: the gradient kept unless the output was ≤ 0.
    #[target_feature(enable = "avx")]
    pub unsafe fn mask(d: &mut [f32], out: &[f32]) {
        let zero = _mm256_setzero_ps();
        let mut chunks = d.chunks_exact_mut(8);
        let mut outs = out.chunks_exact(8);
        for (c, o) in (&mut chunks).zip(&mut outs) {
            let p = c.as_mut_ptr();
            // SAFETY: `c` and `o` hold 8 floats each; unaligned loads/stores.
            unsafe {
                let keep = _mm256_cmp_ps::<_CMP_NLE_UQ>(_mm256_loadu_ps(o.as_ptr()), zero);
                _mm256_storeu_ps(p, _mm256_and_ps(_mm256_loadu_ps(p), keep));
            }
        }
        super::mask_scalar(chunks.into_remainder(), outs.remainder());
    }
}

/// Runs `f` compiled for AVX2 when this CPU has it (checked once), else for the baseline
/// x86-64 the crate is built for (SSE2). Adam's host step and the clipping norm then use
/// 8-wide instead of 4-wide vectors; AVX2 alone permits no fused multiply-add, so the results
/// are bit-identical either way.
#[inline(always)]
pub(crate) fn wide<R>(f: impl FnOnce() -> R) -> R {
    #[cfg(target_arch = "x86_64")]
    {
        #[target_feature(enable = "avx2")]
        fn avx2<R>(f: impl FnOnce() -> R) -> R {
            f()
        }
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2, checked just above.
            return unsafe { avx2(f) };
        }
    }
    f()
}

/// The f32 contents of a contiguous CPU tensor, or `None` for anything else.
///
/// Host access goes through the owners of the buffers, never through this function
/// directly: [`crate::nets::ParamSet::host`] / [`crate::nets::ParamSet::host_mut`] (a
/// network's parameters), [`crate::batch::Minibatch::host`] (a batch's columns) and Adam's
/// own moments. Each ties the slice's lifetime to a borrow of its owner, so the borrow checker
/// keeps every write (which needs the owner mutably) away from a live slice.
///
/// # Safety
/// Nothing may write the tensor's bytes (through another tensor sharing its storage, or a
/// [`host_slice_mut`]) while the slice is alive.
pub(crate) unsafe fn host_slice(t: &Tensor) -> Option<&[f32]> {
    if t.device() != tch::Device::Cpu || t.kind() != tch::Kind::Float || !t.is_contiguous() {
        return None;
    }
    let n = t.numel();
    // SAFETY: a contiguous CPU f32 tensor holds `numel` floats at `data_ptr`, alive while
    // `t` is borrowed.
    Some(unsafe { std::slice::from_raw_parts(t.data_ptr() as *const f32, n) })
}

/// Mutable f32 contents of a contiguous CPU tensor, or `None` for anything else. As
/// [`host_slice`], called only by the owners' accessors.
///
/// # Safety
/// The slice must be the only live view of these bytes for its lifetime: no other slice of
/// them, and no tensor operation on a tensor sharing the storage, until it is dropped.
pub(crate) unsafe fn host_slice_mut(t: &mut Tensor) -> Option<&mut [f32]> {
    if t.device() != tch::Device::Cpu || t.kind() != tch::Kind::Float || !t.is_contiguous() {
        return None;
    }
    let n = t.numel();
    // SAFETY: as in `host_slice`; exclusivity is the caller's obligation (see above).
    Some(unsafe { std::slice::from_raw_parts_mut(t.data_ptr() as *mut f32, n) })
}

/// `target ← lerp(target, source, τ)`, Polyak averaging of a target network's flat buffer, with
/// libtorch's two forms of `lerp` (t + τ(s − t) for τ < ½, s − (s − t)(1 − τ) otherwise, so
/// τ = 1 copies exactly), without its fused multiply-add. Each half on its own lane.
pub fn soft_update(target: &mut [f32], source: &[f32], tau: f64, lanes: &Lanes) {
    assert_eq!(target.len(), source.len(), "soft update sizes");
    let tau = tau as f32;
    let half = target.len() / 2;
    let (t0, t1) = target.split_at_mut(half);
    let (s0, s1) = source.split_at(half);
    let run = |target: &mut [f32], source: &[f32]| {
        wide(|| {
            if tau < 0.5 {
                target.iter_mut().zip(source).for_each(|(t, &s)| *t += tau * (s - *t));
            } else {
                let rest = 1.0 - tau;
                target.iter_mut().zip(source).for_each(|(t, &s)| *t = s - (s - *t) * rest);
            }
        })
    };
    lanes.join(|| run(t0, s0), || run(t1, s1));
}

/// Σ g² in f64 over eight interleaved partial sums (one long dependent chain of adds cost ~4 %
/// of a SAC update).
fn sum_squares(g: &[f32]) -> f64 {
    wide(|| {
        let mut acc = [0.0f64; 8];
        let chunks = g.chunks_exact(8);
        let tail = chunks.remainder().iter().map(|&v| f64::from(v) * f64::from(v)).sum::<f64>();
        for c in chunks {
            for (a, &v) in acc.iter_mut().zip(c) {
                *a += f64::from(v) * f64::from(v);
            }
        }
        acc.iter().sum::<f64>() + tail
    })
}

/// Global L2 norm of `g`, and `g` scaled to `max_norm` when above it — what
/// [`crate::optim::clip_grad_norm`] does to a tensor. The norm is summed over the two halves of
/// `g` separately (on two lanes when there are), then added, so it does not depend on the lanes.
pub fn clip_grad_norm(g: &mut [f32], max_norm: f64, lanes: &Lanes) -> f64 {
    let half = g.len() / 2;
    let (g0, g1) = g.split_at_mut(half);
    let (a, b) = lanes.join(|| sum_squares(g0), || sum_squares(g1));
    let norm = (a + b).sqrt();
    let coef = max_norm / (norm + 1e-6);
    if coef < 1.0 {
        let c = coef as f32;
        let scale = |g: &mut [f32]| wide(|| g.iter_mut().for_each(|v| *v *= c));
        lanes.join(|| scale(g0), || scale(g1));
    }
    norm
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nets::{ParamSet, mlp_forward, mlp_specs, stacked_mlp_forward, stacked_mlp_specs};
    use rand::{Rng, SeedableRng};

    fn close(a: &[f32], b: &[f32], tol: f32) {
        assert_eq!(a.len(), b.len());
        for (i, (x, y)) in a.iter().zip(b).enumerate() {
            assert!((x - y).abs() <= tol * (1.0 + y.abs()), "[{i}] {x} vs {y}");
        }
    }

    #[test]
    fn gemm_matches_libtorch_in_every_transpose() {
        let (m, n, k) = (5usize, 3usize, 4usize);
        let t = |r: usize, c: usize, s: f32| Tensor::from_slice(&(0..r * c).map(|i| (i as f32 * s).sin()).collect::<Vec<_>>()).view([r as i64, c as i64]);
        for (ta, tb) in [(false, false), (true, false), (false, true), (true, true)] {
            let a = if ta { t(k, m, 0.7) } else { t(m, k, 0.7) };
            let b = if tb { t(n, k, 1.3) } else { t(k, n, 1.3) };
            let want = (if ta { a.tr() } else { a.shallow_clone() }).mm(&if tb { b.tr() } else { b.shallow_clone() });
            let mut c = vec![1.0f32; m * n];
            let (a, b) = (Vec::<f32>::try_from(&a.contiguous().reshape([-1])).unwrap(), Vec::<f32>::try_from(&b.contiguous().reshape([-1])).unwrap());
            gemm(ta, tb, m, n, k, &a, &b, 1.0, &mut c);
            let want: Vec<f32> = Vec::try_from(&(want + 1.0).reshape([-1])).unwrap();
            close(&c, &want, 1e-5);
        }
    }

    #[test]
    fn forward_and_backward_match_autograd_for_both_layouts() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(3);
        let (rows, input, hidden) = (6usize, 5usize, 8usize);
        let x = Tensor::from_slice(&(0..rows * input).map(|i| (i as f32 * 0.37).cos()).collect::<Vec<_>>()).view([rows as i64, input as i64]).set_requires_grad(true);
        let dy_of = |o: usize| (0..rows * o).map(|i| (i as f32 * 0.11).sin()).collect::<Vec<f32>>();
        // The actor layout.
        let set = ParamSet::new(mlp_specs("a", input as i64, hidden as i64, 3, &mut rng), tch::Device::Cpu).unwrap();
        let body = Body::single(input, hidden, 3);
        // The second network of a two-network critic stack.
        let stack = ParamSet::new(stacked_mlp_specs("c", 2, input as i64, hidden as i64, 1, &mut rng), tch::Device::Cpu).unwrap();
        let second = Body::stacked(1, 2, input, hidden, 1);
        // The same, layer-normalised (`critic_layer_norm`).
        let normed = second.normed(true);
        let cases = [(&set, body, None), (&stack, second, Some(1i64)), (&stack, normed, Some(1i64))];
        for ((set, body, pick), lanes) in cases.into_iter().flat_map(|case| [(case, Lanes::default()), (case, Lanes::started())]) {
            let y = match pick {
                None => mlp_forward(set.params(), &x),
                Some(j) => stacked_mlp_forward(set.params(), &x, true, body.norm).get(j),
            };
            let o = body.output();
            let dy = dy_of(o);
            let loss = (&y * Tensor::from_slice(&dy).view([rows as i64, o as i64])).sum(None);
            let mut inputs: Vec<&Tensor> = set.params().iter().collect();
            inputs.push(&x);
            let grads = Tensor::run_backward(&[loss], &inputs, false, false);
            let want_grad: Vec<f32> = Vec::try_from(&ParamSet::flat_grad(&grads[..grads.len() - 1])).unwrap();
            let want_dx: Vec<f32> = Vec::try_from(&grads[grads.len() - 1].reshape([-1])).unwrap();

            let p = set.host().unwrap();
            let xs: Vec<f32> = Vec::try_from(&x.detach().reshape([-1])).unwrap();
            let mut act = Acts::default();
            body.forward(p, &xs, rows, &mut act);
            let want_y: Vec<f32> = Vec::try_from(&y.detach().reshape([-1])).unwrap();
            close(&act.y, &want_y, 1e-5);
            let mut grad = vec![0.0f32; p.len()];
            let mut dx = vec![0.0f32; rows * input];
            body.backward(p, &xs, &act, &dy, Some(&mut grad), Some((&mut dx, 0)), &mut Scratch::default(), &lanes);
            close(&dx, &want_dx, 1e-5);
            if pick.is_some() {
                // Only the last two inputs' gradients (the critics' action columns).
                let mut tail = vec![0.0f32; rows * 2];
                body.backward(p, &[], &act, &dy, None, Some((&mut tail, input - 2)), &mut Scratch::default(), &lanes);
                let want_tail: Vec<f32> = want_dx.chunks_exact(input).flat_map(|r| r[input - 2..].to_vec()).collect();
                close(&tail, &want_tail, 1e-5);
            }
            // The stack's other network gets no gradient from network 1's output.
            close(&grad, &want_grad, 1e-5);
        }
    }

    #[test]
    fn a_nan_weight_reaches_the_output_as_in_libtorch() {
        // 2 → 3 → 3 → 1, every parameter 0.1 except l1.weight[0, 0] (offset 2·3 + 3).
        let body = Body::single(2, 3, 1);
        let mut p = vec![0.1f32; 2 * 3 + 3 + 3 * 3 + 3 + 3 + 1];
        p[9] = f32::NAN;
        let mut act = Acts::default();
        body.forward(&p, &[1.0, 1.0], 1, &mut act);
        assert!(act.y[0].is_nan(), "ReLU must not turn NaN into 0: {:?}", act.y);
        // ReLU's backward keeps the gradient where the output is NaN (threshold_backward).
        let mut d = vec![1.0f32, 2.0, 3.0];
        mask(&mut d, &[f32::NAN, -1.0, 0.0]);
        assert_eq!(d, vec![1.0, 0.0, 0.0]);
    }

    #[test]
    fn vector_relu_and_mask_agree_with_the_scalar_rule_bit_for_bit() {
        // 8-wide chunks plus a tail, with every special value in both.
        let special = [f32::NAN, -f32::NAN, -0.0, 0.0, f32::INFINITY, f32::NEG_INFINITY, -1e-38, 1e-38, -2.5, 3.5];
        let v: Vec<f32> = (0..37).map(|i| special[(i * 7) % special.len()] * if i % 4 == 3 { -1.0 } else { 1.0 }).collect();
        let scalar_relu = |x: f32| if x < 0.0 { 0.0 } else { x };
        let mut r = v.clone();
        relu(&mut r);
        for (x, y) in v.iter().zip(&r) {
            assert_eq!(scalar_relu(*x).to_bits(), y.to_bits(), "relu({x}) gave {y}");
        }
        let g: Vec<f32> = (0..37).map(|i| i as f32 - 18.5).collect();
        let mut d = g.clone();
        mask(&mut d, &v);
        for ((o, g0), d) in v.iter().zip(&g).zip(&d) {
            let want = if *o <= 0.0 { 0.0 } else { *g0 };
            assert_eq!(want.to_bits(), d.to_bits(), "mask(out {o}) of {g0} gave {d}");
        }
    }

    #[test]
    fn clipping_matches_the_tensor_version() {
        let mut g = vec![3.0f32, 4.0];
        assert!((clip_grad_norm(&mut g, 1.0, &Lanes::ONE) - 5.0).abs() < 1e-9);
        close(&g, &[0.6, 0.8], 1e-6);
        let mut small = vec![0.3f32, 0.4];
        clip_grad_norm(&mut small, 1.0, &Lanes::started());
        assert_eq!(small, vec![0.3, 0.4]);
    }

    #[test]
    fn soft_update_matches_libtorch_lerp_and_copies_at_tau_one() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        let n = 1000; // not a multiple of 8: the vector loop's tail too
        let src: Vec<f32> = (0..n).map(|_| rng.random_range(-3.0..3.0)).collect();
        let dst0: Vec<f32> = (0..n).map(|_| rng.random_range(-3.0..3.0)).collect();
        for tau in [0.001, 0.005, 0.5, 0.9, 1.0] {
            let mut host = dst0.clone();
            soft_update(&mut host, &src, tau, &Lanes::started());
            let mut t = Tensor::from_slice(&dst0);
            let _ = t.lerp_(&Tensor::from_slice(&src), tau);
            close(&host, &Vec::<f32>::try_from(&t).unwrap(), 1e-6);
            if tau == 1.0 {
                assert_eq!(host, src, "τ = 1 is a copy");
            }
        }
        let mut host = dst0.clone();
        soft_update(&mut host, &src, 0.0, &Lanes::ONE);
        assert_eq!(host, dst0, "τ = 0 leaves the target");
    }
}
