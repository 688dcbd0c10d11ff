//! SSIM on the GPU (kernels `ssim::*`), as a metric and as a loss with its gradient,
//! and the CPU reference from the same shared functions (`drape_shared::ssim`, which
//! states the form: 11 × 11 Gaussian window, σ 1.5, zero-padded "same" convolution,
//! mean over the map), generic over f32/f64.

use drape_shared::real::Real;
use drape_shared::ssim::{
    blur_invocations, ssim_pointwise, window_taps, SsimParams, SSIM_MOMENTS, SSIM_WINDOW,
};

use crate::buffer::{Buffer, BufferDesc};
use crate::context::Context;
use crate::error::Result;
use crate::kernels;
use crate::mirror::{read_through, Mirror};
use crate::recorder::{flat_grid as grid, Recording};

/// Scratch for the SSIM of `width × height × 3` images.
pub struct Ssim {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    a: Buffer,
    b: Buffer,
    smap: Buffer,
    /// The map in host memory, where [`Ssim::keep_host_mirror`] asked for one.
    smap_mirror: Option<Mirror>,
}

impl Ssim {
    /// Scratch for `width × height` RGB images.
    pub fn new(ctx: &Context, width: u32, height: u32) -> Result<Self> {
        let n = u64::from(width) * u64::from(height) * 3;
        Ok(Self {
            width,
            height,
            a: ctx.create_buffer(
                "ssim moments a",
                BufferDesc::gpu_only(4 * n * u64::from(SSIM_MOMENTS)),
            )?,
            b: ctx.create_buffer(
                "ssim moments b",
                BufferDesc::gpu_only(4 * n * u64::from(SSIM_MOMENTS)),
            )?,
            smap: ctx.create_buffer("ssim map", BufferDesc::gpu_only(4 * n))?,
            smap_mirror: None,
        })
    }

    /// Keeps a host copy of the map (H·W·3 floats of host-visible memory): after
    /// [`Ssim::record_readback`] in the recording that computed it, [`Ssim::read_mean`]
    /// and [`Ssim::read_map`] read it without a submission or a wait of their own.
    pub fn keep_host_mirror(&mut self, ctx: &Context) -> Result<()> {
        self.smap_mirror = Some(Mirror::new(ctx, &self.smap)?);
        Ok(())
    }

    /// Records the copy of the map just recorded into the host mirror (nothing without
    /// one).
    pub fn record_readback<'a>(&'a self, rec: &mut Recording<'a>) {
        if let Some(m) = &self.smap_mirror {
            m.record_copy(rec, &self.smap, 4 * u64::from(self.pixels()));
        }
    }

    fn params(&self, planes: u32, vertical: bool, scale: f32) -> SsimParams {
        SsimParams {
            width: self.width,
            height: self.height,
            planes,
            vertical: u32::from(vertical),
            scale,
            _pad: [0; 3],
            taps: window_taps::<f32>(),
            _pad2: 0,
        }
    }

    fn pixels(&self) -> u32 {
        self.width * self.height * 3
    }

    /// Records the SSIM map of `pred` against `target` and, with `grad = Some((buffer,
    /// scale))`, adds `scale · ∂ mean(SSIM) / ∂ pred` to `buffer` (a loss
    /// `λ (1 - SSIM)` passes `-λ`).
    pub fn record<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        pred: &'a Buffer,
        target: &'a Buffer,
        grad: Option<(&'a Buffer, f32)>,
    ) -> Result<()> {
        let n = self.pixels();
        if let Some(m) = &self.smap_mirror {
            m.mark_stale();
        }
        let p = self.params(SSIM_MOMENTS, false, 0.0);
        rec.dispatch(
            "ssim.moments",
            kernels::ssim::Moments {
                x: pred.read(),
                y: target.read(),
                planes: self.a.write(),
            },
            &p,
            grid(n),
        )?;
        self.record_blur(rec, SSIM_MOMENTS, &self.a, &self.b)?;
        rec.dispatch(
            "ssim.map",
            kernels::ssim::Map {
                moments: self.a.read(),
                smap: self.smap.write(),
                partials: self.b.write(),
            },
            &p,
            grid(n),
        )?;
        if let Some((g, scale)) = grad {
            // The blurred partials end in b (b -> a -> b).
            self.record_blur(rec, 3, &self.b, &self.a)?;
            let p = self.params(3, false, scale / n.max(1) as f32);
            rec.dispatch(
                "ssim.grad",
                kernels::ssim::Grad {
                    x: pred.read(),
                    y: target.read(),
                    partials: self.b.read(),
                    grad: g.write(),
                },
                &p,
                grid(n),
            )?;
        }
        Ok(())
    }

    /// Horizontal pass `src -> tmp`, vertical pass `tmp -> src`.
    fn record_blur<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        planes: u32,
        src: &'a Buffer,
        tmp: &'a Buffer,
    ) -> Result<()> {
        let h = self.params(planes, false, 0.0);
        let across = blur_invocations(self.width, self.height, planes, false);
        rec.dispatch(
            "ssim.blur",
            kernels::ssim::Blur {
                src: src.read(),
                dst: tmp.write(),
            },
            &h,
            grid(across),
        )?;
        let v = self.params(planes, true, 0.0);
        let down = blur_invocations(self.width, self.height, planes, true);
        rec.dispatch(
            "ssim.blur",
            kernels::ssim::Blur {
                src: tmp.read(),
                dst: src.write(),
            },
            &v,
            grid(down),
        )?;
        Ok(())
    }

    /// The mean of the last recorded map (reads it back).
    pub fn read_mean(&mut self, ctx: &Context) -> Result<f64> {
        let n = self.pixels() as usize;
        let map = self.read_map(ctx)?;
        Ok(map.iter().map(|&v| f64::from(v)).sum::<f64>() / n.max(1) as f64)
    }

    /// The last recorded map (H·W·3): from the host mirror where the recording that
    /// computed it copied it there, otherwise read back from the device.
    pub fn read_map(&mut self, ctx: &Context) -> Result<Vec<f32>> {
        let n = self.pixels() as usize;
        read_through(ctx, self.smap_mirror.as_mut(), &mut self.smap, n)
    }
}

fn blur<F: Real>(img: &[F], width: usize, height: usize, vertical: bool) -> Vec<F> {
    let taps = window_taps::<F>();
    let half = (SSIM_WINDOW / 2) as i64;
    let mut out = vec![F::zero(); img.len()];
    for y in 0..height as i64 {
        for x in 0..width as i64 {
            for c in 0..3 {
                let mut s = F::zero();
                for (t, &w) in taps.iter().enumerate() {
                    let d = t as i64 - half;
                    let (qx, qy) = if vertical { (x, y + d) } else { (x + d, y) };
                    if qx >= 0 && qy >= 0 && qx < width as i64 && qy < height as i64 {
                        s += w * img[((qy as usize * width) + qx as usize) * 3 + c];
                    }
                }
                out[((y as usize * width) + x as usize) * 3 + c] = s;
            }
        }
    }
    out
}

fn blur2<F: Real>(img: &[F], width: usize, height: usize) -> Vec<F> {
    blur(&blur(img, width, height, false), width, height, true)
}

/// CPU reference: (map, mean, ∂ mean / ∂ pred).
pub fn reference<F: Real>(
    pred: &[F],
    target: &[F],
    width: usize,
    height: usize,
) -> (Vec<F>, F, Vec<F>) {
    let n = pred.len();
    let m = |f: &dyn Fn(usize) -> F| blur2(&(0..n).map(f).collect::<Vec<F>>(), width, height);
    let (mx, my) = (m(&|i| pred[i]), m(&|i| target[i]));
    let (exx, eyy, exy) = (
        m(&|i| pred[i] * pred[i]),
        m(&|i| target[i] * target[i]),
        m(&|i| pred[i] * target[i]),
    );
    let mut map = vec![F::zero(); n];
    let (mut pm, mut pxx, mut pxy) = (vec![F::zero(); n], vec![F::zero(); n], vec![F::zero(); n]);
    let mut sum = F::zero();
    for i in 0..n {
        let (s, a, b, c) = ssim_pointwise(mx[i], my[i], exx[i], eyy[i], exy[i]);
        map[i] = s;
        sum += s;
        pm[i] = a;
        pxx[i] = b;
        pxy[i] = c;
    }
    let (bm, bxx, bxy) = (
        blur2(&pm, width, height),
        blur2(&pxx, width, height),
        blur2(&pxy, width, height),
    );
    let inv = F::one() / F::of(n.max(1) as f32);
    let grad = (0..n)
        .map(|i| (bm[i] + F::of(2.0) * pred[i] * bxx[i] + target[i] * bxy[i]) * inv)
        .collect();
    (map, sum * inv, grad)
}
