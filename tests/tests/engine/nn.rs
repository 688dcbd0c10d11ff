//! MLPs on the GPU against the CPU reference (f64), and the reference's gradients
//! against central differences in f64.

use drape_engine::ops::nn::{
    reference, subgroup_gemm_supported, Activation, GemmVariant, HeadDesc, Mlp, MlpDesc,
};
use drape_engine::{Buffer, Context};
use drape_tests::gpu;
use drape_tests::num::{rel_err, to_f32, to_f64, uniform};

/// A small MLP with every activation and several heads.
fn small_desc() -> MlpDesc {
    MlpDesc {
        input: 7,
        hidden: vec![(16, Activation::Gelu), (13, Activation::Gelu)],
        heads: vec![
            HeadDesc::new("opacity", 1, Activation::Sigmoid),
            HeadDesc::new("raw", 5, Activation::Identity),
            HeadDesc::new("weights", 24, Activation::Softmax { temperature: 0.1 }),
            HeadDesc::new("scale", 2, Activation::Exp),
        ],
        weight_norm: vec![],
    }
}

struct GpuRun {
    heads: Vec<Vec<f64>>,
    grads: Vec<f64>,
    grad_input: Vec<f64>,
}

fn run_gpu(
    ctx: &Context,
    desc: &MlpDesc,
    params: &[f64],
    input: &[f64],
    head_grads: &[Vec<f64>],
    rows: usize,
) -> GpuRun {
    run_gpu_with(
        ctx,
        desc,
        params,
        input,
        head_grads,
        rows,
        GemmVariant::Auto,
    )
}

fn run_gpu_with(
    ctx: &Context,
    desc: &MlpDesc,
    params: &[f64],
    input: &[f64],
    head_grads: &[Vec<f64>],
    rows: usize,
    variant: GemmVariant,
) -> GpuRun {
    let mut mlp =
        Mlp::with_params(ctx, "test mlp", desc.clone(), rows, &to_f32(params)).expect("mlp");
    mlp.variant = variant;
    let x = ctx.upload("test input", &to_f32(input)).expect("upload");
    let mut gx: Buffer = ctx
        .create_buffer(
            "test grad input",
            drape_engine::BufferDesc::gpu_only((input.len().max(1) * 4) as u64),
        )
        .expect("buffer");
    for (h, g) in head_grads.iter().enumerate() {
        mlp.write_head_grad(ctx, h, &to_f32(g))
            .expect("write head grad");
    }
    {
        let mut rec = ctx.record("mlp test").expect("record");
        mlp.record_forward(&mut rec, &x, rows as u32).expect("fwd");
        mlp.record_backward(&mut rec, &x, rows as u32, Some(&gx), false)
            .expect("bwd");
        rec.submit_and_wait().expect("submit");
    }
    let mut heads = Vec::new();
    for h in 0..desc.heads.len() {
        heads.push(to_f64(&mlp.read_head(ctx, h, rows).expect("read head")));
    }
    let n = mlp.param_count();
    let grads = to_f64(
        &ctx.read_buffer::<f32>(&mut mlp.grads, n)
            .expect("read grads"),
    );
    let grad_input = to_f64(
        &ctx.read_buffer::<f32>(&mut gx, input.len())
            .expect("read gx"),
    );
    GpuRun {
        heads,
        grads,
        grad_input,
    }
}

/// `small_desc` with weight normalisation on its second hidden layer and on a head.
fn normed_desc() -> MlpDesc {
    MlpDesc {
        weight_norm: vec![1, 3],
        ..small_desc()
    }
}

/// Widths in multiples of 4: every forward fits the 4-float texel kernels
/// (`GemmVariant::Texel4`: `nn_lavapipe::gemm_fwd_cols*` at every tile width, 32, 16, 8 and
/// 4, with both epilogues), and the gradients of the outputs of 16 or more too (input
/// gradients `gemm_input_grad*`, weight gradients `gemm_weight_grad_vec4` or
/// `gemm_b_along_n*`), where
/// `small_desc`'s odd widths take the fallback.
fn texel4_desc() -> MlpDesc {
    MlpDesc {
        // 12 = 8 + 4: the forward's last pass through `k` has only its first 4 steps.
        input: 12,
        hidden: vec![(16, Activation::Gelu), (32, Activation::Gelu)],
        heads: vec![
            HeadDesc::new("opacity", 1, Activation::Sigmoid),
            HeadDesc::new("raw", 7, Activation::Identity),
            HeadDesc::new("weights", 24, Activation::Softmax { temperature: 0.1 }),
            // 32 + 16 + 1 columns with an odd row stride: the forward's float epilogue
            // at widths 32, 16 and 4.
            HeadDesc::new("wide", 49, Activation::Identity),
            // 8 + 4 columns: the 4-float epilogue at the two narrowest widths.
            HeadDesc::new("quads", 12, Activation::Identity),
        ],
        weight_norm: vec![],
    }
}

#[test]
fn mlp_gpu_matches_cpu_reference() {
    let ctx = gpu();
    for (desc, sizes) in [
        (small_desc(), &[0usize, 1, 7, 1000, 100_003][..]),
        (texel4_desc(), &[0, 1, 7, 1000, 100_003][..]),
        (normed_desc(), &[0, 1, 7, 1000][..]),
    ] {
        check_against_reference(&ctx, &desc, sizes);
    }
}

/// Every GEMM kernel the device runs: the subgroup and texel ones only where subgroups
/// are 8 lanes with ballot (`report`: say so when they are left out).
fn gemm_variants(ctx: &Context, report: bool) -> Vec<GemmVariant> {
    let mut variants = vec![GemmVariant::Tiled, GemmVariant::Blocked];
    let supported = if report {
        drape_tests::has_feature(
            ctx,
            drape_tests::Feature::SubgroupGemm,
            "nn_lavapipe::gemm_subgroup, nn_lavapipe::gemm_texel and the 4-float texel GEMMs",
        )
    } else {
        subgroup_gemm_supported(ctx.info())
    };
    if supported {
        variants.push(GemmVariant::Subgroup);
        variants.push(GemmVariant::Texel);
        variants.push(GemmVariant::Texel4);
    }
    variants
}

fn check_against_reference(ctx: &Context, desc: &MlpDesc, sizes: &[usize]) {
    let desc = desc.clone();
    let ctx = ctx.clone();
    let params = to_f64(&desc.init_params(3));
    for &rows in sizes {
        let input = uniform(rows * desc.input, -2.0, 2.0, rows as u64);
        let head_grads: Vec<Vec<f64>> = desc
            .heads
            .iter()
            .enumerate()
            .map(|(h, d)| uniform(rows * d.width, -1.0, 1.0, 100 + h as u64))
            .collect();
        let saved = reference::forward(&desc, &params, &input, rows);
        let (ref_grads, ref_gx) =
            reference::backward(&desc, &params, &input, rows, &saved, &head_grads);
        for variant in gemm_variants(&ctx, rows == sizes[0]) {
            let run = run_gpu_with(&ctx, &desc, &params, &input, &head_grads, rows, variant);
            for h in 0..desc.heads.len() {
                // f32 against f64: sums of at most 16 products, rounding ~1e-7 each.
                let e = rel_err(&run.heads[h], saved.head(&desc, h), 1e-3);
                assert!(
                    e <= 1e-5,
                    "{variant:?}, rows {rows} head {}: forward relative error {e:e}",
                    desc.heads[h].name
                );
            }
            // Weight gradients sum up to 100k rows in f32 (chunks of >= 1024 rows on CPU
            // devices, >= 128 on GPUs, then in
            // order): relative rounding ~1e-6 · sqrt(chunks); 1e-4 leaves a margin.
            let e = rel_err(&run.grads, &ref_grads, 1e-3);
            assert!(
                e <= 1e-4,
                "{variant:?}, rows {rows}: parameter gradient relative error {e:e}"
            );
            let e = rel_err(&run.grad_input, &ref_gx, 1e-3);
            assert!(
                e <= 1e-4,
                "{variant:?}, rows {rows}: input gradient relative error {e:e}"
            );
        }
    }
}

#[test]
fn hugs_decoders_run_on_the_gpu_as_on_the_cpu() {
    let ctx = gpu();
    let rows = 300;
    for desc in [
        MlpDesc::hugs_appearance(96, 48),
        MlpDesc::hugs_geometry(96),
        MlpDesc::hugs_deformation(96),
        MlpDesc::hugs_deformation(96).with_weight_norm(3),
    ] {
        let params = to_f64(&desc.init_params(11));
        let input = uniform(rows * desc.input, -1.0, 1.0, 5);
        let head_grads: Vec<Vec<f64>> = desc
            .heads
            .iter()
            .enumerate()
            .map(|(h, d)| uniform(rows * d.width, -1.0, 1.0, 50 + h as u64))
            .collect();
        let saved = reference::forward(&desc, &params, &input, rows);
        let (ref_grads, ref_gx) =
            reference::backward(&desc, &params, &input, rows, &saved, &head_grads);
        // Every GEMM kernel, whichever the device would pick: the decoders' widths (up to
        // 128) reach every row and column block of the GPU's 64 x 64 tiles.
        for variant in gemm_variants(&ctx, false) {
            let run = run_gpu_with(&ctx, &desc, &params, &input, &head_grads, rows, variant);
            for h in 0..desc.heads.len() {
                // Sums of up to 128 products in f32.
                let e = rel_err(&run.heads[h], saved.head(&desc, h), 1e-3);
                assert!(
                    e <= 1e-5,
                    "{variant:?}, {}: forward relative error {e:e}",
                    desc.heads[h].name
                );
            }
            let e = rel_err(&run.grads, &ref_grads, 1e-3);
            assert!(
                e <= 1e-4,
                "{variant:?}: parameter gradient relative error {e:e}"
            );
            let e = rel_err(&run.grad_input, &ref_gx, 1e-3);
            assert!(
                e <= 1e-4,
                "{variant:?}: input gradient relative error {e:e}"
            );
        }
    }
}

/// Loss `Σ_h Σ head_h ⊙ c_h` in f64.
fn loss(desc: &MlpDesc, params: &[f64], input: &[f64], rows: usize, coeffs: &[Vec<f64>]) -> f64 {
    let saved = reference::forward(desc, params, input, rows);
    (0..desc.heads.len())
        .map(|h| {
            saved
                .head(desc, h)
                .iter()
                .zip(&coeffs[h])
                .map(|(a, b)| a * b)
                .sum::<f64>()
        })
        .sum()
}

#[test]
fn mlp_gradients_match_central_differences() {
    for desc in [small_desc(), normed_desc()] {
        check_central_differences(&desc);
    }
}

fn check_central_differences(desc: &MlpDesc) {
    let desc = desc.clone();
    let rows = 3;
    let params = to_f64(&desc.init_params(7));
    let input = uniform(rows * desc.input, -2.0, 2.0, 9);
    let coeffs: Vec<Vec<f64>> = desc
        .heads
        .iter()
        .enumerate()
        .map(|(h, d)| uniform(rows * d.width, -1.0, 1.0, 20 + h as u64))
        .collect();
    let saved = reference::forward(&desc, &params, &input, rows);
    let (grads, gx) = reference::backward(&desc, &params, &input, rows, &saved, &coeffs);
    let h = 1e-6;
    let check = |analytic: &[f64], values: &[f64], set: &dyn Fn(usize, f64) -> f64, what: &str| {
        let numeric: Vec<f64> = (0..values.len())
            .map(|i| (set(i, values[i] + h) - set(i, values[i] - h)) / (2.0 * h))
            .collect();
        // Central differences at h = 1e-6 in f64: truncation ~h² · f''' and rounding
        // ~1e-16 / h ≈ 1e-10; 1e-6 of the largest gradient bounds both.
        let e = rel_err(analytic, &numeric, 1e-6);
        assert!(
            e <= 1e-6,
            "{what}: relative error {e:e} against central differences"
        );
    };
    check(
        &grads,
        &params,
        &|i, v| {
            let mut p = params.clone();
            p[i] = v;
            loss(&desc, &p, &input, rows, &coeffs)
        },
        "parameters",
    );
    check(
        &gx,
        &input,
        &|i, v| {
            let mut x = input.clone();
            x[i] = v;
            loss(&desc, &params, &x, rows, &coeffs)
        },
        "input",
    );
}

#[test]
fn activations_stay_finite_at_the_extremes() {
    let ctx = gpu();
    // One hidden layer that passes its input through (identity weights), so the heads
    // see the extreme values as logits.
    let desc = MlpDesc {
        input: 4,
        hidden: vec![(4, Activation::Gelu)],
        heads: vec![
            HeadDesc::new("sigmoid", 4, Activation::Sigmoid),
            HeadDesc::new("softmax", 4, Activation::Softmax { temperature: 0.1 }),
        ],
        weight_norm: vec![],
    };
    let (offsets, len) = desc.layout();
    let mut params = vec![0.0f64; len];
    for l in 0..3 {
        for i in 0..4 {
            params[offsets[l].0 + i * 4 + i] = 1.0;
        }
    }
    // GELU of ±1e4 is 1e4 and -0; the heads then see ±80 scaled by the identity.
    let input = vec![1e4, -1e4, 80.0, -80.0, 80.0, -80.0, 0.0, 1e-3];
    let rows = 2;
    let head_grads = vec![vec![1.0; 8], vec![0.5; 8]];
    let run = run_gpu(&ctx, &desc, &params, &input, &head_grads, rows);
    let saved = reference::forward(&desc, &params, &input, rows);
    for v in run
        .heads
        .iter()
        .flatten()
        .chain(&run.grads)
        .chain(&run.grad_input)
    {
        assert!(v.is_finite(), "non-finite value {v} at extreme logits");
    }
    // sigmoid(1e4) = 1, sigmoid(gelu(-1e4) = 0) = 0.5, sigmoid(80) = 1, sigmoid(gelu(-80)) = 0.5.
    let expect = [1.0, 0.5, 1.0, 0.5];
    for (a, b) in run.heads[0][..4].iter().zip(expect) {
        assert!((a - b).abs() < 1e-6, "sigmoid head {a} vs {b}");
    }
    let e = rel_err(&run.heads[1], saved.head(&desc, 1), 1e-3);
    assert!(e <= 1e-5, "softmax at extreme logits: relative error {e:e}");
}

/// `Auto` takes the texel GEMM only for operands a texel binding can read: an MLP fed
/// from a storage buffer made without texel usage (a readback buffer) still runs, on
/// the storage-buffer kernel, and gives the same outputs.
#[test]
fn auto_gemm_reads_buffers_without_texel_usage_through_storage_bindings() {
    let ctx = gpu();
    let desc = small_desc();
    let rows = 37;
    let params = to_f64(&desc.init_params(5));
    let input = uniform(rows * desc.input, -1.0, 1.0, 9);
    let mut mlp =
        Mlp::with_params(&ctx, "test mlp", desc.clone(), rows, &to_f32(&params)).expect("mlp");
    let mut plain = ctx
        .create_buffer(
            "input (readback memory)",
            drape_engine::BufferDesc::readback((rows * desc.input * 4) as u64),
        )
        .expect("buffer");
    ctx.write_buffer(&mut plain, &to_f32(&input))
        .expect("write");
    assert!(
        !plain.texel_readable(u64::MAX),
        "a readback buffer is not made for texel reads"
    );
    let mut rec = ctx.record("mlp from a readback buffer").expect("record");
    mlp.record_forward(&mut rec, &plain, rows as u32)
        .expect("the forward records");
    rec.submit_and_wait().expect("submit");
    let saved = reference::forward(&desc, &params, &input, rows);
    for h in 0..desc.heads.len() {
        let got = mlp.read_head(&ctx, h, rows).expect("read");
        // f32 against f64, sums of at most 16 products.
        let e = rel_err(&to_f64(&got), saved.head(&desc, h), 1e-3);
        assert!(e <= 1e-5, "head {h}: forward relative error {e:e}");
    }
}
