//! A CPU mesh rasterizer for the synthetic data: z-buffer, near-plane clipping,
//! perspective-correct interpolation of UVs, Lambert shading from one fixed light,
//! and supersampled antialiasing; per pixel it also reports which object is visible
//! (for masks) and its depth.
//!
//! It draws through the trainer's one camera type, [`Camera`] (x right, y down,
//! z forward, pixel centres at +0.5).

use glam::DVec3;

use crate::camera::Camera;

/// Something to draw: triangles with UVs, an object id for masks, and a texture.
pub struct Drawable<'a> {
    pub vertices: &'a [DVec3],
    pub faces: &'a [[u32; 3]],
    pub uvs: &'a [[f64; 2]],
    /// Reported in the id image (0 is the background).
    pub object: u16,
    /// Colour at a UV, in [0, 1].
    pub texture: &'a dyn Fn([f64; 2]) -> [f64; 3],
    /// Draw back faces too (open garments show their inside).
    pub two_sided: bool,
}

/// A rendered frame at the output resolution.
#[derive(Clone, Debug)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    /// RGB in [0, 1], 3 per pixel.
    pub rgb: Vec<f32>,
    /// Camera-space depth of the nearest surface at the pixel centre's samples (0: none).
    pub depth: Vec<f32>,
    /// Fraction of each pixel's samples covered by each object id: `coverage[id][pixel]`.
    pub coverage: Vec<Vec<f32>>,
}

struct Vertex {
    /// Camera space.
    c: DVec3,
    uv: [f64; 2],
}

/// Clips a camera-space triangle against z >= near; 0, 1 or 2 triangles.
fn clip_near(tri: [Vertex; 3], near: f64) -> Vec<[Vertex; 3]> {
    let inside: Vec<bool> = tri.iter().map(|v| v.c[2] >= near).collect();
    let n_in = inside.iter().filter(|&&b| b).count();
    if n_in == 3 {
        return vec![tri];
    }
    if n_in == 0 {
        return vec![];
    }
    let lerp = |a: &Vertex, b: &Vertex| {
        let t = (near - a.c[2]) / (b.c[2] - a.c[2]);
        Vertex {
            c: a.c + (b.c - a.c) * t,
            uv: [
                a.uv[0] + t * (b.uv[0] - a.uv[0]),
                a.uv[1] + t * (b.uv[1] - a.uv[1]),
            ],
        }
    };
    // Rotate so the odd one out is first, keeping the winding.
    let odd = if n_in == 1 {
        inside.iter().position(|&b| b)
    } else {
        inside.iter().position(|&b| !b)
    }
    .expect("one odd vertex");
    let [a, b, c] = [0, 1, 2].map(|k| (odd + k) % 3);
    let v = &tri;
    if n_in == 1 {
        vec![[
            Vertex {
                c: v[a].c,
                uv: v[a].uv,
            },
            lerp(&v[a], &v[b]),
            lerp(&v[a], &v[c]),
        ]]
    } else {
        let ab = lerp(&v[b], &v[a]);
        let ac = lerp(&v[c], &v[a]);
        vec![
            [
                Vertex { c: ab.c, uv: ab.uv },
                Vertex {
                    c: v[b].c,
                    uv: v[b].uv,
                },
                Vertex {
                    c: v[c].c,
                    uv: v[c].uv,
                },
            ],
            [
                ab,
                Vertex {
                    c: v[c].c,
                    uv: v[c].uv,
                },
                ac,
            ],
        ]
    }
}

/// Renders `drawables` with `samples` x `samples` supersampling; `light` is the
/// direction towards the light in world space; `ambient` the unlit share.
pub fn render(
    camera: &Camera,
    drawables: &[Drawable<'_>],
    samples: u32,
    background: [f64; 3],
    light: DVec3,
    ambient: f64,
) -> Frame {
    let s = samples.max(1);
    let (w, h) = (camera.width * s, camera.height * s);
    let mut zbuf = vec![f64::INFINITY; (w * h) as usize];
    let mut color = vec![background; (w * h) as usize];
    let mut ids = vec![0u16; (w * h) as usize];
    let light = light.normalize_or(DVec3::Z);
    let max_id = drawables.iter().map(|d| d.object).max().unwrap_or(0) as usize;
    for d in drawables {
        for f in d.faces {
            let [p0, p1, p2] = f.map(|i| d.vertices[i as usize]);
            let n = (p1 - p0).cross(p2 - p0).normalize_or(DVec3::Z);
            let tri = [0, 1, 2].map(|k| Vertex {
                c: camera.to_camera(d.vertices[f[k] as usize]),
                uv: d.uvs.get(f[k] as usize).copied().unwrap_or([0.0, 0.0]),
            });
            // Back-face test in camera space: the view ray to the triangle against its normal.
            let cn = (tri[1].c - tri[0].c).cross(tri[2].c - tri[0].c);
            let facing = cn.dot(tri[0].c) < 0.0;
            if !facing && !d.two_sided {
                continue;
            }
            let shade = ambient + (1.0 - ambient) * n.dot(light).abs().max(0.0);
            for t in clip_near(tri, camera.near) {
                // Screen positions at the supersampled resolution.
                let sp: Vec<[f64; 2]> = t
                    .iter()
                    .map(|v| {
                        let p = camera.project_camera(v.c);
                        [p[0] * f64::from(s), p[1] * f64::from(s)]
                    })
                    .collect();
                let area = (sp[1][0] - sp[0][0]) * (sp[2][1] - sp[0][1])
                    - (sp[2][0] - sp[0][0]) * (sp[1][1] - sp[0][1]);
                if area.abs() < 1e-12 {
                    continue;
                }
                let xmin = sp
                    .iter()
                    .map(|p| p[0])
                    .fold(f64::MAX, f64::min)
                    .floor()
                    .max(0.0) as u32;
                let xmax = (sp.iter().map(|p| p[0]).fold(f64::MIN, f64::max).ceil() as i64)
                    .clamp(0, i64::from(w)) as u32;
                let ymin = sp
                    .iter()
                    .map(|p| p[1])
                    .fold(f64::MAX, f64::min)
                    .floor()
                    .max(0.0) as u32;
                let ymax = (sp.iter().map(|p| p[1]).fold(f64::MIN, f64::max).ceil() as i64)
                    .clamp(0, i64::from(h)) as u32;
                let inv_z = t.each_ref().map(|v| 1.0 / v.c[2]);
                for y in ymin..ymax {
                    for x in xmin..xmax {
                        let (px, py) = (f64::from(x) + 0.5, f64::from(y) + 0.5);
                        let e = |a: usize, b: usize| {
                            (sp[b][0] - sp[a][0]) * (py - sp[a][1])
                                - (sp[b][1] - sp[a][1]) * (px - sp[a][0])
                        };
                        let (w0, w1, w2) = (e(1, 2) / area, e(2, 0) / area, e(0, 1) / area);
                        if w0 < 0.0 || w1 < 0.0 || w2 < 0.0 {
                            continue;
                        }
                        // Perspective-correct: interpolate 1/z and attribute/z.
                        let iz = w0 * inv_z[0] + w1 * inv_z[1] + w2 * inv_z[2];
                        let z = 1.0 / iz;
                        let i = (y * w + x) as usize;
                        if z >= zbuf[i] {
                            continue;
                        }
                        let uv = [0, 1].map(|k| {
                            (w0 * t[0].uv[k] * inv_z[0]
                                + w1 * t[1].uv[k] * inv_z[1]
                                + w2 * t[2].uv[k] * inv_z[2])
                                * z
                        });
                        let c = (d.texture)(uv);
                        zbuf[i] = z;
                        color[i] = c.map(|v| v * shade);
                        ids[i] = d.object;
                    }
                }
            }
        }
    }
    // Box filter down to the output resolution.
    let (ow, oh) = (camera.width, camera.height);
    let n = f64::from(s * s);
    let mut frame = Frame {
        width: ow,
        height: oh,
        rgb: vec![0.0; (3 * ow * oh) as usize],
        depth: vec![0.0; (ow * oh) as usize],
        coverage: vec![vec![0.0; (ow * oh) as usize]; max_id + 1],
    };
    for y in 0..oh {
        for x in 0..ow {
            let o = (y * ow + x) as usize;
            let mut acc = [0.0; 3];
            let mut nearest = f64::INFINITY;
            for sy in 0..s {
                for sx in 0..s {
                    let i = ((y * s + sy) * w + x * s + sx) as usize;
                    for k in 0..3 {
                        acc[k] += color[i][k];
                    }
                    nearest = nearest.min(zbuf[i]);
                    frame.coverage[ids[i] as usize][o] += (1.0 / n) as f32;
                }
            }
            for k in 0..3 {
                frame.rgb[3 * o + k] = (acc[k] / n) as f32;
            }
            frame.depth[o] = if nearest.is_finite() {
                nearest as f32
            } else {
                0.0
            };
        }
    }
    frame
}
