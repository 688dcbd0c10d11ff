//! Gaussians on the host, the pinhole camera, and the render settings; turns them into
//! the kernels' `FrameParams`.

use drape_shared::real::Real;
use drape_shared::splat::layout::{
    sh_coeffs, FrameParams, DEFAULT_ALPHA_MAX, DEFAULT_ALPHA_MIN, DEFAULT_DILATION,
    DEFAULT_FOV_CLAMP, DEFAULT_MAX_SIGMAS, DEFAULT_TILE_SIZE, DEFAULT_TRANSMITTANCE_MIN,
    MAX_SH_COEFFS, MAX_SH_DEGREE, TILE_SIZES,
};
use drape_shared::splat::project::Gaussian;

use crate::error::EngineError;

/// The largest image side a camera may have (see [`PinholeCamera::MAX_SIDE`]).
pub const MAX_IMAGE_SIDE: u32 = 16384;

/// Gaussians as flat arrays (the GPU layout): `means` 3n, `log_scales` 3n, `quats` 4n
/// (w, x, y, z), `opacity_logits` n, `sh` 3Kn as `[gaussian][k][channel]` with
/// K = (degree + 1)², `groups` n.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct GaussianCloud {
    /// Spherical-harmonics degree (0-3).
    pub sh_degree: u32,
    /// 3 per Gaussian.
    pub means: Vec<f32>,
    /// 3 per Gaussian: the natural logarithms of the scales.
    pub log_scales: Vec<f32>,
    /// 4 per Gaussian (w, x, y, z), not necessarily normalised.
    pub quats: Vec<f32>,
    /// 1 per Gaussian: opacity before the sigmoid.
    pub opacity_logits: Vec<f32>,
    /// 3 (degree + 1)² per Gaussian, `[gaussian][k][channel]`.
    pub sh: Vec<f32>,
    /// Which of the caller's N groups of Gaussians each one belongs to (an index the
    /// engine only carries; compositing and the fused renderer take per-Gaussian masks
    /// that callers build from it).
    pub groups: Vec<u32>,
}

impl GaussianCloud {
    /// An empty cloud of SH degree `sh_degree`.
    pub fn new(sh_degree: u32) -> Self {
        assert!(
            sh_degree <= MAX_SH_DEGREE,
            "SH degree {sh_degree} is above {MAX_SH_DEGREE}"
        );
        Self {
            sh_degree,
            ..Default::default()
        }
    }

    /// Gaussians in the cloud.
    pub fn len(&self) -> usize {
        self.opacity_logits.len()
    }

    /// Whether the cloud has no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Coefficients per channel.
    pub fn sh_coeffs(&self) -> usize {
        sh_coeffs(self.sh_degree)
    }

    /// Appends one Gaussian to group `group` (its SH coefficients past the cloud's
    /// degree are ignored).
    pub fn push(&mut self, g: &Gaussian<f32>, group: impl Into<u32>) {
        self.means.extend_from_slice(&g.mean);
        self.log_scales.extend_from_slice(&g.log_scale);
        self.quats.extend_from_slice(&g.quat);
        self.opacity_logits.push(g.opacity_logit);
        for k in 0..self.sh_coeffs() {
            self.sh.extend_from_slice(&g.sh[k]);
        }
        self.groups.push(group.into());
    }

    /// Gaussian `i` in the float type `F`.
    pub fn gaussian<F: Real>(&self, i: usize) -> Gaussian<F> {
        let c = F::of;
        let k_count = self.sh_coeffs();
        let mut sh = [[F::zero(); 3]; MAX_SH_COEFFS];
        for (k, coeffs) in sh.iter_mut().enumerate().take(k_count) {
            let b = (i * k_count + k) * 3;
            *coeffs = [c(self.sh[b]), c(self.sh[b + 1]), c(self.sh[b + 2])];
        }
        Gaussian {
            mean: [
                c(self.means[3 * i]),
                c(self.means[3 * i + 1]),
                c(self.means[3 * i + 2]),
            ],
            log_scale: [
                c(self.log_scales[3 * i]),
                c(self.log_scales[3 * i + 1]),
                c(self.log_scales[3 * i + 2]),
            ],
            quat: [
                c(self.quats[4 * i]),
                c(self.quats[4 * i + 1]),
                c(self.quats[4 * i + 2]),
                c(self.quats[4 * i + 3]),
            ],
            opacity_logit: c(self.opacity_logits[i]),
            sh,
        }
    }

    /// All Gaussians in the float type `F`.
    pub fn gaussians<F: Real>(&self) -> Vec<Gaussian<F>> {
        (0..self.len()).map(|i| self.gaussian(i)).collect()
    }

    /// Appends every Gaussian of `other` (same SH degree).
    pub fn extend(&mut self, other: &GaussianCloud) {
        assert_eq!(self.sh_degree, other.sh_degree, "SH degrees differ");
        self.means.extend_from_slice(&other.means);
        self.log_scales.extend_from_slice(&other.log_scales);
        self.quats.extend_from_slice(&other.quats);
        self.opacity_logits.extend_from_slice(&other.opacity_logits);
        self.sh.extend_from_slice(&other.sh);
        self.groups.extend_from_slice(&other.groups);
    }

    /// `n` random Gaussians of group 0 in the box
    /// `[-extent, extent]^2 x [z_min, z_max]`, with scales around `scale`, reproducible
    /// from `seed` (for tests and benchmarks).
    pub fn random(
        n: usize,
        sh_degree: u32,
        extent: f32,
        z_range: (f32, f32),
        scale: f32,
        seed: u64,
    ) -> Self {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let mut cloud = Self::new(sh_degree);
        for _ in 0..n {
            let mut sh = [[0.0f32; 3]; MAX_SH_COEFFS];
            for (k, c) in sh.iter_mut().enumerate().take(sh_coeffs(sh_degree)) {
                let amp = if k == 0 { 1.2 } else { 0.3 };
                *c = [
                    rng.random_range(-amp..amp),
                    rng.random_range(-amp..amp),
                    rng.random_range(-amp..amp),
                ];
            }
            let g = Gaussian {
                mean: [
                    rng.random_range(-extent..extent),
                    rng.random_range(-extent..extent),
                    rng.random_range(z_range.0..z_range.1),
                ],
                log_scale: [0, 1, 2].map(|_| (scale * rng.random_range(0.3f32..1.5)).ln()),
                quat: [
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                ],
                opacity_logit: rng.random_range(-2.0..3.0),
                sh,
            };
            cloud.push(&g, 0u32);
        }
        cloud
    }
}

/// A pinhole camera: intrinsics in pixels, world-to-camera `p_c = R p_w + t` (x right,
/// y down, z forward), image size, clipping range and background colour.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PinholeCamera {
    /// Focal length along x, in pixels.
    pub fx: f32,
    /// Focal length along y, in pixels.
    pub fy: f32,
    /// Principal point x, in pixels from the left edge.
    pub cx: f32,
    /// Principal point y, in pixels from the top edge.
    pub cy: f32,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// World-to-camera rotation, rows.
    pub rotation: [[f32; 3]; 3],
    /// World-to-camera translation.
    pub translation: [f32; 3],
    /// Near clipping depth: splats closer than this are culled.
    pub near: f32,
    /// Far clipping depth: splats farther than this are culled.
    pub far: f32,
    /// Background colour behind the splats, each channel in [0, 1].
    pub background: [f32; 3],
}

fn sub(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn cross(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn normalize(a: [f32; 3]) -> Option<[f32; 3]> {
    let n = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
    (n > 1e-12 && n.is_finite()).then(|| [a[0] / n, a[1] / n, a[2] / n])
}

impl PinholeCamera {
    /// A camera at `eye` looking at `target` with `up` the world's up direction and a
    /// vertical field of view in degrees. None when eye = target, up is parallel to
    /// the view direction, or the field of view is not in (0, 180).
    pub fn look_at(
        eye: [f32; 3],
        target: [f32; 3],
        up: [f32; 3],
        fov_y_degrees: f32,
        width: u32,
        height: u32,
    ) -> Option<Self> {
        if !(fov_y_degrees > 0.0 && fov_y_degrees < 180.0) || width == 0 || height == 0 {
            return None;
        }
        let forward = normalize(sub(target, eye))?;
        let right = normalize(cross(forward, up))?;
        let down = cross(forward, right);
        let rotation = [right, down, forward];
        let translation = [
            -(right[0] * eye[0] + right[1] * eye[1] + right[2] * eye[2]),
            -(down[0] * eye[0] + down[1] * eye[1] + down[2] * eye[2]),
            -(forward[0] * eye[0] + forward[1] * eye[1] + forward[2] * eye[2]),
        ];
        let fy = 0.5 * height as f32 / (0.5 * fov_y_degrees.to_radians()).tan();
        Some(Self {
            fx: fy,
            fy,
            cx: 0.5 * width as f32,
            cy: 0.5 * height as f32,
            width,
            height,
            rotation,
            translation,
            near: Self::DEFAULT_NEAR,
            far: Self::DEFAULT_FAR,
            background: [0.0; 3],
        })
    }

    /// The near clipping depth of [`look_at`](Self::look_at) cameras.
    pub const DEFAULT_NEAR: f32 = 0.01;

    /// The far clipping depth of [`look_at`](Self::look_at) cameras.
    pub const DEFAULT_FAR: f32 = 1e4;

    /// The largest image side a camera may have (the splatter's tile grid and buffers
    /// are sized from it; 16384 is the common Vulkan image limit).
    pub const MAX_SIDE: u32 = MAX_IMAGE_SIDE;

    /// Checks what a camera built from outside data could get wrong (non-finite values,
    /// non-positive focal lengths, an empty or oversized image, a background outside
    /// [0, 1], a bad clipping range, a rotation that is not orthonormal): an
    /// [`EngineError::InvalidSetting`] whose `what` is the field's name.
    pub fn validate(&self) -> Result<(), EngineError> {
        let invalid = |what: &'static str, problem: String| {
            Err(EngineError::InvalidSetting { what, problem })
        };
        let scalars = [
            ("fx", self.fx),
            ("fy", self.fy),
            ("cx", self.cx),
            ("cy", self.cy),
            ("near", self.near),
            ("far", self.far),
        ];
        let arrays: [(&'static str, &[f32]); 3] = [
            ("rotation", self.rotation.as_flattened()),
            ("translation", &self.translation),
            ("background", &self.background),
        ];
        for (what, v) in scalars.into_iter().chain(
            arrays
                .into_iter()
                .flat_map(|(w, a)| a.iter().map(move |&v| (w, v))),
        ) {
            if !v.is_finite() {
                return invalid(what, format!("{v} is not a finite number"));
            }
        }
        if !(self.fx > 0.0 && self.fy > 0.0) {
            let what = if self.fx > 0.0 { "fy" } else { "fx" };
            return invalid(
                what,
                format!(
                    "fx and fy must be positive (fx {}, fy {})",
                    self.fx, self.fy
                ),
            );
        }
        if self.width == 0 || self.height == 0 {
            let what = if self.width == 0 { "width" } else { "height" };
            return invalid(
                what,
                format!(
                    "width and height must be positive ({}x{})",
                    self.width, self.height
                ),
            );
        }
        if self.width > MAX_IMAGE_SIDE || self.height > MAX_IMAGE_SIDE {
            let what = if self.width > MAX_IMAGE_SIDE {
                "width"
            } else {
                "height"
            };
            return invalid(
                what,
                format!(
                    "{}x{} is larger than {MAX_IMAGE_SIDE} on a side",
                    self.width, self.height
                ),
            );
        }
        if self.background.iter().any(|c| !(0.0..=1.0).contains(c)) {
            return invalid(
                "background",
                format!("{:?}: each channel in [0, 1]", self.background),
            );
        }
        if !(self.near > 0.0 && self.far > self.near) {
            let what = if self.near > 0.0 { "far" } else { "near" };
            return invalid(
                what,
                format!("need 0 < near < far (near {}, far {})", self.near, self.far),
            );
        }
        let r = self.rotation;
        for i in 0..3 {
            for j in 0..3 {
                let d = r[i][0] * r[j][0] + r[i][1] * r[j][1] + r[i][2] * r[j][2];
                let expected = if i == j { 1.0 } else { 0.0 };
                if (d - expected).abs() > 1e-3 {
                    return invalid(
                        "rotation",
                        format!("not orthonormal (row {i} . row {j} = {d})"),
                    );
                }
            }
        }
        Ok(())
    }

    /// The image's grid of tiles of side `tile_size`.
    pub fn tiles(&self, tile_size: u32) -> (u32, u32) {
        (
            self.width.div_ceil(tile_size),
            self.height.div_ceil(tile_size),
        )
    }
}

/// Render settings; `Default` gives the named defaults of `drape_shared::splat::layout`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RenderSettings {
    /// Antialiased mode: opacity compensated for the dilation (Mip-Splatting).
    pub antialiased: bool,
    /// Added to the 2D covariance's diagonal (pixels²).
    pub dilation: f32,
    /// Alpha below which a splat is skipped at a pixel.
    pub alpha_min: f32,
    /// Alpha clamp per splat.
    pub alpha_max: f32,
    /// Transmittance below which a pixel stops blending.
    pub transmittance_min: f32,
    /// Standard deviations a splat's extent covers at most.
    pub max_sigmas: f32,
    /// The Jacobian's clamp, as a multiple of the field of view.
    pub fov_clamp: f32,
    /// Tile side in pixels: 8, 16 or 32 ([`TILE_SIZES`]). The image does not depend on
    /// it; the time does (smaller tiles: more intersections to sort, shorter lists to
    /// walk). 8 needs the subgroup rasterizers (lavapipe); the workgroup ones rasterize
    /// 16 × 16 blocks.
    pub tile_size: u32,
    /// Render from half-precision SH (binary16, rounded to nearest even): each frame
    /// packs the SH (`splat.pack_sh_half`) and the projection reads half the words. A
    /// render-only knob: a frame rendered so has no backward.
    pub half_sh: bool,
    /// Rasterize half-precision projected splats (`HalfSplat`: centre f32, the rest
    /// binary16): each frame packs them after binning (`splat.pack_splats_half`) and the
    /// forward rasterizers read 6 words a splat instead of 10. Render-only, as
    /// `half_sh`.
    pub half_splats: bool,
}

impl RenderSettings {
    /// Checks the settings a kernel cannot: the tile size
    /// ([`EngineError::InvalidSetting`] for `tile_size`).
    pub fn validate(&self) -> Result<(), EngineError> {
        if !TILE_SIZES.contains(&self.tile_size) {
            return Err(EngineError::InvalidSetting {
                what: "tile_size",
                problem: format!("tile size {} is not one of {TILE_SIZES:?}", self.tile_size),
            });
        }
        Ok(())
    }
}

impl Default for RenderSettings {
    fn default() -> Self {
        Self {
            antialiased: false,
            dilation: DEFAULT_DILATION,
            alpha_min: DEFAULT_ALPHA_MIN,
            alpha_max: DEFAULT_ALPHA_MAX,
            transmittance_min: DEFAULT_TRANSMITTANCE_MIN,
            max_sigmas: DEFAULT_MAX_SIGMAS,
            fov_clamp: DEFAULT_FOV_CLAMP,
            tile_size: DEFAULT_TILE_SIZE,
            half_sh: false,
            half_splats: false,
        }
    }
}

/// The kernels' view of a camera, settings and scene size.
pub fn frame_params(
    cam: &PinholeCamera,
    settings: &RenderSettings,
    sh_degree: u32,
    count: usize,
) -> FrameParams {
    let (tiles_x, tiles_y) = cam.tiles(settings.tile_size);
    let r = cam.rotation;
    FrameParams {
        rot: [
            r[0][0], r[0][1], r[0][2], r[1][0], r[1][1], r[1][2], r[2][0], r[2][1], r[2][2],
        ],
        trans: cam.translation,
        fx: cam.fx,
        fy: cam.fy,
        cx: cam.cx,
        cy: cam.cy,
        near: cam.near,
        far: cam.far,
        width: cam.width,
        height: cam.height,
        tiles_x,
        tiles_y,
        tile_size: settings.tile_size,
        background: cam.background,
        sh_degree,
        count: u32::try_from(count).expect("at most 2^32 - 1 Gaussians"),
        antialiased: u32::from(settings.antialiased),
        dilation: settings.dilation,
        alpha_min: settings.alpha_min,
        alpha_max: settings.alpha_max,
        transmittance_min: settings.transmittance_min,
        max_sigmas: settings.max_sigmas,
        fov_clamp: settings.fov_clamp,
    }
}
