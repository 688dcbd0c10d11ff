//! GPU exclusive scan against the CPU reference `exclusive_scan_in_place` (the same
//! function the shared crate documents). Exact: integer arithmetic, wrapping on both
//! sides. Both variants run on every device: the block kernels (GPUs) and the chunk
//! kernels (CPU devices).

use drape_engine::ops::scan::{exclusive_scan_host_with, ScanVariant};
use drape_shared::chunks::{chunk_count, CHUNK_MAX_LEN};
use drape_shared::scan::exclusive_scan_in_place;
use drape_tests::{gpu, Pattern};

/// Both variants' scans, which must agree.
fn exclusive_scan_host(gpu: &drape_engine::Context, data: &[u32]) -> drape_engine::Result<Vec<u32>> {
    let blocks = exclusive_scan_host_with(gpu, ScanVariant::Blocks, data)?;
    let chunks = exclusive_scan_host_with(gpu, ScanVariant::Chunks, data)?;
    assert!(blocks == chunks, "the block and chunk variants disagree ({} elements)", data.len());
    Ok(blocks)
}

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

/// Three levels (16M = 16,384 blocks of 1,024, then 16, then 1); 512 chunks of at most
/// `CHUNK_MAX_LEN`.
#[test]
fn scan_len_16m() {
    let gpu = gpu();
    assert!(chunk_count(16 << 20) == 512 && (16 << 20) / 512 <= CHUNK_MAX_LEN);
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
    // Block boundaries, and chunk ones: 9 elements make 8 chunks of 2 (one of 1, then
    // three empty); 8,193 make 9 chunks' worth, rounded up to 16 chunks of 513 (the last
    // shorter); 64K + 3 make 64 chunks of 1,025.
    for len in [7, 9, 1023, 1024, 1025, 8 * 1024 + 1, 64 * 1024 + 3, 1024 * 1024, 1024 * 1024 + 1] {
        let data = Pattern::Random.generate(len, 16, len as u64);
        let got = exclusive_scan_host(&gpu, &data).expect("GPU scan");
        let mut expected = data.clone();
        exclusive_scan_in_place(&mut expected);
        assert!(got == expected, "scan differs at len {len}");
    }
}
