//! GPU ops built on the runtime. Each module owns one op: its plan (scratch buffers),
//! its recording, and the CPU reference it is tested against (`ops::<op>::reference`,
//! a module or, for a single function, the function itself), which runs the same
//! `drape-shared` functions as the kernels. The ops know nothing of avatars: splatting
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
