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
    use photostereo::input::{LoadOptions, read_image};
    use photostereo::pipeline::{Config, reconstruct};
    use photostereo::progress::Silent;
    for obj in ["cat", "bear"] {
        let dir = require_shared!(format!("diligent/{obj}PNG"));
        let capture = Capture::from_diligent(&dir, &LoadOptions::default(), &Silent).unwrap();
        let config = Config {
            integrator: None,
            ..Config::default()
        };
        let recon = reconstruct(&capture, &config, &Silent).unwrap();
        let gt = read_image(&dir.join("normal_gt.exr")).unwrap();
        let gt = photostereo::grid::Grid::from_vec(
            gt.width,
            gt.height,
            gt.data
                .chunks_exact(3)
                .map(|c| nalgebra::Vector3::new(c[0], c[1], c[2]))
                .collect(),
        )
        .unwrap();
        let s = photostereo::metrics::angular_errors(&recon.normals, &gt, &capture.mask).unwrap();
        println!(
            "{obj}: default method {:.3}° ({} px, {} unsolved)",
            s.mean_deg, s.pixels, s.missing
        );
        assert!(s.mean_deg < 7.5, "{obj}: {}°", s.mean_deg);
        assert!(s.missing * 1000 < s.pixels, "{obj}: {} unsolved", s.missing);
    }
}
