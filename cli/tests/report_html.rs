//! `report.html`: written beside every run's outputs, self-contained (nothing fetched), and
//! drawn by a real browser — headless Chromium opens the file, runs its 3-D viewer and takes a
//! screenshot, in which the mesh view must show a shaded surface, not a blank canvas.

#[path = "../../tests/common/mod.rs"]
mod common;

use common::{os, run, sphere_dataset};
use photostereo::synth::write::ImageFormat;
use std::path::{Path, PathBuf};
use std::process::Command;

/// Headless Chromium, where installed (`.ci/run` installs Debian's chromium-headless-shell).
fn chromium() -> Option<PathBuf> {
    [
        "chromium-headless-shell",
        "chromium",
        "chromium-browser",
        "google-chrome",
    ]
    .iter()
    .find_map(|name| {
        std::env::var_os("PATH").and_then(|paths| {
            std::env::split_paths(&paths)
                .map(|d| d.join(name))
                .find(|p| p.is_file())
        })
    })
}

fn browser(chrome: &Path, page: &Path, extra: &[&str]) -> std::process::Output {
    let url = format!("file://{}", page.display());
    Command::new(chrome)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--hide-scrollbars",
            "--window-size=1000,1400",
            "--virtual-time-budget=5000",
        ])
        .args(extra)
        .arg(url)
        .output()
        .unwrap()
}

#[test]
fn report_html_is_self_contained_and_draws_the_mesh() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let images = sphere_dataset(&data, ImageFormat::Exr);
    let (lights, mask) = (data.join("lights.json"), data.join("mask.png"));
    let out = tmp.path().join("out");
    let mut args: Vec<&std::ffi::OsStr> = images.iter().map(|p| p.as_os_str()).collect();
    args.extend([
        os("--lights"),
        lights.as_os_str(),
        os("--mask"),
        mask.as_os_str(),
        os("-q"),
        os("-o"),
        out.as_os_str(),
    ]);
    let o = run(&args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let page = out.join("report.html");
    let html = std::fs::read_to_string(&page).unwrap();
    // Self-contained: every image inline, no script or style fetched.
    assert!(!html.contains("src=\"http") && !html.contains("href=\"http"));
    assert_eq!(html.matches("src=\"data:image/png;base64,").count(), 4);
    assert!(html.contains("const MESH = {"));
    for figure in [
        "lights seen from the camera",
        "noise σ estimated per image",
        "pixels",
    ] {
        assert!(html.contains(figure), "{figure}");
    }
    let Some(chrome) = chromium() else {
        eprintln!("SKIPPED: no headless Chromium on PATH; report.html was checked as text only");
        return;
    };
    // The script ran and drew the triangles of the sphere's mesh (one per half cell inside).
    let dom = browser(&chrome, &page, &["--dump-dom"]);
    let dom = String::from_utf8_lossy(&dom.stdout);
    let triangles: usize = dom
        .split("data-triangles=\"")
        .nth(1)
        .and_then(|t| t.split('"').next())
        .and_then(|t| t.parse().ok())
        .unwrap_or(0);
    let inside = photostereo::io::decode::read_mask(&mask).unwrap().count();
    assert!(
        triangles > inside && triangles < 2 * inside,
        "{triangles} triangles for {inside} pixels"
    );
    // The screenshot: the canvas (640x480 under the 56 px header and 16 px margin) shows a
    // shaded surface — many grey levels, a good share of it not white.
    let shot = tmp.path().join("shot.png");
    let o = browser(
        &chrome,
        &page,
        &[&format!("--screenshot={}", shot.display())],
    );
    assert!(shot.is_file(), "{}", String::from_utf8_lossy(&o.stderr));
    let img = image::open(&shot).unwrap().to_rgb8();
    let mut levels = std::collections::BTreeSet::new();
    let (mut drawn, mut total) = (0usize, 0usize);
    for y in 80..540 {
        for x in 24..648 {
            let p = img.get_pixel(x, y).0;
            total += 1;
            if p != [255, 255, 255] {
                drawn += 1;
                if p[0] == p[1] && p[1] == p[2] {
                    levels.insert(p[0]);
                }
            }
        }
    }
    assert!(
        drawn * 10 > total && levels.len() > 40,
        "the mesh view is blank: {drawn} of {total} pixels drawn, {} grey levels",
        levels.len()
    );
    if std::env::var_os("KEEP_SCREENSHOT").is_some() {
        std::fs::copy(&shot, "/tmp/report_html_screenshot.png").unwrap();
    }
}
