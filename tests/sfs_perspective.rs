//! Perspective shape from shading under a near point light (Prados & Faugeras 2005) on shapes
//! rendered by the crate's near-light renderer: the light at the camera centre (the
//! well-posed case) and off it, Lambertian and not, with noise; warm starts and refusals.
//!
//! Metrics: mean angle between normals over the mask (and over the pixels the method solved
//! from their own brightness), depth RMSE after removing the mean offset as a fraction of the
//! true depth range (the table of the orthographic methods uses the same), and the absolute
//! depth RMSE (this method returns absolute depth).
//!
//! `PS_SIZE=256 cargo test --release --test sfs_perspective -- --nocapture` prints the README's
//! table at 256².

mod common;

use photostereo::camera::Intrinsics;
use photostereo::capture::lights::{Light, Lights};
use photostereo::eval::metrics::{angular_errors, depth_errors};
use photostereo::grid::{Grid, Mask, ScalarMap};
use photostereo::nalgebra::Vector3;
use photostereo::sfs::SfsResult;
use photostereo::sfs::perspective::{PerspectiveOptions, PointLight, RefineOptions, solve};
use photostereo::synth::near::{NearPlacement, render_near};
use photostereo::synth::reflectance::{BlinnPhong, Diffuse, Material, Specular};
use photostereo::synth::render::RenderOptions;
use photostereo::synth::scene::{Albedo, HeightField, SceneKind};

const SHAPES: [SceneKind; 5] = [
    SceneKind::Sphere,
    SceneKind::Vase,
    SceneKind::Peaks,
    SceneKind::Relief,
    SceneKind::Bust,
];

fn size() -> usize {
    std::env::var("PS_SIZE")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(128)
}

/// A rendered capture: the image, its truth, the camera and the light (intensity D², so that
/// the image is about 1 where the surface faces the light).
struct Capture {
    image: ScalarMap,
    truth: HeightField,
    camera: Intrinsics,
    light: PointLight,
}

/// The scene `kind` at `size`², its base plane two sizes from the camera, under a light at
/// `slant_deg` from the optical axis as seen from the scene's centre (in the camera's plane,
/// azimuth 40°; 0: at the camera centre).
fn capture(
    kind: SceneKind,
    size: usize,
    slant_deg: f64,
    material: Material,
    noise: f32,
) -> Capture {
    capture_at(kind, size, (slant_deg, 40.0), material, noise)
}

/// [`capture`] with the light at (slant, azimuth) in degrees (azimuth from x right, y up).
fn capture_at(
    kind: SceneKind,
    size: usize,
    (slant_deg, azimuth_deg): (f64, f64),
    material: Material,
    noise: f32,
) -> Capture {
    let scene = kind.build(size, Albedo::Constant(1.0), material);
    let placement = NearPlacement {
        distance: 2.0 * size as f64,
        scale: 1.0,
    };
    let camera = placement.camera(&scene);
    let d = placement.distance;
    let azimuth = azimuth_deg.to_radians();
    let at = Vector3::new(azimuth.cos(), azimuth.sin(), 0.0) * (d * slant_deg.to_radians().tan());
    let mut light = Light::near(at, Vector3::new(0.0, 0.0, -d));
    light.intensity = [d * d; 3];
    let lights = Lights::new(vec![light]).unwrap();
    let options = RenderOptions {
        noise_sigma: noise,
        cast_shadows: true,
        seed: 3,
        ..RenderOptions::default()
    };
    let r = render_near(&scene, &lights, &camera, &placement, &options).unwrap();
    Capture {
        image: r.images[0][0].clone(),
        truth: r.truth,
        camera,
        light: PointLight {
            position: at,
            intensity: d * d,
        },
    }
}

/// `c` solved with `options`.
fn solve_capture(c: &Capture, options: &PerspectiveOptions) -> SfsResult {
    solve(&c.image, &c.truth.mask, &c.camera, &c.light, options).unwrap()
}

/// `c` solved with the default options but `refine`.
fn solve_with(c: &Capture, refine: Option<RefineOptions>) -> SfsResult {
    solve_capture(
        c,
        &PerspectiveOptions {
            refine,
            ..PerspectiveOptions::default()
        },
    )
}

/// Whether one of `out`'s warnings holds `words`.
fn warns(out: &SfsResult, words: &str) -> bool {
    out.report.warnings.iter().any(|w| w.contains(words))
}

struct Scores {
    normals_deg: f64,
    normals_solved_deg: f64,
    depth: f64,
    depth_absolute: f64,
    solved: f64,
}

fn score(out: &SfsResult, truth: &HeightField) -> Scores {
    let mask = &truth.mask;
    let solved: Mask = Grid::from_fn(mask.width(), mask.height(), |c, r| {
        *mask.at(c, r) && !*out.shadow.at(c, r)
    });
    let (mut lo, mut hi, mut se, mut n) = (f64::INFINITY, f64::NEG_INFINITY, 0.0, 0.0);
    for i in 0..mask.len() {
        if mask.data()[i] {
            let t = f64::from(truth.depth.data()[i]);
            lo = lo.min(t);
            hi = hi.max(t);
            se += (f64::from(out.depth.data()[i]) - t).powi(2);
            n += 1.0;
        }
    }
    Scores {
        normals_deg: angular_errors(&out.normals, &truth.normals, mask)
            .unwrap()
            .mean_deg,
        normals_solved_deg: angular_errors(&out.normals, &truth.normals, &solved)
            .unwrap()
            .mean_deg,
        depth: depth_errors(&out.depth, &truth.depth, mask)
            .unwrap()
            .rmse_over_range,
        depth_absolute: (se / n).sqrt() / (hi - lo),
        solved: solved.count() as f64 / mask.count() as f64,
    }
}

fn row(kind: SceneKind, light: &str, out: &SfsResult, s: &Scores) {
    println!(
        "| {} | {light} | {:.2}° | {:.2}° ({:.1}% fitted) | {:.2}% | {:.2}% | {}{}{} | {:.2} s |",
        kind.name(),
        s.normals_deg,
        s.normals_solved_deg,
        100.0 * s.solved,
        100.0 * s.depth,
        100.0 * s.depth_absolute,
        out.report.iterations,
        if out.report.converged {
            ""
        } else {
            " (not converged)"
        },
        out.report
            .refinement
            .as_ref()
            .map_or(String::new(), |r| format!(
                " + {} steps{}",
                r.iterations,
                if r.converged { "" } else { " (not converged)" }
            )),
        out.report.seconds
    );
}

fn header() {
    println!(
        "| scene | light | normals, mean | fitted pixels | depth RMSE / range | absolute | sweeps + refinement | time |"
    );
    println!("| --- | --- | --- | --- | --- | --- | --- | --- |");
}

/// The well-posed case: every shape within 5° and 5% of its depth range, swept and refined
/// (the default), converged well before the limits, without warnings; the swept solution's
/// absolute depth within 5% too. The refined absolute depth is printed, not asserted: on the
/// bust it is 5.2% (swept 4.2%), whose nose hides part of the face, a depth jump that no
/// continuous surface fits, and a least-squares fit spreads it into an offset.
#[test]
fn light_at_the_camera_recovers_every_shape() {
    let size = size();
    header();
    for kind in SHAPES {
        let c = capture(kind, size, 0.0, Material::lambertian(), 0.0);
        let (swept, out) = (
            solve_with(&c, None),
            solve_with(&c, Some(RefineOptions::default())),
        );
        let s0 = score(&swept, &c.truth);
        let s = score(&out, &c.truth);
        row(kind, "at the camera, swept only", &swept, &s0);
        row(kind, "at the camera", &out, &s);
        assert!(
            swept.report.converged && swept.report.iterations < 30,
            "{}",
            kind.name()
        );
        assert!(
            out.report.refinement.as_ref().is_some_and(|r| r.converged),
            "{}",
            kind.name()
        );
        for (what, s) in [("swept", &s0), ("refined", &s)] {
            assert!(
                s.normals_deg < 5.0 && s.depth < 0.05,
                "{} {what}: {:.2}° {:.4}",
                kind.name(),
                s.normals_deg,
                s.depth
            );
        }
        assert!(
            s0.depth_absolute < 0.05,
            "{}: {:.4}",
            kind.name(),
            s0.depth_absolute
        );
        assert!(out.report.warnings.is_empty(), "{:?}", out.report.warnings);
    }
}

/// A light 30° off the axis: where it grazes the surface the equation loses its coercivity and
/// cast shadows cut the characteristics that carry the shape downstream, so the swept solution
/// alone is 5–9° off on four of the five shapes. The refinement fits the image on every lit
/// cell from it: asserted, every shape within 5° and 5% of its depth range over the whole mask
/// (the bar), better than the swept solution on both, and converged.
#[test]
fn light_off_the_axis() {
    let size = size();
    header();
    for kind in SHAPES {
        let c = capture(kind, size, 30.0, Material::lambertian(), 0.0);
        let (swept, out) = (
            solve_with(&c, None),
            solve_with(&c, Some(RefineOptions::default())),
        );
        let (s0, s) = (score(&swept, &c.truth), score(&out, &c.truth));
        row(kind, "30° off, swept only", &swept, &s0);
        row(kind, "30° off the axis", &out, &s);
        let refined = out.report.refinement.as_ref().unwrap();
        assert!(out.report.converged && refined.converged, "{}", kind.name());
        assert!(
            s.normals_deg < 5.0 && s.depth < 0.05,
            "{}: {:.2}° {:.4}",
            kind.name(),
            s.normals_deg,
            s.depth
        );
        assert!(
            s.normals_deg < s0.normals_deg && s.depth < s0.depth,
            "{}: refined {:.2}° {:.4}, swept {:.2}° {:.4}",
            kind.name(),
            s.normals_deg,
            s.depth,
            s0.normals_deg,
            s0.depth
        );
    }
}

/// The largest relative change of depth from `a` to `b` over `mask`, every depth finite.
fn largest_relative_change(mask: &Mask, a: &SfsResult, b: &SfsResult) -> f64 {
    let mut worst = 0f64;
    for i in 0..mask.len() {
        if mask.data()[i] {
            let (x, y) = (a.depth.data()[i], b.depth.data()[i]);
            assert!(x.is_finite() && y.is_finite(), "pixel {i}: {x} against {y}");
            worst = worst.max(f64::from((x - y).abs() / x.abs()));
        }
    }
    worst
}

/// The relief at `size`² under a light 30° off the axis at azimuth 120°, solved swept only and
/// refined.
fn relief_lit_from_120(size: usize) -> (Capture, SfsResult, SfsResult) {
    swept_and_refined(SceneKind::Relief, size, (30.0, 120.0))
}

/// Lambertian `kind` at `size`² without noise under a light at (slant, azimuth), solved swept
/// only and refined.
fn swept_and_refined(
    kind: SceneKind,
    size: usize,
    light: (f64, f64),
) -> (Capture, SfsResult, SfsResult) {
    let c = capture_at(kind, size, light, Material::lambertian(), 0.0);
    let (swept, refined) = (
        solve_with(&c, None),
        solve_with(&c, Some(RefineOptions::default())),
    );
    (c, swept, refined)
}

/// The relief under a light 30° off the axis at azimuth 120° (128²): its refinement at half
/// resolution (64²) ran to its limit of 100 steps while the surface moved towards the camera as
/// a whole (ln Z down by 0.47, a 37% shorter distance) into a valley of lower energy, and that
/// change lowered the full resolution's energy too, so it was kept: 26.1° and 29% of the range
/// (225% absolute), from a swept solution of 5.1° and 7%. A refinement that moves the whole
/// surface by more than `MAX_SHIFT` in ln Z is now stopped and discarded at every level: the
/// full resolution refines the swept solution itself.
#[test]
fn a_refinement_does_not_move_the_whole_surface() {
    let (c, swept, out) = relief_lit_from_120(128);
    let (s0, s) = (score(&swept, &c.truth), score(&out, &c.truth));
    let r = out.report.refinement.as_ref().unwrap();
    // Converged at full resolution from the swept solution: the half-resolution change, which
    // ran away, was not kept.
    assert!(
        r.converged && !r.discarded && r.coarse_iterations == 0,
        "{r:?}"
    );
    assert!(
        s.normals_deg < 5.0 && s.depth < 0.05 && s.depth_absolute < 0.05,
        "{:.2}° {:.4} (absolute {:.4})",
        s.normals_deg,
        s.depth,
        s.depth_absolute
    );
    assert!(
        s.normals_deg < s0.normals_deg && s.depth < s0.depth,
        "refined {:.2}° {:.4}, swept {:.2}° {:.4}",
        s.normals_deg,
        s.depth,
        s0.normals_deg,
        s0.depth
    );
}

/// The same scene at 64², where the full resolution is the level that runs away (ln Z down by
/// 0.05 within 23 steps): the refinement is discarded, a warning says so, and the depth is the
/// swept solution's.
#[test]
fn a_refinement_that_moves_the_whole_surface_is_discarded_and_said() {
    let (c, swept, out) = relief_lit_from_120(64);
    let r = out.report.refinement.as_ref().unwrap();
    assert!(r.discarded && !r.converged, "{r:?}");
    assert!(
        r.shift < -photostereo::sfs::perspective::refine::MAX_SHIFT,
        "{r:?}"
    );
    assert!(
        out.report
            .warnings
            .iter()
            .any(|w| w.contains("refinement was discarded") && w.contains("the swept solution")),
        "{:?}",
        out.report.warnings
    );
    let worst = largest_relative_change(&c.truth.mask, &swept, &out);
    assert!(
        worst < 1e-6,
        "the depth differs from the swept one by {worst:e}"
    );
}

/// The same scene at 136² (18 496 pixels, so swept and refined at 68² first and upsampled): the
/// 68² refinement runs away and is discarded there, the report's assumptions say so, no steps
/// are counted for it, and the full resolution refines the upsampled swept solution within 5°
/// and 5%.
#[test]
fn a_refinement_discarded_below_an_upsampled_start_is_said() {
    let (c, _, out) = relief_lit_from_120(136);
    let s = score(&out, &c.truth);
    let r = out.report.refinement.as_ref().unwrap();
    assert!(
        r.converged && !r.discarded && r.coarse_iterations == 0,
        "{r:?}"
    );
    assert!(
        out.report
            .assumptions
            .iter()
            .any(|a| a.starts_with("swept at 68×68")
                && a.contains("refinement moved the whole surface and was discarded")),
        "{:?}",
        out.report.assumptions
    );
    assert!(
        s.normals_deg < 5.0 && s.depth < 0.05,
        "{:.2}° {:.4}",
        s.normals_deg,
        s.depth
    );
}

/// A refinement stopped by its step limit says so in a warning and in its report.
#[test]
fn a_refinement_cut_short_says_so() {
    let c = capture(SceneKind::Bust, 64, 30.0, Material::lambertian(), 0.0);
    let out = solve_with(
        &c,
        Some(RefineOptions {
            max_iterations: 1,
            ..RefineOptions::default()
        }),
    );
    let r = out.report.refinement.as_ref().unwrap();
    assert!(!r.converged && r.iterations == 1, "{r:?}");
    assert!(r.energy_end < r.energy_start, "{r:?}");
    assert!(
        warns(&out, "refinement stopped at its limit of 1 step"),
        "{:?}",
        out.report.warnings
    );
}

/// A mask of more than 2¹⁴ pixels (peaks filling 136², light 30° off the axis) is swept at
/// half resolution and refined at both: it says so, converges, and is as accurate as the 128²
/// solve (within 5° and 5%), and better than its own swept solution.
#[test]
fn a_large_mask_is_swept_at_half_resolution() {
    let c = capture(SceneKind::Peaks, 136, 30.0, Material::lambertian(), 0.0);
    assert!(c.truth.mask.count() > 1 << 14);
    let (swept, out) = (
        solve_with(&c, None),
        solve_with(&c, Some(RefineOptions::default())),
    );
    let (s0, s) = (score(&swept, &c.truth), score(&out, &c.truth));
    header();
    row(SceneKind::Peaks, "30° off, swept only", &swept, &s0);
    row(SceneKind::Peaks, "30° off, pyramid", &out, &s);
    assert!(
        out.report
            .assumptions
            .iter()
            .any(|a| a.starts_with("swept at 68×68")),
        "{:?}",
        out.report.assumptions
    );
    assert!(
        !swept
            .report
            .assumptions
            .iter()
            .any(|a| a.starts_with("swept at"))
    );
    assert!(out.report.refinement.as_ref().is_some_and(|r| r.converged));
    assert!(out.report.warnings.is_empty(), "{:?}", out.report.warnings);
    assert!(
        s.normals_deg < 5.0 && s.depth < 0.05,
        "{:.2}° {:.4}",
        s.normals_deg,
        s.depth
    );
    assert!(s.normals_deg < s0.normals_deg && s.depth < s0.depth);
}

/// Non-Lambertian surfaces under a light at the camera: with the right reflectance a rough
/// diffuse (Oren–Nayar) shape is recovered within 5°, and a glossy (Blinn–Phong) one is
/// recovered better than by assuming Lambert's law, which bends every shape.
#[test]
fn non_lambertian_reflectance_at_the_camera() {
    let size = 128;
    let rough = Material {
        diffuse: Diffuse::OrenNayar {
            sigma: 25f64.to_radians(),
        },
        ..Material::lambertian()
    };
    let glossy = Material::with_specular(Specular::BlinnPhong(BlinnPhong {
        ks: 0.3,
        exponent: 20.0,
    }));
    for (name, material) in [("oren-nayar", rough), ("blinn-phong", glossy)] {
        for kind in SHAPES {
            let c = capture(kind, size, 0.0, material, 0.0);
            let run = |m: Material| {
                let out = solve_capture(
                    &c,
                    &PerspectiveOptions {
                        material: m,
                        ..PerspectiveOptions::default()
                    },
                );
                score(&out, &c.truth)
            };
            let right = run(material);
            let lambert = run(Material::lambertian());
            println!(
                "{name} {}: {:.2}° / {:.2}% with it, {:.2}° / {:.2}% assuming Lambert",
                kind.name(),
                right.normals_deg,
                100.0 * right.depth,
                lambert.normals_deg,
                100.0 * lambert.depth
            );
            // A glossy lobe is modelled, and helps, but its steep rise near the highlight
            // swamps the fall-off's hold on depth: the brightness barely changes with depth
            // there, and the sweeps settle on the farthest of nearly equal solutions.
            if name == "oren-nayar" {
                assert!(right.normals_deg < 5.0 && right.depth < 0.05, "{name}");
            }
            assert!(right.normals_deg < lambert.normals_deg, "{name}");
        }
    }
}

/// Image noise of 1% of the brightest pixel: still within 5°.
#[test]
fn noise() {
    for kind in [SceneKind::Vase, SceneKind::Bust] {
        let c = capture(kind, 128, 0.0, Material::lambertian(), 0.01);
        let out = solve_capture(&c, &PerspectiveOptions::default());
        let s = score(&out, &c.truth);
        println!(
            "{} with 1% noise: {:.2}°, depth {:.2}%",
            kind.name(),
            s.normals_deg,
            100.0 * s.depth
        );
        assert!(s.normals_deg < 5.0 && s.depth < 0.05, "{}", kind.name());
    }
}

/// The outline tested against the image (`sfs::occluding`, at the depth the result gives each
/// outline pixel): the silhouettes of the sphere and the bust contradict an occluding contour
/// in at most one pixel, with and without 1% noise, with the albedo given right or 0.8 or 1.25
/// times the truth (the depth, and with it the bound, follows a wrong albedo), with the light at
/// the camera or 20°–30° off it from
/// above and below; the vase, whose cut ends are no contour, along more than 5% of its outline
/// under every one of those lights, and each of its solves off the axis warns (lit from below,
/// the vase was solved 6.5–15° off without a word before the test: docs/shape-from-shading.md),
/// while with the light at the camera, where the solution needs nothing from the outline, the
/// report says it among its assumptions.
#[test]
fn the_outline_is_tested_against_the_image() {
    for (slant, azimuth) in [(0.0, 0.0), (30.0, 90.0), (30.0, 270.0), (20.0, 200.0)] {
        // (noise, the albedo given over the true one)
        for (noise, albedo) in [(0.0, 1.0), (0.01, 1.0), (0.0, 0.8), (0.0, 1.25)] {
            for kind in [SceneKind::Sphere, SceneKind::Bust, SceneKind::Vase] {
                let c = capture_at(kind, 96, (slant, azimuth), Material::lambertian(), noise);
                let out = solve_capture(
                    &c,
                    &PerspectiveOptions {
                        albedo,
                        ..PerspectiveOptions::default()
                    },
                );
                let t = out
                    .report
                    .occluding
                    .expect("the outline lies inside the image");
                let warned = warns(&out, "not an occluding contour along");
                println!(
                    "{} light {slant}° at {azimuth}°, noise {noise}, albedo ×{albedo}: {} of {} \
                     outline pixels contradict ({:.1}%), warned {warned}",
                    kind.name(),
                    t.contradicted,
                    t.pixels,
                    100.0 * t.fraction
                );
                if kind == SceneKind::Vase {
                    // With the light at the camera the solution needs nothing from the outline
                    // (the vase within 4°): said among the assumptions, not as a warning.
                    let noted = out
                        .report
                        .assumptions
                        .iter()
                        .any(|a| a.contains("not an occluding contour along"));
                    assert!(t.fraction > 0.05, "{}", t.fraction);
                    assert_eq!((warned, noted), (slant > 0.0, slant == 0.0));
                } else {
                    assert!(t.contradicted <= 1 && !warned, "{}", kind.name());
                }
            }
        }
    }
}

/// A sphere in closed form through a pinhole whose focal lengths differ (f_x 80, f_y 110 px)
/// under a point light off the axis: its silhouette, an occluding contour everywhere, contradicts
/// the outline test nowhere, and the solve does not warn of it. (A contour normal taken in the
/// wrong plane fails it: with the outline's tangent taken along its outward direction, 21 of the
/// 236 outline pixels contradict. Swapping f_x and f_y in that mapping changes too little on
/// this sphere to be seen.) The sphere (radius 30 at distance 100 on the axis) is lit from
/// (25, 15, 0), x right, y up, z to the viewer.
#[test]
fn a_silhouette_seen_with_unequal_focal_lengths_passes_the_outline_test() {
    let (w, h) = (72usize, 96usize);
    let (fx, fy) = (80.0, 110.0);
    let (cx, cy) = ((w - 1) as f64 / 2.0, (h - 1) as f64 / 2.0);
    let (distance, radius, phi) = (100.0, 30.0, 1.0e4);
    let centre = Vector3::new(0.0, 0.0, -distance);
    let light = Vector3::new(25.0, 15.0, 0.0);
    let mut image = Grid::new(w, h, 0f32);
    let mut mask = Grid::new(w, h, false);
    for v in 0..h {
        for u in 0..w {
            let d = Vector3::new((u as f64 - cx) / fx, -(v as f64 - cy) / fy, -1.0);
            let (a, b) = (d.dot(&d), -2.0 * d.dot(&centre));
            let disc = b * b - 4.0 * a * (centre.dot(&centre) - radius * radius);
            if disc <= 0.0 {
                continue;
            }
            let t = (-b - disc.sqrt()) / (2.0 * a);
            let x = d * t;
            let n = (x - centre) / radius;
            let to_light = light - x;
            let dist = to_light.norm();
            let cos = (n.dot(&to_light) / dist).max(0.0);
            image.data_mut()[v * w + u] = (phi * cos / (dist * dist)) as f32;
            mask.data_mut()[v * w + u] = true;
        }
    }
    let camera = Intrinsics { fx, fy, cx, cy };
    let out = solve(
        &image,
        &mask,
        &camera,
        &PointLight {
            position: light,
            intensity: phi,
        },
        &PerspectiveOptions::default(),
    )
    .unwrap();
    let t = out
        .report
        .occluding
        .expect("the outline lies inside the image");
    println!(
        "sphere, f_x {fx} f_y {fy}, light (25, 15, 0): {} of {} outline pixels contradict",
        t.contradicted, t.pixels
    );
    assert!(t.pixels > 100 && t.contradicted == 0, "{t:?}");
    assert!(
        !warns(&out, "not an occluding contour along"),
        "{:?}",
        out.report.warnings
    );
}

/// Starting the sweeps from their result (a warm start) converges at once, to the same depth.
#[test]
fn warm_start() {
    let c = capture(SceneKind::Bust, 128, 0.0, Material::lambertian(), 0.0);
    let cold = solve(
        &c.image,
        &c.truth.mask,
        &c.camera,
        &c.light,
        &PerspectiveOptions {
            refine: None,
            ..PerspectiveOptions::default()
        },
    )
    .unwrap();
    let warm = solve(
        &c.image,
        &c.truth.mask,
        &c.camera,
        &c.light,
        &PerspectiveOptions {
            start: Some(cold.depth.clone()),
            refine: None,
            ..PerspectiveOptions::default()
        },
    )
    .unwrap();
    println!(
        "cold {} sweeps, warm {} sweeps",
        cold.report.iterations, warm.report.iterations
    );
    assert!(warm.report.converged && warm.report.iterations <= 2);
    let worst = (0..cold.depth.len())
        .filter(|&i| c.truth.mask.data()[i])
        .map(|i| (cold.depth.data()[i] - warm.depth.data()[i]).abs())
        .fold(0f32, f32::max);
    assert!(worst < 1e-3, "{worst}");
}

/// What the method cannot model is refused with the parameter named.
#[test]
fn refusals() {
    let c = capture(SceneKind::Sphere, 48, 30.0, Material::lambertian(), 0.0);
    let rough = Material {
        diffuse: Diffuse::OrenNayar { sigma: 0.3 },
        ..Material::lambertian()
    };
    let err = solve(
        &c.image,
        &c.truth.mask,
        &c.camera,
        &c.light,
        &PerspectiveOptions {
            material: rough,
            ..PerspectiveOptions::default()
        },
    )
    .unwrap_err()
    .to_string();
    assert!(
        err.contains("material") && err.contains("camera centre"),
        "{err}"
    );
    let mut ahead = c.light;
    ahead.position.z = -10.0;
    let err = solve(
        &c.image,
        &c.truth.mask,
        &c.camera,
        &ahead,
        &PerspectiveOptions::default(),
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("light position"), "{err}");
    let mut flat = c.camera;
    flat.fx = 0.0;
    let err = solve(
        &c.image,
        &c.truth.mask,
        &flat,
        &c.light,
        &PerspectiveOptions::default(),
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("camera"), "{err}");
    let black = c.image.map(|_| 0.0);
    let err = solve(
        &black,
        &c.truth.mask,
        &c.camera,
        &c.light,
        &PerspectiveOptions::default(),
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("black"), "{err}");
}

/// A refinement discarded at full resolution after its half-resolution refinement moved the
/// swept start (the vase at 160², a light 40° off the axis at azimuth 200°: 44 steps at 80²
/// kept, then two at 160² that move the whole surface by 5.2%): the depth is that moved start,
/// the report's energy ends where it started, the warning names the start, and the assumptions
/// no longer say that the contour pixels continue the swept depth in a straight line (the
/// half-resolution change moved them; until 2026-12-07 they did). The result is poor either way
/// (swept 19.0°, returned 26.3°): a light this far off the axis is beyond what the method holds.
#[test]
fn a_refinement_discarded_after_a_half_resolution_move_returns_the_moved_start() {
    let (c, swept, out) = swept_and_refined(SceneKind::Vase, 160, (40.0, 200.0));
    let r = out.report.refinement.as_ref().unwrap();
    assert!(
        r.discarded && r.coarse_iterations > 0 && r.iterations > 0,
        "{r:?}"
    );
    assert!(
        r.shift.abs() > photostereo::sfs::perspective::refine::MAX_SHIFT,
        "{r:?}"
    );
    assert_eq!(r.energy_end, r.energy_start, "{r:?}");
    assert!(
        warns(
            &out,
            "the depth is that start, the swept solution as its refinement at half resolution \
             moved it"
        ),
        "{:?}",
        out.report.warnings
    );
    assert!(
        swept
            .report
            .assumptions
            .iter()
            .any(|a| a.contains("continue the depth inside in a straight line")),
        "{:?}",
        swept.report.assumptions
    );
    assert!(
        !out.report
            .assumptions
            .iter()
            .any(|a| a.contains("continue the depth inside in a straight line")),
        "{:?}",
        out.report.assumptions
    );
    // The half-resolution change moved the start: the depth is not the swept one.
    let moved = largest_relative_change(&c.truth.mask, &swept, &out);
    assert!(
        moved > 1e-3,
        "the depth is the swept one (largest change {moved:e})"
    );
}

/// The outline's normals against the occluding contour the method assumes there. The vase at
/// 64² under lights 40° off the axis (azimuths 40°, 120° and 200°) comes out on another branch
/// (11–24° off when measured, with about half of its outline's normals turned more than 45° from
/// the outline's outward direction); each such result must say so, and at least two of the three
/// must be such results, so that the test keeps testing the warning. The same vase 30° off at
/// azimuth 40°, and the sphere 40° off, are within 5° and 5%, honour their outlines and must not
/// warn (the threshold is Horn's, `OUTLINE_MISALIGNED_WARN`; over the bench's 320 rendered
/// solves at 64²–160² it warned on none of the 208 within 5° and 5%).
#[test]
fn a_solution_that_contradicts_its_occluding_contour_says_so() {
    use photostereo::sfs::OUTLINE_MISALIGNED_WARN;
    let solved = |kind: SceneKind, light: (f64, f64)| {
        let c = capture_at(kind, 64, light, Material::lambertian(), 0.0);
        let out = solve_with(&c, Some(RefineOptions::default()));
        let s = score(&out, &c.truth);
        let o = out.report.outline.expect("the outline is inside the image");
        let says = warns(&out, "contradicts the occluding boundary it assumed");
        println!(
            "{} 64², {light:?}: {:.2}°, {:.2}%; outline {:.0}% of {} misaligned (mean {:.1}°), \
             warned {says}",
            kind.name(),
            s.normals_deg,
            100.0 * s.depth,
            100.0 * o.misaligned_fraction,
            o.pixels,
            o.mean_angle_deg
        );
        assert_eq!(
            says,
            o.misaligned_fraction > OUTLINE_MISALIGNED_WARN,
            "{o:?}"
        );
        (s, says)
    };
    let mut wrong = 0;
    for azimuth in [40.0, 120.0, 200.0] {
        let (s, says) = solved(SceneKind::Vase, (40.0, azimuth));
        if s.normals_deg > 9.0 {
            wrong += 1;
            assert!(says, "{:.2}° without the warning", s.normals_deg);
        } else {
            assert!(s.normals_deg < 5.0 && s.depth < 0.05 && !says);
        }
    }
    assert!(
        wrong >= 2,
        "{wrong} of 3 on another branch: the warning is no longer tested"
    );
    for (kind, light) in [
        (SceneKind::Vase, (30.0, 40.0)),
        (SceneKind::Sphere, (40.0, 200.0)),
    ] {
        let (s, says) = solved(kind, light);
        assert!(
            s.normals_deg < 5.0 && s.depth < 0.05,
            "{:.2}°",
            s.normals_deg
        );
        assert!(!says);
    }
}

/// The whole perspective method, sweeps and refinement, gives the same depth bit for bit in a
/// pool of one thread and in one of four: the vase at 128², its light 30° off the axis, refined
/// in several steps over more cells than one chunk of the energy's sum. With rayon's own sum
/// (whose split follows the number of threads and the work stealing) the depths differed.
#[test]
fn the_result_does_not_depend_on_the_threads() {
    let c = capture(SceneKind::Vase, 128, 30.0, Material::lambertian(), 0.0);
    let run = |threads: usize| {
        common::with_threads(threads, || solve_with(&c, Some(RefineOptions::default())))
    };
    let (one, four) = (run(1), run(4));
    let refined = one.report.refinement.as_ref().expect("refined");
    println!("{} cells, {} steps", refined.cells, refined.iterations);
    assert!(
        refined.iterations >= 2 && refined.cells > 4096,
        "{refined:?}"
    );
    let bits = |r: &SfsResult| -> Vec<u32> { r.depth.data().iter().map(|v| v.to_bits()).collect() };
    assert_eq!(bits(&one), bits(&four));
}
