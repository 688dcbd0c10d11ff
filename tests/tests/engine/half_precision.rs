//! `drape_shared::half` (the conversions of the half-precision storage knobs) against
//! the `half` crate, an independent implementation of IEEE 754 binary16.

use drape_shared::half::{
    f16_bits_to_f32, f32_to_f16_bits, pack2, sh_half_sources, sh_half_words, unpack2,
};

/// Two NaNs agree when both are NaN (payloads may legitimately differ); everything else
/// bit for bit.
fn same_half(a: u32, b: u16) -> bool {
    let nan = |h: u32| (h & 0x7c00) == 0x7c00 && (h & 0x03ff) != 0;
    if nan(u32::from(b)) {
        return nan(a) && (a & 0x8000) == (u32::from(b) & 0x8000);
    }
    a == u32::from(b)
}

#[test]
fn every_half_unpacks_exactly() {
    for h in 0..=u16::MAX {
        let ours = f16_bits_to_f32(u32::from(h));
        let theirs = half::f16::from_bits(h).to_f32();
        assert!(
            ours.to_bits() == theirs.to_bits() || (ours.is_nan() && theirs.is_nan()),
            "half {h:#06x}: {ours:e} vs {theirs:e}"
        );
    }
}

#[test]
fn packing_rounds_to_nearest_even_like_the_half_crate() {
    // Every f32 exponent, with significands on a stride that lands on ties, on values
    // just around them and on the subnormal, overflow and NaN ranges; plus the edges.
    let mut checked = 0u64;
    let mut bits = 0u32;
    loop {
        for b in [
            bits,
            bits.wrapping_add(1),
            bits.wrapping_sub(1),
            bits | 0x1000,
            (bits | 0x1000) + 1,
            (bits | 0x1000) - 1,
        ] {
            let x = f32::from_bits(b);
            let ours = f32_to_f16_bits(x);
            let theirs = half::f16::from_f32(x).to_bits();
            assert!(
                same_half(ours, theirs),
                "f32 {b:#010x} ({x:e}): ours {ours:#06x}, half crate {theirs:#06x}"
            );
            checked += 1;
        }
        match bits.checked_add(4093) {
            Some(next) => bits = next,
            None => break,
        }
    }
    // Every tie: the midpoint of each pair of neighbouring finite halves (exact in f32,
    // which has 13 more significand bits), normal and subnormal, and its neighbours.
    for h in 0..0x7bffu16 {
        let mid = (half::f16::from_bits(h).to_f32() + half::f16::from_bits(h + 1).to_f32()) / 2.0;
        for x in [
            mid,
            -mid,
            f32::from_bits(mid.to_bits() + 1),
            f32::from_bits(mid.to_bits() - 1),
        ] {
            let ours = f32_to_f16_bits(x);
            let theirs = half::f16::from_f32(x).to_bits();
            assert!(same_half(ours, theirs), "{x:e} (between halves {h:#06x} and the next): ours {ours:#06x}, half crate {theirs:#06x}");
        }
    }
    for x in [
        0.0f32,
        -0.0,
        1.0,
        -1.0,
        65504.0,
        65519.99,
        65520.0,
        6.1035156e-5,
        5.9604645e-8,
        2.9802322e-8,
        2.9802326e-8,
        f32::MAX,
        f32::MIN_POSITIVE,
        f32::INFINITY,
        f32::NEG_INFINITY,
        f32::NAN,
    ] {
        let ours = f32_to_f16_bits(x);
        let theirs = half::f16::from_f32(x).to_bits();
        assert!(
            same_half(ours, theirs),
            "{x:e}: ours {ours:#06x}, half crate {theirs:#06x}"
        );
    }
    assert!(checked > 6_000_000, "{checked} values checked");
    let [lo, hi] = unpack2(pack2(0.1, -3.0));
    assert_eq!((lo, hi), (half::f16::from_f32(0.1).to_f32(), -3.0));
}

/// The packing's word layout: every SH float of a Gaussian lands in exactly one half,
/// in order, and an odd count pads the last word's high half.
#[test]
fn sh_half_layout_covers_every_float_once() {
    for coeffs in [1u32, 4, 9, 16] {
        let words = sh_half_words(coeffs as usize) as u32;
        let floats = 3 * coeffs as usize;
        let mut seen = vec![0u32; 3 * floats];
        let mut pads = 0;
        for w in 0..3 * words {
            let (lo, hi) = sh_half_sources(w, coeffs);
            seen[lo] += 1;
            match hi {
                Some(h) => {
                    assert_eq!(h, lo + 1, "coefficients {coeffs}, word {w}");
                    seen[h] += 1;
                }
                None => pads += 1,
            }
        }
        assert!(
            seen.iter().all(|&c| c == 1),
            "coefficients {coeffs}: {seen:?}"
        );
        assert_eq!(
            pads,
            if floats % 2 == 1 { 3 } else { 0 },
            "coefficients {coeffs}"
        );
    }
}
