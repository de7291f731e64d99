//! Chrome-ball calibration on rendered captures varied as users' are (issue 25): detection
//! that holds or refuses, and uncertainties that mean what they say.

use photostereo::calibrate::sphere::Circle;
use photostereo::calibrate::{ChromeOptions, calibrate_chrome};
use photostereo::capture::lights::Lights;
use photostereo::capture::stack::{ImageStack, LoadOptions, Transfer};
use photostereo::nalgebra::Vector3;
use photostereo::ndarray::Array3;
use photostereo::synth::chrome::{ChromeCapture, Depth, Lamp, LampPlace, Wall};

fn issue_capture() -> ChromeCapture {
    let lamps = (0..10)
        .map(|k| {
            let a = k as f64 * 0.628;
            let el = 0.5 + 0.1 * (k % 3) as f64;
            Lamp {
                place: LampPlace::Direction(
                    Vector3::new(el * a.cos(), el * a.sin(), 1.0).normalize(),
                ),
                radius_deg: 2.0,
                radiance: 5.0,
            }
        })
        .collect();
    ChromeCapture {
        width: 480,
        height: 360,
        balls: vec![Circle {
            cx: 274.0,
            cy: 166.0,
            radius: 112.0,
        }],
        reflectance: 1.0,
        environment: 0.10,
        environment_slope: 0.02,
        wall: Wall::Plain {
            level: 0.15,
            slope: 0.0,
        },
        lamps,
        table_reflection: 0.0,
        noise: 0.02,
        supersampling: 3,
        camera: None,
        depth: Depth::Srgb8,
        seed: 7,
    }
}

/// The capture of the issue: a mirror ball darker than the wall behind it, noisy, 8-bit. The
/// detection used to find a circle 60 px off and report lights 48° off with confidence 0.99.
#[test]
fn a_dark_ball_on_a_lighter_wall_is_found() {
    let cap = issue_capture();
    let c = calibrate_chrome(&stack_of(&cap), None, &ChromeOptions::default()).unwrap();
    let truth = cap.balls[0];
    let off = (c.sphere.circle.cx - truth.cx)
        .hypot(c.sphere.circle.cy - truth.cy)
        .max((c.sphere.circle.radius - truth.radius).abs());
    assert!(off < 0.3, "{:?}", c.sphere);
    let lights = c.lights().unwrap();
    for (k, (l, h)) in lights.directions().iter().zip(c.highlights()).enumerate() {
        let e = l.angle(&cap.light_direction(k, 0).unwrap()).to_degrees();
        let u = h.unwrap().uncertainty_deg;
        println!("light {k}: {e:.3}° off, ±{u:.3}°");
        assert!(e <= 0.3 && e <= 2.0 * u, "light {k}: {e:.3}° off, ±{u:.3}°");
    }
}

use rand::{RngExt, SeedableRng};

/// A capture varied as issue 25 part 1 asks, from `seed`.
fn varied(seed: u64) -> ChromeCapture {
    let mut rng = rand::rngs::ChaCha8Rng::seed_from_u64(seed);
    let radius = (30f64.ln() + rng.random::<f64>() * (400f64 / 30.0).ln()).exp();
    // One capture in seven holds a second, smaller ball beside the first.
    let second = (rng.random::<f64>() < 0.15).then(|| radius * rng.random_range(0.5..1.0));
    let w = (radius * rng.random_range(2.2..3.4) + second.map_or(0.0, |r| 2.0 * r + 10.0))
        .round()
        .max(120.0) as usize;
    let h = (radius * rng.random_range(2.2..3.4)).round().max(100.0) as usize;
    let room = w as f64 - second.map_or(0.0, |r| 2.0 * r + 10.0);
    let mut cx = rng.random_range(radius + 1.0..(room - radius - 1.0).max(radius + 2.0));
    let mut cy = rng.random_range(radius + 1.0..(h as f64 - radius - 1.0).max(radius + 2.0));
    if rng.random::<f64>() < 0.25 {
        // Cut by a border: the centre 0.65–0.9 radii from it.
        let d = radius * rng.random_range(0.65..0.9);
        match rng.random_range(0..4) {
            0 => cx = d,
            1 => cx = w as f64 - d,
            2 => cy = d,
            _ => cy = h as f64 - d,
        }
    }
    let mut balls = vec![Circle { cx, cy, radius }];
    let wall_level = rng.random_range(0.05..0.6);
    let wall = if rng.random::<bool>() {
        Wall::Plain {
            level: wall_level,
            slope: rng.random_range(-0.1..0.1),
        }
    } else {
        Wall::Textured {
            level: wall_level,
            contrast: rng.random_range(0.05..0.3f64).min(wall_level),
            cell: rng.random_range(8.0..60.0),
            seed: rng.random(),
        }
    };
    let contrast = rng.random_range(0.03..0.4);
    let environment = if rng.random::<bool>() && wall_level + contrast < 0.9 {
        wall_level + contrast
    } else {
        (wall_level - contrast).max(0.02)
    };
    if let Some(r2) = second {
        // To the right of the first, its centre in the frame.
        let x2 = (cx + radius + r2 + 5.0).min(w as f64 - 1.0);
        if (x2 - cx).abs() > radius + r2 {
            balls.push(Circle {
                cx: x2,
                cy,
                radius: r2,
            });
        }
    }
    let count = rng.random_range(6..=12);
    let table_reflection = if rng.random::<f64>() < 0.3 {
        rng.random_range(0.1..0.5)
    } else {
        0.0
    };
    let mut lamps = Vec::new();
    while lamps.len() < count {
        let cos = rng.random_range(60f64.to_radians().cos()..0.99);
        let az = rng.random_range(0.0..std::f64::consts::TAU);
        let s = (1.0 - cos * cos).sqrt();
        let d = Vector3::new(s * az.cos(), s * az.sin(), cos);
        // With a table, the lamps stand 10° or more above it.
        if table_reflection > 0.0 && d.y < 10f64.to_radians().sin() {
            continue;
        }
        lamps.push(Lamp {
            place: LampPlace::Direction(d),
            radius_deg: rng.random_range(1.0..5.0),
            radiance: (1.5f64.ln() + rng.random::<f64>() * 20f64.ln()).exp(),
        });
    }
    ChromeCapture {
        width: w,
        height: h,
        balls,
        reflectance: rng.random_range(0.5..0.9),
        environment,
        environment_slope: environment * rng.random_range(0.0..0.3),
        wall,
        lamps,
        table_reflection,
        noise: rng.random_range(0.0..0.02),
        supersampling: if radius > 60.0 { 2 } else { 3 },
        camera: None,
        depth: [Depth::Srgb8, Depth::Linear16, Depth::Float][rng.random_range(0..3)],
        seed,
    }
}

/// The capture's images as the stack a file of its depth would load into.
fn stack_of(cap: &ChromeCapture) -> ImageStack {
    let imgs = cap.render();
    let n = imgs.images.len();
    let unit = Lights::from_directions(&vec![Vector3::z(); n]).unwrap();
    let options = LoadOptions {
        transfer: Transfer::Auto,
        ..LoadOptions::default()
    };
    let shape = (n, imgs.height, imgs.width);
    match cap.depth {
        Depth::Srgb8 => ImageStack::from_array(
            Array3::from_shape_vec(shape, imgs.to_u8().concat())
                .unwrap()
                .view(),
            &unit,
            &options,
        ),
        Depth::Linear16 => ImageStack::from_array(
            Array3::from_shape_vec(shape, imgs.to_u16().concat())
                .unwrap()
                .view(),
            &unit,
            &options,
        ),
        Depth::Float => ImageStack::from_array(
            Array3::from_shape_vec(shape, imgs.images.concat())
                .unwrap()
                .view(),
            &unit,
            &options,
        ),
    }
    .unwrap()
}

/// What became of one light.
enum Outcome {
    /// Accepted: its error and stated uncertainty (degrees) and confidence.
    Accepted {
        error: f64,
        uncertainty: f64,
        confidence: f64,
    },
    /// In doubt, with why.
    Doubtful(String),
    /// No highlight.
    Missing,
}

/// Two hundred captures varied in everything issue 25 lists (seeded): the capture is refused,
/// or its accepted lights are within 0.2° on average and none is more than 2° off, and the
/// stated uncertainty covers the error twice over for about 95% of them.
#[test]
fn varied_captures_are_calibrated_or_refused_never_wrong_with_confidence() {
    let (first, count) = (0u64, 200u64);
    let mut refused_detection = Vec::new();
    let mut lights = Vec::new();
    let mut whole = 0;
    for seed in first..first + count {
        let cap = varied(seed);
        match calibrate_chrome(&stack_of(&cap), None, &ChromeOptions::default()) {
            Err(e) => refused_detection.push((seed, e.to_string())),
            Ok(c) => {
                // The ball it found (a capture may hold two): the lights are the same for both.
                let ball = (0..cap.balls.len())
                    .min_by(|&a, &b| {
                        let d = |i: usize| {
                            (cap.balls[i].cx - c.sphere.circle.cx)
                                .hypot(cap.balls[i].cy - c.sphere.circle.cy)
                        };
                        d(a).total_cmp(&d(b))
                    })
                    .unwrap_or(0);
                let mut all = true;
                for (k, h) in c.highlights().iter().enumerate() {
                    let outcome = match h {
                        None => Outcome::Missing,
                        Some(h) if !h.accepted => Outcome::Doubtful(h.warnings.join("; ")),
                        Some(h) => Outcome::Accepted {
                            error: h
                                .direction
                                .angle(&cap.light_direction(k, ball).unwrap())
                                .to_degrees(),
                            uncertainty: h.uncertainty_deg,
                            confidence: h.confidence,
                        },
                    };
                    all &= matches!(outcome, Outcome::Accepted { .. });
                    lights.push((seed, outcome));
                }
                whole += usize::from(all);
            }
        }
    }
    let accepted: Vec<(u64, f64, f64, f64)> = lights
        .iter()
        .filter_map(|(s, o)| match o {
            Outcome::Accepted {
                error,
                uncertainty,
                confidence,
            } => Some((*s, *error, *uncertainty, *confidence)),
            _ => None,
        })
        .collect();
    let n = accepted.len() as f64;
    let mean = accepted.iter().map(|a| a.1).sum::<f64>() / n;
    let worst = accepted
        .iter()
        .max_by(|a, b| a.1.total_cmp(&b.1))
        .copied()
        .unwrap();
    let covered = accepted.iter().filter(|a| a.1 <= 2.0 * a.2).count() as f64 / n;
    let within_1 = accepted.iter().filter(|a| a.1 <= 1.0).count() as f64 / n;
    let confidence = accepted.iter().map(|a| a.3).sum::<f64>() / n;
    let doubtful: Vec<&String> = lights
        .iter()
        .filter_map(|(_, o)| match o {
            Outcome::Doubtful(w) => Some(w),
            _ => None,
        })
        .collect();
    let ambiguous = doubtful.iter().filter(|w| w.contains("ambiguous")).count();
    let uncertain = doubtful.iter().filter(|w| w.contains("uncertain")).count();
    let rim = doubtful.iter().filter(|w| w.contains("rim")).count();
    let missing = lights
        .iter()
        .filter(|(_, o)| matches!(o, Outcome::Missing))
        .count();
    let two_balls = (first..first + count)
        .filter(|s| varied(*s).balls.len() > 1)
        .count();
    println!(
        "{count} captures ({two_balls} with two balls): {} refused by detection, {} with lights in doubt or missing, {whole} with every light accepted",
        refused_detection.len(),
        count as usize - refused_detection.len() - whole
    );
    for (seed, e) in &refused_detection {
        println!("  seed {seed}: {}", e.chars().take(160).collect::<String>());
    }
    println!(
        "lights of the detected captures: {} accepted, {} in doubt ({ambiguous} ambiguous, {uncertain} uncertain, {rim} at the rim), {missing} without a highlight",
        accepted.len(),
        doubtful.len()
    );
    println!(
        "accepted: mean error {mean:.3}°, worst {:.3}° (seed {}, stated ±{:.3}°); within 2× the stated uncertainty {:.1}%; within 1°: {:.1}% against a mean confidence of {:.1}%",
        worst.1,
        worst.0,
        worst.2,
        covered * 100.0,
        within_1 * 100.0,
        confidence * 100.0
    );
    assert!(mean <= 0.2, "mean error {mean:.3}°");
    assert!(
        worst.1 <= 2.0,
        "a light {:.2}° off was accepted (seed {})",
        worst.1,
        worst.0
    );
    assert!(
        covered >= 0.9,
        "2σ covers {:.1}% of the errors",
        covered * 100.0
    );
    // Refusing everything would pass the above: most lights of detected balls are accepted.
    assert!(
        accepted.len() * 2 > lights.len(),
        "{} of {} lights accepted",
        accepted.len(),
        lights.len()
    );
}
