//! The avatar's layers as the engine's groups of Gaussians: the engine carries a plain
//! group index per Gaussian ([`GaussianCloud::groups`]); which index is the body, the
//! cloth or the scene is the avatar's convention, written here once.
//!
//! [`GaussianCloud::groups`]: drape_engine::ops::splat::scene::GaussianCloud::groups

/// Which layer of the avatar a Gaussian belongs to; its engine group is the
/// discriminant (body 0, cloth 1, scene 2).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[repr(u32)]
pub enum Layer {
    /// The person's body (and whatever the cloth layer does not model).
    Body = 0,
    /// The garment composited over the body (Cloth-HUGS, Sec. 2.3).
    Cloth = 1,
    /// The static background.
    Scene = 2,
}

impl Layer {
    /// The layer's engine group index.
    pub fn group(self) -> u32 {
        self as u32
    }

    /// The layer of an engine group index, if it is one of the avatar's.
    pub fn from_group(group: u32) -> Option<Self> {
        [Self::Body, Self::Cloth, Self::Scene]
            .into_iter()
            .find(|l| l.group() == group)
    }
}

impl From<Layer> for u32 {
    fn from(layer: Layer) -> u32 {
        layer.group()
    }
}

#[cfg(test)]
mod tests {
    use super::Layer;

    #[test]
    fn groups_round_trip() {
        for l in [Layer::Body, Layer::Cloth, Layer::Scene] {
            assert_eq!(Layer::from_group(l.group()), Some(l));
        }
        assert_eq!(
            [Layer::Body, Layer::Cloth, Layer::Scene].map(u32::from),
            [0, 1, 2]
        );
        assert_eq!(Layer::from_group(3), None);
    }
}
