//! The body: the SMPL format (model, `.npz` loader and writer), the project's own
//! procedural body in that format, posing (forward kinematics and linear blend
//! skinning), Gaussians initialised from a skinned mesh (`gaussians`), and the fit of a
//! body to 3D landmarks (`fit`, over the small solver in `least_squares`).

pub mod fit;
pub mod gaussians;
pub mod kinematics;
mod least_squares;
pub mod model;
pub mod procedural;

pub use model::{SmplModel, JOINT_NAMES, NUM_JOINTS, PARENTS};
