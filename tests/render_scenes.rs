//! The renderer against geometry it must reproduce: mirror highlights where reflection puts
//! them, cast shadows of a step where similar triangles put them, the dichromatic sum of a
//! coloured diffuse and a white specular lobe, and the camera model written to disk and read back.

use nalgebra::Vector3;
use photostereo::capture::lights::{Light, Lights};
use photostereo::capture::stack::ColorMode;
use photostereo::synth::reflectance::{
    BlinnPhong, Brdf, Diffuse, Frame, Material, Mirror, Specular,
};
use photostereo::synth::render::{RenderOptions, render};
use photostereo::synth::scene::{Albedo, Object, Primitive, Scene, SceneKind};

fn chrome() -> Material {
    Material {
        diffuse: Diffuse::None,
        diffuse_color: [1.0; 3],
        specular: Some(Specular::Mirror(Mirror { f0: 0.8 })),
        specular_color: [1.0; 3],
    }
}

/// On a mirror sphere the highlight of light l is at the pixel whose normal is the half vector
/// h = (l + v)/|l + v|, v = (0, 0, 1): at (cx + R h_x, cy + R h_y). Checked for several radii,
/// centres and light directions, including grazing ones near the rim.
#[test]
fn mirror_sphere_highlights_land_where_reflection_predicts() {
    let dirs = [
        Vector3::new(0.0, 0.0, 1.0),
        Vector3::new(0.5, 0.2, 0.8),
        Vector3::new(-0.7, 0.4, 0.6),
        Vector3::new(0.1, -0.9, 0.45),
        Vector3::new(-0.94, -0.1, 0.33),
    ];
    let lights = Lights::from_directions(&dirs).unwrap();
    for (size, radius, cx, cy) in [
        (200, 80.0, 0.0, 0.0),
        (240, 60.0, 30.5, -20.0),
        (160, 75.0, -3.0, 2.5),
    ] {
        let scene = Scene {
            width: size,
            height: size,
            objects: vec![
                Object::new(
                    Primitive::Sphere {
                        cx,
                        cy,
                        radius,
                        base: 0.0,
                    },
                    Albedo::Constant(1.0),
                )
                .with_material(chrome()),
            ],
        };
        let r = render(&scene, &lights, &RenderOptions::default()).unwrap();
        for (k, l) in lights.directions().iter().enumerate() {
            let img = &r.images[k][0];
            let (mut sx, mut sy, mut n) = (0.0, 0.0, 0usize);
            for row in 0..size {
                for col in 0..size {
                    if *img.at(col, row) > 1.0 {
                        let (x, y) = scene.pixel_xy(col, row);
                        sx += x;
                        sy += y;
                        n += 1;
                    }
                }
            }
            assert!(n > 0, "no highlight for light {k} on sphere r = {radius}");
            let h = (l + Vector3::z()).normalize();
            let (px, py) = (cx + radius * h.x, cy + radius * h.y);
            let (mx, my) = (sx / n as f64, sy / n as f64);
            let off = ((mx - px).powi(2) + (my - py).powi(2)).sqrt();
            println!("r = {radius}, light {k}: {n} px, offset {off:.3} px");
            assert!(
                off <= 1.0,
                "light {k}, r = {radius}: highlight at ({mx:.2}, {my:.2}), predicted ({px:.2}, {py:.2}), {n} px"
            );
            // Elsewhere a mirror is black.
            assert!(
                img.data()
                    .iter()
                    .filter(|v| **v > 0.0 && **v <= 1.0)
                    .count()
                    == 0
            );
        }
    }
}

/// A step of height h at x = 0 (right side high) lit from the right at elevation e shadows the
/// low side for −h/tan e < x < 0, nothing else.
#[test]
fn step_casts_the_shadow_similar_triangles_predict() {
    let scene = SceneKind::Step.build(96, Albedo::Constant(0.6), Material::lambertian());
    let h = 0.1 * 96.0;
    for elevation in [20.0f64, 35.0, 60.0] {
        let e = elevation.to_radians();
        let lights = Lights::from_directions(&[Vector3::new(e.cos(), 0.0, e.sin())]).unwrap();
        let r = render(&scene, &lights, &RenderOptions::default()).unwrap();
        let reach = h / e.tan();
        for row in 0..96 {
            for col in 0..96 {
                let (x, _) = scene.pixel_xy(col, row);
                let shadowed = *r.cast[0].at(col, row);
                if x >= 0.0 || x < -reach - 1.0 {
                    assert!(!shadowed, "e = {elevation}: x = {x} shadowed");
                } else if x > -reach + 1.0 {
                    assert!(shadowed, "e = {elevation}: x = {x} lit, reach {reach:.2}");
                }
            }
        }
        assert!(r.attached[0].count() == 0);
    }
    // Lit from the left, the wall faces the light: no shadow at all.
    let lights = Lights::from_directions(&[Vector3::new(-0.8, 0.0, 0.6)]).unwrap();
    let r = render(&scene, &lights, &RenderOptions::default()).unwrap();
    assert_eq!(r.cast[0].count(), 0);
}

/// Colour rendering follows the dichromatic model: I_c = E_c π (d_c ρ f_d + s_c f_s) cos θ_i.
/// With a diffuse colour (1, 0.5, 0.25), white specular and a white light, I_G − I_R/2 isolates
/// the specular part: it must equal π f_s cos θ_i / 2 computed from the Blinn–Phong lobe.
#[test]
fn colour_rendering_is_the_dichromatic_sum() {
    let lobe = BlinnPhong {
        ks: 0.4,
        exponent: 40.0,
    };
    let material = Material {
        diffuse: Diffuse::Lambertian,
        diffuse_color: [1.0, 0.5, 0.25],
        specular: Some(Specular::BlinnPhong(lobe)),
        specular_color: [1.0; 3],
    };
    let scene = SceneKind::Sphere.build(96, Albedo::Constant(0.7), material);
    let l = Vector3::new(0.3, 0.4, 0.866).normalize();
    let lights = Lights::from_directions(&[l]).unwrap();
    let r = render(
        &scene,
        &lights,
        &RenderOptions {
            color: true,
            ..RenderOptions::default()
        },
    )
    .unwrap();
    assert_eq!(r.channels, 3);
    let (mut peak, mut checked) = (0f64, 0);
    for i in 0..r.truth.mask.len() {
        if !r.truth.mask.data()[i] {
            continue;
        }
        let n = r.truth.normals.data()[i].cast::<f64>();
        let cos_i = n.dot(&l);
        if cos_i <= 0.0 {
            continue;
        }
        let f = Frame::from_normal(n);
        let spec =
            std::f64::consts::PI * lobe.eval(&f.to_local(&l), &f.to_local(&Vector3::z())) * cos_i;
        let [ir, ig, ib] = [0, 1, 2].map(|c| f64::from(r.images[0][c].data()[i]));
        assert!((ig - ir / 2.0 - spec / 2.0).abs() < 1e-5, "pixel {i}");
        assert!((ib - ir / 4.0 - 0.75 * spec).abs() < 1e-5, "pixel {i}");
        peak = peak.max(spec);
        checked += 1;
    }
    assert!(
        peak > 0.3 && checked > 3000,
        "peak specular {peak}, {checked} px"
    );
    // Grey rendering is the BT.601 mix of the colour one.
    let g = render(&scene, &lights, &RenderOptions::default()).unwrap();
    for i in 0..g.truth.mask.len() {
        let mix: f32 = (0..3)
            .map(|c| [0.299, 0.587, 0.114][c] * r.images[0][c].data()[i])
            .sum();
        assert!((g.images[0][0].data()[i] - mix).abs() < 1e-5);
    }
}

/// A coloured light scales each channel by its intensity; dividing by it (`to_stack`) gives
/// back g = ρN for a Lambertian scene, in grey and per-channel modes.
#[test]
fn coloured_lights_divide_out() {
    let scene = SceneKind::Sphere.build(64, Albedo::Constant(0.5), Material::lambertian());
    let mut lights = Vec::new();
    for (k, d) in Lights::fibonacci(6, 40.0)
        .unwrap()
        .directions()
        .iter()
        .enumerate()
    {
        lights.push(Light {
            direction: *d,
            intensity: [1.0 + 0.1 * k as f64, 0.7, 0.4],
            file: None,
            position: None,
            anisotropy: None,
        });
    }
    let lights = Lights::new(lights).unwrap();
    let r = render(
        &scene,
        &lights,
        &RenderOptions {
            color: true,
            ..RenderOptions::default()
        },
    )
    .unwrap();
    for mode in [ColorMode::Grey, ColorMode::PerChannel] {
        let stack = r.to_stack(&lights, mode).unwrap();
        for (k, l) in lights.directions().iter().enumerate() {
            for c in 0..stack.channels() {
                for (i, v) in stack.plane(k, c).iter().enumerate() {
                    if r.truth.mask.data()[i] {
                        let n = r.truth.normals.data()[i].cast::<f64>();
                        let expect = 0.5 * n.dot(l).max(0.0);
                        assert!(
                            (f64::from(*v) - expect).abs() < 1e-5,
                            "{mode:?} light {k} channel {c}"
                        );
                    }
                }
            }
        }
    }
}

/// Oren–Nayar with σ = 0 renders exactly like Lambertian; with σ > 0 the sphere's limb darkens
/// less relative to its centre under frontal light (the flattening rough surfaces show).
#[test]
fn oren_nayar_renders() {
    let lights = Lights::from_directions(&[Vector3::z()]).unwrap();
    let render_with = |d: Diffuse| {
        let m = Material {
            diffuse: d,
            ..Material::lambertian()
        };
        render(
            &SceneKind::Sphere.build(64, Albedo::Constant(0.8), m),
            &lights,
            &RenderOptions::default(),
        )
        .unwrap()
    };
    let lam = render_with(Diffuse::Lambertian);
    let on0 = render_with(Diffuse::OrenNayar { sigma: 0.0 });
    assert_eq!(lam.images[0][0], on0.images[0][0]);
    let rough = render_with(Diffuse::OrenNayar { sigma: 0.6 });
    // Pixel 20 px right of centre on the middle row: n_z = √(1 − (20/25.6)²).
    let ratio = |r: &photostereo::synth::render::Rendering| {
        r.images[0][0].at(52, 32) / r.images[0][0].at(32, 32)
    };
    assert!(
        ratio(&rough) > ratio(&lam) + 0.05,
        "{} vs {}",
        ratio(&rough),
        ratio(&lam)
    );
}
