//! `drape inspect DIR`: which layout and variant a sequence is in, its counts and
//! image size, which masks and parameters exist, the split training would use, and
//! the first problem found, before a run is started on it.

use std::path::PathBuf;

use clap::Args;
use drape_trainer::dataset::inspect::inspect;

#[derive(Args, Debug, Clone)]
pub struct InspectArgs {
    /// The sequence: NeuMan (`sparse/`), ZJU-MoCap (`annots.npy`) in any published
    /// variant, or a `drape synth` output (its `neuman/` is inspected).
    pub dir: PathBuf,
    /// Print the findings as JSON instead of a table.
    #[arg(long)]
    pub json: bool,
}

/// Prints the findings; fails (exit 1) when a problem was found, so scripts can gate on it.
pub fn run(args: &InspectArgs) -> anyhow::Result<()> {
    let found = inspect(&args.dir);
    if args.json {
        println!("{}", serde_json::to_string_pretty(&found)?);
    } else {
        let size = found
            .image_size
            .map_or("-".to_string(), |(w, h)| format!("{w}x{h}"));
        println!("{}", found.dir.display());
        println!(
            "  layout:  {}",
            found.variant.map_or("unknown".to_string(), |v| format!(
                "{v}: {}",
                found.description.unwrap_or("")
            ))
        );
        println!(
            "  images:  {} frames x {} cameras, {size}",
            found.frames, found.cameras
        );
        println!("  masks:   {}", found.masks);
        println!("  params:  {}", found.params);
        println!("  split:   {}", found.split);
        if !found.unused.is_empty() {
            println!("  present, not read: {}", found.unused.join(", "));
        }
        println!("  problem: {}", found.problem.as_deref().unwrap_or("none"));
    }
    match found.problem {
        Some(_) => Err(anyhow::anyhow!(
            "{}: not loadable as it is (the problem is above)",
            found.dir.display()
        )),
        None => Ok(()),
    }
}
