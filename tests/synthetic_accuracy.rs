//! Accuracy on scenes the crate renders itself, against closed forms.

use nalgebra::{Matrix3, Vector3};
use photostereo::capture::lights::Lights;
use photostereo::eval::demo::synthesize;
use photostereo::eval::metrics::{albedo_relative_error, angular_errors, depth_errors};
use photostereo::integrate::Integrator;
use photostereo::progress::Silent;
use photostereo::ps::solve::{Method, SolveOptions};
use photostereo::run::pipeline::{Config, reconstruct};
use photostereo::synth::render::RenderOptions;
use photostereo::synth::scene::{Albedo, Object, Primitive, Scene};

/// Twelve lights 30°–90° above the image plane: every sphere pixel near the rim is in attached
/// shadow for some of them.
fn twelve_lights() -> Lights {
    Lights::fibonacci(12, 30.0).unwrap()
}

#[test]
fn noise_free_sphere_is_recovered_by_both_integrators() {
    let scene = Scene::sphere(
        160,
        70.0,
        Albedo::Smooth {
            mean: 0.6,
            amplitude: 0.2,
            period: 37.0,
        },
    );
    let synth = synthesize(scene, twelve_lights(), &RenderOptions::default()).unwrap();
    // Attached shadows really occur.
    let shadowed: usize = synth
        .rendering
        .attached
        .iter()
        .map(|m| {
            m.data()
                .iter()
                .zip(synth.truth.mask.data())
                .filter(|(s, m)| **s && **m)
                .count()
        })
        .sum();
    assert!(shadowed > 1000, "only {shadowed} shadowed samples");
    for method in [Method::Threshold, Method::ShadowWeighted] {
        for integrator in [Integrator::Poisson, Integrator::Path] {
            let config = Config {
                solve: SolveOptions {
                    method,
                    ..SolveOptions::default()
                },
                integration: Some(photostereo::integrate::IntegrationOptions {
                    method: integrator,
                    ..Default::default()
                }),
                ..Config::default()
            };
            let recon = reconstruct(&synth.capture, &config, &Silent).unwrap();
            let t = &synth.truth;
            let n = angular_errors(&recon.maps.normals, &t.normals, &t.mask).unwrap();
            let (alb, _) =
                albedo_relative_error(&recon.maps.albedo[0], &t.albedo, &t.mask).unwrap();
            let d = depth_errors(recon.depth().unwrap(), &t.depth, &t.mask).unwrap();
            println!(
                "{method:?} {integrator:?}: mean {:.4}° over {} px ({} unsolved), albedo {:.5}, depth RMSE {:.4} = {:.4}% of range",
                n.mean_deg,
                n.pixels,
                n.missing,
                alb,
                d.rmse,
                100.0 * d.rmse_over_range
            );
            assert!(n.mean_deg <= 0.05, "mean angular error {}°", n.mean_deg);
            assert!(n.missing * 100 < n.pixels, "{} pixels unsolved", n.missing);
            assert!(alb <= 1e-3, "albedo relative error {alb}");
            assert!(
                d.rmse_over_range <= 0.01,
                "depth RMSE {} of range",
                d.rmse_over_range
            );
        }
    }
}

#[test]
fn plain_least_squares_is_biased_by_attached_shadows() {
    // The reference estimator ignores max(0, ·): where some lights are behind the surface its
    // normals tilt. This is why the default rejects shadowed samples.
    let scene = Scene::sphere(160, 70.0, Albedo::Constant(0.6));
    let synth = synthesize(scene, twelve_lights(), &RenderOptions::default()).unwrap();
    let config = Config {
        solve: SolveOptions::least_squares(),
        integration: None,
        ..Config::default()
    };
    let recon = reconstruct(&synth.capture, &config, &Silent).unwrap();
    let n = angular_errors(&recon.maps.normals, &synth.truth.normals, &synth.truth.mask).unwrap();
    println!("ls on a shadowed sphere: mean {:.3}°", n.mean_deg);
    assert!(n.mean_deg > 1.0, "ls mean error only {}°", n.mean_deg);
}

/// With white noise of σ on every image and all lights lit, least squares has covariance
/// σ²(LᵀL)⁻¹: E|ĝ − g|² = σ² tr((LᵀL)⁻¹), and the normal's angular error (the part of δg
/// perpendicular to N, over ρ) has E[θ²] = σ² tr(P⊥(LᵀL)⁻¹)/ρ² with P⊥ = I − NNᵀ.
#[test]
fn noise_matches_the_least_squares_prediction() {
    let (rho, sigma) = (0.5f32, 0.01f32);
    // A flat surface facing the camera, lit by lights 40°–90° up: every sample is lit.
    let scene = Scene {
        width: 200,
        height: 200,
        objects: vec![Object::ground(Albedo::Constant(rho))],
    };
    let lights = Lights::fibonacci(12, 40.0).unwrap();
    let options = RenderOptions {
        noise_sigma: sigma,
        seed: 11,
        ..RenderOptions::default()
    };
    let synth = synthesize(scene, lights.clone(), &options).unwrap();
    let config = Config {
        solve: SolveOptions::least_squares(),
        integration: None,
        ..Config::default()
    };
    let recon = reconstruct(&synth.capture, &config, &Silent).unwrap();
    let gram: Matrix3<f64> = lights
        .directions()
        .iter()
        .fold(Matrix3::zeros(), |a, l| a + l * l.transpose());
    let m = gram.try_inverse().unwrap();
    let n = Vector3::z();
    let (s2, r2) = (f64::from(sigma).powi(2), f64::from(rho).powi(2));
    let predicted_g = s2 * m.trace() / r2;
    let predicted_angle = s2 * (m.trace() - n.dot(&(m * n))) / r2;
    let (mut sum_g, mut sum_a, mut count) = (0.0, 0.0, 0usize);
    for (i, nn) in recon.maps.normals.data().iter().enumerate() {
        let g = nn.cast::<f64>() * f64::from(recon.maps.albedo[0].data()[i]);
        let dg = g - n * f64::from(rho);
        sum_g += dg.norm_squared() / r2;
        sum_a += nn.cast::<f64>().dot(&n).clamp(-1.0, 1.0).acos().powi(2);
        count += 1;
    }
    let (measured_g, measured_angle) = (sum_g / count as f64, sum_a / count as f64);
    println!(
        "E|δg|²/ρ²: measured {measured_g:.4e}, predicted {predicted_g:.4e}; E[θ²]: measured {measured_angle:.4e} rad², predicted {predicted_angle:.4e}"
    );
    assert!((measured_g / predicted_g - 1.0).abs() < 0.15);
    assert!((measured_angle / predicted_angle - 1.0).abs() < 0.15);
}

/// Cast shadows: the default estimator still recovers the normals of the built-in scene (a
/// hemisphere, bump, pyramid and dome casting shadows on the ground) when noise-free.
#[test]
fn default_scene_with_cast_shadows_is_recovered() {
    let synth = photostereo::eval::demo::default_capture(0.0, 1).unwrap();
    let cast: usize = synth.rendering.cast.iter().map(|m| m.count()).sum();
    assert!(cast > 10_000, "only {cast} cast-shadow samples");
    let config = Config {
        integration: Some(photostereo::integrate::IntegrationOptions {
            method: Integrator::Poisson,
            ..Default::default()
        }),
        ..Config::default()
    };
    let recon = reconstruct(&synth.capture, &config, &Silent).unwrap();
    let n = angular_errors(&recon.maps.normals, &synth.truth.normals, &synth.truth.mask).unwrap();
    let d = depth_errors(
        recon.depth().unwrap(),
        &synth.truth.depth,
        &synth.truth.mask,
    )
    .unwrap();
    println!(
        "default scene: mean {:.4}°, p95 {:.4}°, depth {:.3}% of range",
        n.mean_deg,
        n.p95_deg,
        100.0 * d.rmse_over_range
    );
    assert!(n.mean_deg < 0.05 && n.p95_deg < 0.05, "{n:?}");
    assert!(d.rmse_over_range < 0.02, "{d:?}");
}

/// A second shape family: a pyramid (planar facets, creases) and a Gaussian bump on a ground
/// plane, noise-free: creases break nothing in the per-pixel solve.
#[test]
fn bumps_and_creases_on_a_ground_plane() {
    let pyramid = Primitive::Pyramid {
        cx: -25.0,
        cy: 0.0,
        half: 25.0,
        height: 15.0,
        base: 0.0,
    };
    let bump = Primitive::Gaussian {
        cx: 30.0,
        cy: 5.0,
        sigma: 12.0,
        height: 18.0,
        base: 0.0,
    };
    let scene = Scene {
        width: 128,
        height: 96,
        objects: vec![
            Object::ground(Albedo::Constant(0.5)),
            Object::new(pyramid, Albedo::Constant(0.7)),
            Object::new(
                bump,
                Albedo::Checker {
                    size: 8.0,
                    a: 0.4,
                    b: 0.8,
                },
            ),
        ],
    };
    let synth = synthesize(scene, twelve_lights(), &RenderOptions::default()).unwrap();
    let recon = reconstruct(&synth.capture, &Config::default(), &Silent).unwrap();
    let n = angular_errors(&recon.maps.normals, &synth.truth.normals, &synth.truth.mask).unwrap();
    let d = depth_errors(
        recon.depth().unwrap(),
        &synth.truth.depth,
        &synth.truth.mask,
    )
    .unwrap();
    println!(
        "bumps: mean {:.4}°, depth {:.3}% of range",
        n.mean_deg,
        100.0 * d.rmse_over_range
    );
    assert!(n.mean_deg < 0.05);
    assert!(d.rmse_over_range < 0.01);
}
