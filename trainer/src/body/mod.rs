//! The body: the SMPL format (model, `.npz` loader and writer), the project's own
//! procedural body in that format, posing (forward kinematics and linear blend
//! skinning), and Gaussians initialised from a skinned mesh (`gaussians`).

pub mod fit;
pub mod gaussians;
pub mod kinematics;
pub mod model;
pub mod procedural;

pub use model::{SmplModel, JOINT_NAMES, NUM_JOINTS, PARENTS};
