//! The `drape` command line, one binary: each module runs the built binary on small
//! inputs and checks its outputs and its one-line errors.

mod bench_cloth_cli;
mod cli;
mod fixtures;
mod hostile;
mod inspect_cli;
mod motion_cli;
mod prepare_cli;
mod render_fit;
mod render_formats;
mod train_cli;
mod view_cli;
