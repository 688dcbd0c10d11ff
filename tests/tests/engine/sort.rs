//! GPU radix sort against the CPU reference: a stable sort by the low `key_bits` bits
//! (`drape_shared::radix_sort::significant_bits`). Values are the input indices, so
//! exact equality of (key, value) pairs also proves stability. Tolerance: none, the
//! sort is exact. Both variants run on every device: the block kernels (GPUs) and the
//! chunk kernels (CPU devices), whichever `Auto` picks here.

use drape_engine::ops::radix_sort::{sort_pairs_host_with, RadixSort, SortVariant};
use drape_shared::radix_sort::{chunk_count, chunk_len, significant_bits, CHUNK_MAX_LEN};
use drape_tests::{gpu, Pattern};

const VARIANTS: [SortVariant; 2] = [SortVariant::Blocks, SortVariant::Chunks];

fn sort_pairs_host(
    gpu: &drape_engine::Context,
    keys: &[u32],
    values: &[u32],
    bits: u32,
) -> drape_engine::Result<(Vec<u32>, Vec<u32>)> {
    let (k, v) = sort_pairs_host_with(gpu, SortVariant::Blocks, keys, values, bits)?;
    let (ck, cv) = sort_pairs_host_with(gpu, SortVariant::Chunks, keys, values, bits)?;
    assert!(
        k == ck && v == cv,
        "the block and chunk variants disagree ({} keys, {bits} bits)",
        keys.len()
    );
    Ok((k, v))
}

const BITS: [u32; 4] = [1, 8, 16, 32];

fn cpu_reference(keys: &[u32], key_bits: u32) -> (Vec<u32>, Vec<u32>) {
    let mut pairs: Vec<(u32, u32)> = keys.iter().copied().zip(0..).collect();
    pairs.sort_by_key(|&(k, _)| significant_bits(k, key_bits)); // std's sort_by_key is stable
    pairs.into_iter().unzip()
}

/// Every pattern and key width at one length, on one context.
fn check_length(len: usize) {
    let gpu = gpu();
    for pattern in Pattern::ALL {
        for bits in BITS {
            let keys = pattern.generate(len, bits, len as u64 ^ u64::from(bits));
            let values: Vec<u32> = (0..len as u32).collect();
            let (gk, gv) = sort_pairs_host(&gpu, &keys, &values, bits).expect("GPU sort");
            let (ek, ev) = cpu_reference(&keys, bits);
            assert!(gk == ek, "keys differ: len {len}, {pattern:?}, {bits} bits");
            assert!(
                gv == ev,
                "values (input order) differ: len {len}, {pattern:?}, {bits} bits"
            );
        }
    }
}

#[test]
fn sort_len_0() {
    check_length(0);
}

#[test]
fn sort_len_1() {
    check_length(1);
}

#[test]
fn sort_len_255() {
    check_length(255);
}

#[test]
fn sort_len_256() {
    check_length(256);
}

#[test]
fn sort_len_257() {
    check_length(257);
}

#[test]
fn sort_len_65537() {
    check_length(65_537);
}

#[test]
fn sort_len_4m() {
    check_length(4 << 20);
}

#[test]
fn sort_len_16m_random_32_bits() {
    let gpu = gpu();
    let len = 16 << 20;
    // Past 64 chunks of CHUNK_MAX_LEN: the chunk variant cuts this into more chunks.
    assert!(
        chunk_count(len as u32) > 64
            && chunk_len(len as u32, chunk_count(len as u32)) <= CHUNK_MAX_LEN
    );
    let keys = Pattern::Random.generate(len, 32, 16);
    let values: Vec<u32> = (0..len as u32).collect();
    let (ek, ev) = cpu_reference(&keys, 32);
    for variant in VARIANTS {
        let (gk, gv) = sort_pairs_host_with(&gpu, variant, &keys, &values, 32).expect("GPU sort");
        assert!(
            gk == ek && gv == ev,
            "16M random keys differ from the CPU reference ({variant:?})"
        );
    }
}

/// A sort whose length the GPU wrote (`record_bounded`): the first `count` pairs of a
/// larger capacity are sorted (what follows them is scratch: an odd number of passes
/// copies the whole capacity back); a count past the capacity sorts
/// the whole capacity. Both variants, and a count far below the capacity (the chunk
/// variant divides the count, not the capacity, over its chunks).
#[test]
fn bounded_sort_sorts_the_gpu_count() {
    let gpu = gpu();
    let capacity = 300_000u32;
    let keys = Pattern::Random.generate(capacity as usize, 20, 5);
    let values: Vec<u32> = (0..capacity).collect();
    for variant in VARIANTS {
        let plan = RadixSort::with_variant(&gpu, capacity, variant).expect("plan");
        assert_eq!(plan.variant(), variant);
        for count in [
            0u64,
            1,
            4_097,
            123_457,
            u64::from(capacity),
            u64::from(capacity) + 9,
            1 << 33,
        ] {
            let mut key_buf = gpu.upload("keys", &keys).unwrap();
            let mut value_buf = gpu.upload("values", &values).unwrap();
            let count_buf = gpu
                .upload("count", &[count as u32, (count >> 32) as u32])
                .unwrap();
            let mut rec = gpu.record("bounded sort").unwrap();
            plan.record_bounded(&mut rec, &key_buf, &value_buf, capacity, &count_buf, 20)
                .unwrap();
            rec.submit_and_wait().unwrap();
            let gk = gpu
                .read_buffer::<u32>(&mut key_buf, capacity as usize)
                .unwrap();
            let gv = gpu
                .read_buffer::<u32>(&mut value_buf, capacity as usize)
                .unwrap();
            let sorted = count.min(u64::from(capacity)) as usize;
            let (ek, ev) = cpu_reference(&keys[..sorted], 20);
            assert!(
                gk[..sorted] == ek[..] && gv[..sorted] == ev[..],
                "{variant:?}, count {count}: differs from the reference"
            );
        }
    }
}

/// Many duplicates spread over many workgroups: equal keys must keep input order.
#[test]
fn sort_is_stable_across_workgroups() {
    let gpu = gpu();
    let len = 100_003;
    let keys: Vec<u32> = (0..len as u32).map(|i| (i * 7919) % 3).collect();
    let values: Vec<u32> = (0..len as u32).collect();
    let (gk, gv) = sort_pairs_host(&gpu, &keys, &values, 2).expect("GPU sort");
    for w in gk.iter().zip(&gv).collect::<Vec<_>>().windows(2) {
        let ((k0, v0), (k1, v1)) = (w[0], w[1]);
        assert!(
            k0 < k1 || (k0 == k1 && v0 < v1),
            "order broken at key {k0}/{k1}, values {v0}/{v1}"
        );
    }
}

/// With `key_bits` = 8, bits above the eighth do not take part: keys that differ only
/// there keep their input order, and those bits travel with the key unchanged.
#[test]
fn sort_ignores_bits_above_key_bits() {
    let gpu = gpu();
    let keys: Vec<u32> = (0..5000u32)
        .map(|i| (i.wrapping_mul(2_654_435_761)) ^ (i << 8))
        .collect();
    let values: Vec<u32> = (0..5000).collect();
    let (gk, gv) = sort_pairs_host(&gpu, &keys, &values, 8).expect("GPU sort");
    let (ek, ev) = cpu_reference(&keys, 8);
    assert_eq!(gk, ek);
    assert_eq!(gv, ev);
}

/// Zero key bits: nothing to sort by, so nothing moves.
#[test]
fn sort_with_zero_key_bits_is_identity() {
    let gpu = gpu();
    let keys = Pattern::Random.generate(3000, 32, 3);
    let values: Vec<u32> = (0..3000).collect();
    let (gk, gv) = sort_pairs_host(&gpu, &keys, &values, 0).expect("GPU sort");
    assert_eq!(gk, keys);
    assert_eq!(gv, values);
}

/// Keys and values whose bits are every kind of `f32` (NaNs quiet and signalling with
/// payloads, infinities, denormals, -0): the chunk kernels read them through `f32`
/// texel views and must move the bits untouched. Through each set of chunk kernels:
/// texel reads with pairs stored as u64s (devices with `shaderInt64`, lavapipe) or as
/// two u32s (devices without), and storage-buffer reads (buffers past the texel limits).
#[test]
fn chunk_sort_moves_float_special_bits_untouched() {
    let gpu = gpu();
    let special = [
        0x7f80_0001u32,
        0x7fbf_ffff,
        0x7fc0_0000,
        0x7fc0_1234,
        0xffff_ffff,
        0xff80_0001,
        0x7f80_0000,
        0xff80_0000,
        0x0000_0001,
        0x807f_ffff,
        0x8000_0000,
        0,
    ];
    let len = 40_000usize;
    let keys: Vec<u32> = (0..len)
        .map(|i| special[(i * 7) % special.len()] ^ (((i as u32) & 0xff) << 8))
        .collect();
    let values: Vec<u32> = (0..len)
        .map(|i| special[(i * 5 + 3) % special.len()] ^ (i as u32 & 0x3ff))
        .collect();
    let mut expected: Vec<(u32, u32)> = keys.iter().copied().zip(values.iter().copied()).collect();
    expected.sort_by_key(|&(k, _)| k); // stable
    let (ek, ev): (Vec<u32>, Vec<u32>) = expected.into_iter().unzip();
    for (texel_reads, int64_stores) in [(true, true), (true, false), (false, false)] {
        let plan = RadixSort::with_variant(&gpu, len as u32, SortVariant::Chunks).expect("plan");
        let plan = if texel_reads {
            plan
        } else {
            plan.without_texel_reads()
        };
        let plan = if int64_stores {
            plan
        } else {
            plan.without_int64_stores()
        };
        let mut key_buf = gpu.upload("keys", &keys).unwrap();
        let mut value_buf = gpu.upload("values", &values).unwrap();
        let mut rec = gpu.record("special bits sort").unwrap();
        plan.record(&mut rec, &key_buf, &value_buf, len as u32, 32)
            .unwrap();
        rec.submit_and_wait().unwrap();
        let gk = gpu.read_buffer::<u32>(&mut key_buf, len).unwrap();
        let gv = gpu.read_buffer::<u32>(&mut value_buf, len).unwrap();
        assert!(
            gk == ek,
            "keys differ (texel reads {texel_reads}, u64 stores {int64_stores})"
        );
        assert!(
            gv == ev,
            "values differ (texel reads {texel_reads}, u64 stores {int64_stores})"
        );
    }
}

/// The chunk kernels other devices run: those that read storage buffers (where a sort's
/// buffers are past the device's texel-buffer limits; 8 bits: the one-pass kernels) and
/// those that store pairs as two u32s (devices without `shaderInt64`), against the
/// reference, at lengths that leave chunks of odd length and chunks with nothing to do,
/// bounded and not.
#[test]
fn chunk_sort_fallback_kernels_match_the_reference() {
    let gpu = gpu();
    for (len, bits, texel_reads) in [257usize, 65_537].into_iter().flat_map(|len| {
        [
            (len, 8u32, false),
            (len, 16, false),
            (len, 32, false),
            (len, 32, true),
        ]
    }) {
        let keys = Pattern::Random.generate(len, bits, 11 + len as u64);
        let values: Vec<u32> = (0..len as u32).collect();
        let plan = RadixSort::with_variant(&gpu, len as u32, SortVariant::Chunks)
            .expect("plan")
            .without_int64_stores();
        let plan = if texel_reads {
            plan
        } else {
            plan.without_texel_reads()
        };
        let mut key_buf = gpu.upload("keys", &keys).unwrap();
        let mut value_buf = gpu.upload("values", &values).unwrap();
        let count = (len as u32 / 3, 0u32);
        let count_buf = gpu.upload("count", &[count.0, count.1]).unwrap();
        let mut rec = gpu.record("storage-read sort").unwrap();
        plan.record_bounded(&mut rec, &key_buf, &value_buf, len as u32, &count_buf, bits)
            .unwrap();
        rec.submit_and_wait().unwrap();
        let gk = gpu.read_buffer::<u32>(&mut key_buf, len).unwrap();
        let gv = gpu.read_buffer::<u32>(&mut value_buf, len).unwrap();
        let (ek, ev) = cpu_reference(&keys[..count.0 as usize], bits);
        assert!(
            gk[..ek.len()] == ek[..] && gv[..ev.len()] == ev[..],
            "bounded: len {len}, {bits} bits, texel reads {texel_reads}"
        );
        let (sk, sv) = {
            let mut key_buf = gpu.upload("keys", &keys).unwrap();
            let mut value_buf = gpu.upload("values", &values).unwrap();
            let mut rec = gpu.record("storage-read sort").unwrap();
            plan.record(&mut rec, &key_buf, &value_buf, len as u32, bits)
                .unwrap();
            rec.submit_and_wait().unwrap();
            (
                gpu.read_buffer::<u32>(&mut key_buf, len).unwrap(),
                gpu.read_buffer::<u32>(&mut value_buf, len).unwrap(),
            )
        };
        let (ek, ev) = cpu_reference(&keys, bits);
        assert!(
            sk == ek && sv == ev,
            "len {len}, {bits} bits, texel reads {texel_reads}"
        );
    }
}
