//! GPU exclusive scan against the CPU reference `exclusive_scan_in_place` (the same
//! function the shared crate documents). Exact: integer arithmetic, wrapping on both
//! sides.

use drape_engine::ops::scan::exclusive_scan_host;
use drape_shared::scan::exclusive_scan_in_place;
use drape_tests::{gpu, Pattern};

fn check_length(len: usize) {
    let gpu = gpu();
    for pattern in Pattern::ALL {
        // Full 32-bit values so that long inputs also exercise wrap-around.
        for bits in [8, 32] {
            let data = pattern.generate(len, bits, len as u64 + u64::from(bits));
            let got = exclusive_scan_host(&gpu, &data).expect("GPU scan");
            let mut expected = data.clone();
            exclusive_scan_in_place(&mut expected);
            assert!(got == expected, "scan differs: len {len}, {pattern:?}, {bits}-bit values");
        }
    }
}

#[test]
fn scan_len_0() {
    check_length(0);
}

#[test]
fn scan_len_1() {
    check_length(1);
}

#[test]
fn scan_len_255() {
    check_length(255);
}

#[test]
fn scan_len_256() {
    check_length(256);
}

#[test]
fn scan_len_257() {
    check_length(257);
}

#[test]
fn scan_len_65537() {
    check_length(65_537);
}

#[test]
fn scan_len_4m() {
    check_length(4 << 20);
}

/// Three levels (16M = 16,384 blocks of 1,024, then 16, then 1).
#[test]
fn scan_len_16m() {
    let gpu = gpu();
    let data = Pattern::Random.generate(16 << 20, 32, 99);
    let got = exclusive_scan_host(&gpu, &data).expect("GPU scan");
    let mut expected = data.clone();
    exclusive_scan_in_place(&mut expected);
    assert!(got == expected, "16M scan differs from the CPU reference");
}

/// Lengths at every level boundary: a block, a block of blocks, and one past each.
#[test]
fn scan_level_boundaries() {
    let gpu = gpu();
    for len in [1023, 1024, 1025, 1024 * 1024, 1024 * 1024 + 1] {
        let data = Pattern::Random.generate(len, 16, len as u64);
        let got = exclusive_scan_host(&gpu, &data).expect("GPU scan");
        let mut expected = data.clone();
        exclusive_scan_in_place(&mut expected);
        assert!(got == expected, "scan differs at len {len}");
    }
}
