//! The engine's GPU tests, one binary: every op against its CPU reference on the test
//! device (lavapipe in CI) with validation on, and against independent implementations
//! (gsplat, PyTorch) where the module says so. Nothing here links the trainer.

mod cloth_loss;
mod half_precision;
mod lpips;
mod mirror;
mod module_graph;
mod nn;
mod recorder;
mod runtime;
mod scan;
mod shared_math;
mod sizes;
mod sort;
mod splat_gpu;
mod splat_gradients;
mod splat_gsplat;
mod splat_robustness;
mod ssim;
mod step_guard;
mod triplane_deform;
