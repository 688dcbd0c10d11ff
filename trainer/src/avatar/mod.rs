//! The layered avatar (docs/design.md, `trainer/src/avatar`): its layers as the engine's
//! groups of Gaussians (`groups`), the body rig and its per-frame transforms (`rig`), a
//! triplane-driven Gaussian layer with its decoders and optimiser groups (`layer`) and
//! its deformation for a frame (`deform`), the set of layers the data requires
//! (`model`), its rendering and the paper's compositing (`composite`, the geometry
//! buffers' layout in `gaussian_layout`), the model's state on the host (`state`) and its
//! file (`checkpoint`), the cloth layer's simulated targets and edge graph
//! (`cloth_target`) and its losses (`cloth_losses`), the scene layer (`scene`), per-frame
//! pose refinement (`pose_refine`), densification and pruning (`densify`), training
//! (`train`: its config in `config`, its inputs in `inputs`, the avatar it builds in
//! `assemble`, its progress and JSON files in `report`, the step itself in `step`),
//! held-out evaluation (`eval`, with FID from `crate::metrics`), and a finished run
//! opened again (`run`), the trained avatar as one file an app ships (`file`), to animate (`animate`) or edit (`edit`).

pub mod animate;
pub mod assemble;
pub mod checkpoint;
pub mod cloth_losses;
pub mod cloth_target;
pub mod composite;
pub mod config;
pub mod deform;
pub mod densify;
pub mod edit;
pub mod eval;
pub mod file;
pub mod gaussian_layout;
pub mod groups;
pub mod inputs;
pub mod layer;
pub mod losses;
pub mod model;
pub mod player;
pub mod pose_refine;
pub mod report;
pub mod rig;
pub mod run;
pub mod scene;
pub mod state;
pub mod step;
pub mod train;
