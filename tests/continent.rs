//! A continent-sized terrain (10^7 m across, see `support/continent.rs`) draws in
//! `terrastream render` and in `terrastream view` (a real window under Xvfb), each
//! compared with a reference image, and the two agree with each other: they choose
//! their camera, mesh and tiles through one code path. The webplayer's two back ends
//! are checked on the same archive in `webplayer.rs`.
//!
//! Needs Xvfb and xwd (Debian `xvfb`, `x11-apps`; the test command installs them) and a
//! software Vulkan (lavapipe). Without them the window half fails, unless
//! `TERRASTREAM_ALLOW_NO_DISPLAY=1` (then it skips loudly).
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, missing_docs)]

#[path = "support/cli.rs"]
mod cli;

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use cli::{Killed, terrastream};

const WIDTH: u32 = 480;
const HEIGHT: u32 = 270;
/// lavapipe is deterministic for a given Mesa; the allowance covers another Mesa release
/// and the window's swapchain against the offscreen target (the same sRGB format, but
/// presented through X): mean <= 2/255, at most 2 % of pixels off by more than 24/255.
/// A missing drape, a culled terrain or a moved camera breaks both.
const TOLERANCE: terrastream_testkit::golden::Tolerance =
    terrastream_testkit::golden::Tolerance { mean: 2.0, pixel: 24, off_share: 0.02 };

/// Share of pixels that are not the sky colour of the top-left corner.
fn terrain_share(rgba: &[u8]) -> f64 {
    let sky = &rgba[..3];
    let terrain = rgba.chunks_exact(4).filter(|p| p[..3].iter().zip(sky).any(|(a, b)| a.abs_diff(*b) > 12)).count();
    terrain as f64 / (rgba.len() / 4) as f64
}

/// Reads an X window dump (`xwd`, ZPixmap, 24/32 bits per pixel) as RGBA8.
fn read_xwd(bytes: &[u8]) -> (u32, u32, Vec<u8>) {
    let field = |i: usize| u32::from_be_bytes(bytes[i * 4..i * 4 + 4].try_into().unwrap());
    let (header, format, width, height) = (field(0) as usize, field(2), field(4), field(5));
    let (lsb_first, bits, line) = (field(7) == 0, field(11), field(12) as usize);
    let (masks, colours) = ([field(14), field(15), field(16)], field(19) as usize);
    assert_eq!(format, 2, "ZPixmap");
    assert!(bits == 32 || bits == 24, "{bits} bits per pixel");
    let pixels = &bytes[header + colours * 12..];
    let step = bits as usize / 8;
    let mut rgba = Vec::with_capacity((width * height * 4) as usize);
    for y in 0..height as usize {
        for x in 0..width as usize {
            let at = y * line + x * step;
            let mut raw = [0u8; 4];
            raw[..step].copy_from_slice(&pixels[at..at + step]);
            let p = if lsb_first { u32::from_le_bytes(raw) } else { u32::from_be_bytes(raw) >> (32 - bits) };
            for mask in masks {
                rgba.push(((p & mask) >> mask.trailing_zeros()) as u8);
            }
            rgba.push(255);
        }
    }
    (width, height, rgba)
}

fn display_tools() -> bool {
    let found = ["Xvfb", "xwd"].iter().all(|tool| {
        Command::new("sh").args(["-c", &format!("command -v {tool}")]).stdout(Stdio::null()).status().unwrap().success()
    });
    if !found && std::env::var_os("TERRASTREAM_ALLOW_NO_DISPLAY").is_some() {
        eprintln!("\n!!!!! SKIPPING the window: no Xvfb/xwd (apt-get install xvfb x11-apps) !!!!!\n");
        return false;
    }
    assert!(found, "Xvfb and xwd are needed (apt-get install xvfb x11-apps; scripts/test.sh installs them)");
    true
}

/// Starts Xvfb on a free display: the display's name and the server.
fn xvfb() -> (String, Killed) {
    for number in 90 + std::process::id() % 100.. {
        if Path::new(&format!("/tmp/.X11-unix/X{number}")).exists()
            || Path::new(&format!("/tmp/.X{number}-lock")).exists()
        {
            continue;
        }
        let display = format!(":{number}");
        let child = Command::new("Xvfb")
            .args([&display, "-screen", "0", &format!("{WIDTH}x{HEIGHT}x24"), "-nolisten", "tcp"])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        let server = Killed(child);
        let started = Instant::now();
        while !Path::new(&format!("/tmp/.X11-unix/X{number}")).exists() {
            assert!(started.elapsed() < Duration::from_secs(20), "Xvfb {display} did not start");
            std::thread::sleep(Duration::from_millis(50));
        }
        return (display, server);
    }
    unreachable!()
}

#[test]
fn a_continent_draws_in_render_and_in_a_window_alike() {
    let dir = tempfile::tempdir().unwrap();
    let archive =
        terrastream_testkit::continent::continent_archive(Path::new(env!("CARGO_BIN_EXE_terrastream")), dir.path());

    // Headless, on the globe.
    let png = dir.path().join("render.png");
    let out = terrastream()
        .args(["-q", "render", archive.to_str().unwrap(), "-o", png.to_str().unwrap()])
        .arg(format!("--size={WIDTH}x{HEIGHT}"))
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "render: {said} {}", String::from_utf8_lossy(&out.stderr));
    eprintln!("render: {said}");
    let (w, h, rendered) = terrastream_testkit::golden::decode_png(&std::fs::read(&png).unwrap());
    assert_eq!((w, h), (WIDTH, HEIGHT));
    terrastream_testkit::golden::assert_golden("continent-render", w, h, &rendered, TOLERANCE);
    let share = terrain_share(&rendered);
    // The default view frames the continent, 90 x 50 degrees kept on its geographic grid
    // (more than a region) and drawn on the globe: a good part of the picture is terrain.
    assert!(share > 0.2, "only {:.0} % of the render is terrain", share * 100.0);

    // The same archive in a window.
    if !display_tools() {
        return;
    }
    let (display, _xvfb) = xvfb();
    let mut viewer = terrastream()
        .args(["view", archive.to_str().unwrap(), "--no-hud"])
        .arg(format!("--size={WIDTH}x{HEIGHT}"))
        .env("DISPLAY", &display)
        .env("RUST_LOG", "info")
        .env("NO_COLOR", "1")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let log = BufReader::new(viewer.stderr.take().unwrap());
    let viewer = Killed(viewer);
    let (lines_tx, lines) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in log.lines().map_while(Result::ok) {
            let _ = lines_tx.send(line);
        }
    });
    let started = Instant::now();
    let mut seen = Vec::new();
    loop {
        match lines.recv_timeout(Duration::from_secs(1)) {
            Ok(line) if line.contains("view fully streamed") => break,
            Ok(line) => seen.push(line),
            Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {}
            Err(e) => panic!("the viewer ended before the view was complete ({e}): {seen:#?}"),
        }
        assert!(started.elapsed() < Duration::from_secs(120), "the view did not complete: {seen:#?}");
    }
    // A few more frames, then the screen.
    std::thread::sleep(Duration::from_millis(1500));
    let dump = Command::new("xwd").args(["-root", "-silent", "-display", &display]).output().unwrap();
    assert!(dump.status.success(), "xwd: {}", String::from_utf8_lossy(&dump.stderr));
    drop(viewer);
    let (w, h, shown) = read_xwd(&dump.stdout);
    assert_eq!((w, h), (WIDTH, HEIGHT));
    assert!(seen.iter().all(|l| !l.contains("no terrain")), "{seen:#?}");
    terrastream_testkit::golden::assert_golden("continent-view", w, h, &shown, TOLERANCE);
    let share = terrain_share(&shown);
    assert!(share > 0.2, "only {:.0} % of the window is terrain", share * 100.0);
    // One code path: the window shows what the still shows.
    let (mean, off) = terrastream_testkit::golden::difference(&shown, &rendered, TOLERANCE.pixel);
    assert!(
        mean <= TOLERANCE.mean && off as f64 <= TOLERANCE.off_share * f64::from(WIDTH * HEIGHT),
        "the window and the still differ: mean {mean:.2}, {off} pixels off"
    );
}
