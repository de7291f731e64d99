//! End-to-end tests of the `data-synth` binary: render data sets into temporary folders, load
//! them back with the photostereo library and reconstruct them.

use photostereo::capture::dataset::Capture;
use photostereo::capture::lights::Lights;
use photostereo::capture::stack::LoadOptions;
use photostereo::eval::metrics::{AngularErrorStats, angular_errors};
use photostereo::io::decode::{read_image, read_normal_map};
use photostereo::progress::Silent;
use photostereo::ps::solve::{Method, SolveOptions};
use photostereo::run::pipeline::{Config, reconstruct};
use photostereo::synth::scene::SceneKind;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// Every `--brdf` value.
const BRDFS: [&str; 7] = [
    "lambertian",
    "oren-nayar",
    "phong",
    "blinn-phong",
    "torrance-sparrow",
    "ward",
    "mirror",
];

/// Runs `data-synth` with `args`.
fn data_synth(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_data-synth"))
        .args(args)
        .output()
        .expect("data-synth runs")
}

/// Runs `data-synth` with `args` writing to `dir`, asserts that it succeeded with a one-line
/// summary, and returns the summary and stderr (warnings).
fn synth_ok(args: &[&str], dir: &Path) -> (String, String) {
    let mut all = args.to_vec();
    let dir = dir.to_str().expect("UTF-8 temp path");
    all.extend(["-o", dir]);
    let out = data_synth(&all);
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(out.status.success(), "data-synth {all:?} failed: {stderr}");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.starts_with("wrote "), "summary: {stdout}");
    assert_eq!(stdout.lines().count(), 1, "summary: {stdout}");
    (stdout.trim_end().to_owned(), stderr)
}

/// Runs `data-synth` with `args` writing to a fresh folder, asserts that it failed with status 1,
/// an `error: ` naming `flag`, and wrote nothing.
fn synth_fails(args: &[&str], flag: &str) {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("scene");
    let mut all = args.to_vec();
    all.extend(["-o", dir.to_str().unwrap()]);
    let out = data_synth(&all);
    assert_eq!(out.status.code(), Some(1), "data-synth {all:?}");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.starts_with("error: ") && stderr.contains(flag),
        "data-synth {all:?}: {stderr}"
    );
    assert!(
        !dir.exists(),
        "data-synth {all:?} created the output folder"
    );
    assert_eq!(std::fs::read_dir(tmp.path()).unwrap().count(), 0);
}

/// The `img_NNN.ext` files of a data set of `count` images.
fn image_paths(dir: &Path, count: usize, ext: &str) -> Vec<PathBuf> {
    (0..count)
        .map(|k| dir.join(format!("img_{k:03}.{ext}")))
        .collect()
}

/// Loads a written data set as the command line would, reconstructs it with the default
/// configuration, and measures the normals against `normal_gt.exr` inside `mask.png`.
fn reconstruction_error(dir: &Path, count: usize, ext: &str) -> AngularErrorStats {
    let images = image_paths(dir, count, ext);
    let mask = dir.join("mask.png");
    let capture = Capture::from_files(
        &images,
        &dir.join("lights.json"),
        Some(&mask),
        &LoadOptions::default(),
        &Silent,
    )
    .expect("data set loads");
    // The threshold solver is pinned: these tests measure the renderer, and the robust default
    // would hide a wrong specular lobe (tests/robust_methods.rs measures that solver).
    let config = Config {
        solve: SolveOptions::with_method(Method::Threshold),
        ..Config::default()
    };
    let recon = reconstruct(&capture, &config, &Silent).expect("reconstructs");
    let gt = read_normal_map(&dir.join("gt/normal_gt.exr")).expect("normal map reads");
    let stats = angular_errors(&recon.maps.normals, &gt, &capture.mask).expect("comparable");
    assert_eq!(stats.missing, 0, "unsolved pixels: {stats:?}");
    stats
}

/// Asserts that a data set of `count` images has every file `write_synthetic` writes.
fn assert_complete(dir: &Path, count: usize, ext: &str) {
    let mut expected: Vec<PathBuf> = image_paths(dir, count, ext);
    let last = format!("gt/shadow_{:03}.png", count - 1);
    for name in [
        "lights.json",
        "mask.png",
        "gt/normal_gt.exr",
        "gt/depth_gt.exr",
        "gt/albedo_gt.exr",
        "gt/shadow_000.png",
        &last,
    ] {
        expected.push(dir.join(name));
    }
    for f in &expected {
        assert!(f.is_file(), "missing {}", f.display());
    }
    assert!(!dir.join(format!("img_{count:03}.{ext}")).exists());
    let lights = Lights::from_file(&dir.join("lights.json")).expect("lights.json reads");
    assert_eq!(lights.len(), count);
}

/// (1) `--help` lists every shape (the library's scene names) and every BRDF.
#[test]
fn help_lists_every_shape_and_brdf() {
    let out = data_synth(&["--help"]);
    assert!(out.status.success());
    let help = String::from_utf8_lossy(&out.stdout);
    for kind in SceneKind::ALL {
        assert!(
            help.contains(&format!("- {}:", kind.name())),
            "{}",
            kind.name()
        );
    }
    for brdf in BRDFS {
        assert!(help.contains(&format!("- {brdf}:")), "{brdf}");
    }
}

/// (2) Every shape renders and writes its files; the noiseless Lambertian sphere reconstructs to
/// float precision.
#[test]
fn every_shape_renders_and_the_sphere_reconstructs_exactly() {
    let tmp = tempfile::tempdir().unwrap();
    for kind in SceneKind::ALL {
        let dir = tmp.path().join(kind.name());
        let mut args = vec!["--shape", kind.name(), "--format", "exr"];
        // The demo scene has a fixed size and refuses --size.
        if kind != SceneKind::Demo {
            args.extend(["--size", "48"]);
        }
        synth_ok(&args, &dir);
        assert_complete(&dir, 12, "exr");
        let img = read_image(&dir.join("img_000.exr")).unwrap();
        let expect = if kind == SceneKind::Demo {
            (320, 240)
        } else {
            (48, 48)
        };
        assert_eq!(
            (img.width, img.height, img.channels),
            (expect.0, expect.1, 1)
        );
        assert!(
            img.data.iter().any(|v| *v > 0.0),
            "{}: black image",
            kind.name()
        );
    }
    let stats = reconstruction_error(&tmp.path().join("sphere"), 12, "exr");
    // Measured 4.8e-6° mean (float rounding only); anything wrong in the images, the lights or
    // their pairing shows up as degrees.
    assert!(stats.mean_deg < 0.05, "{stats:?}");
}

/// (3) A Blinn–Phong sphere: the specular highlights violate the Lambertian model, so the
/// default solver's error is measurably larger than the Lambertian sphere's, but bounded.
#[test]
fn blinn_phong_sphere_is_worse_than_lambertian_but_bounded() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("scene");
    let (summary, stderr) = synth_ok(
        &[
            "--shape",
            "sphere",
            "--size",
            "128",
            "--brdf",
            "blinn-phong",
            "--specular",
            "0.5",
            "--shininess",
            "40",
        ],
        &dir,
    );
    assert!(stderr.is_empty(), "unexpected warnings: {stderr}");
    assert!(
        summary.contains(
            "of sphere, blinn-phong (k_s 0.5, n 40) over lambertian, 12 fibonacci lights above 30°"
        ),
        "{summary}"
    );
    let stats = reconstruction_error(&dir, 12, "exr");
    // Measured: mean 11.51°, median 3.57° (the same at --size 256: 11.49°, 3.51°), against
    // 4.8e-6° for the Lambertian sphere: the default threshold solver keeps the highlights.
    // What broken renderers would give, measured with the flags changed: no specular lobe
    // (k_s 0) 0°, 0°; k_s 0.25 6.8°, 1.9°; k_s 1 18.0°, 6.6°; a lobe 4× wider (n 10) 9.8°,
    // 10.6°; a narrower one (n 80) 12.3°, 0.34°. The mean catches a mis-scaled lobe, the
    // median a lobe of the wrong width.
    assert!(stats.mean_deg > 8.0 && stats.mean_deg < 15.0, "{stats:?}");
    assert!(
        stats.median_deg > 2.5 && stats.median_deg < 5.0,
        "{stats:?}"
    );
}

/// 16-bit PNG with noise: loads back and reconstructs within the noise's error.
#[test]
fn png16_with_noise_round_trips() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("scene");
    synth_ok(
        &[
            "--shape", "sphere", "--format", "png16", "--noise", "0.005", "--seed", "7",
        ],
        &dir,
    );
    assert_complete(&dir, 12, "png");
    let stats = reconstruction_error(&dir, 12, "png");
    // Measured 0.367° mean (0.367–0.369° over seeds 1–3; 16-bit quantisation alone gives
    // 0.0003°). The bound, tighter than the 1.5° one could tolerate, fails if the noise were
    // ~1.4× stronger than asked (σ = 0.008 measured 0.587°) or the lights were wrong.
    assert!(stats.mean_deg < 0.5, "{stats:?}");
}

/// (4) 8-bit sRGB PNG: the loader decodes sRGB by default, and 8-bit quantisation costs a
/// little accuracy.
#[test]
fn png8_srgb_round_trips() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("scene");
    let (_, stderr) = synth_ok(&["--shape", "sphere", "--format", "png8", "--srgb"], &dir);
    assert!(stderr.is_empty(), "unexpected warnings: {stderr}");
    assert_complete(&dir, 12, "png");
    let stats = reconstruction_error(&dir, 12, "png");
    // Measured 0.106° mean, 0.21° p95 (8-bit quantisation; the same at --size 128). Linear
    // 8-bit PNGs read back as sRGB give 16.2°; 16-bit PNGs 0.0003°: the lower bound checks
    // that the files really are 8-bit.
    assert!(stats.mean_deg > 0.02 && stats.mean_deg < 0.3, "{stats:?}");
}

/// (5) `--color`: RGB EXR images whose channels follow the diffuse colour.
#[test]
fn color_renders_rgb_in_the_diffuse_colour() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("scene");
    synth_ok(
        &[
            "--shape",
            "sphere",
            "--size",
            "48",
            "--color",
            "--diffuse-color",
            "1,0.5,0.25",
        ],
        &dir,
    );
    for path in image_paths(&dir, 12, "exr") {
        let img = read_image(&path).unwrap();
        assert_eq!(img.channels, 3, "{}", path.display());
        // The brightest pixel is lit; its G/R and B/R are the colour's.
        let px = img
            .data
            .chunks_exact(3)
            .max_by(|a, b| a[0].total_cmp(&b[0]))
            .unwrap();
        assert!(px[0] > 0.3, "{}: {px:?}", path.display());
        assert!((px[1] / px[0] - 0.5).abs() < 1e-5, "{px:?}");
        assert!((px[2] / px[0] - 0.25).abs() < 1e-5, "{px:?}");
    }
    // Mixed to grey by the loader, the colour is a constant factor: exact normals still
    // (measured 4.8e-6° mean).
    let stats = reconstruction_error(&dir, 12, "exr");
    assert!(stats.mean_deg < 0.05, "{stats:?}");
}

/// (6) Light sets: DiLiGenT's 96 lights; a degenerate coplanar set is written with a warning;
/// --lights is refused with the fixed-size DiLiGenT set.
#[test]
fn light_sets() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("diligent");
    synth_ok(&["--light-set", "diligent", "--size", "32"], &dir);
    assert_complete(&dir, 96, "exr");

    let dir = tmp.path().join("coplanar");
    let (_, stderr) = synth_ok(
        &["--light-set", "coplanar", "--tilt", "0", "--size", "32"],
        &dir,
    );
    assert!(
        stderr.starts_with("warning: ") && stderr.contains("condition number"),
        "{stderr}"
    );
    assert_complete(&dir, 12, "exr");
    let lights = Lights::from_file(&dir.join("lights.json")).unwrap();
    assert!(lights.condition_number() > 1e8);

    synth_fails(&["--lights", "5", "--light-set", "diligent"], "--lights");
}

/// (7) The same seed gives byte-identical image files; another seed does not.
#[test]
fn same_seed_gives_identical_images() {
    let tmp = tempfile::tempdir().unwrap();
    let args = [
        "--shape",
        "bumps",
        "--size",
        "64",
        "--noise",
        "0.01",
        "--light-set",
        "cone",
    ];
    let run = |name: &str, seed: &str| {
        let dir = tmp.path().join(name);
        let mut all = args.to_vec();
        all.extend(["--seed", seed]);
        synth_ok(&all, &dir);
        let mut files: Vec<Vec<u8>> = image_paths(&dir, 12, "exr")
            .iter()
            .map(|p| std::fs::read(p).unwrap())
            .collect();
        files.push(std::fs::read(dir.join("lights.json")).unwrap());
        files
    };
    let a = run("a", "5");
    let b = run("b", "5");
    let c = run("c", "6");
    assert!(a == b, "the same seed gave different files");
    // The seed does reach the noise and the random light set.
    assert!(a[0] != c[0], "different seeds gave identical images");
    assert!(a[12] != c[12], "different seeds gave identical cone lights");
}

/// (7) An invalid flag exits with status 1, names the flag, and creates nothing.
#[test]
fn bad_arguments_fail_and_write_nothing() {
    for (args, flag) in [
        (&["--lights", "2"][..], "--lights"),
        (&["--brdf", "ward", "--shininess", "10"], "--shininess"),
        (&["--srgb", "--format", "exr"], "--srgb"),
        (&["--brdf", "phong", "--specular", "1.5"], "--specular"),
        (&["--brdf", "torrance-sparrow", "--f0", "2"], "--f0"),
        (&["--diffuse-color", "1,0.5"], "--diffuse-color"),
        (&["--tilt", "3"], "--tilt"),
        // clap's own errors exit with 1 too.
        (&["--brdf", "velvet"], "--brdf"),
        (&["--lights", "many"], "--lights"),
    ] {
        synth_fails(args, flag);
    }
}

/// (8) Interreflections: a groove rendered with bounces is brighter inside than without them,
/// in every image, while the plane beside it, which sees nothing of the surface, is unchanged;
/// area lights write images too.
#[test]
fn bounces_brighten_the_inside_of_a_groove() {
    let tmp = tempfile::tempdir().unwrap();
    let size = 48;
    let common = ["--shape", "groove", "--size", "48", "--lights", "8"];
    let render = |name: &str, extra: &[&str]| {
        let dir = tmp.path().join(name);
        let mut args = common.to_vec();
        args.extend_from_slice(extra);
        let (summary, _) = synth_ok(&args, &dir);
        let images: Vec<Vec<f32>> = image_paths(&dir, 8, "exr")
            .iter()
            .map(|p| read_image(p).unwrap().data)
            .collect();
        (summary, images)
    };
    let (_, direct) = render("direct", &[]);
    let (summary, bounced) = render("bounced", &["--bounces", "2", "--bounce-samples", "32"]);
    assert!(
        summary.contains("2 bounces of interreflection (32 rays)"),
        "{summary}"
    );
    // The groove spans |x| < 0.3·size around the centre.
    let x_of = |i: usize| (i % size) as f64 - (size as f64 - 1.0) / 2.0;
    for (k, (d, b)) in direct.iter().zip(&bounced).enumerate() {
        let (mut inside_d, mut inside_b) = (0.0, 0.0);
        for (i, (vd, vb)) in d.iter().zip(b).enumerate() {
            let x = x_of(i).abs();
            if x < 0.3 * size as f64 - 1.0 {
                inside_d += f64::from(*vd);
                inside_b += f64::from(*vb);
                assert!(vb >= vd, "image {k} pixel {i}: {vb} < {vd}");
            } else if x > 0.3 * size as f64 + 1.0 {
                assert_eq!(vb, vd, "image {k} pixel {i}: the plane changed");
            }
        }
        // A 90° groove's faces exchange F = 1 − √2/2 ≈ 0.29 of their light: at albedo 0.7
        // two bounces add ρF + (ρF)² ≈ 25% of the direct light whatever its direction (both
        // faces are planar), less what escapes at the groove's ends: measured +22.3% in every
        // image. Without the second bounce it would be ≈ +20%, without interreflections 0.
        assert!(
            inside_b > 1.18 * inside_d && inside_b < 1.27 * inside_d,
            "image {k}: {inside_b} vs {inside_d} without bounces"
        );
    }
    let (summary, soft) = render(
        "soft",
        &["--area-light-samples", "16", "--light-radius", "5"],
    );
    assert!(
        summary.contains("area lights 5° in radius (16 samples)"),
        "{summary}"
    );
    assert_ne!(soft, direct);
}

/// --near-distance renders an LED rig: lights.json holds each LED's position and profile, K.txt
/// the camera, and the near-field shading differs from distant lights'; flags that do not apply
/// to the rig are refused.
#[test]
fn near_distance_writes_an_led_rig_with_its_camera() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("rig");
    let (summary, _) = synth_ok(
        &[
            "--size",
            "48",
            "--near-distance",
            "2",
            "--led-mu",
            "1",
            "--lights",
            "8",
        ],
        &dir,
    );
    assert!(summary.contains("8 LEDs at 2 scene widths"), "{summary}");
    assert!(summary.contains("K.txt"), "{summary}");
    let k = photostereo::camera::Intrinsics::from_file(&dir.join("K.txt")).unwrap();
    assert_eq!((k.fx, k.cx), (96.0, 23.5));
    let lights = photostereo::capture::lights::Lights::from_file(&dir.join("lights.json")).unwrap();
    assert_eq!(lights.positioned(), 8);
    assert!(
        lights
            .lights()
            .iter()
            .all(|l| l.anisotropy.is_some_and(|a| a.mu == 1.0))
    );
    // Every LED is 96 units from the scene's centre, 96 units in front of the camera.
    for l in lights.lights() {
        let p = l.position.unwrap();
        assert!(
            ((p - photostereo::nalgebra::Vector3::new(0.0, 0.0, -96.0)).norm() - 96.0).abs() < 1e-9
        );
    }
    synth_fails(
        &["--near-distance", "2", "--elevation", "40"],
        "--elevation",
    );
    synth_fails(&["--near-distance", "0.5"], "--near-distance");
    synth_fails(&["--led-mu", "1"], "--near-distance");
}
