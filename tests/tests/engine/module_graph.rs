//! The modules of `engine/src` form no cycle: no two modules import each other, directly
//! or through others (the reader: `drape_tests::module_graph`, as the trainer's test).

use std::path::Path;

use drape_tests::module_graph::{join, ModuleGraph};

#[test]
fn engine_modules_form_no_cycle() {
    let graph = engine_graph();
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

fn engine_graph() -> ModuleGraph {
    ModuleGraph::of_crate(&Path::new(env!("CARGO_MANIFEST_DIR")).join("../engine/src"))
}

/// The modules the device is built from name no engine module but the error type: the
/// recording pools and the pipeline cache work on an `ash::Device`, not on the engine's
/// `Device`, so `context` can own them without a circle.
#[test]
fn the_device_s_parts_are_leaves() {
    let graph = engine_graph();
    assert!(graph.has_edge(&["context"], &["pools"]));
    assert!(graph.has_edge(&["context"], &["kernels"]));
    for leaf in [
        "error",
        "validation",
        "profile",
        "retire",
        "pools",
        "requirements",
        "kernels",
    ] {
        let edges = graph
            .edges
            .get(&vec![leaf.to_string()])
            .unwrap_or_else(|| panic!("engine/src has no module {leaf}"));
        for (to, site) in edges {
            assert!(
                to.as_slice() == ["error"],
                "{leaf} names {} ({}:{}): a part of the device names no engine module but error",
                join(to),
                site.file,
                site.line
            );
        }
    }
}
