//! Densify and prune every layer on a schedule: 3DGS's adaptive density control, with
//! HUGS's human thresholds as the defaults (PAPER.md).
//!
//! The statistics are gathered on the GPU every step (`drape_engine::ops::splat::
//! densify`: per Gaussian, the summed norm of its projected centre's gradient in NDC
//! units, the frames it was visible in, its largest screen radius). Every `every`
//! steps from `from` to `until` the trainer reads them with the layer's current
//! opacity and scale, and [`plan`] decides, per Gaussian:
//! - prune: opacity below `min_opacity`, or a screen radius above `max_screen_radius`
//!   pixels, or a largest scale above the layer's world-size limit (the two size
//!   prunes from `size_prune_after` steps on, as 3DGS after its first opacity reset);
//! - otherwise, where the mean gradient norm reaches `grad_threshold`: split (two
//!   children drawn from the Gaussian, scales divided by 1.6, the parent removed) when
//!   its largest scale is above `percent_dense` of the layer's extent, else clone (a
//!   copy at the same place, which the position gradient then moves apart);
//! - the layer stays at most `max_gaussians` (the growth with the smallest gradients
//!   is dropped first) and never empties.
//!
//! [`apply_to_layer`] and [`apply_to_scene`] rebuild the layer at its new size: a
//! triplane-driven layer's new Gaussians get canonical positions (their triplane
//! features, and so their decoded opacity, colour and offsets, follow from where they
//! are) and their parent's skinning targets; the triplane, the decoders and their
//! optimiser state are kept as they are; the per-Gaussian Adam moments of survivors are
//! kept and those of new Gaussians start at zero; the cloth's ARAP graph keeps the
//! edges between survivors (new Gaussians join no edge). The statistics start again.
//!
//! Where this differs from the code it follows: the two
//! children of a split in a triplane-driven layer are not drawn from the Gaussian but
//! placed a quarter of its largest (decoded) scale either side of its mean along that
//! axis of its canonical rotation (`split_pair` says why), and their base scale (which
//! the decoder's delta multiplies) is divided by 1.6; there is no opacity reset (HUGS
//! decodes the human layers' opacity, which a reset of a stored value cannot reach);
//! the screen-radius prune applies from the first densification (3DGS waits for its
//! first opacity reset).

use drape_engine::ops::splat::densify::SCREEN_STATS_FLOATS;
use drape_engine::Context;
use drape_shared::splat::project::{normalize_quat, quat_to_mat};
use rand::{Rng, SeedableRng};

use crate::avatar::layer::HumanLayer;
use crate::avatar::scene::SceneLayer;
use crate::avatar::state::{AdamState, LayerState, SceneState};
use crate::body::model::NUM_JOINTS;
use crate::TrainerError;

/// When and how the layers are densified and pruned (HUGS's human schedule and
/// thresholds are the defaults).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DensifyConfig {
    /// Steps between densifications (HUGS: 600); 0 turns densification off.
    pub every: u32,
    /// First and last step (counted in steps done) at which it runs (HUGS: 3,000, 15,000).
    pub from: u32,
    pub until: u32,
    /// Mean NDC gradient norm at or above which a Gaussian grows (HUGS, 3DGS: 2e-4).
    pub grad_threshold: f32,
    /// Opacity below which a Gaussian is pruned (HUGS: 0.005).
    pub min_opacity: f32,
    /// Screen radius in pixels above which a Gaussian is pruned (HUGS: 20).
    pub max_screen_radius: f32,
    /// Steps done after which the two size prunes (screen radius, world size) apply:
    /// 3DGS applies them only after its first opacity reset (3,000 steps), so that a
    /// scene's large background splats are not pruned before smaller ones can cover
    /// their area. Missing from a config file: 3,000.
    #[serde(default = "first_opacity_reset")]
    pub size_prune_after: u32,
    /// Largest scale above which a Gaussian is pruned: metres for the human layers
    /// (HUGS: 0.1), a fraction of the scene's extent for the scene layer (3DGS: 0.1).
    pub max_world_size: f32,
    /// Fraction of the layer's extent above which a growing Gaussian is split rather
    /// than cloned (3DGS: 0.01).
    pub percent_dense: f32,
    /// Most Gaussians a layer grows to (HUGS: 524,288).
    pub max_gaussians: u32,
}

fn first_opacity_reset() -> u32 {
    3000
}

impl Default for DensifyConfig {
    fn default() -> Self {
        Self {
            every: 600,
            from: 3000,
            until: 15000,
            grad_threshold: 2e-4,
            min_opacity: 0.005,
            max_screen_radius: 20.0,
            size_prune_after: first_opacity_reset(),
            max_world_size: 0.1,
            percent_dense: 0.01,
            max_gaussians: 524_288,
        }
    }
}

impl DensifyConfig {
    /// No densification (also what a config file without `densify` gets).
    pub fn off() -> Self {
        Self {
            every: 0,
            ..Self::default()
        }
    }

    /// Whether the layers are densified once `done` steps are done.
    pub fn due(&self, done: u32) -> bool {
        self.every > 0 && done >= self.from && done <= self.until && done % self.every == 0
    }

    /// Errors name the field.
    pub fn validate(&self) -> crate::Result<()> {
        let rates = [
            ("grad_threshold", self.grad_threshold),
            ("min_opacity", self.min_opacity),
            ("max_screen_radius", self.max_screen_radius),
            ("max_world_size", self.max_world_size),
            ("percent_dense", self.percent_dense),
        ];
        for (name, v) in rates {
            if !(v.is_finite() && v >= 0.0) {
                return Err(TrainerError::config(
                    format!("densify.{name}"),
                    format!("must be a finite number >= 0, got {v}"),
                ));
            }
        }
        if self.max_gaussians == 0 {
            return Err(TrainerError::config(
                "densify.max_gaussians",
                "must be at least 1",
            ));
        }
        if self.every > 0 && self.from > self.until {
            return Err(TrainerError::config(
                "densify.from",
                format!("{} is after densify.until ({})", self.from, self.until),
            ));
        }
        Ok(())
    }
}

/// What one densification does to a layer: the Gaussians kept (in their order), then
/// one copy of each cloned one, then two children of each split one.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Plan {
    /// Survivors (cloned ones included; split ones are not).
    pub keep: Vec<u32>,
    pub clone: Vec<u32>,
    pub split: Vec<u32>,
    pub pruned: u32,
}

impl Plan {
    /// Gaussians after the plan.
    pub fn count(&self) -> usize {
        self.keep.len() + self.clone.len() + 2 * self.split.len()
    }

    /// Whether the plan changes nothing.
    pub fn is_identity(&self, count: usize) -> bool {
        self.clone.is_empty() && self.split.is_empty() && self.keep.len() == count
    }
}

/// A layer's densification summary (logged).
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize)]
pub struct Summary {
    pub before: usize,
    pub pruned: u32,
    pub cloned: usize,
    pub split: usize,
    pub after: usize,
}

impl Summary {
    fn of(plan: &Plan, before: usize) -> Self {
        Self {
            before,
            pruned: plan.pruned,
            cloned: plan.clone.len(),
            split: plan.split.len(),
            after: plan.count(),
        }
    }
}

/// Largest distance of a point from the points' centroid.
pub fn extent(means: &[f32]) -> f32 {
    let n = (means.len() / 3).max(1) as f64;
    let mut c = [0.0f64; 3];
    for p in means.chunks_exact(3) {
        for a in 0..3 {
            c[a] += f64::from(p[a]) / n;
        }
    }
    means
        .chunks_exact(3)
        .map(|p| {
            (0..3)
                .map(|a| (f64::from(p[a]) - c[a]).powi(2))
                .sum::<f64>()
                .sqrt()
        })
        .fold(0.0, f64::max) as f32
}

/// Decides what to do with each of a layer's Gaussians from its statistics
/// (`SCREEN_STATS_FLOATS` per Gaussian), opacity logits and log-scales (the decoded
/// ones for a triplane-driven layer, without the frame's global scale), the layer's
/// extent (for `percent_dense`) and its world-size limit (None: no size prunes yet).
pub fn plan(
    stats: &[f32],
    opacity_logits: &[f32],
    log_scales: &[f32],
    extent: f32,
    world_limit: Option<f32>,
    c: &DensifyConfig,
) -> Plan {
    let n = opacity_logits.len();
    assert_eq!(
        stats.len(),
        SCREEN_STATS_FLOATS * n,
        "statistics of another layer"
    );
    assert_eq!(log_scales.len(), 3 * n, "scales of another layer");
    let mut p = Plan::default();
    // (mean gradient, index, split?) of every growing Gaussian.
    let mut growing: Vec<(f32, u32, bool)> = Vec::new();
    let mut keep = vec![false; n];
    for i in 0..n {
        let opacity = 1.0 / (1.0 + (-opacity_logits[i]).exp());
        let max_scale = log_scales[3 * i..3 * i + 3]
            .iter()
            .copied()
            .fold(f32::NEG_INFINITY, f32::max)
            .exp();
        let s = &stats[SCREEN_STATS_FLOATS * i..SCREEN_STATS_FLOATS * (i + 1)];
        // NaN opacity or scale fails the keep test: such a Gaussian is pruned.
        let small =
            world_limit.is_none_or(|limit| s[2] <= c.max_screen_radius && max_scale <= limit);
        let fine = opacity >= c.min_opacity && small;
        if !fine {
            p.pruned += 1;
            continue;
        }
        keep[i] = true;
        let mean_grad = if s[1] > 0.0 { s[0] / s[1] } else { 0.0 };
        if mean_grad >= c.grad_threshold {
            growing.push((mean_grad, i as u32, max_scale > c.percent_dense * extent));
        }
    }
    // Within the cap: the growth of the smallest gradients goes first.
    let survivors = keep.iter().filter(|&&k| k).count();
    let mut after = survivors + growing.len();
    growing.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
    while after > c.max_gaussians as usize && !growing.is_empty() {
        growing.pop();
        after -= 1;
    }
    for &(_, i, split) in &growing {
        if split {
            keep[i as usize] = false;
            p.split.push(i);
        } else {
            p.clone.push(i);
        }
    }
    p.clone.sort_unstable();
    p.split.sort_unstable();
    p.keep = (0..n as u32).filter(|&i| keep[i as usize]).collect();
    if p.count() == 0 && n > 0 {
        // Never empty a layer: keep its most opaque Gaussian.
        // (A NaN opacity is not a candidate: total_cmp would rank it above all.)
        let best = (0..n)
            .filter(|&i| opacity_logits[i].is_finite())
            .max_by(|&a, &b| opacity_logits[a].total_cmp(&opacity_logits[b]))
            .unwrap_or(0);
        p.keep.push(best as u32);
        p.pruned -= 1;
    }
    p
}

/// A standard normal sample (Box–Muller).
fn normal(rng: &mut impl Rng) -> f32 {
    let u1: f64 = rng.random::<f64>().max(1e-300);
    let u2: f64 = rng.random();
    ((-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()) as f32
}

/// The two children of a split in a triplane-driven layer: the parent's mean moved by
/// ± a quarter of its largest scale along that axis (rotation `quat`, `log_scale`).
/// Not drawn from the Gaussian as 3DGS does: a triplane starts as noise (HUGS: N(0, 1))
/// and only the texels around the Gaussians are ever trained, so a child drawn a full
/// standard deviation away reads untrained features and decodes an arbitrary offset,
/// colour and opacity (the quick demo's cloth Chamfer to its targets went from 9 to
/// 37 mm at the first densification). Kept within the parent's footprint, the children
/// read its features, and the position gradient moves them apart.
fn split_pair(mean: &[f32], quat: &[f32], log_scale: &[f32]) -> [[f32; 3]; 2] {
    let (q, _) = normalize_quat([quat[0], quat[1], quat[2], quat[3]]);
    let r = quat_to_mat(q);
    let axis = (0..3)
        .max_by(|&a, &b| log_scale[a].total_cmp(&log_scale[b]))
        .unwrap_or(0);
    let d = 0.25 * log_scale[axis].exp();
    [1.0f32, -1.0].map(|sign| std::array::from_fn(|a| mean[a] + sign * d * r[a][axis]))
}

/// A point drawn from the Gaussian of mean `mean`, rotation `quat` and `log_scale`.
fn sample(rng: &mut impl Rng, mean: &[f32], quat: &[f32], log_scale: &[f32]) -> [f32; 3] {
    let (q, _) = normalize_quat([quat[0], quat[1], quat[2], quat[3]]);
    let r = quat_to_mat(q);
    let e: [f32; 3] = std::array::from_fn(|a| normal(rng) * log_scale[a].exp());
    std::array::from_fn(|a| mean[a] + r[a][0] * e[0] + r[a][1] * e[1] + r[a][2] * e[2])
}

/// ln 1.6: a split child's scales are its parent's divided by 1.6 (3DGS).
const SPLIT_LOG_SHRINK: f32 = 0.470_003_6;

/// Rows `width` floats wide of `src`, in the order of `rows` (a row index, or None
/// for a zero row), as Adam moments of the new layer: survivors keep theirs.
fn gather_rows(src: &[f32], width: usize, rows: &[Option<u32>]) -> Vec<f32> {
    let mut out = Vec::with_capacity(width * rows.len());
    for r in rows {
        match r {
            Some(i) => out.extend_from_slice(&src[width * *i as usize..width * (*i as usize + 1)]),
            None => out.extend(std::iter::repeat_n(0.0, width)),
        }
    }
    out
}

/// Densifies and prunes a triplane-driven layer: reads its statistics and its last
/// forward pass's decoded opacity and scales (`log_scale_offset`: the frame's global
/// scale, taken off), plans, and rebuilds the layer at its new size.
pub fn apply_to_layer(
    ctx: &Context,
    layer: &mut HumanLayer,
    c: &DensifyConfig,
    done: u32,
    log_scale_offset: f32,
) -> crate::Result<Summary> {
    let n = layer.count as usize;
    let stats = ctx.read_buffer::<f32>(&mut layer.screen_stats, SCREEN_STATS_FLOATS * n)?;
    let opacity = ctx.read_buffer::<f32>(&mut layer.deformer.posed.opacity_logits, n)?;
    let decoded: Vec<f32> = ctx
        .read_buffer::<f32>(&mut layer.deformer.posed.log_scales, 3 * n)?
        .iter()
        .map(|v| v - log_scale_offset)
        .collect();
    let state = layer.state(ctx)?;
    let limit = (done > c.size_prune_after).then_some(c.max_world_size);
    let p = plan(&stats, &opacity, &decoded, extent(&state.means), limit, c);
    let summary = Summary::of(&p, n);
    if p.is_identity(n) {
        // Nothing changes but the statistics, which start again.
        ctx.write_buffer(
            &mut layer.screen_stats,
            &vec![0.0f32; SCREEN_STATS_FLOATS * n],
        )?;
        return Ok(summary);
    }
    let next = resized_state(&state, &p, &decoded);
    layer.restore(ctx, &next)?;
    Ok(summary)
}

/// The layer state after `p`: canonical Gaussians, skinning targets, position moments,
/// the edge graph; zero statistics. `decoded` (log-scales) sizes the split samples.
fn resized_state(s: &LayerState, p: &Plan, decoded: &[f32]) -> LayerState {
    let targets = s
        .weight_targets
        .as_deref()
        .expect("a layer's state read from the GPU has its targets");
    let (mut means, mut quats, mut log_scales, mut weights) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let mut rows: Vec<Option<u32>> = Vec::new();
    let mut push = |i: usize, mean: &[f32], log_shrink: f32, moments: bool| {
        means.extend_from_slice(mean);
        quats.extend_from_slice(&s.quats[4 * i..4 * i + 4]);
        log_scales.extend(
            s.log_scales[3 * i..3 * i + 3]
                .iter()
                .map(|v| v - log_shrink),
        );
        weights.extend_from_slice(&targets[NUM_JOINTS * i..NUM_JOINTS * (i + 1)]);
        rows.push(moments.then_some(i as u32));
    };
    for &i in &p.keep {
        let i = i as usize;
        push(i, &s.means[3 * i..3 * i + 3], 0.0, true);
    }
    for &i in &p.clone {
        let i = i as usize;
        push(i, &s.means[3 * i..3 * i + 3], 0.0, false);
    }
    for &i in &p.split {
        let i = i as usize;
        for m in split_pair(
            &s.means[3 * i..3 * i + 3],
            &s.quats[4 * i..4 * i + 4],
            &decoded[3 * i..3 * i + 3],
        ) {
            push(i, &m, SPLIT_LOG_SHRINK, false);
        }
    }
    // Edges between survivors, renumbered.
    let mut new_index = vec![u32::MAX; s.count()];
    for (k, &i) in p.keep.iter().enumerate() {
        new_index[i as usize] = k as u32;
    }
    let edges = s.edges.as_ref().map(|e| {
        e.iter()
            .filter_map(|&[a, b]| {
                (new_index[a as usize] != u32::MAX && new_index[b as usize] != u32::MAX)
                    .then_some([new_index[a as usize], new_index[b as usize]])
            })
            .collect()
    });
    let mut adam = s.adam.clone();
    let pos = &s.adam[0];
    adam[0] = AdamState {
        m: gather_rows(&pos.m, 3, &rows),
        v: gather_rows(&pos.v, 3, &rows),
        step: pos.step,
    };
    let n = rows.len();
    LayerState {
        means,
        quats,
        log_scales,
        adam,
        weight_targets: Some(weights),
        screen_stats: Some(vec![0.0; SCREEN_STATS_FLOATS * n]),
        edges,
        ..s.clone()
    }
}

/// Densifies and prunes the scene layer (plain 3DGS: its parameters are its values;
/// the world-size limit is `max_world_size` of its extent).
pub fn apply_to_scene(
    ctx: &Context,
    scene: &mut SceneLayer,
    c: &DensifyConfig,
    done: u32,
    seed: u64,
) -> crate::Result<Summary> {
    let n = scene.count as usize;
    let stats = ctx.read_buffer::<f32>(&mut scene.screen_stats, SCREEN_STATS_FLOATS * n)?;
    let state = scene.state(ctx)?;
    let limit = (done > c.size_prune_after).then_some(c.max_world_size * scene.extent);
    let p = plan(
        &stats,
        &state.params[3],
        &state.params[1],
        scene.extent,
        limit,
        c,
    );
    let summary = Summary::of(&p, n);
    if p.is_identity(n) {
        ctx.write_buffer(
            &mut scene.screen_stats,
            &vec![0.0f32; SCREEN_STATS_FLOATS * n],
        )?;
        return Ok(summary);
    }
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let widths: Vec<usize> = state.params.iter().map(|a| a.len() / n).collect();
    let mut params: Vec<Vec<f32>> = vec![Vec::new(); state.params.len()];
    let mut rows: Vec<Option<u32>> = Vec::new();
    for (list, fresh) in [(&p.keep, false), (&p.clone, true)] {
        for &i in list {
            for (k, out) in params.iter_mut().enumerate() {
                out.extend_from_slice(
                    &state.params[k][widths[k] * i as usize..widths[k] * (i as usize + 1)],
                );
            }
            rows.push((!fresh).then_some(i));
        }
    }
    for &i in &p.split {
        let i = i as usize;
        for _ in 0..2 {
            let m = sample(
                &mut rng,
                &state.params[0][3 * i..3 * i + 3],
                &state.params[2][4 * i..4 * i + 4],
                &state.params[1][3 * i..3 * i + 3],
            );
            params[0].extend_from_slice(&m);
            params[1].extend(
                state.params[1][3 * i..3 * i + 3]
                    .iter()
                    .map(|v| v - SPLIT_LOG_SHRINK),
            );
            for k in 2..params.len() {
                params[k].extend_from_slice(&state.params[k][widths[k] * i..widths[k] * (i + 1)]);
            }
            rows.push(None);
        }
    }
    let adam = state
        .adam
        .iter()
        .zip(&widths)
        .map(|(a, &w)| AdamState {
            m: gather_rows(&a.m, w, &rows),
            v: gather_rows(&a.v, w, &rows),
            step: a.step,
        })
        .collect();
    let next = SceneState {
        params,
        adam,
        screen_stats: None,
    };
    scene.restore(ctx, &next)?;
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Stats of a Gaussian with mean gradient `g` over 2 frames and radius `r`.
    fn stats(rows: &[(f32, f32)]) -> Vec<f32> {
        rows.iter().flat_map(|&(g, r)| [2.0 * g, 2.0, r]).collect()
    }

    fn logit(p: f32) -> f32 {
        (p / (1.0 - p)).ln()
    }

    #[test]
    fn plan_prunes_clones_and_splits_by_the_thresholds() {
        let c = DensifyConfig::default();
        // extent 1: split above 0.01, prune above 0.1 (world) and 20 px.
        let small = (0.005f32).ln();
        let large = (0.05f32).ln();
        let rows = [
            (1e-3, 5.0),  // 0: small, high gradient: clone
            (1e-3, 5.0),  // 1: large, high gradient: split
            (1e-5, 5.0),  // 2: low gradient: kept as it is
            (1e-3, 5.0),  // 3: transparent: pruned (and not grown)
            (1e-5, 25.0), // 4: too big on screen: pruned
            (1e-5, 5.0),  // 5: too big in the world: pruned
        ];
        let opacity = [
            logit(0.5),
            logit(0.5),
            logit(0.5),
            logit(0.001),
            logit(0.5),
            logit(0.5),
        ];
        let scales: Vec<f32> = [small, large, small, small, small, (0.2f32).ln()]
            .iter()
            .flat_map(|&s| [s, s - 1.0, s - 2.0])
            .collect();
        let p = plan(
            &stats(&rows),
            &opacity,
            &scales,
            1.0,
            Some(c.max_world_size),
            &c,
        );
        assert_eq!(p.keep, vec![0, 2]);
        assert_eq!(p.clone, vec![0]);
        assert_eq!(p.split, vec![1]);
        assert_eq!(p.pruned, 3);
        assert_eq!(p.count(), 5);
        // Before the size prunes apply, only the transparent one goes.
        let early = plan(&stats(&rows), &opacity, &scales, 1.0, None, &c);
        assert_eq!(early.keep, vec![0, 2, 4, 5]);
        assert_eq!(early.pruned, 1);
    }

    #[test]
    fn plan_keeps_the_cap_dropping_the_smallest_gradients_first() {
        let c = DensifyConfig {
            max_gaussians: 5,
            ..DensifyConfig::default()
        };
        let rows: Vec<(f32, f32)> = [1e-3, 5e-3, 2e-3, 4e-3].iter().map(|&g| (g, 1.0)).collect();
        let opacity = [0.0; 4];
        let scales = vec![(0.001f32).ln(); 12];
        let p = plan(&stats(&rows), &opacity, &scales, 1.0, Some(0.1), &c);
        // 4 survivors + 1 growth: the largest gradient (Gaussian 1) grows.
        assert_eq!(p.clone, vec![1]);
        assert_eq!(p.count(), 5);
    }

    #[test]
    fn plan_never_empties_a_layer_and_prunes_non_finite_values() {
        let c = DensifyConfig::default();
        let opacity = [logit(0.001), f32::NAN, logit(0.002)];
        let scales = vec![(0.001f32).ln(); 9];
        let p = plan(
            &stats(&[(0.0, 1.0); 3]),
            &opacity,
            &scales,
            1.0,
            Some(0.1),
            &c,
        );
        assert_eq!(p.keep, vec![2], "the most opaque stays");
        assert_eq!(p.pruned, 2);
    }

    #[test]
    fn the_schedule_runs_from_to_until_every_steps() {
        let c = DensifyConfig {
            every: 100,
            from: 200,
            until: 400,
            ..DensifyConfig::default()
        };
        let due: Vec<u32> = (0..600).filter(|&s| c.due(s)).collect();
        assert_eq!(due, vec![200, 300, 400]);
        assert!((0..10_000).all(|s| !DensifyConfig::off().due(s)));
        let err = DensifyConfig {
            grad_threshold: -1.0,
            ..c.clone()
        }
        .validate()
        .unwrap_err();
        assert!(
            matches!(&err, TrainerError::Config { key, .. } if key == "densify.grad_threshold"),
            "{err}"
        );
    }
}
