//! Per-pixel front-to-back blending, forward and backward.
//!
//! Forward, for the splats of a pixel's tile in depth order: `σ = ½(a dx² + c dy²) + b dx dy`
//! with `d = centre - pixel`, `α = min(alpha_max, opacity · e^(-σ))`; splats with
//! `σ < 0` or `α < alpha_min` are skipped; blending stops before a splat that would
//! bring transmittance `T` to or below `transmittance_min`. Outputs colour
//! `Σ wᵢ cᵢ + T·background`, alpha `1 - T` and depth `Σ wᵢ zᵢ` (not normalized by
//! alpha), with `wᵢ = αᵢ Tᵢ`.
//!
//! Backward walks the same splats back to front from the last one blended, undoing
//! `T` and carrying what lies behind, so each splat's gradient needs no stored
//! per-splat state.

use crate::real::{Float, Real, V3};
use crate::splat::project::SplatGrad;

/// What a splat looks like to the rasterizer.
#[derive(Clone, Copy, Debug)]
pub struct SplatView<F> {
    pub x: F,
    pub y: F,
    pub depth: F,
    pub conic: [F; 3],
    pub opacity: F,
    pub color: V3<F>,
}

impl crate::splat::layout::ProjectedSplat {
    /// The rasterizer's view of a projected splat.
    #[inline]
    pub fn view(&self) -> SplatView<f32> {
        SplatView {
            x: self.x,
            y: self.y,
            depth: self.depth,
            conic: [self.conic_a, self.conic_b, self.conic_c],
            opacity: self.opacity,
            color: [self.r, self.g, self.b],
        }
    }
}

impl crate::splat::layout::HalfSplat {
    /// Packs a projected splat's view (see the type).
    #[inline]
    pub fn pack(s: &SplatView<f32>) -> Self {
        use crate::half::pack2;
        Self {
            x: s.x,
            y: s.y,
            conic_ab: pack2(s.conic[0], s.conic[1]),
            conic_c_opacity: pack2(s.conic[2], s.opacity),
            rg: pack2(s.color[0], s.color[1]),
            b_depth: pack2(s.color[2], s.depth),
        }
    }

    /// The rasterizer's view (exact: every half is an f32).
    #[inline]
    pub fn view(&self) -> SplatView<f32> {
        use crate::half::unpack2;
        let ab = unpack2(self.conic_ab);
        let co = unpack2(self.conic_c_opacity);
        let rg = unpack2(self.rg);
        let bd = unpack2(self.b_depth);
        SplatView {
            x: self.x,
            y: self.y,
            depth: bd[1],
            conic: [ab[0], ab[1], co[0]],
            opacity: co[1],
            color: [rg[0], rg[1], bd[0]],
        }
    }
}

impl SplatView<f32> {
    /// The view, for code generic over the splat layouts (`HalfSplat::view`).
    #[inline]
    pub fn view(&self) -> SplatView<f32> {
        *self
    }
}

impl<F: Real> BlendSettings<F> {
    pub fn from_frame(p: &crate::splat::layout::FrameParams) -> Self {
        Self {
            alpha_min: F::of(p.alpha_min),
            alpha_max: F::of(p.alpha_max),
            transmittance_min: F::of(p.transmittance_min),
        }
    }
}

/// Blending thresholds.
#[derive(Clone, Copy, Debug)]
pub struct BlendSettings<F> {
    pub alpha_min: F,
    pub alpha_max: F,
    pub transmittance_min: F,
}

/// A splat's footprint at a pixel centre.
#[derive(Clone, Copy, Debug)]
pub struct Footprint<F> {
    pub dx: F,
    pub dy: F,
    /// `e^(-σ)`.
    pub gauss: F,
    /// `opacity · e^(-σ)` before the `alpha_max` clamp.
    pub raw_alpha: F,
    pub alpha: F,
}

/// The footprint at pixel centre (px, py), or None when the splat is skipped there.
#[inline]
pub fn footprint<F: Real>(
    s: &SplatView<F>,
    px: F,
    py: F,
    cfg: &BlendSettings<F>,
) -> Option<Footprint<F>> {
    let dx = s.x - px;
    let dy = s.y - py;
    let half = F::of(0.5);
    let sigma = half * (s.conic[0] * dx * dx + s.conic[2] * dy * dy) + s.conic[1] * dx * dy;
    if !(sigma >= F::zero()) {
        return None;
    }
    let gauss = (-sigma).exp_k();
    let raw_alpha = s.opacity * gauss;
    let alpha = raw_alpha.min(cfg.alpha_max);
    if !(alpha >= cfg.alpha_min) {
        return None;
    }
    Some(Footprint {
        dx,
        dy,
        gauss,
        raw_alpha,
        alpha,
    })
}

/// Conic condition number `(a + c)² / (ac − b²)` above which [`may_touch_rect`] does not
/// cull: past it `σ`'s rounding in f32 (about `4ε` of `(a + c)·|d|²`) is no longer small
/// against `σ` itself, and the exact ellipse no longer bounds where `footprint` passes.
const CULL_MAX_CONDITION: f32 = 1.0e4;

/// Whether `s` may be blended at a pixel centre inside `[lo, hi]` (pixel-centre
/// coordinates, `lo ≤ hi`): false only when [`footprint`] returns None at every pixel
/// centre there, so a rasterizer may skip the splat for that block of pixels and
/// blend exactly what it would have blended.
///
/// A splat passes [`footprint`] only where `opacity · e^(-σ) ≥ alpha_min`, i.e.
/// `σ ≤ t = ln(opacity / alpha_min)`, inside the ellipse `dᵀ C d ≤ 2t` whose bounding
/// box has half-widths `√(2t·c/det)` and `√(2t·a/det)`. The box is widened for f32
/// rounding: `t` by 5% and 0.02 (`σ`'s rounding is under 0.3% of `σ` below
/// [`CULL_MAX_CONDITION`]; `exp_f32` and `ln_f32` are within a few ulp), the widths by
/// 0.01 px and 1e-5 of the centre's coordinates (the rounding of `d`). Degenerate or
/// non-finite conics are never culled.
#[inline]
pub fn may_touch_rect(
    s: &SplatView<f32>,
    lo: [f32; 2],
    hi: [f32; 2],
    cfg: &BlendSettings<f32>,
) -> bool {
    // opacity · e^(-σ) ≤ opacity for σ ≥ 0 (the product rounds to at most opacity).
    if s.opacity < cfg.alpha_min {
        return false;
    }
    let [a, b, c] = s.conic;
    let det = a * c - b * b;
    let trace = a + c;
    // Written so that NaN anywhere keeps the splat.
    if !(det > 0.0 && a > 0.0 && c > 0.0 && trace * trace <= CULL_MAX_CONDITION * det) {
        return true;
    }
    let t = (s.opacity / cfg.alpha_min).ln_k() * 1.05 + 0.02;
    let slack = 0.01 + 1e-5 * (Float::abs(s.x) + Float::abs(s.y));
    let half_x = Float::sqrt(2.0 * t * c / det) + slack;
    let half_y = Float::sqrt(2.0 * t * a / det) + slack;
    // Distance from the centre to the rectangle along each axis (0 inside).
    let out_x = (lo[0] - s.x).max(s.x - hi[0]).max(0.0);
    let out_y = (lo[1] - s.y).max(s.y - hi[1]).max(0.0);
    !(out_x > half_x || out_y > half_y)
}

/// Forward blending state of one pixel.
#[derive(Clone, Copy, Debug)]
pub struct PixelFwd<F> {
    pub transmittance: F,
    pub color: V3<F>,
    pub depth: F,
    /// Splats of the tile's list visited up to and including the last one blended.
    pub contributors: u32,
    /// Splats actually blended (the benchmark's blend steps).
    pub blended: u32,
    pub done: bool,
}

impl<F: Real> PixelFwd<F> {
    pub fn new() -> Self {
        let z = F::zero();
        Self {
            transmittance: F::one(),
            color: [z; 3],
            depth: z,
            contributors: 0,
            blended: 0,
            done: false,
        }
    }

    /// Blends the `index`-th splat of the tile list (0-based); sets `done` when the
    /// pixel is saturated.
    #[inline]
    pub fn blend(&mut self, s: &SplatView<F>, index: u32, px: F, py: F, cfg: &BlendSettings<F>) {
        let Some(f) = footprint(s, px, py, cfg) else {
            return;
        };
        self.blend_footprint(&f, s.color, s.depth, index, cfg);
    }

    /// [`blend`](Self::blend) with the footprint already computed (the fused
    /// rasterizer blends one footprint into several states) and the colour given.
    #[inline]
    pub fn blend_footprint(
        &mut self,
        f: &Footprint<F>,
        color: V3<F>,
        depth: F,
        index: u32,
        cfg: &BlendSettings<F>,
    ) {
        let next = self.transmittance * (F::one() - f.alpha);
        if !(next > cfg.transmittance_min) {
            self.done = true;
            return;
        }
        let w = f.alpha * self.transmittance;
        // Written out, not looped: llvmpipe caps the loop iterations of a whole
        // invocation at 65,535, and this runs once per splat per pixel.
        self.color[0] += w * color[0];
        self.color[1] += w * color[1];
        self.color[2] += w * color[2];
        self.depth += w * depth;
        self.transmittance = next;
        self.contributors = index + 1;
        self.blended += 1;
    }

    /// Final colour over `background`.
    pub fn rgb(&self, background: V3<F>) -> V3<F> {
        let t = self.transmittance;
        [
            self.color[0] + t * background[0],
            self.color[1] + t * background[1],
            self.color[2] + t * background[2],
        ]
    }
}

impl<F: Real> Default for PixelFwd<F> {
    fn default() -> Self {
        Self::new()
    }
}

/// Mask bits of the fused rasterizer: which of a pixel's three states a splat blends
/// into, the three passes of `ops::splat::composite` (the caller says which of its
/// clouds goes where; the trainer: body and scene into the base, the cloth over it).
/// Blends into the base pass.
pub const FUSED_BASE: u32 = 1;
/// Blends into the over pass (the layer composited over the base, drawn alone).
pub const FUSED_OVER: u32 = 2;
/// Blends into the matte with colour 0 (an occluder of the over layer).
pub const FUSED_MATTE_ZERO: u32 = 4;
/// Blends into the matte with colour 1 (the over layer).
pub const FUSED_MATTE_ONE: u32 = 8;

/// The three forward states of one pixel of the fused rasterizer: the base pass, the
/// over pass and the matte, each blended exactly as its own
/// pass would blend it, in one walk of the tile's depth-sorted list of every layer.
/// Each state's members keep their depth order in the merged list, so each state
/// sums the same terms in the same order as its own pass. A state's `contributors`
/// counts the merged list (one past its last blended splat there), which is where
/// its backward walk ([`FusedPixelBwd`]) starts.
#[derive(Clone, Copy, Debug)]
pub struct FusedPixel<F> {
    pub base: PixelFwd<F>,
    pub over: PixelFwd<F>,
    pub matte: PixelFwd<F>,
}

impl<F: Real> FusedPixel<F> {
    /// A state is done when saturated; one that never saturates (no over layer at a
    /// pixel) keeps the walk going to the end of the list, where its own pass would
    /// also have ended.
    pub fn new() -> Self {
        Self {
            base: PixelFwd::new(),
            over: PixelFwd::new(),
            matte: PixelFwd::new(),
        }
    }

    /// All three states saturated.
    #[inline]
    pub fn done(&self) -> bool {
        self.base.done && self.over.done && self.matte.done
    }

    /// Blends the `index`-th splat of the merged tile list (0-based), with layer mask
    /// `mask`.
    #[inline]
    pub fn blend(
        &mut self,
        s: &SplatView<F>,
        mask: u32,
        index: u32,
        px: F,
        py: F,
        cfg: &BlendSettings<F>,
    ) {
        let in_base = mask & FUSED_BASE != 0;
        let in_over = mask & FUSED_OVER != 0;
        let in_matte = mask & (FUSED_MATTE_ZERO | FUSED_MATTE_ONE) != 0;
        let wanted = (in_base && !self.base.done)
            || (in_over && !self.over.done)
            || (in_matte && !self.matte.done);
        if wanted {
            if let Some(f) = footprint(s, px, py, cfg) {
                if in_base && !self.base.done {
                    self.base.blend_footprint(&f, s.color, s.depth, index, cfg);
                }
                if in_over && !self.over.done {
                    self.over.blend_footprint(&f, s.color, s.depth, index, cfg);
                }
                if in_matte && !self.matte.done {
                    let m = matte_value::<F>(mask);
                    self.matte
                        .blend_footprint(&f, [m, m, m], s.depth, index, cfg);
                }
            }
        }
    }

    /// The states' final transmittances (base, over, matte): what the backward starts from.
    #[inline]
    pub fn transmittances(&self) -> [F; 3] {
        [
            self.base.transmittance,
            self.over.transmittance,
            self.matte.transmittance,
        ]
    }

    /// The states' ends in the merged list (base, over, matte): one past each one's
    /// last blended splat.
    #[inline]
    pub fn ends(&self) -> [u32; 3] {
        [
            self.base.contributors,
            self.over.contributors,
            self.matte.contributors,
        ]
    }
}

impl<F: Real> Default for FusedPixel<F> {
    fn default() -> Self {
        Self::new()
    }
}

/// A splat's colour in the matte: 1 for the composited layer, 0 for an occluder.
#[inline]
fn matte_value<F: Real>(mask: u32) -> F {
    if mask & FUSED_MATTE_ONE != 0 {
        F::one()
    } else {
        F::zero()
    }
}

/// Backward state of one pixel of the fused rasterizer: the three states' backward
/// walks ([`PixelBwd`], as each pass's own) over the merged list, back to front. A
/// splat gets the sum of what the states it blended into send it; the matte's colour
/// is fixed (1 or 0), so the matte sends no colour gradient.
#[derive(Clone, Copy, Debug)]
pub struct FusedPixelBwd<F> {
    pub base: PixelBwd<F>,
    pub over: PixelBwd<F>,
    pub matte: PixelBwd<F>,
    /// The forward's [`FusedPixel::ends`].
    pub ends: [u32; 3],
}

impl<F: Real> FusedPixelBwd<F> {
    /// From the forward's final transmittances and ends ([`FusedPixel::transmittances`],
    /// [`FusedPixel::ends`]) and the pixel's upstream gradients: on the base rgb (drawn
    /// over `background`), the over pass's rgb and alpha (over black), and the matte's
    /// value.
    pub fn new(
        transmittances: [F; 3],
        ends: [u32; 3],
        background: V3<F>,
        grad_base: V3<F>,
        grad_over: V3<F>,
        grad_over_alpha: F,
        grad_matte: F,
    ) -> Self {
        let z = F::zero();
        Self {
            base: PixelBwd::new(transmittances[0], background, grad_base, z, z),
            over: PixelBwd::new(transmittances[1], [z; 3], grad_over, grad_over_alpha, z),
            matte: PixelBwd::new(transmittances[2], [z; 3], [grad_matte, z, z], z, z),
            ends,
        }
    }

    /// The furthest end of the three: where the pixel's backward walk starts.
    #[inline]
    pub fn end(&self) -> u32 {
        let e = if self.ends[0] > self.ends[1] {
            self.ends[0]
        } else {
            self.ends[1]
        };
        if e > self.ends[2] {
            e
        } else {
            self.ends[2]
        }
    }

    /// The gradient this pixel sends to the `index`-th splat of the merged list (layer
    /// mask `mask`); visit the splats from the last to the first. None when no state
    /// blended it.
    #[inline]
    pub fn step(
        &mut self,
        s: &SplatView<F>,
        mask: u32,
        index: u32,
        px: F,
        py: F,
        cfg: &BlendSettings<F>,
    ) -> Option<SplatGrad<F>> {
        let in_base = mask & FUSED_BASE != 0 && index < self.ends[0];
        let in_over = mask & FUSED_OVER != 0 && index < self.ends[1];
        let in_matte = mask & (FUSED_MATTE_ZERO | FUSED_MATTE_ONE) != 0 && index < self.ends[2];
        if !(in_base || in_over || in_matte) {
            return None;
        }
        // One footprint for every state (the forward blended one footprint into each).
        let f = footprint(s, px, py, cfg)?;
        let mut total = SplatGrad::zero();
        if in_base {
            total = total.add(&self.base.step_footprint(&f, s, cfg));
        }
        if in_over {
            total = total.add(&self.over.step_footprint(&f, s, cfg));
        }
        if in_matte {
            let m = matte_value::<F>(mask);
            let v = SplatView {
                color: [m, m, m],
                ..*s
            };
            let mut g = self.matte.step_footprint(&f, &v, cfg);
            g.color = [F::zero(); 3];
            total = total.add(&g);
        }
        Some(total)
    }
}

/// Backward state of one pixel, walking its splats from the last blended to the first.
///
/// The gradient on a splat's alpha is, per output channel `c` (colour and depth) with
/// upstream gradient `g_c`, `g_c · (v_c · T - B_c / (1 - α))` plus
/// `g_alpha · T_final / (1 - α)`, where `B_c` is what lies behind the splat in channel
/// `c` (background included). Summed over the channels that is
/// `T · Σ g_c v_c - (Σ g_c B_c - g_alpha · T_final) / (1 - α)`, and the bracket grows by
/// `w · Σ g_c v_c` at each splat: one running scalar, [`behind`](Self::behind), in place
/// of the four per-channel sums and the final transmittance. The state is 6 floats
/// instead of 11, which matters where one lane keeps four pixels (the subgroup
/// rasterizers on llvmpipe spilled the larger state to the stack).
#[derive(Clone, Copy, Debug)]
pub struct PixelBwd<F> {
    /// Transmittance in front of the splat being visited (starts at the final one).
    pub transmittance: F,
    /// `Σ_c g_c · B_c - g_alpha · T_final` for everything behind the splat being visited.
    behind: F,
    grad_color: V3<F>,
    grad_depth: F,
}

impl<F: Real> PixelBwd<F> {
    /// Starts from the forward pass's final transmittance and the pixel's upstream
    /// gradients on colour, alpha and depth.
    pub fn new(
        final_transmittance: F,
        background: V3<F>,
        grad_color: V3<F>,
        grad_alpha: F,
        grad_depth: F,
    ) -> Self {
        let t = final_transmittance;
        // Behind the last splat: the background seen through T_final (depth 0 there);
        // the alpha term enters with the opposite sign (alpha = 1 - T_final rises with α).
        let behind_background = t
            * (grad_color[0] * background[0]
                + grad_color[1] * background[1]
                + grad_color[2] * background[2]);
        Self {
            transmittance: t,
            behind: behind_background - grad_alpha * t,
            grad_color,
            grad_depth,
        }
    }

    /// The gradient this pixel sends to splat `s` (None when the forward pass skipped it).
    #[inline]
    pub fn step(
        &mut self,
        s: &SplatView<F>,
        px: F,
        py: F,
        cfg: &BlendSettings<F>,
    ) -> Option<SplatGrad<F>> {
        let f = footprint(s, px, py, cfg)?;
        Some(self.step_footprint(&f, s, cfg))
    }

    /// [`step`](Self::step) with the footprint already computed (the fused backward
    /// steps one footprint through several states).
    #[inline]
    pub fn step_footprint(
        &mut self,
        f: &Footprint<F>,
        s: &SplatView<F>,
        cfg: &BlendSettings<F>,
    ) -> SplatGrad<F> {
        let one_minus = F::one() - f.alpha;
        self.transmittance = self.transmittance / one_minus;
        let t = self.transmittance;
        let w = f.alpha * t;
        let mut g = SplatGrad::zero();
        // The upstream gradient's projection on this splat's colour and depth.
        let seen = self.grad_color[0] * s.color[0]
            + self.grad_color[1] * s.color[1]
            + self.grad_color[2] * s.color[2]
            + self.grad_depth * s.depth;
        g.color = [
            w * self.grad_color[0],
            w * self.grad_color[1],
            w * self.grad_color[2],
        ];
        g.depth = w * self.grad_depth;
        let g_alpha = t * seen - self.behind / one_minus;
        self.behind += w * seen;

        // α = opacity · e^(-σ) unless clamped at alpha_max (then flat).
        if f.raw_alpha < cfg.alpha_max {
            g.opacity = f.gauss * g_alpha;
            let g_sigma = -s.opacity * f.gauss * g_alpha;
            let half = F::of(0.5);
            g.conic = [
                half * f.dx * f.dx * g_sigma,
                f.dx * f.dy * g_sigma,
                half * f.dy * f.dy * g_sigma,
            ];
            g.x = (s.conic[0] * f.dx + s.conic[1] * f.dy) * g_sigma;
            g.y = (s.conic[2] * f.dy + s.conic[1] * f.dx) * g_sigma;
        }
        g
    }
}
