//! The C ABI as its callers use it: the committed header is what cbindgen generates
//! now; the C example, compiled with the system's `cc` against it, and the Python
//! ctypes example render the tiny run's first held-out frame with the same pixels as the
//! Rust library; a panic, a null, destroyed or forged handle each return an error status;
//! two avatars on two threads render at the same time; the C hardening test
//! (`tests/hardening.c`) retires a panicked avatar and refuses a short output buffer.

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

/// Where libdrape.so is (the test binary is in target/<profile>/deps). `cargo test`
/// builds the crate's rlib for its tests, not the cdylib: the test command builds it with
/// the tests (`cargo build --workspace --all-targets --profile test`); a library missing
/// or older than the sources it is built from is built here with the same cargo, target
/// directory and profile (the test run holds no build lock).
fn lib_dir() -> PathBuf {
    static BUILT: std::sync::OnceLock<PathBuf> = std::sync::OnceLock::new();
    BUILT
        .get_or_init(|| {
            let exe = std::env::current_exe().unwrap();
            let profile_dir = exe.parent().unwrap().parent().unwrap().to_path_buf();
            let lib = profile_dir.join("libdrape.so");
            let built = std::fs::metadata(&lib).and_then(|m| m.modified()).ok();
            let sources = [
                "capi/src",
                "engine/src",
                "trainer/src",
                "shaders-rs/spirv",
                "shaders-rs/shared/src",
            ]
            .iter()
            .filter_map(|d| newest(&root().join(d)))
            .max();
            if built.is_some() && built >= sources {
                return profile_dir;
            }
            let target_dir = profile_dir.parent().unwrap();
            let mut cargo = Command::new(env!("CARGO"));
            cargo
                // `--tests` too, so that features resolve as for the tests: the C tests
                // call the `testing` feature's hook, and the dependencies are the ones
                // `cargo test` built.
                .args([
                    "build",
                    "--quiet",
                    "-p",
                    "drape-capi",
                    "--lib",
                    "--tests",
                    "--target-dir",
                ])
                .arg(target_dir)
                .current_dir(root());
            cargo.args([
                "--profile",
                if profile_dir.file_name().is_some_and(|n| n == "release") {
                    "release"
                } else {
                    "test"
                },
            ]);
            let o = cargo.output().expect("cargo");
            assert!(
                o.status.success(),
                "building libdrape: {}",
                String::from_utf8_lossy(&o.stderr)
            );
            assert!(lib.is_file(), "no libdrape.so in {}", profile_dir.display());
            profile_dir
        })
        .clone()
}

/// The newest modification time of any file under `dir`.
fn newest(dir: &Path) -> Option<std::time::SystemTime> {
    let mut out = None;
    for e in std::fs::read_dir(dir).ok()?.flatten() {
        let t = if e.file_type().ok()?.is_dir() {
            newest(&e.path())
        } else {
            e.metadata().ok()?.modified().ok()
        };
        out = out.max(t);
    }
    out
}

fn tmp(name: &str) -> PathBuf {
    let d = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(name);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn generated_header() -> String {
    let crate_dir = env!("CARGO_MANIFEST_DIR");
    let config = cbindgen::Config::from_file(Path::new(crate_dir).join("cbindgen.toml"))
        .expect("cbindgen.toml");
    let mut out = Vec::new();
    cbindgen::Builder::new()
        .with_crate(crate_dir)
        .with_config(config)
        .generate()
        .expect("cbindgen")
        .write(&mut out);
    String::from_utf8(out).unwrap()
}

#[test]
fn header_is_what_cbindgen_generates_from_the_source() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("include/drape.h");
    let fresh = generated_header();
    if std::env::var("DRAPE_UPDATE_HEADER").is_ok_and(|v| v == "1") {
        drape_io::write(&path, &fresh).unwrap();
    }
    let committed = std::fs::read_to_string(&path).unwrap_or_default();
    assert!(committed == fresh, "{} is stale: a signature changed without regenerating it; run DRAPE_UPDATE_HEADER=1 cargo test -p drape-capi --test capi -- header and commit it", path.display());
}

/// The library's render of the run's default view (owned context, same device).
fn library_render(run: &Path) -> Vec<f32> {
    let ctx = drape_tests::gpu();
    let mut player = AvatarPlayer::load(&ctx, run, 1).expect("player");
    let cam = ViewCamera::from_camera(player.default_camera());
    let (w, h) = (
        player.default_camera().width,
        player.default_camera().height,
    );
    let (pose, trans) =
        smpl_pose_of(player.default_body()).expect("the synthetic run has SMPL bodies");
    player.set_pose(&pose, &trans).expect("pose");
    player.render(&cam, w, h).expect("render")
}

fn read_rgba(path: &Path) -> Vec<f32> {
    let bytes = std::fs::read(path).unwrap();
    let newline = bytes.iter().position(|&b| b == b'\n').unwrap();
    bytes[newline + 1..]
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
        .collect()
}

fn compare(what: &str, got: &[f32], expected: &[f32]) {
    assert_eq!(got.len(), expected.len(), "{what}: pixel count");
    let d = got
        .iter()
        .zip(expected)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f32::max);
    assert!(
        d <= SAME_DEVICE_TOLERANCE,
        "{what} differs from the library's render by {d}"
    );
    assert!(
        expected.chunks(4).any(|p| p[3] > 0.5),
        "the avatar covers some pixels"
    );
}

fn the_run() -> PathBuf {
    let ctx = drape_tests::gpu();
    tiny_run(&ctx).to_path_buf()
}

/// Compiles the C program `source` against the header and libdrape.so into `exe`.
fn compile_c(source: &Path, exe: &Path, extra: &[&str]) {
    let lib = lib_dir();
    let o = Command::new("cc")
        .arg("-std=c99")
        .arg("-Wall")
        .arg("-Werror")
        .args(extra)
        .arg("-I")
        .arg(root().join("capi/include"))
        .arg(source)
        .arg("-L")
        .arg(&lib)
        .arg("-ldrape")
        .arg(format!("-Wl,-rpath,{}", lib.display()))
        .arg("-o")
        .arg(exe)
        .output()
        .expect("cc");
    assert!(
        o.status.success(),
        "cc {}: {}",
        source.display(),
        String::from_utf8_lossy(&o.stderr)
    );
}

#[test]
fn the_c_example_compiles_against_the_header_and_renders_the_librarys_pixels() {
    let run = the_run();
    let dir = tmp("c-example");
    let exe = dir.join("render_avatar");
    compile_c(&root().join("examples/c/render_avatar.c"), &exe, &[]);
    let out = dir.join("c.rgba32f");
    let o = Command::new(&exe).arg(&run).arg(&out).output().unwrap();
    assert!(
        o.status.success(),
        "render_avatar: {}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    compare(
        "the C example's render",
        &read_rgba(&out),
        &library_render(&run),
    );
}

#[test]
fn the_python_ctypes_example_renders_the_librarys_pixels() {
    let run = the_run();
    let out = tmp("python-example").join("py.rgba32f");
    let o = Command::new("python3")
        .arg(root().join("examples/python/render_avatar.py"))
        .arg(lib_dir().join("libdrape.so"))
        .arg(&run)
        .arg(&out)
        .output()
        .expect("python3");
    assert!(
        o.status.success(),
        "render_avatar.py: {}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    compare(
        "the Python example's render",
        &read_rgba(&out),
        &library_render(&run),
    );
}

fn last_error() -> String {
    // SAFETY: drape_last_error returns a valid nul-terminated string.
    unsafe { CStr::from_ptr(drape_last_error()) }
        .to_string_lossy()
        .into_owned()
}

#[test]
fn null_destroyed_and_forged_handles_are_errors_and_a_missing_run_names_its_path() {
    assert_eq!(
        drape_avatar_destroy(std::ptr::null_mut()),
        drape_status::DRAPE_ERROR_INVALID_HANDLE
    );
    assert!(last_error().contains("handle"), "{}", last_error());
    assert_eq!(
        drape_context_destroy(0xdead_beef_0000_0007usize as *mut drape_context),
        drape_status::DRAPE_ERROR_INVALID_HANDLE
    );
    let name = CString::new(std::env::var("DRAPE_DEVICE").unwrap_or_default()).unwrap();
    let desc = drape_context_desc {
        device_name: name.as_ptr(),
        validation: 1,
    };
    // SAFETY: a valid descriptor.
    let ctx = unsafe { drape_context_create(&desc) };
    assert!(!ctx.is_null(), "{}", last_error());
    let missing = CString::new("/nonexistent/run-dir").unwrap();
    let mut load_status = drape_status::DRAPE_OK;
    // SAFETY: a valid context handle and string.
    let avatar =
        unsafe { drape_avatar_load(ctx, missing.as_ptr(), std::ptr::null(), &mut load_status) };
    assert!(avatar.is_null());
    assert_eq!(load_status, drape_status::DRAPE_ERROR_INVALID_ARGUMENT);
    assert!(
        last_error().contains("/nonexistent/run-dir"),
        "{}",
        last_error()
    );
    let camera = drape_camera {
        fx: 10.0,
        fy: 10.0,
        cx: 8.0,
        cy: 8.0,
        world_to_camera: [0.0; 16],
        z_near: 0.01,
        z_far: 100.0,
    };
    let mut pixels = vec![0f32; 16 * 16 * 4];
    // SAFETY: a forged avatar handle (never dereferenced) and valid buffers.
    let status = unsafe {
        drape_avatar_render(
            0x1_0000_0001usize as *mut drape_avatar,
            &camera,
            16,
            16,
            pixels.as_mut_ptr(),
            pixels.len(),
        )
    };
    assert_eq!(status, drape_status::DRAPE_ERROR_INVALID_HANDLE);
    assert_eq!(drape_context_destroy(ctx), drape_status::DRAPE_OK);
    assert_eq!(
        drape_context_destroy(ctx),
        drape_status::DRAPE_ERROR_INVALID_HANDLE,
        "destroyed twice"
    );
}

#[test]
fn a_panic_inside_a_call_is_an_error_status_with_a_message() {
    assert_eq!(
        drape::testing::panic_probe(),
        drape_status::DRAPE_ERROR_PANIC
    );
    assert!(
        last_error().contains("a deliberate panic"),
        "{}",
        last_error()
    );
}

/// `drape_context_from_vulkan` over the test's own device and `drape_avatar_record` into
/// its command buffer and image: the library's pixels, and validation (synchronization
/// included) silent on the test's instance; a device said to lack `vulkanMemoryModel`
/// is refused with the feature named.
#[test]
fn from_vulkan_and_record_into_the_applications_command_buffer() {
    use drape_engine::ash::vk::{self, Handle};
    use drape_tests::host::Host;
    use std::ffi::{c_char, c_void};
    let run = the_run();
    let expected = library_render(&run);
    let host = Host::new(false);
    let extensions: Vec<*const c_char> = host.extensions.iter().map(|e| e.as_ptr()).collect();
    let f = host.features;
    let mut desc = drape_vulkan_desc {
        // SAFETY: vkGetInstanceProcAddr, as the header's pointer type (same ABI).
        get_instance_proc_addr: Some(unsafe {
            std::mem::transmute::<
                vk::PFN_vkGetInstanceProcAddr,
                unsafe extern "system" fn(
                    *mut c_void,
                    *const c_char,
                ) -> Option<unsafe extern "system" fn()>,
            >(host.entry.static_fn().get_instance_proc_addr)
        }),
        instance: host.instance.handle().as_raw() as *mut c_void,
        physical_device: host.physical.as_raw() as *mut c_void,
        device: host.device.handle().as_raw() as *mut c_void,
        queue_family: host.family,
        queue_index: 0,
        api_version: vk::API_VERSION_1_2,
        enabled_extensions: extensions.as_ptr(),
        enabled_extension_count: extensions.len() as u32,
        vulkan_memory_model: 0,
        vulkan_memory_model_device_scope: u32::from(f.vulkan_memory_model_device_scope),
        timeline_semaphore: u32::from(f.timeline_semaphore),
        shader_int64: u32::from(f.shader_int64),
        shader_buffer_float32_atomic_add: u32::from(f.shader_buffer_float32_atomic_add),
    };
    // SAFETY: the descriptor holds the test's live handles.
    let refused = unsafe { drape_context_from_vulkan(&desc) };
    assert!(refused.is_null(), "a device without vulkanMemoryModel");
    assert!(
        last_error().contains("vulkanMemoryModel"),
        "{}",
        last_error()
    );
    desc.vulkan_memory_model = 1;
    // SAFETY: as above.
    let ctx = unsafe { drape_context_from_vulkan(&desc) };
    assert!(!ctx.is_null(), "{}", last_error());
    let dir = CString::new(run.to_str().unwrap()).unwrap();
    // SAFETY: a live context and a string.
    let avatar =
        unsafe { drape_avatar_load(ctx, dir.as_ptr(), std::ptr::null(), std::ptr::null_mut()) };
    assert!(!avatar.is_null(), "{}", last_error());
    let mut camera = drape_camera {
        fx: 0.0,
        fy: 0.0,
        cx: 0.0,
        cy: 0.0,
        world_to_camera: [0.0; 16],
        z_near: 0.0,
        z_far: 0.0,
    };
    let (mut w, mut h) = (0u32, 0u32);
    let (mut pose, mut trans) = ([0f32; 72], [0f32; 3]);
    // SAFETY: room for each output.
    let status = unsafe {
        drape_avatar_default_view(
            avatar,
            &mut camera,
            &mut w,
            &mut h,
            pose.as_mut_ptr(),
            trans.as_mut_ptr(),
        )
    };
    assert_eq!(status, drape_status::DRAPE_OK, "{}", last_error());
    // SAFETY: 72 and 3 floats.
    let posed = unsafe { drape_avatar_set_pose(avatar, pose.as_ptr(), trans.as_ptr()) };
    assert_eq!(posed, drape_status::DRAPE_OK);
    let t = host.image_and_readback(w, h);
    let cmd = host.begin();
    let dst = (
        vk::ImageLayout::TRANSFER_DST_OPTIMAL,
        vk::PipelineStageFlags::TRANSFER,
        vk::AccessFlags::TRANSFER_WRITE,
    );
    host.image_barrier(
        cmd,
        t.image,
        (
            vk::ImageLayout::UNDEFINED,
            vk::PipelineStageFlags::TOP_OF_PIPE,
            vk::AccessFlags::empty(),
        ),
        dst,
    );
    // SAFETY: a recording command buffer of the context's queue family and an image of
    // the frame's size in TRANSFER_DST_OPTIMAL; the test waits for the work below.
    let status = unsafe {
        drape_avatar_record(
            avatar,
            &camera,
            w,
            h,
            cmd.as_raw() as *mut c_void,
            t.image.as_raw(),
            vk::ImageLayout::TRANSFER_DST_OPTIMAL.as_raw(),
        )
    };
    assert_eq!(status, drape_status::DRAPE_OK, "{}", last_error());
    // A layout the copy cannot take is refused before anything is recorded.
    // SAFETY: as above.
    let bad = unsafe {
        drape_avatar_record(
            avatar,
            &camera,
            w,
            h,
            cmd.as_raw() as *mut c_void,
            t.image.as_raw(),
            vk::ImageLayout::PRESENT_SRC_KHR.as_raw(),
        )
    };
    assert_eq!(bad, drape_status::DRAPE_ERROR_INVALID_ARGUMENT);
    host.record_readback(cmd, &t);
    host.submit(cmd, None);
    compare("drape_avatar_record's image", &host.read(&t), &expected);
    assert_eq!(drape_avatar_destroy(avatar), drape_status::DRAPE_OK);
    assert_eq!(drape_context_destroy(ctx), drape_status::DRAPE_OK);
    host.destroy_target(t);
    let messages = host.finish();
    assert!(
        messages.is_empty(),
        "validation on the application's instance:\n{}",
        messages.join("\n")
    );
}

/// The avatar file through the C ABI: the trainer's fixture run (see
/// `trainer/tests/fixtures/README.md`) exported, the run and its dataset deleted, and
/// the file rendered through `drape_avatar_load`, `drape_avatar_default_view`,
/// `drape_avatar_set_pose` and `drape_avatar_render`: bit-identical to the fixture's
/// renders (made through the run directory before avatar files existed).
#[test]
fn an_avatar_file_renders_the_fixture_through_the_c_abi_without_its_run_or_dataset() {
    let fixture = root().join("trainer/tests/fixtures/avatar");
    let expected: Vec<f32> = {
        let bytes = std::fs::read(fixture.join("renders.npy")).unwrap();
        let a = drape_trainer::npy::decode(&bytes, "renders.npy", None).unwrap();
        assert_eq!(a.shape, [3, 64, 64, 4]);
        a.data.iter().map(|&v| v as f32).collect()
    };
    let dir = tmp("avatar-file");
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let data = dir.join("synth");
    drape_trainer::dataset::synth::generate(
        &data,
        &drape_trainer::testing::tiny_synth_options(),
        &mut |_, _, _| {},
    )
    .unwrap();
    let run = dir.join("run");
    std::fs::create_dir_all(&run).unwrap();
    for f in ["config.json", "model.npz"] {
        std::fs::copy(fixture.join("run").join(f), run.join(f)).unwrap();
    }
    drape_trainer::avatar::run::RunInfo::new(&data, None)
        .write(&run)
        .unwrap();
    let file = dir.join("tiny.avatar");
    {
        let ctx = drape_tests::gpu();
        drape_trainer::avatar::file::AvatarFile::from_run(&ctx, &run)
            .unwrap()
            .write(&file)
            .unwrap();
    }
    std::fs::remove_dir_all(&run).unwrap();
    std::fs::remove_dir_all(&data).unwrap();

    let name = CString::new(std::env::var("DRAPE_DEVICE").unwrap_or_default()).unwrap();
    let desc = drape_context_desc {
        device_name: name.as_ptr(),
        validation: 1,
    };
    // SAFETY: a valid descriptor.
    let ctx = unsafe { drape_context_create(&desc) };
    assert!(!ctx.is_null(), "{}", last_error());
    let path = CString::new(file.to_str().unwrap()).unwrap();
    // SAFETY: a valid context handle and string.
    let avatar =
        unsafe { drape_avatar_load(ctx, path.as_ptr(), std::ptr::null(), std::ptr::null_mut()) };
    assert!(!avatar.is_null(), "{}", last_error());
    let mut cam = drape_camera {
        fx: 0.0,
        fy: 0.0,
        cx: 0.0,
        cy: 0.0,
        world_to_camera: [0.0; 16],
        z_near: 0.0,
        z_far: 0.0,
    };
    let (mut w, mut h) = (0u32, 0u32);
    let mut pose = [0f32; 72];
    let mut trans = [0f32; 3];
    // SAFETY: a valid avatar handle and room for each value.
    let s = unsafe {
        drape_avatar_default_view(
            avatar,
            &mut cam,
            &mut w,
            &mut h,
            pose.as_mut_ptr(),
            trans.as_mut_ptr(),
        )
    };
    assert_eq!(s, drape_status::DRAPE_OK, "{}", last_error());
    // The fixture's three images (trainer/tests/trainer/avatar_file.rs `renders`).
    let k = 64.0 / w as f32;
    cam.fx *= k;
    cam.fy *= k;
    cam.cx *= k;
    cam.cy *= k;
    let mut side = cam;
    side.world_to_camera[3] += 0.3;
    let mut bent = pose;
    bent[3 * 16 + 2] -= 0.8;
    bent[3 * 17 + 2] += 0.8;
    bent[3 * 4] += 0.6;
    let mut got = Vec::new();
    // The first two in the pose the avatar loads in (the file's, in f64: setting it
    // again through the f32 pose would round it), the third set as the fixture set it.
    for (camera, p) in [(&cam, None), (&side, None), (&cam, Some(&bent))] {
        if let Some(p) = p {
            // SAFETY: a valid avatar handle, 72 and 3 floats.
            let s = unsafe { drape_avatar_set_pose(avatar, p.as_ptr(), trans.as_ptr()) };
            assert_eq!(s, drape_status::DRAPE_OK, "{}", last_error());
        }
        let mut pixels = vec![0f32; 64 * 64 * 4];
        // SAFETY: a valid avatar handle and a buffer of 64 x 64 x 4 floats.
        let s = unsafe {
            drape_avatar_render(avatar, camera, 64, 64, pixels.as_mut_ptr(), pixels.len())
        };
        assert_eq!(s, drape_status::DRAPE_OK, "{}", last_error());
        got.extend(pixels);
    }
    assert_eq!(drape_avatar_destroy(avatar), drape_status::DRAPE_OK);
    assert_eq!(drape_context_destroy(ctx), drape_status::DRAPE_OK);
    assert_eq!(got.len(), expected.len());
    if let Some(i) = (0..got.len()).find(|&i| got[i].to_bits() != expected[i].to_bits()) {
        panic!(
            "value {i} (image {}) is {}, the fixture has {}",
            i / (64 * 64 * 4),
            got[i],
            expected[i]
        );
    }
}

/// `tests/hardening.c`, compiled as a `<windows.h>` user would (`near` and `far` defined
/// away, `-Wpedantic`): version and status strings, a 1x1 image into 3 floats refused
/// with nothing written, frames in flight out of range refused at load, and a panic
/// inside an avatar call retiring that avatar (and only it).
#[test]
fn the_c_hardening_test_passes() {
    let run = the_run();
    let exe = tmp("c-hardening").join("hardening");
    compile_c(
        &root().join("capi/tests/hardening.c"),
        &exe,
        &["-Wpedantic", "-Dnear=", "-Dfar="],
    );
    let o = Command::new(&exe).arg(&run).output().unwrap();
    assert!(
        o.status.success(),
        "hardening: {}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
}

#[test]
fn version_and_status_strings() {
    // SAFETY: both return static nul-terminated strings.
    let version = unsafe { CStr::from_ptr(drape_version()) };
    assert_eq!(version.to_str().unwrap(), env!("CARGO_PKG_VERSION"));
    for (status, name) in [
        (drape_status::DRAPE_OK, "DRAPE_OK"),
        (
            drape_status::DRAPE_ERROR_INVALID_ARGUMENT,
            "DRAPE_ERROR_INVALID_ARGUMENT",
        ),
        (
            drape_status::DRAPE_ERROR_INVALID_HANDLE,
            "DRAPE_ERROR_INVALID_HANDLE",
        ),
        (drape_status::DRAPE_ERROR_ENGINE, "DRAPE_ERROR_ENGINE"),
        (drape_status::DRAPE_ERROR_PANIC, "DRAPE_ERROR_PANIC"),
        (
            drape_status::DRAPE_ERROR_OUT_OF_MEMORY,
            "DRAPE_ERROR_OUT_OF_MEMORY",
        ),
    ] {
        // SAFETY: as above.
        let text = unsafe { CStr::from_ptr(drape_status_str(status as i32)) };
        assert!(
            text.to_str().unwrap().starts_with(&format!("{name}: ")),
            "{text:?}"
        );
    }
    // SAFETY: as above.
    let unknown = unsafe { CStr::from_ptr(drape_status_str(-1)) };
    assert_eq!(unknown.to_str().unwrap(), "unknown status");
}

/// A context on the test device with validation, and its validation messages' sink.
fn validated_context() -> (
    *mut drape_context,
    std::sync::Arc<drape_engine::validation::ValidationSink>,
) {
    let name = CString::new(std::env::var("DRAPE_DEVICE").unwrap_or_default()).unwrap();
    let desc = drape_context_desc {
        device_name: name.as_ptr(),
        validation: 1,
    };
    // SAFETY: a valid descriptor.
    let ctx = unsafe { drape_context_create(&desc) };
    assert!(!ctx.is_null(), "{}", last_error());
    let sink = drape::testing::validation_sink(ctx).expect("opened with validation");
    (ctx, sink)
}

/// Loads `run` on `ctx` and poses it as its default view; returns the avatar and that
/// view's camera.
fn posed_avatar(ctx: *mut drape_context, run: &Path) -> (*mut drape_avatar, drape_camera) {
    let dir = CString::new(run.to_str().unwrap()).unwrap();
    // SAFETY: a live context and a string.
    let avatar =
        unsafe { drape_avatar_load(ctx, dir.as_ptr(), std::ptr::null(), std::ptr::null_mut()) };
    assert!(!avatar.is_null(), "{}", last_error());
    let mut camera = drape_camera {
        fx: 0.0,
        fy: 0.0,
        cx: 0.0,
        cy: 0.0,
        world_to_camera: [0.0; 16],
        z_near: 0.0,
        z_far: 0.0,
    };
    let (mut w, mut h) = (0u32, 0u32);
    let (mut pose, mut trans) = ([0f32; 72], [0f32; 3]);
    // SAFETY: room for each output; 72 and 3 floats.
    unsafe {
        let s = drape_avatar_default_view(
            avatar,
            &mut camera,
            &mut w,
            &mut h,
            pose.as_mut_ptr(),
            trans.as_mut_ptr(),
        );
        assert_eq!(s, drape_status::DRAPE_OK, "{}", last_error());
        let s = drape_avatar_set_pose(avatar, pose.as_ptr(), trans.as_ptr());
        assert_eq!(s, drape_status::DRAPE_OK, "{}", last_error());
    }
    // The camera scaled from the run's image width to 1 pixel wide.
    let k = 1.0 / w as f32;
    camera.fx *= k;
    camera.fy *= k;
    camera.cx *= k;
    camera.cy *= k;
    (avatar, camera)
}

/// Renders `side` x `side` pixels of the unit-width `camera` (scaled to that size).
fn render_square(avatar: usize, camera: &drape_camera, side: u32) -> Vec<f32> {
    let mut cam = *camera;
    for v in [&mut cam.fx, &mut cam.fy, &mut cam.cx, &mut cam.cy] {
        *v *= side as f32;
    }
    let mut pixels = vec![0f32; 4 * (side * side) as usize];
    // SAFETY: a live avatar handle and a buffer of its length.
    let s = unsafe {
        drape_avatar_render(
            avatar as *mut drape_avatar,
            &cam,
            side,
            side,
            pixels.as_mut_ptr(),
            pixels.len(),
        )
    };
    assert_eq!(s, drape_status::DRAPE_OK, "{}", last_error());
    pixels
}

/// Per-avatar locking: while avatar A renders 1024x1024 on one thread, avatar B's 64x64
/// render on another thread (started once A's call has begun) returns first. Each avatar
/// has its own context, so its own queue: lavapipe runs one queue's submissions one
/// after another on one thread, and two avatars sharing a queue would take turns on
/// the device whatever the library's locks. Both were rendered once before at 64x64, so
/// that neither call compiles pipelines. Validation reports nothing.
#[test]
fn two_avatars_on_two_threads_render_at_the_same_time() {
    use std::sync::atomic::{AtomicUsize, Ordering};
    let run = the_run();
    let (ctx_a, sink_a) = validated_context();
    let (ctx_b, sink_b) = validated_context();
    let (a, camera) = posed_avatar(ctx_a, &run);
    let (b, _) = posed_avatar(ctx_b, &run);
    let (a, b) = (a as usize, b as usize);
    let warm_a = render_square(a, &camera, 64);
    let warm_b = render_square(b, &camera, 64);
    assert_eq!(warm_a, warm_b, "two avatars of one run, one view");
    let finished = AtomicUsize::new(0);
    let (started_tx, started_rx) = std::sync::mpsc::channel();
    let (rank_a, rank_b) = std::thread::scope(|s| {
        let big = s.spawn(|| {
            started_tx.send(()).unwrap();
            let pixels = render_square(a, &camera, 1024);
            (finished.fetch_add(1, Ordering::SeqCst), pixels)
        });
        started_rx.recv().unwrap();
        let small = s.spawn(|| {
            let pixels = render_square(b, &camera, 64);
            (finished.fetch_add(1, Ordering::SeqCst), pixels)
        });
        let (rank_b, pixels_b) = small.join().unwrap();
        let (rank_a, pixels_a) = big.join().unwrap();
        assert_eq!(pixels_b, warm_b, "B's render beside A's");
        assert!(
            pixels_a.chunks(4).any(|p| p[3] > 0.5),
            "A covers some pixels"
        );
        (rank_a, rank_b)
    });
    assert_eq!(
        (rank_b, rank_a),
        (0, 1),
        "avatar B's 64x64 render returned after avatar A's 1024x1024 one: the avatars took turns"
    );
    for avatar in [a, b] {
        assert_eq!(
            drape_avatar_destroy(avatar as *mut drape_avatar),
            drape_status::DRAPE_OK
        );
    }
    for ctx in [ctx_a, ctx_b] {
        assert_eq!(drape_context_destroy(ctx), drape_status::DRAPE_OK);
    }
    let messages: Vec<String> = [sink_a, sink_b].iter().flat_map(|s| s.drain()).collect();
    assert!(messages.is_empty(), "validation:\n{}", messages.join("\n"));
}

/// Two avatars on one context (one queue) on two threads at once: each renders what it
/// renders alone, and validation (the queue's external synchronisation included)
/// reports nothing.
#[test]
fn two_avatars_on_one_context_render_from_two_threads() {
    let run = the_run();
    let (ctx, sink) = validated_context();
    let (a, camera) = posed_avatar(ctx, &run);
    let (b, _) = posed_avatar(ctx, &run);
    let (a, b) = (a as usize, b as usize);
    let alone = render_square(a, &camera, 48);
    std::thread::scope(|s| {
        let threads = [a, b].map(|avatar| {
            let camera = &camera;
            s.spawn(move || {
                (0..3)
                    .map(|_| render_square(avatar, camera, 48))
                    .collect::<Vec<_>>()
            })
        });
        for t in threads {
            for pixels in t.join().unwrap() {
                assert_eq!(pixels, alone, "a render beside the other avatar's");
            }
        }
    });
    for avatar in [a, b] {
        assert_eq!(
            drape_avatar_destroy(avatar as *mut drape_avatar),
            drape_status::DRAPE_OK
        );
    }
    assert_eq!(drape_context_destroy(ctx), drape_status::DRAPE_OK);
    let messages = sink.drain();
    assert!(messages.is_empty(), "validation:\n{}", messages.join("\n"));
}

/// Premultiplied means every colour value within [0, alpha] and alpha within [0, 1], as
/// the header promises: through the C ABI, the test run with its SH biases raised (whose
/// colours rise far above their alpha: the player's clamp, which the trainer's
/// `avatar_file` test checks over more views, bounds them) at its default view, at rest
/// and posed (the fixture's bend: elbows and a knee), at 32x32 and 96x96.
#[test]
fn every_colour_value_is_within_zero_and_its_alpha() {
    let run = the_run();
    let hot = tmp("premultiplied").join("hot.avatar");
    drape_trainer::testing::write_saturated_avatar(&drape_tests::gpu(), &run, &hot)
        .expect("the saturated avatar");
    let (ctx, sink) = validated_context();
    let (avatar, camera) = posed_avatar(ctx, &hot);
    let mut at_alpha = 0;
    for posed in [false, true] {
        if posed {
            pose_like(avatar, avatar, |pose| {
                pose[3 * 16 + 2] -= 0.8;
                pose[3 * 17 + 2] += 0.8;
                pose[3 * 4] += 0.6;
            });
        }
        for side in [32, 96] {
            let pixels = render_square(avatar as usize, &camera, side);
            at_alpha += drape_tests::premultiplied_at_alpha(
                &pixels,
                &format!("posed {posed}, {side}x{side}"),
            );
        }
    }
    assert!(
        at_alpha > 0,
        "no colour reaches its alpha: the biases did not saturate it"
    );
    assert_eq!(drape_avatar_destroy(avatar), drape_status::DRAPE_OK);
    assert_eq!(drape_context_destroy(ctx), drape_status::DRAPE_OK);
    let messages = sink.drain();
    assert!(messages.is_empty(), "validation:\n{}", messages.join("\n"));
}

/// Poses `avatar` as `like`'s default view is posed (its pose and translation), the pose
/// changed by `edit` first.
fn pose_like(
    avatar: *mut drape_avatar,
    like: *mut drape_avatar,
    edit: impl FnOnce(&mut [f32; 72]),
) {
    let (mut pose, mut trans) = ([0f32; 72], [0f32; 3]);
    // SAFETY: live avatars, room for 72 and 3 floats.
    unsafe {
        let s = drape_avatar_default_view(
            like,
            std::ptr::null_mut(),
            std::ptr::null_mut(),
            std::ptr::null_mut(),
            pose.as_mut_ptr(),
            trans.as_mut_ptr(),
        );
        assert_eq!(s, drape_status::DRAPE_OK, "{}", last_error());
        edit(&mut pose);
        let s = drape_avatar_set_pose(avatar, pose.as_ptr(), trans.as_ptr());
        assert_eq!(s, drape_status::DRAPE_OK, "{}", last_error());
    }
}

/// `drape_load_options`: frames in flight as asked (the player's count), out of range
/// refused; `DRAPE_COLOUR_LINEAR` renders each pixel's colour / alpha decoded with the
/// sRGB transfer function (computed here in f64) times alpha, alpha unchanged; an
/// unknown encoding is refused, and so is recording a linear avatar.
#[test]
fn load_options_choose_frames_in_flight_and_the_colour_encoding() {
    let run = the_run();
    let (ctx, sink) = validated_context();
    let dir = CString::new(run.to_str().unwrap()).unwrap();
    let load = |options: drape_load_options| {
        let mut status = drape_status::DRAPE_ERROR_ENGINE;
        // SAFETY: a live context, a string, valid options and room for a status.
        let avatar = unsafe { drape_avatar_load(ctx, dir.as_ptr(), &options, &mut status) };
        (avatar, status)
    };
    for (frames, expected) in [(0, Some(2)), (1, Some(1)), (3, Some(3)), (9, None)] {
        let (avatar, status) = load(drape_load_options {
            frames_in_flight: frames,
            colour: 0,
        });
        assert_eq!(
            drape::testing::frames_in_flight(avatar),
            expected,
            "{frames}"
        );
        if expected.is_none() {
            assert_eq!(status, drape_status::DRAPE_ERROR_INVALID_ARGUMENT);
            assert!(
                last_error().contains("frames_in_flight"),
                "{}",
                last_error()
            );
        } else {
            assert_eq!(status, drape_status::DRAPE_OK);
            assert_eq!(drape_avatar_destroy(avatar), drape_status::DRAPE_OK);
        }
    }
    let (refused, status) = load(drape_load_options {
        frames_in_flight: 0,
        colour: 2,
    });
    assert!(refused.is_null());
    assert_eq!(status, drape_status::DRAPE_ERROR_INVALID_ARGUMENT);

    let (srgb, camera) = posed_avatar(ctx, &run);
    let (linear, status) = load(drape_load_options {
        frames_in_flight: 0,
        colour: drape_colour::DRAPE_COLOUR_LINEAR as u32,
    });
    assert_eq!(status, drape_status::DRAPE_OK, "{}", last_error());
    pose_like(linear, srgb, |_| {});
    let encoded = render_square(srgb as usize, &camera, 48);
    let decoded = render_square(linear as usize, &camera, 48);
    let mut mid_tones = 0;
    for (e, d) in encoded.chunks(4).zip(decoded.chunks(4)) {
        assert_eq!(e[3].to_bits(), d[3].to_bits(), "alpha unchanged");
        for c in 0..3 {
            let a = f64::from(e[3]);
            let expected = if a > 0.0 {
                let v = f64::from(e[c]) / a;
                let v = if v <= 0.04045 {
                    v / 12.92
                } else {
                    ((v + 0.055) / 1.055).powf(2.4)
                };
                v * a
            } else {
                0.0
            };
            // f32 arithmetic against f64: a few ulps of values at most 1.
            assert!(
                (f64::from(d[c]) - expected).abs() <= 1e-6,
                "{e:?} decoded as {d:?}, expected channel {c} {expected}"
            );
            if e[3] > 0.5 && e[c] / e[3] > 0.1 && e[c] / e[3] < 0.9 {
                mid_tones += 1;
                assert!(d[c] < e[c], "a mid tone is darker in linear: {e:?} {d:?}");
            }
        }
    }
    assert!(mid_tones > 0, "the view has mid tones to compare");
    // SAFETY: a linear avatar is refused before the (dummy, never used) command buffer
    // and image are looked at.
    let record = unsafe {
        drape_avatar_record(
            linear,
            &camera,
            48,
            48,
            std::ptr::dangling_mut::<std::ffi::c_void>(),
            1,
            7,
        )
    };
    assert_eq!(record, drape_status::DRAPE_ERROR_INVALID_ARGUMENT);
    assert!(
        last_error().contains("DRAPE_COLOUR_LINEAR"),
        "{}",
        last_error()
    );
    for avatar in [srgb, linear] {
        assert_eq!(drape_avatar_destroy(avatar), drape_status::DRAPE_OK);
    }
    assert_eq!(drape_context_destroy(ctx), drape_status::DRAPE_OK);
    let messages = sink.drain();
    assert!(messages.is_empty(), "validation:\n{}", messages.join("\n"));
}

/// `drape_avatar_load_memory`: the run exported to an avatar file's bytes, loaded from
/// memory, renders bit-identically to the run loaded from its path; the bytes truncated
/// are refused as an invalid argument naming them.
#[test]
fn an_avatar_loads_from_memory() {
    let run = the_run();
    let bytes = {
        let ctx = drape_tests::gpu();
        drape_trainer::avatar::file::AvatarFile::from_run(&ctx, &run)
            .unwrap()
            .to_bytes()
            .unwrap()
    };
    let (ctx, sink) = validated_context();
    let (from_path, camera) = posed_avatar(ctx, &run);
    let mut status = drape_status::DRAPE_ERROR_ENGINE;
    // SAFETY: a live context and `bytes.len()` readable bytes.
    let from_memory = unsafe {
        drape_avatar_load_memory(
            ctx,
            bytes.as_ptr(),
            bytes.len(),
            std::ptr::null(),
            &mut status,
        )
    };
    assert_eq!(status, drape_status::DRAPE_OK, "{}", last_error());
    pose_like(from_memory, from_path, |_| {});
    let expected = render_square(from_path as usize, &camera, 48);
    let got = render_square(from_memory as usize, &camera, 48);
    assert!(
        got.iter()
            .zip(&expected)
            .all(|(a, b)| a.to_bits() == b.to_bits()),
        "the avatar from memory renders other pixels than from its path"
    );
    // SAFETY: as above, half the bytes.
    let truncated = unsafe {
        drape_avatar_load_memory(
            ctx,
            bytes.as_ptr(),
            bytes.len() / 2,
            std::ptr::null(),
            &mut status,
        )
    };
    assert!(truncated.is_null());
    assert_eq!(status, drape_status::DRAPE_ERROR_INVALID_ARGUMENT);
    assert!(last_error().contains("in memory"), "{}", last_error());
    for avatar in [from_path, from_memory] {
        assert_eq!(drape_avatar_destroy(avatar), drape_status::DRAPE_OK);
    }
    assert_eq!(drape_context_destroy(ctx), drape_status::DRAPE_OK);
    let messages = sink.drain();
    assert!(messages.is_empty(), "validation:\n{}", messages.join("\n"));
}
