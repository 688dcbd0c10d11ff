//! GPU ops built on the runtime. Each module owns one op: its plan (scratch buffers),
//! its recording, and the CPU reference it is tested against, which runs the same
//! `drape-shared` functions as the kernels.

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
