//! GPU exclusive scan against the CPU reference `exclusive_scan_in_place` (the same
//! function the shared crate documents). Exact: integer arithmetic, wrapping on both
//! sides. Both variants run on every device: the block kernels (GPUs) and the chunk
//! kernels (CPU devices).

use drape_engine::ops::scan::{exclusive_scan_host_with, ExclusiveScan, ScanVariant};
use drape_shared::chunks::{chunk_count, CHUNK_MAX_LEN};
use drape_shared::scan::{exclusive_scan_in_place, SERIAL_SCAN_MAX_LEN};
use drape_tests::{gpu, Pattern};

/// Both variants' scans, which must agree; and the chunk variant's three-dispatch
/// kernels where a chunked scan of this length takes the one-invocation kernel
/// (`scan::chunk_serial`, up to `SERIAL_SCAN_MAX_LEN`).
fn exclusive_scan_host(
    gpu: &drape_engine::Context,
    data: &[u32],
) -> drape_engine::Result<Vec<u32>> {
    let blocks = exclusive_scan_host_with(gpu, ScanVariant::Blocks, data)?;
    let chunks = exclusive_scan_host_with(gpu, ScanVariant::Chunks, data)?;
    assert!(
        blocks == chunks,
        "the block and chunk variants disagree ({} elements)",
        data.len()
    );
    if data.len() as u32 <= SERIAL_SCAN_MAX_LEN {
        let three = three_dispatch_chunk_scan(gpu, data)?;
        assert!(
            three == chunks,
            "the one-invocation and three-dispatch chunk scans disagree ({} elements)",
            data.len()
        );
    }
    Ok(blocks)
}

/// The chunk variant's scan by `chunk_reduce`, `chunk_sums` and `chunk_downsweep`
/// whatever the length.
fn three_dispatch_chunk_scan(
    gpu: &drape_engine::Context,
    data: &[u32],
) -> drape_engine::Result<Vec<u32>> {
    let mut buf = gpu.upload("scan data", data)?;
    let plan = ExclusiveScan::with_variant(gpu, "scan", data.len() as u32, ScanVariant::Chunks)?
        .without_serial();
    let mut rec = gpu.record("three-dispatch chunk scan")?;
    plan.record(&mut rec, &buf, data.len() as u32)?;
    rec.submit_and_wait()?;
    gpu.read_buffer(&mut buf, data.len())
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
            assert!(
                got == expected,
                "scan differs: len {len}, {pattern:?}, {bits}-bit values"
            );
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

/// The longest scan the chunk variant does in one invocation.
#[test]
fn scan_len_65536() {
    check_length(SERIAL_SCAN_MAX_LEN as usize);
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
    // Block boundaries, and chunk ones (chunks are cut in quads of 4 elements): 9
    // elements (3 quads) make 8 chunks, 3 of one quad (the last of one element) and 5
    // empty; 8,193 (2,049 quads) make 9 chunks' worth, rounded up to 16 chunks of 129
    // quads (the last shorter); 64K + 3 make 64 chunks of 257 quads.
    for len in [
        7,
        9,
        1023,
        1024,
        1025,
        8 * 1024 + 1,
        64 * 1024 + 3,
        1024 * 1024,
        1024 * 1024 + 1,
    ] {
        let data = Pattern::Random.generate(len, 16, len as u64);
        let got = exclusive_scan_host(&gpu, &data).expect("GPU scan");
        let mut expected = data.clone();
        exclusive_scan_in_place(&mut expected);
        assert!(got == expected, "scan differs at len {len}");
    }
}

/// A scan of the first `len` elements of a longer buffer leaves the rest as it was, in
/// both variants (the chunk variant's one-invocation and three-dispatch kernels); the
/// chunk kernels move whole quads of 4, so the lengths put the end at each place in a
/// quad (and one chunk's run at a quad's end, one inside).
#[test]
fn scan_leaves_elements_past_len_unchanged() {
    use drape_engine::ops::scan::ExclusiveScan;
    let gpu = gpu();
    for len in [1u32, 2, 3, 4, 5, 1029, 1030, 1031, 65_538] {
        let capacity = len as usize + 11;
        let data = Pattern::Random.generate(capacity, 32, u64::from(len));
        // The chunk variant twice: by one invocation where the length allows, and by
        // the three-dispatch kernels.
        for (variant, serial) in [
            (ScanVariant::Blocks, true),
            (ScanVariant::Chunks, true),
            (ScanVariant::Chunks, false),
        ] {
            let mut buf = gpu.upload("scan data", &data).expect("upload");
            let plan = ExclusiveScan::with_variant(&gpu, "scan", len, variant).expect("plan");
            let plan = if serial { plan } else { plan.without_serial() };
            let mut rec = gpu.record("scan_prefix").expect("record");
            plan.record(&mut rec, &buf, len).expect("record scan");
            rec.submit_and_wait().expect("submit");
            let got = gpu
                .read_buffer::<u32>(&mut buf, capacity)
                .expect("read back");
            let mut expected = data.clone();
            exclusive_scan_in_place(&mut expected[..len as usize]);
            assert!(
                got[..len as usize] == expected[..len as usize],
                "{variant:?} (serial {serial}) len {len}: the scan differs"
            );
            assert!(
                got[len as usize..] == data[len as usize..],
                "{variant:?} (serial {serial}) len {len}: elements past len changed"
            );
        }
    }
}
