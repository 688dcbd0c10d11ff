//! The body: the SMPL format (model, `.npz` loader and writer), the project's own
//! procedural body in that format, and posing (forward kinematics and linear blend
//! skinning).

pub mod gaussians;
pub mod kinematics;
pub mod model;
pub mod procedural;

pub use model::{SmplModel, JOINT_NAMES, NUM_JOINTS, PARENTS};
