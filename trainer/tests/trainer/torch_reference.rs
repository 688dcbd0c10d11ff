//! The neural ops against an independent implementation: PyTorch (CPU, float64) on the
//! same inputs, through `tests/python/torch_reference.py` in the virtual environment
//! `scripts/torch-env.sh` makes (the test command runs it). `nn.Linear` + `F.gelu` +
//! sigmoid / exp / softmax heads (outputs and every gradient), `F.grid_sample`
//! triplanes (align_corners=True, zeros padding), the 6D rotation (PyTorch3D's
//! formula).
//!
//! Without the environment these tests fail (they are not skipped): set
//! `DRAPE_TORCH_PYTHON` to a Python with torch, or run `scripts/torch-env.sh`.

use std::path::Path;

use drape_engine::ops::deform::{self, HostInputs};
use drape_engine::ops::nn::{reference, Activation, HeadDesc, Mlp, MlpDesc};
use drape_engine::ops::triplane::{Triplane, TriplaneDesc};
use drape_engine::{BufferDesc, Context};
use drape_shared::deform::rot6d_to_matrix;
use drape_tests::gpu;
use drape_tests::num::{rel_err, to_f32, to_f64, uniform};
use drape_tests::reference_python::{case_dir, get, put};
use rand::{Rng, SeedableRng};

fn run_torch(dir: &Path, case: serde_json::Value) {
    drape_io::write(dir.join("case.json"), case.to_string()).expect("case.json");
    drape_tests::reference_python::run("torch_reference.py", &[dir.to_path_buf()]);
}

fn act_name(a: Activation) -> &'static str {
    match a {
        Activation::Identity => "identity",
        Activation::Gelu => "gelu",
        Activation::Sigmoid => "sigmoid",
        Activation::Exp => "exp",
        Activation::Softmax { .. } => "softmax",
    }
}

/// Runs `desc` on the GPU and in PyTorch (heads concatenated into one last layer, the
/// same function) and compares outputs and every gradient.
fn check_mlp(ctx: &Context, name: &str, desc: &MlpDesc, rows: usize) {
    let params = to_f64(&desc.init_params(17));
    let input = uniform(rows * desc.input, -2.0, 2.0, 3);
    let head_grads: Vec<Vec<f64>> = desc
        .heads
        .iter()
        .enumerate()
        .map(|(h, d)| uniform(rows * d.width, -1.0, 1.0, 30 + h as u64))
        .collect();
    // GPU.
    let mut mlp = Mlp::with_params(ctx, name, desc.clone(), rows, &to_f32(&params)).expect("mlp");
    for (h, g) in head_grads.iter().enumerate() {
        mlp.write_head_grad(ctx, h, &to_f32(g)).expect("head grad");
    }
    let x = ctx.upload("x", &to_f32(&input)).expect("upload");
    let mut gx = ctx
        .create_buffer("gx", BufferDesc::gpu_only((input.len().max(1) * 4) as u64))
        .expect("buffer");
    {
        let mut rec = ctx.record("torch check").expect("record");
        mlp.record_forward(&mut rec, &x, rows as u32).expect("fwd");
        mlp.record_backward(&mut rec, &x, rows as u32, Some(&gx), false)
            .expect("bwd");
        rec.submit_and_wait().expect("submit");
    }
    let heads: Vec<Vec<f64>> = (0..desc.heads.len())
        .map(|h| to_f64(&mlp.read_head(ctx, h, rows).expect("read")))
        .collect();
    let count = mlp.param_count();
    let grads = to_f64(&ctx.read_buffer::<f32>(&mut mlp.grads, count).expect("read"));
    let gpu_gx = to_f64(&ctx.read_buffer::<f32>(&mut gx, input.len()).expect("read"));

    // PyTorch: hidden layers as they are, the heads as one concatenated last layer.
    let dir = case_dir("torch-cases", name);
    let (offsets, _) = desc.layout();
    let linears = desc.linears();
    let hidden = desc.hidden.len();
    let mut layers = Vec::new();
    assert!(
        desc.weight_norm.iter().all(|&l| l < hidden),
        "{name}: the check covers weight normalisation on hidden layers only"
    );
    let norms = desc.weight_norm_params();
    for l in 0..hidden {
        let (i, o) = linears[l];
        put(
            &dir,
            &format!("w{l}"),
            &[o, i],
            &params[offsets[l].0..offsets[l].0 + o * i],
        );
        put(
            &dir,
            &format!("b{l}"),
            &[o],
            &params[offsets[l].1..offsets[l].1 + o],
        );
        let mut j = serde_json::json!({ "in": i, "out": o, "act": act_name(desc.hidden[l].1) });
        if let Some(k) = desc.weight_norm.iter().position(|&w| w == l) {
            let g = norms[k].g_off as usize;
            put(&dir, &format!("g{l}"), &[o], &params[g..g + o]);
            j["weight_norm"] = true.into();
        }
        layers.push(j);
    }
    let trunk = desc.trunk_width();
    let total: usize = desc.heads.iter().map(|h| h.width).sum();
    let (mut w, mut b, mut heads_json, mut gy) =
        (Vec::new(), Vec::new(), Vec::new(), vec![0.0; rows * total]);
    let mut start = 0;
    for (h, d) in desc.heads.iter().enumerate() {
        let l = hidden + h;
        w.extend_from_slice(&params[offsets[l].0..offsets[l].0 + d.width * trunk]);
        b.extend_from_slice(&params[offsets[l].1..offsets[l].1 + d.width]);
        let mut j = serde_json::json!({ "start": start, "end": start + d.width, "act": act_name(d.activation) });
        if let Activation::Softmax { temperature } = d.activation {
            j["temperature"] = serde_json::json!(temperature);
        }
        heads_json.push(j);
        for r in 0..rows {
            gy[r * total + start..r * total + start + d.width]
                .copy_from_slice(&head_grads[h][r * d.width..(r + 1) * d.width]);
        }
        start += d.width;
    }
    put(&dir, &format!("w{hidden}"), &[total, trunk], &w);
    put(&dir, &format!("b{hidden}"), &[total], &b);
    layers.push(serde_json::json!({ "in": trunk, "out": total, "act": "none" }));
    put(&dir, "x", &[rows, desc.input], &input);
    put(&dir, "gy", &[rows, total], &gy);
    run_torch(
        &dir,
        serde_json::json!({ "op": "mlp", "layers": layers, "heads": heads_json }),
    );
    let ty = get(&dir, "y");
    let tgx = get(&dir, "gx");
    // Forward: f32 GPU sums of up to 128 products against float64 PyTorch.
    let mut start = 0;
    for (h, d) in desc.heads.iter().enumerate() {
        let t: Vec<f64> = (0..rows)
            .flat_map(|r| ty[r * total + start..r * total + start + d.width].to_vec())
            .collect();
        let e = rel_err(&heads[h], &t, 1e-3);
        assert!(
            e <= 1e-5,
            "{name}: head {} differs from PyTorch by {e:e} (relative)",
            d.name
        );
        start += d.width;
    }
    // Gradients are f32 sums over the rows: 1e-4 relative, ten times the outputs'.
    let e = rel_err(&gpu_gx, &tgx, 1e-3);
    assert!(
        e <= 1e-4,
        "{name}: input gradient differs from PyTorch by {e:e}"
    );
    for l in 0..hidden {
        let (i, o) = linears[l];
        let e = rel_err(
            &grads[offsets[l].0..offsets[l].0 + o * i],
            &get(&dir, &format!("gw{l}")),
            1e-3,
        );
        assert!(
            e <= 1e-4,
            "{name}: weight gradient of layer {l} differs from PyTorch by {e:e}"
        );
        let e = rel_err(
            &grads[offsets[l].1..offsets[l].1 + o],
            &get(&dir, &format!("gb{l}")),
            1e-3,
        );
        assert!(
            e <= 1e-4,
            "{name}: bias gradient of layer {l} ({i}->{o}) differs from PyTorch by {e:e}"
        );
        if let Some(k) = desc.weight_norm.iter().position(|&w| w == l) {
            let g = norms[k].g_off as usize;
            let e = rel_err(&grads[g..g + o], &get(&dir, &format!("gg{l}")), 1e-3);
            assert!(
                e <= 1e-4,
                "{name}: weight-norm g gradient of layer {l} differs from PyTorch by {e:e}"
            );
        }
    }
    let (tgw, tgb) = (
        get(&dir, &format!("gw{hidden}")),
        get(&dir, &format!("gb{hidden}")),
    );
    let mut row0 = 0;
    for (h, d) in desc.heads.iter().enumerate() {
        let l = hidden + h;
        let e = rel_err(
            &grads[offsets[l].0..offsets[l].0 + d.width * trunk],
            &tgw[row0 * trunk..(row0 + d.width) * trunk],
            1e-3,
        );
        assert!(
            e <= 1e-4,
            "{name}: weight gradient of head {} differs from PyTorch by {e:e}",
            d.name
        );
        let e = rel_err(
            &grads[offsets[l].1..offsets[l].1 + d.width],
            &tgb[row0..row0 + d.width],
            1e-3,
        );
        assert!(
            e <= 1e-4,
            "{name}: bias gradient of head {} differs from PyTorch by {e:e}",
            d.name
        );
        row0 += d.width;
    }
    // The CPU reference agrees too (it is what the other tests trust).
    let saved = drape_engine::ops::nn::reference::forward(desc, &params, &input, rows);
    let (ref_grads, _) = reference::backward(desc, &params, &input, rows, &saved, &head_grads);
    assert!(
        rel_err(&ref_grads, &grads, 1e-3) <= 1e-4,
        "{name}: CPU reference and GPU disagree"
    );
}

#[test]
fn mlps_match_pytorch() {
    let ctx = gpu();
    let mixed = MlpDesc {
        input: 9,
        hidden: vec![(20, Activation::Gelu), (17, Activation::Gelu)],
        heads: vec![
            HeadDesc::new("opacity", 1, Activation::Sigmoid),
            HeadDesc::new("raw", 5, Activation::Identity),
            HeadDesc::new("weights", 24, Activation::Softmax { temperature: 0.1 }),
            HeadDesc::new("scale", 3, Activation::Exp),
        ],
        weight_norm: vec![],
    };
    check_mlp(&ctx, "mixed", &mixed, 1000);
    // Weight normalisation against torch.nn.utils.parametrizations.weight_norm, on the
    // mixed MLP's second hidden layer and on HUGS's deformation decoder's last.
    let mut normed = mixed.clone();
    normed.weight_norm = vec![1];
    check_mlp(&ctx, "mixed-weight-norm", &normed, 1000);
    check_mlp(
        &ctx,
        "deformation-weight-norm",
        &MlpDesc::hugs_deformation(96).with_weight_norm(3),
        300,
    );
    check_mlp(&ctx, "mixed-one-row", &mixed, 1);
    check_mlp(&ctx, "appearance", &MlpDesc::hugs_appearance(96, 48), 300);
    check_mlp(&ctx, "geometry", &MlpDesc::hugs_geometry(96), 300);
    check_mlp(&ctx, "deformation", &MlpDesc::hugs_deformation(96), 300);
}

#[test]
fn triplane_matches_grid_sample() {
    let ctx = gpu();
    let desc = TriplaneDesc {
        resolution: 13,
        channels: 6,
        box_min: [-1.0, -0.3, -2.0],
        box_max: [0.8, 1.7, 0.5],
    };
    let planes = uniform(desc.len(), -1.0, 1.0, 8);
    let n = 2000;
    let mut rng = rand::rngs::StdRng::seed_from_u64(9);
    let mut pts = Vec::new();
    for i in 0..n {
        for a in 0..3 {
            let (lo, hi) = (f64::from(desc.box_min[a]), f64::from(desc.box_max[a]));
            let w = hi - lo;
            // Inside, on the faces, just outside (zero padding fades) and far outside.
            pts.push(match i % 8 {
                0 => lo,
                1 => hi,
                2 => hi + 0.03 * w,
                3 => lo - 2.0 * w,
                _ => rng.random_range(lo - 0.05 * w..hi + 0.05 * w),
            });
        }
    }
    let gfeat = uniform(n * desc.feature_width(), -1.0, 1.0, 10);
    let mut tp =
        Triplane::with_planes(&ctx, "torch triplane", desc, &to_f32(&planes)).expect("triplane");
    let p = ctx.upload("points", &to_f32(&pts)).expect("upload");
    let g = ctx.upload("gfeat", &to_f32(&gfeat)).expect("upload");
    let mut f = ctx
        .create_buffer("features", BufferDesc::gpu_only((gfeat.len() * 4) as u64))
        .expect("buffer");
    let mut gp = ctx
        .create_buffer("grad points", BufferDesc::gpu_only((pts.len() * 4) as u64))
        .expect("buffer");
    {
        let mut rec = ctx.record("triplane torch").expect("record");
        tp.record_forward(&mut rec, &p, &f, n as u32).expect("fwd");
        tp.record_backward(
            &mut rec,
            &p,
            &g,
            &gp,
            n as u32,
            drape_engine::ops::accumulate::Accumulation::Auto,
        )
        .expect("bwd");
        rec.submit_and_wait().expect("submit");
    }
    let feat = to_f64(&ctx.read_buffer::<f32>(&mut f, gfeat.len()).expect("read"));
    let gplanes = to_f64(
        &ctx.read_buffer::<f32>(&mut tp.grads, desc.len())
            .expect("read"),
    );
    let gpoints = to_f64(&ctx.read_buffer::<f32>(&mut gp, pts.len()).expect("read"));
    let dir = case_dir("torch-cases", "triplane");
    let r = desc.resolution as usize;
    let c = desc.channels as usize;
    put(&dir, "planes", &[3, r, r, c], &planes);
    put(&dir, "points", &[n, 3], &pts);
    put(&dir, "gfeat", &[n, 3 * c], &gfeat);
    run_torch(
        &dir,
        serde_json::json!({ "op": "triplane", "box_min": desc.box_min, "box_max": desc.box_max }),
    );
    // Four products per feature in f32; the box mapping in f32 moves a sample by
    // ~1e-7 of the box, i.e. ~1e-6 of a texel's value.
    let e = rel_err(&feat, &get(&dir, "feat"), 1e-3);
    assert!(e <= 1e-5, "features differ from grid_sample by {e:e}");
    let e = rel_err(&gplanes, &get(&dir, "gplanes"), 1e-3);
    assert!(
        e <= 1e-4,
        "plane gradient differs from grid_sample's by {e:e}"
    );
    // Point gradients are differences of texels times (R-1)/2 / half-extent: f32
    // rounding of the sample position and of the texel differences, 1e-4 relative.
    let e = rel_err(&gpoints, &get(&dir, "gpoints"), 1e-3);
    assert!(
        e <= 1e-4,
        "point gradient differs from grid_sample's by {e:e}"
    );
}

#[test]
fn rotation_6d_matches_pytorch() {
    let n = 500;
    let r6 = uniform(6 * n, -2.0, 2.0, 11);
    let g = uniform(9 * n, -1.0, 1.0, 12);
    let dir = case_dir("torch-cases", "rot6d");
    put(&dir, "r6", &[n, 6], &r6);
    put(&dir, "gR", &[n, 3, 3], &g);
    run_torch(&dir, serde_json::json!({ "op": "rot6d" }));
    let (tr, tg) = (get(&dir, "R"), get(&dir, "gr6"));
    let mut ours = Vec::new();
    let mut ours_g = Vec::new();
    for i in 0..n {
        let v: [f64; 6] = r6[6 * i..6 * i + 6].try_into().expect("6");
        ours.extend(rot6d_to_matrix(v).iter().flatten());
        let gm = [
            [g[9 * i], g[9 * i + 1], g[9 * i + 2]],
            [g[9 * i + 3], g[9 * i + 4], g[9 * i + 5]],
            [g[9 * i + 6], g[9 * i + 7], g[9 * i + 8]],
        ];
        ours_g.extend(drape_shared::deform::rot6d_to_matrix_bwd(v, &gm));
    }
    // Both in float64: agreement to rounding.
    assert!(
        rel_err(&ours, &tr, 1e-6) <= 1e-12,
        "6D rotation differs from PyTorch"
    );
    assert!(
        rel_err(&ours_g, &tg, 1e-6) <= 1e-10,
        "6D rotation gradient differs from PyTorch"
    );
    // And the GPU's deformation path uses the same functions: a quick consistency
    // check of the CPU reference on one Gaussian with identity transforms.
    let host = HostInputs::<f64> {
        transforms: (0..24)
            .flat_map(|_| [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0])
            .collect(),
        means: vec![0.1, 0.2, 0.3],
        quats: vec![1.0, 0.0, 0.0, 0.0],
        log_scales: vec![-3.0; 3],
        offsets: vec![0.0; 3],
        rot6d: r6[..6].to_vec(),
        log_scale_deltas: vec![0.0; 3],
        weights: vec![1.0 / 24.0; 24],
    };
    let out = deform::reference::forward(&host);
    let q = out[0].quat;
    let back = drape_shared::splat::project::quat_to_mat(
        drape_shared::splat::project::normalize_quat(q).0,
    );
    let flat: Vec<f64> = back.iter().flatten().copied().collect();
    assert!(
        rel_err(&flat, &tr[..9], 1e-6) <= 1e-9,
        "posed rotation under identity transforms is not R6(r)"
    );
}

#[test]
fn ssim_interior_matches_pytorch_msssim() {
    let ctx = gpu();
    let (w, h) = (48usize, 40usize);
    let mut rng = rand::rngs::StdRng::seed_from_u64(21);
    let target: Vec<f64> = (0..w * h * 3)
        .map(|i| {
            (0.5 + 0.35 * ((i as f64 * 0.013).sin()) + rng.random_range(-0.1..0.1)).clamp(0.0, 1.0)
        })
        .collect();
    let pred: Vec<f64> = target
        .iter()
        .map(|&v| (v + rng.random_range(-0.2..0.2)).clamp(0.0, 1.0))
        .collect();
    let p = ctx.upload("pred", &to_f32(&pred)).expect("upload");
    let t = ctx.upload("target", &to_f32(&target)).expect("upload");
    let mut s = drape_engine::ops::ssim::Ssim::new(&ctx, w as u32, h as u32).expect("ssim");
    {
        let mut rec = ctx.record("ssim torch").expect("record");
        s.record(&mut rec, &p, &t, None).expect("record");
        rec.submit_and_wait().expect("submit");
    }
    let map = to_f64(&s.read_map(&ctx).expect("map"));
    // pytorch-msssim convolves without padding ("valid"): its mean is the mean of
    // drape's map over the pixels at least 5 from every border.
    let mut sum = 0.0;
    let mut count = 0;
    for y in 5..h - 5 {
        for x in 5..w - 5 {
            for c in 0..3 {
                sum += map[(y * w + x) * 3 + c];
                count += 1;
            }
        }
    }
    let interior = sum / f64::from(count);
    let dir = case_dir("torch-cases", "ssim");
    put(&dir, "img1", &[h, w, 3], &pred);
    put(&dir, "img2", &[h, w, 3], &target);
    run_torch(&dir, serde_json::json!({ "op": "ssim" }));
    let theirs = get(&dir, "ssim")[0];
    // f32 moments on the GPU against float64: 1e-5 relative.
    assert!(
        (interior - theirs).abs() <= 1e-5 * theirs.abs(),
        "interior SSIM {interior} vs pytorch-msssim {theirs}"
    );
}

#[test]
fn chamfer_geman_mcclure_matches_pytorch() {
    use drape_engine::ops::cloth_loss::Chamfer;
    let ctx = gpu();
    let (n, m, sigma) = (700usize, 900usize, 0.05f32);
    let pred = uniform(3 * n, -0.3, 0.3, 41);
    let target = uniform(3 * m, -0.3, 0.3, 42);
    let p = ctx.upload("pred", &to_f32(&pred)).expect("upload");
    let t = ctx.upload("target", &to_f32(&target)).expect("upload");
    let mut g = ctx
        .create_buffer("grad", BufferDesc::gpu_only(12 * n as u64))
        .expect("buffer");
    let mut c = Chamfer::new(&ctx, n as u32, m as u32).expect("chamfer");
    {
        let mut rec = ctx.record("chamfer torch").expect("record");
        rec.fill(&g, 0);
        c.record(&mut rec, &p, n as u32, &t, m as u32, sigma, Some((&g, 1.0)))
            .expect("record");
        rec.submit_and_wait().expect("submit");
    }
    let loss = c.read_value(&ctx).expect("value").robust;
    let grad = to_f64(&ctx.read_buffer::<f32>(&mut g, 3 * n).expect("read"));
    let dir = case_dir("torch-cases", "chamfer");
    put(&dir, "pred", &[n, 3], &pred);
    put(&dir, "target", &[m, 3], &target);
    run_torch(&dir, serde_json::json!({ "op": "chamfer", "sigma": sigma }));
    let theirs = get(&dir, "loss")[0];
    // f32 distances on the GPU against float64 cdist: 1e-5 relative on the loss.
    assert!(
        (loss - theirs).abs() <= 1e-5 * theirs,
        "loss {loss} vs PyTorch {theirs}"
    );
    // Gradients: 1e-4 of the largest (f32 pair terms).
    let e = rel_err(&grad, &get(&dir, "gpred"), 1e-12);
    assert!(
        e <= 1e-4,
        "gradient relative error {e:e} against PyTorch autograd"
    );
}

#[test]
fn arap_matches_pytorch() {
    use drape_engine::ops::cloth_loss::Arap;
    let ctx = gpu();
    let n = 500usize;
    let positions = uniform(3 * n, -0.2, 0.2, 51);
    let mut rng = rand::rngs::StdRng::seed_from_u64(52);
    let edges: Vec<[u32; 2]> = (0..1500)
        .map(|_| {
            let a = rng.random_range(0..n as u32);
            let b = (a + rng.random_range(1..n as u32)) % n as u32;
            [a, b]
        })
        .collect();
    let p = ctx
        .upload("positions", &to_f32(&positions))
        .expect("upload");
    let mut g = ctx
        .create_buffer("grad", BufferDesc::gpu_only(12 * n as u64))
        .expect("buffer");
    let mut a = Arap::new(&ctx, n as u32, &edges).expect("arap");
    {
        let mut rec = ctx.record("arap torch").expect("record");
        rec.fill(&g, 0);
        a.record(&mut rec, &p, Some((&g, 1.0))).expect("record");
        rec.submit_and_wait().expect("submit");
    }
    let var = f64::from(a.read_stats(&ctx).expect("stats")[1]);
    let grad = to_f64(&ctx.read_buffer::<f32>(&mut g, 3 * n).expect("read"));
    let dir = case_dir("torch-cases", "arap");
    put(&dir, "positions", &[n, 3], &positions);
    put(
        &dir,
        "edges",
        &[edges.len(), 2],
        &edges
            .iter()
            .flatten()
            .map(|&v| f64::from(v))
            .collect::<Vec<_>>(),
    );
    run_torch(&dir, serde_json::json!({ "op": "arap" }));
    let theirs = get(&dir, "loss")[0];
    // The f32 variance of lengths ~0.2 (mean subtracted on the GPU): 1e-4 relative.
    assert!(
        (var - theirs).abs() <= 1e-4 * theirs,
        "variance {var} vs PyTorch {theirs}"
    );
    let e = rel_err(&grad, &get(&dir, "gpositions"), 1e-12);
    assert!(
        e <= 1e-4,
        "gradient relative error {e:e} against PyTorch autograd"
    );
}

#[test]
fn lpips_matches_the_lpips_package() {
    use drape_engine::ops::lpips::{Lpips, LpipsNet, LpipsWeights};
    let ctx = gpu();
    let (w, h) = (64usize, 48usize);
    let a = uniform(3 * w * h, 0.0, 1.0, 61);
    let b: Vec<f64> = a
        .iter()
        .zip(uniform(3 * w * h, -0.3, 0.3, 62))
        .map(|(x, d)| (x + d).clamp(0.0, 1.0))
        .collect();
    let dir = case_dir("torch-cases", "lpips");
    put(&dir, "img0", &[h, w, 3], &a);
    put(&dir, "img1", &[h, w, 3], &b);
    let converter =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../scripts/lpips-to-safetensors.py");
    run_torch(
        &dir,
        serde_json::json!({ "op": "lpips", "net": "alex", "seed": 7, "converter": converter }),
    );
    // The weights the package used, through the conversion script, read by drape.
    let weights = LpipsWeights::load(&dir.join("weights.safetensors"), LpipsNet::Alex)
        .expect("the converted weights load");
    let mut l = Lpips::new(&ctx, &weights, w as u32, h as u32).expect("lpips");
    let pa = ctx.upload("a", &to_f32(&a)).expect("upload");
    let pb = ctx.upload("b", &to_f32(&b)).expect("upload");
    let mut g = ctx
        .create_buffer("grad", BufferDesc::gpu_only(4 * a.len() as u64))
        .expect("buffer");
    {
        let mut rec = ctx.record("lpips torch").expect("record");
        rec.fill(&g, 0);
        l.record(&mut rec, &pa, &pb, Some((&g, 1.0)))
            .expect("record");
        rec.submit_and_wait().expect("submit");
    }
    let value = l.read_value(&ctx).expect("value");
    let grad = to_f64(&ctx.read_buffer::<f32>(&mut g, a.len()).expect("read"));
    let theirs = get(&dir, "lpips")[0];
    // f32 convolutions on the GPU against the package in float64: 1e-4 relative.
    assert!(
        (value - theirs).abs() <= 1e-4 * theirs,
        "LPIPS {value} vs the lpips package {theirs}"
    );
    let e = rel_err(&grad, &get(&dir, "gimg0"), 1e-12);
    assert!(
        e <= 1e-3,
        "gradient relative error {e:e} against autograd through the lpips package"
    );
}

/// The pose-dependent offsets against PyTorch: the rig's pose features against SMPL's
/// `(R_j − I)` with smplx's Rodrigues formula, and the blend (forward and basis
/// gradient, the f64 reference the GPU is checked against) against `torch.einsum`.
#[test]
fn pose_blend_matches_pytorch() {
    use drape_engine::ops::deform::{reference, POSE_BLEND_FLOATS};
    use drape_trainer::avatar::rig::Rig;
    use drape_trainer::body::procedural::{default_body, BodyOptions};
    use drape_trainer::dataset::loader::BodyParams;
    let n = 50;
    let pose_flat = uniform(72, -0.8, 0.8, 60);
    let basis = uniform(n * POSE_BLEND_FLOATS, -0.01, 0.01, 61);
    let decoded = uniform(3 * n, -0.05, 0.05, 62);
    let g = uniform(3 * n, -1.0, 1.0, 63);
    let dir = case_dir("torch-cases", "pose_blend");
    put(&dir, "pose", &[24, 3], &pose_flat);
    put(&dir, "basis", &[n, 207, 3], &basis);
    put(&dir, "decoded", &[n, 3], &decoded);
    put(&dir, "g", &[n, 3], &g);
    run_torch(&dir, serde_json::json!({ "op": "pose_blend" }));
    let (tf, to, tg) = (
        get(&dir, "features"),
        get(&dir, "offsets"),
        get(&dir, "gbasis"),
    );
    let mut pose = [glam::DVec3::ZERO; 24];
    for (j, p) in pose.iter_mut().enumerate() {
        *p = glam::DVec3::from_slice(&pose_flat[3 * j..3 * j + 3]);
    }
    let rig = Rig::new(default_body(&BodyOptions::default()), &[0.0; 10]);
    let ft = rig.frame(&BodyParams::Smpl {
        pose,
        betas: vec![0.0; 10],
        translation: glam::DVec3::ZERO,
        scale: 1.0,
    });
    // f32 features from f64 matrices: rounding only.
    assert!(
        rel_err(&to_f64(&ft.pose_features), &tf, 1e-6) <= 1e-6,
        "pose features differ from SMPL's: {}",
        rel_err(&to_f64(&ft.pose_features), &tf, 1e-6)
    );
    // Both in float64: agreement to rounding.
    let ours = reference::pose_blend_forward(&basis, &tf, &decoded);
    assert!(
        rel_err(&ours, &to, 1e-6) <= 1e-12,
        "offsets differ from PyTorch"
    );
    let ours_g = reference::pose_blend_backward(&tf, &g);
    assert!(
        rel_err(&ours_g, &tg, 1e-6) <= 1e-12,
        "basis gradient differs from PyTorch"
    );
}

#[test]
fn skinning_and_its_transform_gradient_match_pytorch() {
    use drape_engine::ops::deform::{
        reference, reference::backward as deform_backward, reference::forward as deform_forward,
    };
    use drape_shared::deform::DeformOutput;
    use drape_trainer::avatar::rig::Rig;
    use drape_trainer::body::procedural::{default_body, BodyOptions};
    use drape_trainer::dataset::loader::BodyParams;
    let n = 60;
    // A posed, translated and scaled body's 24 skinning transforms (3 x 4 each).
    let pose_flat = uniform(72, -0.6, 0.6, 70);
    let mut pose = [glam::DVec3::ZERO; 24];
    for (j, p) in pose.iter_mut().enumerate() {
        *p = glam::DVec3::from_slice(&pose_flat[3 * j..3 * j + 3]);
    }
    let rig = Rig::new(default_body(&BodyOptions::default()), &[0.0; 10]);
    let frame = rig.frame(&BodyParams::Smpl {
        pose,
        betas: vec![0.0; 10],
        translation: glam::DVec3::new(0.1, -0.2, 2.5),
        scale: 1.0,
    });
    let mut rng = rand::rngs::StdRng::seed_from_u64(71);
    let mut host = HostInputs::<f64> {
        transforms: to_f64(&frame.transforms),
        ..Default::default()
    };
    host.means = uniform(3 * n, -0.8, 0.8, 72);
    host.offsets = uniform(3 * n, -0.05, 0.05, 73);
    host.rot6d = uniform(6 * n, -1.0, 1.0, 74);
    host.log_scales = uniform(3 * n, -5.0, -3.0, 75);
    host.log_scale_deltas = uniform(3 * n, -0.5, 0.5, 76);
    for _ in 0..n {
        let q: [f64; 4] = std::array::from_fn(|_| rng.random_range(-1.0..1.0));
        let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
        host.quats.extend(q.map(|v| v / norm));
        // Softmax-like weights, some exactly zero (the forward skips those joints; the
        // gradient to their weights is still defined).
        let w: [f64; 24] = std::array::from_fn(|_| {
            if rng.random_bool(0.3) {
                0.0
            } else {
                rng.random_range(0.0..1.0)
            }
        });
        let sum: f64 = w.iter().sum::<f64>().max(1e-9);
        host.weights.extend(w.map(|v| v / sum));
    }
    let (g_mean, g_quat, g_log_scale) = (
        uniform(3 * n, -1.0, 1.0, 77),
        uniform(4 * n, -1.0, 1.0, 78),
        uniform(3 * n, -1.0, 1.0, 79),
    );
    let dir = case_dir("torch-cases", "deform");
    put(&dir, "transforms", &[24, 3, 4], &host.transforms);
    put(&dir, "means", &[n, 3], &host.means);
    put(&dir, "quats", &[n, 4], &host.quats);
    put(&dir, "offsets", &[n, 3], &host.offsets);
    put(&dir, "rot6d", &[n, 6], &host.rot6d);
    put(&dir, "log_scales", &[n, 3], &host.log_scales);
    put(&dir, "log_scale_deltas", &[n, 3], &host.log_scale_deltas);
    put(&dir, "weights", &[n, 24], &host.weights);
    put(&dir, "g_mean", &[n, 3], &g_mean);
    put(&dir, "g_quat", &[n, 4], &g_quat);
    put(&dir, "g_log_scale", &[n, 3], &g_log_scale);
    run_torch(&dir, serde_json::json!({ "op": "deform" }));

    let out = deform_forward(&host);
    let upstream: Vec<DeformOutput<f64>> = (0..n)
        .map(|i| DeformOutput {
            mean: [g_mean[3 * i], g_mean[3 * i + 1], g_mean[3 * i + 2]],
            quat: [
                g_quat[4 * i],
                g_quat[4 * i + 1],
                g_quat[4 * i + 2],
                g_quat[4 * i + 3],
            ],
            log_scale: [
                g_log_scale[3 * i],
                g_log_scale[3 * i + 1],
                g_log_scale[3 * i + 2],
            ],
        })
        .collect();
    let grads = deform_backward(&host, &upstream);
    let gather = |f: &dyn Fn(usize) -> Vec<f64>| -> Vec<f64> { (0..n).flat_map(f).collect() };
    // Both in float64: agreement to rounding (sums of 24 joints' terms).
    let checks: [(&str, Vec<f64>, f64); 8] = [
        ("mean", gather(&|i| out[i].mean.to_vec()), 1e-12),
        ("quat", gather(&|i| out[i].quat.to_vec()), 1e-12),
        (
            "gtransforms",
            reference::transform_grad(&host, &grads),
            1e-10,
        ),
        ("gmeans", gather(&|i| grads[i].mean.to_vec()), 1e-10),
        ("goffsets", gather(&|i| grads[i].offset.to_vec()), 1e-10),
        ("grot6d", gather(&|i| grads[i].rot6d.to_vec()), 1e-10),
        (
            "glog_scale_deltas",
            gather(&|i| grads[i].log_scale_delta.to_vec()),
            1e-10,
        ),
        ("gweights", gather(&|i| grads[i].weights.to_vec()), 1e-10),
    ];
    for (name, ours, tol) in checks {
        let theirs = get(&dir, name);
        assert_eq!(ours.len(), theirs.len(), "{name}: lengths");
        let e = rel_err(&ours, &theirs, 1e-6);
        assert!(
            e <= tol,
            "{name} differs from PyTorch's autograd by {e:e} (relative)"
        );
    }
}
