//! The C ABI as its callers use it: the committed header is what cbindgen generates
//! now; the C example, compiled with the system's `cc` against it, and the Python
//! ctypes example render the tiny run's first held-out frame with the same pixels as the
//! Rust library; a panic, a null, destroyed or forged handle each return an error status.

use std::ffi::{CStr, CString};
use std::path::{Path, PathBuf};
use std::process::Command;

use drape::*;
use drape_trainer::avatar::player::{smpl_pose_of, AvatarPlayer, ViewCamera};
use drape_trainer::testing::tiny_run;

/// The C and Python examples and the library run the same kernels on the same device:
/// only a different order of equal floats could differ.
const SAME_DEVICE_TOLERANCE: f32 = 1e-5;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// Where cargo put libdrape.so (the test binary is in target/<profile>/deps).
fn lib_dir() -> PathBuf {
    std::env::current_exe().unwrap().parent().unwrap().parent().unwrap().to_path_buf()
}

fn tmp(name: &str) -> PathBuf {
    let d = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(name);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn generated_header() -> String {
    let crate_dir = env!("CARGO_MANIFEST_DIR");
    let config = cbindgen::Config::from_file(Path::new(crate_dir).join("cbindgen.toml")).expect("cbindgen.toml");
    let mut out = Vec::new();
    cbindgen::Builder::new().with_crate(crate_dir).with_config(config).generate().expect("cbindgen").write(&mut out);
    String::from_utf8(out).unwrap()
}

#[test]
fn header_is_what_cbindgen_generates_from_the_source() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("include/drape.h");
    let fresh = generated_header();
    if std::env::var("DRAPE_UPDATE_HEADER").is_ok_and(|v| v == "1") {
        std::fs::write(&path, &fresh).unwrap();
    }
    let committed = std::fs::read_to_string(&path).unwrap_or_default();
    assert!(committed == fresh, "{} is stale: a signature changed without regenerating it; run DRAPE_UPDATE_HEADER=1 cargo test -p drape-capi --test capi -- header and commit it", path.display());
}

/// The library's render of the run's default view (owned context, same device).
fn library_render(run: &Path) -> Vec<f32> {
    let ctx = drape_tests::gpu();
    let mut player = AvatarPlayer::load(&ctx, run, 1).expect("player");
    let cam = ViewCamera::from_camera(player.default_camera());
    let (w, h) = (player.default_camera().width, player.default_camera().height);
    let (pose, trans) = smpl_pose_of(player.default_body()).expect("the synthetic run has SMPL bodies");
    player.set_pose(&pose, &trans).expect("pose");
    player.render(&cam, w, h).expect("render")
}

fn read_rgba(path: &Path) -> Vec<f32> {
    let bytes = std::fs::read(path).unwrap();
    let newline = bytes.iter().position(|&b| b == b'\n').unwrap();
    bytes[newline + 1..].chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect()
}

fn compare(what: &str, got: &[f32], expected: &[f32]) {
    assert_eq!(got.len(), expected.len(), "{what}: pixel count");
    let d = got.iter().zip(expected).map(|(a, b)| (a - b).abs()).fold(0.0, f32::max);
    assert!(d <= SAME_DEVICE_TOLERANCE, "{what} differs from the library's render by {d}");
    assert!(expected.chunks(4).any(|p| p[3] > 0.5), "the avatar covers some pixels");
}

fn the_run() -> PathBuf {
    let ctx = drape_tests::gpu();
    tiny_run(&ctx).to_path_buf()
}

#[test]
fn the_c_example_compiles_against_the_header_and_renders_the_librarys_pixels() {
    let run = the_run();
    let dir = tmp("c-example");
    let exe = dir.join("render_avatar");
    let lib = lib_dir();
    let o = Command::new("cc")
        .arg("-std=c99")
        .arg("-Wall")
        .arg("-Werror")
        .arg("-I")
        .arg(root().join("capi/include"))
        .arg(root().join("examples/c/render_avatar.c"))
        .arg("-L")
        .arg(&lib)
        .arg("-ldrape")
        .arg(format!("-Wl,-rpath,{}", lib.display()))
        .arg("-o")
        .arg(&exe)
        .output()
        .expect("cc");
    assert!(o.status.success(), "cc: {}", String::from_utf8_lossy(&o.stderr));
    let out = dir.join("c.rgba32f");
    let o = Command::new(&exe).arg(&run).arg(&out).output().unwrap();
    assert!(o.status.success(), "render_avatar: {}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    compare("the C example's render", &read_rgba(&out), &library_render(&run));
}

#[test]
fn the_python_ctypes_example_renders_the_librarys_pixels() {
    let run = the_run();
    let out = tmp("python-example").join("py.rgba32f");
    let o = Command::new("python3").arg(root().join("examples/python/render_avatar.py")).arg(lib_dir().join("libdrape.so")).arg(&run).arg(&out).output().expect("python3");
    assert!(o.status.success(), "render_avatar.py: {}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    compare("the Python example's render", &read_rgba(&out), &library_render(&run));
}

fn last_error() -> String {
    // SAFETY: drape_last_error returns a valid nul-terminated string.
    unsafe { CStr::from_ptr(drape_last_error()) }.to_string_lossy().into_owned()
}

#[test]
fn null_destroyed_and_forged_handles_are_errors_and_a_missing_run_names_its_path() {
    assert_eq!(drape_avatar_destroy(std::ptr::null_mut()), drape_status::DRAPE_ERROR_INVALID_HANDLE);
    assert!(last_error().contains("handle"), "{}", last_error());
    assert_eq!(drape_context_destroy(0xdead_beef_0000_0007usize as *mut drape_context), drape_status::DRAPE_ERROR_INVALID_HANDLE);
    let name = CString::new(std::env::var("DRAPE_DEVICE").unwrap_or_default()).unwrap();
    let desc = drape_context_desc { device_name: name.as_ptr(), validation: 1 };
    // SAFETY: a valid descriptor.
    let ctx = unsafe { drape_context_create(&desc) };
    assert!(!ctx.is_null(), "{}", last_error());
    let missing = CString::new("/nonexistent/run-dir").unwrap();
    // SAFETY: a valid context handle and string.
    let avatar = unsafe { drape_avatar_load(ctx, missing.as_ptr()) };
    assert!(avatar.is_null());
    assert!(last_error().contains("/nonexistent/run-dir"), "{}", last_error());
    let camera = drape_camera { fx: 10.0, fy: 10.0, cx: 8.0, cy: 8.0, world_to_camera: [0.0; 16], near: 0.01, far: 100.0 };
    let mut pixels = vec![0f32; 16 * 16 * 4];
    // SAFETY: a forged avatar handle (never dereferenced) and valid buffers.
    let status = unsafe { drape_avatar_render(0x1_0000_0001usize as *mut drape_avatar, &camera, 16, 16, pixels.as_mut_ptr()) };
    assert_eq!(status, drape_status::DRAPE_ERROR_INVALID_HANDLE);
    assert_eq!(drape_context_destroy(ctx), drape_status::DRAPE_OK);
    assert_eq!(drape_context_destroy(ctx), drape_status::DRAPE_ERROR_INVALID_HANDLE, "destroyed twice");
}

#[test]
fn a_panic_inside_a_call_is_an_error_status_with_a_message() {
    assert_eq!(drape::testing_panic_probe(), drape_status::DRAPE_ERROR_PANIC);
    assert!(last_error().contains("a deliberate panic"), "{}", last_error());
}
