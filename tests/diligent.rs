//! Conventions proven on real data: plain least squares on DiLiGenT reproduces the published
//! baseline (mean angular error 8.41° on cat, 8.39° on bear), end to end through the CLI.

mod common;

use std::path::Path;
use std::process::Command;

/// Runs `photostereo DIR --method ls -o OUT` then `photostereo eval` against `normal_gt.exr`,
/// returning the mean angular error in degrees.
fn ls_mean_error(dir: &Path) -> f64 {
    let out = tempfile::tempdir().unwrap();
    let run = Command::new(common::bin())
        .arg(dir)
        .args(["--method", "ls", "--integrate", "none", "-q", "-o"])
        .arg(out.path())
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let eval = Command::new(common::bin())
        .arg("eval")
        .arg("--normals")
        .arg(out.path().join("normal.exr"))
        .arg("--gt")
        .arg(dir.join("normal_gt.exr"))
        .arg("--mask")
        .arg(dir.join("mask.png"))
        .output()
        .unwrap();
    assert!(
        eval.status.success(),
        "{}",
        String::from_utf8_lossy(&eval.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&eval.stdout).unwrap();
    assert_eq!(v["missing"], 0);
    v["mean_deg"].as_f64().unwrap()
}

#[test]
fn diligent_cat_least_squares_baseline() {
    let dir = require_shared!("diligent/catPNG");
    let e = ls_mean_error(&dir);
    println!("cat: {e:.4}°");
    assert!((e - 8.41).abs() <= 0.05, "cat mean angular error {e}°");
}

#[test]
fn diligent_bear_least_squares_baseline() {
    let dir = require_shared!("diligent/bearPNG");
    let e = ls_mean_error(&dir);
    println!("bear: {e:.4}°");
    assert!((e - 8.39).abs() <= 0.05, "bear mean angular error {e}°");
}

/// The default estimator (threshold rejection of shadows and saturation) beats the baseline on
/// both objects with one setting.
#[test]
fn diligent_default_method_beats_the_baseline() {
    use photostereo::dataset::Capture;
    use photostereo::input::{LoadOptions, read_normal_map};
    use photostereo::pipeline::{Config, reconstruct};
    use photostereo::progress::Silent;
    for obj in ["cat", "bear"] {
        let dir = require_shared!(format!("diligent/{obj}PNG"));
        let capture = Capture::from_diligent(&dir, &LoadOptions::default(), &Silent).unwrap();
        let config = Config {
            integration: None,
            ..Config::default()
        };
        let recon = reconstruct(&capture, &config, &Silent).unwrap();
        let gt = read_normal_map(&dir.join("normal_gt.exr")).unwrap();
        let s = photostereo::metrics::angular_errors(&recon.normals, &gt, &capture.mask).unwrap();
        println!(
            "{obj}: default method {:.3}° ({} px, {} unsolved)",
            s.mean_deg, s.pixels, s.missing
        );
        assert!(s.mean_deg < 7.5, "{obj}: {}°", s.mean_deg);
        assert!(s.missing * 1000 < s.pixels, "{obj}: {} unsolved", s.missing);
    }
}

/// A 16-bit PNG normal map (n = v/65535·2 − 1) decodes to the same normals as the EXR ground
/// truth: the integration set's `normal_map.png` equals DiLiGenT's `Normal_gt` inside the mask.
#[test]
fn png_normal_map_decodes_like_the_exr_ground_truth() {
    use photostereo::input::{read_mask, read_normal_map};
    let png = require_shared!("integration/cat/normal_map.png");
    let exr = require_shared!("diligent/catPNG/normal_gt.exr");
    let mask = read_mask(&png.with_file_name("mask.png")).unwrap();
    let a = read_normal_map(&png).unwrap();
    let b = read_normal_map(&exr).unwrap();
    let s = photostereo::metrics::angular_errors(&a, &b, &mask).unwrap();
    println!(
        "normal_map.png vs normal_gt.exr: mean {:.5}°, p95 {:.5}°",
        s.mean_deg, s.p95_deg
    );
    assert_eq!(s.pixels, mask.count());
    assert!(s.mean_deg < 0.01 && s.p95_deg < 0.02, "{s:?}");
}
