//! Generates the typed kernel handles (`enum Kernel`) from the committed manifest
//! `shaders-rs/spirv/manifest.json`, embedding each module with `include_bytes!`.
//! A kernel that is not in the manifest therefore does not compile.
//!
//! It also generates each kernel's bindings struct (`kernels::<module>::<Entry>`, see
//! `src/bindings.rs`): one field per binding, typed by the access the SPIR-V declares,
//! and the push-constant type the manifest records.

use std::fmt::Write as _;
use std::path::PathBuf;

fn camel(entry: &str) -> String {
    entry
        .split(['_', ':'])
        .filter(|s| !s.is_empty())
        .map(|s| {
            let mut c = s.chars();
            c.next()
                .map(|f| f.to_ascii_uppercase().to_string() + c.as_str())
                .unwrap_or_default()
        })
        .collect()
}

fn main() {
    let spirv_dir =
        PathBuf::from(std::env::var("CARGO_MANIFEST_DIR").unwrap()).join("../shaders-rs/spirv");
    let manifest_path = spirv_dir.join("manifest.json");
    println!("cargo:rerun-if-changed={}", manifest_path.display());
    let text = std::fs::read_to_string(&manifest_path)
        .unwrap_or_else(|e| panic!("reading {}: {e}", manifest_path.display()));
    let manifest: serde_json::Value = serde_json::from_str(&text)
        .unwrap_or_else(|e| panic!("parsing {}: {e}", manifest_path.display()));
    let modules = manifest["modules"]
        .as_array()
        .expect("manifest.json: 'modules' is not an array");

    let mut variants = String::new();
    let mut all = String::new();
    let mut entry = String::new();
    let mut spirv = String::new();
    let mut wg = String::new();
    let mut bindings = String::new();
    let mut requires = String::new();
    let mut requires_ballot = String::new();
    let mut requires_int64 = String::new();
    let mut push_constant = String::new();
    // Rust module -> its kernels' bindings structs.
    let mut structs: std::collections::BTreeMap<String, String> = Default::default();
    // Which kernels run with which struct: the same bindings in the same order (name and
    // read-only alike; a texel and a storage read of one binding are alike) and the same
    // push-constant type.
    let signatures: Vec<(String, String)> = modules
        .iter()
        .map(|m| {
            let name = m["entry_point"]
                .as_str()
                .expect("manifest.json: entry_point");
            let bindings: Vec<String> = m["bindings"]
                .as_array()
                .expect("manifest.json: 'bindings' is not an array")
                .iter()
                .map(|b| {
                    let read_only = b["access"].as_str() != Some("read_write");
                    format!("{}:{read_only}", b["name"].as_str().unwrap_or_default())
                })
                .collect();
            let push = m
                .get("push_constant")
                .and_then(|v| v.as_str())
                .unwrap_or("");
            (camel(name), format!("{push}|{}", bindings.join(",")))
        })
        .collect();
    for m in modules {
        let name = m["entry_point"]
            .as_str()
            .expect("manifest.json: entry_point");
        let file = m["file"].as_str().expect("manifest.json: file");
        let size: Vec<u64> = m["workgroup_size"]
            .as_array()
            .expect("manifest.json: workgroup_size")
            .iter()
            .map(|v| v.as_u64().expect("manifest.json: workgroup_size entry"))
            .collect();
        let decls: Vec<String> = m["bindings"]
            .as_array()
            .expect("manifest.json: 'bindings' is not an array (rebuild the shaders with tools/shader-builder)")
            .iter()
            .map(|b| {
                let binding = b["name"].as_str().expect("manifest.json: binding name");
                let (read_only, texel, texel4) = match b["access"].as_str().expect("manifest.json: binding access") {
                    "read" => (true, false, false),
                    "read_write" => (false, false, false),
                    "texel" => (true, true, false),
                    "texel4" => (true, true, true),
                    other => panic!("manifest.json: {name}: binding '{binding}' has access '{other}'"),
                };
                format!("BindingDecl {{ name: {binding:?}, read_only: {read_only}, texel: {texel}, texel4: {texel4} }}")
            })
            .collect();
        let needs_atomics = m["requires"]
            .as_array()
            .map(|r| r.iter().any(|c| c.as_str() == Some("AtomicFloat32AddEXT")))
            .unwrap_or(false);
        let needs_ballot = m["requires"]
            .as_array()
            .map(|r| {
                r.iter()
                    .any(|c| c.as_str() == Some("GroupNonUniformBallot"))
            })
            .unwrap_or(false);
        let needs_int64 = m["requires"]
            .as_array()
            .map(|r| r.iter().any(|c| c.as_str() == Some("Int64")))
            .unwrap_or(false);
        let v = camel(name);
        let params = match m.get("push_constant") {
            Some(serde_json::Value::Null) => None,
            Some(serde_json::Value::String(t)) => Some(t.clone()),
            _ => panic!("manifest.json: {name}: 'push_constant' is not a type path or null (rebuild the shaders with tools/shader-builder)"),
        };
        writeln!(
            push_constant,
            "            Kernel::{v} => {:?},",
            params.as_deref().unwrap_or("")
        )
        .unwrap();
        let (module, function) = name
            .split_once("::")
            .unwrap_or_else(|| panic!("manifest.json: entry point {name} is not module::function"));
        let ty = camel(function);
        let code = structs.entry(module.to_string()).or_default();
        let mut fields = String::new();
        let mut list = Vec::new();
        for b in m["bindings"].as_array().unwrap() {
            let binding = b["name"].as_str().unwrap();
            let (access, what) = match b["access"].as_str().unwrap() {
                "read" => ("Read", "read-only storage buffer: [`Buffer::read`](crate::Buffer::read) or [`read_range`](crate::Buffer::read_range)"),
                "read_write" => ("Write", "written storage buffer: [`Buffer::write`](crate::Buffer::write) or [`write_range`](crate::Buffer::write_range)"),
                "texel" => ("Texel", "uniform texel buffer of `f32`: [`Buffer::texel`](crate::Buffer::texel)"),
                _ => ("Texel", "uniform texel buffer of 4 floats a texel: [`Buffer::texel`](crate::Buffer::texel)"),
            };
            writeln!(fields, "        /// Binding {} `{binding}`, a {what}.\n        pub {binding}: crate::bindings::{access}<'a>,", list.len()).unwrap();
            list.push(format!("self.{binding}.0"));
        }
        let params_ty = params.clone().unwrap_or_else(|| "()".to_string());
        let own_signature = &signatures.iter().find(|(k, _)| *k == v).expect("listed").1;
        let fitting: Vec<&str> = signatures
            .iter()
            .filter(|(_, sig)| sig == own_signature)
            .map(|(k, _)| k.as_str())
            .collect();
        let choice = format!("{ty}Kernel");
        let choice_variants: String = fitting
            .iter()
            .map(|k| format!("        /// [`Kernel::{k}`](crate::Kernel::{k}).\n        {k},\n"))
            .collect();
        let choice_arms: String = fitting
            .iter()
            .map(|k| format!("                {choice}::{k} => crate::Kernel::{k},\n"))
            .collect();
        let choice_back: String = fitting
            .iter()
            .map(|k| format!("                crate::Kernel::{k} => Ok({choice}::{k}),\n"))
            .collect();
        let params_doc = match &params {
            Some(t) => format!("push constants `{t}`"),
            None => "no push constants".to_string(),
        };
        write!(
            code,
            "    /// The bindings of kernel `{name}` ([`Kernel::{v}`](crate::Kernel::{v})), {params_doc}.
    pub struct {ty}<'a> {{
{fields}    }}

    /// The kernels that run with [`{ty}`]'s bindings and push constants: what
    /// [`Recording::dispatch_as`](crate::Recording::dispatch_as) takes with it.
    #[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
    pub enum {choice} {{
{choice_variants}    }}

    impl From<{choice}> for crate::Kernel {{
        fn from(kernel: {choice}) -> crate::Kernel {{
            match kernel {{
{choice_arms}            }}
        }}
    }}

    impl TryFrom<crate::Kernel> for {choice} {{
        /// The kernel, which does not run with [`{ty}`].
        type Error = crate::Kernel;
        fn try_from(kernel: crate::Kernel) -> Result<Self, crate::Kernel> {{
            match kernel {{
{choice_back}                other => Err(other),
            }}
        }}
    }}

    impl<'a> crate::bindings::Bindings<'a> for {ty}<'a> {{
        const KERNEL: crate::Kernel = crate::Kernel::{v};
        type Kernels = {choice};
        type Params = {params_ty};
        type List = [crate::bindings::Bound<'a>; {n}];
        fn into_list(self) -> Self::List {{
            [{items}]
        }}
    }}

    const _: () = assert!(
        core::mem::size_of::<{params_ty}>() <= crate::kernels::PUSH_CONSTANT_BYTES as usize,
        \"the push constants of {name} are larger than the pipeline layout's range\"
    );

",
            n = list.len(),
            items = list.join(", "),
        )
        .unwrap();
        writeln!(requires_int64, "            Kernel::{v} => {needs_int64},").unwrap();
        writeln!(requires, "            Kernel::{v} => {needs_atomics},").unwrap();
        writeln!(
            requires_ballot,
            "            Kernel::{v} => {needs_ballot},"
        )
        .unwrap();
        let path = spirv_dir.join(file);
        println!("cargo:rerun-if-changed={}", path.display());
        writeln!(variants, "    /// Entry point `{name}` ({file}).\n    {v},").unwrap();
        writeln!(all, "        Kernel::{v},").unwrap();
        writeln!(entry, "            Kernel::{v} => {name:?},").unwrap();
        writeln!(
            spirv,
            "            Kernel::{v} => include_bytes!({:?}),",
            path.display().to_string()
        )
        .unwrap();
        writeln!(
            wg,
            "            Kernel::{v} => [{}, {}, {}],",
            size[0], size[1], size[2]
        )
        .unwrap();
        writeln!(
            bindings,
            "            Kernel::{v} => &[{}],",
            decls.join(", ")
        )
        .unwrap();
    }
    let code = format!(
        "/// Every kernel of the committed manifest, as a typed handle.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Kernel {{
{variants}}}

impl Kernel {{
    /// All kernels, in manifest order.
    pub const ALL: &'static [Kernel] = &[
{all}    ];

    /// The SPIR-V entry point name.
    pub const fn entry_point(self) -> &'static str {{
        match self {{
{entry}        }}
    }}

    /// The committed SPIR-V module (little-endian words).
    pub const fn spirv(self) -> &'static [u8] {{
        match self {{
{spirv}        }}
    }}

    /// Workgroup size the manifest records.
    pub const fn workgroup_size(self) -> [u32; 3] {{
        match self {{
{wg}        }}
    }}

    /// Whether the module needs `shaderBufferFloat32AtomicAdd`.
    pub const fn requires_float_atomics(self) -> bool {{
        match self {{
{requires}        }}
    }}

    /// Whether the module uses subgroup operations (`GroupNonUniformBallot` and
    /// `GroupNonUniformShuffle`).
    pub const fn requires_subgroup_ballot(self) -> bool {{
        match self {{
{requires_ballot}        }}
    }}

    /// Whether the module uses 64-bit integers (`Int64`: the `shaderInt64` feature).
    pub const fn requires_int64(self) -> bool {{
        match self {{
{requires_int64}        }}
    }}

    /// The buffer bindings (numbered 0..n) the manifest records: the kernel parameter's
    /// name, whether the SPIR-V declares it `NonWritable` and whether it is a uniform
    /// texel buffer.
    pub const fn bindings(self) -> &'static [BindingDecl] {{
        match self {{
{bindings}        }}
    }}

    /// The path of the push-constant type the kernel's source declares (\"\" for none),
    /// as the manifest records it.
    pub const fn push_constant(self) -> &'static str {{
        match self {{
{push_constant}        }}
    }}

    /// Number of buffer bindings (numbered 0..n).
    pub const fn binding_count(self) -> u32 {{
        self.bindings().len() as u32
    }}
}}
"
    );
    let mut code = code;
    for (module, items) in &structs {
        write!(
            code,
            "/// Bindings structs of the kernels of the kernels crate's module `{module}` (see
/// [`crate::bindings`]).
pub mod {module} {{
{items}}}

"
        )
        .unwrap();
    }
    let out = PathBuf::from(std::env::var("OUT_DIR").unwrap()).join("kernels_generated.rs");
    // OUT_DIR is cargo's scratch directory, rebuilt from scratch when this fails.
    #[allow(clippy::disallowed_methods)]
    std::fs::write(out, code).unwrap();
}
