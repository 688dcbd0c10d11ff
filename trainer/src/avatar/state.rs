//! The trained model's state on the host, as the layers hand it over and take it back
//! (`HumanLayer::state`, `SceneLayer::state`, `Avatar::state`) and as the model file
//! stores it (`checkpoint`): each layer's Gaussians, triplane, decoders and Adam
//! moments, the scene layer's, and the training frames' pose corrections.

use crate::avatar::pose_refine::PoseState;

/// One Adam group's state.
#[derive(Clone, Debug, PartialEq)]
pub struct AdamState {
    pub m: Vec<f32>,
    pub v: Vec<f32>,
    pub step: u32,
}

/// One layer's state on the host.
#[derive(Clone, Debug, PartialEq)]
pub struct LayerState {
    pub means: Vec<f32>,
    pub quats: Vec<f32>,
    pub log_scales: Vec<f32>,
    pub triplane: Vec<f32>,
    /// (resolution, channels).
    pub triplane_size: (u32, u32),
    pub triplane_box: [[f32; 3]; 2],
    pub appearance: Vec<f32>,
    pub geometry: Vec<f32>,
    pub deformation: Vec<f32>,
    /// By group name, in [`ADAM_GROUPS`] order.
    pub adam: Vec<AdamState>,
    /// The skinning targets (n×24); None when the file lacks them.
    pub weight_targets: Option<Vec<f32>>,
    /// Densification statistics (n×3); None: zero.
    pub screen_stats: Option<Vec<f32>>,
    /// The ARAP graph between the layer's Gaussians; None: the model's own.
    pub edges: Option<Vec<[u32; 2]>>,
}

impl LayerState {
    /// Gaussians in the state.
    pub fn count(&self) -> usize {
        self.means.len() / 3
    }
}

/// The Adam groups of a layer, in file order.
pub const ADAM_GROUPS: [&str; 5] = [
    "position",
    "triplane",
    "appearance",
    "geometry",
    "deformation",
];

/// What a layer of the model being loaded into expects: its name, triplane resolution
/// and channels, and decoder parameter counts. Its Gaussian count is the file's;
/// `count` (the model's own) only decides whether the file must carry the layer's
/// skinning targets (a file of another count, made by densification, must).
#[derive(Clone, Debug, PartialEq)]
pub struct LayerShape {
    pub name: String,
    pub count: usize,
    pub triplane_size: (u32, u32),
    pub decoders: [usize; 3],
}

/// A whole model.
#[derive(Clone, Debug, PartialEq)]
pub struct ModelState {
    pub step: u32,
    pub layers: Vec<(String, LayerState)>,
    pub scene: Option<SceneState>,
    /// The training frames' pose corrections, where the run refines them.
    pub poses: Option<PoseState>,
}

/// Names of the scene's parameter buffers and Adam groups, in `GaussianBuffers::all` order.
pub const SCENE_PARAMS: [&str; 5] = ["means", "log_scales", "quats", "opacity_logits", "sh"];

/// The scene layer's state on the host: the five parameter arrays in
/// [`SCENE_PARAMS`] order and their Adam states.
#[derive(Clone, Debug, PartialEq)]
pub struct SceneState {
    pub params: Vec<Vec<f32>>,
    pub adam: Vec<AdamState>,
    /// Densification statistics (n×3); None: zero.
    pub screen_stats: Option<Vec<f32>>,
}
