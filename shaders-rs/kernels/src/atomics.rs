//! SPIR-V atomics, one of the kernels' two `unsafe` modules (with `texel`): spirv-std
//! exposes them as `unsafe fn` because they take raw pointers. Each call passes a
//! reference to one element of a storage buffer (a valid, aligned location for the whole
//! dispatch) or of workgroup memory (for the workgroup's lifetime). Relaxed (no) memory
//! semantics suffice: a storage-buffer total is read only after the dispatch, across a
//! pipeline barrier, and a workgroup-memory one only after the caller's workgroup
//! barrier.
#![allow(unsafe_code)]

use spirv_std::arch::{atomic_compare_exchange, atomic_i_add, atomic_load, atomic_u_max};
use spirv_std::memory::{Scope, Semantics};

// QueueFamily, not Device: under the Vulkan memory model, Device scope needs the
// vulkanMemoryModelDeviceScope feature, and all invocations of a dispatch share a queue.
const DEVICE: u32 = Scope::QueueFamily as u32;
const RELAXED: u32 = Semantics::NONE.bits();

const WORKGROUP: u32 = Scope::Workgroup as u32;

/// `*slot += value` on a workgroup-memory counter (ordered by the caller's barriers).
#[inline]
pub fn add_u32_workgroup(slot: &mut u32, value: u32) {
    // SAFETY: see the module header.
    unsafe { atomic_i_add::<u32, WORKGROUP, RELAXED>(slot, value) };
}

/// `*slot = max(*slot, value)` on a workgroup-memory value.
#[inline]
pub fn max_u32_workgroup(slot: &mut u32, value: u32) {
    // SAFETY: see the module header.
    unsafe { atomic_u_max::<u32, WORKGROUP, RELAXED>(slot, value) };
}

/// `*slot += value` for a u32 counter.
#[inline]
pub fn add_u32(slot: &mut u32, value: u32) {
    fetch_add_u32(slot, value);
}

/// `*slot += value` (wrapping) for a u32 counter; returns the value before the add, so
/// that the caller can see whether its own add wrapped.
#[inline]
pub fn fetch_add_u32(slot: &mut u32, value: u32) -> u32 {
    // SAFETY: see the module header.
    unsafe { atomic_i_add::<u32, DEVICE, RELAXED>(slot, value) }
}

/// `*slot = max(*slot, value)` for a u32 flag or maximum.
#[inline]
pub fn max_u32(slot: &mut u32, value: u32) {
    // SAFETY: see the module header.
    unsafe { atomic_u_max::<u32, DEVICE, RELAXED>(slot, value) };
}

/// `grads[index] += value` in 64-bit fixed point (`drape_shared::fixed_point`): words
/// `2·index` (low) and `2·index + 1` (high); the buffer's last word is the flag a
/// non-finite value raises. Integer adds commute, so the sum's bits do not depend on
/// the order the invocations run in.
#[inline]
pub fn add_fixed(grads: &mut [u32], index: usize, value: f32) {
    if value == 0.0 {
        return;
    }
    if !value.is_finite() {
        let flag = grads.len() - 1;
        max_u32(&mut grads[flag], 1);
        return;
    }
    let [lo, hi] = drape_shared::fixed_point::encode(value);
    let before = fetch_add_u32(&mut grads[2 * index], lo);
    // The low word wrapped: carry one into the high word.
    let carry = if before.wrapping_add(lo) < before {
        1
    } else {
        0
    };
    let high = hi.wrapping_add(carry);
    if high != 0 {
        fetch_add_u32(&mut grads[2 * index + 1], high);
    }
}

/// `grads[index] += value` with a float atomic.
#[cfg(feature = "float-atomics")]
#[inline]
pub fn add_f32(grads: &mut [f32], index: usize, value: f32) {
    if value == 0.0 {
        return;
    }
    // SAFETY: see the module header.
    unsafe { spirv_std::arch::atomic_f_add::<f32, DEVICE, RELAXED>(&mut grads[index], value) };
}

/// `grads[index] += value` on f32 bits stored as u32, by compare-and-swap: for
/// devices without float atomics. Terminates: each failed exchange means another
/// invocation's add succeeded.
#[inline]
pub fn add_f32_cas(grads: &mut [u32], index: usize, value: f32) {
    if value == 0.0 {
        return;
    }
    let slot = &mut grads[index];
    // SAFETY: see the module header.
    let mut old = unsafe { atomic_load::<u32, DEVICE, RELAXED>(slot) };
    loop {
        let new = (f32::from_bits(old) + value).to_bits();
        // SAFETY: see the module header.
        let seen =
            unsafe { atomic_compare_exchange::<u32, DEVICE, RELAXED, RELAXED>(slot, new, old) };
        if seen == old {
            break;
        }
        old = seen;
    }
}

/// How a backward kernel adds into a gradient buffer of [`Word`](GradAdd::Word)s: the
/// kernels are generic over it, and each entry point names one. Zero-sized.
pub trait GradAdd {
    /// The gradient buffer's element: `f32` for float atomics, `u32` for f32 bits or
    /// fixed-point words.
    type Word;
    /// `grads[index] += value` (the buffer's `index`-th gradient, whatever its words).
    fn add(grads: &mut [Self::Word], index: usize, value: f32);
}

/// Float atomics ([`add_f32`]; needs shaderBufferFloat32AtomicAdd).
#[cfg(feature = "float-atomics")]
pub struct FloatAtomics;

#[cfg(feature = "float-atomics")]
impl GradAdd for FloatAtomics {
    type Word = f32;
    #[inline]
    fn add(grads: &mut [f32], index: usize, value: f32) {
        add_f32(grads, index, value);
    }
}

/// Compare-and-swap on f32 bits ([`add_f32_cas`]; any device).
pub struct CompareAndSwap;

impl GradAdd for CompareAndSwap {
    type Word = u32;
    #[inline]
    fn add(grads: &mut [u32], index: usize, value: f32) {
        add_f32_cas(grads, index, value);
    }
}

/// 64-bit fixed point ([`add_fixed`]; bit-identical sums whatever the order).
pub struct FixedPoint;

impl GradAdd for FixedPoint {
    type Word = u32;
    #[inline]
    fn add(grads: &mut [u32], index: usize, value: f32) {
        add_fixed(grads, index, value);
    }
}

/// Adds one splat's 10-float gradient `g` at `grads[10 splat ..]`, written out (no
/// loop: on llvmpipe a loop here would spend 10 of an invocation's 65,535 loop
/// iterations per splat).
#[inline]
pub fn add_splat_grad<A: GradAdd>(
    grads: &mut [A::Word],
    splat: usize,
    g: &[f32; drape_shared::splat::layout::SPLAT_GRAD_FLOATS],
) {
    let base = splat * drape_shared::splat::layout::SPLAT_GRAD_FLOATS;
    drape_shared::each_index!(10, c => {
        A::add(grads, base + c, g[c]);
    });
}
