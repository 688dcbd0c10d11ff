//! The recorder binds buffers through each kernel's generated bindings struct (whose
//! fields' types follow the SPIR-V's `NonWritable` declarations), and places barriers
//! from those declared accesses: one only where a command reads or writes what an earlier
//! one wrote since the last barrier, or writes what one read. Synchronization
//! validation is on in every test context, so a derived barrier that is missing shows
//! up as a validation message (and fails the test that caused it).

use drape_engine::kernels::{self, check_module, Kernel};
use drape_engine::{Buffer, BufferDesc, Context, EngineError, PassTimings};
use drape_shared::adam::LossParams;
use drape_shared::nn::GemmParams;
use drape_tests::gpu;

const LEN: u32 = 1000;

fn params() -> LossParams {
    LossParams {
        len: LEN,
        scale: 1.0,
        _pad: [0; 2],
    }
}

fn groups() -> [u32; 3] {
    [LEN.div_ceil(256), 1, 1]
}

/// The kernels an op chooses at run time for one bindings struct are the generated
/// `<Struct>Kernel` enum's (a kernel outside it does not compile: see the
/// `compile_fail` examples of `drape_engine::bindings`). Checked here against the
/// manifest's declarations: every listed kernel has the struct's binding names,
/// accesses and push constants, every variant the ops need is listed, and kernels with
/// other bindings or push constants are not.
#[test]
fn the_kernels_a_struct_takes_share_its_bindings_and_push_constants() {
    use drape_engine::Bindings;
    fn same_signature(a: Kernel, b: Kernel) -> bool {
        a.push_constant() == b.push_constant()
            && a.bindings().len() == b.bindings().len()
            && a.bindings()
                .iter()
                .zip(b.bindings())
                .all(|(x, y)| x.name == y.name && x.read_only == y.read_only)
    }
    fn takes<'a, B: Bindings<'a>>(variants: &[Kernel])
    where
        B::Kernels: TryFrom<Kernel, Error = Kernel>,
    {
        for &k in variants.iter().chain([&B::KERNEL]) {
            let listed: Kernel = B::Kernels::try_from(k)
                .unwrap_or_else(|k| panic!("{k:?} is not among {:?}'s kernels", B::KERNEL))
                .into();
            assert_eq!(listed, k, "the conversion round-trips");
            assert!(
                same_signature(B::KERNEL, k),
                "{k:?} does not fit {:?}",
                B::KERNEL
            );
        }
        for &k in Kernel::ALL {
            if B::Kernels::try_from(k).is_ok() {
                assert!(
                    same_signature(B::KERNEL, k),
                    "{k:?} listed for {:?}",
                    B::KERNEL
                );
            }
        }
    }
    use Kernel as K;
    takes::<kernels::radix_sort::Histogram>(&[
        K::RadixSortChunkHistogram,
        K::RadixSortChunkHistogramTexel,
    ]);
    takes::<kernels::radix_sort::Scatter>(&[
        K::RadixSortChunkScatter,
        K::RadixSortChunkScatterTexel,
    ]);
    takes::<kernels::radix_sort::ChunkHistogram>(&[K::RadixSortChunkHistogramTexel]);
    takes::<kernels::radix_sort::ChunkHistogramPairs>(&[K::RadixSortChunkHistogramPairsTexel]);
    takes::<kernels::radix_sort::ChunkScatterZip>(&[
        K::RadixSortChunkScatterZipTexel,
        K::RadixSortChunkScatterZipTexelU64,
    ]);
    takes::<kernels::radix_sort::ChunkScatterUnzip>(&[K::RadixSortChunkScatterUnzipTexel]);
    takes::<kernels::radix_sort::ChunkScatterPairs>(&[
        K::RadixSortChunkScatterPairsTexel,
        K::RadixSortChunkScatterPairsTexelU64,
    ]);
    let gemms: Vec<Kernel> = Kernel::ALL
        .iter()
        .copied()
        .filter(|k| {
            k.entry_point().starts_with("nn::gemm")
                || k.entry_point().starts_with("nn_lavapipe::gemm")
        })
        .collect();
    assert!(gemms.len() > 10, "{gemms:?}");
    takes::<kernels::nn::GemmTiled>(&gemms);
    takes::<kernels::nn::ActFwd>(&[K::NnActFwd4, K::NnActFwd4Gelu]);
    takes::<kernels::nn::ActBwd>(&[K::NnActBwd4, K::NnActBwd4Gelu]);
    takes::<kernels::splat::RasterizeFwd>(&[
        K::SplatRasterizeFwdHalf,
        K::SplatLavapipeRasterizeFwd,
        K::SplatLavapipeRasterizeFwdHalf,
    ]);
    takes::<kernels::splat::RasterizeFusedFwd>(&[
        K::SplatRasterizeFusedFwdHalf,
        K::SplatLavapipeRasterizeFusedFwd,
        K::SplatLavapipeRasterizeFusedFwdHalf,
    ]);
    takes::<kernels::splat::RasterizeBwdAtomic>(&[
        K::SplatRasterizeBwdCas,
        K::SplatRasterizeBwdFixed,
        K::SplatLavapipeRasterizeBwdAtomic,
        K::SplatLavapipeRasterizeBwdCas,
        K::SplatLavapipeRasterizeBwdFixed,
    ]);
    takes::<kernels::splat::RasterizeFusedBwdAtomic>(&[
        K::SplatRasterizeFusedBwdCas,
        K::SplatRasterizeFusedBwdFixed,
        K::SplatLavapipeRasterizeFusedBwdAtomic,
        K::SplatLavapipeRasterizeFusedBwdCas,
        K::SplatLavapipeRasterizeFusedBwdFixed,
    ]);
    takes::<kernels::triplane::SampleBwdAtomic>(&[
        K::TriplaneSampleBwdCas,
        K::TriplaneSampleBwdFixed,
    ]);
    // Other bindings or other push constants are not listed.
    assert!(kernels::train::AddIntoKernel::try_from(K::NnActFwd).is_err());
    assert!(kernels::splat::RasterizeFwdKernel::try_from(K::SplatRasterizeBwdAtomic).is_err());
    assert!(kernels::radix_sort::ScatterKernel::try_from(K::RadixSortChunkScatterPairs).is_err());
    assert_eq!(
        K::TrainAddInto.push_constant(),
        "drape_shared::adam::LossParams"
    );
    assert_eq!(K::SplatRasterizeFwd.push_constant(), "");
}

/// `err` is a binding error of `(pass, kernel)` naming `binding`, and its message holds
/// every one of `words`.
fn assert_binding_error_of(
    err: &EngineError,
    (pass, kernel): (&str, &str),
    binding: &str,
    words: &[&str],
) {
    let text = err.to_string();
    match err {
        EngineError::Binding {
            kernel: k,
            binding: b,
            pass: p,
            ..
        } => {
            assert_eq!(*k, kernel, "{text}");
            assert_eq!(b, binding, "{text}");
            assert_eq!(p, pass, "{text}");
        }
        other => panic!("expected a binding error, got {other:?}"),
    }
    for w in words {
        assert!(text.contains(w), "'{w}' missing from: {text}");
    }
}

/// Commands that share only read-only data get no barrier between them; a read of
/// what was written (RAW), a write of what was read (WAR) and a copy of what was
/// written each get one. The sums prove the order held.
#[test]
fn barriers_are_derived_from_declared_access() {
    let gpu = gpu();
    let n = LEN as usize;
    let x = gpu.upload("x", &vec![1.0f32; n]).expect("upload");
    let mut y = gpu.upload("y", &vec![10.0f32; n]).expect("upload");
    let mut z = gpu.upload("z", &vec![100.0f32; n]).expect("upload");
    let mut w = gpu.upload("w", &vec![1000.0f32; n]).expect("upload");
    let mut copy = gpu.upload("copy", &vec![0.0f32; n]).expect("upload");
    let p = params();
    let mut rec = gpu.record("derived barriers").expect("record");
    // y += x and z += x: both only read x, write different buffers.
    rec.dispatch(
        "add.y",
        kernels::train::AddInto {
            src: x.read(),
            dst: y.write(),
        },
        &p,
        groups(),
    )
    .expect("y");
    rec.dispatch(
        "add.z",
        kernels::train::AddInto {
            src: x.read(),
            dst: z.write(),
        },
        &p,
        groups(),
    )
    .expect("z");
    assert_eq!(
        rec.barrier_count(),
        0,
        "independent passes must not be ordered"
    );
    // w += y reads what add.y wrote: a barrier.
    rec.dispatch(
        "add.w",
        kernels::train::AddInto {
            src: y.read(),
            dst: w.write(),
        },
        &p,
        groups(),
    )
    .expect("w");
    assert_eq!(rec.barrier_count(), 1, "read after write");
    // y += z writes y, which add.w read since the barrier (and reads z, written before it).
    rec.dispatch(
        "add.y2",
        kernels::train::AddInto {
            src: z.read(),
            dst: y.write(),
        },
        &p,
        groups(),
    )
    .expect("y2");
    assert_eq!(rec.barrier_count(), 2, "write after read");
    // A copy of what add.y2 wrote.
    rec.copy(&y, &copy, u64::from(LEN) * 4);
    assert_eq!(rec.barrier_count(), 3, "copy after write");
    rec.submit_and_wait().expect("submit");
    let read = |b: &mut Buffer| gpu.read_buffer::<f32>(b, n).expect("read");
    // y = 10 + 1 = 11; z = 100 + 1 = 101; w = 1000 + 11 = 1011; y = 11 + 101 = 112.
    assert!(read(&mut z).iter().all(|&v| v == 101.0));
    assert!(
        read(&mut w).iter().all(|&v| v == 1011.0),
        "add.w ran before add.y finished"
    );
    assert!(
        read(&mut y).iter().all(|&v| v == 112.0),
        "add.y2 ran before add.w read y"
    );
    assert!(read(&mut copy).iter().all(|&v| v == 112.0));
}

/// The start-up check reads each binding's name and access from the module: a
/// renamed parameter or a dropped `NonWritable` is a mismatch naming the binding.
#[test]
fn a_module_whose_bindings_disagree_with_the_manifest_is_named() {
    let original = Kernel::TrainAddInto.spirv();
    check_module(Kernel::TrainAddInto, original).expect("the committed module matches");

    // Rename `src` (an OpName literal "src\0") to `srx`.
    let mut renamed = original.to_vec();
    let at = renamed
        .windows(4)
        .position(|w| w == b"src\0")
        .expect("OpName of src");
    renamed[at + 2] = b'x';
    let text = check_module(Kernel::TrainAddInto, &renamed)
        .expect_err("renamed")
        .to_string();
    assert!(
        text.contains("binding 0") && text.contains("'srx'") && text.contains("'src'"),
        "{text}"
    );

    // Turn the NonWritable decoration (OpDecorate %id 24) into Restrict (19).
    let words: Vec<u32> = original
        .chunks_exact(4)
        .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    let mut at = 5;
    let mut patched = original.to_vec();
    let mut found = false;
    while at < words.len() {
        let (op, count) = (words[at] & 0xffff, (words[at] >> 16) as usize);
        if op == 71 && count == 3 && words[at + 2] == 24 {
            patched[(at + 2) * 4..(at + 3) * 4].copy_from_slice(&19u32.to_le_bytes());
            found = true;
        }
        at += count;
    }
    assert!(found, "add_into declares src NonWritable");
    let text = check_module(Kernel::TrainAddInto, &patched)
        .expect_err("writable")
        .to_string();
    assert!(
        text.contains("'src'") && text.contains("writable in the module"),
        "{text}"
    );
}

/// Passes free to overlap are not counted twice in a submission's GPU time.
#[test]
fn busy_time_counts_overlapping_passes_once() {
    let timings = PassTimings {
        passes: vec![
            ("a".into(), 2.0),
            ("b".into(), 2.0),
            ("c".into(), 1.0),
            ("d".into(), 1.0),
        ],
        // a and b overlap by 1 ms; c starts after a gap; d runs beside c.
        intervals: vec![(0.0, 2.0), (1.0, 3.0), (5.0, 6.0), (5.0, 6.0)],
        // a and b are the body's, c the cloth's, d has no scope.
        scopes: vec!["body".into(), "body".into(), "cloth".into(), String::new()],
    };
    assert_eq!(timings.total_ms(), 6.0);
    assert_eq!(timings.busy_ms(), 4.0);
    // Per scope: the body's two passes overlap and count 3 ms, not 4; unscoped left out.
    let scopes = timings.by_scope();
    assert_eq!(
        scopes.into_iter().collect::<Vec<_>>(),
        [("body".to_string(), 3.0), ("cloth".to_string(), 1.0)]
    );
    let mut two = timings.clone();
    two.extend(timings);
    assert_eq!(
        two.busy_ms(),
        8.0,
        "a second submission's passes follow the first's"
    );
    assert_eq!(two.by_scope()["body"], 6.0, "and their scopes with them");
}

/// Passes recorded under a scope carry it into the submission's timings and the
/// profile (`gpu_scopes`); pass names are unchanged; a scope ends with "".
#[test]
fn scoped_passes_are_timed_per_scope() {
    let gpu = gpu();
    if !drape_tests::has_feature(
        &gpu,
        drape_tests::Feature::Timestamps,
        "scoped_passes_are_timed_per_scope",
    ) {
        return;
    }
    let n = LEN as usize;
    let a = gpu.upload("a", &vec![1.0f32; n]).expect("upload");
    let b = gpu.upload("b", &vec![2.0f32; n]).expect("upload");
    let c = gpu.upload("c", &vec![3.0f32; n]).expect("upload");
    let p = params();
    gpu.start_profile();
    let mut rec = gpu.record("scopes").expect("record");
    rec.set_scope("body");
    rec.dispatch(
        "add.body",
        kernels::train::AddInto {
            src: a.read(),
            dst: b.write(),
        },
        &p,
        groups(),
    )
    .expect("pass");
    rec.set_scope("cloth");
    rec.dispatch(
        "add.cloth",
        kernels::train::AddInto {
            src: a.read(),
            dst: c.write(),
        },
        &p,
        groups(),
    )
    .expect("pass");
    rec.set_scope("");
    rec.dispatch(
        "add.none",
        kernels::train::AddInto {
            src: b.read(),
            dst: c.write(),
        },
        &p,
        groups(),
    )
    .expect("pass");
    let timings = rec.submit_and_wait().expect("submit");
    let profile = gpu.take_profile().expect("profile");
    assert_eq!(timings.scopes, ["body", "cloth", ""]);
    let names: Vec<&str> = timings.passes.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(names, ["add.body", "add.cloth", "add.none"]);
    let by_scope = timings.by_scope();
    assert_eq!(by_scope.keys().collect::<Vec<_>>(), ["body", "cloth"]);
    for (scope, pass) in [("body", 0), ("cloth", 1)] {
        // One pass each: the scope's time is the pass's (up to the rounding of its
        // interval, start + ms - start, in f64).
        let ms = timings.passes[pass].1;
        assert!(ms > 0.0, "{scope}: a timed pass");
        assert!(
            (by_scope[scope] - ms).abs() <= 1e-9 * ms,
            "{scope}: {} vs {ms}",
            by_scope[scope]
        );
        assert!(
            (profile.gpu_scopes[scope].ms - ms).abs() <= 1e-9 * ms,
            "{scope}: profile {} vs {ms}",
            profile.gpu_scopes[scope].ms
        );
        assert_eq!(profile.gpu_scopes[scope].calls, 1);
    }
}

/// Two chains of dependent passes recorded one after the other (as two renders of one
/// frame are) interleave: three waves and two barriers, not five, with each chain's
/// order kept (the sums prove it).
#[test]
fn independent_chains_interleave_wave_by_wave() {
    let gpu = gpu();
    let n = LEN as usize;
    let one = gpu.upload("one", &vec![1.0f32; n]).expect("upload");
    let mut chains = Vec::new();
    for c in 0..2 {
        let bufs: Vec<Buffer> = (0..3)
            .map(|k| {
                gpu.upload(&format!("chain {c} buffer {k}"), &vec![(10 * k) as f32; n])
                    .expect("upload")
            })
            .collect();
        chains.push(bufs);
    }
    let p = params();
    let mut rec = gpu.record("two chains").expect("record");
    for bufs in &chains {
        // b0 += 1; b1 += b0; b2 += b1: each reads what the one before wrote.
        rec.dispatch(
            "chain.0",
            kernels::train::AddInto {
                src: one.read(),
                dst: bufs[0].write(),
            },
            &p,
            groups(),
        )
        .expect("0");
        rec.dispatch(
            "chain.1",
            kernels::train::AddInto {
                src: bufs[0].read(),
                dst: bufs[1].write(),
            },
            &p,
            groups(),
        )
        .expect("1");
        rec.dispatch(
            "chain.2",
            kernels::train::AddInto {
                src: bufs[1].read(),
                dst: bufs[2].write(),
            },
            &p,
            groups(),
        )
        .expect("2");
    }
    assert_eq!(
        rec.barrier_count(),
        2,
        "the second chain runs beside the first"
    );
    let timings = rec.submit_and_wait().expect("submit");
    let names: Vec<&str> = timings.passes.iter().map(|(n, _)| n.as_str()).collect();
    if !names.is_empty() {
        assert_eq!(
            names,
            ["chain.0", "chain.0", "chain.1", "chain.1", "chain.2", "chain.2"],
            "emitted wave by wave"
        );
    }
    for mut bufs in chains {
        // b0 = 0 + 1; b1 = 10 + 1; b2 = 20 + 11.
        for (k, want) in [1.0f32, 11.0, 31.0].into_iter().enumerate() {
            let got = gpu.read_buffer::<f32>(&mut bufs[k], n).expect("read");
            assert!(
                got.iter().all(|&v| v == want),
                "buffer {k}: {} instead of {want}",
                got[0]
            );
        }
    }
}

/// A frame loop creates no Vulkan pools per frame: each recording takes the command,
/// descriptor and query pools a finished one left, reset; timestamps stay valid.
#[test]
fn recordings_reuse_the_pools_of_finished_ones() {
    let gpu = gpu();
    let n = LEN as usize;
    let x = gpu.upload("x", &vec![1.0f32; n]).expect("upload");
    let mut y = gpu.upload("y", &vec![0.0f32; n]).expect("upload");
    let p = params();
    let frame = |expect_passes: bool| {
        let mut rec = gpu.record("frame").expect("record");
        for _ in 0..3 {
            rec.dispatch(
                "add",
                kernels::train::AddInto {
                    src: x.read(),
                    dst: y.write(),
                },
                &p,
                groups(),
            )
            .expect("add");
        }
        let t = rec.submit_and_wait().expect("submit");
        if expect_passes {
            assert!(t.passes.is_empty() || t.passes.len() == 3, "{:?}", t.passes);
            assert!(
                t.passes.iter().all(|(_, ms)| ms.is_finite() && *ms >= 0.0),
                "{:?}",
                t.passes
            );
        }
    };
    frame(true);
    let created = gpu.command_pools_created();
    for _ in 0..20 {
        frame(true);
    }
    assert_eq!(
        gpu.command_pools_created(),
        created,
        "20 more frames created pools"
    );
    // A recording dropped unsubmitted gives its pools back too.
    drop(gpu.record("abandoned").expect("record"));
    frame(true);
    assert_eq!(gpu.command_pools_created(), created);
    // Two alive at once: the second needs its own.
    let a = gpu.record("a").expect("record");
    let b = gpu.record("b").expect("record");
    assert_eq!(gpu.command_pools_created(), created + 1);
    drop((a, b));
    let sums = gpu.read_buffer::<f32>(&mut y, n).expect("read");
    assert!(
        sums.iter().all(|&v| v == 66.0),
        "22 frames of 3 adds: {}",
        sums[0]
    );
}

/// A pass of `nn_lavapipe::gemm_texel` (bindings `a`, `b`: texel buffers; `bias`: read; `c`:
/// written) over 8 × 8 matrices with the bindings `bind` makes of `a`, `c` and a
/// readback buffer, recorded as the storage GEMM's struct with the kernel chosen at
/// run time; its dispatch's result.
fn texel_pass(
    bind: impl for<'a> FnOnce(&'a Buffer, &'a Buffer, &'a Buffer) -> kernels::nn::GemmTiled<'a>,
) -> drape_engine::Result<()> {
    let gpu = gpu();
    let a = gpu.upload("a", &[1.0f32; 64]).expect("upload");
    let c = gpu.upload("c", &[0.0f32; 64]).expect("upload");
    let readback = gpu
        .create_buffer("readback", BufferDesc::readback(256))
        .expect("buffer");
    let mut rec = gpu.record("texel bindings").expect("record");
    let p = GemmParams {
        m: 8,
        n: 8,
        k: 8,
        a_sm: 8,
        a_sk: 1,
        b_sk: 1,
        b_sn: 8,
        ldc: 8,
        k_chunk: 8,
        ..Default::default()
    };
    rec.dispatch_as(
        "test.gemm",
        kernels::nn::GemmTiledKernel::NnLavapipeGemmTexel,
        bind(&a, &c, &readback),
        &p,
        [1, 1, 1],
    )
}

fn assert_texel_error(result: drape_engine::Result<()>, binding: &str, words: &[&str]) {
    let err = result.expect_err("a wrong texel binding must be refused");
    assert_binding_error_of(
        &err,
        ("test.gemm", "nn_lavapipe::gemm_texel"),
        binding,
        words,
    );
}

/// Texel bindings read a whole buffer through its `R32_SFLOAT` view: a correct pass
/// runs (its own struct, or a storage variant's struct with the kernel chosen at run
/// time); a range, or a buffer not made for texel reads (a readback buffer), is an
/// error naming the pass, the kernel and the binding. (Texel fields take only
/// [`Buffer::texel`], whole buffers: a range or a writable buffer does not compile.)
#[test]
fn texel_bindings_read_whole_buffers_through_their_views() {
    if !drape_tests::has_feature(
        &gpu(),
        drape_tests::Feature::SubgroupGemm,
        "texel_bindings_read_whole_buffers_through_their_views (nn_lavapipe::gemm_texel)",
    ) {
        return;
    }
    {
        let gpu = gpu();
        let a = gpu.upload("a", &[1.0f32; 64]).expect("upload");
        let c = gpu.upload("c", &[0.0f32; 64]).expect("upload");
        let mut rec = gpu.record("texel bindings").expect("record");
        let p = GemmParams {
            m: 8,
            n: 8,
            k: 8,
            a_sm: 8,
            a_sk: 1,
            b_sk: 1,
            b_sn: 8,
            ldc: 8,
            k_chunk: 8,
            ..Default::default()
        };
        rec.dispatch(
            "test.gemm",
            kernels::nn_lavapipe::GemmTexel {
                a: a.texel(),
                b: a.texel(),
                bias: a.read(),
                c: c.write(),
            },
            &p,
            [1, 1, 1],
        )
        .expect("whole buffers bind");
    }
    texel_pass(|a, c, _| kernels::nn::GemmTiled {
        a: a.read(),
        b: a.read(),
        bias: a.read(),
        c: c.write(),
    })
    .expect("whole buffers bind");
    let err = texel_pass(|a, c, _| kernels::nn::GemmTiled {
        a: a.read_range(0, 128),
        b: a.read(),
        bias: a.read(),
        c: c.write(),
    });
    assert_texel_error(err, "a", &["texel binding", "whole buffer", "'a'"]);
    let err = texel_pass(|a, c, r| kernels::nn::GemmTiled {
        a: a.read(),
        b: r.read(),
        bias: a.read(),
        c: c.write(),
    });
    assert_texel_error(
        err,
        "b",
        &["'readback'", "texel reads", "UNIFORM_TEXEL_BUFFER"],
    );
}

/// The start-up check tells a texel binding from a storage buffer by the module's
/// types: the same module with its buffer images turned into 1-D images no longer
/// declares texel buffers, and the check names the binding.
#[test]
fn a_texel_binding_the_module_does_not_declare_is_named() {
    let original = Kernel::NnLavapipeGemmTexel.spirv();
    check_module(Kernel::NnLavapipeGemmTexel, original).expect("the committed module matches");
    let words: Vec<u32> = original
        .chunks_exact(4)
        .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    let mut patched = original.to_vec();
    let (mut at, mut found) = (5, false);
    while at < words.len() {
        let (op, count) = (words[at] & 0xffff, (words[at] >> 16) as usize);
        // OpTypeImage %result %sampled Dim(Buffer = 5) ...: make the Dim 1D (0).
        if op == 25 && count >= 4 && words[at + 3] == 5 {
            patched[(at + 3) * 4..(at + 4) * 4].copy_from_slice(&0u32.to_le_bytes());
            found = true;
        }
        at += count;
    }
    assert!(found, "gemm_texel declares a buffer image");
    let text = check_module(Kernel::NnLavapipeGemmTexel, &patched)
        .expect_err("no texel buffer")
        .to_string();
    assert!(
        text.contains("binding 0")
            && text.contains("'a'")
            && text.contains("a storage buffer in the module, a texel buffer in the manifest"),
        "{text}"
    );
}

/// A leaked submission (`mem::forget`, against `Submission`'s contract) may still read
/// the buffers it bound: dropping one defers its destruction until that work finished
/// (polled, never waited for), and the validation layer (on in every test context) sees
/// no buffer destroyed in use.
#[test]
fn a_leaked_submission_finishes_before_its_buffers_are_freed() {
    use drape_engine::ops::radix_sort::RadixSort;
    use drape_engine::SubmitSync;
    let gpu = gpu();
    let n: u32 = 1 << 18;
    let keys: Vec<u32> = (0..n).map(|i| i.wrapping_mul(2_654_435_761)).collect();
    let values: Vec<u32> = (0..n).collect();
    let k = gpu.upload("keys", &keys).expect("upload");
    let v = gpu.upload("values", &values).expect("upload");
    let sort = RadixSort::new(&gpu, n).expect("sort");
    let mut rec = gpu.record("leaked sort").expect("record");
    sort.record(&mut rec, &k, &v, n, 32).expect("record sort");
    let submission = rec.submit(&SubmitSync::default()).expect("submit");
    std::mem::forget(submission);
    let (waits, deferred) = (gpu.fence_waits(), gpu.deferred_buffers().total);
    drop(k);
    assert_eq!(gpu.fence_waits(), waits, "freeing a buffer never waits");
    assert!(
        gpu.deferred_buffers().total > deferred,
        "a buffer freed while the leaked sort may run is deferred"
    );
    drop(v);
    drop(sort);
    // Each later free polls the leaked work: once it has finished, the list empties.
    let start = std::time::Instant::now();
    while gpu.deferred_buffers().waiting > 0 {
        assert!(
            start.elapsed().as_secs() < 60,
            "a minute after a 256k-key sort, {} buffers still wait for it",
            gpu.deferred_buffers().waiting
        );
        std::thread::sleep(std::time::Duration::from_millis(10));
        drop(
            gpu.create_buffer("poll", BufferDesc::gpu_only(16))
                .expect("create"),
        );
    }
}

/// Buffers created and dropped while frames are in flight are freed after those frames,
/// not by waiting for them: over N frames with k in flight the host waits N - k times,
/// for k = 1, 2, 3, however many buffers the loop drops.
#[test]
fn buffers_dropped_while_frames_are_in_flight_do_not_wait() {
    use drape_engine::{FramesInFlight, SubmitSync};
    const FRAMES: u64 = 12;
    let gpu = gpu();
    for k in 1..=3u64 {
        let slots: Vec<(Buffer, Buffer)> = (0..k)
            .map(|i| {
                let a = gpu.upload(&format!("a{i}"), &[1.0f32; LEN as usize]);
                let b = gpu.upload(&format!("b{i}"), &[2.0f32; LEN as usize]);
                (a.expect("upload"), b.expect("upload"))
            })
            .collect();
        let mut frames = FramesInFlight::new(slots);
        let (waits, deferred) = (gpu.fence_waits(), gpu.deferred_buffers().total);
        // The test context poisons new buffers: through a fill it waits for where the
        // memory is not mapped (a discrete GPU); on lavapipe it writes the mapping.
        let mut poison_waits = 0;
        for _ in 0..FRAMES {
            frames
                .submit(&SubmitSync::default(), |(a, b)| {
                    let mut rec = gpu.record("frame")?;
                    let pass = kernels::train::AddInto {
                        src: a.read(),
                        dst: b.write(),
                    };
                    rec.dispatch("add", pass, &params(), groups())?;
                    Ok(rec)
                })
                .expect("frame");
            let mut scratch = gpu
                .create_buffer("scratch", BufferDesc::gpu_only(1 << 16))
                .expect("create");
            poison_waits += u64::from(!scratch.host_mapped());
            drop(scratch);
        }
        assert_eq!(
            gpu.fence_waits() - waits - poison_waits,
            FRAMES - k,
            "{k} frames in flight: one wait per frame beyond the first {k}"
        );
        assert!(
            gpu.deferred_buffers().total - deferred >= FRAMES,
            "every scratch buffer was dropped with a frame in flight, so deferred"
        );
        frames.wait_all().expect("wait");
        assert_eq!(
            gpu.deferred_buffers().waiting,
            0,
            "once every frame is waited for, no buffer waits to be freed"
        );
    }
}

/// `Recording::submit` returns at once; `Submission::wait` returns the passes' times.
#[test]
fn submit_returns_a_submission_to_poll_and_wait() {
    use drape_engine::SubmitSync;
    let gpu = gpu();
    let a = gpu.upload("a", &[1.0f32; LEN as usize]).expect("upload");
    let b = gpu.upload("b", &[2.0f32; LEN as usize]).expect("upload");
    let mut rec = gpu.record("submit").expect("record");
    rec.dispatch(
        "add",
        kernels::train::AddInto {
            src: a.read(),
            dst: b.write(),
        },
        &params(),
        groups(),
    )
    .expect("pass");
    let submissions = gpu.submission_count();
    let s = rec.submit(&SubmitSync::default()).expect("submit");
    assert_eq!(gpu.submission_count(), submissions + 1);
    let _ = s.is_complete().expect("poll");
    let timings = s.wait().expect("wait");
    assert_eq!(timings.passes.len(), 1);
}

/// A frame recorded into the host's command buffer that the host then does not submit
/// (it could not present, say, and frees that command buffer) is given up with
/// `FramesInFlight::abandon`: the slot records again at once, without waiting for
/// timestamps that will never be written, and the abandoned frame's work never runs.
#[test]
fn a_host_frame_never_submitted_can_be_abandoned() {
    use drape_engine::{FramesInFlight, HostCommandBuffer, Recording, SubmitSync};
    fn add<'r>(
        ctx: &Context,
        (a, b): &'r mut (Buffer, Buffer),
    ) -> drape_engine::Result<Recording<'r>> {
        let mut rec = ctx.record("frame")?;
        let pass = kernels::train::AddInto {
            src: a.read(),
            dst: b.write(),
        };
        rec.dispatch("add", pass, &params(), groups())?;
        Ok(rec)
    }
    let host = drape_tests::host::Host::new(false);
    {
        let ctx = host.context();
        let a = ctx.upload("a", &[1.0f32; LEN as usize]).expect("upload");
        let b = ctx.upload("b", &[2.0f32; LEN as usize]).expect("upload");
        let mut frames = FramesInFlight::new(vec![(a, b)]);
        let cmd = host.begin();
        // SAFETY: a primary command buffer of the host's device in the recording state;
        // it is freed below without being submitted, and the frame is abandoned.
        let hcb = unsafe { HostCommandBuffer::new(cmd, None) };
        frames
            .record_into(&hcb, |slot| add(&ctx, slot))
            .expect("record into");
        // SAFETY: never submitted, so not pending; the host's pool made it.
        unsafe { host.device.free_command_buffers(host.pool, &[cmd]) };
        assert!(
            frames.abandon(0).expect("abandon"),
            "slot 0 held a host frame"
        );
        assert!(!frames.is_pending(0));
        frames
            .submit(&SubmitSync::default(), |slot| add(&ctx, slot))
            .expect("the slot's next frame");
        let (_, (_, b), _) = frames.next_slot().expect("wait for it");
        let sums: Vec<f32> = ctx.read_buffer(b, LEN as usize).expect("read");
        assert!(
            sums.iter().all(|&s| s == 3.0),
            "one add ran (2 + 1), the abandoned one did not: {:?}",
            &sums[..4]
        );
    }
    let messages = host.finish();
    assert!(messages.is_empty(), "validation:\n{}", messages.join("\n"));
}
