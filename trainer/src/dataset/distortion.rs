//! Lens distortion, removed once at load. The splatter and the rasterizer are pure
//! pinholes, so a dataset whose camera has a distorting lens (ZJU-MoCap's `D`, COLMAP's
//! SIMPLE_RADIAL, RADIAL, OPENCV) has its images and masks resampled at load into the
//! pinhole camera with the same K, as the public ZJU loaders do with
//! `cv2.undistort(img, K, D)`: nothing per training step, and nothing on the GPU.
//!
//! The model is OpenCV's five-coefficient one ([`Distortion`]): on normalized camera
//! coordinates `(x, y) = (X/Z, Y/Z)`, with `r² = x² + y²`,
//! `x_d = x (1 + k1 r² + k2 r⁴ + k3 r⁶) + 2 p1 x y + p2 (r² + 2 x²)` and
//! `y_d = y (1 + k1 r² + k2 r⁴ + k3 r⁶) + p1 (r² + 2 y²) + 2 p2 x y`, then
//! `u = fx x_d + cx`, `v = fy y_d + cy`. COLMAP's SIMPLE_RADIAL (k1), RADIAL (k1, k2)
//! and OPENCV (k1 k2 p1 p2) are this model with the other coefficients zero.
//!
//! Pixel convention: drape's and COLMAP's, pixel centres at +0.5 (the same as
//! [`Camera::project`]). OpenCV puts centres at integers, so [`Undistorter`] with
//! principal point (cx, cy) makes the same map as `cv2.initUndistortRectifyMap` with
//! (cx - 0.5, cy - 0.5); a K calibrated with OpenCV (ZJU-MoCap's) describes drape's
//! camera with (cx + 0.5, cy + 0.5).
//!
//! Images are RGB interleaved in [0, 1] (row-major, as the loader holds them), masks one
//! bool per pixel. Sampling is bilinear; a neighbour outside the source image counts as
//! zero (black, or outside the mask), as OpenCV's `BORDER_CONSTANT` with value 0 does.
//! NaN policy: a source position that is NaN or infinite (a point [`undistort_normalized`]
//! could not invert) samples as outside: the guards are written so that NaN fails them.
//!
//! [`undistort_normalized`]: Distortion::undistort_normalized

use glam::DVec3;

use crate::camera::Camera;

/// OpenCV's distortion coefficients (k1 k2 p1 p2 k3): radial k1, k2, k3 on r², r⁴, r⁶
/// and tangential p1, p2.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Distortion {
    pub k1: f64,
    pub k2: f64,
    pub p1: f64,
    pub p2: f64,
    pub k3: f64,
}

impl Distortion {
    /// No distortion: a pinhole.
    pub const NONE: Self = Self {
        k1: 0.0,
        k2: 0.0,
        p1: 0.0,
        p2: 0.0,
        k3: 0.0,
    };

    /// From OpenCV's `distCoeffs` order (k1, k2, p1, p2, k3), as ZJU-MoCap's `D` holds it.
    pub fn from_opencv(d: &[f64; 5]) -> Self {
        Self {
            k1: d[0],
            k2: d[1],
            p1: d[2],
            p2: d[3],
            k3: d[4],
        }
    }

    /// OpenCV's `distCoeffs` order (k1, k2, p1, p2, k3).
    pub fn to_opencv(&self) -> [f64; 5] {
        [self.k1, self.k2, self.p1, self.p2, self.k3]
    }

    /// Whether every coefficient is exactly zero, so images need no resampling (an
    /// identity resampling would still blur nothing, but costs a pass per image).
    pub fn is_identity(&self) -> bool {
        self.to_opencv().iter().all(|&c| c == 0.0)
    }

    /// The distorted normalized coordinates of the undistorted `(x, y)`, term for term as
    /// `cv2.projectPoints` computes them.
    pub fn distort(&self, x: f64, y: f64) -> [f64; 2] {
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        let xy2 = 2.0 * x * y;
        [
            x * radial + self.p1 * xy2 + self.p2 * (r2 + 2.0 * x * x),
            y * radial + self.p1 * (r2 + 2.0 * y * y) + self.p2 * xy2,
        ]
    }

    /// The undistorted normalized coordinates whose [`distort`](Self::distort) is
    /// `(xd, yd)`: what `cv2.undistortPoints` returns without R and P. OpenCV iterates a
    /// fixed point (5 steps by default, which leaves errors of 1e-4 at the corners of a
    /// strongly distorted image); this runs Newton's method from `(xd, yd)` with the
    /// exact Jacobian until the residual is below 1e-14, which fixtures need. NaN when it
    /// does not converge in 50 steps (beyond the radius where the radial polynomial
    /// folds back, the inverse does not exist).
    pub fn undistort_normalized(&self, xd: f64, yd: f64) -> [f64; 2] {
        let (mut x, mut y) = (xd, yd);
        for _ in 0..50 {
            let [fx, fy] = self.distort(x, y);
            let (ex, ey) = (fx - xd, fy - yd);
            if ex.abs().max(ey.abs()) < 1e-14 {
                return [x, y];
            }
            let r2 = x * x + y * y;
            let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
            // d(radial)/d(r²), times 2x or 2y below.
            let dradial = self.k1 + r2 * (2.0 * self.k2 + 3.0 * r2 * self.k3);
            let j00 = radial + 2.0 * x * x * dradial + 2.0 * self.p1 * y + 6.0 * self.p2 * x;
            let j01 = 2.0 * x * y * dradial + 2.0 * self.p1 * x + 2.0 * self.p2 * y;
            let j11 = radial + 2.0 * y * y * dradial + 6.0 * self.p1 * y + 2.0 * self.p2 * x;
            // The Jacobian is symmetric: d(x_d)/dy = d(y_d)/dx.
            let det = j00 * j11 - j01 * j01;
            if det.is_nan() || det.abs() <= 1e-300 {
                break;
            }
            x -= (j11 * ex - j01 * ey) / det;
            y -= (j00 * ey - j01 * ex) / det;
        }
        [f64::NAN; 2]
    }
}

/// Pixel coordinates of a world point seen through `camera` with lens `d`, as
/// `cv2.projectPoints` computes them (pinhole division, [`Distortion::distort`], then
/// K). Like OpenCV it does not test the depth: a point behind the camera gives a
/// meaningless position; [`Camera::to_camera`] says which side a point is on.
pub fn project(camera: &Camera, d: &Distortion, point_world: DVec3) -> [f64; 2] {
    let c = camera.to_camera(point_world);
    let [xd, yd] = d.distort(c[0] / c[2], c[1] / c[2]);
    [camera.fx * xd + camera.cx, camera.fy * yd + camera.cy]
}

/// Where each output pixel samples its source image, in index coordinates (centre of
/// pixel (x, y) at (x, y)): f32 like OpenCV's CV_32FC1 maps, row-major.
#[derive(Clone, Debug)]
struct SourceMap {
    width: usize,
    height: usize,
    map: Vec<[f32; 2]>,
}

impl SourceMap {
    /// The map of `camera`'s image size where output pixel centres, in normalized
    /// coordinates, go through `source` to normalized coordinates in the source image.
    fn build(camera: &Camera, source: impl Fn(f64, f64) -> [f64; 2]) -> Self {
        let (width, height) = (camera.width as usize, camera.height as usize);
        let mut map = Vec::with_capacity(width * height);
        for y in 0..height {
            let ny = (y as f64 + 0.5 - camera.cy) / camera.fy;
            for x in 0..width {
                let nx = (x as f64 + 0.5 - camera.cx) / camera.fx;
                let [sx, sy] = source(nx, ny);
                map.push([
                    (camera.fx * sx + camera.cx - 0.5) as f32,
                    (camera.fy * sy + camera.cy - 0.5) as f32,
                ]);
            }
        }
        Self { width, height, map }
    }

    /// Bilinear sample of a `C`-channel image at `[sx, sy]`; neighbours outside count as 0.
    fn sample<const C: usize>(&self, image: &[f32], [sx, sy]: [f32; 2]) -> [f32; C] {
        let (w, h) = (self.width as i64, self.height as i64);
        let mut out = [0.0; C];
        // Written so that NaN fails it; also keeps the casts below in range.
        if !(sx > -1.0 && sy > -1.0 && sx < w as f32 && sy < h as f32) {
            return out;
        }
        let (x0, y0) = (sx.floor(), sy.floor());
        let (ax, ay) = (sx - x0, sy - y0);
        let (x0, y0) = (x0 as i64, y0 as i64);
        for (yi, wy) in [(y0, 1.0 - ay), (y0 + 1, ay)] {
            for (xi, wx) in [(x0, 1.0 - ax), (x0 + 1, ax)] {
                if (0..w).contains(&xi) && (0..h).contains(&yi) {
                    let p = (yi * w + xi) as usize * C;
                    for (o, v) in out.iter_mut().zip(&image[p..p + C]) {
                        *o += wx * wy * v;
                    }
                }
            }
        }
        out
    }

    fn rgb(&self, rgb: &[f32]) -> Vec<f32> {
        assert_eq!(
            rgb.len(),
            self.width * self.height * 3,
            "an RGB image of {}x{} has {} values",
            self.width,
            self.height,
            self.width * self.height * 3
        );
        self.map
            .iter()
            .flat_map(|&s| self.sample::<3>(rgb, s))
            .collect()
    }

    /// Bilinear of the 0/1 mask, then at least one half. Why: it puts the edge where
    /// the interpolated coverage crosses one half, so the edge moves with the image's
    /// content to sub-pixel accuracy (nearest neighbour moves it by up to half a pixel,
    /// differently at each pixel, and makes staircases along a distorted edge); and it is
    /// what the public ZJU loaders get from `cv2.undistort` of a 0/1 `uint8` mask,
    /// whose rounding to the nearest integer is this threshold.
    fn mask(&self, mask: &[bool]) -> Vec<bool> {
        assert_eq!(
            mask.len(),
            self.width * self.height,
            "a mask of {}x{} has {} values",
            self.width,
            self.height,
            self.width * self.height
        );
        let coverage: Vec<f32> = mask.iter().map(|&m| if m { 1.0 } else { 0.0 }).collect();
        self.map
            .iter()
            .map(|&s| self.sample::<1>(&coverage, s)[0] >= 0.5)
            .collect()
    }
}

/// Resamples the images of one distorting camera into the pinhole camera with the same
/// K and image size. Built once per camera; each image is then one bilinear pass.
#[derive(Clone, Debug)]
pub struct Undistorter {
    map: SourceMap,
}

impl Undistorter {
    /// The map of `camera` (its intrinsics and image size; the pose does not matter)
    /// with lens `distortion`: the pinhole pixel at normalized `(x, y)` takes the
    /// distorted image at `distort(x, y)`, as `cv2.initUndistortRectifyMap(K, D, None,
    /// K, size, CV_32FC1)` computes it (in drape's pixel convention, see the module).
    pub fn new(camera: &Camera, distortion: Distortion) -> Self {
        Self {
            map: SourceMap::build(camera, |x, y| distortion.distort(x, y)),
        }
    }

    pub fn width(&self) -> u32 {
        self.map.width as u32
    }

    pub fn height(&self) -> u32 {
        self.map.height as u32
    }

    /// Where pinhole pixel (x, y) samples the distorted image, in index coordinates
    /// (centre of pixel (i, j) at (i, j), OpenCV's): what cv2's map holds for K with the
    /// principal point moved by -0.5.
    pub fn source(&self, x: u32, y: u32) -> [f32; 2] {
        self.map.map[y as usize * self.map.width + x as usize]
    }

    /// The pinhole image of a distorted RGB image (interleaved, in [0, 1]); pixels that
    /// see outside it are black. Panics if `rgb` is not width × height × 3 values.
    pub fn rgb(&self, rgb: &[f32]) -> Vec<f32> {
        self.map.rgb(rgb)
    }

    /// The pinhole mask of a distorted mask: bilinear of 0/1, then at least one half
    /// (the rule and why are at `SourceMap::mask`); outside the image is outside the
    /// mask. Panics if `mask` is not width × height values.
    pub fn mask(&self, mask: &[bool]) -> Vec<bool> {
        self.map.mask(mask)
    }
}

/// The image `camera` with lens `distortion` would have taken of what the pinhole image
/// `rgb` shows: each distorted pixel samples the pinhole image at
/// [`Distortion::undistort_normalized`] of itself. For fixtures (tests, the synthetic
/// generator); the inverse of [`Undistorter::rgb`] up to two bilinear resamplings.
pub fn distort_rgb(camera: &Camera, distortion: Distortion, rgb: &[f32]) -> Vec<f32> {
    SourceMap::build(camera, |x, y| distortion.undistort_normalized(x, y)).rgb(rgb)
}

/// [`distort_rgb`] for a mask, with [`Undistorter::mask`]'s rule.
pub fn distort_mask(camera: &Camera, distortion: Distortion, mask: &[bool]) -> Vec<bool> {
    SourceMap::build(camera, |x, y| distortion.undistort_normalized(x, y)).mask(mask)
}

#[cfg(test)]
mod tests {
    use super::*;

    const ZJU_LIKE: Distortion = Distortion {
        k1: -0.3,
        k2: 0.1,
        p1: 1e-3,
        p2: -5e-4,
        k3: 0.02,
    };

    #[test]
    fn undistort_normalized_inverts_distort() {
        // Out to r = 0.7, the corners of a 1024² image at f ≈ 1000.
        for i in -7..=7 {
            for j in -7..=7 {
                let (x, y) = (0.05 * f64::from(i), 0.05 * f64::from(j));
                let [xd, yd] = ZJU_LIKE.distort(x, y);
                let [u, v] = ZJU_LIKE.undistort_normalized(xd, yd);
                // Newton stops at a residual of 1e-14; the Jacobian is near 1 here.
                assert!(
                    (u - x).abs() < 1e-13 && (v - y).abs() < 1e-13,
                    "({x}, {y}) -> ({xd}, {yd}) -> ({u}, {v})"
                );
            }
        }
    }

    #[test]
    fn no_distortion_is_the_identity() {
        let camera = Camera::look_at(
            DVec3::new(0.0, 0.0, -3.0),
            DVec3::ZERO,
            DVec3::NEG_Y,
            40.0,
            7,
            5,
        );
        let rgb: Vec<f32> = (0..7 * 5 * 3).map(|i| (i % 11) as f32 / 10.0).collect();
        let mask: Vec<bool> = (0..7 * 5).map(|i| i % 3 == 0).collect();
        let u = Undistorter::new(&camera, Distortion::NONE);
        assert!(Distortion::NONE.is_identity() && !ZJU_LIKE.is_identity());
        assert_eq!(u.rgb(&rgb), rgb);
        assert_eq!(u.mask(&mask), mask);
        assert_eq!(distort_rgb(&camera, Distortion::NONE, &rgb), rgb);
    }

    #[test]
    fn opencv_order() {
        let d = Distortion::from_opencv(&[1.0, 2.0, 3.0, 4.0, 5.0]);
        assert_eq!(
            d,
            Distortion {
                k1: 1.0,
                k2: 2.0,
                p1: 3.0,
                p2: 4.0,
                k3: 5.0
            }
        );
        assert_eq!(d.to_opencv(), [1.0, 2.0, 3.0, 4.0, 5.0]);
    }

    #[test]
    fn a_nan_source_samples_as_outside() {
        let camera = Camera::look_at(
            DVec3::new(0.0, 0.0, -3.0),
            DVec3::ZERO,
            DVec3::NEG_Y,
            40.0,
            4,
            4,
        );
        let map = SourceMap::build(&camera, |_, _| [f64::NAN, 0.0]);
        assert!(map.rgb(&[1.0; 48]).iter().all(|&v| v == 0.0));
        assert!(map.mask(&[true; 16]).iter().all(|&m| !m));
    }
}
