//! `drape edit RUN --out NEW (--remove-cloth | --recolour DEGREES | --swap-cloth OTHER)`:
//! a new run with the garments changed (see `drape_trainer::avatar::edit`), which
//! `drape eval` and `drape animate` open like a trained one.

use std::path::PathBuf;

use drape_cli_support::DeviceArgs;
use drape_trainer::avatar::edit::{edit, Edit};
use drape_trainer::avatar::run::OpenRun;

/// Options of `drape edit`.
#[derive(Clone, Debug, clap::Args)]
#[command(group(clap::ArgGroup::new("edit").required(true).args(["remove_cloth", "recolour", "swap_cloth"])))]
pub struct EditArgs {
    /// The run to edit (it is not changed).
    pub run: PathBuf,
    /// The new run directory (must not exist, or be empty).
    #[arg(long)]
    pub out: PathBuf,
    /// Remove the cloth layer: the body underneath shows.
    #[arg(long)]
    pub remove_cloth: bool,
    /// Rotate the garments' hue by this many degrees (about the grey axis, inside the
    /// cloth layer's appearance decoder).
    #[arg(long, allow_negative_numbers = true, value_parser = drape_cli_support::number_in::<f64>(-3600.0, 3600.0))]
    pub recolour: Option<f64>,
    /// Put this run's cloth layer on RUN's body (runs of the same data and preset).
    #[arg(long)]
    pub swap_cloth: Option<PathBuf>,
    /// The sequence the run was trained on (default: from its run.json).
    #[arg(long)]
    pub data: Option<PathBuf>,
}

pub fn run(device: &DeviceArgs, args: &EditArgs) -> anyhow::Result<()> {
    let which = match (&args.recolour, &args.swap_cloth) {
        (Some(h), _) => {
            anyhow::ensure!(h.is_finite(), "--recolour {h}: not a number of degrees");
            Edit::Recolour { hue_degrees: *h }
        }
        (None, Some(_)) => Edit::SwapCloth,
        (None, None) => Edit::RemoveCloth,
    };
    if args.out.exists()
        && std::fs::read_dir(&args.out)
            .map(|mut d| d.next().is_some())
            .unwrap_or(true)
    {
        anyhow::bail!(
            "--out {}: the output directory exists and is not empty",
            args.out.display()
        );
    }
    let staged = drape_cli_support::output::StagedDir::new(&args.out, "--out", false)?;
    let ctx = device.open()?;
    let mut run = OpenRun::open(&ctx, &args.run, args.data.as_deref(), None)?;
    let mut other = match &args.swap_cloth {
        Some(o) => Some(OpenRun::open(&ctx, o, None, None)?),
        None => None,
    };
    let what = edit(&ctx, &mut run, &which, other.as_mut(), staged.path())?;
    device.check_validation(&ctx)?;
    staged.commit()?;
    println!("{what}; wrote {} (config.json, run.json, model.npz): `drape eval {0}` and `drape animate {0}` open it", args.out.display());
    Ok(())
}
