//! Adam (Kingma and Ba, 2015) in PyTorch's formulation, one parameter at a time, so the same
//! element-wise kernel runs on the CPU and on the GPU. Each parameter group has its own
//! [`AdamConfig`] (the paper uses lr 0.01 for the grids and 1e-5 for the MLPs).
//!
//! The per-step scalars (`beta^t` via [`math::pow_int`], the bias corrections) are computed
//! once per step on the host in an [`AdamStep`] and passed to kernels as plain values.
//! The update of one parameter, with `bc1 = 1 - beta1^t`, `bc2 = 1 - beta2^t`:
//!
//! ```text
//! m     = beta1 * m + (1 - beta1) * g
//! v     = beta2 * v + (1 - beta2) * g * g
//! denom = sqrt(v) / sqrt(bc2) + eps
//! param = param - (lr / bc1) * m / denom
//! ```
//!
//! Every operation is a separately rounded `f32` operation in this order (no `mul_add`), and
//! `sqrt` is the vendored correctly rounded [`math::sqrt`], so CPU and GPU give the same bits.

use crate::{fixed, math, Error};

/// Hyper-parameters of one parameter group.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct AdamConfig {
    /// Learning rate.
    pub lr: f32,
    /// Decay of the first-moment estimate.
    pub beta1: f32,
    /// Decay of the second-moment estimate.
    pub beta2: f32,
    /// Added to the denominator for numerical stability.
    pub eps: f32,
}

impl AdamConfig {
    /// PyTorch's defaults with the given learning rate: betas (0.9, 0.999), eps 1e-8.
    pub const fn new(lr: f32) -> Self {
        Self {
            lr,
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
        }
    }

    /// Changes the learning rate ([`crate::train::backend::Backend::set_adam_lr`] of every backend):
    /// it must be finite and `>= 0`; the moments are not touched.
    pub fn set_lr(&mut self, lr: f32) -> Result<(), crate::Error> {
        if !(lr.is_finite() && lr >= 0.0) {
            return Err(crate::Error::InvalidConfig(
                "learning rate must be finite and >= 0",
            ));
        }
        self.lr = lr;
        Ok(())
    }
}

/// The scalars of one Adam step of one group, computed once on the host and passed to every
/// [`adam_update`] of that step.
///
/// `#[repr(C)]`: it is the tail of the GPU's push-constant block
/// ([`crate::gpu_abi::AdamPush`]).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[repr(C)]
pub struct AdamStep {
    /// Learning rate.
    pub lr: f32,
    /// Decay of the first-moment estimate.
    pub beta1: f32,
    /// Decay of the second-moment estimate.
    pub beta2: f32,
    /// Added to the denominator for numerical stability.
    pub eps: f32,
    /// `1 - beta1^t`.
    pub bias_correction1: f32,
    /// `1 - beta2^t`.
    pub bias_correction2: f32,
}

impl AdamStep {
    /// The scalars of step `t` (`t >= 1` counts the steps taken, this one included; `t = 0`
    /// is treated as 1 so that the bias corrections are never 0). `beta^t` is
    /// [`math::pow_int`], so host and device compute identical values.
    pub fn new(cfg: &AdamConfig, t: u32) -> Self {
        let t = if t == 0 { 1 } else { t };
        Self {
            lr: cfg.lr,
            beta1: cfg.beta1,
            beta2: cfg.beta2,
            eps: cfg.eps,
            bias_correction1: 1.0 - math::pow_int(cfg.beta1, t),
            bias_correction2: 1.0 - math::pow_int(cfg.beta2, t),
        }
    }

    /// The scalars of step `t` with this step's learning rate, betas and epsilon: the bias
    /// corrections recomputed as in [`Self::new`]. The GPU derives each step's bias
    /// corrections this way from its device-side count of accepted steps, so that a step
    /// queued before the previous one's finiteness check is known still uses the CPU's `t`.
    pub fn at(&self, t: u32) -> Self {
        let cfg = AdamConfig {
            lr: self.lr,
            beta1: self.beta1,
            beta2: self.beta2,
            eps: self.eps,
        };
        Self::new(&cfg, t)
    }
}

/// One Adam update of one parameter with gradient `grad` (PyTorch's `torch.optim.Adam` form,
/// see the module documentation). Updates `param` and the moments `m`, `v` in place.
#[inline]
pub fn adam_update(s: &AdamStep, param: &mut f32, m: &mut f32, v: &mut f32, grad: f32) {
    let m_new = s.beta1 * *m + (1.0 - s.beta1) * grad;
    let v_new = s.beta2 * *v + (1.0 - s.beta2) * grad * grad;
    let denom = math::div(math::sqrt(v_new), math::sqrt(s.bias_correction2)) + s.eps;
    let step_size = math::div(s.lr, s.bias_correction1);
    *param -= math::div(step_size * m_new, denom);
    *m = m_new;
    *v = v_new;
}

/// `x` is neither infinite nor NaN (`x - x` is 0 only for finite values; plain arithmetic, so
/// the same test compiles on every target, shaders included).
#[inline]
#[allow(clippy::eq_op)]
pub fn is_finite(x: f32) -> bool {
    x - x == 0.0
}

/// Whether [`adam_update`] would leave the parameter and both moments finite. Computed on
/// copies: nothing is written (the check pass before a step is applied).
#[inline]
pub fn adam_update_is_finite(s: &AdamStep, param: f32, m: f32, v: f32, grad: f32) -> bool {
    let (mut p, mut m, mut v) = (param, m, v);
    adam_update(s, &mut p, &mut m, &mut v, grad);
    is_finite(p) && is_finite(m) && is_finite(v)
}

/// [`adam_update_is_finite`] over a whole group (lengths as [`adam_update_fixed`]'s; a
/// mismatch reads as not finite).
pub fn adam_group_is_finite(
    s: &AdamStep,
    params: &[f32],
    m: &[f32],
    v: &[f32],
    grads: &[i64],
) -> bool {
    let n = params.len();
    if m.len() != n || v.len() != n || grads.len() != n {
        return false;
    }
    let mut i = 0;
    while i < n {
        if !adam_update_is_finite(s, params[i], m[i], v[i], fixed::from_fixed(grads[i])) {
            return false;
        }
        i += 1;
    }
    true
}

/// [`adam_update`] over a whole group whose gradient was accumulated in fixed point: each
/// `grads[i]` is converted with [`fixed::from_fixed`] first.
///
/// Errors: [`Error::Shape`] unless `m`, `v` and `grads` have the length of `params` (nothing is
/// updated then).
pub fn adam_update_fixed(
    s: &AdamStep,
    params: &mut [f32],
    m: &mut [f32],
    v: &mut [f32],
    grads: &[i64],
) -> Result<(), Error> {
    let n = params.len();
    crate::error::check_len("adam first moments", m.len(), n)?;
    crate::error::check_len("adam second moments", v.len(), n)?;
    crate::error::check_len("adam gradients", grads.len(), n)?;
    let mut i = 0;
    while i < n {
        adam_update(
            s,
            &mut params[i],
            &mut m[i],
            &mut v[i],
            fixed::from_fixed(grads[i]),
        );
        i += 1;
    }
    Ok(())
}

#[cfg(test)]
#[allow(clippy::disallowed_methods)] // std's functions as test oracles
mod tests {
    use super::*;

    #[test]
    fn finiteness_check_matches_the_update() {
        let s = AdamStep::new(&AdamConfig::new(0.01), 1);
        // first step: m = 0.1 g, v = 0.001 g^2, the parameter moves by lr (sign of g)
        assert!(adam_update_is_finite(&s, 1.0, 0.0, 0.0, 0.5));
        let (mut p, mut m, mut v) = (1.0f32, 0.0f32, 0.0f32);
        adam_update(&s, &mut p, &mut m, &mut v, 0.5);
        assert!((p - 0.99).abs() < 1e-6, "{p}");
        // lr / (1 - beta1) = 1e38 / 0.1 overflows: the update is not finite
        let huge = AdamStep::new(&AdamConfig::new(1e38), 1);
        assert!(huge.lr.is_finite());
        assert!(!adam_update_is_finite(&huge, 1.0, 0.0, 0.0, 0.5));
        // non-finite inputs never pass
        assert!(!adam_update_is_finite(&s, f32::INFINITY, 0.0, 0.0, 0.5));
        assert!(!adam_update_is_finite(&s, 1.0, f32::NAN, 0.0, 0.5));
        assert!(!is_finite(f32::NAN) && !is_finite(-f32::INFINITY) && is_finite(f32::MAX));
        assert!(adam_group_is_finite(
            &s,
            &[1.0, 2.0],
            &[0.0; 2],
            &[0.0; 2],
            &[5, -7]
        ));
        assert!(!adam_group_is_finite(
            &s,
            &[1.0, 2.0],
            &[0.0; 2],
            &[0.0; 2],
            &[5]
        ));
    }

    #[test]
    fn config_defaults() {
        let c = AdamConfig::new(0.01);
        assert_eq!(c.lr, 0.01);
        assert_eq!((c.beta1, c.beta2, c.eps), (0.9, 0.999, 1e-8));
    }

    #[test]
    #[allow(clippy::excessive_precision)] // the digits spell out exact binary values
    fn step_scalars() {
        let c = AdamConfig::new(1e-5);
        let s = AdamStep::new(&c, 1);
        // 1 - 0.9f32 and 1 - 0.999f32 are exact (Sterbenz): 0.10000002384185791015625 and
        // 0.000999987125396728515625.
        assert_eq!(s.bias_correction1, 0.100_000_024);
        assert_eq!(s.bias_correction1 as f64, 0.100_000_023_841_857_910_156_25);
        assert_eq!(s.bias_correction2 as f64, 0.000_999_987_125_396_728_515_625);
        assert_eq!(s.lr, 1e-5);
        assert_eq!(AdamStep::new(&c, 0), s);
        // t = 2: 1 - 0.9^2 = 0.19, 1 - 0.999^2 = 0.001999 (up to the f32 rounding of beta).
        let s2 = AdamStep::new(&c, 2);
        assert!((s2.bias_correction1 - 0.19).abs() < 1e-7);
        assert!((s2.bias_correction2 - 0.001_999).abs() < 1e-7);
        // Against f64 for t = 1..5000: beta^t by repeated squaring carries at most about t
        // roundings of 2^-24 relative (see math::pow_int), and 1 - beta^t adds one more
        // rounding: |bc - (1 - beta^t)| <= (t + 1) * 2^-24 (absolute, since beta^t <= 1).
        for t in 1..=5000u32 {
            let s = AdamStep::new(&c, t);
            for (bc, beta) in [(s.bias_correction1, c.beta1), (s.bias_correction2, c.beta2)] {
                let exact = 1.0 - (beta as f64).powi(t as i32);
                let tol = (t as f64 + 1.0) * f64::from(f32::EPSILON) * 0.5;
                assert!((bc as f64 - exact).abs() <= tol, "t {t}: {bc} vs {exact}");
            }
        }
        // Large t: the corrections go to 1.
        let s = AdamStep::new(&c, 100_000);
        assert_eq!(s.bias_correction1, 1.0);
        assert!((s.bias_correction2 - 1.0).abs() < 1e-6);
    }

    /// First step by hand, g = 0.5, lr = 0.01, p = 1, m = v = 0:
    /// m = 0.9 * 0 + (1 - 0.9f32) * 0.5 = 0.100000024 * 0.5 = 0.0500000119 (exact);
    /// v = (1 - 0.999f32) * 0.25 = 0.00024999678 (exact, a power-of-two scaling);
    /// sqrt(v) / sqrt(bc2) = sqrt(bc2 / 4) / sqrt(bc2) = 0.5 exactly (correct rounding
    /// commutes with scaling by 4); denom = 0.5 + 1e-8 rounds to 0.5 (half an ULP of 0.5 is
    /// 3e-8); update = (0.01 / 0.100000024) * 0.0500000119 / 0.5 = 0.01 up to rounding
    /// (the two 1.0000002 factors cancel): p = 0.99 within 1 ULP. That is Adam's
    /// `-lr * sign(g)` first step.
    #[test]
    #[allow(clippy::excessive_precision)] // the digits spell out exact binary values
    fn golden_first_step() {
        let s = AdamStep::new(&AdamConfig::new(0.01), 1);
        let (mut p, mut m, mut v) = (1.0f32, 0.0f32, 0.0f32);
        adam_update(&s, &mut p, &mut m, &mut v, 0.5);
        assert_eq!(m as f64, 0.100_000_023_841_857_910_156_25 * 0.5);
        assert_eq!(v as f64, 0.000_999_987_125_396_728_515_625 * 0.25);
        let ulp = 0.99f32.to_bits().abs_diff(p.to_bits());
        assert!(ulp <= 1, "p = {p}");
        // Any gradient: the first step is -lr * g / (|g| + eps) (exactly -lr * sign(g) up to
        // eps), because m / bc1 = g and sqrt(v / bc2) = |g| up to rounding.
        for &g in &[-0.5f32, -3.0, -1e-3, 1e-3, 7.0, 2e-8, -1e-6] {
            let (mut p, mut m, mut v) = (0.0f32, 0.0f32, 0.0f32);
            adam_update(&s, &mut p, &mut m, &mut v, g);
            let gd = g as f64;
            let expect = -0.01 * gd / (gd.abs() + 1e-8);
            assert!((p as f64 - expect).abs() <= 4e-9, "g {g}: {p} vs {expect}");
        }
        // A zero gradient leaves everything at zero.
        let (mut p, mut m, mut v) = (2.0f32, 0.0f32, 0.0f32);
        adam_update(&s, &mut p, &mut m, &mut v, 0.0);
        assert_eq!((p, m, v), (2.0, 0.0, 0.0));
    }

    /// Several steps against a straightforward f64 implementation of the same formula, with
    /// the f32 hyper-parameters and the step's bias corrections widened to f64 (their own
    /// accuracy is tested in `step_scalars`). f32 rounding of m, v, sqrt and the divisions
    /// gives a relative error of a few 1e-7 per step: tolerance after 20 steps 2e-6 relative
    /// for p (|p| ~ 1, floor 1) and v, and 2e-6 times the gradient scale for m (which
    /// crosses zero).
    #[test]
    fn matches_f64_reference() {
        let cfg = AdamConfig::new(0.05);
        let n = 16;
        let mut p: Vec<f32> = (0..n).map(|i| 1.0 - 0.13 * i as f32).collect();
        let mut m = vec![0.0f32; n];
        let mut v = vec![0.0f32; n];
        let mut pd: Vec<f64> = p.iter().map(|&x| x as f64).collect();
        let mut md = vec![0.0f64; n];
        let mut vd = vec![0.0f64; n];
        let (b1, b2, eps, lr) = (
            cfg.beta1 as f64,
            cfg.beta2 as f64,
            cfg.eps as f64,
            cfg.lr as f64,
        );
        for t in 1..=20u32 {
            let s = AdamStep::new(&cfg, t);
            for i in 0..n {
                // A gradient that changes sign and magnitude over steps and parameters.
                let g = ((i as f32 * 0.7 + t as f32 * 0.3).sin()) * (0.1 + i as f32 * 0.05);
                adam_update(&s, &mut p[i], &mut m[i], &mut v[i], g);
                let g = g as f64;
                md[i] = b1 * md[i] + (1.0 - b1) * g;
                vd[i] = b2 * vd[i] + (1.0 - b2) * g * g;
                let bc1 = s.bias_correction1 as f64;
                let bc2 = s.bias_correction2 as f64;
                let denom = vd[i].sqrt() / bc2.sqrt() + eps;
                pd[i] -= lr / bc1 * md[i] / denom;
            }
        }
        for i in 0..n {
            // Scale of parameter i's gradients (m can cross zero, so its error is measured
            // against that scale, not against m itself).
            let gs = 0.1 + i as f64 * 0.05;
            let err_p = (p[i] as f64 - pd[i]).abs();
            assert!(
                err_p <= 2e-6 * pd[i].abs().max(1.0),
                "p[{i}]: {} vs {}",
                p[i],
                pd[i]
            );
            let err_m = (m[i] as f64 - md[i]).abs();
            assert!(err_m <= 2e-6 * gs, "m[{i}]: {} vs {}", m[i], md[i]);
            let err_v = (v[i] as f64 - vd[i]).abs();
            assert!(err_v <= 2e-6 * vd[i], "v[{i}]: {} vs {}", v[i], vd[i]);
        }
        // The parameters actually moved (about lr per step at first).
        assert!((p[0] - 1.0).abs() > 0.05);
    }

    #[test]
    fn fixed_variant_equals_f32_variant() {
        let s = AdamStep::new(&AdamConfig::new(0.01), 3);
        let n = 9;
        let grads: Vec<i64> = (0..n)
            .map(|i| fixed::to_fixed((i as f32 - 4.0) * 0.37 + 1e-6))
            .collect();
        let mut p: Vec<f32> = (0..n).map(|i| i as f32 * 0.1).collect();
        let mut m: Vec<f32> = (0..n).map(|i| i as f32 * -0.01).collect();
        let mut v: Vec<f32> = (0..n).map(|i| i as f32 * 0.002).collect();
        let (mut p2, mut m2, mut v2) = (p.clone(), m.clone(), v.clone());
        adam_update_fixed(&s, &mut p, &mut m, &mut v, &grads).unwrap();
        for i in 0..n {
            let g = fixed::from_fixed(grads[i]);
            adam_update(&s, &mut p2[i], &mut m2[i], &mut v2[i], g);
        }
        let bits = |x: &[f32]| x.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&p), bits(&p2));
        assert_eq!(bits(&m), bits(&m2));
        assert_eq!(bits(&v), bits(&v2));
        assert_ne!(p, (0..n).map(|i| i as f32 * 0.1).collect::<Vec<_>>());
    }

    #[test]
    fn fixed_variant_shape_errors() {
        let s = AdamStep::new(&AdamConfig::new(0.01), 1);
        let mut p = [1.0f32; 3];
        let mut m = [0.0f32; 3];
        let mut v = [0.0f32; 2];
        let g = [1i64; 3];
        assert_eq!(
            adam_update_fixed(&s, &mut p, &mut m, &mut v, &g),
            Err(Error::Shape {
                what: "adam second moments",
                expected: 3,
                got: 2
            })
        );
        assert_eq!(p, [1.0; 3]);
        let mut v = [0.0f32; 3];
        assert!(matches!(
            adam_update_fixed(&s, &mut p, &mut m, &mut v, &g[..2]),
            Err(Error::Shape { .. })
        ));
        let mut m4 = [0.0f32; 4];
        assert!(matches!(
            adam_update_fixed(&s, &mut p, &mut m4, &mut v, &g),
            Err(Error::Shape { .. })
        ));
        assert_eq!(p, [1.0; 3]);
    }
}
