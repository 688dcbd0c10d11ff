//! What several of this binary's modules share.

/// A body-only training configuration small enough for seconds on lavapipe: the test's
/// own tables (`[schedule]`, and `[densify]` where it densifies) and then the layers.
pub fn tiny_body_config(tables: &str) -> String {
    format!(
        "{tables}[layers]\nchoice = \"body\"\ndecimate = 6\n[layers.body]\ntriplane_resolution = 8\ntriplane_channels = 2\n"
    )
}
