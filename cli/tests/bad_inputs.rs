//! Every bad input the command line can meet (issue "Reliability"): a non-zero exit, a message
//! naming the file, image or parameter and what to do, and no output file afterwards; inputs
//! that can still be solved give a warning and a complete result instead. The README's table
//! of messages comes from this test (`cargo test --test bad_inputs -- --nocapture` prints it).

#[path = "../../tests/common/mod.rs"]
mod common;

use common::{listing, main_args, os, run, sphere_dataset};
use photostereo::io::decode::read_image;
use photostereo::io::output::write_exr;
use photostereo::synth::write::ImageFormat;
use std::ffi::OsString;
use std::path::{Path, PathBuf};

/// The sphere data set (10 grey EXR images, `lights.json`, `mask.png`) in `dir/name`.
fn dataset(root: &Path, name: &str) -> (PathBuf, Vec<PathBuf>) {
    let dir = root.join(name);
    let images = sphere_dataset(&dir, ImageFormat::Exr);
    (dir, images)
}

/// Rewrites grey EXR `path` through `f(width, height, values)`, as channel `Y`.
fn rewrite(path: &Path, f: impl FnOnce(usize, usize, &mut Vec<f32>)) {
    let img = read_image(path).unwrap();
    let (mut w, mut h) = (img.width, img.height);
    let mut v = img.data.clone();
    f(w, h, &mut v);
    if v.len() != w * h {
        // A crop: keep whole rows.
        h = v.len() / w;
        w = v.len() / h;
    }
    write_exr(path, w, h, &[("Y", &v)], &[]).unwrap();
}

/// One row of the table: the case, the arguments, and the words its message must hold.
struct Case {
    what: &'static str,
    args: Vec<OsString>,
    words: Vec<&'static str>,
}

fn error_cases(root: &Path, out: &Path) -> Vec<Case> {
    let mut cases = Vec::new();
    let mut add = |what, args, words: &[&'static str]| {
        cases.push(Case {
            what,
            args,
            words: words.to_vec(),
        })
    };
    // Images of different sizes.
    let (d, imgs) = dataset(root, "size");
    rewrite(&imgs[3], |w, _, v| v.truncate(v.len() - 3 * w));
    add(
        "images of different sizes",
        main_args(&imgs, &d.join("lights.json"), &[], out),
        &["img_003.exr", "image 3", "96x93", "same size"],
    );
    // Grey and RGB images mixed.
    let (d, imgs) = dataset(root, "channels");
    let img = read_image(&imgs[3]).unwrap();
    write_exr(
        &imgs[3],
        img.width,
        img.height,
        &[("R", &img.data), ("G", &img.data), ("B", &img.data)],
        &[],
    )
    .unwrap();
    add(
        "images with different channel counts",
        main_args(&imgs, &d.join("lights.json"), &[], out),
        &[
            "img_003.exr",
            "image 3",
            "3 colour channel",
            "all images must be grey or all RGB",
        ],
    );
    // Fewer than 3 lights.
    let (d, imgs) = dataset(root, "two");
    let two = d.join("two.txt");
    std::fs::write(&two, "0 0 1\n0.5 0 0.866\n").unwrap();
    add(
        "fewer than 3 lights",
        main_args(&imgs[..2], &two, &[], out),
        &["2 image(s)", "at least 3 lights"],
    );
    // Lights and images that do not match in number or names.
    add(
        "more lights than images",
        main_args(&imgs[..9], &d.join("lights.json"), &[], out),
        &["img_009.exr", "matches no image"],
    );
    let stray = d.join("stray.exr");
    std::fs::copy(&imgs[0], &stray).unwrap();
    let mut with_stray = imgs[..9].to_vec();
    with_stray.push(stray);
    add(
        "an image that no light names",
        main_args(&with_stray, &d.join("lights.json"), &[], out),
        &["stray.exr", "has no light"],
    );
    let text = d.join("ten.txt");
    let rows: String = (0..9).map(|_| "0 0 1\n").collect();
    std::fs::write(&text, rows).unwrap();
    add(
        "a lights text file with fewer rows than images",
        main_args(&imgs, &text, &[], out),
        &["9 lights", "10 images"],
    );
    // Zero, NaN or non-finite light vectors and intensities.
    let json = std::fs::read_to_string(d.join("lights.json")).unwrap();
    let mut v: serde_json::Value = serde_json::from_str(&json).unwrap();
    v["lights"][4]["direction"] = serde_json::json!([0.0, 0.0, 0.0]);
    let zero = d.join("zero.json");
    std::fs::write(&zero, v.to_string()).unwrap();
    add(
        "a zero light direction",
        main_args(&imgs, &zero, &[], out),
        &["light 4", "zero vector"],
    );
    let nan = d.join("nan.txt");
    let mut rows: Vec<&str> = vec!["0 0 1"; 10];
    rows[6] = "nan 0 1";
    std::fs::write(&nan, rows.join("\n")).unwrap();
    add(
        "a NaN light direction",
        main_args(&imgs, &nan, &[], out),
        &["light 6", "finite"],
    );
    let mut v: serde_json::Value = serde_json::from_str(&json).unwrap();
    v["lights"][2]["intensity"] = serde_json::json!(0.0);
    let dark = d.join("zero_intensity.json");
    std::fs::write(&dark, v.to_string()).unwrap();
    add(
        "a zero light intensity",
        main_args(&imgs, &dark, &[], out),
        &["light 2", "finite and positive"],
    );
    // Coplanar lights: all in the plane y = 0.
    let flat = d.join("coplanar.txt");
    let rows: String = (0..10)
        .map(|k| {
            let a = (k as f64 / 10.0) * std::f64::consts::PI;
            format!("{} 0 {}\n", a.cos(), a.sin())
        })
        .collect();
    std::fs::write(&flat, rows).unwrap();
    add(
        "coplanar lights",
        main_args(&imgs, &flat, &[], out),
        &[
            "condition number",
            "coplanar",
            "add lights out of their plane",
        ],
    );
    // An all-dark and an all-saturated image.
    let (d, imgs) = dataset(root, "dark");
    rewrite(&imgs[5], |_, _, v| v.fill(0.0));
    add(
        "an all-dark image",
        main_args(&imgs, &d.join("lights.json"), &[], out),
        &[
            "img_005.exr",
            "image 5",
            "entirely dark",
            "remove it and its light",
        ],
    );
    let (d, imgs) = dataset(root, "saturated");
    rewrite(&imgs[5], |_, _, v| v.fill(1.0));
    add(
        "an all-saturated image",
        main_args(&imgs, &d.join("lights.json"), &["--saturation", "1.0"], out),
        &[
            "img_005.exr",
            "image 5",
            "every pixel is saturated",
            "lower the exposure",
        ],
    );
    // An empty mask, and a mask of another size.
    let (d, imgs) = dataset(root, "masks");
    let empty = d.join("empty.png");
    image::GrayImage::new(96, 96).save(&empty).unwrap();
    let e = empty.to_string_lossy().into_owned();
    let empty_args = main_args(&imgs, &d.join("lights.json"), &["--mask", &e], out);
    add(
        "an empty mask",
        empty_args,
        &["empty.png", "no pixel is set"],
    );
    let small = d.join("small.png");
    image::GrayImage::from_pixel(50, 40, image::Luma([255]))
        .save(&small)
        .unwrap();
    let s = small.to_string_lossy().into_owned();
    let small_args = main_args(&imgs, &d.join("lights.json"), &["--mask", &s], out);
    add(
        "a mask of another size",
        small_args,
        &["small.png", "50x40"],
    );
    // An ambient frame that is missing, of another size, or stored otherwise than the images
    // (8-bit beside float).
    let (d, imgs) = dataset(root, "ambient");
    let missing = d.join("dark.exr").to_string_lossy().into_owned();
    add(
        "a missing ambient image",
        main_args(&imgs, &d.join("lights.json"), &["--ambient", &missing], out),
        &["dark.exr", "No such file"],
    );
    let small = d.join("dark-small.exr");
    write_exr(&small, 48, 96, &[("Y", &vec![0.01; 48 * 96])], &[]).unwrap();
    let s = small.to_string_lossy().into_owned();
    add(
        "an ambient image of another size",
        main_args(&imgs, &d.join("lights.json"), &["--ambient", &s], out),
        &["ambient image", "dark-small.exr", "48x96", "96x96"],
    );
    let byte = d.join("dark-8bit.png");
    image::GrayImage::from_pixel(96, 96, image::Luma([3]))
        .save(&byte)
        .unwrap();
    let b = byte.to_string_lossy().into_owned();
    add(
        "an 8-bit ambient image beside float images",
        main_args(&imgs, &d.join("lights.json"), &["--ambient", &b], out),
        &[
            "ambient image",
            "dark-8bit.png",
            "8-bit",
            "floating-point",
            "as the images are",
        ],
    );
    // Corrupt and unsupported image files.
    let (d, imgs) = dataset(root, "corrupt");
    let bytes = std::fs::read(&imgs[7]).unwrap();
    std::fs::write(&imgs[7], &bytes[..bytes.len() / 3]).unwrap();
    add(
        "a truncated (corrupt) image",
        main_args(&imgs, &d.join("lights.json"), &[], out),
        &["img_007.exr", "cannot decode"],
    );
    let (d, mut imgs) = dataset(root, "unsupported");
    let gif = d.join("img_007.gif");
    std::fs::write(&gif, b"GIF89a\x01\x00\x01\x00\x00\x00\x00;").unwrap();
    imgs[7] = gif;
    let json = std::fs::read_to_string(d.join("lights.json"))
        .unwrap()
        .replace("img_007.exr", "img_007.gif");
    std::fs::write(d.join("lights.json"), json).unwrap();
    add(
        "an unsupported image format",
        main_args(&imgs, &d.join("lights.json"), &[], out),
        &["img_007.gif", "unsupported", "PNG", "JPEG", "EXR"],
    );
    // A mistyped folder is named as missing, not taken for a list of images without lights.
    add(
        "a mistyped folder",
        vec![
            root.join("catPNGG").into_os_string(),
            "-q".into(),
            "-o".into(),
            out.as_os_str().to_owned(),
        ],
        &["catPNGG", "no such file or folder"],
    );
    // One image missing among several is named before any count of lights is compared.
    let (d, mut imgs) = dataset(root, "missing");
    imgs[9] = d.join("img_009_typo.exr");
    add(
        "a missing image among several",
        main_args(&imgs, &d.join("lights.json"), &[], out),
        &["img_009_typo.exr", "1 of the 10 inputs"],
    );
    // Numbered images as a shell sorts them (frame.1, frame.10, frame.2, …) with a plain list
    // of lights: refused, with the numeric order and the way out.
    let (_, mut renamed, text) = common::numbered_dataset(root);
    renamed.sort();
    add(
        "numbered images in text order with a plain list of lights",
        main_args(&renamed, &text, &[], out),
        &[
            "frame.10.exr before frame.2.exr",
            "frame.1.exr frame.2.exr frame.3.exr",
            "--image-order natural",
        ],
    );
    // An output folder that cannot be written is found before any image is decoded (the
    // corrupt image would fail later).
    let (d, imgs) = dataset(root, "unwritable");
    std::fs::write(&imgs[4], b"not an EXR").unwrap();
    let file = d.join("a-file");
    std::fs::write(&file, b"x").unwrap();
    let mut args = main_args(&imgs, &d.join("lights.json"), &[], out);
    let n = args.len();
    args[n - 1] = file.join("out").into_os_string();
    add(
        "an output folder that cannot be created (checked before loading)",
        args,
        &["a-file", "output folder"],
    );
    cases
}

/// Every error case exits non-zero, prints its key words, and leaves no output file.
#[test]
fn every_bad_input_is_refused_with_a_clear_message_and_no_output() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    let cases = error_cases(tmp.path(), &out);
    println!("| bad input | exit | message |\n| --- | --- | --- |");
    for case in &cases {
        let args: Vec<&std::ffi::OsStr> = case.args.iter().map(|a| a.as_os_str()).collect();
        let o = run(&args);
        let err = String::from_utf8_lossy(&o.stderr);
        let code = o.status.code();
        assert_eq!(code, Some(1), "{}: exit {code:?}\n{err}", case.what);
        assert!(err.starts_with("error: "), "{}: {err}", case.what);
        for w in &case.words {
            assert!(err.contains(w), "{}: {w:?} missing from\n{err}", case.what);
        }
        assert!(
            listing(&out).is_empty(),
            "{}: left {:?}",
            case.what,
            listing(&out)
        );
        let shown = err
            .trim()
            .replace(&format!("{}/", tmp.path().display()), "");
        println!("| {} | 1 | `{}` |", case.what, shown.replace('|', "\\|"));
    }
}

/// An existing, non-empty output folder is refused unless `--force`, and left untouched; an
/// output path that cannot be a folder is refused naming it.
#[test]
fn existing_or_unwritable_output_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let (d, imgs) = dataset(tmp.path(), "data");
    let out = tmp.path().join("out");
    std::fs::create_dir(&out).unwrap();
    std::fs::write(out.join("notes.txt"), b"mine").unwrap();
    let args = main_args(&imgs, &d.join("lights.json"), &[], &out);
    let a: Vec<&std::ffi::OsStr> = args.iter().map(|a| a.as_os_str()).collect();
    let o = run(&a);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    for w in ["out", "already exists", "1 entries", "--force"] {
        assert!(err.contains(w), "{w:?} missing from {err}");
    }
    assert_eq!(listing(&out), vec!["notes.txt"]);
    // The demo refuses the same way.
    let o = run(&[os("demo"), os("-q"), os("-o"), out.as_os_str()]);
    assert_eq!(o.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&o.stderr).contains("--force"));
    assert_eq!(listing(&out), vec!["notes.txt"]);
    // --force replaces a previous output set only: a folder holding anything else is refused
    // and left as it is.
    let args = main_args(&imgs, &d.join("lights.json"), &["--force"], &out);
    let a: Vec<&std::ffi::OsStr> = args.iter().map(|a| a.as_os_str()).collect();
    let o = run(&a);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("notes.txt") && err.contains("not an output"),
        "{err}"
    );
    assert_eq!(listing(&out), vec!["notes.txt"]);
    std::fs::remove_file(out.join("notes.txt")).unwrap();
    for force in [false, true] {
        let extra: &[&str] = if force { &["--force"] } else { &[] };
        let args = main_args(&imgs, &d.join("lights.json"), extra, &out);
        let a: Vec<&std::ffi::OsStr> = args.iter().map(|a| a.as_os_str()).collect();
        let o = run(&a);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    }
    let files = listing(&out);
    assert!(files.contains(&"depth.exr".to_string()));
    assert_eq!(files.len(), 12, "{files:?}"); // the outputs, report.html and the set's list
    // An empty existing folder is fine.
    let empty = tmp.path().join("empty");
    std::fs::create_dir(&empty).unwrap();
    let args = main_args(&imgs, &d.join("lights.json"), &[], &empty);
    let a: Vec<&std::ffi::OsStr> = args.iter().map(|a| a.as_os_str()).collect();
    assert!(run(&a).status.success());
    // Unwritable: the output path lies under a regular file.
    let file = tmp.path().join("a-file");
    std::fs::write(&file, b"x").unwrap();
    let under = file.join("out");
    let args = main_args(&imgs, &d.join("lights.json"), &[], &under);
    let a: Vec<&std::ffi::OsStr> = args.iter().map(|a| a.as_os_str()).collect();
    let o = run(&a);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("a-file"), "{err}");
    assert_eq!(std::fs::read(&file).unwrap(), b"x");
    // `integrate` refuses an existing output file unless --force.
    let depth = out.join("depth.exr");
    let before = std::fs::read(&depth).unwrap();
    let normals = out.join("normal.exr");
    let o = run(&[
        os("integrate"),
        os("--normals"),
        normals.as_os_str(),
        os("-o"),
        depth.as_os_str(),
    ]);
    assert_eq!(o.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&o.stderr).contains("already exists"));
    assert_eq!(std::fs::read(&depth).unwrap(), before);
}

/// Inputs that can still be solved: exit 0, a complete result, and a warning naming the
/// problem. NaN/Inf pixels are masked and counted, not propagated.
#[test]
fn solvable_problems_give_warnings_and_a_result() {
    let tmp = tempfile::tempdir().unwrap();
    let (d, imgs) = dataset(tmp.path(), "data");
    let lights = d.join("lights.json");
    let mask = d.join("mask.png").to_string_lossy().into_owned();
    // NaN and infinite pixels: a 4×4 NaN block and one +Inf in image 2, inside the sphere.
    let (dn, nimgs) = dataset(tmp.path(), "nan");
    rewrite(&nimgs[2], |w, _, v| {
        for y in 40..44 {
            for x in 40..44 {
                v[y * w + x] = f32::NAN;
            }
        }
        v[50 * w + 50] = f32::INFINITY;
    });
    let nmask = dn.join("mask.png").to_string_lossy().into_owned();
    // Intensities declared 1 but the images 2.5× too bright, with --albedo-normalised.
    let (db, bimgs) = dataset(tmp.path(), "bright");
    for p in &bimgs {
        rewrite(p, |_, _, v| v.iter_mut().for_each(|x| *x *= 2.5));
    }
    let bmask = db.join("mask.png").to_string_lossy().into_owned();
    // 8-bit PNGs, sRGB-encoded as a camera writes them.
    let d8 = tmp.path().join("png8");
    let imgs8 = sphere_dataset(&d8, ImageFormat::Png8 { srgb: true });
    let mask8 = d8.join("mask.png").to_string_lossy().into_owned();
    let cases: Vec<(&str, Vec<OsString>, Vec<&str>)> = vec![
        (
            "NaN / Inf pixels",
            main_args(
                &nimgs,
                &dn.join("lights.json"),
                &["--mask", &nmask],
                &tmp.path().join("o1"),
            ),
            vec!["17 NaN or infinite samples were excluded"],
        ),
        (
            "8-bit gamma-encoded images",
            main_args(
                &imgs8,
                &d8.join("lights.json"),
                &["--mask", &mask8],
                &tmp.path().join("o0"),
            ),
            vec!["decoded as sRGB-encoded (gamma) data", "--linear"],
        ),
        (
            "saturated pixels",
            main_args(
                &imgs,
                &lights,
                &["--mask", &mask, "--saturation", "0.5"],
                &tmp.path().join("o2"),
            ),
            vec!["saturated samples were excluded"],
        ),
        (
            "pixels with fewer than 3 lit samples (no mask: the background)",
            main_args(&imgs, &lights, &[], &tmp.path().join("o3")),
            vec!["fewer than 3 usable samples", "pass --mask"],
        ),
        (
            "albedo > 1 on normalised data",
            main_args(
                &bimgs,
                &db.join("lights.json"),
                &["--mask", &bmask, "--albedo-normalised", "--no-recalibrate"],
                &tmp.path().join("o4"),
            ),
            vec!["albedo > 1", "check the light intensities or exposure"],
        ),
        (
            "poor integrability (noisy normals)",
            vec![
                "demo".into(),
                "--noise".into(),
                "0.1".into(),
                "-o".into(),
                tmp.path().join("o5").into_os_string(),
            ],
            vec!["poor integrability", "median |curl|"],
        ),
    ];
    println!("| solvable problem | exit | warning |\n| --- | --- | --- |");
    for (what, args, words) in &cases {
        let a: Vec<&std::ffi::OsStr> = args.iter().map(|a| a.as_os_str()).collect();
        let o = run(&a);
        let (stdout, stderr) = (
            String::from_utf8_lossy(&o.stdout),
            String::from_utf8_lossy(&o.stderr),
        );
        assert!(o.status.success(), "{what}: {stderr}");
        let all = format!("{stdout}{stderr}");
        let line = all
            .lines()
            .find(|l| l.contains(words[0]))
            .unwrap_or_else(|| panic!("{what}: no {:?} in\n{all}", words[0]));
        for w in words {
            assert!(all.contains(w), "{what}: {w:?} missing from\n{all}");
        }
        let dir = Path::new(args.last().unwrap());
        assert!(listing(dir).contains(&"depth.exr".to_string()), "{what}");
        println!("| {what} | 0 | `{}` |", line.trim().replace('|', "\\|"));
    }
    // The NaN pixels are counted in the report and left out of the solve, not propagated:
    // every masked pixel outside the NaN block still has a normal.
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(tmp.path().join("o1/report.json")).unwrap()).unwrap();
    assert_eq!(
        report["pixels"]["too_few_samples"], 0,
        "{}",
        report["pixels"]
    );
    assert_eq!(report["pixels"]["solved"], report["pixels"]["masked"]);
}

/// A run stopped by Ctrl-C (SIGINT) or killed (SIGKILL) at any moment leaves either nothing or
/// complete files: never a half-written file, and after Ctrl-C never a temporary. A killed run
/// cannot clean up: it may leave the hidden staging folder and lock file of a set it was
/// writing (the demo's scene is one, inside the output folder), as `io::output` documents, and
/// the next run removes them; nothing else. Ctrl-C exits with status 130.
#[test]
fn interrupted_runs_leave_no_partial_file() {
    use std::process::{Command, Stdio};
    let tmp = tempfile::tempdir().unwrap();
    let mut outcomes = Vec::new();
    // The demo (render, solve, integrate, write the outputs, then the scene) runs for about
    // 0.6 s here; the delays catch it in every stage.
    for (i, delay_ms) in [5u64, 100, 200, 300, 380, 440, 500, 560, 620, 900]
        .into_iter()
        .enumerate()
    {
        for signal in ["INT", "KILL"] {
            let out = tmp.path().join(format!("out-{signal}-{i}"));
            let mut child = Command::new(common::bin())
                .args(["demo", "-q", "-o"])
                .arg(&out)
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .spawn()
                .unwrap();
            std::thread::sleep(std::time::Duration::from_millis(delay_ms));
            let _ = Command::new("kill")
                .arg(format!("-{signal}"))
                .arg(child.id().to_string())
                .status();
            let status = child.wait().unwrap();
            let files = listing(&out);
            for dir in [out.clone(), out.join("scene"), out.join("scene/gt")] {
                let names = listing(&dir);
                let allowed = |f: &String| {
                    !f.starts_with('.')
                        || f == photostereo::io::output::MANIFEST
                        || (signal == "KILL" && photostereo::io::output::is_leftover(f))
                };
                assert!(
                    names.iter().all(allowed),
                    "{signal} at {delay_ms} ms left temporaries in {dir:?}: {names:?}"
                );
            }
            let outputs: Vec<&String> = files
                .iter()
                .filter(|f| photostereo::run::pipeline::OUTPUT_FILES.contains(&f.as_str()))
                .collect();
            let complete = outputs.len() == photostereo::run::pipeline::OUTPUT_FILES.len();
            assert!(
                outputs.is_empty() || complete,
                "{signal} at {delay_ms} ms left a partial set: {files:?}"
            );
            // Whatever is there is whole: every EXR decodes.
            for f in outputs.iter().filter(|f| f.ends_with(".exr")) {
                exr::prelude::read_all_data_from_file(out.join(f)).unwrap();
            }
            if !complete && signal == "INT" {
                assert_eq!(
                    status.code(),
                    Some(130),
                    "Ctrl-C at {delay_ms} ms: {status:?}"
                );
            }
            outcomes.push((signal, delay_ms, outputs.len()));
        }
    }
    // The delays span the run: some runs were stopped before their outputs appeared.
    assert!(outcomes.iter().any(|o| o.2 == 0), "{outcomes:?}");
    println!("{outcomes:?}");
}
