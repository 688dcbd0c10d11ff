//! The scene layer: plain 3DGS Gaussians in world space (no triplane, no skinning),
//! initialised from the sequence's sparse COLMAP points as 3DGS does (one isotropic
//! Gaussian per point, scale the root mean squared distance to its three nearest
//! neighbours, opacity 0.1, colour from the point), optimised directly by Adam with
//! the paper's rates. It is rendered with the avatar's layers (in their depth-sorted
//! pass, or in the composite's base and matte passes) at its own SH degree
//! ([`SceneConfig::sh_degree`]; the pass pads the lower degrees to the highest).

use crate::avatar::groups::Layer;
use drape_engine::ops::adam::{AdamGroup, LrSchedule};
use drape_engine::ops::splat::densify::SCREEN_STATS_FLOATS;
use drape_engine::ops::splat::render::GaussianBuffers;
use drape_engine::ops::splat::scene::GaussianCloud;
use drape_engine::{Buffer, Context, Recording, Result};
use drape_shared::splat::layout::MAX_SH_COEFFS;
use drape_shared::splat::project::Gaussian;

use crate::avatar::state::{AdamState, SceneState, SCENE_PARAMS};
use crate::dataset::colmap::ColmapModel;

/// The scene layer's learning rates (paper: position 1.6e-4 → 1.6e-6 over the run,
/// scaled by the scene's extent as 3DGS does; rotation 1e-3, scale 5e-3, opacity
/// 5e-2; SH 2.5e-3 as 3DGS).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneConfig {
    pub lr_position: f32,
    pub lr_position_final: f32,
    pub lr_rotation: f32,
    pub lr_scale: f32,
    pub lr_opacity: f32,
    pub lr_sh: f32,
    /// At most this many COLMAP points become Gaussians (every k-th beyond it).
    pub max_points: u32,
    /// SH degree of the scene's colours (3DGS: 3; the human layers have their own).
    /// Missing from a config file: 0.
    #[serde(default)]
    pub sh_degree: u32,
}

impl Default for SceneConfig {
    fn default() -> Self {
        Self {
            lr_position: 1.6e-4,
            lr_position_final: 1.6e-6,
            lr_rotation: 1e-3,
            lr_scale: 5e-3,
            lr_opacity: 5e-2,
            lr_sh: 2.5e-3,
            max_points: 100_000,
            sh_degree: 3,
        }
    }
}

/// The initial scene Gaussians from COLMAP points, and the scene's extent (the
/// largest distance of a point from their centroid, for the position rate).
pub fn scene_init(colmap: &ColmapModel, sh_degree: u32, max_points: u32) -> (GaussianCloud, f32) {
    let all: Vec<([f64; 3], [u8; 3])> = colmap.points.values().map(|p| (p.xyz, p.rgb)).collect();
    let step = all.len().div_ceil(max_points.max(1) as usize).max(1);
    let pts: Vec<([f64; 3], [u8; 3])> = all.into_iter().step_by(step).collect();
    let mut cloud = GaussianCloud::new(sh_degree);
    let n = pts.len();
    let centroid = pts
        .iter()
        .fold([0.0; 3], |a, (p, _)| {
            [a[0] + p[0], a[1] + p[1], a[2] + p[2]]
        })
        .map(|v| v / n.max(1) as f64);
    let extent = pts
        .iter()
        .map(|(p, _)| {
            ((p[0] - centroid[0]).powi(2)
                + (p[1] - centroid[1]).powi(2)
                + (p[2] - centroid[2]).powi(2))
            .sqrt()
        })
        .fold(0.0f64, f64::max);
    let opacity_logit = (0.1f64 / 0.9).ln() as f32;
    for (i, (p, rgb)) in pts.iter().enumerate() {
        // Three nearest neighbours by brute force: COLMAP models are 10⁴-10⁵ points
        // and this runs once.
        let mut best = [f64::INFINITY; 3];
        for (j, (q, _)) in pts.iter().enumerate() {
            if i == j {
                continue;
            }
            let d = (p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2);
            if d < best[2] {
                best[2] = d;
                best.sort_by(f64::total_cmp);
            }
        }
        let finite: Vec<f64> = best.iter().copied().filter(|d| d.is_finite()).collect();
        let mean_d2 = if finite.is_empty() {
            1e-2
        } else {
            finite.iter().sum::<f64>() / finite.len() as f64
        };
        let scale = (mean_d2.max(1e-14).sqrt().ln()) as f32;
        let mut sh = [[0.0f32; 3]; MAX_SH_COEFFS];
        // Colour = 0.5 + C0 · dc at degree 0.
        sh[0] = rgb.map(|c| (f32::from(c) / 255.0 - 0.5) / 0.282_094_8);
        cloud.push(
            &Gaussian {
                mean: p.map(|v| v as f32),
                log_scale: [scale; 3],
                quat: [1.0, 0.0, 0.0, 0.0],
                opacity_logit,
                sh,
            },
            Layer::Scene,
        );
    }
    (cloud, extent.max(1e-3) as f32)
}

/// The scene layer on the GPU: its parameters (which the renderer reads as they are),
/// their gradients, and one Adam group per parameter buffer.
pub struct SceneLayer {
    pub count: u32,
    pub params: GaussianBuffers,
    pub grads: GaussianBuffers,
    pub groups: Vec<AdamGroup>,
    /// Densification statistics since the last densification (`ops::splat::densify`).
    pub screen_stats: Buffer,
    /// The largest distance of an initial point from their centroid (3DGS's scene
    /// extent: it scales the position rate and the densification sizes).
    pub extent: f32,
    config: SceneConfig,
    steps: u32,
}

/// The scene's parameters of `s` as a cloud (to rebuild the layer at its size).
pub(crate) fn cloud_of(s: &SceneState, sh_degree: u32) -> GaussianCloud {
    let n = s.params[3].len();
    GaussianCloud {
        sh_degree,
        means: s.params[0].clone(),
        log_scales: s.params[1].clone(),
        quats: s.params[2].clone(),
        opacity_logits: s.params[3].clone(),
        sh: s.params[4].clone(),
        groups: vec![Layer::Scene.group(); n],
    }
}

impl SceneLayer {
    pub fn new(
        ctx: &Context,
        cloud: &GaussianCloud,
        extent: f32,
        config: &SceneConfig,
        steps: u32,
    ) -> Result<Self> {
        let params = GaussianBuffers::upload(ctx, "scene", cloud)?;
        let grads = GaussianBuffers::new(ctx, "scene grads", cloud.len(), cloud.sh_degree)?;
        let lens = params.lens();
        let schedules = [
            LrSchedule::exponential(
                config.lr_position * extent,
                config.lr_position_final * extent,
                steps,
            ),
            LrSchedule::constant(config.lr_scale),
            LrSchedule::constant(config.lr_rotation),
            LrSchedule::constant(config.lr_opacity),
            LrSchedule::constant(config.lr_sh),
        ];
        let mut groups = Vec::new();
        for ((name, len), schedule) in SCENE_PARAMS.iter().zip(lens).zip(schedules) {
            groups.push(AdamGroup::new(
                ctx,
                &format!("scene {name}"),
                len,
                schedule,
            )?);
        }
        let screen_stats = ctx.upload(
            "scene screen stats",
            &vec![0.0f32; SCREEN_STATS_FLOATS * cloud.len().max(1)],
        )?;
        Ok(Self {
            count: params.count,
            params,
            grads,
            groups,
            screen_stats,
            extent,
            config: config.clone(),
            steps,
        })
    }

    /// Records one Adam step of every group (independent passes).
    /// (With `guard`: see `HumanLayer::record_adam`.)
    pub fn record_adam<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        guard: Option<&'a Buffer>,
    ) -> Result<()> {
        for ((g, p), d) in self
            .groups
            .iter()
            .zip(self.params.all())
            .zip(self.grads.all())
        {
            crate::avatar::layer::record_adam_step(rec, g, p, d, guard)?;
        }
        Ok(())
    }

    /// Counts a guarded step of [`record_adam`](Self::record_adam) that was applied.
    pub fn advance_adam(&self) {
        self.groups.iter().for_each(AdamGroup::advance);
    }

    /// Floats of each parameter buffer.
    pub fn lens(&self) -> [usize; 5] {
        self.params.lens()
    }

    /// Parameters and Adam state, for the checkpoint.
    pub fn state(&mut self, ctx: &Context) -> Result<SceneState> {
        let lens = self.lens();
        let mut params = Vec::new();
        for (b, len) in [
            &mut self.params.means,
            &mut self.params.log_scales,
            &mut self.params.quats,
            &mut self.params.opacity_logits,
            &mut self.params.sh,
        ]
        .into_iter()
        .zip(lens)
        {
            params.push(ctx.read_buffer(b, len)?);
        }
        let mut adam = Vec::new();
        for g in &mut self.groups {
            let step = g.steps();
            let (m, v) = g.read_moments(ctx)?;
            adam.push(AdamState { m, v, step });
        }
        let screen_stats = Some(ctx.read_buffer(
            &mut self.screen_stats,
            SCREEN_STATS_FLOATS * self.count as usize,
        )?);
        Ok(SceneState {
            params,
            adam,
            screen_stats,
        })
    }

    /// Loads `s` (of any Gaussian count: the layer is rebuilt at the state's size
    /// where it differs, as after densification).
    pub fn restore(&mut self, ctx: &Context, s: &SceneState) -> Result<()> {
        if s.params[3].len() != self.count as usize {
            *self = Self::new(
                ctx,
                &cloud_of(s, self.params.sh_degree),
                self.extent,
                &self.config,
                self.steps,
            )?;
        }
        match &s.screen_stats {
            Some(st) => ctx.write_buffer(&mut self.screen_stats, st)?,
            None => ctx.write_buffer(
                &mut self.screen_stats,
                &vec![0.0f32; SCREEN_STATS_FLOATS * self.count as usize],
            )?,
        }
        for (b, p) in [
            &mut self.params.means,
            &mut self.params.log_scales,
            &mut self.params.quats,
            &mut self.params.opacity_logits,
            &mut self.params.sh,
        ]
        .into_iter()
        .zip(&s.params)
        {
            ctx.write_buffer(b, p)?;
        }
        for (g, a) in self.groups.iter_mut().zip(&s.adam) {
            g.restore(ctx, &a.m, &a.v, a.step)?;
        }
        Ok(())
    }
}
