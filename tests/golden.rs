//! Golden-output regression tests of the renderer: a small scene with cast shadows, rendered and
//! compared with the committed truth files in `tests/golden/`. After an intended change to the
//! renderer, regenerate them with `REGENERATE=1 cargo test --release --test golden` and review
//! the new images before committing.

use photostereo::capture::lights::Lights;
use photostereo::synth::render::{RenderOptions, render};
use photostereo::synth::scene::{Albedo, Object, Primitive, Scene};
use std::path::PathBuf;

fn golden_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/golden")
}

fn scene() -> Scene {
    let sphere = Primitive::Sphere {
        cx: -20.0,
        cy: 5.0,
        radius: 18.0,
        base: 0.0,
    };
    let pyramid = Primitive::Pyramid {
        cx: 25.0,
        cy: -8.0,
        half: 14.0,
        height: 10.0,
        base: 0.0,
    };
    let bump = Primitive::Gaussian {
        cx: 22.0,
        cy: 22.0,
        sigma: 6.0,
        height: 9.0,
        base: 0.0,
    };
    Scene {
        width: 96,
        height: 72,
        objects: vec![
            Object::ground(Albedo::Checker {
                size: 12.0,
                a: 0.3,
                b: 0.45,
            }),
            Object::new(
                sphere,
                Albedo::Smooth {
                    mean: 0.6,
                    amplitude: 0.2,
                    period: 15.0,
                },
            ),
            Object::new(pyramid, Albedo::Constant(0.8)),
            Object::new(bump, Albedo::Constant(0.7)),
        ],
    }
}

/// Compares 16-bit codes, allowing one code of difference (libm rounding across platforms).
#[test]
fn rendered_scene_matches_golden_images() {
    let lights = Lights::ring(4, 40.0, 20.0).unwrap();
    let r = render(&scene(), &lights, &RenderOptions::default()).unwrap();
    let regenerate = std::env::var_os("REGENERATE").is_some();
    for (k, planes) in r.images.iter().enumerate() {
        let img = &planes[0];
        let codes: Vec<u16> = img
            .data()
            .iter()
            .map(|v| (v.clamp(0.0, 1.0) * 65535.0).round() as u16)
            .collect();
        let path = golden_dir().join(format!("render_{k}.png"));
        if regenerate {
            std::fs::create_dir_all(golden_dir()).unwrap();
            photostereo::io::output::write_png16(&path, 96, 72, 1, &codes).unwrap();
            continue;
        }
        let truth = image::open(&path)
            .unwrap_or_else(|e| {
                panic!(
                    "{}: {e}; run with REGENERATE=1 to create it",
                    path.display()
                )
            })
            .into_luma16();
        assert_eq!((truth.width(), truth.height()), (96, 72));
        let worst = truth
            .as_raw()
            .iter()
            .zip(&codes)
            .map(|(a, b)| a.abs_diff(*b))
            .max()
            .unwrap();
        assert!(
            worst <= 1,
            "{}: differs by up to {worst} codes",
            path.display()
        );
    }
}

/// Shadow masks: at most a few boundary pixels may flip between platforms.
#[test]
fn shadow_masks_match_golden_masks() {
    let lights = Lights::ring(4, 40.0, 20.0).unwrap();
    let r = render(&scene(), &lights, &RenderOptions::default()).unwrap();
    let regenerate = std::env::var_os("REGENERATE").is_some();
    for (k, (a, c)) in r.attached.iter().zip(&r.cast).enumerate() {
        let bytes: Vec<u8> = a
            .data()
            .iter()
            .zip(c.data())
            .map(|(a, c)| (*a as u8) * 128 + (*c as u8) * 127)
            .collect();
        let path = golden_dir().join(format!("shadow_{k}.png"));
        if regenerate {
            photostereo::io::output::write_png8(&path, 96, 72, 1, &bytes).unwrap();
            continue;
        }
        let truth = image::open(&path)
            .unwrap_or_else(|e| {
                panic!(
                    "{}: {e}; run with REGENERATE=1 to create it",
                    path.display()
                )
            })
            .into_luma8();
        let differ = truth
            .as_raw()
            .iter()
            .zip(&bytes)
            .filter(|(a, b)| a != b)
            .count();
        assert!(differ <= 3, "{}: {differ} pixels differ", path.display());
        // The scene does cast shadows under every light.
        assert!(
            c.count() > 50,
            "light {k}: {} cast-shadow pixels",
            c.count()
        );
    }
}
