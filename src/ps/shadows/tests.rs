use super::*;
use crate::eval::metrics::angular_error_map;
use crate::progress::Silent;
use crate::ps::solve::{Method, solve};
use crate::synth::reflectance::Material;
use crate::synth::render::{RenderOptions, render};
use crate::synth::scene::{Albedo, SceneKind};

/// A rendered scene: its stack, lights, mask and true normals.
struct Rendered {
    stack: ImageStack,
    lights: Lights,
    mask: Mask,
    truth: crate::grid::NormalMap,
    /// Per light, the pixels in a cast shadow and in an attached one.
    cast: Vec<Mask>,
    attached: Vec<Mask>,
}

fn rendered(kind: SceneKind, size: usize, lights: usize, noise: f32, ambient: f32) -> Rendered {
    let scene = kind.build(size, Albedo::Constant(0.7), Material::lambertian());
    let lights = Lights::fibonacci(lights, 25.0).unwrap();
    let r = render(
        &scene,
        &lights,
        &RenderOptions {
            noise_sigma: noise,
            ambient,
            seed: 11,
            ..RenderOptions::default()
        },
    )
    .unwrap();
    Rendered {
        stack: r
            .to_stack(&lights, crate::capture::stack::ColorMode::Grey)
            .unwrap(),
        lights,
        mask: r.truth.mask.clone(),
        truth: r.truth.normals.clone(),
        cast: r.cast.clone(),
        attached: r.attached.clone(),
    }
}

/// Mean angular error (degrees) over the pixels solved in both, and the unsolved counts.
fn errors(a: &Solution, b: &Solution, r: &Rendered) -> (f64, f64, usize, usize) {
    let normals = |s: &Solution| crate::ps::normals::albedo_and_normals(s).1;
    let (na, nb) = (normals(a), normals(b));
    let ea = angular_error_map(&na, &r.truth, &r.mask).unwrap();
    let eb = angular_error_map(&nb, &r.truth, &r.mask).unwrap();
    let (mut sa, mut sb, mut n, mut ua, mut ub) = (0.0, 0.0, 0usize, 0, 0);
    for i in 0..r.mask.len() {
        if !r.mask.data()[i] {
            continue;
        }
        let (x, y) = (ea.data()[i], eb.data()[i]);
        ua += usize::from(!x.is_finite());
        ub += usize::from(!y.is_finite());
        if x.is_finite() && y.is_finite() {
            sa += f64::from(x);
            sb += f64::from(y);
            n += 1;
        }
    }
    (sa / n as f64, sb / n as f64, ua, ub)
}

/// The default method on `r` without and with the labels (default options).
fn with_and_without(r: &Rendered, method: Method) -> (Solution, Solution) {
    let base = SolveOptions::with_method(method);
    let a = solve(&r.stack, 0, &r.lights, &r.mask, &base, &Silent).unwrap();
    let opts = SolveOptions {
        shadow_labels: Some(ShadowLabelOptions::default()),
        ..base
    };
    let b = solve(&r.stack, 0, &r.lights, &r.mask, &opts, &Silent).unwrap();
    (a, b)
}

/// Cast shadows lifted above the per-pixel threshold by ambient light (0.1 of the albedo):
/// the torus on its ground plane and the demo scene under 6 and 12 lights, noise σ = 0.01.
/// The labels take those samples out of the fit: the default method's mean error (over the
/// pixels solved both ways) falls by more than a quarter — measured 5.67° → 3.2° and
/// 3.63° → 2.6° on the torus, 4.58° → 2.9° on the demo.
#[test]
fn labels_cut_the_error_of_cast_shadows_above_the_threshold() {
    for (kind, lights) in [
        (SceneKind::Torus, 6),
        (SceneKind::Torus, 12),
        (SceneKind::Demo, 6),
    ] {
        let r = rendered(kind, 128, lights, 0.01, 0.1);
        let (a, b) = with_and_without(&r, Method::Auto);
        let (before, after, ua, ub) = errors(&a, &b, &r);
        assert!(
            after < 0.75 * before,
            "{} under {lights} lights: {before:.3}° → {after:.3}°",
            kind.name()
        );
        assert!(ub <= ua, "{ua} → {ub} unsolved");
        let s = b.shadow_labels.unwrap();
        assert!(
            s.removed > 0 && s.refitted > 0 && s.rounds == DEFAULT_ROUNDS,
            "{s:?}"
        );
    }
}

/// Where the rule already finds every shadow (no ambient light: shadowed samples are noise
/// around 0) or there are no cast shadows (a lone sphere), the labels change next to nothing
/// and never cost more than 0.5% of the mean error (measured: torus 2.136° → 2.12°, sphere
/// unchanged to 0.1%).
#[test]
fn labels_do_no_harm_where_the_rule_suffices() {
    for (kind, lights, noise) in [(SceneKind::Torus, 6, 0.02), (SceneKind::Sphere, 12, 0.01)] {
        let r = rendered(kind, 96, lights, noise, 0.0);
        for method in [Method::Auto, Method::Threshold] {
            let (a, b) = with_and_without(&r, method);
            let (before, after, ua, ub) = errors(&a, &b, &r);
            assert!(
                after <= 1.005 * before,
                "{} {}: {before:.4}° → {after:.4}°",
                kind.name(),
                method.name()
            );
            assert_eq!(ua, ub);
        }
    }
}

/// Against the renderer's cast-shadow masks (torus, 12 lights, ambient 0.1, σ = 0.01): of the
/// cast-shadowed samples the per-pixel rule keeps (the ambient light lifts them above 0.1 of
/// the brightest), the labels call most shadow; of the samples truly lit, very few.
#[test]
fn labels_find_the_cast_shadows_the_rule_keeps() {
    let r = rendered(SceneKind::Torus, 128, 12, 0.01, 0.1);
    let options = SolveOptions::default();
    let solution = solve(&r.stack, 0, &r.lights, &r.mask, &options, &Silent).unwrap();
    let sigma = solution.noise.clone();
    let mut pass = Pass::new(&r.stack, 0, &r.lights, &r.mask, &options, &solution, sigma);
    pass.run(&ShadowLabelOptions::default());
    let n = pass.pixel.len();
    let (mut cast_kept, mut cast_caught, mut lit, mut lit_shadow) = (0, 0, 0, 0);
    for k in 0..r.lights.len() {
        for (i, &p) in pass.pixel.iter().enumerate() {
            let j = k * n + i;
            let cast = r.cast[k].data()[p];
            let attached = r.attached[k].data()[p];
            if cast && pass.kept[j] == 1 {
                cast_kept += 1;
                cast_caught += usize::from(pass.lit[j] == 0);
            }
            if !cast && !attached {
                lit += 1;
                lit_shadow += usize::from(pass.lit[j] == 0);
            }
        }
    }
    let caught = cast_caught as f64 / cast_kept as f64;
    let false_shadow = lit_shadow as f64 / lit as f64;
    // Measured: 1720 kept, 93% caught; 0.03% of the lit samples called shadow.
    assert!(cast_kept > 1000, "{cast_kept}");
    assert!(caught > 0.85, "{caught}");
    assert!(false_shadow < 0.005, "{false_shadow}");
}

/// Bad options and a solution of another size are errors, not panics; an empty mask is no
/// work.
#[test]
fn bad_inputs_are_errors() {
    let r = rendered(SceneKind::Sphere, 24, 8, 0.01, 0.0);
    let options = SolveOptions::default();
    let mut solution = solve(&r.stack, 0, &r.lights, &r.mask, &options, &Silent).unwrap();
    for bad in [
        ShadowLabelOptions {
            smoothness: -1.0,
            rounds: 2,
        },
        ShadowLabelOptions {
            smoothness: f64::NAN,
            rounds: 2,
        },
        ShadowLabelOptions {
            smoothness: 1.0,
            rounds: 0,
        },
    ] {
        let err = label_shadows(
            &r.stack,
            0,
            &r.lights,
            &r.mask,
            &options,
            &bad,
            &mut solution,
        )
        .unwrap_err();
        assert!(matches!(err, Error::InvalidParameter { .. }), "{err}");
        let in_options = SolveOptions {
            shadow_labels: Some(bad),
            ..options
        };
        assert!(in_options.validate().is_err());
    }
    let mut small = solve(&r.stack, 0, &r.lights, &r.mask, &options, &Silent)
        .unwrap()
        .top_rows(10);
    let err = label_shadows(
        &r.stack,
        0,
        &r.lights,
        &r.mask,
        &options,
        &ShadowLabelOptions::default(),
        &mut small,
    )
    .unwrap_err();
    assert!(matches!(err, Error::DimensionMismatch { .. }), "{err}");
    // An empty mask (a band of rows with no masked pixel) labels nothing.
    let empty = Mask::new(r.mask.width(), r.mask.height(), false);
    let mut none = solve(&r.stack, 0, &r.lights, &empty, &options, &Silent).unwrap();
    let s = label_shadows(
        &r.stack,
        0,
        &r.lights,
        &empty,
        &options,
        &ShadowLabelOptions::default(),
        &mut none,
    )
    .unwrap();
    assert_eq!((s.samples, s.refitted), (0, 0));
}

#[test]
#[ignore = "measurement: prints the table of docs/photometric-stereo.md"]
fn measure_rendered() {
    println!(
        "| scene | lights | noise σ | ambient | auto | auto + labels | threshold | threshold + labels | labels time |"
    );
    println!("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |");
    for kind in [SceneKind::Bumps, SceneKind::Torus, SceneKind::Demo] {
        for lights in [6, 12] {
            for (noise, ambient) in [(0.02, 0.0), (0.01, 0.1)] {
                let r = rendered(kind, 128, lights, noise, ambient);
                let mut line = format!("| {} | {lights} | {noise} | {ambient} |", kind.name());
                let mut time = 0.0;
                for method in [Method::Auto, Method::Threshold] {
                    let (a, b) = with_and_without(&r, method);
                    let (ea, eb, _, _) = errors(&a, &b, &r);
                    line += &format!(" {ea:.2}° | {eb:.2}° |");
                    time += b.shadow_labels.unwrap().seconds;
                }
                println!("{line} {:.0} ms |", 0.5 * time * 1e3);
            }
        }
    }
}

/// A run with the labels on reports what they changed, once per solved channel; with them off
/// (the default) the report has no such entry.
#[test]
fn the_run_reports_the_labels_when_on() {
    use crate::run::pipeline::{Config, reconstruct};
    let r = rendered(SceneKind::Torus, 48, 8, 0.01, 0.1);
    let capture = crate::capture::dataset::Capture::from_stack(
        r.stack.clone(),
        r.lights.clone(),
        Some(r.mask.clone()),
    )
    .unwrap();
    let off = Config {
        integration: None,
        ..Config::default()
    };
    let on = Config {
        solve: SolveOptions {
            shadow_labels: Some(ShadowLabelOptions::default()),
            ..SolveOptions::default()
        },
        ..off
    };
    let without = reconstruct(&capture, &off, &Silent).unwrap();
    assert!(without.model.shadow_labels.is_empty());
    let with = reconstruct(&capture, &on, &Silent).unwrap();
    let s = &with.model.shadow_labels;
    assert_eq!(s.len(), 1);
    assert_eq!(s[0].samples, r.mask.count() * r.lights.len());
    assert!(s[0].removed > 0 && s[0].refitted > 0, "{s:?}");
    let json = serde_json::to_value(&without.model).unwrap();
    assert!(json.get("shadow_labels").is_none(), "{json}");
}
