//! The layout of a Gaussian cloud's geometry on the GPU (`GaussianBuffers::all`): the
//! floats per Gaussian of each of its first four buffers, which the avatar's copies and
//! gradient sums between a layer's own buffers and a shared cloud walk slice by slice.

/// Floats per Gaussian of means, log-scales, quaternions, opacity.
pub(crate) const GEOMETRY_FLOATS: [u32; 4] = [3, 3, 4, 1];
