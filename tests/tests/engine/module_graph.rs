//! The modules of `engine/src` form no cycle: no two modules import each other, directly
//! or through others (the reader: `drape_tests::module_graph`, as the trainer's test).

use std::path::Path;

use drape_tests::module_graph::ModuleGraph;

#[test]
fn engine_modules_form_no_cycle() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("../engine/src");
    let graph = ModuleGraph::of_crate(&src);
    assert!(
        graph.edges.len() > 20,
        "engine/src has {} files",
        graph.edges.len()
    );
    // The reader sees known edges, so an empty graph cannot pass for an acyclic one.
    assert!(graph.has_edge(&["ops", "radix_sort"], &["kernels"]));
    assert!(graph.has_edge(&["buffer"], &["error"]));
    let explanations = graph.explained_cycles();
    assert!(
        explanations.is_empty(),
        "modules of engine/src import each other:\n{}",
        explanations.join("\n")
    );
}
