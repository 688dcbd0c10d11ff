//! The Vulkan runtime itself: device choice, typed errors, poisoned buffers, the
//! kernel-manifest check, per-pass timestamps, and that validation messages are caught.

use drape_engine::kernels::{check_module, Kernel};
use drape_engine::ops::scan::ExclusiveScan;
use drape_engine::{BufferDesc, Context, ContextDesc, EngineError, POISON_WORD};
use drape_tests::gpu;

#[test]
fn chosen_device_is_reported() {
    let gpu = gpu();
    let info = gpu.info();
    assert!(!info.name.is_empty());
    assert!(info.subgroup_size >= 1, "subgroup size {}", info.subgroup_size);
    assert!(info.api_version >= (1, 2, 0));
}

#[test]
fn unknown_device_name_is_a_typed_error_listing_devices() {
    let err = Context::new(&ContextDesc { device_name: Some("nosuch".into()), ..ContextDesc::for_tests() })
        .expect_err("no device is called nosuch");
    match &err {
        EngineError::DeviceNotFound { requested, available } => {
            assert_eq!(requested, "nosuch");
            assert!(!available.is_empty(), "the error lists the devices there are");
        }
        other => panic!("expected DeviceNotFound, got {other:?}"),
    }
    assert!(err.to_string().contains("'nosuch'"));
}

#[test]
fn device_override_by_name_picks_that_device() {
    let name = gpu().info().name.clone();
    let word = name.split_whitespace().next().expect("a device name").to_uppercase();
    let ctx = Context::new(&ContextDesc { device_name: Some(word), ..ContextDesc::for_tests() }).expect("override");
    assert_eq!(ctx.info().name, name, "case-insensitive substring match");
    assert!(ctx.take_validation_messages().is_empty());
}

#[test]
fn new_buffers_are_poisoned_in_tests() {
    let gpu = gpu();
    let mut buffer = gpu.create_buffer("poisoned", BufferDesc::gpu_only(64)).expect("buffer");
    let words = gpu.read_buffer::<u32>(&mut buffer, 16).expect("read");
    assert!(words.iter().all(|&w| w == POISON_WORD), "{words:x?}");
}

#[test]
fn buffers_round_trip_through_upload_and_readback() {
    let gpu = gpu();
    let data: Vec<u32> = (0..1000).map(|i| i * 3 + 1).collect();
    let mut buffer = gpu.upload("round trip", &data).expect("upload");
    assert_eq!(gpu.read_buffer::<u32>(&mut buffer, 1000).expect("read"), data);
}

#[test]
fn embedded_modules_match_the_manifest() {
    drape_engine::kernels::check_manifest().expect("committed SPIR-V and manifest agree");
    assert!(Kernel::ALL.len() >= 4);
}

#[test]
fn a_module_that_disagrees_with_the_manifest_is_named() {
    // The scan's module where the sort's scatter is expected: wrong entry point.
    let err = check_module(Kernel::RadixSortScatter, Kernel::ScanReduce.spirv()).expect_err("mismatch");
    let text = err.to_string();
    assert!(matches!(err, EngineError::ShaderManifestMismatch { .. }), "{err:?}");
    assert!(text.contains("radix_sort::scatter") && text.contains("scan::reduce"), "{text}");
    // Truncated bytes are not a module at all.
    let err = check_module(Kernel::ScanReduce, &Kernel::ScanReduce.spirv()[..10]).expect_err("truncated");
    assert!(err.to_string().contains("scan::reduce"), "{err}");
}

#[test]
fn passes_are_timed_by_name() {
    let gpu = gpu();
    if gpu.info().timestamp_valid_bits == 0 {
        eprintln!("device has no compute timestamps; nothing to check");
        return;
    }
    let data: Vec<u32> = vec![1; 100_000];
    let buffer = gpu.upload("timed", &data).expect("upload");
    let plan = ExclusiveScan::new(&gpu, "scan", 100_000).expect("plan");
    let mut rec = gpu.record("timed scan").expect("record");
    plan.record(&mut rec, &buffer, 100_000).expect("record scan");
    let timings = rec.submit_and_wait().expect("submit");
    let names: Vec<&str> = timings.passes.iter().map(|(n, _)| n.as_str()).collect();
    // 100,000 elements: reduce, top-level downsweep, downsweep.
    assert_eq!(names, ["scan.reduce", "scan.downsweep", "scan.downsweep"]);
    assert!(timings.passes.iter().all(|(_, ms)| ms.is_finite() && *ms >= 0.0));
    assert_eq!(timings.by_name().len(), 2);
}

/// The messenger really reports: a deliberately invalid call produces a message that
/// the sink collects (so a test that caused one would fail).
#[test]
fn validation_messages_are_collected() {
    let ctx = Context::new(&ContextDesc::for_tests()).expect("context");
    ctx.provoke_validation_error_for_tests();
    let messages = ctx.take_validation_messages();
    assert!(
        messages.iter().any(|m| m.contains("VUID-VkBufferCreateInfo-size")),
        "expected the zero-size buffer to be reported, got {messages:?}"
    );
}
