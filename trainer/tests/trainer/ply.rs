//! 3DGS PLY import and export: exact round trips, SH degrees, and bad files that must
//! each give an error naming the file and the problem.

use std::path::{Path, PathBuf};

use drape_engine::ops::splat::scene::GaussianCloud;
use drape_trainer::ply::{read, write};

fn temp(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("drape-ply-tests-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

#[test]
fn round_trip_is_exact_for_every_degree() {
    for degree in 0..=3 {
        let cloud = GaussianCloud::random(257, degree, 2.0, (-1.0, 1.0), 0.1, u64::from(degree));
        let path = temp(&format!("round-trip-{degree}.ply"));
        write(&path, &cloud).expect("write");
        let back = read(&path).expect("read");
        assert_eq!(back.sh_degree, degree);
        assert_eq!(back.len(), cloud.len());
        assert_eq!(bits(&back.means), bits(&cloud.means));
        assert_eq!(bits(&back.log_scales), bits(&cloud.log_scales));
        assert_eq!(bits(&back.quats), bits(&cloud.quats));
        assert_eq!(bits(&back.opacity_logits), bits(&cloud.opacity_logits));
        assert_eq!(bits(&back.sh), bits(&cloud.sh));
    }
}

/// A file laid out as the reference implementation writes it, built by hand here:
/// f_rest channel-major, so f_rest_0..14 are the red channel's 15 coefficients.
#[test]
fn reads_the_reference_layout_channel_major() {
    let names: Vec<String> = [
        "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2",
    ]
    .iter()
    .map(|s| s.to_string())
    .chain((0..45).map(|i| format!("f_rest_{i}")))
    .chain(
        [
            "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
        ]
        .iter()
        .map(|s| s.to_string()),
    )
    .collect();
    let mut header = String::from(
        "ply\nformat binary_little_endian 1.0\ncomment written by a test\nelement vertex 1\n",
    );
    for n in &names {
        header += &format!("property float {n}\n");
    }
    header += "end_header\n";
    let mut bytes = header.into_bytes();
    for (i, _) in names.iter().enumerate() {
        bytes.extend_from_slice(&(i as f32).to_le_bytes());
    }
    let path = temp("reference-layout.ply");
    drape_io::write(&path, bytes).unwrap();
    let cloud = read(&path).expect("read");
    assert_eq!(cloud.sh_degree, 3);
    // Coefficient k of channel c sits at f_rest_{c*15 + k-1}, i.e. column 9 + c*15 + k-1.
    let sh = |k: usize, c: usize| cloud.sh[3 * k + c];
    assert_eq!(sh(0, 0), 6.0);
    assert_eq!(sh(0, 2), 8.0);
    assert_eq!(sh(1, 0), 9.0);
    assert_eq!(sh(1, 1), 24.0);
    assert_eq!(sh(15, 2), (9 + 2 * 15 + 14) as f32);
    assert_eq!(cloud.opacity_logits[0], 54.0);
    assert_eq!(cloud.quats, vec![58.0, 59.0, 60.0, 61.0]);
}

fn write_degree0(name: &str) -> (PathBuf, Vec<u8>) {
    let cloud = GaussianCloud::random(10, 0, 1.0, (0.0, 1.0), 0.1, 9);
    let path = temp(name);
    write(&path, &cloud).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    (path, bytes)
}

fn expect_error(path: &Path, needle: &str) {
    let err = read(path)
        .expect_err("a bad file must not load")
        .to_string();
    assert!(
        err.contains(&path.display().to_string()),
        "the error names the file: {err}"
    );
    assert!(err.contains(needle), "'{needle}' not in: {err}");
}

#[test]
fn truncated_file_is_reported() {
    let (path, bytes) = write_degree0("truncated.ply");
    drape_io::write(&path, &bytes[..bytes.len() - 7]).unwrap();
    expect_error(&path, "truncated");
    drape_io::write(&path, &bytes[..40]).unwrap();
    expect_error(&path, "end_header");
}

#[test]
fn missing_property_is_named() {
    let (path, bytes) = write_degree0("missing.ply");
    let text = String::from_utf8_lossy(&bytes).replacen(
        "property float scale_1\n",
        "property float other\n",
        1,
    );
    drape_io::write(&path, text.as_bytes()).unwrap();
    expect_error(&path, "missing property 'scale_1'");
}

#[test]
fn wrong_property_type_is_named() {
    let (path, bytes) = write_degree0("wrong-type.ply");
    let end = bytes
        .windows(11)
        .position(|w| w == b"end_header\n")
        .unwrap()
        + 11;
    let header = String::from_utf8_lossy(&bytes[..end]).replacen(
        "property float opacity",
        "property uchar opacity",
        1,
    );
    let mut out = header.into_bytes();
    out.extend_from_slice(&bytes[end..]);
    drape_io::write(&path, out).unwrap();
    expect_error(&path, "property 'opacity' has type 'uchar'");
}

#[test]
fn vertex_count_larger_than_the_data_is_reported() {
    let (path, bytes) = write_degree0("count.ply");
    let text =
        String::from_utf8_lossy(&bytes).replacen("element vertex 10\n", "element vertex 11\n", 1);
    // Same byte length: only the count changed.
    let mut out = bytes.clone();
    out[..text.len().min(bytes.len())]
        .copy_from_slice(&text.as_bytes()[..text.len().min(bytes.len())]);
    drape_io::write(&path, out).unwrap();
    expect_error(&path, "11 vertices");
}

#[test]
fn missing_file_is_named() {
    let path = temp("does-not-exist.ply");
    expect_error(&path, "No such file");
}
