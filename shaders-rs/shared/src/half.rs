//! IEEE 754 binary16 ("half") conversions in integer arithmetic, for the half-precision
//! storage knobs of the splatter (`engine-bench trade`).
//!
//! Why not the GLSL `PackHalf2x16`: Vulkan leaves its rounding to the implementation
//! (round to nearest even on llvmpipe, toward zero on some GPUs), so a kernel that
//! packed with it could not be checked bit for bit against the CPU reference. These
//! functions round to nearest, ties to even, on every device and on the host; the
//! unpacking is exact either way (every half is an f32).

/// The binary16 bits (in the low 16 bits) of the half nearest `x`, ties to even:
/// overflow gives ±infinity, values below half the smallest subnormal give ±0, NaN stays
/// NaN (quiet, the payload's high bits kept).
pub fn f32_to_f16_bits(x: f32) -> u32 {
    let b = x.to_bits();
    let sign = (b >> 16) & 0x8000;
    let exp = ((b >> 23) & 0xff) as i32;
    let man = b & 0x007f_ffff;
    if exp == 0xff {
        let nan = if man != 0 { 0x0200 | (man >> 13) } else { 0 };
        return sign | 0x7c00 | nan;
    }
    // The half's biased exponent.
    let e = exp - 127 + 15;
    if e >= 0x1f {
        return sign | 0x7c00;
    }
    if e <= 0 {
        // A subnormal half (or zero): the value is r · 2^-24 with r the significand,
        // implicit bit included, shifted right by 14 - e.
        if e < -10 {
            return sign;
        }
        let m = man | 0x0080_0000;
        let shift = (14 - e) as u32;
        let half = 1u32 << (shift - 1);
        let rem = m & ((1u32 << shift) - 1);
        let mut r = m >> shift;
        if rem > half || (rem == half && (r & 1) == 1) {
            r += 1;
        }
        return sign | r;
    }
    let mut r = ((e as u32) << 10) | (man >> 13);
    let rem = man & 0x1fff;
    // A carry out of the significand moves into the exponent: the next binade, or
    // infinity from the largest finite half, as rounding requires.
    if rem > 0x1000 || (rem == 0x1000 && (r & 1) == 1) {
        r += 1;
    }
    sign | r
}

/// The f32 of the binary16 bits in the low 16 bits of `h` (exact).
pub fn f16_bits_to_f32(h: u32) -> f32 {
    let sign = (h & 0x8000) << 16;
    let exp = (h >> 10) & 0x1f;
    let man = h & 0x03ff;
    if exp == 0x1f {
        return f32::from_bits(sign | 0x7f80_0000 | (man << 13));
    }
    if exp == 0 {
        // Subnormal: man · 2^-24, exact in f32.
        let v = man as f32 * (1.0 / 16_777_216.0);
        return if sign != 0 { -v } else { v };
    }
    f32::from_bits(sign | ((exp + 112) << 23) | (man << 13))
}

/// Two values in one word: `lo` in the low 16 bits, `hi` in the high.
pub fn pack2(lo: f32, hi: f32) -> u32 {
    f32_to_f16_bits(lo) | (f32_to_f16_bits(hi) << 16)
}

/// The two values of a word from [`pack2`].
pub fn unpack2(w: u32) -> [f32; 2] {
    [f16_bits_to_f32(w & 0xffff), f16_bits_to_f32(w >> 16)]
}

/// `x` rounded to the nearest half and back (what half-precision storage keeps).
pub fn round_to_f16(x: f32) -> f32 {
    f16_bits_to_f32(f32_to_f16_bits(x))
}

/// Words of half-precision SH per Gaussian with `coeffs` coefficients per channel:
/// `3 · coeffs` halves, two to a word, the last word's high half 0 when odd.
pub const fn sh_half_words(coeffs: usize) -> usize {
    (3 * coeffs).div_ceil(2)
}

/// Push constants of `splat::pack_sh_half`: Gaussians `[0, count)` of SH with `coeffs`
/// coefficients per channel, one invocation per output word.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(not(target_arch = "spirv"), derive(bytemuck::Pod, bytemuck::Zeroable))]
pub struct ShHalfParams {
    pub count: u32,
    pub coeffs: u32,
    pub _pad: [u32; 2],
}

/// For output word `w` of the packing: the indices of its two SH floats in the
/// `[gaussian][k][channel]` f32 layout (None: the padding half of an odd Gaussian).
pub fn sh_half_sources(w: u32, coeffs: u32) -> (usize, Option<usize>) {
    let words = sh_half_words(coeffs as usize) as u32;
    let floats = 3 * coeffs;
    let g = w / words;
    let j = 2 * (w % words);
    let base = (g * floats) as usize;
    let hi = if j + 1 < floats {
        Some(base + j as usize + 1)
    } else {
        None
    };
    (base + j as usize, hi)
}
