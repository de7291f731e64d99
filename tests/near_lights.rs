//! Near-light photometric stereo on rendered LED rigs (`photostereo::eval::near`): the near
//! model recovers normals and absolute depth where the distant approximation fails, the
//! solver says when it stops at its cap, and bad light files are refused.

mod common;

use photostereo::Intrinsics;
use photostereo::capture::lights::Lights;
use photostereo::capture::stack::ColorMode;
use photostereo::eval::near::{NearCase, run_case};
use photostereo::integrate::Integrator;
use photostereo::progress::Silent;
use photostereo::ps::near::{NearOptions, solve_near};
use photostereo::synth::near::{NearPlacement, render_near, two_ring_rig};
use photostereo::synth::reflectance::{BlinnPhong, Material, Specular};
use photostereo::synth::render::RenderOptions;
use photostereo::synth::scene::{Albedo, Scene, SceneKind};

/// Sphere, vase and bumps on a plane, 16 Lambertian-profile LEDs (μ = 1) at 2, 5 and 10 object
/// sizes, 1% read noise: the near model is within 1° and 1% of the depth range (absolute depth:
/// its scale comes from the fall-off), and the distant approximation is at least three times
/// further off in normals at every distance.
#[test]
fn near_model_recovers_normals_and_absolute_depth() {
    let options = masked_ls();
    for kind in [SceneKind::Sphere, SceneKind::Vase, SceneKind::Bumps] {
        for distance in [2.0, 5.0, 10.0] {
            let case = NearCase {
                kind,
                size: 128,
                light_distance: distance,
                lights: 16,
                noise: 0.01,
                mu: 1.0,
                material: Material::lambertian(),
            };
            let r = run_case(&case, &options).unwrap();
            let name = format!("{} at {distance} sizes", kind.name());
            println!(
                "{name}: near {:.3}° {:.3}% in {} steps, distant {:.2}° {:.2}%",
                r.near_normal_deg,
                100.0 * r.near_depth,
                r.iterations,
                r.distant_normal_deg,
                100.0 * r.distant_depth
            );
            assert!(r.converged, "{name}: not converged");
            assert!(r.near_normal_deg <= 1.0, "{name}: {}°", r.near_normal_deg);
            assert!(r.near_depth <= 0.01, "{name}: depth {}", r.near_depth);
            assert!(
                r.distant_normal_deg >= 3.0 * r.near_normal_deg,
                "{name}: distant {}° against near {}°",
                r.distant_normal_deg,
                r.near_normal_deg
            );
        }
    }
}

/// The near model with the default integrator (`auto`) on noise-free data: exact to the
/// rendering's precision (0.01°, 0.1% of the range), so that any bias in the light model, the
/// perspective integration or the scale fit shows.
#[test]
fn near_model_is_exact_without_noise() {
    for kind in [SceneKind::Sphere, SceneKind::Vase] {
        let case = NearCase {
            kind,
            size: 96,
            light_distance: 3.0,
            lights: 12,
            noise: 0.0,
            mu: 0.0,
            material: Material::lambertian(),
        };
        let r = run_case(&case, &NearOptions::default()).unwrap();
        println!(
            "{}: {:.4}° {:.4}%",
            kind.name(),
            r.near_normal_deg,
            100.0 * r.near_depth
        );
        assert!(
            r.near_normal_deg < 0.01,
            "{}: {}°",
            kind.name(),
            r.near_normal_deg
        );
        assert!(r.near_depth < 0.001, "{}: {}", kind.name(), r.near_depth);
    }
}

/// The near solve's defaults with masked least squares as its integrator.
fn masked_ls() -> NearOptions {
    NearOptions {
        integration: photostereo::IntegrationOptions {
            method: Integrator::MaskedLs,
            ..Default::default()
        },
        ..NearOptions::default()
    }
}

fn sphere_capture() -> (
    photostereo::ImageStack,
    Lights,
    photostereo::Mask,
    Intrinsics,
) {
    let scene = Scene::sphere(64, 25.0, Albedo::Constant(0.7));
    let placement = NearPlacement {
        distance: 200.0,
        scale: 1.0,
    };
    let camera = placement.camera(&scene);
    let lights = two_ring_rig(
        8,
        200.0,
        photostereo::nalgebra::Vector3::new(0.0, 0.0, -200.0),
        0.0,
    )
    .unwrap();
    let r = render_near(
        &scene,
        &lights,
        &camera,
        &placement,
        &RenderOptions::default(),
    )
    .unwrap();
    let stack = r.to_stack(&lights, ColorMode::Grey).unwrap();
    (stack, lights, r.truth.mask, camera)
}

/// A cap of one alternation is reported as not converged, with its step; the default run
/// converges.
#[test]
fn an_iteration_cap_is_reported() {
    let (stack, lights, mask, camera) = sphere_capture();
    let options = NearOptions {
        max_iterations: 1,
        tolerance: 1e-9,
        start_distance: Some(190.0),
        ..NearOptions::default()
    };
    let s = solve_near(&stack, 0, &lights, &mask, &camera, &options, &Silent).unwrap();
    assert!(!s.converged);
    assert_eq!(s.steps.len(), 1);
    // A given start distance is the start plane itself.
    assert_eq!(s.start_distance, 190.0);
    let full = solve_near(
        &stack,
        0,
        &lights,
        &mask,
        &camera,
        &NearOptions::default(),
        &Silent,
    )
    .unwrap();
    assert!(full.converged && full.steps.len() > 1);
    assert!(full.steps.last().unwrap().depth_change < photostereo::ps::near::DEFAULT_TOLERANCE);
}

/// Lights without a position, and bad options, are errors that name what is wrong.
#[test]
fn refuses_lights_without_positions_and_bad_options() {
    let (stack, lights, mask, camera) = sphere_capture();
    let mut plain = lights.lights().to_vec();
    plain[3].position = None;
    let plain = Lights::new(plain).unwrap();
    let e = solve_near(
        &stack,
        0,
        &plain,
        &mask,
        &camera,
        &NearOptions::default(),
        &Silent,
    )
    .unwrap_err();
    assert!(e.to_string().contains("position"), "{e}");
    assert!(e.to_string().contains('3'), "{e}");
    for bad in [
        NearOptions {
            max_iterations: 0,
            ..NearOptions::default()
        },
        NearOptions {
            tolerance: 0.0,
            ..NearOptions::default()
        },
        NearOptions {
            start_distance: Some(-1.0),
            ..NearOptions::default()
        },
    ] {
        assert!(solve_near(&stack, 0, &lights, &mask, &camera, &bad, &Silent).is_err());
    }
}

/// Highlights under near LEDs (Blinn–Phong, k_s 0.4, n 40, on the vase at 3 object sizes): the
/// default `auto` estimator works inside the near solve, rejecting the highlights that plain
/// threshold least squares fits, and the alternation converges. The highlights' tails still
/// bias the absolute distance (measured: 2.1% of the depth range, 0.26% of the distance, where
/// the Lambertian vase gives 0.08%; the shape after scaling is 0.07% off): a known limit of
/// the scale fit, bounded here so that it cannot grow unnoticed.
#[test]
fn auto_rejects_highlights_inside_the_near_solve() {
    let glossy = Material::with_specular(Specular::BlinnPhong(BlinnPhong {
        ks: 0.4,
        exponent: 40.0,
    }));
    let case = NearCase {
        kind: SceneKind::Vase,
        size: 96,
        light_distance: 3.0,
        lights: 24,
        noise: 0.005,
        mu: 1.0,
        material: glossy,
    };
    let auto = run_case(&case, &NearOptions::default()).unwrap();
    let threshold = run_case(
        &case,
        &NearOptions {
            solve: photostereo::SolveOptions::with_method(photostereo::Method::Threshold),
            ..NearOptions::default()
        },
    )
    .unwrap();
    println!(
        "auto {:.2}° {:.2}% ({} steps), threshold {:.2}° {:.2}%, distant {:.2}°",
        auto.near_normal_deg,
        100.0 * auto.near_depth,
        auto.iterations,
        threshold.near_normal_deg,
        100.0 * threshold.near_depth,
        auto.distant_normal_deg
    );
    assert!(auto.converged);
    assert!(auto.near_normal_deg < 1.0, "{}", auto.near_normal_deg);
    assert!(auto.near_depth < 0.03, "{}", auto.near_depth);
    assert!(
        auto.near_normal_deg < 0.5 * threshold.near_normal_deg,
        "auto {} against threshold {}",
        auto.near_normal_deg,
        threshold.near_normal_deg
    );
}

/// Each near light's position is checked against the other images: under the rendered rig
/// (sphere, vase, bumps on a plane at 96²; 16 Lambertian-profile LEDs at 3 and 6 object sizes;
/// noise 0.5% of the mean level) no light is named and none is 0.5° off; with light 6's
/// position turned by 10° about the object's centre it is named, alone, 10 ± 1.5° off, and the
/// position the images give it is within 0.5° of where it was rendered, seen from the object's
/// centre (measured: 0.03–0.11°; 9.9–11.0°; 0.00–0.12°).
#[test]
fn a_misplaced_near_light_is_named_and_the_right_ones_are_not() {
    use photostereo::nalgebra::{Rotation3, Unit, Vector3};
    let options = masked_ls();
    for kind in [SceneKind::Sphere, SceneKind::Vase, SceneKind::Bumps] {
        for sizes in [3.0, 6.0] {
            let scene = kind.build(96, Albedo::Constant(0.8), Material::lambertian());
            let reach = sizes * 96.0;
            let placement = NearPlacement {
                distance: reach,
                scale: 1.0,
            };
            let camera = placement.camera(&scene);
            let target = Vector3::new(0.0, 0.0, -reach);
            let lights = two_ring_rig(16, reach, target, 1.0).unwrap();
            let render = |sigma: f32| {
                render_near(
                    &scene,
                    &lights,
                    &camera,
                    &placement,
                    &RenderOptions {
                        noise_sigma: sigma,
                        seed: 5,
                        ..RenderOptions::default()
                    },
                )
                .unwrap()
            };
            let clean = render(0.0);
            let level = clean
                .images
                .iter()
                .flat_map(|p| p[0].data())
                .map(|&v| f64::from(v))
                .sum::<f64>()
                / (clean.images.len() * 96 * 96) as f64;
            let r = render(0.005 * level as f32);
            let stack = r.to_stack(&lights, ColorMode::Grey).unwrap();
            let mask = &r.truth.mask;
            let check = |given: &Lights| {
                let s = solve_near(&stack, 0, given, mask, &camera, &options, &Silent).unwrap();
                s.solution.light_agreement.unwrap()
            };
            let right = check(&lights);
            let truth = lights.lights()[5].position.unwrap();
            let axis = Unit::new_normalize((truth - target).cross(&Vector3::z()));
            let turned =
                target + Rotation3::from_axis_angle(&axis, 10f64.to_radians()) * (truth - target);
            let mut moved = lights.lights().to_vec();
            moved[5].position = Some(turned);
            let wrong = check(&Lights::new(moved).unwrap());
            let fit = wrong.lights[5].clone().unwrap();
            let p = fit.position.unwrap();
            let centre_angle =
                |a: Vector3<f64>, b: Vector3<f64>| (a - target).angle(&(b - target)).to_degrees();
            let back = centre_angle(Vector3::new(p[0], p[1], p[2]), truth);
            let worst = right.largest_deg();
            println!(
                "{} at {sizes} sizes: right worst {worst:.2}° (threshold {:.2}°); light 6 turned 10°: {:.2}° (threshold {:.2}°), fitted position {back:.2}° from the truth",
                kind.name(),
                right.threshold_deg.unwrap(),
                fit.disagreement_deg,
                wrong.threshold_deg.unwrap()
            );
            assert!(right.disagreeing.is_empty(), "{right:?}");
            assert!(worst < 0.5, "{}: {worst}° under the right rig", kind.name());
            assert_eq!(wrong.disagreeing, vec![5], "{wrong:?}");
            assert!(
                (fit.disagreement_deg - 10.0).abs() < 1.5,
                "{}: {}°",
                kind.name(),
                fit.disagreement_deg
            );
            assert!(back < 0.5, "{}: {back}° from the truth", kind.name());
        }
    }
}
