//! The trainer's tests, one binary: body, garments, cloth, datasets, the layered avatar's
//! GPU paths, training, evaluation and the run tools, against CPU references and the
//! independent Python references (PyTorch, OpenCV, scikit-image, numpy).

mod avatar_file;
mod body;
mod calibration;
mod cloth;
mod composite;
mod config_layout;
mod datasets;
mod distortion;
mod embedding;
mod errors;
mod eval_metrics;
mod fid;
mod fixtures;
mod fuzz_corpus;
mod garments_motions;
mod image_formats;
mod loose_garment;
mod module_graph;
mod motion_files;
mod pickle;
mod ply;
mod raster;
mod run_tools;
mod skinning;
mod synth;
mod torch_reference;
mod train;
