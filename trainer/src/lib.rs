//! The Cloth-HUGS avatar (body model, garments, cloth simulation, datasets, training,
//! evaluation). Nothing is implemented here yet: the body-and-cloth and dataset issues
//! fill this crate. It exists so the workspace layout of `DESIGN.md` holds from the start.
#![forbid(unsafe_code)]
