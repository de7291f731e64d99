//! The command line end to end: data sets written to disk, read back, reconstructed, written,
//! evaluated — and bad input answered with a clear error and no partial output.

#[path = "../../tests/common/mod.rs"]
mod common;

use common::{listing, os, run, sphere_dataset};
use photostereo::capture::lights::Lights;
use photostereo::eval::demo::synthesize;
use photostereo::synth::render::RenderOptions;
use photostereo::synth::scene::{Albedo, Scene};
use photostereo::synth::write::{ImageFormat, write_synthetic};
use std::path::{Path, PathBuf};

/// Mean angular error of `out/normal.exr` against `gt` via the `eval` subcommand.
fn eval(out: &Path, gt: &Path, mask: &Path) -> serde_json::Value {
    let o = run(&[
        os("eval"),
        os("--normals"),
        out.join("normal.exr").as_os_str(),
        os("--gt"),
        gt.as_os_str(),
        os("--mask"),
        mask.as_os_str(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    serde_json::from_slice(&o.stdout).unwrap()
}

#[test]
fn images_with_json_lights_given_in_shuffled_order() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let mut images = sphere_dataset(&data, ImageFormat::Exr);
    // The lights file names each image: command-line order does not matter.
    images.reverse();
    images.swap(2, 7);
    let out = tmp.path().join("out");
    let mut args: Vec<&std::ffi::OsStr> = images.iter().map(|p| p.as_os_str()).collect();
    let (lights, mask) = (data.join("lights.json"), data.join("mask.png"));
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
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(stdout.contains("integrability"), "{stdout}");
    for f in photostereo::run::pipeline::OUTPUT_FILES {
        assert!(out.join(f).is_file(), "missing {f}");
    }
    // No temporary files remain (the set's list of its files is the one hidden name).
    assert!(
        listing(&out)
            .iter()
            .all(|f| !f.starts_with('.') || f == photostereo::io::output::MANIFEST),
        "{:?}",
        listing(&out)
    );
    let e = eval(&out, &data.join("gt/normal_gt.exr"), &mask);
    assert!(e["mean_deg"].as_f64().unwrap() < 0.05, "{e}");
    // The report carries counts, integrability and timings.
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
    let masked = report["pixels"]["masked"].as_u64().unwrap();
    assert_eq!(masked, report["pixels"]["solved"].as_u64().unwrap());
    assert!(masked > 4000);
    // Exact normals are integrable: the curl vanishes except at the grazing rim.
    assert!(report["integrability"]["median_abs_curl"].as_f64().unwrap() < 1e-3);
    assert!(report["timings_s"]["solve"].as_f64().unwrap() >= 0.0);
    assert_eq!(report["inputs"]["count"], 10);
    // Outside the mask every EXR holds NaN; inside, unit normals.
    let n = photostereo::io::decode::read_image(&out.join("normal.exr")).unwrap();
    let m = photostereo::io::decode::read_mask(&mask).unwrap();
    for (px, inside) in n.data.chunks_exact(3).zip(m.data()) {
        if *inside {
            let len = (px[0] * px[0] + px[1] * px[1] + px[2] * px[2]).sqrt();
            assert!((len - 1.0).abs() < 1e-5);
        } else {
            assert!(px.iter().all(|v| v.is_nan()));
        }
    }
    let d = photostereo::io::decode::read_image(&out.join("depth.exr")).unwrap();
    assert_eq!(d.channels, 1);
    assert_eq!(d.data.iter().filter(|v| v.is_finite()).count(), m.count());
}

#[test]
fn text_lights_and_16_bit_png_give_the_same_normals() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let images = sphere_dataset(&data, ImageFormat::Png16);
    // Plain `x y z` lines in image order, with the optional count line.
    let lights = Lights::fibonacci(10, 30.0).unwrap();
    let mut txt = format!("{}\n", lights.len());
    for d in lights.directions() {
        txt += &format!("{} {} {}\n", d.x, d.y, d.z);
    }
    let lights_txt = tmp.path().join("lights.txt");
    std::fs::write(&lights_txt, txt).unwrap();
    let out = tmp.path().join("out");
    let mask = data.join("mask.png");
    let mut args: Vec<&std::ffi::OsStr> = images.iter().map(|p| p.as_os_str()).collect();
    args.extend([
        os("--lights"),
        lights_txt.as_os_str(),
        os("--mask"),
        mask.as_os_str(),
        os("-q"),
        os("-o"),
        out.as_os_str(),
    ]);
    let o = run(&args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    // 16-bit quantisation (step 1.5e-5) costs well under a hundredth of a degree here.
    let e = eval(&out, &data.join("gt/normal_gt.exr"), &mask);
    assert!(e["mean_deg"].as_f64().unwrap() < 0.02, "{e}");
}

/// A folder in the DiLiGenT layout with per-channel light intensities, written as 16-bit RGB
/// PNG: intensities must be divided out per channel for the normals and albedo to come out.
fn diligent_like(dir: &Path) -> PathBuf {
    std::fs::create_dir_all(dir).unwrap();
    let scene = Scene::sphere(80, 34.0, Albedo::Constant(0.5));
    let lights = Lights::fibonacci(8, 35.0).unwrap();
    let synth = synthesize(scene, lights.clone(), &RenderOptions::default()).unwrap();
    let (w, h) = (80u32, 80u32);
    let mut names = String::new();
    let mut dirs = String::new();
    let mut intens = String::new();
    for (k, planes) in synth.rendering.images.iter().enumerate() {
        let img = &planes[0];
        // Colour light: the camera sees E_c·ρ·(n·l) in channel c.
        let e = [0.9, 0.6 + 0.05 * k as f32, 0.4];
        let mut rgb = Vec::with_capacity(img.len() * 3);
        for v in img.data() {
            for ec in e {
                rgb.push((v * ec).clamp(0.0, 1.0) * 65535.0);
            }
        }
        let buf: image::ImageBuffer<image::Rgb<u16>, Vec<u16>> =
            image::ImageBuffer::from_raw(w, h, rgb.iter().map(|v| v.round() as u16).collect())
                .unwrap();
        let name = format!("{:03}.png", k + 1);
        buf.save(dir.join(&name)).unwrap();
        names += &format!("{name}\n");
        let d = lights.directions()[k];
        dirs += &format!("{} {} {}\n", d.x, d.y, d.z);
        intens += &format!("{} {} {}\n", e[0], e[1], e[2]);
    }
    std::fs::write(dir.join("filenames.txt"), names).unwrap();
    std::fs::write(dir.join("light_directions.txt"), dirs).unwrap();
    std::fs::write(dir.join("light_intensities.txt"), intens).unwrap();
    let mask: Vec<u8> = synth
        .truth
        .mask
        .data()
        .iter()
        .map(|m| if *m { 255 } else { 0 })
        .collect();
    image::GrayImage::from_raw(w, h, mask)
        .unwrap()
        .save(dir.join("mask.png"))
        .unwrap();
    let (nx, ny, nz) = (
        synth.truth.normals.map(|n| n.x),
        synth.truth.normals.map(|n| n.y),
        synth.truth.normals.map(|n| n.z),
    );
    photostereo::io::output::write_exr(
        &dir.join("normal_gt.exr"),
        80,
        80,
        &[("R", nx.data()), ("G", ny.data()), ("B", nz.data())],
        &[],
    )
    .unwrap();
    dir.to_path_buf()
}

#[test]
fn diligent_layout_folder_with_colour_intensities() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = diligent_like(&tmp.path().join("objPNG"));
    for color in ["grey", "shared", "per-channel"] {
        let out = tmp.path().join(format!("out-{color}"));
        let o = run(&[
            dir.as_os_str(),
            os("--color"),
            os(color),
            os("-q"),
            os("-o"),
            out.as_os_str(),
        ]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let e = eval(&out, &dir.join("normal_gt.exr"), &dir.join("mask.png"));
        assert!(e["mean_deg"].as_f64().unwrap() < 0.05, "{color}: {e}");
        // Albedo: 0.5 in every channel once intensities are divided out.
        let a = photostereo::io::decode::read_image(&out.join("albedo.exr")).unwrap();
        assert_eq!(a.channels, if color == "grey" { 1 } else { 3 });
        let finite: Vec<f32> = a.data.iter().copied().filter(|v| v.is_finite()).collect();
        let mean = finite.iter().sum::<f32>() / finite.len() as f32;
        assert!((mean - 0.5).abs() < 1e-3, "{color}: mean albedo {mean}");
    }
}

/// `--mask` on a DiLiGenT folder replaces the folder's mask, and the images are read for the
/// rows it spans (here every row, where the folder's mask covers only the sphere's).
#[test]
fn mask_option_replaces_a_folder_mask() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = diligent_like(&tmp.path().join("objPNG"));
    let wide = tmp.path().join("wide.png");
    image::GrayImage::from_pixel(80, 80, image::Luma([255u8]))
        .save(&wide)
        .unwrap();
    let out = tmp.path().join("out");
    let o = run(&[
        dir.as_os_str(),
        os("--mask"),
        wide.as_os_str(),
        os("--integrate"),
        os("none"),
        os("-q"),
        os("-o"),
        out.as_os_str(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
    assert_eq!(report["pixels"]["masked"], 6400, "{}", report["pixels"]);
    let e = eval(&out, &dir.join("normal_gt.exr"), &dir.join("mask.png"));
    assert!(e["mean_deg"].as_f64().unwrap() < 0.05, "{e}");
}

#[test]
fn demo_writes_outputs_scene_and_evaluation() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("demo");
    let o = run(&[os("demo"), os("-q"), os("-o"), out.as_os_str()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(stdout.contains("error against ground truth"), "{stdout}");
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
    let mean = report["evaluation"]["normals"]["mean_deg"]
        .as_f64()
        .unwrap();
    // Default noise σ = 0.005 under 12 lights: about half a degree.
    assert!(mean < 1.0, "{mean}");
    // The rendered inputs re-run through the main command.
    let scene = out.join("scene");
    assert!(scene.join("lights.json").is_file() && scene.join("gt/normal_gt.exr").is_file());
    let images: Vec<PathBuf> = (0..12)
        .map(|k| scene.join(format!("img_{k:03}.exr")))
        .collect();
    let out2 = tmp.path().join("again");
    let lights = scene.join("lights.json");
    let mut args: Vec<&std::ffi::OsStr> = images.iter().map(|p| p.as_os_str()).collect();
    args.extend([
        os("--lights"),
        lights.as_os_str(),
        os("-q"),
        os("-o"),
        out2.as_os_str(),
    ]);
    let o = run(&args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let a = photostereo::io::decode::read_image(&out.join("normal.exr")).unwrap();
    let b = photostereo::io::decode::read_image(&out2.join("normal.exr")).unwrap();
    assert_eq!(a.data.len(), b.data.len());
    assert!(
        a.data
            .iter()
            .zip(&b.data)
            .all(|(x, y)| (x - y).abs() < 1e-6)
    );
}

/// Bad input: non-zero exit, a message naming what is wrong, and nothing written.
#[test]
fn bad_input_fails_cleanly() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let images = sphere_dataset(&data, ImageFormat::Exr);
    let out = tmp.path().join("out");
    let lights = data.join("lights.json");
    let img_args: Vec<&std::ffi::OsStr> = images.iter().map(|p| p.as_os_str()).collect();
    let cases: Vec<(Vec<&std::ffi::OsStr>, &str)> = vec![
        // No lights file.
        (
            [img_args.clone(), vec![os("-o"), out.as_os_str()]].concat(),
            "--lights",
        ),
        // A light for an image that is not given.
        (
            [
                img_args[..9].to_vec(),
                vec![
                    os("--lights"),
                    lights.as_os_str(),
                    os("-o"),
                    out.as_os_str(),
                ],
            ]
            .concat(),
            "matches no image",
        ),
        // A missing image: named as missing before lights are matched.
        (
            [
                img_args[..9].to_vec(),
                vec![
                    os("missing.exr"),
                    os("--lights"),
                    lights.as_os_str(),
                    os("-o"),
                    out.as_os_str(),
                ],
            ]
            .concat(),
            "missing.exr: no such file",
        ),
        // An invalid parameter.
        (
            [
                img_args.clone(),
                vec![
                    os("--lights"),
                    lights.as_os_str(),
                    os("--shadow-threshold"),
                    os("1.5"),
                    os("-o"),
                    out.as_os_str(),
                ],
            ]
            .concat(),
            "shadow-threshold",
        ),
    ];
    for (args, needle) in &cases[..3] {
        let o = run(args);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "succeeded: {args:?}");
        assert!(err.contains("error:") && err.contains(needle), "{err}");
        assert!(listing(&out).is_empty(), "{:?}", listing(&out));
    }
    let o = run(&cases[3].0);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("shadow-threshold"));
    assert!(listing(&out).is_empty());
    // A mask of another size is refused.
    let small = tmp.path().join("small.png");
    image::GrayImage::from_pixel(10, 10, image::Luma([255]))
        .save(&small)
        .unwrap();
    let mut args = img_args.clone();
    args.extend([
        os("--lights"),
        lights.as_os_str(),
        os("--mask"),
        small.as_os_str(),
        os("-o"),
        out.as_os_str(),
    ]);
    let o = run(&args);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("small.png") && err.contains("10x10"),
        "{err}"
    );
    assert!(listing(&out).is_empty());
    // Output path is an existing file.
    let file = tmp.path().join("a-file");
    std::fs::write(&file, b"x").unwrap();
    let mut args = img_args.clone();
    args.extend([
        os("--lights"),
        lights.as_os_str(),
        os("-o"),
        file.as_os_str(),
    ]);
    let o = run(&args);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("a-file"));
    assert_eq!(std::fs::read(&file).unwrap(), b"x");
}

/// A colour scene written as sRGB-encoded 8-bit PNGs — the way a camera writes — read back by
/// the main command, which decodes sRGB by default: the round trip through quantisation and the
/// transfer function costs a fraction of a degree, while misreading the files as linear costs
/// several degrees.
#[test]
fn srgb_8_bit_colour_dataset_round_trips() {
    use photostereo::synth::reflectance::Material;
    use photostereo::synth::scene::SceneKind;
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let material = Material {
        diffuse_color: [0.9, 0.7, 0.5],
        ..Material::lambertian()
    };
    let scene = SceneKind::Sphere.build(96, Albedo::Constant(0.8), material);
    let lights = Lights::fibonacci(12, 30.0).unwrap();
    let options = RenderOptions {
        color: true,
        ..RenderOptions::default()
    };
    let synth = synthesize(scene, lights.clone(), &options).unwrap();
    write_synthetic(
        &synth.rendering,
        &lights,
        &data,
        ImageFormat::Png8 { srgb: true },
    )
    .unwrap();
    let images: Vec<PathBuf> = (0..12)
        .map(|k| data.join(format!("img_{k:03}.png")))
        .collect();
    let (lights_json, mask, gt) = (
        data.join("lights.json"),
        data.join("mask.png"),
        data.join("gt/normal_gt.exr"),
    );
    let run_with = |out: &Path, extra: &[&str]| {
        let mut args: Vec<&std::ffi::OsStr> = images.iter().map(|p| p.as_os_str()).collect();
        args.extend([
            os("--lights"),
            lights_json.as_os_str(),
            os("--mask"),
            mask.as_os_str(),
            os("-q"),
            os("-o"),
            out.as_os_str(),
        ]);
        args.extend(extra.iter().map(os));
        let o = run(&args);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        String::from_utf8_lossy(&o.stderr).into_owned()
    };
    let srgb = tmp.path().join("srgb");
    // The run says that 8-bit data were decoded as sRGB.
    assert!(run_with(&srgb, &[]).contains("sRGB"));
    let good = eval(&srgb, &gt, &mask)["mean_deg"].as_f64().unwrap();
    let lin = tmp.path().join("linear");
    run_with(&lin, &["--linear"]);
    let wrong = eval(&lin, &gt, &mask)["mean_deg"].as_f64().unwrap();
    println!(
        "8-bit sRGB colour sphere: mean {good:.3}° decoded as sRGB, {wrong:.3}° read as linear"
    );
    assert!(good < 0.5, "{good}°");
    assert!(
        wrong > 3.0 * good && wrong > 1.0,
        "treating sRGB data as linear should hurt: {wrong}° vs {good}°"
    );
}
