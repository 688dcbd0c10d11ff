//! The avatar: the set of layers the data requires (decided from the data and
//! printed at start), and the one set of posed Gaussians the splatter renders them
//! from.
//!
//! Layers: the body (Gaussians of the SMPL-format body in the canonical Da-pose);
//! when the data shows garments, the cloth (the T-shirt and the pants sharing one
//! triplane and one set of decoders, as the paper says); when it shows a scene (an
//! unmasked capture with sparse points: NeuMan), the scene (plain 3DGS, `scene`). Each
//! layer deforms and skins its own Gaussians; their posed Gaussians are copied into one
//! cloud, which `composite::AvatarRenderer` renders as the run's compositing says (the
//! paper's three passes, their fused walk, or one depth-sorted pass), and the gradients
//! are copied back.
//!
//! Cloth Gaussians come from the garment meshes made in their build pose (A-pose),
//! brought to the canonical pose by `A(Da) A(build)⁻¹` with the garments' weights;
//! their skinning targets are the nearest body vertex's weights (the paper's W_gt),
//! and the cloth-LBS loss `λ ‖W - W_gt‖²` keeps the predicted weights near them.

use crate::avatar::groups::Layer;
use drape_engine::ops::accumulate::Accumulation;
use drape_engine::ops::splat::render::GaussianBuffers;
use drape_engine::ops::splat::scene::GaussianCloud;
use drape_engine::ops::splat::sh_copy::{record_copy_sh, ShSlice};
use drape_engine::{Buffer, Context, Recording, Result};

use crate::avatar::cloth_target::{contracted_edges, garments};
use crate::avatar::gaussian_layout::GEOMETRY_FLOATS;
use crate::avatar::layer::{HumanLayer, LayerConfig};
use crate::avatar::rig::{FrameTransforms, Rig};
use crate::avatar::scene::SceneLayer;
use crate::avatar::state::{LayerShape, ModelState};
use crate::body::gaussians::{gaussians_from_mesh, SkinnedMesh};
use crate::body::kinematics::{forward_kinematics, relative_transforms, skin};
use crate::garment::GarmentFit;

/// Which layers to build: each optional layer forced on or off, or (None) decided
/// from the data. In a config it is the string [`LayerChoice::parse`] reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(try_from = "String", into = "String")]
pub struct LayerChoice {
    pub cloth: Option<bool>,
    pub scene: Option<bool>,
}

impl LayerChoice {
    /// Every optional layer decided from the data.
    pub const AUTO: Self = Self {
        cloth: None,
        scene: None,
    };

    /// `auto`, or the layers joined by `+`, body first: `body` (the single-layer
    /// baseline: cloth folded into the body, as HUGS), `body+cloth`, `body+scene`,
    /// `body+cloth+scene`.
    pub fn parse(s: &str) -> crate::Result<Self> {
        Self::try_from(s.to_string())
            .map_err(|e| crate::TrainerError::config("layers", e.to_string()))
    }
}

impl std::fmt::Display for LayerChoice {
    /// The string [`LayerChoice::parse`] reads back; a layer left to the data (in a
    /// choice not made by `parse`) is written as absent.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if *self == Self::AUTO {
            return f.write_str("auto");
        }
        f.write_str("body")?;
        if self.cloth == Some(true) {
            f.write_str("+cloth")?;
        }
        if self.scene == Some(true) {
            f.write_str("+scene")?;
        }
        Ok(())
    }
}

impl TryFrom<String> for LayerChoice {
    type Error = crate::error::BadChoice;
    fn try_from(value: String) -> Result<Self, Self::Error> {
        if value == "auto" {
            return Ok(Self::AUTO);
        }
        let parts: Vec<&str> = value.split('+').collect();
        let has = |name: &str| parts.iter().filter(|p| **p == name).count();
        let known = parts.first() == Some(&"body")
            && parts[1..].iter().all(|p| ["cloth", "scene"].contains(p));
        if !known || has("cloth") > 1 || has("scene") > 1 {
            return Err(crate::error::BadChoice { value, allowed: "auto, or body joined with cloth and/or scene by '+' (body, body+cloth, body+scene, body+cloth+scene)" });
        }
        Ok(Self {
            cloth: Some(has("cloth") == 1),
            scene: Some(has("scene") == 1),
        })
    }
}

impl From<LayerChoice> for String {
    fn from(c: LayerChoice) -> String {
        c.to_string()
    }
}

/// Canonical Gaussians of one layer with their skinning targets (count × 24).
pub struct LayerInit {
    pub name: String,
    pub cloud: GaussianCloud,
    pub weights: Vec<f32>,
    /// The mesh edges between this layer's Gaussians (contracted onto the kept ones
    /// when decimated): the cloth layer's ARAP graph; empty for the body.
    pub edges: Vec<[u32; 2]>,
}

/// Every `keep`-th Gaussian of `full`, widened by √keep in the surface plane, with
/// its row of `weights`.
fn decimated(
    name: &str,
    full: &GaussianCloud,
    weights: &[[f64; 24]],
    keep: usize,
    layer: Layer,
) -> LayerInit {
    let keep = keep.max(1);
    let widen = 0.5 * (keep as f32).ln();
    let mut cloud = GaussianCloud::new(full.sh_degree);
    let mut w = Vec::new();
    for i in (0..full.len()).step_by(keep) {
        let mut g = full.gaussian::<f32>(i);
        // The two tangent axes (the third is the normal).
        g.log_scale[0] += widen;
        g.log_scale[1] += widen;
        cloud.push(&g, layer);
        w.extend(weights[i].iter().map(|&v| v as f32));
    }
    LayerInit {
        name: name.to_string(),
        cloud,
        weights: w,
        edges: Vec::new(),
    }
}

/// The body layer's canonical Gaussians.
pub fn body_init(rig: &Rig, subdivision: u32, decimate: u32, sh_degree: u32) -> LayerInit {
    let mesh = SkinnedMesh {
        vertices: rig.canonical_vertices(),
        faces: rig.model.faces.clone(),
        weights: rig.model.weights.clone(),
        shapedirs: vec![[Vec::new(), Vec::new(), Vec::new()]; rig.model.num_vertices()],
    };
    let (full, sub) = gaussians_from_mesh(&mesh, subdivision, sh_degree, Layer::Body);
    decimated("body", &full, &sub.weights, decimate as usize, Layer::Body)
}

/// The cloth layer's canonical Gaussians: the project's T-shirt of `fit` and pants made
/// on the rig's body (the garments `drape synth` dresses it in).
pub fn cloth_init(rig: &Rig, fit: GarmentFit, decimate: u32, sh_degree: u32) -> LayerInit {
    let (canonical, _) = forward_kinematics(
        &rig.model.parents,
        &rig.rest_joints(),
        &crate::body::kinematics::da_pose(),
    );
    let mut vertices = Vec::new();
    let mut faces = Vec::new();
    let mut weights = Vec::new();
    for g in garments(rig, fit) {
        let (built, _) = forward_kinematics(&rig.model.parents, &rig.rest_joints(), &g.build_pose);
        let to_canonical = relative_transforms(&canonical, &built);
        let base = vertices.len() as u32;
        vertices.extend(skin(&g.weights, &to_canonical, &g.vertices));
        faces.extend(g.faces.iter().map(|f| f.map(|i| i + base)));
        weights.extend(g.weights.iter().copied());
    }
    let n = vertices.len();
    let mesh = SkinnedMesh {
        vertices,
        faces,
        weights,
        shapedirs: vec![[Vec::new(), Vec::new(), Vec::new()]; n],
    };
    let (full, sub) = gaussians_from_mesh(&mesh, 0, sh_degree, Layer::Cloth);
    let mut init = decimated(
        "cloth",
        &full,
        &sub.weights,
        decimate as usize,
        Layer::Cloth,
    );
    init.edges = contracted_edges(sub.vertices.len(), &sub.faces, decimate as usize);
    init
}

/// The layers and the cloud they are rendered from.
pub struct Avatar {
    pub layers: Vec<HumanLayer>,
    /// Plain 3DGS in world space, rendered after the human layers' Gaussians.
    pub scene: Option<SceneLayer>,
    /// All layers' posed Gaussians, layer after layer.
    pub posed: GaussianBuffers,
    pub posed_grads: GaussianBuffers,
    /// Cloth-LBS weight per layer (0 for the body).
    pub lbs_weights: Vec<f32>,
    /// How every scatter-add backward accumulates ([`set_accumulation`](Self::set_accumulation)).
    accumulation: Accumulation,
}

impl Avatar {
    /// Builds the layers from their initial Gaussians (configs and LBS weights in the
    /// same order).
    pub fn new(
        ctx: &Context,
        inits: &[LayerInit],
        configs: &[LayerConfig],
        lbs_weights: &[f32],
        scene: Option<SceneLayer>,
        steps: u32,
        seed: u64,
    ) -> Result<Self> {
        let mut layers = Vec::new();
        for (k, (init, config)) in inits.iter().zip(configs).enumerate() {
            let mut layer = HumanLayer::new(
                ctx,
                &init.name,
                &init.cloud,
                &init.weights,
                config,
                steps,
                seed + 100 * k as u64,
            )?;
            layer.edges = init.edges.clone();
            layers.push(layer);
        }
        let total: usize = layers.iter().map(|l| l.count as usize).sum::<usize>()
            + scene.as_ref().map_or(0, |s| s.count as usize);
        // Each layer keeps its own SH degree; the posed cloud that the layers are
        // rendered from together has the highest (`ops::splat::sh_copy` pads the rest).
        let sh = configs
            .iter()
            .map(|c| c.sh_degree)
            .chain(scene.iter().map(|s| s.params.sh_degree))
            .max()
            .unwrap_or(0);
        Ok(Self {
            layers,
            scene,
            posed: GaussianBuffers::new(ctx, "avatar posed", total, sh)?,
            posed_grads: GaussianBuffers::new(ctx, "avatar posed grads", total, sh)?,
            lbs_weights: lbs_weights.to_vec(),
            accumulation: Accumulation::Auto,
        })
    }

    /// Chooses how the backward passes accumulate, in every layer and in the
    /// renderers that read [`accumulation`](Self::accumulation):
    /// [`Accumulation::Deterministic`] makes a training step bit-identical from run to run.
    pub fn set_accumulation(&mut self, ctx: &Context, accumulation: Accumulation) -> Result<()> {
        for l in &mut self.layers {
            l.set_accumulation(ctx, accumulation)?;
        }
        self.accumulation = accumulation;
        Ok(())
    }

    pub fn accumulation(&self) -> Accumulation {
        self.accumulation
    }

    /// The cloth layer, if the avatar has one.
    pub fn cloth(&self) -> Option<&HumanLayer> {
        self.layers.iter().find(|l| l.name == "cloth")
    }

    /// Gaussians per layer.
    pub fn counts(&self) -> Vec<(String, u32)> {
        let mut c: Vec<(String, u32)> = self
            .layers
            .iter()
            .map(|l| (l.name.clone(), l.count))
            .collect();
        if let Some(s) = &self.scene {
            c.push(("scene".into(), s.count));
        }
        c
    }

    /// The posed cloud's SH degree: the highest of the layers'.
    pub fn sh_degree(&self) -> u32 {
        self.posed.sh_degree
    }

    /// Records the copy of one layer's posed Gaussians (`count`, from its own buffers)
    /// into the slice of `dst` that starts at Gaussian `first`, or back with
    /// `to_layer`: geometry and opacity as they are, SH padded or truncated to the
    /// receiving buffer's degree.
    pub(crate) fn record_move<'a>(
        rec: &mut Recording<'a>,
        layer: &'a GaussianBuffers,
        shared: &'a GaussianBuffers,
        first: u32,
        count: u32,
        to_layer: bool,
    ) -> Result<()> {
        let (src, dst) = if to_layer {
            (shared, layer)
        } else {
            (layer, shared)
        };
        let (src_first, dst_first) = if to_layer { (first, 0) } else { (0, first) };
        let (s, d) = (src.all(), dst.all());
        for k in 0..4 {
            let per = 4 * u64::from(GEOMETRY_FLOATS[k]);
            rec.copy_region(
                s[k],
                per * u64::from(src_first),
                d[k],
                per * u64::from(dst_first),
                per * u64::from(count),
            );
        }
        record_copy_sh(
            rec,
            ShSlice {
                buffer: &src.sh,
                degree: src.sh_degree,
                first: src_first,
            },
            ShSlice {
                buffer: &dst.sh,
                degree: dst.sh_degree,
                first: dst_first,
            },
            count,
        )
    }

    /// Records every layer's forward pass for the frame's transforms (written into
    /// each layer's `transforms` before) and gathers the posed cloud. Each layer's
    /// passes are timed under its name (`Recording::set_scope`).
    pub fn record_forward<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        log_scale_offset: f32,
    ) -> Result<()> {
        for l in &self.layers {
            rec.set_scope(&l.name);
            l.record_forward(rec, log_scale_offset)?;
        }
        rec.set_scope("");
        self.record_gather(rec)
    }

    /// Records the gather of every layer's posed Gaussians (and the scene's) into
    /// [`posed`](Self::posed), layer after layer.
    pub fn record_gather<'a>(&'a self, rec: &mut Recording<'a>) -> Result<()> {
        let mut first = 0;
        for l in &self.layers {
            // Each buffer's slice of this layer starts at `first` Gaussians.
            Self::record_move(rec, &l.deformer.posed, &self.posed, first, l.count, false)?;
            first += l.count;
        }
        if let Some(s) = &self.scene {
            Self::record_move(rec, &s.params, &self.posed, first, s.count, false)?;
        }
        Ok(())
    }

    /// Records the backward pass from `posed_grads` (the splatter's), through every
    /// layer, with each layer's cloth-LBS term (and, with `pose_gradient`, the
    /// transforms' gradient for pose refinement).
    pub fn record_backward<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        pose_gradient: bool,
    ) -> Result<()> {
        self.record_scatter_grads(rec)?;
        self.record_layers_backward(rec, pose_gradient)
    }

    /// Copies each layer's slice of `posed_grads` into the layer's own `posed_grads`
    /// (where per-layer losses then add theirs).
    pub fn record_scatter_grads<'a>(&'a self, rec: &mut Recording<'a>) -> Result<()> {
        let mut first = 0;
        for l in &self.layers {
            Self::record_move(
                rec,
                &l.deformer.posed_grads,
                &self.posed_grads,
                first,
                l.count,
                true,
            )?;
            first += l.count;
        }
        if let Some(s) = &self.scene {
            Self::record_move(rec, &s.grads, &self.posed_grads, first, s.count, true)?;
        }
        Ok(())
    }

    /// Records every layer's backward pass from its own `posed_grads`, with each
    /// layer's cloth-LBS term (and, with `pose_gradient`, the transforms' gradient).
    pub fn record_layers_backward<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        pose_gradient: bool,
    ) -> Result<()> {
        for (l, &lbs) in self.layers.iter().zip(&self.lbs_weights) {
            rec.set_scope(&l.name);
            l.record_backward(rec, lbs, pose_gradient)?;
        }
        rec.set_scope("");
        Ok(())
    }

    /// Records the count of non-finite gradient values of every layer into `counter`
    /// (with `pose_gradient`, also the layers' partial sums of `∂L/∂A`).
    pub fn record_count_nonfinite<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        counter: &'a Buffer,
        pose_gradient: bool,
    ) -> Result<()> {
        for l in &self.layers {
            l.record_count_nonfinite(rec, counter, pose_gradient)?;
        }
        if let Some(s) = &self.scene {
            crate::avatar::layer::record_count_nonfinite(
                rec,
                s.grads.all().into_iter().zip(s.lens()),
                counter,
            )?;
        }
        Ok(())
    }

    /// Records one Adam step of every layer; with `guard`, applied on the GPU only
    /// while the guard's first word is 0 (then [`advance_adam`](Self::advance_adam)
    /// once the host has seen it stay down).
    pub fn record_adam<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        guard: Option<&'a Buffer>,
    ) -> Result<()> {
        for l in &self.layers {
            rec.set_scope(&l.name);
            l.record_adam(rec, true, guard)?;
        }
        if let Some(s) = &self.scene {
            rec.set_scope("scene");
            s.record_adam(rec, guard)?;
        }
        rec.set_scope("");
        Ok(())
    }

    /// Counts a guarded Adam step that the GPU applied.
    pub fn advance_adam(&self) {
        for l in &self.layers {
            l.advance_adam(true);
        }
        if let Some(s) = &self.scene {
            s.advance_adam();
        }
    }

    /// Records the writes of the frame's transforms and pose features into every layer
    /// (`vkCmdUpdateBuffer`: no host write while an earlier frame may still read them,
    /// and no submission of their own).
    pub fn record_set_frame<'a>(&'a self, rec: &mut Recording<'a>, frame: &FrameTransforms) {
        for l in &self.layers {
            rec.update(&l.deformer.transforms, &frame.transforms);
            rec.update(&l.deformer.pose_features, &frame.pose_features);
        }
    }

    /// Writes the frame's transforms and pose features into every layer.
    pub fn set_frame(&mut self, ctx: &Context, frame: &FrameTransforms) -> Result<()> {
        for l in &mut self.layers {
            ctx.write_buffer(&mut l.deformer.transforms, &frame.transforms)?;
            ctx.write_buffer(&mut l.deformer.pose_features, &frame.pose_features)?;
        }
        Ok(())
    }

    pub fn shapes(&self) -> Vec<LayerShape> {
        self.layers.iter().map(|l| l.shape()).collect()
    }

    /// The scene layer's SH degree (for reading a checkpoint), if it has one.
    pub fn scene_sh_degree(&self) -> Option<u32> {
        self.scene.as_ref().map(|s| s.params.sh_degree)
    }

    /// Gaussians of every layer together.
    pub fn total_count(&self) -> u32 {
        self.layers.iter().map(|l| l.count).sum::<u32>()
            + self.scene.as_ref().map_or(0, |s| s.count)
    }

    /// Re-allocates the posed cloud after a layer changed its count (densification).
    pub fn resize_posed(&mut self, ctx: &Context) -> Result<()> {
        let total = self.total_count() as usize;
        if total != self.posed.count as usize {
            let sh = self.posed.sh_degree;
            self.posed = GaussianBuffers::new(ctx, "avatar posed", total, sh)?;
            self.posed_grads = GaussianBuffers::new(ctx, "avatar posed grads", total, sh)?;
        }
        Ok(())
    }

    pub fn state(&mut self, ctx: &Context, step: u32) -> Result<ModelState> {
        let mut layers = Vec::new();
        for l in &mut self.layers {
            layers.push((l.name.clone(), l.state(ctx)?));
        }
        let scene = match &mut self.scene {
            Some(s) => Some(s.state(ctx)?),
            None => None,
        };
        Ok(ModelState {
            step,
            layers,
            scene,
            poses: None,
        })
    }

    pub fn restore(&mut self, ctx: &Context, state: &ModelState) -> Result<()> {
        for (l, (_, s)) in self.layers.iter_mut().zip(&state.layers) {
            l.restore(ctx, s)?;
        }
        if let (Some(s), Some(st)) = (&mut self.scene, &state.scene) {
            s.restore(ctx, st)?;
        }
        self.resize_posed(ctx)
    }

    /// The posed cloud of the last forward pass, read back, with each Gaussian's layer.
    pub fn read_posed(&mut self, ctx: &Context) -> Result<GaussianCloud> {
        let mut kinds = Vec::new();
        for l in &self.layers {
            let kind = if l.name == "cloth" {
                Layer::Cloth
            } else {
                Layer::Body
            };
            kinds.extend(std::iter::repeat_n(kind, l.count as usize));
        }
        if let Some(s) = &self.scene {
            kinds.extend(std::iter::repeat_n(Layer::Scene, s.count as usize));
        }
        self.posed.download(ctx, &kinds)
    }
}
