//! The push-constant type of every entry point, read from the kernels crate's source:
//! rust-gpu's SPIR-V keeps variable names (`NameVariables`) but not the names of struct
//! types, so the manifest takes them from the `#[spirv(push_constant)] p: &Type`
//! parameter of each `#[spirv(compute(..))]` function. Entry points written inside a
//! `macro_rules!` (their name a macro parameter) are found through the macro's
//! invocations in the same file, whose first argument is the entry point's name.
//!
//! A type is recorded as the path the engine names it by: a name the file imports
//! (`use drape_shared::adam::AdamParams`) becomes that import's path.

use std::collections::BTreeMap;
use std::path::Path;

use proc_macro2::{Delimiter, TokenStream, TokenTree};
use quote::ToTokens;

/// Entry point (`module::function`) to its push-constant type path, `None` for an
/// entry point without push constants.
pub type PushTypes = BTreeMap<String, Option<String>>;

/// Reads every `*.rs` file of `src` (the kernels crate's `src/`), one module per file.
pub fn read(src: &Path) -> Result<PushTypes, String> {
    let mut files: Vec<_> = std::fs::read_dir(src)
        .map_err(|e| format!("reading {}: {e}", src.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "rs"))
        .collect();
    files.sort();
    let mut out = PushTypes::new();
    for path in files {
        let module = path
            .file_stem()
            .unwrap_or_default()
            .to_string_lossy()
            .to_string();
        let text = std::fs::read_to_string(&path)
            .map_err(|e| format!("reading {}: {e}", path.display()))?;
        let file =
            syn::parse_file(&text).map_err(|e| format!("parsing {}: {e}", path.display()))?;
        for (entry, ty) in file_push_types(&file).map_err(|e| format!("{}: {e}", path.display()))? {
            out.insert(format!("{module}::{entry}"), ty);
        }
    }
    Ok(out)
}

fn file_push_types(file: &syn::File) -> Result<Vec<(String, Option<String>)>, String> {
    let mut uses = BTreeMap::new();
    for item in &file.items {
        if let syn::Item::Use(u) = item {
            flatten_use(&u.tree, String::new(), &mut uses);
        }
    }
    let resolve = |ty: String| -> String {
        let first = ty.split("::").next().unwrap_or_default().to_string();
        match uses.get(&first) {
            Some(full) => format!("{full}{}", &ty[first.len()..]),
            None => ty,
        }
    };
    let mut found = Vec::new();
    // Macros defining an entry point: name -> its push-constant type.
    let mut entry_macros: BTreeMap<String, Option<String>> = BTreeMap::new();
    for item in &file.items {
        match item {
            syn::Item::Fn(f) if f.attrs.iter().any(|a| is_spirv(a, "compute")) => {
                let mut ty = None;
                for input in &f.sig.inputs {
                    if let syn::FnArg::Typed(t) = input {
                        if t.attrs.iter().any(|a| is_spirv(a, "push_constant")) {
                            let syn::Type::Reference(r) = &*t.ty else {
                                return Err(format!(
                                    "{}: the push constant is not a reference",
                                    f.sig.ident
                                ));
                            };
                            ty = Some(compact(r.elem.to_token_stream()));
                        }
                    }
                }
                found.push((f.sig.ident.to_string(), ty.map(&resolve)));
            }
            syn::Item::Macro(m) if m.mac.path.is_ident("macro_rules") => {
                let Some(name) = &m.ident else { continue };
                let tokens: Vec<TokenTree> = m.mac.tokens.clone().into_iter().collect();
                if let Some(ty) = macro_entry(&tokens) {
                    entry_macros.insert(name.to_string(), ty.map(&resolve));
                }
            }
            _ => {}
        }
    }
    for item in &file.items {
        if let syn::Item::Macro(m) = item {
            let Some(name) = m.mac.path.get_ident().map(|i| i.to_string()) else {
                continue;
            };
            if let Some(ty) = entry_macros.get(&name) {
                let Some(TokenTree::Ident(entry)) = m.mac.tokens.clone().into_iter().next() else {
                    return Err(format!(
                        "an invocation of {name}! does not start with the entry point's name"
                    ));
                };
                found.push((entry.to_string(), ty.clone()));
            }
        }
    }
    Ok(found)
}

/// `use` tree to (imported name -> full path).
fn flatten_use(tree: &syn::UseTree, prefix: String, out: &mut BTreeMap<String, String>) {
    let join = |p: &str, s: &str| {
        if p.is_empty() {
            s.to_string()
        } else {
            format!("{p}::{s}")
        }
    };
    match tree {
        syn::UseTree::Path(p) => flatten_use(&p.tree, join(&prefix, &p.ident.to_string()), out),
        syn::UseTree::Name(n) => {
            out.insert(n.ident.to_string(), join(&prefix, &n.ident.to_string()));
        }
        syn::UseTree::Rename(r) => {
            out.insert(r.rename.to_string(), join(&prefix, &r.ident.to_string()));
        }
        syn::UseTree::Group(g) => g
            .items
            .iter()
            .for_each(|t| flatten_use(t, prefix.clone(), out)),
        syn::UseTree::Glob(_) => {}
    }
}

/// Whether `attr` is `#[spirv(word ..)]`.
fn is_spirv(attr: &syn::Attribute, word: &str) -> bool {
    let syn::Meta::List(list) = &attr.meta else {
        return false;
    };
    list.path.is_ident("spirv")
        && matches!(list.tokens.clone().into_iter().next(), Some(TokenTree::Ident(i)) if i == word)
}

fn compact(tokens: TokenStream) -> String {
    tokens.to_string().replace(' ', "")
}

/// In a `macro_rules!` body: if it defines a `#[spirv(compute(..))]` function, its
/// push-constant type (`Some(None)` for none); `None` when it defines no entry point.
fn macro_entry(tokens: &[TokenTree]) -> Option<Option<String>> {
    let mut compute = false;
    let mut push = None;
    scan(tokens, &mut compute, &mut push);
    compute.then_some(push)
}

fn scan(tokens: &[TokenTree], compute: &mut bool, push: &mut Option<String>) {
    for (i, t) in tokens.iter().enumerate() {
        match t {
            TokenTree::Group(g) if g.delimiter() == Delimiter::Bracket => {
                let inner: Vec<TokenTree> = g.stream().into_iter().collect();
                let spirv_word = match inner.as_slice() {
                    [TokenTree::Ident(s), TokenTree::Group(args)] if s == "spirv" => {
                        match args.stream().into_iter().next() {
                            Some(TokenTree::Ident(w)) => Some(w.to_string()),
                            _ => None,
                        }
                    }
                    _ => None,
                };
                match spirv_word.as_deref() {
                    Some("compute") => *compute = true,
                    Some("push_constant") => {
                        // `name : & Type ,`
                        let rest = &tokens[i + 1..];
                        if let [TokenTree::Ident(_), TokenTree::Punct(colon), TokenTree::Punct(amp), ty @ ..] =
                            rest
                        {
                            if colon.as_char() == ':' && amp.as_char() == '&' {
                                let end = ty
                                    .iter()
                                    .position(
                                        |t| matches!(t, TokenTree::Punct(p) if p.as_char() == ','),
                                    )
                                    .unwrap_or(ty.len());
                                *push = Some(compact(ty[..end].iter().cloned().collect()));
                            }
                        }
                    }
                    _ => scan(&inner, compute, push),
                }
            }
            TokenTree::Group(g) => {
                let inner: Vec<TokenTree> = g.stream().into_iter().collect();
                scan(&inner, compute, push);
            }
            _ => {}
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(src: &str) -> Vec<(String, Option<String>)> {
        file_push_types(&syn::parse_file(src).unwrap()).unwrap()
    }

    #[test]
    fn plain_entry_points_resolve_their_imports() {
        let found = parse(
            "use drape_shared::adam::{AdamParams, LossParams as Loss};
             #[spirv(compute(threads(256)))]
             pub fn step(#[spirv(push_constant)] p: &AdamParams, #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] x: &mut [f32]) {}
             #[spirv(compute(threads(256)))]
             pub fn loss(#[spirv(push_constant)] p: &Loss) {}
             #[spirv(compute(threads(256)))]
             pub fn full(#[spirv(push_constant)] p: &drape_shared::nn::GemmParams) {}
             #[spirv(compute(threads(256)))]
             pub fn none(#[spirv(storage_buffer, descriptor_set = 0, binding = 0)] x: &mut [f32]) {}
             pub fn helper(p: &AdamParams) {}",
        );
        assert_eq!(
            found,
            vec![
                (
                    "step".to_string(),
                    Some("drape_shared::adam::AdamParams".to_string())
                ),
                (
                    "loss".to_string(),
                    Some("drape_shared::adam::LossParams".to_string())
                ),
                (
                    "full".to_string(),
                    Some("drape_shared::nn::GemmParams".to_string())
                ),
                ("none".to_string(), None),
            ]
        );
    }

    #[test]
    fn entry_points_of_a_macro_are_named_by_its_invocations() {
        let found = parse(
            "use drape_shared::triplane::TriplaneParams;
             macro_rules! helper { ($x:expr) => { $x + 1 }; }
             macro_rules! bwd_entry {
                 ($name:ident, $t:ty) => {
                     #[spirv(compute(threads(256)))]
                     pub fn $name(#[spirv(push_constant)] p: &TriplaneParams, #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] x: &mut [$t]) {}
                 };
             }
             macro_rules! raster_entry {
                 ($name:ident) => {
                     #[spirv(compute(threads(16, 16)))]
                     pub fn $name(#[spirv(storage_buffer, descriptor_set = 0, binding = 0)] x: &mut [f32]) {}
                 };
             }
             bwd_entry!(bwd_atomic, f32);
             bwd_entry!(bwd_cas, u32);
             raster_entry!(raster);",
        );
        assert_eq!(
            found,
            vec![
                (
                    "bwd_atomic".to_string(),
                    Some("drape_shared::triplane::TriplaneParams".to_string())
                ),
                (
                    "bwd_cas".to_string(),
                    Some("drape_shared::triplane::TriplaneParams".to_string())
                ),
                ("raster".to_string(), None),
            ]
        );
    }
}
