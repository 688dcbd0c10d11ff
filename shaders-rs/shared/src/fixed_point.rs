//! Deterministic accumulation: f32 values summed as 64-bit fixed-point integers.
//!
//! Float atomics add in whatever order the GPU schedules the invocations, and f32
//! addition is not associative, so two runs of a scatter-add differ in their last
//! bits (and Adam, which divides by √v, turns that into visible differences within
//! a few steps). Integer addition is associative: each value is rounded once to a
//! multiple of 2^-[`FRACTION_BITS`], held as a two's-complement 64-bit integer in two
//! u32 words `[lo, hi]`, and added with two u32 atomics (the low word's carry goes
//! into the high word), so the sum is the same bits whatever the order. Only u32
//! atomics are needed (every Vulkan device has them; no `shaderInt64`).
//!
//! The price: two atomics per value instead of one, a buffer twice the size, and a
//! resolution of 2^-36 ≈ 1.5e-11 per value added (a gradient smaller than half of that
//! is lost); a sum must stay within ±2^27 ≈ 1.3e8 (one value past it is clamped, a sum
//! past it wraps). A non-finite value cannot be held in an integer: the kernels raise
//! a flag word instead, and [`decode`] of a flagged buffer gives NaN for every value,
//! so that a training step's non-finite guard still sees it.
//!
//! ```
//! use drape_shared::fixed_point::{decode, encode, wrapping_add};
//! let mut sum = [0u32; 2];
//! for v in [0.25f32, -1.5, 3.0e-3, 1.0e6] {
//!     sum = wrapping_add(sum, encode(v));
//! }
//! assert!((decode(sum) - (0.25 - 1.5 + 3.0e-3 + 1.0e6)).abs() < 1e-1);
//! ```

// Called as `Float::floor(x)`: the host has the inherent method, the shader target
// only the trait.
use num_traits::Float;

/// Fractional bits of the fixed-point representation.
pub const FRACTION_BITS: u32 = 36;

/// 2^FRACTION_BITS.
const SCALE: f32 = (1u64 << FRACTION_BITS) as f32;
/// 2^32, the weight of the high word.
const WORD: f32 = 4_294_967_296.0;
/// The largest f32 below 2^63: the largest magnitude [`encode`] holds.
const MAX_MAGNITUDE: f32 = 9_223_371_487_098_961_920.0;
/// Below 2^23 an f32 may have a fraction; from there on it is an integer.
const INTEGRAL: f32 = 8_388_608.0;

/// Push constants of `fixed_point::resolve`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(not(target_arch = "spirv"), derive(bytemuck::Pod, bytemuck::Zeroable))]
pub struct ResolveParams {
    /// Values to resolve (the scratch holds 2·count words and then the flag word).
    pub count: u32,
    pub _pad: [u32; 3],
}

/// u32 words of a scratch buffer for `count` values: two per value and the
/// non-finite flag.
pub const fn scratch_words(count: u32) -> u64 {
    2 * count as u64 + 1
}

/// `value` (finite) rounded to the nearest multiple of 2^-FRACTION_BITS, as `[lo, hi]`.
#[inline]
pub fn encode(value: f32) -> [u32; 2] {
    // Scaling by a power of two is exact; the magnitude's bits below 2^32 are at most
    // 24 significant bits, so the split below is exact too.
    let mut a = (value.abs() * SCALE).min(MAX_MAGNITUDE);
    if a < INTEGRAL {
        a = Float::floor(a + 0.5);
    }
    let hi = Float::floor(a * (1.0 / WORD));
    let lo = a - hi * WORD;
    let magnitude = [lo as u32, hi as u32];
    if value < 0.0 {
        negate(magnitude)
    } else {
        magnitude
    }
}

/// The 64-bit sum of two encoded values (wrapping), as the kernels' atomics form it.
#[inline]
pub fn wrapping_add(a: [u32; 2], b: [u32; 2]) -> [u32; 2] {
    let lo = a[0].wrapping_add(b[0]);
    let carry = if lo < a[0] { 1 } else { 0 };
    [lo, a[1].wrapping_add(b[1]).wrapping_add(carry)]
}

/// The f32 nearest an encoded sum (two roundings: the high and low words' sum, then
/// the scale, which is exact).
#[inline]
pub fn decode(word: [u32; 2]) -> f32 {
    let negative = word[1] >= 0x8000_0000;
    let m = if negative { negate(word) } else { word };
    let magnitude = (m[1] as f32 * WORD + m[0] as f32) * (1.0 / SCALE);
    if negative {
        -magnitude
    } else {
        magnitude
    }
}

/// Two's-complement negation of a 64-bit value held as `[lo, hi]`.
#[inline]
fn negate(word: [u32; 2]) -> [u32; 2] {
    let lo = (!word[0]).wrapping_add(1);
    let carry = if word[0] == 0 { 1 } else { 0 };
    [lo, (!word[1]).wrapping_add(carry)]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn encoding_round_trips_to_the_resolution() {
        let step = 1.0 / SCALE as f64;
        for v in [
            0.0f32, 1.0, -1.0, 0.5, -0.5, 3.7e-11, -3.7e-11, 1.0e-3, -2.5e4, 1.0e8, -1.0e8,
            123.456, -7.0e-6,
        ] {
            let d = decode(encode(v)) as f64;
            // One rounding to the grid (≤ half a step) and one f32 rounding of the result.
            let tol = 0.5 * step + f64::from(v.abs()) * f64::from(f32::EPSILON);
            assert!((d - f64::from(v)).abs() <= tol, "{v} -> {d}");
        }
    }

    #[test]
    fn sums_are_exact_and_order_free() {
        // Values that cancel across the word boundary and across signs.
        let values = [
            1.0e6f32, -3.0e-9, 2.5, -1.0e6, 7.0e-4, -2.5, 4.0e-11, 12.0, -0.125,
        ];
        let exact: i128 = values
            .iter()
            .map(|&v| {
                let [lo, hi] = encode(v);
                i128::from(((u64::from(hi) << 32) | u64::from(lo)) as i64)
            })
            .sum();
        let forward = values
            .iter()
            .fold([0u32; 2], |s, &v| wrapping_add(s, encode(v)));
        let backward = values
            .iter()
            .rev()
            .fold([0u32; 2], |s, &v| wrapping_add(s, encode(v)));
        assert_eq!(forward, backward);
        let got = ((u64::from(forward[1]) << 32) | u64::from(forward[0])) as i64;
        assert_eq!(i128::from(got), exact);
        let want: f64 = values.iter().map(|&v| f64::from(v)).sum();
        // The inputs' own grid rounding (9 × half a step) and one f32 rounding of 12.
        assert!(
            (f64::from(decode(forward)) - want).abs() < 1e-6,
            "{} vs {want}",
            decode(forward)
        );
    }

    #[test]
    fn negative_values_near_zero_keep_their_size() {
        // hi = -1 with lo near 2^32: the case a naive hi·2^32 + lo in f32 cancels to 0.
        let v = -3.0e-9f32;
        let [_, hi] = encode(v);
        assert_eq!(hi, u32::MAX);
        assert!((decode(encode(v)) - v).abs() < 2e-11);
    }

    #[test]
    fn magnitudes_past_the_range_are_clamped_not_wrapped() {
        assert!(decode(encode(1.0e30)) > 1.0e8);
        assert!(decode(encode(-1.0e30)) < -1.0e8);
    }
}
