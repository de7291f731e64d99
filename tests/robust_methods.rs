//! The robust estimators and the automatic method on rendered scenes with ground truth: a
//! sphere on a ground plane beside a pyramid (attached and cast shadows), matte and glossy.

mod common;

use photostereo::capture::dataset::Capture;
use photostereo::eval::metrics::angular_errors;
use photostereo::progress::Silent;
use photostereo::ps::solve::{Method, SolveOptions};
use photostereo::run::pipeline::{Config, Reconstruction, reconstruct};
use photostereo::synth::reflectance::{BlinnPhong, Material, Specular, TorranceSparrow};
use photostereo::synth::render::Rendering;

fn rendered(material: Material) -> (Capture, Rendering) {
    common::sphere_on_ground(material, 32, 96)
}

fn run(capture: &Capture, r: &Rendering, method: Method) -> (f64, Reconstruction) {
    let config = Config {
        solve: SolveOptions::with_method(method),
        integration: None,
        ..Config::default()
    };
    let recon = reconstruct(capture, &config, &Silent).unwrap();
    let e = angular_errors(&recon.maps.normals, &r.truth.normals, &capture.mask).unwrap();
    assert_eq!(e.missing, 0, "{}: unsolved pixels", method.name());
    (e.mean_deg, recon)
}

/// On a matte scene Lambert's law fits: the automatic method refits almost no pixel, keeps no
/// intensity correction, and equals threshold least squares.
#[test]
fn auto_uses_no_more_model_than_a_matte_scene_needs() {
    let (capture, r) = rendered(Material::lambertian());
    let (threshold, _) = run(&capture, &r, Method::Threshold);
    let (auto, recon) = run(&capture, &r, Method::Auto);
    println!(
        "matte: threshold {threshold:.3}°, auto {auto:.3}° with {:.3}% robust pixels",
        100.0 * recon.model.robust_fraction
    );
    // Measured 0.02% of the pixels (the χ² test's 0.1% false-alarm rate, less in shadows).
    assert!(recon.model.robust_fraction < 0.005, "{:?}", recon.model);
    assert!((auto - threshold).abs() < 0.01, "{auto} vs {threshold}");
    // Noise-only data: the estimated gains stay within 1% of the truth (all 1).
    for g in recon.model.gains.iter().flatten() {
        assert!((g - 1.0).abs() < 0.01, "gain {g}");
    }
    // σ estimated per image within 15% of the rendered 0.005 (the images are divided by unit
    // intensities, so σ carries over).
    for s in recon.model.noise.iter().flatten() {
        assert!((s - 0.005).abs() < 0.00075, "σ {s}");
    }
}

/// Glossy scenes: least squares and threshold rejection are degrees off, the specular-rejecting
/// and automatic methods stay within half a degree, for two different lobe models.
#[test]
fn auto_and_specular_reject_highlights() {
    for (name, lobe) in [
        (
            "blinn-phong",
            Specular::BlinnPhong(BlinnPhong {
                ks: 0.2,
                exponent: 50.0,
            }),
        ),
        (
            "torrance-sparrow",
            Specular::TorranceSparrow(TorranceSparrow {
                ks: 0.2,
                roughness: 0.2,
                f0: 1.0,
            }),
        ),
    ] {
        let (capture, r) = rendered(Material::with_specular(lobe));
        let (threshold, _) = run(&capture, &r, Method::Threshold);
        let (specular, _) = run(&capture, &r, Method::Specular);
        let (tukey, _) = run(&capture, &r, Method::Tukey);
        let (auto, recon) = run(&capture, &r, Method::Auto);
        println!(
            "{name}: threshold {threshold:.2}°, tukey {tukey:.2}°, specular {specular:.2}°, auto {auto:.2}° ({:.1}% robust)",
            100.0 * recon.model.robust_fraction
        );
        // Measured (96², 32 lights): threshold 5.0°, tukey 2.3–2.7°, specular 0.35°, auto 0.32°.
        assert!(threshold > 3.0, "{name}: threshold {threshold}");
        assert!(tukey < threshold, "{name}: tukey {tukey}");
        assert!(specular < 0.6, "{name}: specular {specular}");
        assert!(auto < 0.6, "{name}: auto {auto}");
        assert!(recon.model.robust_fraction > 0.5);
    }
}

/// Highlights must not read as intensity errors. On glossy scenes with exact intensities the
/// estimated gains stay within 3% of 1 up to k_s = 0.4 (before gain ratios were restricted to
/// samples outside the specular cone they strayed 5% at k_s = 0.2 and 10% at 0.4), and where
/// the highlights defeat the robust fit (k_s = 0.8) the estimate fits the data no better than
/// the stated intensities and is reported but not applied.
#[test]
fn highlights_do_not_become_intensity_corrections() {
    for ks in [0.2, 0.4, 0.8] {
        let lobe = Specular::BlinnPhong(BlinnPhong { ks, exponent: 50.0 });
        let (capture, r) = rendered(Material::with_specular(lobe));
        let (_, recon) = run(&capture, &r, Method::Auto);
        let estimate = photostereo::ps::intensities::estimate_gains(
            &capture.stack,
            0,
            &capture.lights,
            &capture.mask,
            &SolveOptions::with_method(Method::Auto),
        )
        .unwrap();
        let worst = estimate
            .estimated
            .iter()
            .map(|g| (g - 1.0).abs())
            .fold(0.0f32, f32::max);
        println!(
            "k_s {ks}: estimated gains within {:.3} of 1, applied {}, misfit {:.4} vs unit {:.4}",
            worst, estimate.applied, estimate.misfit, estimate.unit_misfit
        );
        if ks <= 0.4 {
            assert!(worst < 0.03, "k_s {ks}: gain {worst} from 1");
        } else {
            assert!(!estimate.applied, "k_s {ks}: runaway gains applied");
        }
        for g in recon.model.gains.iter().flatten() {
            assert!((g - 1.0).abs() < 0.03, "k_s {ks}: applied gain {g}");
        }
    }
}

/// A strong highlight must not set the shadow threshold: relative to a highlight tens of times
/// the diffuse level, the threshold drops the diffuse samples and leaves the pixel to the lobe
/// (issue 24: DiLiGenT reading lost 1,257 pixels and erred 64° where the brightest sample was
/// over six times the 90th percentile). With the brightest tenth set aside the reference is a
/// diffuse sample. The two references are compared without `auto`'s refit with specular
/// lobes, which rescues part of the damage (3.2° with the brightest sample as the reference;
/// tested in `tests/lobes.rs`); the default, with it, must be no worse than the rejection.
#[test]
fn a_strong_highlight_does_not_set_the_shadow_threshold() {
    let lobe = Specular::BlinnPhong(BlinnPhong {
        ks: 0.8,
        exponent: 50.0,
    });
    let (capture, r) = rendered(Material::with_specular(lobe));
    let solve = |highlight_fraction, lobes| {
        let config = Config {
            solve: SolveOptions {
                highlight_fraction,
                lobes,
                ..SolveOptions::default()
            },
            integration: None,
            ..Config::default()
        };
        let recon = reconstruct(&capture, &config, &Silent).unwrap();
        angular_errors(&recon.maps.normals, &r.truth.normals, &capture.mask).unwrap()
    };
    let brightest = solve(0.0, false);
    let tenth = solve(photostereo::ps::solve::DEFAULT_HIGHLIGHT_FRACTION, false);
    let default = solve(photostereo::ps::solve::DEFAULT_HIGHLIGHT_FRACTION, true);
    println!(
        "k_s 0.8: brightest sample as reference {:.2}° ({} unsolved), brightest tenth set aside {:.2}° ({} unsolved)",
        brightest.mean_deg, brightest.missing, tenth.mean_deg, tenth.missing
    );
    // Measured 20.4° against 0.68° (`bench specularity`, 32 lights, 96²).
    assert!(brightest.mean_deg > 5.0, "{brightest:?}");
    assert!(tenth.mean_deg < 1.5, "{tenth:?}");
    assert_eq!(tenth.missing, 0);
    // The default, with the refit: no worse than the rejection alone.
    assert!(
        default.mean_deg <= tenth.mean_deg,
        "{default:?} vs {tenth:?}"
    );
}
