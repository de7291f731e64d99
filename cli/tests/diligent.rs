//! Conventions proven on real data: plain least squares on DiLiGenT reproduces the published
//! baseline (mean angular error 8.41° on cat, 8.39° on bear), end to end through the CLI.

#[path = "../../tests/common/mod.rs"]
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

/// The default estimator (`auto`) with one setting for both objects: mean angular error at most
/// 5.5° (the least-squares baseline is 8.41° / 8.39°), every pixel solved, and on bear the
/// intensity recalibration finds the images whose listed intensities are wrong (images 1–19 are
/// 12–31% brighter than `light_intensities.txt` says; the literature drops bear's first 20
/// images for this reason) while leaving the other 77 within 10%.
#[test]
fn diligent_default_method_meets_the_robust_target() {
    use photostereo::capture::dataset::Capture;
    use photostereo::capture::stack::LoadOptions;
    use photostereo::io::decode::read_normal_map;
    use photostereo::progress::Silent;
    use photostereo::run::pipeline::{Config, reconstruct};
    for obj in ["cat", "bear"] {
        let dir = require_shared!(format!("diligent/{obj}PNG"));
        let capture = Capture::from_diligent(&dir, &LoadOptions::default(), &Silent).unwrap();
        let config = Config {
            integration: None,
            ..Config::default()
        };
        let recon = reconstruct(&capture, &config, &Silent).unwrap();
        let gt = read_normal_map(&dir.join("normal_gt.exr")).unwrap();
        let s = photostereo::eval::metrics::angular_errors(&recon.maps.normals, &gt, &capture.mask)
            .unwrap();
        println!(
            "{obj}: auto {:.3}° mean, {:.3}° median, {:.1}% robust ({} px, {} unsolved)",
            s.mean_deg,
            s.median_deg,
            100.0 * recon.model.robust_fraction,
            s.pixels,
            s.missing
        );
        // Measured: cat 5.31°, bear 4.27°.
        assert!(s.mean_deg <= 5.5, "{obj}: {}°", s.mean_deg);
        assert_eq!(s.missing, 0, "{obj}: unsolved pixels");
        let gains = &recon.model.gains[0];
        let off: Vec<usize> = (0..gains.len())
            .filter(|&k| (gains[k] - 1.0).abs() > 0.1)
            .collect();
        println!("{obj}: images with gains off by > 10%: {off:?}");
        if obj == "bear" {
            // Measured: 18 of the 19 beyond 10% (image 17 is 12% too bright in the data and
            // gets 0.91), all 19 below 0.95, none of the other 77 beyond 10%.
            assert!(off.iter().all(|&k| k < 19) && off.len() >= 17, "{gains:?}");
            assert!(gains[..19].iter().all(|g| *g < 0.95), "{gains:?}");
        } else {
            assert!(off.is_empty(), "{gains:?}");
        }
    }
}

/// Every estimator beats the least-squares baseline on both objects, and the rejecting ones
/// beat it by at least a degree.
#[test]
fn diligent_every_estimator_beats_the_baseline() {
    use photostereo::capture::dataset::Capture;
    use photostereo::capture::stack::LoadOptions;
    use photostereo::io::decode::read_normal_map;
    use photostereo::progress::Silent;
    use photostereo::ps::solve::{Method, SolveOptions};
    use photostereo::run::pipeline::{Config, reconstruct};
    for obj in ["cat", "bear"] {
        let dir = require_shared!(format!("diligent/{obj}PNG"));
        let capture = Capture::from_diligent(&dir, &LoadOptions::default(), &Silent).unwrap();
        let gt = read_normal_map(&dir.join("normal_gt.exr")).unwrap();
        for method in [
            Method::Threshold,
            Method::Trimmed,
            Method::Huber,
            Method::Tukey,
            Method::L1,
            Method::Specular,
        ] {
            let config = Config {
                solve: SolveOptions::with_method(method),
                integration: None,
                ..Config::default()
            };
            let recon = reconstruct(&capture, &config, &Silent).unwrap();
            let s =
                photostereo::eval::metrics::angular_errors(&recon.maps.normals, &gt, &capture.mask)
                    .unwrap();
            println!("{obj} {}: {:.3}°", method.name(), s.mean_deg);
            assert!(
                s.mean_deg < 8.39 - 0.7,
                "{obj} {}: {}°",
                method.name(),
                s.mean_deg
            );
        }
    }
}

/// A 16-bit PNG normal map (n = v/65535·2 − 1) decodes to the same normals as the EXR ground
/// truth: the integration set's `normal_map.png` equals DiLiGenT's `Normal_gt` inside the mask.
#[test]
fn png_normal_map_decodes_like_the_exr_ground_truth() {
    use photostereo::io::decode::{read_mask, read_normal_map};
    let png = require_shared!("integration/cat/normal_map.png");
    let exr = require_shared!("diligent/catPNG/normal_gt.exr");
    let mask = read_mask(&png.with_file_name("mask.png")).unwrap();
    let a = read_normal_map(&png).unwrap();
    let b = read_normal_map(&exr).unwrap();
    let s = photostereo::eval::metrics::angular_errors(&a, &b, &mask).unwrap();
    println!(
        "normal_map.png vs normal_gt.exr: mean {:.5}°, p95 {:.5}°",
        s.mean_deg, s.p95_deg
    );
    assert_eq!(s.pixels, mask.count());
    assert!(s.mean_deg < 0.01 && s.p95_deg < 0.02, "{s:?}");
}
