//! Light calibration against ground truth: rendered mirror spheres (directions), rendered
//! matte spheres and grey cards (intensities), and the classic 12-light capture, where the
//! calibrated lights are judged by how well they explain real images.

#[path = "../../tests/common/mod.rs"]
mod common;

use nalgebra::Vector3;
use photostereo::calibrate::intensity::{
    MatteOptions, intensities_from_card, intensities_from_sphere,
};
use photostereo::calibrate::sphere::Circle;
use photostereo::calibrate::{
    ChromeCalibration, ChromeOptions, calibrate_chrome, find_sphere, load_reference_images,
    read_grey_mask,
};
use photostereo::capture::dataset::{Capture, read_image_list};
use photostereo::capture::lights::{Light, Lights};
use photostereo::capture::stack::{ColorMode, ImageStack, LoadOptions, Transfer, load_stack};
use photostereo::eval::metrics::angular_errors;
use photostereo::grid::{Grid, Mask, ScalarMap};
use photostereo::progress::Silent;
use photostereo::run::pipeline::{Config, Reconstruction, reconstruct};
use photostereo::synth::reflectance::{Diffuse, Material, Mirror, Specular};
use photostereo::synth::render::{RenderOptions, Rendering, render};
use photostereo::synth::scene::{Albedo, Object, Primitive, Scene};
use std::path::Path;

/// A chrome ball: a mirror with a faint diffuse part (`diffuse` > 0 shows its outline under
/// ambient light, as a real ball shows its surroundings).
fn chrome(diffuse: bool) -> Material {
    Material {
        diffuse: if diffuse {
            Diffuse::Lambertian
        } else {
            Diffuse::None
        },
        diffuse_color: [0.1; 3],
        specular: Some(Specular::Mirror(Mirror { f0: 0.8 })),
        specular_color: [1.0; 3],
    }
}

fn sphere_scene(size: (usize, usize), centre: (f64, f64), radius: f64, m: Material) -> Scene {
    Scene {
        width: size.0,
        height: size.1,
        objects: vec![
            Object::new(
                Primitive::Sphere {
                    cx: centre.0,
                    cy: centre.1,
                    radius,
                    base: 0.0,
                },
                Albedo::Constant(1.0),
            )
            .with_material(m),
        ],
    }
}

/// The rendered images as stored (not divided by intensity), grey or RGB.
fn raw_stack(r: &Rendering) -> ImageStack {
    let (w, h) = (r.truth.mask.width(), r.truth.mask.height());
    let images = r
        .images
        .iter()
        .map(|planes| planes.iter().flat_map(|p| p.data().to_vec()).collect())
        .collect();
    ImageStack::from_images(w, h, r.channels, images).unwrap()
}

fn grey_mask(m: &Mask) -> ScalarMap {
    m.map(|v| f32::from(u8::from(*v)))
}

fn errors_deg(found: &[Vector3<f64>], truth: &[Vector3<f64>]) -> Vec<f64> {
    found
        .iter()
        .zip(truth)
        .map(|(a, b)| a.angle(b).to_degrees())
        .collect()
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len() as f64
}

/// Angular radius of the rendered lamps (the classic 12-light chrome ball's highlights, about
/// 80 px on a 120 px sphere, are lamps of about 4°).
const LAMP_DEG: f64 = 4.0;

/// Lamps of [`LAMP_DEG`] angular radius, pixels that integrate over their area (4×4 samples), highlights
/// clipped at 1 as a camera saturates, ambient light, read noise.
fn capture_options(noise: f32, seed: u64) -> RenderOptions {
    RenderOptions {
        light_radius_deg: LAMP_DEG,
        pixel_samples: 4,
        clip: None,
        noise_sigma: noise,
        ambient: 0.5,
        seed,
        ..RenderOptions::default()
    }
}

/// Directions within 0.2° (mean) of the truth on mirror spheres of several radii and positions,
/// with and without noise, the outline from the mask or detected in the images.
#[test]
fn mirror_spheres_give_the_lights_within_a_fifth_of_a_degree() {
    let truth = Lights::random_cone(16, Vector3::z(), 55.0, 11).unwrap();
    let truth_dirs = truth.directions();
    for (k, (size, centre, radius, noise)) in [
        ((180, 160), (0.0, 0.0), 60.0, 0.0),
        ((240, 200), (-20.5, 12.25), 85.0, 0.01),
        ((320, 300), (30.0, -17.0), 125.0, 0.02),
    ]
    .into_iter()
    .enumerate()
    {
        let scene = sphere_scene(size, centre, radius, chrome(true));
        let r = render(&scene, &truth, &capture_options(noise, k as u64)).unwrap();
        let stack = raw_stack(&r);
        let mask = grey_mask(&r.truth.mask);
        let pixel_centre = (
            centre.0 + (size.0 as f64 - 1.0) / 2.0,
            (size.1 as f64 - 1.0) / 2.0 - centre.1,
        );
        let opts = ChromeOptions::default();
        for detect in [false, true] {
            let m = (!detect).then_some((&mask, Path::new("mask")));
            let cal = calibrate_chrome(&stack, m, &opts).unwrap();
            let c = cal.sphere.circle;
            let off = (c.cx - pixel_centre.0)
                .hypot(c.cy - pixel_centre.1)
                .max((c.radius - radius).abs());
            let found = cal.lights().unwrap().directions();
            let e = errors_deg(&found, &truth_dirs);
            let max = e.iter().copied().fold(0.0, f64::max);
            let unc = mean(
                &cal.highlights()
                    .iter()
                    .map(|h| h.unwrap().uncertainty_deg)
                    .collect::<Vec<_>>(),
            );
            println!(
                "R {radius}, noise {noise}, {}: circle off {off:.3} px, mean {:.3}°, max {max:.3}°, stated uncertainty {unc:.3}°",
                if detect { "detected" } else { "mask" },
                mean(&e)
            );
            assert!(off < 0.3, "circle off by {off} px");
            assert!(mean(&e) <= 0.2, "mean error {:.3}°", mean(&e));
            assert!(max <= 0.6, "max error {max:.3}°");
            if detect {
                // A detected outline's uncertainty allows for the shift a mirror ball's rim
                // reflections make (0.15 px, absent from these renders): it covers every
                // error twice over.
                for (h, e) in cal.highlights().iter().zip(&e) {
                    assert!(*e <= 2.0 * h.unwrap().uncertainty_deg, "{e}° off, {h:?}");
                }
            } else {
                // The stated uncertainty is of the size of the errors made.
                assert!(unc > mean(&e) / 4.0 && unc < 4.0 * mean(&e).max(0.02));
            }
        }
    }
}

/// A light behind the sphere leaves no highlight: it is reported, and the lights file is
/// refused naming the image, instead of inventing a direction.
#[test]
fn a_missing_highlight_is_reported_not_invented() {
    let lights = Lights::from_directions(&[
        Vector3::new(0.3, 0.2, 0.93),
        Vector3::new(0.05, -0.02, -1.0),
        Vector3::new(-0.4, 0.3, 0.87),
    ])
    .unwrap();
    let scene = sphere_scene((120, 120), (0.0, 0.0), 40.0, chrome(false));
    let r = render(&scene, &lights, &capture_options(0.005, 3)).unwrap();
    let mask = grey_mask(&r.truth.mask);
    let cal = calibrate_chrome(
        &raw_stack(&r),
        Some((&mask, Path::new("mask"))),
        &ChromeOptions::default(),
    )
    .unwrap();
    let found: Vec<bool> = cal.highlights().iter().map(Option::is_some).collect();
    assert_eq!(found, [true, false, true]);
    let err = cal.lights().unwrap_err().to_string();
    assert!(
        err.contains("image 1") && err.contains("no highlight"),
        "{err}"
    );
}

/// A secondary reflection (a dimmer, smaller blob elsewhere on the ball) is rejected; two equal
/// blobs are flagged as ambiguous.
#[test]
fn secondary_reflections_are_rejected_and_ties_flagged() {
    let truth = Lights::from_directions(&[Vector3::new(0.25, 0.3, 0.92)]).unwrap();
    let scene = sphere_scene((240, 240), (0.0, 0.0), 100.0, chrome(false));
    let r = render(&scene, &truth, &capture_options(0.0, 0)).unwrap();
    let mask = grey_mask(&r.truth.mask);
    let peak = r.images[0][0].data().iter().copied().fold(0.0, f32::max);
    let run = |spot: f32, half: usize| -> ChromeCalibration {
        let mut img = r.images[0][0].clone();
        // A square reflection of another bright object on the lower left of the ball.
        for y in 90 - half..=90 + half {
            for x in 50 - half..=50 + half {
                *img.at_mut(x, y) = spot * peak;
            }
        }
        let stack = ImageStack::from_images(240, 240, 1, vec![img.into_vec()]).unwrap();
        calibrate_chrome(
            &stack,
            Some((&mask, Path::new("mask"))),
            &ChromeOptions::default(),
        )
        .unwrap()
    };
    let dim = run(0.6, 0);
    let h = dim.highlights()[0].unwrap().clone();
    assert_eq!(h.secondary, 1);
    assert!(h.warnings.is_empty(), "{:?}", h.warnings);
    assert!(h.direction.angle(&truth.directions()[0]).to_degrees() < 0.3);
    // A blob as large as the highlight itself.
    let pixels = h.pixels;
    let half = ((pixels as f64).sqrt() / 2.0).round() as usize;
    let tie = run(1.0, half);
    let h2 = tie.highlights()[0].unwrap();
    assert!(h2.share < 0.8, "share {}", h2.share);
    assert!(
        h2.warnings.iter().any(|w| w.contains("ambiguous")),
        "{:?}",
        h2.warnings
    );
    assert!(h2.confidence < h.confidence);
}

/// Matte spheres under coloured lights of known intensity: relative intensities within 1% per
/// channel, with exact directions and with the directions a chrome ball gives.
#[test]
fn matte_sphere_and_grey_card_give_intensities_within_one_percent() {
    let dirs = Lights::random_cone(12, Vector3::z(), 50.0, 5)
        .unwrap()
        .directions();
    let intensity = |k: usize| {
        let t = k as f64;
        [
            0.6 + 0.07 * t,
            1.4 - 0.05 * t,
            0.8 + 0.4 * (t * 0.7).sin().abs(),
        ]
    };
    let lights = Lights::new(
        dirs.iter()
            .enumerate()
            .map(|(k, d)| Light {
                direction: *d,
                intensity: intensity(k),
                file: None,
                position: None,
                anisotropy: None,
            })
            .collect(),
    )
    .unwrap();
    let normalised = |v: Vec<[f64; 3]>| -> Vec<[f64; 3]> {
        let mut v = v;
        for c in 0..3 {
            let m = v.iter().map(|e| e[c]).sum::<f64>() / v.len() as f64;
            v.iter_mut().for_each(|e| e[c] /= m);
        }
        v
    };
    let truth = normalised((0..12).map(intensity).collect());
    let worst = |est: &[[f64; 3]]| {
        est.iter()
            .zip(&truth)
            .flat_map(|(a, b)| (0..3).map(move |c| (a[c] / b[c] - 1.0).abs()))
            .fold(0.0, f64::max)
    };
    let options = RenderOptions {
        color: true,
        noise_sigma: 0.005,
        seed: 9,
        ..RenderOptions::default()
    };
    // A matte ball, white albedo 0.7, images kept below saturation.
    let mut matte = sphere_scene((200, 180), (8.0, -5.0), 70.0, Material::lambertian());
    matte.objects[0].albedo = Albedo::Constant(0.55);
    let r = render(&matte, &lights, &options).unwrap();
    let stack = raw_stack(&r);
    let (fit, _) = find_sphere(&stack, None).unwrap();
    let est =
        intensities_from_sphere(&stack, &fit.circle, &dirs, &MatteOptions::default()).unwrap();
    let e_exact = worst(&est.iter().map(|m| m.intensity).collect::<Vec<_>>());
    // Directions from a chrome ball under the same lights.
    let ball = sphere_scene((200, 180), (0.0, 0.0), 75.0, chrome(false));
    let rc = render(&ball, &lights, &capture_options(0.005, 4)).unwrap();
    let cal = calibrate_chrome(
        &raw_stack(&rc),
        Some((&grey_mask(&rc.truth.mask), Path::new("mask"))),
        &ChromeOptions::default(),
    )
    .unwrap();
    let chrome_dirs = cal.lights().unwrap().directions();
    let est2 = intensities_from_sphere(&stack, &fit.circle, &chrome_dirs, &MatteOptions::default())
        .unwrap();
    let e_chrome = worst(&est2.iter().map(|m| m.intensity).collect::<Vec<_>>());
    let angle = est.iter().map(|m| m.angle_to_given_deg).fold(0.0, f64::max);
    println!(
        "matte sphere: worst intensity error {:.3}% (exact directions), {:.3}% (chrome directions); shading directions within {angle:.2}°",
        e_exact * 100.0,
        e_chrome * 100.0
    );
    assert!(e_exact <= 0.01 && e_chrome <= 0.01);
    assert!(angle < 1.0);

    // A grey card: the ground plane, facing the camera.
    let card = Scene {
        width: 64,
        height: 48,
        objects: vec![Object::ground(Albedo::Constant(0.5))],
    };
    let rg = render(&card, &lights, &options).unwrap();
    let all = Grid::new(64, 48, true);
    let est3 = intensities_from_card(&raw_stack(&rg), &all, Vector3::z(), &dirs, 0.98).unwrap();
    let e_card = worst(&est3);
    println!("grey card: worst intensity error {:.3}%", e_card * 100.0);
    assert!(e_card <= 0.01);
    // A light grazing the card is refused, naming the image.
    let mut grazing = dirs.clone();
    grazing[3] = Vector3::new(1.0, 0.0, 0.05);
    let err = intensities_from_card(&raw_stack(&rg), &all, Vector3::z(), &grazing, 0.98)
        .unwrap_err()
        .to_string();
    assert!(err.contains("image 3") && err.contains("grazes"), "{err}");
}

/// Photometric stereo on one object of the classic set with the given lights.
fn reconstruct_psm(list: &Path, lights: &Lights) -> Reconstruction {
    let list = read_image_list(list).unwrap();
    let options = LoadOptions {
        transfer: Transfer::Linear,
        color: ColorMode::Grey,
        ..LoadOptions::default()
    };
    let stack = load_stack(&list.images, lights, &options, &Silent).unwrap();
    let mask = photostereo::io::decode::read_mask(list.mask.as_ref().unwrap()).unwrap();
    let capture = Capture::from_stack(stack, lights.clone(), Some(mask)).unwrap();
    let config = Config {
        integration: None,
        ..Config::default()
    };
    reconstruct(&capture, &config, &Silent).unwrap()
}

fn mean_residual(r: &Reconstruction) -> f64 {
    let v: Vec<f64> = r
        .maps
        .residual
        .data()
        .iter()
        .filter(|v| v.is_finite())
        .map(|v| f64::from(*v))
        .collect();
    mean(&v)
}

/// The classic 12-light chrome ball. Its `lights.txt` does not match these images under the
/// mirror model (see the README), so the calibration is judged by what it is for: the
/// calibrated lights must explain the objects' images better than `lights.txt` does (lower
/// photometric-stereo residual, lower error on the grey sphere, whose shape is known), and give
/// normals within a few degrees of those `lights.txt` gives.
#[test]
fn psm_chrome_calibration_explains_the_objects_better_than_the_reference() {
    let psm = require_shared!("psm");
    let chrome = read_image_list(&psm.join("chrome.txt")).unwrap();
    let stack = load_reference_images(&chrome.images, Transfer::Linear, None, &Silent).unwrap();
    let mask_path = chrome.mask.unwrap();
    let mask = read_grey_mask(&mask_path).unwrap();
    let cal = calibrate_chrome(
        &stack,
        Some((&mask, mask_path.as_path())),
        &ChromeOptions::default(),
    )
    .unwrap();
    let calibrated = cal.lights().unwrap();
    let reference = Lights::from_file(&psm.join("lights.txt")).unwrap();
    let e = errors_deg(&calibrated.directions(), &reference.directions());
    println!(
        "psm chrome vs lights.txt: mean {:.2}°, max {:.2}°; per light {:?}",
        mean(&e),
        e.iter().copied().fold(0.0, f64::max),
        e.iter()
            .map(|v| (v * 100.0).round() / 100.0)
            .collect::<Vec<_>>()
    );
    // Without the mask the ball is refused: its outline, one 8-bit code deep, shows in 10 of
    // the 12 images (two lamps light the cloth behind it).
    let detected = calibrate_chrome(&stack, None, &ChromeOptions::default()).unwrap_err();
    println!("psm chrome detection: {detected}");
    assert!(
        detected.to_string().contains("outline seen in 10"),
        "{detected}"
    );

    // The grey sphere: its normals are known from its outline.
    let gray = read_image_list(&psm.join("gray.txt")).unwrap();
    let gmask = read_grey_mask(gray.mask.as_ref().unwrap()).unwrap();
    let (gfit, _) = {
        let gstack = load_reference_images(&gray.images, Transfer::Linear, None, &Silent).unwrap();
        find_sphere(&gstack, Some((&gmask, Path::new("gray mask")))).unwrap()
    };
    let truth_normals = sphere_normals(&gfit.circle, gmask.width(), gmask.height());
    let inner = Grid::from_fn(gmask.width(), gmask.height(), |x, y| {
        (x as f64 - gfit.circle.cx).hypot(y as f64 - gfit.circle.cy) < 0.9 * gfit.circle.radius
    });
    let mut gray_err = Vec::new();
    for lights in [&calibrated, &reference] {
        let r = reconstruct_psm(&psm.join("gray.txt"), lights);
        gray_err.push(angular_errors(&r.maps.normals, &truth_normals, &inner).unwrap());
    }
    println!(
        "grey sphere normals: calibrated mean {:.2}° / median {:.2}°, lights.txt {:.2}° / {:.2}°",
        gray_err[0].mean_deg, gray_err[0].median_deg, gray_err[1].mean_deg, gray_err[1].median_deg
    );
    assert!(gray_err[0].mean_deg < gray_err[1].mean_deg);
    assert!(gray_err[0].median_deg < gray_err[1].median_deg);

    // Over all six objects the calibrated lights explain the images better; cat and buddha,
    // checked since the calibration landed, each on its own. (Rock is 2.4% worse: see
    // docs/calibration.md.)
    let mut totals = [0.0; 2];
    for object in ["buddha", "cat", "gray", "horse", "owl", "rock"] {
        let list = psm.join(format!("{object}.txt"));
        let ours = reconstruct_psm(&list, &calibrated);
        let theirs = reconstruct_psm(&list, &reference);
        let (ro, rt) = (mean_residual(&ours), mean_residual(&theirs));
        let agree =
            angular_errors(&ours.maps.normals, &theirs.maps.normals, &ours.maps.solved).unwrap();
        println!(
            "{object}: mean residual {ro:.4} (calibrated) vs {rt:.4} (lights.txt); normals differ by mean {:.2}°, median {:.2}°",
            agree.mean_deg, agree.median_deg
        );
        if ["cat", "buddha"].contains(&object) {
            assert!(ro < rt, "{object}: residual {ro} vs {rt}");
        }
        assert!(agree.median_deg < 6.0, "{object}: {agree:?}");
        totals[0] += ro;
        totals[1] += rt;
    }
    assert!(totals[0] < totals[1], "residuals {totals:?}");
}

fn sphere_normals(c: &Circle, w: usize, h: usize) -> photostereo::grid::NormalMap {
    Grid::from_fn(w, h, |x, y| {
        c.normal_at(x as f64, y as f64)
            .map_or(Vector3::repeat(f32::NAN), |n| n.cast::<f32>())
    })
}

/// Image lists of the classic set resolve their `psmImages/` paths and name the mask.
#[test]
fn psm_image_lists_are_read() {
    let psm = require_shared!("psm");
    let list = read_image_list(&psm.join("cat.txt")).unwrap();
    assert_eq!(list.images.len(), 12);
    assert!(list.images.iter().all(|p| p.is_file()));
    assert!(list.images[10].ends_with("cat/cat.10.png"));
    assert!(list.mask.unwrap().ends_with("cat/cat.mask.png"));
}

/// Malformed image lists are refused with the line at fault.
#[test]
fn bad_image_lists_name_the_problem() {
    let dir = tempfile::tempdir().unwrap();
    let write = |name: &str, text: &str| {
        let p = dir.path().join(name);
        std::fs::write(&p, text).unwrap();
        p
    };
    std::fs::write(dir.path().join("a.png"), b"").unwrap();
    let e = read_image_list(&write("count.txt", "two\na.png\n"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("line 1"), "{e}");
    let e = read_image_list(&write("short.txt", "3\na.png\na.png\n"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("3 images announced"), "{e}");
    let e = read_image_list(&write("missing.txt", "1\nnot_there.png\n"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("line 2") && e.contains("not_there.png"), "{e}");
    assert!(!photostereo::capture::dataset::is_image_list(&write(
        "lights.txt",
        "2\n0 0 1\n0 1 1\n"
    )));
}

/// The command end to end: calibrate the classic chrome ball from its image list (with the grey
/// ball for intensities), then reconstruct the cat from its image list with that lights file.
#[test]
fn calibrate_command_writes_a_lights_file_the_main_command_reads() {
    let psm = require_shared!("psm");
    let dir = tempfile::tempdir().unwrap();
    let lights = dir.path().join("lights.json");
    let out = common::run(&[
        common::os("calibrate"),
        psm.join("chrome.txt").as_os_str(),
        common::os("--matte"),
        psm.join("gray.txt").as_os_str(),
        common::os("--linear"),
        common::os("-o"),
        lights.as_os_str(),
        common::os("-q"),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("chrome sphere (from its mask)"), "{stdout}");
    let read = Lights::from_file(&lights).unwrap();
    assert_eq!(read.len(), 12);
    // Relative intensities: mean 1 per channel, and this rig's lamps are alike (within 5%).
    let grey: Vec<f64> = read.lights().iter().map(|l| l.intensity[1]).collect();
    assert!((mean(&grey) - 1.0).abs() < 1e-6);
    assert!(grey.iter().all(|g| (g - 1.0).abs() < 0.05), "{grey:?}");
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&lights).unwrap()).unwrap();
    assert!(json["lights"][0]["confidence"].as_f64().unwrap() > 0.5);
    assert!(json["calibration"]["chrome"]["sphere"]["circle"]["radius"].is_number());
    assert_eq!(
        json["calibration"]["intensity"]["reference"],
        "matte-sphere"
    );

    // The output is not overwritten without --force.
    let again = common::run(&[
        common::os("calibrate"),
        psm.join("chrome.txt").as_os_str(),
        common::os("-o"),
        lights.as_os_str(),
    ]);
    assert!(!again.status.success());
    assert!(String::from_utf8_lossy(&again.stderr).contains("--force"));

    let recon = dir.path().join("cat");
    let out = common::run(&[
        psm.join("cat.txt").as_os_str(),
        common::os("--lights"),
        lights.as_os_str(),
        common::os("--linear"),
        common::os("--integrate"),
        common::os("none"),
        common::os("-o"),
        recon.as_os_str(),
        common::os("-q"),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(recon.join("normal.exr").is_file());
}

/// What `photostereo calibrate` says of inputs it cannot use: a mask that is not a disc, a mask
/// of another size, a light behind the ball, a highlight at the rim (in doubt: refused unless
/// `--keep-doubtful`), and a saturation level that is not one.
#[test]
fn calibrate_names_bad_inputs() {
    use photostereo::synth::chrome::{ChromeCapture, Depth, Lamp, LampPlace, Wall};
    let dir = tempfile::tempdir().unwrap();
    let lamp = |d: Vector3<f64>| Lamp {
        place: LampPlace::Direction(d.normalize()),
        radius_deg: 3.0,
        radiance: 4.0,
    };
    let capture = |lamps: Vec<Lamp>| ChromeCapture {
        width: 160,
        height: 150,
        balls: vec![Circle {
            cx: 80.3,
            cy: 74.6,
            radius: 60.0,
        }],
        reflectance: 0.8,
        environment: 0.3,
        environment_slope: 0.05,
        wall: Wall::Plain {
            level: 0.6,
            slope: 0.0,
        },
        lamps,
        wall_gain: Vec::new(),
        table_reflection: 0.0,
        noise: 0.005,
        supersampling: 3,
        camera: None,
        depth: Depth::Linear16,
        seed: 5,
    };
    let write = |name: &str, cap: &ChromeCapture| -> Vec<std::path::PathBuf> {
        let imgs = cap.render();
        imgs.to_u16()
            .into_iter()
            .enumerate()
            .map(|(k, codes)| {
                let p = dir.path().join(format!("{name}{k}.png"));
                image::ImageBuffer::<image::Luma<u16>, _>::from_raw(160, 150, codes)
                    .unwrap()
                    .save(&p)
                    .unwrap();
                p
            })
            .collect()
    };
    let good = [
        Vector3::new(0.3, 0.2, 0.93),
        Vector3::new(-0.4, 0.3, 0.87),
        Vector3::new(0.1, -0.5, 0.86),
    ];
    let images = write("good", &capture(good.iter().map(|d| lamp(*d)).collect()));
    let save_mask = |name: &str, w: u32, h: u32, inside: &dyn Fn(f64, f64) -> bool| {
        let p = dir.path().join(name);
        image::GrayImage::from_fn(w, h, |x, y| {
            image::Luma([if inside(f64::from(x), f64::from(y)) {
                255
            } else {
                0
            }])
        })
        .save(&p)
        .unwrap();
        p
    };
    let square = save_mask("square.png", 160, 150, &|x, y| {
        (x - 80.3).abs() < 55.0 && (y - 74.6).abs() < 55.0
    });
    let small = save_mask("small.png", 120, 150, &|x, y| {
        (x - 80.3).hypot(y - 74.6) < 60.0
    });
    let out = dir.path().join("lights.json");
    let calibrate = |images: &[std::path::PathBuf], extra: &[&str]| {
        let mut args: Vec<&std::ffi::OsStr> = vec![common::os("calibrate")];
        args.extend(images.iter().map(|p| p.as_os_str()));
        args.extend(extra.iter().map(common::os));
        args.extend([common::os("-o"), out.as_os_str(), common::os("--force")]);
        let o = common::run(&args);
        (
            o.status.success(),
            String::from_utf8_lossy(&o.stderr).into_owned(),
        )
    };
    // The good capture calibrates, detected and with a disc mask.
    let (ok, err) = calibrate(&images, &[]);
    assert!(ok, "{err}");
    let (ok, err) = calibrate(&images, &["--mask", square.to_str().unwrap()]);
    assert!(
        !ok && err.contains("square.png") && err.contains("not a circle"),
        "{err}"
    );
    let (ok, err) = calibrate(&images, &["--mask", small.to_str().unwrap()]);
    assert!(!ok && err.contains("120") && err.contains("160"), "{err}");
    let (ok, err) = calibrate(&images, &["--saturation", "0"]);
    assert!(!ok && err.contains("--saturation"), "{err}");
    // A light behind the ball: no highlight, named.
    let behind = write(
        "behind",
        &capture(vec![
            lamp(good[0]),
            lamp(Vector3::new(0.1, 0.0, -1.0)),
            lamp(good[1]),
        ]),
    );
    let (ok, err) = calibrate(&behind, &[]);
    assert!(
        !ok && err.contains("image 1") && err.contains("no highlight"),
        "{err}"
    );
    // A light 150° from the view (behind the ball, above it): its highlight is at the rim, in
    // doubt.
    let rim = write(
        "rim",
        &capture(vec![
            lamp(good[0]),
            lamp(good[1]),
            lamp(Vector3::new(0.0, 0.5, -0.866)),
        ]),
    );
    let (ok, err) = calibrate(&rim, &[]);
    assert!(
        !ok && err.contains("image 2") && err.contains("rim") && err.contains("--keep-doubtful"),
        "{err}"
    );
    let (ok, err) = calibrate(&rim, &["--keep-doubtful"]);
    assert!(ok, "{err}");
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
    assert_eq!(json["lights"][2]["accepted"], false);
    assert_eq!(json["lights"][0]["accepted"], true);
}

/// `calibrate --camera K --ball-radius R` on a rendered rig of two balls and near LEDs: a
/// lights file with each light's position (within 2% of its distance, as the uncertainty
/// written beside it allows) that the lights reader takes back; refused without the camera or
/// with one ball.
#[test]
fn calibrate_command_places_near_lights_from_two_balls() {
    use photostereo::camera::Intrinsics;
    use photostereo::synth::chrome::{ChromeCapture, Depth, Lamp, LampPlace, Wall};
    let dir = tempfile::tempdir().unwrap();
    let k = Intrinsics {
        fx: 700.0,
        fy: 700.0,
        cx: 350.0,
        cy: 225.0,
    };
    let lamps: Vec<Vector3<f64>> = vec![
        Vector3::new(1500.0, 900.0, -1500.0),
        Vector3::new(-1200.0, 1100.0, -1000.0),
        Vector3::new(-1400.0, -900.0, -1800.0),
        Vector3::new(1100.0, -1200.0, -700.0),
        Vector3::new(200.0, 1500.0, -1200.0),
    ];
    let capture = |balls: Vec<Circle>| ChromeCapture {
        width: 700,
        height: 450,
        balls,
        reflectance: 0.7,
        environment: 0.1,
        environment_slope: 0.03,
        wall: Wall::Plain {
            level: 0.35,
            slope: 0.05,
        },
        lamps: lamps
            .iter()
            .map(|p| Lamp {
                place: LampPlace::Position(*p),
                radius_deg: 4.0,
                radiance: 5.0,
            })
            .collect(),
        wall_gain: Vec::new(),
        table_reflection: 0.0,
        noise: 0.003,
        supersampling: 2,
        camera: Some((k, 3000.0)),
        depth: Depth::Linear16,
        seed: 11,
    };
    let ball = |cx: f64| Circle {
        cx,
        cy: 225.0,
        radius: 60.0,
    };
    let write = |name: &str, cap: &ChromeCapture| -> Vec<std::path::PathBuf> {
        cap.render()
            .to_u16()
            .into_iter()
            .enumerate()
            .map(|(i, codes)| {
                let p = dir.path().join(format!("{name}{i}.png"));
                image::ImageBuffer::<image::Luma<u16>, _>::from_raw(700, 450, codes)
                    .unwrap()
                    .save(&p)
                    .unwrap();
                p
            })
            .collect()
    };
    let rig = capture(vec![ball(90.0), ball(610.0)]);
    let images = write("rig", &rig);
    let camera = dir.path().join("K.txt");
    std::fs::write(&camera, "700 0 350\n0 700 225\n0 0 1\n").unwrap();
    let radius = 60.0 / 700.0 * 3000.0;
    let out = dir.path().join("lights.json");
    let calibrate = |images: &[std::path::PathBuf], extra: &[&str]| {
        let mut args: Vec<&std::ffi::OsStr> = vec![common::os("calibrate")];
        args.extend(images.iter().map(|p| p.as_os_str()));
        args.extend(extra.iter().map(common::os));
        args.extend([common::os("-o"), out.as_os_str(), common::os("--force")]);
        common::run(&args)
    };
    let r = radius.to_string();
    let o = calibrate(
        &images,
        &[
            "--camera",
            camera.to_str().unwrap(),
            "--ball-radius",
            &r,
            "--keep-doubtful",
        ],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let read = Lights::from_file(&out).unwrap();
    let mid = 0.5 * (rig.ball_centre(0).unwrap() + rig.ball_centre(1).unwrap());
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
    for (i, (l, truth)) in read.lights().iter().zip(&lamps).enumerate() {
        let p = l.position.expect("a position");
        let d = (truth - mid).norm();
        let u = json["lights"][i]["position_uncertainty"].as_f64().unwrap();
        let e = (p - truth).norm();
        println!(
            "light {i}: {e:.2} off at {d:.0} ({:.2}%), stated ±{u:.2}",
            e / d * 100.0
        );
        assert!(
            e <= 0.02 * d && e <= 3.0 * u,
            "light {i}: {e:.2} off, ±{u:.2}"
        );
        // The direction is the one from the balls' midpoint (as measured).
        let c = &json["calibration"]["two_balls"]["centres"];
        let centre = |b: usize| Vector3::from_fn(|j, _| c[b][j].as_f64().unwrap());
        let measured_mid = 0.5 * (centre(0) + centre(1));
        assert!((measured_mid - mid).norm() < 1e-3 * mid.norm());
        assert!(l.direction.angle(&(p - measured_mid)) < 1e-9);
    }
    assert_eq!(json["calibration"]["ball_radius"].as_f64(), Some(radius));
    assert!(json["calibration"]["two_balls"]["positions"][0]["found"]["accepted"].is_boolean());
    // Balls this small leave every position more uncertain than 0.5% of its distance: in
    // doubt, refused without --keep-doubtful.
    let o = calibrate(
        &images,
        &["--camera", camera.to_str().unwrap(), "--ball-radius", &r],
    );
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(
        !o.status.success() && err.contains("in doubt") && err.contains("--keep-doubtful"),
        "{err}"
    );
    // Without the camera, the radius is refused; with one ball, positions are.
    let o = calibrate(&images, &["--ball-radius", &r]);
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(!o.status.success() && err.contains("--camera"), "{err}");
    let one = write("one", &capture(vec![ball(610.0)]));
    let o = calibrate(
        &one,
        &["--camera", camera.to_str().unwrap(), "--ball-radius", &r],
    );
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(!o.status.success() && err.contains("need two"), "{err}");
}

/// `calibrate --from-object` end to end: a rendered sphere with two albedos under 12 lights,
/// written as 16-bit PNGs; the lights file it writes is within 1° of the truth on average, names
/// each light's spread, and the main command accepts it. Without a mask it refuses.
#[test]
fn lights_from_the_object_end_to_end() {
    use photostereo::eval::demo::synthesize;
    use photostereo::synth::write::{ImageFormat, write_synthetic};
    let dir = tempfile::tempdir().unwrap();
    let scene = Scene::sphere(
        96,
        40.0,
        Albedo::Checker {
            size: 12.0,
            a: 0.9,
            b: 0.45,
        },
    );
    let lights = Lights::fibonacci(12, 35.0).unwrap();
    let synth = synthesize(scene, lights.clone(), &RenderOptions::default()).unwrap();
    let data = dir.path().join("data");
    write_synthetic(&synth.rendering, &lights, &data, ImageFormat::Png16).unwrap();
    let images: Vec<_> = (0..12)
        .map(|k| data.join(format!("img_{k:03}.png")))
        .collect();
    let out = dir.path().join("recovered.json");
    let mut args: Vec<&std::ffi::OsStr> =
        vec![common::os("calibrate"), common::os("--from-object")];
    args.extend(images.iter().map(|p| p.as_os_str()));
    let mask = data.join("mask.png");
    let without = common::run(&[args.clone(), vec![common::os("-o"), out.as_os_str()]].concat());
    assert!(!without.status.success());
    let text = String::from_utf8_lossy(&without.stderr);
    assert!(text.contains("--mask"), "{text}");
    args.extend([
        common::os("--mask"),
        mask.as_os_str(),
        common::os("-o"),
        out.as_os_str(),
    ]);
    let o = common::run(&args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let doc: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
    let entries = doc["lights"].as_array().unwrap();
    assert_eq!(entries.len(), 12);
    let mut sum = 0.0;
    for (e, t) in entries.iter().zip(lights.directions()) {
        let d: Vec<f64> = e["direction"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect();
        sum += Vector3::new(d[0], d[1], d[2]).angle(&t).to_degrees();
        assert!(e["uncertainty_deg"].as_f64().is_some_and(f64::is_finite));
    }
    assert!(sum / 12.0 < 1.0, "mean light error {:.2}°", sum / 12.0);
    // The recovered file drives photometric stereo.
    let recon = Lights::from_file(&out).unwrap();
    assert_eq!(recon.len(), 12);
    let run_dir = dir.path().join("out");
    let mut main: Vec<&std::ffi::OsStr> = images.iter().map(|p| p.as_os_str()).collect();
    main.extend([
        common::os("--lights"),
        out.as_os_str(),
        common::os("--mask"),
        mask.as_os_str(),
        common::os("-q"),
        common::os("-o"),
        run_dir.as_os_str(),
    ]);
    let o = common::run(&main);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(run_dir.join("normal.exr").is_file());
}
