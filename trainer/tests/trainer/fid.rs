//! FID (`drape_trainer::metrics::fid`) against pytorch-fid's definitions, through
//! `tests/python/fid_reference.py` in the environment `scripts/torch-env.sh` makes:
//! the FID Inception's pool3 features against the same network in PyTorch (torchvision's
//! Inception-v3 with pytorch-fid's FID blocks, built by `scripts/fid-to-safetensors.py`,
//! whose seeded random weights it writes and drape reads), and the Fréchet distance
//! against pytorch-fid's `calculate_frechet_distance` (scipy's `sqrtm`) on the same
//! statistics. Pretrained weights cannot be downloaded here; random ones exercise the
//! same names, shapes and arithmetic.
//!
//! Without the environment these tests fail (they are not skipped).

use std::path::{Path, PathBuf};

use drape_tests::num::{to_f32, uniform};
use drape_tests::reference_python::{case_dir, get, put};
use drape_tests::test_picture;
use drape_trainer::metrics::fid::{
    frechet_distance, frechet_distance_of_features, FidInception, ImageRef, Statistics, FEATURE_DIM,
};

fn converter() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../scripts/fid-to-safetensors.py")
}

fn run_reference(dir: &Path, case: serde_json::Value) {
    drape_io::write(dir.join("case.json"), case.to_string()).expect("case.json");
    drape_tests::reference_python::run("fid_reference.py", &[dir.to_path_buf()]);
}

/// Rows of a (rows × cols) f64 array as f32 feature vectors.
fn rows(data: &[f64], cols: usize) -> Vec<Vec<f32>> {
    data.chunks_exact(cols).map(to_f32).collect()
}

#[test]
fn features_match_the_pytorch_fid_network() {
    // A downscale of noise, an upscale of a picture at an odd size, and the network's
    // own size (the resize is then the identity).
    let images: Vec<(&str, u32, u32, Vec<f32>)> = vec![
        (
            "noise_64x48",
            64,
            48,
            to_f32(&uniform(64 * 48 * 3, 0.0, 1.0, 91)),
        ),
        ("picture_97x61", 97, 61, test_picture(97, 61).rgb),
        ("picture_299x299", 299, 299, test_picture(299, 299).rgb),
    ];
    let dir = case_dir("fid-cases", "network");
    for (name, w, h, rgb) in &images {
        put(
            &dir,
            name,
            &[*h as usize, *w as usize, 3],
            &rgb.iter().map(|&v| f64::from(v)).collect::<Vec<_>>(),
        );
    }
    let names: Vec<&str> = images.iter().map(|i| i.0).collect();
    run_reference(
        &dir,
        serde_json::json!({ "case": "network", "converter": converter(), "seed": 5, "images": names }),
    );
    let net =
        FidInception::load(&dir.join("weights.safetensors")).expect("the converted weights load");
    let refs: Vec<ImageRef> = images
        .iter()
        .map(|(_, w, h, rgb)| ImageRef {
            rgb,
            width: *w,
            height: *h,
        })
        .collect();
    let t0 = std::time::Instant::now();
    let ours = net.features_of_images(&refs).expect("features");
    println!(
        "{} images through the FID Inception in {:.2} s",
        images.len(),
        t0.elapsed().as_secs_f64()
    );
    let mut fails = Vec::new();
    for ((name, ..), f) in images.iter().zip(&ours) {
        assert_eq!(f.len(), FEATURE_DIM);
        let theirs = get(&dir, &format!("{name}_features"));
        let theirs_f32 = get(&dir, &format!("{name}_features_f32"));
        let scale = theirs.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let err = f
            .iter()
            .zip(&theirs)
            .fold(0.0f64, |m, (&a, b)| m.max((f64::from(a) - b).abs()));
        let torch_f32 = theirs_f32
            .iter()
            .zip(&theirs)
            .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
        println!("{name}: max |ours - PyTorch f64| {err:.3e} (PyTorch f32: {torch_f32:.3e}) of max |feature| {scale:.3}: {:.2e} relative", err / scale);
        // f32 through ~95 convolutions (folded batchnorm, GEMM summation orders) against
        // float64: 1e-5 of the largest feature (measured 2e-7 to 4e-7; PyTorch's own f32
        // lands 3e-7 to 7e-7 away).
        if !(err <= 1e-5 * scale) || scale < 1e-3 {
            fails.push(format!(
                "{name}: max |ours - PyTorch| {err:e} of feature scale {scale:e}"
            ));
        }
    }
    // Identical sets: FID 0 up to roundoff. The trace term is the sum of √ of the
    // eigenvalues of M Mᵀ (3 x 3, rank 2 after centring): the zero one comes out as
    // ±ε·λmax, whose root is ~1e-8 of the scale; 1e-6 of tr Σ (measured 3e-12).
    let same = frechet_distance_of_features(&ours, &ours).expect("fid");
    let trace: f64 = Statistics::of(&ours)
        .expect("stats")
        .cov
        .iter()
        .step_by(FEATURE_DIM + 1)
        .sum();
    println!("FID of the features against themselves: {same:.3e} (tr Σ {trace:.3e})");
    if !(same.abs() <= 1e-6 * trace) {
        fails.push(format!(
            "identical feature sets give FID {same:e}, tr Σ {trace:e}"
        ));
    }
    assert!(fails.is_empty(), "{}", fails.join("\n"));
}

#[test]
fn frechet_distance_matches_scipy_sqrtm() {
    let dim = 64;
    let dir = case_dir("fid-cases", "frechet");
    // full: more images than dimensions (Σ1 Σ2 regular: scipy's sqrtm is accurate);
    // few: fewer (the product is singular, as FID's usual 2048-d case).
    run_reference(
        &dir,
        serde_json::json!({ "case": "frechet", "seed": 11, "dim": dim, "sets": { "full": [150, 120], "few": [20, 30] } }),
    );
    let results: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(dir.join("results.json")).expect("results.json"),
    )
    .expect("json");
    let r = |k: &str| {
        results[k]
            .as_f64()
            .unwrap_or_else(|| panic!("results.json has no {k}"))
    };
    let stats = |i: u32| Statistics {
        dim,
        mean: get(&dir, &format!("mu{i}")),
        cov: get(&dir, &format!("sigma{i}")),
    };
    let mut fails = Vec::new();
    let mut check = |what: &str, ours: f64, theirs: f64, tol: f64| {
        let rel = (ours - theirs).abs() / theirs.abs();
        println!("{what}: {ours:.12} vs {theirs:.12} ({rel:.2e} relative, tolerance {tol:.0e})");
        if !(rel <= tol) {
            fails.push(format!(
                "{what}: {ours} vs {theirs}, {rel:e} relative > {tol:e}"
            ));
        }
    };

    // Random SPD covariances: f64 eigendecompositions against scipy's Schur-based sqrtm;
    // both at roundoff (measured 2e-14); 1e-6.
    let ours = frechet_distance(&stats(1), &stats(2)).expect("fid");
    check("statistics (64-d SPD)", ours, r("stats"), 1e-6);

    // The script's features are f32 values (written as f64), so both sides see the same
    // numbers. More images than dimensions: ours goes through the statistics, as
    // scipy: f64 roundoff; 1e-6.
    let features = |set: &str| {
        (
            rows(&get(&dir, &format!("{set}_f1")), dim),
            rows(&get(&dir, &format!("{set}_f2")), dim),
        )
    };
    let (f1, f2) = features("full");
    check(
        "features, 150 and 120 of 64-d (through the statistics)",
        frechet_distance_of_features(&f1, &f2).expect("fid"),
        r("full"),
        1e-6,
    );

    // Fewer images than dimensions: ours (20 x 20 eigenproblem) against the SVD's
    // nuclear norm (exact), and against scipy's sqrtm of the singular 64 x 64 product,
    // which is less accurate there (measured: 5e-10 from the SVD, 4e-8 from scipy).
    let (f1, f2) = features("few");
    let gram = frechet_distance_of_features(&f1, &f2).expect("fid");
    check(
        "features, 20 and 30 of 64-d (images x images) vs SVD",
        gram,
        r("few_svd"),
        1e-6,
    );
    check(
        "features, 20 and 30 of 64-d (images x images) vs scipy sqrtm",
        gram,
        r("few"),
        1e-6,
    );
    // The two routes of ours agree: the same features through the 64 x 64 statistics,
    // whose product has 45 zero eigenvalues (rank 19), each computed as ±ε·λmax² and so
    // adding up to ~1e-8·λmax under the roots (measured 4e-8 relative); 1e-6.
    let through_stats = frechet_distance(
        &Statistics::of(&f1).expect("stats"),
        &Statistics::of(&f2).expect("stats"),
    )
    .expect("fid");
    check(
        "features, 20 and 30: images x images vs through the statistics",
        gram,
        through_stats,
        1e-6,
    );
    assert!(fails.is_empty(), "{}", fails.join("\n"));
}

#[test]
fn identical_sets_give_zero_and_a_shift_gives_its_square() {
    let (n, dim) = (25, 64);
    let f = rows(&uniform(n * dim, 0.0, 3.0, 17), dim);
    let s = Statistics::of(&f).expect("stats");
    let trace: f64 = s.cov.iter().step_by(dim + 1).sum();
    // Σ1^½ Σ Σ1^½ = Σ²: √ of its eigenvalues sum to tr Σ up to roundoff in the zero
    // eigenvalues (rank 24 of 64: 40 roots of ±ε·λmax², each ~1e-8·λmax); 1e-6 of tr Σ
    // (measured 3e-8 through the statistics, 5e-10 images x images).
    let by_stats = frechet_distance(&s, &s).expect("fid");
    let by_features = frechet_distance_of_features(&f, &f).expect("fid");
    println!("identical sets: FID {by_stats:.3e} (statistics), {by_features:.3e} (images x images), tr Σ {trace:.3e}");
    assert!(
        by_stats.abs() <= 1e-6 * trace,
        "identical statistics give FID {by_stats:e} (tr Σ {trace:e})"
    );
    assert!(
        by_features.abs() <= 1e-6 * trace,
        "identical features give FID {by_features:e} (tr Σ {trace:e})"
    );
    // Shifting one set leaves the covariance: FID = |shift|² (0.5² · 64 = 16).
    let shifted: Vec<Vec<f32>> = f
        .iter()
        .map(|v| v.iter().map(|x| x + 0.5).collect())
        .collect();
    let d = frechet_distance_of_features(&f, &shifted).expect("fid");
    println!("shifted by 0.5 in each of {dim} dimensions: FID {d:.9} (|shift|² = 16)");
    // The shift is added in f32 (features near 3 move by up to 1.2e-7 each): 1e-5
    // (measured 2e-9).
    assert!(
        (d - 16.0).abs() <= 1e-5 * 16.0,
        "a shift of 0.5 per dimension gives FID {d}, not 16"
    );
    // Fewer than two images: no covariance, an error rather than a number.
    assert!(
        frechet_distance_of_features(&f[..1], &f).is_err(),
        "one image gave an FID"
    );
}

/// Rewrites the safetensors file `from` to `to` with `edit` applied to its header (the
/// data left as it is).
fn edit_header(
    from: &Path,
    to: &Path,
    edit: impl FnOnce(&mut serde_json::Map<String, serde_json::Value>),
) {
    let bytes = std::fs::read(from).expect("weights");
    let n = u64::from_le_bytes(bytes[..8].try_into().expect("8 bytes")) as usize;
    let mut header: serde_json::Map<String, serde_json::Value> =
        serde_json::from_slice(&bytes[8..8 + n]).expect("header");
    edit(&mut header);
    let mut h = serde_json::to_vec(&header).expect("json");
    while h.len() % 8 != 0 {
        h.push(b' ');
    }
    let mut out = (h.len() as u64).to_le_bytes().to_vec();
    out.extend(h);
    out.extend(&bytes[8 + n..]);
    drape_io::write(to, out).expect("write");
}

#[test]
fn bad_weights_files_name_the_file_and_the_tensor() {
    let dir = case_dir("fid-cases", "bad-weights");
    run_reference(
        &dir,
        serde_json::json!({ "case": "network", "converter": converter(), "seed": 1, "images": [] }),
    );
    let good = dir.join("weights.safetensors");
    FidInception::load(&good).expect("the converted weights load");
    let expect_err = |path: &Path, needles: &[&str]| {
        let e = FidInception::load(path)
            .err()
            .unwrap_or_else(|| panic!("{} loaded", path.display()))
            .to_string();
        println!("{e}");
        assert!(!e.contains('\n'), "not one line: {e}");
        assert!(
            e.contains(&path.display().to_string()),
            "the message does not name the file: {e}"
        );
        for n in needles {
            assert!(e.contains(n), "the message does not say '{n}': {e}");
        }
    };
    // A tensor of the last block missing.
    let missing = dir.join("missing.safetensors");
    edit_header(&good, &missing, |h| {
        h.remove("Mixed_7c.branch_pool.bn.running_var")
            .expect("the converter writes it");
    });
    expect_err(
        &missing,
        &["Mixed_7c.branch_pool.bn.running_var", "missing"],
    );
    // A 1 x 7 kernel stored as 7 x 1 (same size, wrong shape).
    let shape = dir.join("shape.safetensors");
    edit_header(&good, &shape, |h| {
        h["Mixed_6b.branch7x7_2.conv.weight"]["shape"] = serde_json::json!([128, 128, 7, 1]);
    });
    expect_err(
        &shape,
        &[
            "Mixed_6b.branch7x7_2.conv.weight",
            "shape [128, 128, 7, 1], expected [128, 128, 1, 7]",
        ],
    );
    // Not a safetensors file; no file.
    let junk = dir.join("junk.safetensors");
    drape_io::write(&junk, b"not weights").expect("write");
    expect_err(&junk, &["not a safetensors file"]);
    expect_err(&dir.join("absent.safetensors"), &[]);
}
