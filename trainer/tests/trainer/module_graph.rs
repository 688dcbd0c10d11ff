//! The modules of `trainer/src` form no cycle: no two modules import each other, directly
//! or through others (the graph and its reader: `drape_tests::module_graph`, shared with
//! the engine's test).

use std::path::Path;

use drape_tests::module_graph::{join, ModPath, ModuleGraph};

fn trainer_graph() -> ModuleGraph {
    ModuleGraph::of_crate(&Path::new(env!("CARGO_MANIFEST_DIR")).join("src"))
}

#[test]
fn trainer_modules_form_no_cycle() {
    let graph = trainer_graph();
    assert!(
        graph.edges.len() > 20,
        "trainer/src has {} files",
        graph.edges.len()
    );
    // The reader sees known edges, so an empty graph cannot pass for an acyclic one.
    assert!(graph.has_edge(&["avatar", "train"], &["avatar", "step"]));
    assert!(graph.has_edge(&["avatar", "train"], &["error"]));
    let explanations = graph.explained_cycles();
    assert!(
        explanations.is_empty(),
        "modules of trainer/src import each other:\n{}",
        explanations.join("\n")
    );
}

#[test]
fn the_metrics_name_no_module_of_the_avatar() {
    let graph = trainer_graph();
    let metrics: Vec<&ModPath> = graph
        .edges
        .keys()
        .filter(|m| m.first().is_some_and(|s| s == "metrics"))
        .collect();
    assert_eq!(
        metrics.len(),
        6,
        "metrics, metrics::fid (mod, network, distance, linalg), metrics::fid_weights: \
         {metrics:?}"
    );
    // The reader sees the metrics' known edges, so an empty graph cannot pass.
    assert!(graph.has_edge(&["metrics", "fid", "network"], &["metrics", "fid_weights"]));
    for m in metrics {
        for (to, site) in &graph.edges[m] {
            assert!(
                to.first().is_none_or(|s| s != "avatar"),
                "{} names {} ({}:{}): a metric knows no avatar",
                join(m),
                join(to),
                site.file,
                site.line
            );
        }
    }
}
