//! `drape view` end to end on a virtual X server: the shared tiny run exported as an
//! avatar file (`drape export`) and viewed from the file alone (a copy of the file in a
//! directory of its own, no run directory or dataset beside it), three frames
//! presented through the viewer's own swapchain (validation on), the window captured
//! from the X server with `xwd` and compared with the library's render of the same
//! frame that the viewer writes next to it (`--screenshot`), then the viewer told to
//! exit and checked for exit 0 and no validation message.
//!
//! Needs `Xvfb` and `xwd` (`scripts/setup.sh` installs xvfb and x11-apps); without them
//! the test fails, naming the package.

use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

fn drape() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_drape"));
    c.stdin(Stdio::null()).env("RUST_BACKTRACE", "0");
    c
}

fn on_path(tool: &str) -> bool {
    std::env::var_os("PATH")
        .is_some_and(|p| std::env::split_paths(&p).any(|d| d.join(tool).is_file()))
}

/// An `Xvfb` this test started, killed (by its own pid) when dropped.
struct Xvfb {
    child: Child,
    display: String,
}

impl Drop for Xvfb {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Starts `Xvfb :N -screen 0 320x240x24` on the first display number that is free.
fn start_xvfb() -> Xvfb {
    for n in (90..140).map(|i| i + (std::process::id() % 7) as usize) {
        let socket = PathBuf::from(format!("/tmp/.X11-unix/X{n}"));
        if socket.exists() || Path::new(&format!("/tmp/.X{n}-lock")).exists() {
            continue;
        }
        let display = format!(":{n}");
        let mut child = Command::new("Xvfb")
            .args([
                display.as_str(),
                "-screen",
                "0",
                "320x240x24",
                "-nolisten",
                "tcp",
            ])
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("Xvfb starts");
        let t0 = Instant::now();
        while t0.elapsed() < Duration::from_secs(15) {
            if let Ok(Some(_)) = child.try_wait() {
                break; // lost a race for the display number: try the next one.
            }
            if socket.exists() {
                return Xvfb { child, display };
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        let _ = child.kill();
        let _ = child.wait();
    }
    panic!("no free X display number in :90..:146 for Xvfb");
}

/// The shared tiny run (`DRAPE_TEST_RUN`, made once by the test command; else trained
/// once in this process).
fn tiny_run() -> PathBuf {
    let ctx =
        drape_engine::Context::new(&drape_engine::ContextDesc::for_tests()).expect("test device");
    drape_trainer::testing::tiny_run(&ctx).to_path_buf()
}

/// An XWD file's image as 8-bit RGB, row-major from the top (ZPixmap, 24 or 32 bits
/// per pixel, either byte order, channels by the header's masks).
fn parse_xwd(bytes: &[u8]) -> (u32, u32, Vec<[u8; 3]>) {
    let field = |i: usize| u32::from_be_bytes(bytes[4 * i..4 * i + 4].try_into().unwrap());
    let (header_size, version, format) = (field(0) as usize, field(1), field(2));
    assert_eq!(version, 7, "XWD version");
    assert_eq!(format, 2, "XWD pixmap format (2 = ZPixmap)");
    let (width, height) = (field(4), field(5));
    let byte_order = field(7); // 0 = LSBFirst
    let bpp = field(11) as usize;
    let bytes_per_line = field(12) as usize;
    let masks = [field(14), field(15), field(16)];
    let ncolors = field(19) as usize;
    assert!(bpp == 24 || bpp == 32, "XWD bits per pixel {bpp}");
    let data = &bytes[header_size + 12 * ncolors..];
    let step = bpp / 8;
    let mut out = Vec::with_capacity((width * height) as usize);
    for y in 0..height as usize {
        for x in 0..width as usize {
            let p = &data[y * bytes_per_line + x * step..][..step];
            let v = if byte_order == 0 {
                p.iter().rev().fold(0u32, |a, &b| (a << 8) | u32::from(b))
            } else {
                p.iter().fold(0u32, |a, &b| (a << 8) | u32::from(b))
            };
            out.push(masks.map(|m| {
                let shift = m.trailing_zeros();
                let max = m >> shift;
                ((u64::from((v & m) >> shift) * 255 + u64::from(max) / 2) / u64::from(max.max(1)))
                    as u8
            }));
        }
    }
    (width, height, out)
}

#[test]
fn view_presents_the_library_render() {
    assert!(
        on_path("Xvfb"),
        "Xvfb is not installed (package xvfb; scripts/setup.sh installs it)"
    );
    assert!(
        on_path("xwd"),
        "xwd is not installed (package x11-apps; scripts/setup.sh installs it)"
    );
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR"))
        .join("view-cli")
        .join(std::process::id().to_string());
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let run = tiny_run();
    let avatar = dir.join("tiny.avatar");
    let o = drape()
        .arg("export")
        .arg(&run)
        .arg("--out")
        .arg(&avatar)
        .output()
        .expect("drape export runs");
    assert!(
        o.status.success(),
        "drape export: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    let x = start_xvfb();
    let shot = dir.join("S.png");
    let mut child = drape()
        .arg("view")
        .arg(&avatar)
        .args(["--frames", "3", "--screenshot"])
        .arg(&shot)
        .env("DISPLAY", &x.display)
        .env("DRAPE_VALIDATION", "1")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("drape view starts");
    // stdout and stderr read on threads, so neither pipe fills up while we wait.
    let (tx, rx) = mpsc::channel();
    let stdout = child.stdout.take().unwrap();
    let out_thread = std::thread::spawn(move || {
        let mut all = String::new();
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            let _ = tx.send(line.clone());
            all.push_str(&line);
            all.push('\n');
        }
        all
    });
    let mut stderr = child.stderr.take().unwrap();
    let err_thread = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = stderr.read_to_string(&mut s);
        s
    });
    let window = rx
        .recv_timeout(Duration::from_secs(120))
        .expect("drape view prints `window 0x...` first");
    let window = window
        .strip_prefix("window ")
        .unwrap_or_else(|| panic!("first stdout line: {window}"))
        .to_string();
    let ready = PathBuf::from(format!("{}.ready", shot.display()));
    let t0 = Instant::now();
    while !ready.exists() {
        if let Ok(Some(status)) = child.try_wait() {
            panic!(
                "drape view exited ({status}) before {} appeared:\n{}",
                ready.display(),
                err_thread.join().unwrap()
            );
        }
        assert!(
            t0.elapsed() < Duration::from_secs(300),
            "{} did not appear",
            ready.display()
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    // The capture, from the X server.
    let xwd_path = dir.join("window.xwd");
    let o = Command::new("xwd")
        .args(["-id", &window, "-silent", "-display", &x.display, "-out"])
        .arg(&xwd_path)
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "xwd: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    drape_io::write(PathBuf::from(format!("{}.done", shot.display())), b"").unwrap();
    let t0 = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if t0.elapsed() > Duration::from_secs(60) {
            let _ = child.kill();
            panic!("drape view did not exit after .done");
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let stdout = out_thread.join().unwrap();
    let stderr = err_thread.join().unwrap();
    print!("{stdout}");
    assert!(status.success(), "drape view: {status}\n{stderr}");
    assert!(
        !stderr.contains("validation:"),
        "validation messages:\n{stderr}"
    );

    let (w, h, captured) = parse_xwd(&std::fs::read(&xwd_path).unwrap());
    let reference = image::open(&shot).unwrap().into_rgb16();
    assert_eq!(
        (w, h),
        reference.dimensions(),
        "the window's size is the render's"
    );
    // The blit's float -> UNORM conversion: round(clamp(c) * 255).
    let expected: Vec<[u8; 3]> = reference
        .pixels()
        .map(|p| {
            p.0.map(|v| ((f64::from(v) / 65535.0) * 255.0).round() as u8)
        })
        .collect();
    assert!(
        expected.iter().any(|p| p.iter().any(|&c| c > 8)),
        "the reference render is black: nothing to compare"
    );
    let close = captured
        .iter()
        .zip(&expected)
        .filter(|(a, b)| a.iter().zip(b.iter()).all(|(&x, &y)| x.abs_diff(y) <= 1))
        .count();
    let worst = captured
        .iter()
        .zip(&expected)
        .flat_map(|(a, b)| a.iter().zip(b.iter()).map(|(&x, &y)| x.abs_diff(y)))
        .max()
        .unwrap_or(0);
    let share = close as f64 / expected.len() as f64;
    println!(
        "view: {w}x{h} window vs library render: {:.3}% of pixels within 1/255 (worst {worst}/255)",
        100.0 * share
    );
    assert!(
        share >= 0.999,
        "only {:.3}% of pixels within 1/255 of the library render (worst {worst})",
        100.0 * share
    );
}
