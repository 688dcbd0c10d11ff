//! GPU ops built on the runtime. Each module owns one op: its plan (scratch buffers)
//! and its recording. The tests check each op against a CPU reference on the same
//! `drape-shared` functions as the kernels: `ops::<op>::reference` (a module or, for a
//! single function, the function itself) in `splat`, `skinning`, `deform`, `nn`,
//! `triplane`, `ssim`, `lpips` and `cloth_loss`; for `scan`, `radix_sort` and `adam`
//! the `drape-shared` functions directly (each module's header names them);
//! `accumulate` is how backward kernels add gradients, checked through the ops that
//! use it. The ops know nothing of avatars: splatting
//! and compositing take clouds whose Gaussians carry a group index, one of the
//! caller's N groups.

pub mod accumulate;
pub mod adam;
pub mod cloth_loss;
pub mod deform;
pub mod lpips;
pub mod nn;
pub mod radix_sort;
pub mod scan;
pub mod skinning;
pub mod splat;
pub mod ssim;
pub mod triplane;
