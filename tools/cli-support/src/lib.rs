//! What every drape binary shares: the `--device` / `--validation` options, opening
//! the context (and printing the chosen device), argument parsing that reports a bad
//! argument in one line, and a `main` wrapper that turns any error into one line on
//! stderr and a non-zero exit code, never a panic trace.
#![forbid(unsafe_code)]

pub mod output;

use std::process::ExitCode;

use clap::Parser;
use drape_engine::{Context, ContextDesc};

/// Device options every binary takes.
#[derive(Clone, Debug, clap::Args)]
pub struct DeviceArgs {
    /// Use the Vulkan device whose name contains NAME (case-insensitive), e.g. "llvmpipe".
    /// Default: a discrete GPU, then an integrated one, then a CPU implementation.
    #[arg(long, global = true, value_name = "NAME")]
    pub device: Option<String>,

    /// Enable the Khronos validation layer, with synchronization validation, and fail
    /// on any message.
    #[arg(long, global = true)]
    pub validation: bool,
}

impl DeviceArgs {
    /// Opens the device and prints which one was chosen (to stderr, so JSON on
    /// stdout stays clean).
    pub fn open(&self) -> anyhow::Result<Context> {
        let ctx = Context::new(&ContextDesc {
            device_name: self.device.clone(),
            validation: self.validation,
            poison_new_buffers: false,
            // As in the tests: DRAPE_FORCE_STAGING=1 takes the discrete-GPU data path.
            force_staging: std::env::var("DRAPE_FORCE_STAGING").is_ok_and(|v| v == "1"),
            synchronization_validation: self.validation,
            max_storage_buffer_range: None,
        })?;
        eprintln!("device: {}", ctx.info());
        Ok(ctx)
    }

    /// With `--validation`, turns collected messages into an error.
    pub fn check_validation(&self, ctx: &Context) -> anyhow::Result<()> {
        let messages = ctx.take_validation_messages();
        anyhow::ensure!(
            messages.is_empty(),
            "{} validation message(s); first: {}",
            messages.len(),
            messages[0]
        );
        Ok(())
    }
}

/// Parses arguments; a usage error is printed as its first line only (exit 2), help
/// and version as clap renders them (exit 0).
pub fn parse_args<T: Parser>() -> Result<T, ExitCode> {
    match T::try_parse() {
        Ok(args) => Ok(args),
        Err(e) => {
            use clap::error::ErrorKind;
            if matches!(
                e.kind(),
                ErrorKind::DisplayHelp
                    | ErrorKind::DisplayVersion
                    | ErrorKind::DisplayHelpOnMissingArgumentOrSubcommand
            ) {
                let _ = e.print();
                return Err(
                    if e.kind() == ErrorKind::DisplayHelpOnMissingArgumentOrSubcommand {
                        ExitCode::from(2)
                    } else {
                        ExitCode::SUCCESS
                    },
                );
            }
            let rendered = e.render().to_string();
            // The message up to the usage block, on one line (clap puts the missing
            // arguments on the lines after the first).
            let message: Vec<&str> = rendered
                .lines()
                .take_while(|l| !l.trim().is_empty())
                .map(str::trim)
                .collect();
            let first = if message.is_empty() {
                "error: bad arguments".to_string()
            } else {
                message.join(" ")
            };
            eprintln!("{first} (see --help)");
            Err(ExitCode::from(2))
        }
    }
}

/// An ending that is not a failure but has an exit status of its own, e.g. 75
/// (`EX_TEMPFAIL`: a training stopped by a signal, checkpointed, to be resumed).
/// [`run`] prints its message as it is (no `error:`) and exits with `code`.
#[derive(Debug)]
pub struct Exit {
    pub code: u8,
    pub message: String,
}

impl std::fmt::Display for Exit {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.message)
    }
}

impl std::error::Error for Exit {}

/// Runs `body`; an error is printed as one line (`error: ...: cause`) with exit code 1
/// ([`Exit`]: its message and its code).
pub fn run(body: impl FnOnce() -> anyhow::Result<()>) -> ExitCode {
    match body() {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) if e.is::<Exit>() => {
            let exit = e.downcast::<Exit>().expect("checked");
            eprintln!("{}", exit.message);
            ExitCode::from(exit.code)
        }
        Err(e) => {
            eprintln!("error: {}", format!("{e:#}").replace('\n', " "));
            ExitCode::FAILURE
        }
    }
}

/// A length argument: a non-negative integer (underscores allowed, e.g. 1_000_000).
pub fn parse_len(s: &str) -> Result<u32, String> {
    let cleaned = s.replace('_', "");
    if cleaned.starts_with('-') {
        return Err(format!(
            "'{s}' is negative; a length is a non-negative integer"
        ));
    }
    cleaned
        .parse::<u32>()
        .map_err(|_| format!("'{s}' is not a non-negative integer below 2^32"))
}

/// Median of a non-empty list (the mean of the middle two for an even count).
pub fn median(values: &[f64]) -> f64 {
    assert!(!values.is_empty(), "median of nothing");
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let mid = v.len() / 2;
    if v.len() % 2 == 0 {
        (v[mid - 1] + v[mid]) / 2.0
    } else {
        v[mid]
    }
}

/// A parser for a finite number option in `[min, max]`; the message says the range
/// (clap puts the option's name before it).
pub fn number_in<T>(
    min: f64,
    max: f64,
) -> impl Fn(&str) -> Result<T, String> + Clone + Send + Sync + 'static
where
    T: std::str::FromStr + Copy + Into<f64> + Send + Sync + 'static,
{
    move |s: &str| {
        let v: T = s
            .trim()
            .parse()
            .map_err(|_| format!("'{s}' is not a number"))?;
        let x: f64 = v.into();
        if !x.is_finite() || x < min || x > max {
            return Err(format!("'{s}' is outside [{min}, {max}]"));
        }
        Ok(v)
    }
}

/// Bytes of memory the machine can still give (Linux's MemAvailable); None where the
/// system does not say.
pub fn available_memory() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

/// Refuses work that needs `bytes` of host memory for `what` beyond what the machine
/// has available, naming the option that asked for it.
pub fn ensure_memory(bytes: u64, what: &str, option: &str) -> anyhow::Result<()> {
    if let Some(available) = available_memory() {
        anyhow::ensure!(
            bytes <= available,
            "{option}: {what} needs {:.1} GiB of memory, and {:.1} GiB is available",
            bytes as f64 / (1u64 << 30) as f64,
            available as f64 / (1u64 << 30) as f64
        );
    }
    Ok(())
}
