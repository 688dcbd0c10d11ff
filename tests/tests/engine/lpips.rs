//! LPIPS: the GPU network against the CPU reference (f64) for AlexNet and VGG16, its
//! gradient against f64 central differences of the reference, the extremes (identical
//! and constant images, an image below the network's minimum), and the weights file's
//! bad inputs (missing tensor, wrong shape, truncated body). Weights are random (He
//! initialisation, seeded): pretrained ones cannot be downloaded here.

use std::collections::BTreeMap;
use std::path::PathBuf;

use drape_engine::ops::lpips::{reference, Lpips, LpipsNet, LpipsWeights};
use drape_engine::{BufferDesc, Context};
use drape_tests::gpu;
use drape_tests::num::{to_f32, to_f64, uniform};
use rand::{Rng, SeedableRng};

pub(crate) fn random_tensors(net: LpipsNet, seed: u64) -> BTreeMap<String, (Vec<usize>, Vec<f32>)> {
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    net.tensors()
        .into_iter()
        .map(|(name, shape)| {
            let n: usize = shape.iter().product();
            let data: Vec<f32> = if name.starts_with("lin") {
                // The learned linear layers are non-negative.
                (0..n).map(|_| rng.random_range(0.0..0.2)).collect()
            } else if name.ends_with(".bias") {
                (0..n).map(|_| rng.random_range(-0.05..0.05)).collect()
            } else {
                let fan_in: usize = shape[1..].iter().product();
                let bound = (6.0 / fan_in as f32).sqrt();
                (0..n).map(|_| rng.random_range(-bound..bound)).collect()
            };
            (name, (shape, data))
        })
        .collect()
}

pub(crate) fn weights_file(
    name: &str,
    tensors: &BTreeMap<String, (Vec<usize>, Vec<f32>)>,
) -> PathBuf {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("lpips");
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join(name);
    LpipsWeights::write_safetensors(&path, tensors).expect("write");
    path
}

fn image(w: u32, h: u32, seed: u64) -> Vec<f64> {
    uniform((3 * w * h) as usize, 0.0, 1.0, seed)
}

fn gpu_lpips(
    ctx: &Context,
    weights: &LpipsWeights,
    a: &[f64],
    b: &[f64],
    w: u32,
    h: u32,
) -> (f64, Vec<f64>) {
    let mut l = Lpips::new(ctx, weights, w, h).expect("lpips");
    let pa = ctx.upload("a", &to_f32(a)).expect("upload");
    let pb = ctx.upload("b", &to_f32(b)).expect("upload");
    let mut g = ctx
        .create_buffer("grad", BufferDesc::gpu_only(4 * a.len() as u64))
        .expect("buffer");
    {
        let mut rec = ctx.record("lpips test").expect("record");
        rec.fill(&g, 0);
        l.record(&mut rec, &pa, &pb, Some((&g, 1.0)))
            .expect("record");
        rec.submit_and_wait().expect("submit");
    }
    (
        l.read_value(ctx).expect("value"),
        to_f64(&ctx.read_buffer::<f32>(&mut g, a.len()).expect("read")),
    )
}

#[test]
fn lpips_gpu_matches_cpu_reference_alex_and_vgg() {
    let ctx = gpu();
    for (net, w, h) in [
        (LpipsNet::Alex, 64u32, 48u32),
        (LpipsNet::Alex, 31, 31),
        (LpipsNet::Vgg16, 32, 24),
    ] {
        let weights = LpipsWeights::load(
            &weights_file("ref.safetensors", &random_tensors(net, 3)),
            net,
        )
        .expect("load");
        let (a, b) = (image(w, h, 1), image(w, h, 2));
        let cpu = reference(&weights, &a, &b, w, h).expect("reference");
        let (g, _) = gpu_lpips(&ctx, &weights, &a, &b, w, h);
        // f32 convolutions over up to 4,608 terms per output through 5-13 layers:
        // ~1e-6 relative measured; 1e-4 leaves room for other summation orders.
        assert!(
            (g - cpu).abs() <= 1e-4 * cpu.abs(),
            "{net:?} {w}x{h}: GPU {g} vs CPU {cpu}"
        );
        assert!(
            cpu > 0.0,
            "{net:?}: a zero distance between different images"
        );
    }
}

#[test]
fn lpips_gradient_matches_central_differences() {
    let ctx = gpu();
    let net = LpipsNet::Alex;
    let weights = LpipsWeights::load(
        &weights_file("fd.safetensors", &random_tensors(net, 5)),
        net,
    )
    .expect("load");
    let (w, h) = (35u32, 33u32);
    let (a, b) = (image(w, h, 7), image(w, h, 8));
    let (_, grad) = gpu_lpips(&ctx, &weights, &a, &b, w, h);
    let scale = grad.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    assert!(scale > 0.0, "zero gradient");
    let mut rng = rand::rngs::StdRng::seed_from_u64(9);
    let eps = 1e-5;
    let mut worst = 0.0f64;
    // 60 sampled inputs (the reference forward is too slow for all 3,465 here).
    for _ in 0..60 {
        let i = rng.random_range(0..a.len());
        let (mut p, mut m) = (a.clone(), a.clone());
        p[i] += eps;
        m[i] -= eps;
        let fd = (reference(&weights, &p, &b, w, h).unwrap()
            - reference(&weights, &m, &b, w, h).unwrap())
            / (2.0 * eps);
        worst = worst.max((fd - grad[i]).abs());
    }
    // The GPU gradient in f32 against f64 differences (ReLU and max-pool switches are
    // not crossed by ±1e-5 on random inputs): 1e-3 of the largest gradient.
    assert!(
        worst <= 1e-3 * scale,
        "worst difference {worst:e} (largest gradient {scale:e})"
    );
}

#[test]
fn lpips_extremes() {
    let ctx = gpu();
    let net = LpipsNet::Alex;
    let weights = LpipsWeights::load(
        &weights_file("ext.safetensors", &random_tensors(net, 11)),
        net,
    )
    .expect("load");
    let (w, h) = (40u32, 40u32);
    // Identical images: zero distance, zero gradient. Exactly on a CPU device. A GPU
    // may fuse one of the two divisions of `f0/(n0+ε) - f1/(n1+ε)` into the
    // subtraction, which leaves that division's rounding error (|d| ≤ 2^-22 |u| a
    // channel, Σ u² ≤ 1 a pixel): a distance of at most 2^-44 max w per layer, under
    // 1e-12 for these weights, and a gradient that small against a real one (an H200
    // gave 3.2e-16 where the exact check failed).
    let a = image(w, h, 1);
    let (v, g) = gpu_lpips(&ctx, &weights, &a, &a, w, h);
    if ctx.info().kind == drape_engine::DeviceKind::Cpu {
        assert_eq!(v, 0.0);
        assert!(g.iter().all(|&x| x == 0.0));
    } else {
        let (_, g_real) = gpu_lpips(&ctx, &weights, &a, &image(w, h, 2), w, h);
        let largest = |g: &[f64]| g.iter().fold(0.0f64, |m, x| m.max(x.abs()));
        assert!(v.abs() <= 1e-12, "identical images: distance {v:e}");
        // The real gradient comes from d ~ 0.1 |u| or more; identical ones from d ≤ 2^-22 |u|.
        assert!(
            largest(&g) <= 1e-5 * largest(&g_real),
            "identical images: gradient {:e} against {:e}",
            largest(&g),
            largest(&g_real)
        );
    }
    // Constant images (features may vanish: zero norms): finite.
    let (black, white) = (vec![0.0; a.len()], vec![1.0; a.len()]);
    let (v, g) = gpu_lpips(&ctx, &weights, &black, &white, w, h);
    assert!(
        v.is_finite() && g.iter().all(|x| x.is_finite()),
        "constant images: {v}"
    );
    // Below the stack's minimum (AlexNet: 31 px): an error naming the size.
    let err = Lpips::new(&ctx, &weights, 30, 64).err().expect("too small");
    assert!(
        matches!(err, drape_engine::EngineError::ImageTooSmall { .. }),
        "{err:?}"
    );
    let err = err.to_string();
    assert!(err.contains("31x31") && err.contains("30x64"), "{err}");
}

#[test]
fn bad_weights_files_name_the_file_and_tensor() {
    let net = LpipsNet::Alex;
    let good = random_tensors(net, 1);
    let mut missing = good.clone();
    missing.remove("lin3.model.1.weight");
    let e = LpipsWeights::load(&weights_file("missing.safetensors", &missing), net)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("missing.safetensors")
            && e.contains("lin3.model.1.weight")
            && e.contains("missing"),
        "{e}"
    );
    let mut shape = good.clone();
    shape.get_mut("net.slice2.3.bias").unwrap().0 = vec![191];
    shape.get_mut("net.slice2.3.bias").unwrap().1.pop();
    let e = LpipsWeights::load(&weights_file("shape.safetensors", &shape), net)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("shape.safetensors") && e.contains("net.slice2.3.bias") && e.contains("[191]"),
        "{e}"
    );
    // Truncated: the last tensor's bytes cut off.
    let path = weights_file("truncated.safetensors", &good);
    let bytes = std::fs::read(&path).unwrap();
    drape_io::write(&path, &bytes[..bytes.len() - 100]).unwrap();
    let e = LpipsWeights::load(&path, net).unwrap_err().to_string();
    assert!(
        e.contains("truncated.safetensors") && e.contains("truncated"),
        "{e}"
    );
    assert!(e.contains("tensor '"), "the message names the tensor: {e}");
    // Not a safetensors file at all.
    let junk = path.with_file_name("junk.safetensors");
    drape_io::write(&junk, b"PK\x03\x04 a zip").unwrap();
    let e = LpipsWeights::load(&junk, net).unwrap_err().to_string();
    assert!(
        e.contains("junk.safetensors") && e.contains("not a safetensors"),
        "{e}"
    );
    // A VGG file read as AlexNet: a missing tensor, named.
    let vgg = weights_file("vgg.safetensors", &random_tensors(LpipsNet::Vgg16, 2));
    let e = LpipsWeights::load(&vgg, net).unwrap_err().to_string();
    assert!(
        e.contains("net.slice1.0.weight") || e.contains("tensor '"),
        "{e}"
    );
}
