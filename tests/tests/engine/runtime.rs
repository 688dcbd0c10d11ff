//! The Vulkan runtime itself: device choice, typed errors, poisoned buffers, the
//! kernel-manifest check, per-pass timestamps, and that validation messages are caught.

use drape_engine::kernels::{check_module, Kernel};
use drape_engine::ops::scan::{ExclusiveScan, ScanVariant};
use drape_engine::{BufferDesc, Context, ContextDesc, EngineError, POISON_WORD};
use drape_tests::{gpu, has_feature, Feature};

#[test]
fn chosen_device_is_reported() {
    let gpu = gpu();
    let info = gpu.info();
    assert!(!info.name.is_empty());
    assert!(
        info.subgroup_size >= 1,
        "subgroup size {}",
        info.subgroup_size
    );
    assert!(info.api_version >= (1, 2, 0));
}

#[test]
fn unknown_device_name_is_a_typed_error_listing_devices() {
    let err = Context::new(&ContextDesc {
        device_name: Some("nosuch".into()),
        ..ContextDesc::for_tests()
    })
    .expect_err("no device is called nosuch");
    match &err {
        EngineError::DeviceNotFound {
            requested,
            available,
        } => {
            assert_eq!(requested, "nosuch");
            assert!(
                !available.is_empty(),
                "the error lists the devices there are"
            );
        }
        other => panic!("expected DeviceNotFound, got {other:?}"),
    }
    assert!(err.to_string().contains("'nosuch'"));
}

#[test]
fn device_override_by_name_picks_that_device() {
    let name = gpu().info().name.clone();
    let word = name
        .split_whitespace()
        .next()
        .expect("a device name")
        .to_uppercase();
    let ctx = Context::new(&ContextDesc {
        device_name: Some(word),
        ..ContextDesc::for_tests()
    })
    .expect("override");
    assert_eq!(ctx.info().name, name, "case-insensitive substring match");
    assert!(ctx.take_validation_messages().is_empty());
}

#[test]
fn new_buffers_are_poisoned_in_tests() {
    let gpu = gpu();
    let mut buffer = gpu
        .create_buffer("poisoned", BufferDesc::gpu_only(64))
        .expect("buffer");
    let words = gpu.read_buffer::<u32>(&mut buffer, 16).expect("read");
    assert!(words.iter().all(|&w| w == POISON_WORD), "{words:x?}");
}

#[test]
fn buffers_round_trip_through_upload_and_readback() {
    let gpu = gpu();
    let data: Vec<u32> = (0..1000).map(|i| i * 3 + 1).collect();
    let mut buffer = gpu.upload("round trip", &data).expect("upload");
    assert_eq!(
        gpu.read_buffer::<u32>(&mut buffer, 1000).expect("read"),
        data
    );
}

/// Host writes and reads through staging buffers and copies, and poisoning through
/// `vkCmdFillBuffer`: the path a discrete GPU takes, which lavapipe (all memory
/// host-visible) never takes unless forced.
#[test]
fn forced_staging_round_trips_and_poisons_through_copies() {
    let mapped = {
        let ctx = Context::new(&ContextDesc {
            force_staging: false,
            ..ContextDesc::for_tests()
        })
        .expect("context");
        let mut b = ctx
            .create_buffer("mapped?", BufferDesc::gpu_only(64))
            .expect("buffer");
        let mapped = b.host_mapped();
        drop(b);
        assert!(ctx.take_validation_messages().is_empty());
        mapped
    };
    eprintln!(
        "without the switch, device buffers are {}host-mapped on this device",
        if mapped { "" } else { "not " }
    );
    let ctx = Context::new(&ContextDesc {
        force_staging: true,
        ..ContextDesc::for_tests()
    })
    .expect("context");
    let mut fresh = ctx
        .create_buffer("poisoned by fill", BufferDesc::gpu_only(64))
        .expect("buffer");
    assert!(
        !fresh.host_mapped(),
        "the switch keeps the host out of device buffers"
    );
    let words = ctx
        .read_buffer::<u32>(&mut fresh, 16)
        .expect("read through staging");
    assert!(words.iter().all(|&w| w == POISON_WORD), "{words:x?}");
    let data: Vec<u32> = (0..1000).map(|i| i * 7 + 3).collect();
    let mut buffer = ctx.upload("staged", &data).expect("upload through staging");
    assert_eq!(
        ctx.read_buffer::<u32>(&mut buffer, 1000).expect("read"),
        data
    );
    assert_eq!(
        ctx.read_buffer_at::<u32>(&mut buffer, 990, 10)
            .expect("read part"),
        data[990..]
    );
    drop((fresh, buffer));
    let messages = ctx.take_validation_messages();
    assert!(messages.is_empty(), "{messages:?}");
}

#[test]
fn embedded_modules_match_the_manifest() {
    drape_engine::kernels::check_manifest().expect("committed SPIR-V and manifest agree");
}

/// The entry points in the kernel sources, found by reading them (not through the
/// manifest `Kernel` is generated from): each `#[spirv(compute(...))] pub fn` and each
/// entry-point macro invocation, as `module::name`.
fn entry_points_in_sources() -> std::collections::BTreeSet<String> {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shaders-rs/kernels/src");
    let mut found = std::collections::BTreeSet::new();
    for entry in std::fs::read_dir(&dir).expect("kernel sources") {
        let path = entry.expect("entry").path();
        let module = path
            .file_stem()
            .expect("stem")
            .to_string_lossy()
            .into_owned();
        let text = std::fs::read_to_string(&path).expect("read source");
        let mut after_compute = false;
        for line in text.lines().map(str::trim) {
            if line.starts_with("#[spirv(compute(") {
                after_compute = true;
            } else if after_compute && line.starts_with("pub fn ") {
                let name = line["pub fn ".len()..]
                    .split(['(', '<'])
                    .next()
                    .expect("name");
                // Inside a macro_rules! body the name is a metavariable.
                if !name.starts_with('$') {
                    found.insert(format!("{module}::{name}"));
                }
                after_compute = false;
            }
            // `rasterize_bwd_entry!(rasterize_bwd_cas, ...)` and the like (not a macro's
            // own rules calling each other, `..._entry!(@entry $name, ...)`).
            if let Some((mac, rest)) = line.split_once("_entry!(") {
                let name = rest.split(',').next().expect("name").trim();
                let is_name = name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_');
                if !mac.contains("macro_rules") && !line.starts_with("//") && is_name {
                    found.insert(format!("{module}::{name}"));
                }
            }
        }
    }
    found
}

#[test]
fn every_kernel_in_the_sources_is_embedded_and_nothing_else() {
    let sources = entry_points_in_sources();
    let embedded: std::collections::BTreeSet<String> = Kernel::ALL
        .iter()
        .map(|k| k.entry_point().to_string())
        .collect();
    assert!(sources.len() > 40, "the source scan found only {sources:?}");
    let missing: Vec<_> = sources.difference(&embedded).collect();
    let extra: Vec<_> = embedded.difference(&sources).collect();
    assert!(
        missing.is_empty() && extra.is_empty(),
        "in the sources but not embedded: {missing:?}; embedded but not in the sources: {extra:?}"
    );
    // And each embedded module is a SPIR-V module (magic number first).
    for k in Kernel::ALL {
        assert_eq!(
            k.spirv()[..4],
            0x0723_0203u32.to_le_bytes(),
            "{}",
            k.entry_point()
        );
    }
}

#[test]
fn a_module_that_disagrees_with_the_manifest_is_named() {
    // The scan's module where the sort's scatter is expected: wrong entry point.
    let err =
        check_module(Kernel::RadixSortScatter, Kernel::ScanReduce.spirv()).expect_err("mismatch");
    let text = err.to_string();
    assert!(
        matches!(err, EngineError::ShaderManifestMismatch { .. }),
        "{err:?}"
    );
    assert!(
        text.contains("radix_sort::scatter") && text.contains("scan::reduce"),
        "{text}"
    );
    // Truncated bytes are not a module at all.
    let err =
        check_module(Kernel::ScanReduce, &Kernel::ScanReduce.spirv()[..10]).expect_err("truncated");
    assert!(err.to_string().contains("scan::reduce"), "{err}");
}

#[test]
fn passes_are_timed_by_name() {
    let gpu = gpu();
    if !has_feature(&gpu, Feature::Timestamps, "passes_are_timed_by_name") {
        return;
    }
    let data: Vec<u32> = vec![1; 100_000];
    let buffer = gpu.upload("timed", &data).expect("upload");
    let plan =
        ExclusiveScan::with_variant(&gpu, "scan", 100_000, ScanVariant::Blocks).expect("plan");
    let mut rec = gpu.record("timed scan").expect("record");
    plan.record(&mut rec, &buffer, 100_000)
        .expect("record scan");
    let timings = rec.submit_and_wait().expect("submit");
    let names: Vec<&str> = timings.passes.iter().map(|(n, _)| n.as_str()).collect();
    // 100,000 elements: reduce, top-level downsweep, downsweep.
    assert_eq!(names, ["scan.reduce", "scan.downsweep", "scan.downsweep"]);
    assert!(timings
        .passes
        .iter()
        .all(|(_, ms)| ms.is_finite() && *ms >= 0.0));
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
        messages
            .iter()
            .any(|m| m.contains("VUID-VkBufferCreateInfo-size")),
        "expected the zero-size buffer to be reported, got {messages:?}"
    );
}
