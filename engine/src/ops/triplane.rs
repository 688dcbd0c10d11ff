//! Triplane features on the GPU (kernels `triplane::*`), forward and backward, and the
//! CPU reference from the same shared functions (`drape_shared::triplane`, which
//! states the sampling and the zero padding), generic over f32/f64.
//!
//! A [`Triplane`] owns its planes (3 × R × R × C, channels-last), their gradient, and
//! the layer's box that maps canonical points into `[-1, 1]³`.

use drape_shared::real::Real;
use drape_shared::triplane::{
    corners, footprint, inside, normalise, texel_index, TriplaneParams, PLANE_AXES,
};
use rand::{Rng, SeedableRng};

use crate::buffer::{Buffer, BufferDesc};
use crate::context::Context;
use crate::error::Result;
use crate::kernels;
use crate::ops::accumulate::{Accumulation, FixedPointScratch, Method};
use crate::recorder::Recording;

/// How the planes start.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum TriplaneInit {
    /// Every value drawn from N(0, 1) (HUGS), reproducible from the seed.
    Normal {
        /// The random seed.
        seed: u64,
    },
    /// Every value 0.
    Zeros,
}

/// Size and placement of a triplane.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TriplaneDesc {
    /// Texels per side of each plane.
    pub resolution: u32,
    /// Features per texel.
    pub channels: u32,
    /// The box's low corner: the planes span the box, mapped to [-1, 1] per axis.
    pub box_min: [f32; 3],
    /// The box's high corner.
    pub box_max: [f32; 3],
}

impl TriplaneDesc {
    /// Floats in the three planes.
    pub fn len(&self) -> usize {
        3 * (self.resolution as usize).pow(2) * self.channels as usize
    }

    /// Whether the planes have no floats.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Width of a point's feature vector (3C).
    pub fn feature_width(&self) -> usize {
        3 * self.channels as usize
    }

    /// The kernels' parameters for `count` points.
    pub fn params(&self, count: u32) -> TriplaneParams {
        let s = |a: usize| 2.0 / (self.box_max[a] - self.box_min[a]);
        TriplaneParams {
            count,
            resolution: self.resolution,
            channels: self.channels,
            _pad0: 0,
            box_min: [self.box_min[0], self.box_min[1], self.box_min[2], 0.0],
            box_scale: [s(0), s(1), s(2), 0.0],
        }
    }

    /// Initial plane values.
    pub fn init(&self, init: TriplaneInit) -> Vec<f32> {
        match init {
            TriplaneInit::Zeros => vec![0.0; self.len()],
            TriplaneInit::Normal { seed } => {
                let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
                // Box–Muller: two uniforms give two independent N(0, 1) values.
                let mut out = Vec::with_capacity(self.len() + 1);
                while out.len() < self.len() {
                    let u1: f64 = 1.0 - rng.random::<f64>(); // (0, 1]: ln is finite
                    let u2: f64 = rng.random();
                    let r = (-2.0 * u1.ln()).sqrt();
                    let t = std::f64::consts::TAU * u2;
                    out.push((r * t.cos()) as f32);
                    out.push((r * t.sin()) as f32);
                }
                out.truncate(self.len());
                out
            }
        }
    }

    fn check(&self) {
        assert!(
            self.resolution >= 2,
            "a triplane needs at least 2 texels per side"
        );
        assert!(self.channels >= 1, "a triplane needs at least one channel");
        for a in 0..3 {
            assert!(
                self.box_max[a] > self.box_min[a],
                "the triplane's box is empty along axis {a}"
            );
        }
    }
}

/// A triplane's planes and gradient on the GPU.
pub struct Triplane {
    /// Its size and placement.
    pub desc: TriplaneDesc,
    /// The three planes, `3 × resolution² × channels` floats.
    pub planes: Buffer,
    /// Gradient on the planes, accumulated by [`Triplane::record_backward`].
    pub grads: Buffer,
    /// For [`Accumulation::Deterministic`], made by [`Triplane::prepare`].
    fixed: Option<FixedPointScratch>,
}

impl Triplane {
    /// Planes initialised by `init`.
    pub fn new(ctx: &Context, label: &str, desc: TriplaneDesc, init: TriplaneInit) -> Result<Self> {
        Self::with_planes(ctx, label, desc, &desc.init(init))
    }

    /// Planes with the given values.
    pub fn with_planes(
        ctx: &Context,
        label: &str,
        desc: TriplaneDesc,
        planes: &[f32],
    ) -> Result<Self> {
        desc.check();
        assert_eq!(
            planes.len(),
            desc.len(),
            "{label}: plane data has the wrong length"
        );
        let bytes = desc.len() as u64 * 4;
        let mut p = ctx.create_buffer(&format!("{label} planes"), BufferDesc::gpu_only(bytes))?;
        ctx.write_buffer(&mut p, planes)?;
        Ok(Self {
            desc,
            planes: p,
            grads: ctx
                .create_buffer(&format!("{label} plane grads"), BufferDesc::gpu_only(bytes))?,
            fixed: None,
        })
    }

    /// Allocates what `accumulation` needs in [`record_backward`](Self::record_backward)
    /// (for the deterministic way, a fixed-point scratch twice the planes' size).
    pub fn prepare(&mut self, ctx: &Context, accumulation: Accumulation) -> Result<()> {
        if accumulation == Accumulation::Deterministic && self.fixed.is_none() {
            self.fixed = Some(FixedPointScratch::new(
                ctx,
                "triplane plane grads",
                self.desc.len() as u32,
            )?);
        }
        Ok(())
    }

    /// Records `features = sample(points)` for `count` points (features count × 3C).
    pub fn record_forward<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        points: &'a Buffer,
        features: &'a Buffer,
        count: u32,
    ) -> Result<()> {
        let p = self.desc.params(count);
        rec.dispatch(
            "triplane.sample_fwd",
            kernels::triplane::SampleFwd {
                planes: self.planes.read(),
                points: points.read(),
                features: features.write(),
            },
            &p,
            [count.div_ceil(256), 1, 1],
        )
    }

    /// Records the backward pass: the plane gradient (overwritten) and the points'
    /// gradient (count × 3, written). `accumulation` picks the scatter-add: float
    /// atomics, compare-and-swap, or deterministic fixed point (which needs
    /// [`prepare`](Self::prepare) first).
    #[allow(clippy::too_many_arguments)]
    pub fn record_backward<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        points: &'a Buffer,
        grad_features: &'a Buffer,
        grad_points: &'a Buffer,
        count: u32,
        accumulation: Accumulation,
    ) -> Result<()> {
        let p = self.desc.params(count);
        let method = accumulation.method(rec.context());
        let (kernel, target) = match method {
            Method::FloatAtomics => (
                kernels::triplane::SampleBwdAtomicKernel::TriplaneSampleBwdAtomic,
                &self.grads,
            ),
            Method::CompareAndSwap => (
                kernels::triplane::SampleBwdAtomicKernel::TriplaneSampleBwdCas,
                &self.grads,
            ),
            Method::FixedPoint => {
                let fixed = self.fixed.as_ref().expect("Triplane::prepare(ctx, Accumulation::Deterministic) before a deterministic backward");
                (
                    kernels::triplane::SampleBwdAtomicKernel::TriplaneSampleBwdFixed,
                    fixed.buffer(),
                )
            }
        };
        rec.fill(target, 0);
        rec.dispatch_as(
            "triplane.sample_bwd",
            kernel,
            kernels::triplane::SampleBwdAtomic {
                planes: self.planes.read(),
                points: points.read(),
                grad_features: grad_features.read(),
                grad_planes: target.write(),
                grad_points: grad_points.write(),
            },
            &p,
            [count.div_ceil(256), 1, 1],
        )?;
        if let (Method::FixedPoint, Some(fixed)) = (method, &self.fixed) {
            fixed.record_resolve(rec, &self.grads, self.desc.len() as u32)?;
        }
        Ok(())
    }
}

/// CPU references of the triplane lookup, forward and backward, generic over f32/f64.
pub mod reference {
    use super::*;

    /// CPU reference of the forward pass: count × 3C features.
    pub fn forward<F: Real>(desc: &TriplaneDesc, planes: &[F], points: &[F]) -> Vec<F> {
        let p = desc.params((points.len() / 3) as u32);
        let ch = desc.channels as usize;
        let mut out = vec![F::zero(); points.len() / 3 * 3 * ch];
        for (i, pt) in points.chunks_exact(3).enumerate() {
            if !pt.iter().all(|v| v.is_finite()) {
                continue;
            }
            let u = normalise([pt[0], pt[1], pt[2]], &p);
            for (plane, &(ax, ay)) in PLANE_AXES.iter().enumerate() {
                let cs = corners(
                    &footprint(u[ax], p.resolution),
                    &footprint(u[ay], p.resolution),
                );
                for (row, col, w, _, _) in cs {
                    if inside(row, p.resolution) && inside(col, p.resolution) {
                        let t = texel_index(plane, row, col, &p);
                        for c in 0..ch {
                            out[i * 3 * ch + plane * ch + c] += w * planes[t + c];
                        }
                    }
                }
            }
        }
        out
    }

    /// CPU reference of the backward pass: (plane gradient, points' gradient).
    pub fn backward<F: Real>(
        desc: &TriplaneDesc,
        planes: &[F],
        points: &[F],
        grad_features: &[F],
    ) -> (Vec<F>, Vec<F>) {
        let p = desc.params((points.len() / 3) as u32);
        let ch = desc.channels as usize;
        let mut gplanes = vec![F::zero(); planes.len()];
        let mut gpoints = vec![F::zero(); points.len()];
        for (i, pt) in points.chunks_exact(3).enumerate() {
            if !pt.iter().all(|v| v.is_finite()) {
                continue;
            }
            let u = normalise([pt[0], pt[1], pt[2]], &p);
            let mut gu = [F::zero(); 3];
            for (plane, &(ax, ay)) in PLANE_AXES.iter().enumerate() {
                let cs = corners(
                    &footprint(u[ax], p.resolution),
                    &footprint(u[ay], p.resolution),
                );
                for (row, col, w, dwx, dwy) in cs {
                    if inside(row, p.resolution) && inside(col, p.resolution) {
                        let t = texel_index(plane, row, col, &p);
                        let mut dot = F::zero();
                        for c in 0..ch {
                            let g = grad_features[i * 3 * ch + plane * ch + c];
                            dot += g * planes[t + c];
                            gplanes[t + c] += w * g;
                        }
                        gu[ax] += dwx * dot;
                        gu[ay] += dwy * dot;
                    }
                }
            }
            for a in 0..3 {
                gpoints[3 * i + a] = gu[a] * F::of(p.box_scale[a]);
            }
        }
        (gplanes, gpoints)
    }
}
