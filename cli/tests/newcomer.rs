//! What a newcomer trips over (issue "What a newcomer trips over"), each reproduced end to end
//! on data the test writes: numbered images sorted as text, the depth preview and curl under a
//! camera, outputs that say what they are, units checked by `eval`, a background integrated
//! with the object, and a memory budget that the run fits in.

#[path = "../../tests/common/mod.rs"]
mod common;

use common::{listing, numbered_dataset, run, sphere_dataset};
use photostereo::synth::write::ImageFormat;
use std::ffi::OsString;
use std::path::{Path, PathBuf};

fn ok(args: &[OsString]) -> (String, String) {
    let a: Vec<&std::ffi::OsStr> = args.iter().map(|a| a.as_os_str()).collect();
    let o = run(&a);
    let (out, err) = (
        String::from_utf8_lossy(&o.stdout).into_owned(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    );
    assert!(o.status.success(), "{args:?}\n{out}\n{err}");
    (out, err)
}

fn args(parts: &[&dyn AsRef<std::ffi::OsStr>]) -> Vec<OsString> {
    parts.iter().map(|p| p.as_ref().to_owned()).collect()
}

fn mean_deg(normals: &Path, gt: &Path, mask: &Path) -> f64 {
    let (out, _) = ok(&args(&[
        &"eval",
        &"--normals",
        &normals,
        &"--gt",
        &gt,
        &"--mask",
        &mask,
    ]));
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    v["mean_deg"].as_f64().unwrap()
}

/// Item 1: with the shell's order and a plain list, the run is refused (`bad_inputs` checks the
/// message); `--image-order natural` gives the normals of the numeric order, and
/// `--image-order given` the wrong pairing the check exists for — far off.
#[test]
fn numbered_images_sorted_as_text_are_put_right_or_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let (dir, images, lights) = numbered_dataset(tmp.path());
    let mut shell = images.clone();
    shell.sort();
    assert_ne!(shell, images);
    let (mask, gt) = (dir.join("mask.png"), dir.join("gt/normal_gt.exr"));
    let run_with = |imgs: &[PathBuf], extra: &[&str], out: &Path| {
        let mut a: Vec<OsString> = imgs.iter().map(|p| p.clone().into_os_string()).collect();
        a.extend(args(&[
            &"--lights",
            &lights,
            &"--mask",
            &mask,
            &"-q",
            &"--integrate",
            &"none",
        ]));
        a.extend(extra.iter().map(OsString::from));
        a.extend(args(&[&"-o", &out]));
        ok(&a);
        mean_deg(&out.join("normal.exr"), &gt, &mask)
    };
    let right = run_with(&images, &[], &tmp.path().join("right"));
    let natural = run_with(
        &shell,
        &["--image-order", "natural"],
        &tmp.path().join("natural"),
    );
    let given = run_with(
        &shell,
        &["--image-order", "given"],
        &tmp.path().join("given"),
    );
    assert!(right < 0.05, "{right}");
    assert!((natural - right).abs() < 1e-9, "{natural} vs {right}");
    assert!(given > 5.0, "the wrong pairing gave only {given}°");
}

/// Items 2 and 6: under a camera the depth preview shows the relief (not one grey level) and
/// the curl is printed in units that show it; `--integrate none` writes no depth files and
/// lists none; every EXR says what it holds; a grey run reports grey in both places.
#[test]
fn outputs_say_what_they_are() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let images = sphere_dataset(&data, ImageFormat::Exr);
    let (lights, mask) = (data.join("lights.json"), data.join("mask.png"));
    let k = tmp.path().join("K.txt");
    std::fs::write(&k, "2000 0 48\n0 2000 48\n0 0 1\n").unwrap();
    let base = |out: &Path, extra: &[&str]| {
        let mut a: Vec<OsString> = images.iter().map(|p| p.clone().into_os_string()).collect();
        a.extend(args(&[&"--lights", &lights, &"--mask", &mask, &"-q"]));
        a.extend(extra.iter().map(OsString::from));
        a.extend(args(&[&"-o", &out]));
        a
    };
    // Under a camera.
    let out = tmp.path().join("camera");
    let k_arg = k.to_string_lossy().into_owned();
    let (stdout, _) = ok(&base(
        &out,
        &["--camera", &k_arg, "--integrate", "masked-ls"],
    ));
    let line = stdout
        .lines()
        .find(|l| l.contains("integrability"))
        .unwrap();
    assert!(
        line.contains("log-depth") && !line.contains("mean |curl| 0.0000"),
        "{line}"
    );
    let png = image::open(out.join("depth.png")).unwrap().to_luma8();
    let m = image::open(&mask).unwrap().to_luma8();
    let inside: Vec<f64> = png
        .pixels()
        .zip(m.pixels())
        .filter(|(_, m)| m.0[0] > 0)
        .map(|(p, _)| f64::from(p.0[0]))
        .collect();
    let mean = inside.iter().sum::<f64>() / inside.len() as f64;
    let sd = (inside.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / inside.len() as f64).sqrt();
    // A lit sphere: shades from dark to bright, as the orthographic preview has.
    assert!(sd > 20.0, "depth.png is flat: sd {sd}");
    let units = |file: &str| {
        photostereo::io::decode::read_exr_text(&out.join(file), "photostereo:units")
            .unwrap()
            .unwrap_or_default()
    };
    assert!(units("depth.exr").contains("optical axis"));
    assert!(units("curl.exr").contains("log-depth"));
    for file in ["normal.exr", "albedo.exr", "residual.exr"] {
        assert!(
            !units(file).contains("Z:") && !units(file).is_empty(),
            "{file}: {}",
            units(file)
        );
    }
    // Without integration: no depth file, none listed.
    let out = tmp.path().join("none");
    let (stdout, _) = ok(&base(&out, &["--integrate", "none"]));
    let files = listing(&out);
    assert!(!files.iter().any(|f| f.starts_with("depth.")), "{files:?}");
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
    let listed: Vec<&str> = report["outputs"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_str().unwrap())
        .collect();
    assert!(
        !listed.iter().any(|f| f.starts_with("depth.")),
        "{listed:?}"
    );
    assert!(!stdout.contains("depth.exr"), "{stdout}");
    // A grey run says grey in the inputs and the configuration.
    assert_eq!(report["inputs"]["color"], "grey");
    assert_eq!(report["config"]["color"], "grey");
}

/// Item 7: `eval` warns when an orthographic height is aligned by median scale (it assumes
/// depths from the camera) — the figures are not a depth error; `integrate` without a mask
/// leaves out a uniform background and says so.
#[test]
fn units_and_domains_are_checked() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let images = sphere_dataset(&data, ImageFormat::Exr);
    let (lights, mask) = (data.join("lights.json"), data.join("mask.png"));
    let out = tmp.path().join("out");
    let mut a: Vec<OsString> = images.iter().map(|p| p.clone().into_os_string()).collect();
    a.extend(args(&[
        &"--lights",
        &lights,
        &"--mask",
        &mask,
        &"-q",
        &"-o",
        &out,
    ]));
    ok(&a);
    let depth = out.join("depth.exr");
    let gt = data.join("gt/depth_gt.exr");
    let gt = if gt.exists() { gt } else { depth.clone() };
    let (stdout, stderr) = ok(&args(&[
        &"eval",
        &"--depth",
        &depth,
        &"--depth-gt",
        &gt,
        &"--mask",
        &mask,
        &"--align",
        &"median-scale",
    ]));
    assert!(
        stderr.contains("orthographic height") && stderr.contains("not a depth error"),
        "{stderr}"
    );
    let v: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    assert_eq!(v["warnings"].as_array().map(Vec::len), Some(1), "{v}");
    // The default alignment of an orthographic height is fine: no warning.
    let (stdout, stderr) = ok(&args(&[
        &"eval",
        &"--depth",
        &depth,
        &"--depth-gt",
        &gt,
        &"--mask",
        &mask,
    ]));
    assert!(!stderr.contains("warning"), "{stderr}");
    assert!(serde_json::from_str::<serde_json::Value>(&stdout).unwrap()["warnings"].is_null());
    // A normal map on a uniform white background (as exported maps have it), integrated without a mask: the background is
    // found from the border, left out, and reported.
    let normals = image::open(out.join("normal.png")).unwrap().to_rgb8();
    let mut painted = normals.clone();
    for p in painted.pixels_mut() {
        if p.0 == [0, 0, 0] {
            p.0 = [255, 255, 255];
        }
    }
    let map = tmp.path().join("on_background.png");
    painted.save(&map).unwrap();
    let z = tmp.path().join("z.exr");
    let (stdout, stderr) = ok(&args(&[&"integrate", &"--normals", &map, &"-o", &z, &"-q"]));
    assert!(stderr.contains("taken as background"), "{stderr}");
    let m = photostereo::io::decode::read_mask(&mask).unwrap();
    assert!(
        stdout.contains(&format!(": {} pixels", m.count())),
        "{stdout}"
    );
}

/// Item 8: a memory budget the run fits in loads the images whole and says so; `--band-rows`
/// still streams.
#[test]
fn a_budget_the_run_fits_in_does_not_stream() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let images = sphere_dataset(&data, ImageFormat::Exr);
    let lights = data.join("lights.json");
    let run_with = |extra: &[&str], out: &Path| {
        let mut a: Vec<OsString> = images.iter().map(|p| p.clone().into_os_string()).collect();
        a.extend(args(&[&"--lights", &lights, &"-q"]));
        a.extend(extra.iter().map(OsString::from));
        a.extend(args(&[&"-o", &out]));
        ok(&a).0
    };
    let stdout = run_with(&["--max-memory", "500M"], &tmp.path().join("a"));
    assert!(stdout.contains("loading the images whole"), "{stdout}");
    assert!(!stdout.contains("streamed"), "{stdout}");
    let stdout = run_with(
        &["--max-memory", "500M", "--band-rows", "16"],
        &tmp.path().join("b"),
    );
    assert!(stdout.contains("streamed"), "{stdout}");
}

/// Without `--max-memory`, a run that may need more than the default budget (2 GiB, or half the
/// available memory) is streamed in row bands instead of loaded whole, and says so: a 2400²
/// sphere under 4 lights, no mask given, whose in-memory plan (with the bilateral integrator
/// `auto` may run, over the whole frame) is about 2.5 GB; its normals are those of the rendered
/// sphere.
#[test]
fn a_large_capture_streams_by_default() {
    use photostereo::capture::lights::Lights;
    use photostereo::eval::demo::synthesize;
    use photostereo::synth::render::RenderOptions;
    use photostereo::synth::scene::{Albedo, Scene};
    use photostereo::synth::write::write_synthetic;
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let lights = Lights::fibonacci(4, 40.0).unwrap();
    let synth = synthesize(
        Scene::sphere(2400, 960.0, Albedo::Constant(0.7)),
        lights.clone(),
        &RenderOptions::default(),
    )
    .unwrap();
    let images: Vec<PathBuf> =
        write_synthetic(&synth.rendering, &lights, &data, ImageFormat::Png16)
            .unwrap()
            .into_iter()
            .filter(|p| p.starts_with(&data) && p.parent() == Some(data.as_path()))
            .filter(|p| {
                p.extension().is_some_and(|e| e == "png")
                    && p.file_name() != Some("mask.png".as_ref())
            })
            .collect();
    assert_eq!(images.len(), 4);
    drop(synth);
    let run_with = |extra: &[&str], out: &Path| {
        let mut a: Vec<OsString> = images.iter().map(|p| p.clone().into_os_string()).collect();
        a.extend(args(&[&"--lights", &data.join("lights.json"), &"-q"]));
        a.extend(extra.iter().map(OsString::from));
        a.extend(args(&[&"-o", &out]));
        ok(&a).0
    };
    let streamed = tmp.path().join("streamed");
    let stdout = run_with(&[], &streamed);
    assert!(
        stdout.contains("streaming the images in row bands"),
        "{stdout}"
    );
    assert!(stdout.contains("streamed"), "{stdout}");
    // Within the default budget: 2 GiB (or half the available memory), more than this run's
    // least.
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(streamed.join("report.json")).unwrap())
            .unwrap();
    let plan = &report["streaming"];
    let budget = plan["max_memory"].as_u64().unwrap();
    assert!(budget <= 2 << 30, "{plan}");
    assert!(plan["finish_bytes"].as_u64().unwrap() <= budget, "{plan}");
    let deg = mean_deg(
        &streamed.join("normal.exr"),
        &data.join("gt/normal_gt.exr"),
        &data.join("mask.png"),
    );
    assert!(deg < 0.05, "streamed normals against the truth: {deg}°");
}

/// Room light left in the images: a relief of dimples and bumps and a bumpy torus on a
/// ground, rendered with an ambient term of 8% of a lamp's light and written as `data-synth
/// --ambient` writes them, with the frame taken with every lamp off (`ambient.exr`). Without that frame the run measures the light in
/// the attached shadows, says how far it bends the normals and names `--ambient`; with it the
/// error falls to within 0.15° of the same scene rendered in a dark room, and the report names
/// the frame.
#[test]
fn room_light_is_measured_and_an_ambient_frame_removes_it() {
    let tmp = tempfile::tempdir().unwrap();
    use photostereo::synth::render::{RenderOptions, render};
    use photostereo::synth::scene::{Albedo, SceneKind};
    let lights = photostereo::capture::lights::Lights::fibonacci(16, 30.0).unwrap();
    for (shape, kind) in [("relief", SceneKind::Relief), ("torus", SceneKind::Torus)] {
        let scene = kind.build(
            128,
            Albedo::Constant(0.7),
            photostereo::synth::reflectance::Material::lambertian(),
        );
        let render = |ambient: f32, dir: &Path| {
            let options = RenderOptions {
                noise_sigma: 0.005,
                ambient,
                seed: 9,
                ..RenderOptions::default()
            };
            let r = render(&scene, &lights, &options).unwrap();
            photostereo::synth::write::write_synthetic(&r, &lights, dir, ImageFormat::Exr).unwrap();
        };
        let (lit, dark) = (
            tmp.path().join(format!("{shape}-lit")),
            tmp.path().join(format!("{shape}-dark")),
        );
        render(0.08, &lit);
        render(0.0, &dark);
        assert!(lit.join("ambient.exr").is_file() && !dark.join("ambient.exr").exists());
        let solve = |dir: &Path, extra: &[&dyn AsRef<std::ffi::OsStr>], out: &Path| {
            let mut a: Vec<OsString> = (0..16)
                .map(|k| dir.join(format!("img_{k:03}.exr")).into_os_string())
                .collect();
            a.extend(args(&[
                &"--lights",
                &dir.join("lights.json"),
                &"--mask",
                &dir.join("mask.png"),
                &"--integrate",
                &"none",
                &"-q",
                &"-o",
                &out,
            ]));
            a.extend(args(extra));
            let (_, err) = ok(&a);
            let e = mean_deg(
                &out.join("normal.exr"),
                &dir.join("gt/normal_gt.exr"),
                &dir.join("mask.png"),
            );
            let report: serde_json::Value =
                serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap())
                    .unwrap();
            (e, err, report)
        };
        let (base, base_err, _) = solve(&dark, &[], &tmp.path().join(format!("{shape}-o0")));
        let (left, left_err, left_report) =
            solve(&lit, &[], &tmp.path().join(format!("{shape}-o1")));
        let (removed, removed_err, removed_report) = solve(
            &lit,
            &[&"--ambient", &lit.join("ambient.exr")],
            &tmp.path().join(format!("{shape}-o2")),
        );
        println!(
            "{shape}: dark room {base:.3}°, room light left in {left:.3}° ({}), ambient frame subtracted {removed:.3}°",
            left_report["model"]["shadow_light"]
        );
        let warned = |err: &str| err.contains("attached shadow");
        assert!(
            !warned(&base_err) && !warned(&removed_err),
            "{base_err}\n{removed_err}"
        );
        assert!(
            warned(&left_err) && left_err.contains("(--ambient FILE)"),
            "{left_err}"
        );
        let level = left_report["model"]["shadow_light"][0]["level"]
            .as_f64()
            .unwrap();
        assert!((0.065..0.082).contains(&level), "{level}");
        assert!(left > base + 1.0, "{left} vs {base}");
        assert!(removed < base + 0.15, "{removed} vs {base}");
        assert_eq!(
            removed_report["inputs"]["ambient"].as_str().map(Path::new),
            Some(lit.join("ambient.exr").as_path())
        );
        assert!(left_report["inputs"].get("ambient").is_none());
    }
}

/// A row of the lights file turned by 10° (a typo, a lamp moved after the calibration) gives
/// normals that look fine; the run names the image whose brightness disagrees with its light,
/// with the direction the other images give it, and `report.json` holds the check. Under the
/// right lights nothing is named.
#[test]
fn a_wrong_row_of_the_lights_file_is_named() {
    use nalgebra::{Rotation3, Unit, Vector3};
    use photostereo::capture::lights::{Light, Lights};
    let tmp = tempfile::tempdir().unwrap();
    let (dir, images, lights) = numbered_dataset(tmp.path());
    let mask = dir.join("mask.png");
    let truth = Lights::fibonacci(10, 30.0).unwrap().directions();
    let mut turned = truth.clone();
    let axis = Unit::new_normalize(turned[6].cross(&Vector3::z()));
    turned[6] = Rotation3::from_axis_angle(&axis, 10f64.to_radians()) * turned[6];
    let wrong = dir.join("wrong.txt");
    common::write_plain_lights(
        &wrong,
        &Lights::new(turned.into_iter().map(Light::new).collect()).unwrap(),
    );
    let run_with = |lights: &Path, out: &Path| {
        let mut a = common::main_args(&images, lights, &["--integrate", "none"], out);
        a.extend(args(&[&"--mask", &mask]));
        let (_, err) = ok(&a);
        let report: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap())
                .unwrap();
        (err, report["model"]["light_agreement"][0].clone())
    };
    let (err, right) = run_with(&lights, &tmp.path().join("right"));
    assert!(!err.contains("disagrees with the light given"), "{err}");
    assert_eq!(right["disagreeing"], serde_json::json!([]), "{right}");
    let (err, check) = run_with(&wrong, &tmp.path().join("wrong"));
    assert!(
        err.contains("the brightness of 1 image(s) (numbered from 1")
            && err.contains(": 7 (")
            && err.contains("calibrate --from-object"),
        "{err}"
    );
    assert_eq!(check["disagreeing"], serde_json::json!([6]), "{check}");
    let d = &check["lights"][6]["direction"];
    let found = Vector3::new(
        d[0].as_f64().unwrap(),
        d[1].as_f64().unwrap(),
        d[2].as_f64().unwrap(),
    );
    let off = found.dot(&truth[6]).clamp(-1.0, 1.0).acos().to_degrees();
    println!(
        "light 7 turned by 10°: {:.2}° from the given, {off:.2}° from the truth",
        check["lights"][6]["disagreement_deg"].as_f64().unwrap()
    );
    assert!(off < 2.5, "{check}");
}
