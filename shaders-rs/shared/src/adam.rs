//! Adam, one element at a time, and the loss kernel's parameters.

/// Push constants of `adam_step`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(not(target_arch = "spirv"), derive(bytemuck::Pod, bytemuck::Zeroable))]
pub struct AdamParams {
    pub len: u32,
    pub lr: f32,
    pub beta1: f32,
    pub beta2: f32,
    pub eps: f32,
    /// `1 - beta1^t` and `1 - beta2^t` for step t (1-based).
    pub bias1: f32,
    pub bias2: f32,
    pub _pad: u32,
}

/// Push constants of `flag_exceeds`: the limit a 64-bit count (two words, low
/// first) may reach before the training step's guard is raised.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(not(target_arch = "spirv"), derive(bytemuck::Pod, bytemuck::Zeroable))]
pub struct ExceedsParams {
    pub limit_low: u32,
    pub limit_high: u32,
    pub _pad: [u32; 2],
}

impl ExceedsParams {
    /// The parameters for `limit`.
    pub fn new(limit: u64) -> Self {
        Self {
            limit_low: limit as u32,
            limit_high: (limit >> 32) as u32,
            _pad: [0; 2],
        }
    }
}

/// Whether the 64-bit count `(low, high)` is past `p`'s limit.
#[inline]
pub fn exceeds(low: u32, high: u32, p: &ExceedsParams) -> bool {
    high > p.limit_high || (high == p.limit_high && low > p.limit_low)
}

/// Push constants of `mse_grad`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(not(target_arch = "spirv"), derive(bytemuck::Pod, bytemuck::Zeroable))]
pub struct LossParams {
    pub len: u32,
    /// Multiplies the gradient (1 / elements for a mean).
    pub scale: f32,
    pub _pad: [u32; 2],
}

/// One Adam step of one parameter: returns (param, m, v). A non-finite gradient
/// leaves the parameter and moments unchanged.
///
/// ```
/// use drape_shared::adam::{adam_update, AdamParams};
/// let p = AdamParams { len: 1, lr: 0.1, beta1: 0.9, beta2: 0.999, eps: 1e-8, bias1: 0.1, bias2: 0.001, _pad: 0 };
/// let (x, _, _) = adam_update(1.0, 2.0, 0.0, 0.0, &p);
/// assert!((x - 0.9).abs() < 1e-6); // the first step moves by lr against the gradient's sign
/// ```
#[inline]
pub fn adam_update(param: f32, grad: f32, m: f32, v: f32, p: &AdamParams) -> (f32, f32, f32) {
    if !grad.is_finite() {
        return (param, m, v);
    }
    let m = p.beta1 * m + (1.0 - p.beta1) * grad;
    let v = p.beta2 * v + (1.0 - p.beta2) * grad * grad;
    let m_hat = m / p.bias1;
    let v_hat = v / p.bias2;
    (
        param - p.lr * m_hat / (num_traits::Float::sqrt(v_hat) + p.eps),
        m,
        v,
    )
}
