//! The shader builder: compiles `shaders-rs/kernels` to SPIR-V with rust-gpu and writes
//! one module per entry point plus `manifest.json` into `shaders-rs/spirv/`, where they
//! are committed. `--check` rebuilds into a temporary directory instead and fails,
//! naming each module, if any byte differs from what is committed (`--baseline-only`:
//! the build without extra capabilities alone). Each build declares its own device
//! capabilities (float atomics, subgroups, `Int64`), and each module records in the
//! manifest those it needs, and its push-constant type (read from the kernels' source,
//! see `push_types`), from which the engine generates each kernel's typed bindings.
//!
//! It runs on the pinned nightly of its own `rust-toolchain.toml`; the product
//! workspace never needs that toolchain.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use spirv_builder::{ModuleResult, SpirvBuilder};

use drape_shared::spirv_module;

mod push_types;

const TARGET: &str = "spirv-unknown-vulkan1.2";
/// Must match `rust-toolchain.toml` beside this crate: rust-gpu 0.11 links against it.
const TOOLCHAIN: &str = "nightly-2026-08-15";
const USAGE: &str = "\
shader-builder: compile shaders-rs/kernels to SPIR-V with rust-gpu

USAGE: shader-builder [--check [--baseline-only] | --push-types] [--shaders DIR] [--out DIR]

  (no flag)        rebuild and write DIR/spirv/*.spv and manifest.json
  --check          rebuild into a temporary directory and compare byte for byte with the
                   committed modules; exit 1 naming every module that differs
  --baseline-only  with --check: build only the baseline (no extra capability) and
                   compare its modules alone, in a fifth of the time; the other builds'
                   modules and the manifest are not checked
  --push-types     print each entry point's push-constant type as the manifest records
                   it (read from the kernels' source, no build) and exit
  --shaders DIR    the shaders-rs directory to compile (default: this repository's)
  --out DIR        where the committed modules live (default: <shaders>/spirv)";

struct Args {
    check: bool,
    baseline_only: bool,
    push_types: bool,
    shaders: PathBuf,
    out: Option<PathBuf>,
}

fn parse_args() -> Result<Args, String> {
    let mut args = Args {
        check: false,
        baseline_only: false,
        push_types: false,
        shaders: Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shaders-rs"),
        out: None,
    };
    let mut it = std::env::args().skip(1);
    while let Some(a) = it.next() {
        match a.as_str() {
            "--check" => args.check = true,
            "--baseline-only" => args.baseline_only = true,
            "--push-types" => args.push_types = true,
            "--shaders" => args.shaders = it.next().ok_or("--shaders needs a directory")?.into(),
            "--out" => args.out = Some(it.next().ok_or("--out needs a directory")?.into()),
            "-h" | "--help" => {
                println!("{USAGE}");
                std::process::exit(0);
            }
            other => return Err(format!("unknown argument '{other}' (see --help)")),
        }
    }
    if args.baseline_only && !args.check {
        return Err(
            "--baseline-only needs --check: writing one build's modules would drop the others'"
                .into(),
        );
    }
    Ok(args)
}

/// A built module and the optional device capability it needs.
struct Module {
    bytes: Vec<u8>,
    /// SPIR-V capabilities beyond the baseline (e.g. float atomics).
    requires: &'static [&'static str],
}

/// One rust-gpu build of the kernels crate. Capabilities are declared per build, not per
/// entry point, so kernels that need one exist only in the build of their cargo
/// feature, and every other module stays loadable on devices without it.
struct Flavour {
    /// The kernels crate's features (none: the baseline build).
    features: &'static [&'static str],
    capabilities: &'static [spirv_builder::Capability],
    extension: Option<&'static str>,
    /// What the manifest records as the device capabilities its new modules need.
    requires: &'static [&'static str],
}

// SampledBuffer (core Vulkan: every device takes it, no feature to enable) in every
// build: the texel-buffer reads of kernels for CPU devices (`kernels/src/texel.rs`).
const FLAVOURS: &[Flavour] = &[
    Flavour {
        features: &[],
        capabilities: &[spirv_builder::Capability::SampledBuffer],
        extension: None,
        requires: &[],
    },
    Flavour {
        features: &["float-atomics"],
        capabilities: &[
            spirv_builder::Capability::SampledBuffer,
            spirv_builder::Capability::AtomicFloat32AddEXT,
        ],
        extension: Some("SPV_EXT_shader_atomic_float_add"),
        requires: &["AtomicFloat32AddEXT"],
    },
    Flavour {
        features: &["subgroup-ballot"],
        // Ballot and Shuffle: the ballots, broadcasts, sums and votes of
        // `kernels/src/subgroup.rs` (all but the ballot by shuffles, so no Vote or
        // Arithmetic).
        capabilities: &[
            spirv_builder::Capability::GroupNonUniform,
            spirv_builder::Capability::GroupNonUniformBallot,
            spirv_builder::Capability::GroupNonUniformShuffle,
            spirv_builder::Capability::SampledBuffer,
        ],
        extension: None,
        requires: &["GroupNonUniformBallot", "GroupNonUniformShuffle"],
    },
    // Kernels that need both (the subgroup rasterizer's float-atomic backward); every
    // other module of this build was already taken from an earlier one.
    Flavour {
        features: &["subgroup-ballot", "float-atomics"],
        capabilities: &[
            spirv_builder::Capability::GroupNonUniform,
            spirv_builder::Capability::GroupNonUniformBallot,
            spirv_builder::Capability::GroupNonUniformShuffle,
            spirv_builder::Capability::SampledBuffer,
            spirv_builder::Capability::AtomicFloat32AddEXT,
        ],
        extension: Some("SPV_EXT_shader_atomic_float_add"),
        requires: &[
            "GroupNonUniformBallot",
            "GroupNonUniformShuffle",
            "AtomicFloat32AddEXT",
        ],
    },
    // Kernels that store u64s (the chunked sort's pairs, one store where two u32s take
    // two: llvmpipe loops over the lanes once per component).
    Flavour {
        features: &["int64"],
        capabilities: &[
            spirv_builder::Capability::SampledBuffer,
            spirv_builder::Capability::Int64,
        ],
        extension: None,
        requires: &["Int64"],
    },
];

/// Where the kernels' builds keep their target directories: beside the builder's own
/// build. `CARGO_TARGET_DIR`, when set, moves both (the test command points it at a cache
/// outside the clone, so that a fresh clone compiles the kernels from its own source but
/// not `core` and spirv-std for the SPIR-V target again); else `target/` here.
fn kernel_target_root() -> PathBuf {
    match std::env::var_os("CARGO_TARGET_DIR") {
        Some(dir) if !dir.is_empty() => PathBuf::from(dir),
        _ => Path::new(env!("CARGO_MANIFEST_DIR")).join("target"),
    }
}

fn build_once(shaders: &Path, flavour: &Flavour) -> Result<BTreeMap<String, Vec<u8>>, String> {
    let kernels = shaders.join("kernels");
    // One target directory per configuration, shared by every build (also of temporary
    // copies) so that spirv-std and friends are compiled once; separate per
    // configuration because cargo does not tell the two apart by their flags alone.
    let dir = if flavour.features.is_empty() {
        "spirv-kernels".to_string()
    } else {
        format!("spirv-kernels-{}", flavour.features.join("-"))
    };
    let target_dir = kernel_target_root().join(dir);
    let mut builder = SpirvBuilder::new(&kernels, TARGET);
    builder.multimodule = true;
    builder.release = true;
    // Keep the `OpName` of interface variables: the manifest names each binding after
    // the kernel parameter, and the engine names its bindings structs' fields after them.
    builder.spirv_metadata = spirv_builder::SpirvMetadata::NameVariables;
    builder.target_dir_path = Some(target_dir);
    builder.build_script.defaults = false;
    // The nested cargo must run on the pinned nightly, whatever toolchain invoked us.
    builder.toolchain_overwrite = Some(TOOLCHAIN.to_string());
    for &c in flavour.capabilities {
        builder = builder.capability(c);
    }
    if let Some(e) = flavour.extension {
        builder = builder.extension(e);
    }
    if !flavour.features.is_empty() {
        builder.shader_crate_features.features =
            flavour.features.iter().map(|f| f.to_string()).collect();
    }
    let result = builder
        .build()
        .map_err(|e| format!("rust-gpu build of {} failed: {e}", kernels.display()))?;
    let ModuleResult::MultiModule(modules) = result.module else {
        return Err("rust-gpu returned a single module; multimodule was requested".into());
    };
    let mut out = BTreeMap::new();
    for (entry, path) in modules {
        let bytes = std::fs::read(&path).map_err(|e| format!("reading {}: {e}", path.display()))?;
        out.insert(entry, bytes);
    }
    Ok(out)
}

/// Compiles the kernels crate under `shaders` in each of `flavours`: the baseline build,
/// plus the modules that exist only in a flavour with an extra capability.
/// The builds run side by side (each is one mostly single-threaded rustc and its own
/// target directory); their modules are merged in the order of `flavours`, so a module
/// comes from the first build that has it whatever finishes first.
fn compile(shaders: &Path, flavours: &[Flavour]) -> Result<BTreeMap<String, Module>, String> {
    let built: Vec<Result<BTreeMap<String, Vec<u8>>, String>> = std::thread::scope(|scope| {
        let builds: Vec<_> = flavours
            .iter()
            .map(|flavour| scope.spawn(move || build_once(shaders, flavour)))
            .collect();
        builds
            .into_iter()
            .map(|b| {
                b.join()
                    .unwrap_or_else(|_| Err("a rust-gpu build thread panicked".into()))
            })
            .collect()
    });
    let mut out: BTreeMap<String, Module> = BTreeMap::new();
    for (flavour, modules) in flavours.iter().zip(built) {
        for (entry, bytes) in modules? {
            out.entry(entry).or_insert(Module {
                bytes,
                requires: flavour.requires,
            });
        }
    }
    Ok(out)
}

/// The file a module is committed as.
fn module_file(entry: &str) -> String {
    format!("{}.spv", entry.replace("::", "-"))
}

fn manifest_json(
    modules: &BTreeMap<String, Module>,
    push: &push_types::PushTypes,
) -> Result<String, String> {
    let mut list = Vec::new();
    for (entry, module) in modules {
        let bytes = &module.bytes;
        let facts = spirv_module::inspect(bytes).map_err(|e| format!("module {entry}: {e}"))?;
        let name = String::from_utf8_lossy(facts.entry_point_name(bytes));
        if facts.entry_points != 1 || name != *entry {
            return Err(format!(
                "module {entry}: expected one OpEntryPoint named '{entry}', found {} (last '{name}')",
                facts.entry_points
            ));
        }
        let workgroup_size = facts
            .workgroup_size
            .ok_or_else(|| format!("module {entry}: no LocalSize execution mode"))?;
        let count = facts
            .contiguous_binding_count()
            .ok_or_else(|| format!("module {entry}: bindings are not numbered 0..n"))?;
        let mut bindings = Vec::new();
        for b in 0..count {
            let name = spirv_module::binding_name(bytes, b).ok_or_else(|| {
                format!("module {entry}: binding {b} has no OpName (built without NameVariables?)")
            })?;
            let access = if facts.texel4_mask & (1 << b) != 0 {
                "texel4"
            } else if facts.texel_mask & (1 << b) != 0 {
                "texel"
            } else if facts.read_only_mask & (1 << b) != 0 {
                "read"
            } else {
                "read_write"
            };
            bindings.push(
                serde_json::json!({ "name": String::from_utf8_lossy(name), "access": access }),
            );
        }
        let push_constant = push
            .get(entry)
            .ok_or_else(|| format!("module {entry}: no `#[spirv(compute(..))]` function of that name in the kernels' source"))?;
        list.push(serde_json::json!({
            "entry_point": entry,
            "push_constant": push_constant,
            "file": module_file(entry),
            "workgroup_size": workgroup_size,
            "bindings": bindings,
            "bytes": bytes.len(),
            "requires": module.requires,
        }));
    }
    let manifest = serde_json::json!({
        "generator": "tools/shader-builder (rust-gpu spirv-builder 0.11)",
        "target": TARGET,
        "modules": list,
    });
    serde_json::to_string_pretty(&manifest)
        .map(|s| s + "\n")
        .map_err(|e| e.to_string())
}

fn write(
    out: &Path,
    modules: &BTreeMap<String, Module>,
    push: &push_types::PushTypes,
) -> Result<(), String> {
    std::fs::create_dir_all(out).map_err(|e| format!("creating {}: {e}", out.display()))?;
    // Remove modules of entry points that no longer exist.
    for entry in std::fs::read_dir(out).map_err(|e| e.to_string())? {
        let path = entry.map_err(|e| e.to_string())?.path();
        if path.extension().is_some_and(|x| x == "spv") {
            std::fs::remove_file(&path).map_err(|e| format!("removing {}: {e}", path.display()))?;
        }
    }
    for (entry, module) in modules {
        let path = out.join(module_file(entry));
        std::fs::write(&path, &module.bytes)
            .map_err(|e| format!("writing {}: {e}", path.display()))?;
    }
    let manifest = manifest_json(modules, push)?;
    std::fs::write(out.join("manifest.json"), manifest).map_err(|e| e.to_string())?;
    println!(
        "wrote {} modules and manifest.json to {}",
        modules.len(),
        out.display()
    );
    Ok(())
}

/// Every difference between a fresh build and the committed files, one line each. A
/// build of some flavours only (`complete` false) checks its own modules alone: the
/// committed modules it did not build and the manifest are left unchecked.
fn compare(
    out: &Path,
    modules: &BTreeMap<String, Module>,
    push: &push_types::PushTypes,
    complete: bool,
) -> Result<Vec<String>, String> {
    let mut problems = Vec::new();
    for (entry, module) in modules {
        let bytes = &module.bytes;
        let path = out.join(module_file(entry));
        match std::fs::read(&path) {
            Ok(committed) if committed == *bytes => {}
            Ok(committed) => {
                let first = committed.iter().zip(bytes).position(|(a, b)| a != b);
                problems.push(format!(
                    "module {entry}: {} differs from a fresh build ({} committed bytes, {} built; first difference at byte {})",
                    path.display(),
                    committed.len(),
                    bytes.len(),
                    first.unwrap_or(committed.len().min(bytes.len()))
                ));
            }
            Err(_) => problems.push(format!(
                "module {entry}: {} is not committed",
                path.display()
            )),
        }
    }
    if !complete {
        return Ok(problems);
    }
    for entry in std::fs::read_dir(out).map_err(|e| format!("reading {}: {e}", out.display()))? {
        let path = entry.map_err(|e| e.to_string())?.path();
        if path.extension().is_some_and(|x| x == "spv") {
            let name = path
                .file_stem()
                .unwrap_or_default()
                .to_string_lossy()
                .replace('-', "::");
            if !modules.contains_key(&name) {
                problems.push(format!(
                    "module {name}: {} is committed but no longer built",
                    path.display()
                ));
            }
        }
    }
    let manifest = manifest_json(modules, push)?;
    let manifest_path = out.join("manifest.json");
    match std::fs::read_to_string(&manifest_path) {
        Ok(committed) if committed == manifest => {}
        _ => problems.push(format!(
            "{} differs from a fresh build",
            manifest_path.display()
        )),
    }
    Ok(problems)
}

fn run() -> Result<ExitCode, String> {
    let args = parse_args()?;
    let out = args
        .out
        .clone()
        .unwrap_or_else(|| args.shaders.join("spirv"));
    let flavours = if args.baseline_only {
        &FLAVOURS[..1]
    } else {
        FLAVOURS
    };
    if args.push_types {
        for (entry, ty) in push_types::read(&args.shaders.join("kernels").join("src"))? {
            println!("{entry}: {}", ty.as_deref().unwrap_or("-"));
        }
        return Ok(ExitCode::SUCCESS);
    }
    // Read before the (long) builds, so that a kernel source it cannot read fails at once.
    let push = push_types::read(&args.shaders.join("kernels").join("src"))?;
    let modules = compile(&args.shaders, flavours)?;
    if !args.check {
        write(&out, &modules, &push)?;
        return Ok(ExitCode::SUCCESS);
    }
    let problems = compare(&out, &modules, &push, !args.baseline_only)?;
    if problems.is_empty() {
        println!(
            "SPIR-V is fresh: {} modules match {}",
            modules.len(),
            out.display()
        );
        Ok(ExitCode::SUCCESS)
    } else {
        for p in &problems {
            eprintln!("stale SPIR-V: {p}");
        }
        eprintln!("run `cargo run --release` in tools/shader-builder and commit shaders-rs/spirv/");
        Ok(ExitCode::FAILURE)
    }
}

fn main() -> ExitCode {
    match run() {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(2)
        }
    }
}
