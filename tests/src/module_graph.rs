//! A crate's module graph, read from its source text, and the circles in it: the check
//! behind the trainer's and the engine's `module_graph` tests (no two modules of a crate
//! import each other, directly or through others).
//!
//! A module is a file (`foo.rs` or `foo/mod.rs`); module A depends on module B when A's
//! file names anything in B's file, through `crate::`, `super::`, `self::`, a child
//! module's name or a `use` alias. Module declarations (`mod foo;`) are not dependencies,
//! and a path through a `pub use` re-export counts as a dependency on the module that
//! defines the item, so a re-export never hides an edge nor adds one.
//!
//! The graph is read from the source text (comments and string literals blanked first),
//! so it needs no compiler support and names the file and line of each edge of a cycle.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// A module's path from the crate root: `[]` is `lib.rs`, `["avatar", "train"]` is
/// `avatar/train.rs`.
pub type ModPath = Vec<String>;

#[derive(Clone, Debug, PartialEq)]
enum Token {
    Ident(String),
    PathSep,
    Punct(char),
}

/// Where a reference was written, to explain an edge.
#[derive(Clone, Debug)]
pub struct Site {
    pub file: String,
    pub line: usize,
}

/// The dependency graph: for each module, the modules it names and where first.
#[derive(Default)]
pub struct ModuleGraph {
    pub edges: BTreeMap<ModPath, BTreeMap<ModPath, Site>>,
}

/// One source file, tokenized, with its module path.
struct SourceModule {
    path: ModPath,
    file: String,
    tokens: Vec<(Token, usize)>,
}

fn module_path(relative: &Path) -> ModPath {
    let mut parts: Vec<String> = relative
        .iter()
        .map(|p| p.to_string_lossy().into_owned())
        .collect();
    let last = parts.pop().expect("a file name");
    let stem = last.strip_suffix(".rs").expect("a .rs file").to_string();
    if stem != "mod" && !(parts.is_empty() && stem == "lib") {
        parts.push(stem);
    }
    parts
}

/// Replaces comments, string, byte-string and char literals by spaces, keeping newlines
/// so that line numbers survive. Lifetimes (`'a`) are kept.
fn blank_comments_and_literals(src: &str) -> String {
    let c: Vec<char> = src.chars().collect();
    let mut out = String::with_capacity(src.len());
    let blank = |ch: char| if ch == '\n' { '\n' } else { ' ' };
    let mut i = 0;
    while i < c.len() {
        let next = c.get(i + 1).copied();
        if c[i] == '/' && next == Some('/') {
            while i < c.len() && c[i] != '\n' {
                out.push(' ');
                i += 1;
            }
        } else if c[i] == '/' && next == Some('*') {
            let mut depth = 0;
            while i < c.len() {
                if c[i] == '/' && c.get(i + 1) == Some(&'*') {
                    depth += 1;
                    out.push_str("  ");
                    i += 2;
                } else if c[i] == '*' && c.get(i + 1) == Some(&'/') {
                    depth -= 1;
                    out.push_str("  ");
                    i += 2;
                    if depth == 0 {
                        break;
                    }
                } else {
                    out.push(blank(c[i]));
                    i += 1;
                }
            }
        } else if let Some(hashes) = raw_string_start(&c, i) {
            // r"..." / r#"..."# / br"...": ends at a quote followed by as many hashes.
            let open = c[i..].iter().position(|&ch| ch == '"').unwrap() + i;
            for _ in i..=open {
                out.push(' ');
            }
            i = open + 1;
            loop {
                if i >= c.len() {
                    break;
                }
                if c[i] == '"' && (1..=hashes).all(|k| c.get(i + k) == Some(&'#')) {
                    for _ in 0..=hashes {
                        out.push(' ');
                    }
                    i += hashes + 1;
                    break;
                }
                out.push(blank(c[i]));
                i += 1;
            }
        } else if c[i] == '"' {
            out.push(' ');
            i += 1;
            while i < c.len() && c[i] != '"' {
                if c[i] == '\\' {
                    out.push(' ');
                    i += 1;
                }
                if i < c.len() {
                    out.push(blank(c[i]));
                    i += 1;
                }
            }
            out.push(' ');
            i += 1;
        } else if c[i] == '\'' && is_char_literal(&c, i) {
            out.push(' ');
            i += 1;
            while i < c.len() && c[i] != '\'' {
                if c[i] == '\\' {
                    out.push(' ');
                    i += 1;
                }
                out.push(' ');
                i += 1;
            }
            out.push(' ');
            i += 1;
        } else if is_ident_char(c[i]) {
            // Copy a whole identifier, so that the `r` of `r"` is only seen at its start.
            while i < c.len() && is_ident_char(c[i]) {
                out.push(c[i]);
                i += 1;
            }
        } else {
            out.push(c[i]);
            i += 1;
        }
    }
    out
}

/// The number of `#` of a raw (byte) string starting at `i`, if one starts there.
fn raw_string_start(c: &[char], i: usize) -> Option<usize> {
    let mut j = i;
    if c.get(j) == Some(&'b') {
        j += 1;
    }
    if c.get(j) != Some(&'r') {
        return None;
    }
    j += 1;
    let mut hashes = 0;
    while c.get(j) == Some(&'#') {
        hashes += 1;
        j += 1;
    }
    (c.get(j) == Some(&'"')).then_some(hashes)
}

/// `'x'`, `'\n'`, `'\u{1F600}'` are char literals; `'a` in `&'a T` is a lifetime.
fn is_char_literal(c: &[char], i: usize) -> bool {
    match c.get(i + 1) {
        Some('\\') => true,
        Some(_) => c.get(i + 2) == Some(&'\''),
        None => false,
    }
}

fn is_ident_char(ch: char) -> bool {
    ch.is_alphanumeric() || ch == '_'
}

fn tokenize(src: &str) -> Vec<(Token, usize)> {
    let c: Vec<char> = src.chars().collect();
    let mut tokens = Vec::new();
    let (mut i, mut line) = (0, 1);
    while i < c.len() {
        let ch = c[i];
        if ch == '\n' {
            line += 1;
            i += 1;
        } else if ch.is_whitespace() {
            i += 1;
        } else if ch == ':' && c.get(i + 1) == Some(&':') {
            tokens.push((Token::PathSep, line));
            i += 2;
        } else if ch == '$' && c[i + 1..].starts_with(&['c', 'r', 'a', 't', 'e']) {
            // `$crate` in a macro is this crate's root.
            i += 1;
        } else if is_ident_char(ch) {
            let start = i;
            while i < c.len() && is_ident_char(c[i]) {
                i += 1;
            }
            let word: String = c[start..i].iter().collect();
            if word.starts_with(|d: char| d.is_ascii_digit()) {
                tokens.push((Token::Punct('0'), line));
            } else {
                tokens.push((Token::Ident(word), line));
            }
        } else {
            tokens.push((Token::Punct(ch), line));
            i += 1;
        }
    }
    tokens
}

fn ident(t: Option<&(Token, usize)>) -> Option<&str> {
    match t {
        Some((Token::Ident(s), _)) => Some(s),
        _ => None,
    }
}

/// Expands a `use` tree starting at `tokens[*i]` into its leaves: (path, name bound),
/// the name being `None` for a glob. Leaves `*i` after the tree.
fn parse_use_tree(
    tokens: &[(Token, usize)],
    i: &mut usize,
    prefix: &[String],
    out: &mut Vec<(Vec<String>, Option<String>)>,
) {
    let mut path = prefix.to_vec();
    if tokens.get(*i).map(|t| &t.0) == Some(&Token::PathSep) {
        *i += 1; // a leading `::` names an external crate
        path.push("::".into());
    }
    loop {
        match tokens.get(*i).map(|t| &t.0) {
            Some(Token::Ident(s)) => {
                path.push(s.clone());
                *i += 1;
            }
            Some(Token::Punct('{')) => {
                *i += 1;
                loop {
                    match tokens.get(*i).map(|t| &t.0) {
                        Some(Token::Punct('}')) => {
                            *i += 1;
                            return;
                        }
                        Some(Token::Punct(',')) => *i += 1,
                        None => return,
                        _ => parse_use_tree(tokens, i, &path, out),
                    }
                }
            }
            Some(Token::Punct('*')) => {
                *i += 1;
                out.push((path, None));
                return;
            }
            _ => return,
        }
        if tokens.get(*i).map(|t| &t.0) == Some(&Token::PathSep) {
            *i += 1;
            continue;
        }
        // The end of a leaf: `path`, `path as name` or `prefix::{self}`.
        let mut name = path.last().cloned();
        if ident(tokens.get(*i)) == Some("as") {
            name = ident(tokens.get(*i + 1)).map(str::to_string);
            *i += 2;
        }
        if path.last().map(String::as_str) == Some("self") {
            path.pop();
            if name.as_deref() == Some("self") {
                name = path.last().cloned();
            }
        }
        out.push((path, name));
        return;
    }
}

impl SourceModule {
    fn new(path: ModPath, file: String, src: &str) -> Self {
        SourceModule {
            path,
            file,
            tokens: tokenize(&blank_comments_and_literals(src)),
        }
    }

    /// Every path written in the file: `use` leaves (with the name they bind and
    /// whether they are re-exported) and paths in code, each with its line and the depth
    /// of inline modules (`mod tests { .. }`) it sits in.
    fn paths(&self) -> Vec<WrittenPath> {
        let t = &self.tokens;
        let mut found = Vec::new();
        let mut inline_mods: Vec<usize> = Vec::new(); // brace depths of open inline mods
        let mut depth = 0usize;
        let mut i = 0;
        while i < t.len() {
            match &t[i].0 {
                Token::Punct('{') => {
                    depth += 1;
                    i += 1;
                }
                Token::Punct('}') => {
                    depth = depth.saturating_sub(1);
                    if inline_mods.last() == Some(&depth) {
                        inline_mods.pop();
                    }
                    i += 1;
                }
                Token::Ident(w) if w == "mod" => {
                    if ident(t.get(i + 1)).is_some()
                        && t.get(i + 2).map(|x| &x.0) == Some(&Token::Punct('{'))
                    {
                        inline_mods.push(depth);
                    }
                    i += 2;
                }
                Token::Ident(w) if w == "use" => {
                    let exported = i > 0
                        && (ident(t.get(i - 1)) == Some("pub")
                            || (t[i - 1].0 == Token::Punct(')')
                                && (1..i).rev().take(5).any(|k| ident(t.get(k)) == Some("pub"))));
                    let line = t[i].1;
                    i += 1;
                    let mut leaves = Vec::new();
                    parse_use_tree(t, &mut i, &[], &mut leaves);
                    for (segments, name) in leaves {
                        found.push(WrittenPath {
                            segments,
                            binds: Some(name),
                            exported,
                            line,
                            inline_depth: inline_mods.len(),
                        });
                    }
                }
                Token::Ident(w) => {
                    let after_sep = i > 0 && t[i - 1].0 == Token::PathSep;
                    let mut segments = vec![w.clone()];
                    let line = t[i].1;
                    let mut j = i + 1;
                    while t.get(j).map(|x| &x.0) == Some(&Token::PathSep) {
                        match ident(t.get(j + 1)) {
                            Some(s) => {
                                segments.push(s.to_string());
                                j += 2;
                            }
                            None => break,
                        }
                    }
                    if !after_sep && segments.len() > 1 {
                        found.push(WrittenPath {
                            segments,
                            binds: None,
                            exported: false,
                            line,
                            inline_depth: inline_mods.len(),
                        });
                    }
                    i = j;
                }
                _ => i += 1,
            }
        }
        found
    }
}

struct WrittenPath {
    segments: Vec<String>,
    /// `Some` for a `use` leaf: the name it binds (`None` for a glob).
    binds: Option<Option<String>>,
    exported: bool,
    line: usize,
    inline_depth: usize,
}

/// What the modules export and import, to resolve paths.
struct Resolver {
    modules: BTreeSet<ModPath>,
    /// `pub use` re-exports: module → name → absolute path.
    reexports: BTreeMap<ModPath, BTreeMap<String, Vec<String>>>,
}

impl Resolver {
    /// Makes `segments`, written in module `at` (inside `inline_depth` inline modules)
    /// with `aliases` in scope, absolute; `None` for a path outside the crate or one
    /// that stays inside the file.
    fn absolute(
        &self,
        at: &ModPath,
        inline_depth: usize,
        aliases: &BTreeMap<String, Vec<String>>,
        segments: &[String],
    ) -> Option<Vec<String>> {
        let first = segments[0].as_str();
        match first {
            "crate" => Some(segments[1..].to_vec()),
            "self" => (inline_depth == 0).then(|| [at.as_slice(), &segments[1..]].concat()),
            "super" => {
                let supers = segments.iter().take_while(|s| *s == "super").count();
                if supers <= inline_depth {
                    return None; // `super` of an inline module: the file itself
                }
                let up = supers - inline_depth;
                let base = &at[..at.len().checked_sub(up)?];
                Some([base, &segments[supers..]].concat())
            }
            "::" => None,
            _ => {
                let mut child = at.clone();
                child.push(first.to_string());
                if inline_depth == 0 && self.modules.contains(&child) {
                    Some([at.as_slice(), segments].concat())
                } else {
                    aliases
                        .get(first)
                        .map(|target| [target.as_slice(), &segments[1..]].concat())
                }
            }
        }
    }

    /// The module that defines what absolute path `path` names, following re-exports:
    /// the longest module prefix, or the module itself for a path to a module. Returns
    /// the module and whether the path names the module itself.
    fn defining_module(&self, path: &[String]) -> (ModPath, bool) {
        let mut path = path.to_vec();
        for _ in 0..16 {
            let len = (0..=path.len())
                .rev()
                .find(|&n| self.modules.contains(&path[..n]))
                .unwrap();
            let module = path[..len].to_vec();
            if len == path.len() {
                return (module, true);
            }
            match self.reexports.get(&module).and_then(|r| r.get(&path[len])) {
                Some(target) => path = [target.as_slice(), &path[len + 1..]].concat(),
                None => return (module, false),
            }
        }
        panic!("re-exports of {path:?} go round in a circle");
    }
}

/// A module path as Rust writes it (`crate` for the root).
pub fn join(path: &ModPath) -> String {
    if path.is_empty() {
        "crate".into()
    } else {
        path.join("::")
    }
}

impl ModuleGraph {
    fn build(sources: &[SourceModule]) -> Self {
        let modules: BTreeSet<ModPath> = sources.iter().map(|s| s.path.clone()).collect();
        let paths: Vec<Vec<WrittenPath>> = sources.iter().map(SourceModule::paths).collect();
        let mut resolver = Resolver {
            modules,
            reexports: BTreeMap::new(),
        };
        // Re-exports first (they may chain, so resolve them lazily through `absolute`).
        for (source, written) in sources.iter().zip(&paths) {
            for w in written.iter().filter(|w| w.exported && w.inline_depth == 0) {
                if let (Some(Some(name)), Some(abs)) = (
                    &w.binds,
                    resolver.absolute(&source.path, 0, &BTreeMap::new(), &w.segments),
                ) {
                    resolver
                        .reexports
                        .entry(source.path.clone())
                        .or_default()
                        .insert(name.clone(), abs);
                }
            }
        }
        let mut graph = ModuleGraph::default();
        for (source, written) in sources.iter().zip(&paths) {
            let edges = graph.edges.entry(source.path.clone()).or_default();
            let mut aliases: BTreeMap<String, Vec<String>> = BTreeMap::new();
            for w in written {
                let Some(abs) =
                    resolver.absolute(&source.path, w.inline_depth, &aliases, &w.segments)
                else {
                    continue;
                };
                let (module, names_module) = resolver.defining_module(&abs);
                // `use a::b;` of a module only names it: its uses through the alias count.
                if let Some(Some(name)) = &w.binds {
                    aliases.insert(name.clone(), abs.clone());
                    if names_module {
                        continue;
                    }
                }
                if module != source.path {
                    edges.entry(module).or_insert(Site {
                        file: source.file.clone(),
                        line: w.line,
                    });
                }
            }
        }
        graph
    }

    /// The strongly connected components with more than one module (Tarjan).
    pub fn cycles(&self) -> Vec<Vec<ModPath>> {
        struct Tarjan<'a> {
            graph: &'a ModuleGraph,
            index: BTreeMap<&'a ModPath, usize>,
            low: BTreeMap<&'a ModPath, usize>,
            stack: Vec<&'a ModPath>,
            on_stack: BTreeSet<&'a ModPath>,
            components: Vec<Vec<ModPath>>,
        }
        impl<'a> Tarjan<'a> {
            fn visit(&mut self, v: &'a ModPath) {
                let n = self.index.len();
                self.index.insert(v, n);
                self.low.insert(v, n);
                self.stack.push(v);
                self.on_stack.insert(v);
                for w in self.graph.edges.get(v).into_iter().flat_map(|e| e.keys()) {
                    if !self.index.contains_key(w) {
                        self.visit(w);
                        let low = self.low[v].min(self.low[w]);
                        self.low.insert(v, low);
                    } else if self.on_stack.contains(w) {
                        let low = self.low[v].min(self.index[w]);
                        self.low.insert(v, low);
                    }
                }
                if self.low[v] == self.index[v] {
                    let mut component = Vec::new();
                    loop {
                        let w = self.stack.pop().unwrap();
                        self.on_stack.remove(w);
                        component.push(w.clone());
                        if w == v {
                            break;
                        }
                    }
                    if component.len() > 1 {
                        component.sort();
                        self.components.push(component);
                    }
                }
            }
        }
        let mut t = Tarjan {
            graph: self,
            index: BTreeMap::new(),
            low: BTreeMap::new(),
            stack: Vec::new(),
            on_stack: BTreeSet::new(),
            components: Vec::new(),
        };
        for v in self.edges.keys() {
            if !t.index.contains_key(v) {
                t.visit(v);
            }
        }
        t.components
    }

    /// One cycle through the first module of `component`, as an explanation: each edge
    /// with the file and line that makes it.
    pub fn explain(&self, component: &[ModPath]) -> String {
        let inside: BTreeSet<&ModPath> = component.iter().collect();
        let start = &component[0];
        // Breadth-first from `start` back to itself, inside the component.
        let mut previous: BTreeMap<&ModPath, &ModPath> = BTreeMap::new();
        let mut queue = std::collections::VecDeque::from([start]);
        'search: while let Some(v) = queue.pop_front() {
            for w in self.edges[v].keys().filter(|w| inside.contains(w)) {
                if w == start {
                    previous.insert(start, v);
                    break 'search;
                }
                if !previous.contains_key(w) {
                    previous.insert(w, v);
                    queue.push_back(w);
                }
            }
        }
        let mut cycle = vec![start];
        let mut v = previous[start];
        while v != start {
            cycle.push(v);
            v = previous[v];
        }
        cycle.push(start);
        cycle.reverse();
        let steps: Vec<String> = cycle
            .windows(2)
            .map(|pair| {
                let site = &self.edges[pair[0]][pair[1]];
                format!(
                    "  {} -> {} ({}:{})",
                    join(pair[0]),
                    join(pair[1]),
                    site.file,
                    site.line
                )
            })
            .collect();
        let members: Vec<String> = component.iter().map(join).collect();
        format!(
            "cycle among {{{}}}:\n{}",
            members.join(", "),
            steps.join("\n")
        )
    }
}

impl ModuleGraph {
    /// The graph of the crate whose sources lie under `src` (its `lib.rs` the root);
    /// files are named `src/...` in explanations.
    pub fn of_crate(src: &Path) -> Self {
        let mut files = Vec::new();
        rust_files(src, &mut files);
        files.sort();
        let sources: Vec<SourceModule> = files
            .iter()
            .map(|file| {
                let relative = file.strip_prefix(src).unwrap();
                let text = std::fs::read_to_string(file)
                    .unwrap_or_else(|e| panic!("{}: {e}", file.display()));
                SourceModule::new(
                    module_path(relative),
                    format!("src/{}", relative.display()),
                    &text,
                )
            })
            .collect();
        ModuleGraph::build(&sources)
    }

    /// The graph of files given as (path relative to `src`, text), for tests of the reader.
    pub fn in_memory(files: &[(&str, &str)]) -> Self {
        let sources: Vec<SourceModule> = files
            .iter()
            .map(|(file, src)| {
                SourceModule::new(module_path(Path::new(file)), file.to_string(), src)
            })
            .collect();
        ModuleGraph::build(&sources)
    }

    /// Whether module `from` names module `to` (paths from the crate root, `[]` the root).
    pub fn has_edge(&self, from: &[&str], to: &[&str]) -> bool {
        let from: ModPath = from.iter().map(|s| s.to_string()).collect();
        let to: ModPath = to.iter().map(|s| s.to_string()).collect();
        self.edges.get(&from).is_some_and(|e| e.contains_key(&to))
    }

    /// Every circle, explained (one line per edge, with the file and line that makes it);
    /// empty when the modules form none.
    pub fn explained_cycles(&self) -> Vec<String> {
        self.cycles().iter().map(|c| self.explain(c)).collect()
    }
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display())) {
        let path = entry.unwrap().path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::ModuleGraph;

    #[test]
    fn a_back_edge_through_super_or_a_reexport_is_a_cycle() {
        let graph = ModuleGraph::in_memory(&[
            ("lib.rs", "pub mod a; pub mod b; pub use b::Thing;"),
            // `crate::Thing` is b's, through the root's re-export: the edge is a→b, not a→crate.
            (
                "a/mod.rs",
                "pub mod inner;\nuse crate::Thing;\npub fn f() {}\n",
            ),
            ("a/inner.rs", "pub struct Inner;\nfn g() { super::f() }\n"),
            (
                "b.rs",
                "pub struct Thing;\nfn h() { let _ = super::a::inner::Inner; }\n",
            ),
        ]);
        assert!(
            !graph.has_edge(&["a"], &[]),
            "a names b's Thing, not the root"
        );
        let cycles = graph.cycles();
        assert_eq!(cycles.len(), 1, "{cycles:?}");
        let text = graph.explain(&cycles[0]);
        assert!(text.contains("a -> b (a/mod.rs:2)"), "{text}");
        assert!(text.contains("b -> a::inner (b.rs:2)"), "{text}");
        assert!(text.contains("a::inner -> a (a/inner.rs:2)"), "{text}");
    }

    #[test]
    fn comments_strings_and_inline_test_modules_make_no_edge() {
        let graph = ModuleGraph::in_memory(&[
            ("lib.rs", "pub mod a; pub mod b;"),
            ("a.rs", "use crate::b::B;\n"),
            (
                "b.rs",
                "pub struct B;\n// crate::a::x\n/* crate::a::y */\nconst S: &str = \"crate::a::z\";\n\
                 const R: &str = r#\"super::a::w\"#;\nfn f<'a>(_: &'a str) -> char { 'a' }\n\
                 #[cfg(test)]\nmod tests { use super::*; fn g() -> B { super::B } }\n",
            ),
        ]);
        assert!(graph.has_edge(&["a"], &["b"]));
        assert!(graph.cycles().is_empty(), "{:?}", graph.edges);
    }
}
