//! Rendering the avatar: the paper's depth-aware three-pass composite (Sec. 2.3), or one
//! depth-sorted pass of every layer (the baseline without compositing).
//!
//! Three passes, each the engine's splatter: the base (body + scene over the frame's
//! background), the cloth alone (over black: its premultiplied colour and alpha), and
//! the matte (cloth in colour 1 and its occluders in colour 0, over black: the cloth's
//! visibility V), composited by `drape_engine::ops::splat::composite` into
//! `I = (C_cloth / A_cloth) · V + I_base · (1 − V)`. The paper's matte lets only the scene
//! hide the cloth (the body never does: an arm in front of the shirt is drawn behind
//! it); [`Matte::Occlusion`] adds the body as an occluder. The matte pass renders at SH
//! degree 0 from constant colours, so it sends gradients to geometry and opacity only.
//! Where nothing can hide the cloth (the paper's matte without a scene layer: masked
//! studio data) the matte equals the cloth pass's alpha and is not rendered.
//! The cloth mask loss reads the cloth pass's alpha (the matte without occluders) and
//! joins the composite's gradient on it, so the cloth is rendered once per step.
//!
//! A frame is one submission: the gather, the three renders (which the recorder
//! interleaves, as they share only what they read) and the composite. The fused
//! variant ([`Compositing::Fused`], `ops::splat::fused`) renders the same three images
//! from one sort and one walk of every layer's Gaussians, and back-propagates in one
//! walk too (its densification statistics then include the matte's gradients).

use crate::avatar::groups::Layer;
use drape_engine::ops::splat::composite::{
    matte_sh_dc, record_add_slice, record_composite, record_composite_backward, record_to_rgba,
    CompositeGrads, CompositeInputs, Coverage,
};
use drape_engine::ops::splat::densify::record_screen_stats;
use drape_engine::ops::splat::fused::{FusedGrads, FusedRenderer};
use drape_engine::ops::splat::render::{GaussianBuffers, SavedForward, SplatRenderer};
use drape_engine::ops::splat::scene::{PinholeCamera, RenderSettings};
use drape_engine::{Buffer, BufferDesc, Context, EngineError, Recording, Result};
use drape_shared::splat::raster::{FUSED_BASE, FUSED_MATTE_ONE, FUSED_MATTE_ZERO, FUSED_OVER};

use crate::avatar::cloth_losses::ClothLosses;
use crate::avatar::gaussian_layout::GEOMETRY_FLOATS;
use crate::avatar::model::Avatar;

/// Which Gaussians may hide the cloth in the matte.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Matte {
    /// The paper's: the scene only.
    Paper,
    /// The scene and the body.
    Occlusion,
}

/// How the layers become one image. In a config it is the string
/// [`Compositing::parse`] reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(try_from = "String", into = "String")]
pub enum Compositing {
    /// Every layer in one depth-sorted pass (no matte): the baseline.
    SinglePass,
    /// The paper's three passes and composite (needs a cloth layer; without one the
    /// avatar renders in one pass).
    ThreePass(Matte),
    /// The same three images from one depth sort and one rasterization of every layer,
    /// and one backward walk (`ops::splat::fused`).
    Fused(Matte),
}

impl Compositing {
    /// `three-pass` (the paper's matte), `three-pass-occlusion`, `single-pass`,
    /// `fused` or `fused-occlusion`.
    pub fn parse(s: &str) -> crate::Result<Self> {
        Self::try_from(s.to_string())
            .map_err(|e| crate::TrainerError::config("compositing", e.to_string()))
    }

    /// Every choice, the paper's first.
    pub const ALL: [Self; 5] = [
        Self::ThreePass(Matte::Paper),
        Self::ThreePass(Matte::Occlusion),
        Self::SinglePass,
        Self::Fused(Matte::Paper),
        Self::Fused(Matte::Occlusion),
    ];

    /// The name [`Compositing::parse`] reads.
    pub fn name(self) -> &'static str {
        match self {
            Self::ThreePass(Matte::Paper) => "three-pass",
            Self::ThreePass(Matte::Occlusion) => "three-pass-occlusion",
            Self::SinglePass => "single-pass",
            Self::Fused(Matte::Paper) => "fused",
            Self::Fused(Matte::Occlusion) => "fused-occlusion",
        }
    }
}

impl std::fmt::Display for Compositing {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl TryFrom<String> for Compositing {
    type Error = crate::error::BadChoice;
    fn try_from(value: String) -> Result<Self, Self::Error> {
        Self::ALL
            .into_iter()
            .find(|c| c.name() == value)
            .ok_or(crate::error::BadChoice {
                value,
                allowed: "three-pass, three-pass-occlusion, single-pass, fused or fused-occlusion",
            })
    }
}

impl From<Compositing> for String {
    fn from(c: Compositing) -> String {
        c.name().to_string()
    }
}

/// The fused rasterizer's mask of each Gaussian (`drape_shared::splat::raster::FUSED_*`):
/// the body into the base (and, with `occlusion`, into the matte at 0), the cloth into
/// the over state and the matte at 1, the scene into the base and the matte at 0.
pub fn layer_masks(layers: &[Layer], occlusion: bool) -> Vec<u32> {
    layers
        .iter()
        .map(|l| match l {
            Layer::Body if occlusion => FUSED_BASE | FUSED_MATTE_ZERO,
            Layer::Body => FUSED_BASE,
            Layer::Cloth => FUSED_OVER | FUSED_MATTE_ONE,
            Layer::Scene => FUSED_BASE | FUSED_MATTE_ZERO,
        })
        .collect()
}

/// One source of Gaussians in a pass: a human layer (by index) or the scene.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Source {
    Layer(usize),
    Scene,
}

/// A source's slice of a pass (in Gaussians).
#[derive(Clone, Copy, Debug)]
struct Part {
    source: Source,
    first: u32,
    count: u32,
    /// Matte colour (1 for the cloth, 0 for an occluder); unused in the base pass.
    matte: bool,
}

fn params(avatar: &Avatar, s: Source) -> &GaussianBuffers {
    match s {
        Source::Layer(k) => &avatar.layers[k].deformer.posed,
        Source::Scene => {
            &avatar
                .scene
                .as_ref()
                .expect("a pass names the scene only when there is one")
                .params
        }
    }
}

fn screen_stats(avatar: &Avatar, s: Source) -> &Buffer {
    match s {
        Source::Layer(k) => &avatar.layers[k].screen_stats,
        Source::Scene => {
            &avatar
                .scene
                .as_ref()
                .expect("a pass names the scene only when there is one")
                .screen_stats
        }
    }
}

fn grads(avatar: &Avatar, s: Source) -> &GaussianBuffers {
    match s {
        Source::Layer(k) => &avatar.layers[k].deformer.posed_grads,
        Source::Scene => {
            &avatar
                .scene
                .as_ref()
                .expect("a pass names the scene only when there is one")
                .grads
        }
    }
}

fn parts(avatar: &Avatar, sources: &[(Source, bool)]) -> (Vec<Part>, u32) {
    let mut first = 0;
    let mut out = Vec::new();
    for &(source, matte) in sources {
        let count = match source {
            Source::Layer(k) => avatar.layers[k].count,
            Source::Scene => avatar.scene.as_ref().map_or(0, |s| s.count),
        };
        out.push(Part {
            source,
            first,
            count,
            matte,
        });
        first += count;
    }
    (out, first)
}

/// The matte pass, where something can hide the cloth.
struct MattePass {
    parts: Vec<Part>,
    gaussians: GaussianBuffers,
    grads: GaussianBuffers,
    renderer: SplatRenderer,
    grad_image: Buffer,
}

struct ThreePass {
    cloth: usize,
    base_parts: Vec<Part>,
    base: GaussianBuffers,
    base_grads: GaussianBuffers,
    base_renderer: SplatRenderer,
    cloth_renderer: SplatRenderer,
    matte: Option<MattePass>,
    image: Buffer,
    grad_base: Buffer,
    grad_over: Buffer,
    grad_over_alpha: Buffer,
    pixels: u32,
}

struct Fused {
    renderer: FusedRenderer,
    image: Buffer,
    /// The composite's backward writes the three images' gradients here.
    grad_base: Buffer,
    grad_over: Buffer,
    grad_over_alpha: Buffer,
    grad_matte: Buffer,
    pixels: u32,
}

enum Inner {
    Single(Box<SplatRenderer>),
    ThreePass(Box<ThreePass>),
    Fused(Box<Fused>),
}

/// The cloth mask loss that [`AvatarRenderer::backward`] back-propagates with the
/// image's gradient, and the view of the forward it belongs to: where no pass renders
/// the cloth alone (single-pass compositing), the mask loss renders it from that view.
pub struct MaskLoss<'a> {
    pub losses: &'a mut ClothLosses,
    pub camera: &'a PinholeCamera,
    pub settings: &'a RenderSettings,
}

/// The avatar's renderer: forward to an image on the GPU, backward to every layer's
/// posed-Gaussian gradients.
pub struct AvatarRenderer {
    inner: Inner,
    /// What the last forward's renders left for the backward (single or fused: one;
    /// three passes: base, cloth, and the matte's where it is rendered).
    saved: Vec<SavedForward>,
}

impl AvatarRenderer {
    pub fn new(
        ctx: &Context,
        avatar: &Avatar,
        width: u32,
        height: u32,
        compositing: Compositing,
    ) -> Result<Self> {
        let cloth = avatar.layers.iter().position(|l| l.name == "cloth");
        if let (Compositing::Fused(matte), Some(_)) = (compositing, cloth) {
            // The avatar's posed buffer holds every layer, then the scene.
            let mut layers = Vec::new();
            for l in &avatar.layers {
                let kind = if l.name == "cloth" {
                    Layer::Cloth
                } else {
                    Layer::Body
                };
                layers.extend(std::iter::repeat_n(kind, l.count as usize));
            }
            layers.extend(std::iter::repeat_n(
                Layer::Scene,
                avatar.scene.as_ref().map_or(0, |s| s.count as usize),
            ));
            let mut renderer = FusedRenderer::new(ctx, width, height, avatar.posed.count as usize)?;
            renderer.set_masks(ctx, &layer_masks(&layers, matte == Matte::Occlusion))?;
            let pixels = width * height;
            let image = |name: &str, floats: u32| {
                ctx.create_buffer(name, BufferDesc::gpu_only(4 * u64::from(floats)))
            };
            let fused = Fused {
                renderer,
                image: image("composite image", 3 * pixels)?,
                grad_base: image("fused grad base", 3 * pixels)?,
                grad_over: image("fused grad cloth", 3 * pixels)?,
                grad_over_alpha: image("fused grad cloth alpha", pixels)?,
                grad_matte: image("fused grad matte", 3 * pixels)?,
                pixels,
            };
            return Ok(Self {
                inner: Inner::Fused(Box::new(fused)),
                saved: Vec::new(),
            });
        }
        let (Compositing::ThreePass(matte), Some(cloth)) = (compositing, cloth) else {
            return Ok(Self {
                inner: Inner::Single(Box::new(SplatRenderer::new(
                    ctx,
                    width,
                    height,
                    avatar.posed.count as usize,
                )?)),
                saved: Vec::new(),
            });
        };
        let humans: Vec<Source> = (0..avatar.layers.len())
            .filter(|&k| k != cloth)
            .map(Source::Layer)
            .collect();
        let scene: Vec<Source> = avatar.scene.iter().map(|_| Source::Scene).collect();
        let base_sources: Vec<(Source, bool)> =
            humans.iter().chain(&scene).map(|&s| (s, false)).collect();
        let mut matte_sources: Vec<(Source, bool)> = scene.iter().map(|&s| (s, false)).collect();
        if matte == Matte::Occlusion {
            matte_sources.extend(humans.iter().map(|&s| (s, false)));
        }
        matte_sources.push((Source::Layer(cloth), true));
        let (base_parts, base_count) = parts(avatar, &base_sources);
        let (matte_parts, matte_count) = parts(avatar, &matte_sources);
        let sh = avatar.posed.sh_degree;
        let pixels = width * height;
        let image = |name: &str, floats: u32| {
            ctx.create_buffer(name, BufferDesc::gpu_only(4 * u64::from(floats)))
        };
        // Without occluders the matte is the cloth pass's alpha: no pass for it.
        let matte = if !matte_parts.iter().any(|p| !p.matte && p.count > 0) {
            None
        } else {
            let mut gaussians =
                GaussianBuffers::new(ctx, "composite matte", matte_count as usize, 0)?;
            let colours: Vec<f32> = matte_parts
                .iter()
                .flat_map(|p| std::iter::repeat_n(matte_sh_dc(p.matte), 3 * p.count as usize))
                .collect();
            ctx.write_buffer(&mut gaussians.sh, &colours)?;
            Some(MattePass {
                grads: GaussianBuffers::new(ctx, "composite matte grads", matte_count as usize, 0)?,
                renderer: SplatRenderer::new(ctx, width, height, matte_count as usize)?,
                grad_image: image("composite grad matte", 3 * pixels)?,
                gaussians,
                parts: matte_parts,
            })
        };
        let pass = ThreePass {
            cloth,
            base: GaussianBuffers::new(ctx, "composite base", base_count as usize, sh)?,
            base_grads: GaussianBuffers::new(ctx, "composite base grads", base_count as usize, sh)?,
            base_renderer: SplatRenderer::new(ctx, width, height, base_count as usize)?,
            cloth_renderer: SplatRenderer::new(
                ctx,
                width,
                height,
                avatar.layers[cloth].count as usize,
            )?,
            matte,
            image: image("composite image", 3 * pixels)?,
            grad_base: image("composite grad base", 3 * pixels)?,
            grad_over: image("composite grad cloth", 3 * pixels)?,
            grad_over_alpha: image("composite grad cloth alpha", pixels)?,
            base_parts,
            pixels,
        };
        Ok(Self {
            inner: Inner::ThreePass(Box::new(pass)),
            saved: Vec::new(),
        })
    }

    /// Renders the avatar's posed Gaussians (of the last `Avatar::record_forward`).
    pub fn forward(
        &mut self,
        ctx: &Context,
        avatar: &Avatar,
        camera: &PinholeCamera,
        settings: &RenderSettings,
    ) -> Result<()> {
        // One submission per frame: for three passes the gather, the three renders
        // (which share only what they read, so the recorder interleaves them) and the
        // composite. A render whose tile intersections outgrew its buffers grows them,
        // and the frame is recorded again.
        loop {
            self.prepare_frame(avatar, camera, settings)?;
            {
                let mut rec = ctx.record(self.frame_label())?;
                self.record_frame(&mut rec, avatar)?;
                rec.submit_and_wait()?;
            }
            if !self.finish_frame()? {
                return Ok(());
            }
        }
    }

    fn frame_label(&self) -> &'static str {
        match self.inner {
            Inner::Single(_) => "splat forward",
            Inner::ThreePass(_) => "composite frame",
            Inner::Fused(_) => "fused frame",
        }
    }

    /// Sets the next frame's camera and settings (host-side only): then
    /// [`record_frame`](Self::record_frame), the submission, and
    /// [`finish_frame`](Self::finish_frame).
    pub fn prepare_frame(
        &mut self,
        avatar: &Avatar,
        camera: &PinholeCamera,
        settings: &RenderSettings,
    ) -> Result<()> {
        match &mut self.inner {
            Inner::Single(r) => r.prepare_forward(&avatar.posed, camera, settings),
            Inner::Fused(f) => f.renderer.prepare_forward(&avatar.posed, camera, settings),
            Inner::ThreePass(t) => {
                let black = PinholeCamera {
                    background: [0.0; 3],
                    ..*camera
                };
                t.base_renderer.prepare_forward(&t.base, camera, settings)?;
                t.cloth_renderer.prepare_forward(
                    &avatar.layers[t.cloth].deformer.posed,
                    &black,
                    settings,
                )?;
                if let Some(m) = &mut t.matte {
                    m.renderer.prepare_forward(&m.gaussians, &black, settings)?;
                }
                Ok(())
            }
        }
    }

    /// Records the frame [`prepare_frame`](Self::prepare_frame) set into `rec`, with no
    /// host read or wait inside: the image lands in [`rgb`](Self::rgb).
    pub fn record_frame<'a>(&'a self, rec: &mut Recording<'a>, avatar: &'a Avatar) -> Result<()> {
        match &self.inner {
            Inner::Single(r) => r.record_forward(rec, &avatar.posed),
            Inner::Fused(f) => {
                rec.set_scope("render.fused");
                f.renderer.record_forward(rec, &avatar.posed)?;
                record_composite(rec, f.renderer.outputs(), &f.image, f.pixels)?;
                rec.set_scope("");
                Ok(())
            }
            Inner::ThreePass(t) => {
                for p in &t.base_parts {
                    Avatar::record_move(
                        rec,
                        params(avatar, p.source),
                        &t.base,
                        p.first,
                        p.count,
                        false,
                    )?;
                }
                for p in t.matte.iter().flat_map(|m| &m.parts) {
                    let dst = t
                        .matte
                        .as_ref()
                        .expect("parts come from the matte")
                        .gaussians
                        .all();
                    let src = params(avatar, p.source).all();
                    for k in 0..4 {
                        let per = u64::from(GEOMETRY_FLOATS[k]);
                        rec.copy_region(
                            src[k],
                            0,
                            dst[k],
                            4 * per * u64::from(p.first),
                            4 * per * u64::from(p.count),
                        );
                    }
                }
                // Each render timed under its pass (interleaved passes counted once each).
                rec.set_scope("render.base");
                t.base_renderer.record_forward(rec, &t.base)?;
                rec.set_scope("render.cloth");
                t.cloth_renderer
                    .record_forward(rec, &avatar.layers[t.cloth].deformer.posed)?;
                if let Some(m) = &t.matte {
                    rec.set_scope("render.matte");
                    m.renderer.record_forward(rec, &m.gaussians)?;
                }
                rec.set_scope("");
                record_composite(rec, t.inputs(), &t.image, t.pixels)
            }
        }
    }

    /// Records the last recorded frame's image as premultiplied RGBA into `out` (4
    /// floats per pixel, row-major from the top row). The frame must have been rendered
    /// over a black background (its colour is then premultiplied); the alpha is the
    /// render's coverage (for a composite, `1 − (1 − A_base)(1 − V)`).
    pub fn record_rgba<'a>(&'a self, rec: &mut Recording<'a>, out: &'a Buffer) -> Result<()> {
        let (rgb, coverage, pixels) = match &self.inner {
            Inner::Single(r) => {
                let (rgb, alpha, _) = r.outputs();
                (rgb, Coverage::Alpha(alpha), r.width() * r.height())
            }
            Inner::Fused(f) => {
                let layer = f
                    .renderer
                    .outputs()
                    .matte_rgb
                    .expect("the fused renderer always renders its matte");
                (
                    &f.image,
                    Coverage::Two {
                        base: (f.renderer.transmittances(), 3, true),
                        layer: (layer, 3),
                    },
                    f.pixels,
                )
            }
            Inner::ThreePass(t) => {
                let layer = match &t.matte {
                    Some(m) => (m.renderer.outputs().0, 3),
                    None => (t.cloth_renderer.outputs().1, 1),
                };
                (
                    &t.image,
                    Coverage::Two {
                        base: (t.base_renderer.outputs().1, 1, false),
                        layer,
                    },
                    t.pixels,
                )
            }
        };
        record_to_rgba(rec, rgb, coverage, out, pixels)
    }

    /// After the submission of a [`record_frame`](Self::record_frame) completed: reads
    /// each render's intersection total. True when one outgrew its buffers: they have
    /// grown, and that frame's image is not valid (record it again).
    pub fn finish_frame(&mut self) -> Result<bool> {
        let stats = match &mut self.inner {
            Inner::Single(r) => vec![r.finish_forward()?],
            Inner::Fused(f) => vec![f.renderer.finish_forward()?],
            Inner::ThreePass(t) => {
                let mut stats = vec![
                    t.base_renderer.finish_forward()?,
                    t.cloth_renderer.finish_forward()?,
                ];
                if let Some(m) = &mut t.matte {
                    stats.push(m.renderer.finish_forward()?);
                }
                stats
            }
        };
        let overflowed = stats.iter().any(|s| s.rerendered);
        if !overflowed {
            self.saved = stats.into_iter().map(|s| s.saved).collect();
        }
        Ok(overflowed)
    }

    /// Whether the cloth is rendered apart, in its own pass or the fused frame's cloth
    /// state (the mask loss then reads it, and there are three images to show).
    pub fn is_three_pass(&self) -> bool {
        matches!(self.inner, Inner::ThreePass(_) | Inner::Fused(_))
    }

    /// Whether the three images come from one fused walk.
    pub fn is_fused(&self) -> bool {
        matches!(self.inner, Inner::Fused(_))
    }

    /// The last forward's image (3 floats per pixel) on the GPU.
    pub fn rgb(&self) -> &Buffer {
        match &self.inner {
            Inner::Single(r) => r.outputs().0,
            Inner::ThreePass(t) => &t.image,
            Inner::Fused(f) => &f.image,
        }
    }

    /// The last forward's image, read back.
    pub fn read_rgb(&mut self, ctx: &Context) -> Result<Vec<f32>> {
        match &mut self.inner {
            Inner::Single(r) => Ok(r.read_image()?.rgb),
            Inner::ThreePass(t) => ctx.read_buffer(&mut t.image, 3 * t.pixels as usize),
            Inner::Fused(f) => ctx.read_buffer(&mut f.image, 3 * f.pixels as usize),
        }
    }

    /// The three passes' images of the last forward (base, cloth, matte), read back;
    /// None for the single pass.
    pub fn read_passes(&mut self) -> Result<Option<[Vec<f32>; 3]>> {
        match &mut self.inner {
            Inner::Single(_) => Ok(None),
            Inner::ThreePass(t) => {
                let cloth = t.cloth_renderer.read_image()?;
                let matte = match &mut t.matte {
                    Some(m) => m.renderer.read_image()?.rgb,
                    None => cloth.alpha.iter().flat_map(|&a| [a; 3]).collect(),
                };
                Ok(Some([t.base_renderer.read_image()?.rgb, cloth.rgb, matte]))
            }
            Inner::Fused(f) => {
                let [base, cloth, _, matte] = f.renderer.read_images()?;
                Ok(Some([base, cloth, matte]))
            }
        }
    }

    /// Back-propagates `grad_rgb` (the loss's gradient on [`rgb`](Self::rgb)) and, with
    /// `mask`, the cloth mask loss, through the passes; then
    /// [`record_scatter`](Self::record_scatter) moves the gradients into every layer.
    /// `zeros` holds at least one zero float per pixel.
    pub fn backward(
        &mut self,
        ctx: &Context,
        avatar: &Avatar,
        grad_rgb: &Buffer,
        zeros: &Buffer,
        mask: Option<MaskLoss<'_>>,
    ) -> Result<()> {
        if self.saved.is_empty() {
            return Err(EngineError::StaleForward {
                op: "avatar backward",
                problem: "no forward pass to back-propagate through".into(),
            });
        }
        self.prepare_backward(avatar)?;
        {
            let mut rec = ctx.record("avatar backward")?;
            let cloth_losses = mask.as_ref().map(|m| &*m.losses);
            self.record_backward(&mut rec, avatar, grad_rgb, zeros, cloth_losses)?;
            rec.submit_and_wait()?;
        }
        if let (Inner::Single(_), Some(m), Some(cloth)) = (&self.inner, mask, avatar.cloth()) {
            m.losses.mask_pass(ctx, cloth, m.camera, m.settings)?;
        }
        Ok(())
    }

    /// Makes what [`record_backward`](Self::record_backward) needs for the avatar's
    /// accumulation (host-side; before the recording).
    pub fn prepare_backward(&mut self, avatar: &Avatar) -> Result<()> {
        let accumulation = avatar.accumulation();
        match &mut self.inner {
            Inner::Single(r) => r.prepare_backward(accumulation),
            Inner::Fused(f) => f.renderer.prepare_backward(accumulation),
            Inner::ThreePass(t) => {
                t.base_renderer.prepare_backward(accumulation)?;
                t.cloth_renderer.prepare_backward(accumulation)?;
                if let Some(m) = &mut t.matte {
                    m.renderer.prepare_backward(accumulation)?;
                }
                Ok(())
            }
        }
    }

    /// Records the backward of the frame recorded last (finished or still in the same
    /// recording), with no host wait: the composite's backward, the cloth mask loss
    /// where the compositor renders the cloth alone, and every render's backward.
    /// Without compositing the mask loss needs a render of its own
    /// (`ClothLosses::record_mask_pass`).
    pub fn record_backward<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        avatar: &'a Avatar,
        grad_rgb: &'a Buffer,
        zeros: &'a Buffer,
        cloth_losses: Option<&'a ClothLosses>,
    ) -> Result<()> {
        let accumulation = avatar.accumulation();
        match &self.inner {
            Inner::Fused(f) => {
                let grads = CompositeGrads {
                    base_rgb: &f.grad_base,
                    over_rgb: &f.grad_over,
                    over_alpha: &f.grad_over_alpha,
                    matte_rgb: Some(&f.grad_matte),
                };
                record_composite_backward(rec, grad_rgb, f.renderer.outputs(), grads, f.pixels)?;
                if let Some(c) = cloth_losses {
                    c.record_mask_grad(rec, f.renderer.outputs().over_alpha, &f.grad_over_alpha)?;
                }
                let upstream = FusedGrads {
                    base_rgb: &f.grad_base,
                    over_rgb: &f.grad_over,
                    over_alpha: &f.grad_over_alpha,
                    matte_rgb: &f.grad_matte,
                };
                let saved = f.renderer.splat_renderer().recorded_forward();
                f.renderer.record_backward(
                    rec,
                    &saved,
                    &avatar.posed,
                    upstream,
                    &avatar.posed_grads,
                    accumulation,
                )
            }
            Inner::Single(r) => r.record_backward(
                rec,
                &r.recorded_forward(),
                &avatar.posed,
                grad_rgb,
                zeros,
                zeros,
                &avatar.posed_grads,
                accumulation,
            ),
            Inner::ThreePass(t) => {
                let grads = CompositeGrads {
                    base_rgb: &t.grad_base,
                    over_rgb: &t.grad_over,
                    over_alpha: &t.grad_over_alpha,
                    matte_rgb: t.matte.as_ref().map(|m| &m.grad_image),
                };
                record_composite_backward(rec, grad_rgb, t.inputs(), grads, t.pixels)?;
                if let Some(c) = cloth_losses {
                    c.record_mask_grad(rec, t.cloth_renderer.outputs().1, &t.grad_over_alpha)?;
                }
                t.base_renderer.record_backward(
                    rec,
                    &t.base_renderer.recorded_forward(),
                    &t.base,
                    &t.grad_base,
                    zeros,
                    zeros,
                    &t.base_grads,
                    accumulation,
                )?;
                let cloth = &avatar.layers[t.cloth];
                t.cloth_renderer.record_backward(
                    rec,
                    &t.cloth_renderer.recorded_forward(),
                    &cloth.deformer.posed,
                    &t.grad_over,
                    &t.grad_over_alpha,
                    zeros,
                    &cloth.deformer.posed_grads,
                    accumulation,
                )?;
                if let Some(m) = &t.matte {
                    m.renderer.record_backward(
                        rec,
                        &m.renderer.recorded_forward(),
                        &m.gaussians,
                        &m.grad_image,
                        zeros,
                        zeros,
                        &m.grads,
                        accumulation,
                    )?;
                }
                Ok(())
            }
        }
    }

    /// Records `counter[0] += 1` for each render of the frame recorded last whose
    /// intersections outgrew its buffers (in the same recording, after the frame): a
    /// guard for the work recorded after it (Adam skips the step).
    pub fn record_overflow_flags<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        counter: &'a Buffer,
    ) -> Result<()> {
        match &self.inner {
            Inner::Single(r) => r.record_overflow_flag(rec, counter),
            Inner::Fused(f) => f
                .renderer
                .splat_renderer()
                .record_overflow_flag(rec, counter),
            Inner::ThreePass(t) => {
                t.base_renderer.record_overflow_flag(rec, counter)?;
                t.cloth_renderer.record_overflow_flag(rec, counter)?;
                if let Some(m) = &t.matte {
                    m.renderer.record_overflow_flag(rec, counter)?;
                }
                Ok(())
            }
        }
    }

    /// Records the addition of the last step into every layer's densification
    /// statistics (`ops::splat::densify`), from the pass that draws the layer in colour:
    /// the base pass for the body and the scene, the cloth pass for the cloth (the
    /// matte's gradients are left out); one pass for everything without compositing;
    /// the fused walk's per-splat gradients (there the matte's are summed in: its walk
    /// does not keep them apart).
    pub fn record_screen_stats<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        avatar: &'a Avatar,
    ) -> Result<()> {
        let r = match &self.inner {
            Inner::Single(r) => &**r,
            Inner::Fused(f) => f.renderer.splat_renderer(),
            Inner::ThreePass(t) => {
                for p in &t.base_parts {
                    record_screen_stats(
                        rec,
                        &t.base_renderer,
                        p.first,
                        p.count,
                        screen_stats(avatar, p.source),
                        0,
                    )?;
                }
                let cloth = &avatar.layers[t.cloth];
                return record_screen_stats(
                    rec,
                    &t.cloth_renderer,
                    0,
                    cloth.count,
                    &cloth.screen_stats,
                    0,
                );
            }
        };
        let mut first = 0;
        for l in &avatar.layers {
            record_screen_stats(rec, r, first, l.count, &l.screen_stats, 0)?;
            first += l.count;
        }
        if let Some(s) = &avatar.scene {
            record_screen_stats(rec, r, first, s.count, &s.screen_stats, 0)?;
        }
        Ok(())
    }

    /// Records the move of the passes' gradients into every layer's own posed
    /// gradients (where the per-layer losses then add theirs).
    pub fn record_scatter<'a>(&'a self, rec: &mut Recording<'a>, avatar: &'a Avatar) -> Result<()> {
        let t = match &self.inner {
            Inner::Single(_) | Inner::Fused(_) => {
                avatar.record_scatter_grads(rec)?;
                return Ok(());
            }
            Inner::ThreePass(t) => t,
        };
        for p in &t.base_parts {
            Avatar::record_move(
                rec,
                grads(avatar, p.source),
                &t.base_grads,
                p.first,
                p.count,
                true,
            )?;
        }
        for (m, p) in t
            .matte
            .iter()
            .flat_map(|m| m.parts.iter().map(move |p| (m, p)))
        {
            let (src, dst) = (m.grads.all(), grads(avatar, p.source).all());
            for k in 0..4 {
                let per = GEOMETRY_FLOATS[k];
                record_add_slice(rec, src[k], per * p.first, dst[k], per * p.count)?;
            }
        }
        Ok(())
    }
}

impl ThreePass {
    fn inputs(&self) -> CompositeInputs<'_> {
        CompositeInputs {
            base_rgb: self.base_renderer.outputs().0,
            over_rgb: self.cloth_renderer.outputs().0,
            over_alpha: self.cloth_renderer.outputs().1,
            matte_rgb: self.matte.as_ref().map(|m| m.renderer.outputs().0),
        }
    }
}
