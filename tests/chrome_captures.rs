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
        wall_gain: Vec::new(),
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

/// A lamp that lights the wall less (or more) than the others can reverse the ball's contrast
/// in its image: here (the issue's capture in 16 bits with 1% noise) the wall is half as bright
/// in three of the ten images, darker than the ball there instead of lighter. Such a capture is
/// refused, naming how many images show the outline, rather than calibrated: the same rule
/// refuses the classic chrome ball, whose outline one 8-bit code deep would otherwise give lights
/// 0.9° from its mask's with ±0.14° stated (see docs/calibration.md).
#[test]
fn a_ball_whose_contrast_reverses_in_some_images_is_refused() {
    let mut cap = issue_capture();
    cap.depth = Depth::Linear16;
    cap.noise = 0.01;
    cap.wall_gain = vec![1.0, 1.0, 0.5, 1.0, 1.0, 0.5, 1.0, 1.0, 0.5, 1.0];
    let e = calibrate_chrome(&stack_of(&cap), None, &ChromeOptions::default()).unwrap_err();
    let text = e.to_string();
    assert!(
        text.contains("outline seen in 7") && text.contains("radius 112.0"),
        "{text}"
    );
    // With every image lit alike it is found.
    cap.wall_gain.clear();
    assert!(calibrate_chrome(&stack_of(&cap), None, &ChromeOptions::default()).is_ok());
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
        wall_gain: Vec::new(),
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

use photostereo::calibrate::near::{NearOptions, calibrate_two_balls};
use photostereo::camera::Intrinsics;

/// A pinhole capture of one ball somewhere in a wide frame (up to 23° off the optical
/// axis), under distant lamps, from `seed`.
fn perspective(seed: u64) -> ChromeCapture {
    let mut rng = rand::rngs::ChaCha8Rng::seed_from_u64(seed);
    let (w, h) = (800usize, 600usize);
    let f = rng.random_range(700.0..1600.0);
    let k = Intrinsics {
        fx: f,
        fy: f,
        cx: 400.0 + rng.random_range(-10.0..10.0),
        cy: 300.0 + rng.random_range(-10.0..10.0),
    };
    let radius = rng.random_range(40.0..120.0);
    let ball = Circle {
        cx: rng.random_range(radius + 5.0..w as f64 - radius - 5.0),
        cy: rng.random_range(radius + 5.0..h as f64 - radius - 5.0),
        radius,
    };
    let lamps = (0..rng.random_range(6..=10))
        .map(|_| {
            let cos = rng.random_range(55f64.to_radians().cos()..0.98);
            let az = rng.random_range(0.0..std::f64::consts::TAU);
            let s = (1.0 - cos * cos).sqrt();
            Lamp {
                place: LampPlace::Direction(Vector3::new(s * az.cos(), s * az.sin(), cos)),
                radius_deg: rng.random_range(1.5..4.0),
                radiance: rng.random_range(1.5..6.0),
            }
        })
        .collect();
    ChromeCapture {
        width: w,
        height: h,
        balls: vec![ball],
        reflectance: 0.7,
        environment: rng.random_range(0.05..0.2),
        environment_slope: 0.03,
        wall: Wall::Plain {
            level: rng.random_range(0.3..0.6),
            slope: 0.05,
        },
        lamps,
        wall_gain: Vec::new(),
        table_reflection: 0.0,
        noise: rng.random_range(0.0..0.01),
        supersampling: 2,
        // The ball's centre f / R of its radii from the camera (6–40); the scale is free.
        camera: Some((k, 1000.0)),
        depth: Depth::Linear16,
        seed,
    }
}

/// Issue 25 part 3: under a pinhole camera each pixel of the ball reflects its own view ray.
/// Thirty seeded captures of a ball across a wide frame: with the camera, the lights are as
/// good as orthographic captures' (mean ≤ 0.2°, none accepted beyond 2°, 2σ covering about
/// 95%); calibrated as if orthographic, the same images give lights several times worse.
#[test]
fn perspective_captures_need_the_camera_and_are_calibrated_with_it() {
    let mut with = Vec::new();
    let mut without = Vec::new();
    let mut refused = 0;
    let mut widest = 0.0f64;
    for seed in 0..30u64 {
        let cap = perspective(seed);
        let (k, _) = cap.camera.unwrap();
        let b = cap.balls[0];
        widest = widest.max(
            ((b.cx - k.cx) / k.fx)
                .hypot((b.cy - k.cy) / k.fy)
                .atan()
                .to_degrees(),
        );
        let stack = stack_of(&cap);
        let options = ChromeOptions {
            camera: cap.camera.map(|(k, _)| k),
            ..ChromeOptions::default()
        };
        let c = match calibrate_chrome(&stack, None, &options) {
            Ok(c) => c,
            Err(e) => {
                println!("seed {seed}: {e}");
                refused += 1;
                continue;
            }
        };
        for (k, h) in c.highlights().iter().enumerate() {
            if let Some(h) = h.filter(|h| h.accepted) {
                let e = h
                    .direction
                    .angle(&cap.light_direction(k, 0).unwrap())
                    .to_degrees();
                with.push((seed, e, h.uncertainty_deg));
            }
        }
        if let Ok(o) = calibrate_chrome(&stack, None, &ChromeOptions::default()) {
            for (k, h) in o.highlights().iter().enumerate() {
                if let Some(h) = h {
                    let e = h
                        .direction
                        .angle(&cap.light_direction(k, 0).unwrap())
                        .to_degrees();
                    without.push(e);
                }
            }
        }
    }
    let n = with.len() as f64;
    let mean = with.iter().map(|a| a.1).sum::<f64>() / n;
    let worst = with.iter().map(|a| a.1).fold(0.0, f64::max);
    let covered = with.iter().filter(|a| a.1 <= 2.0 * a.2).count() as f64 / n;
    let ortho = without.iter().sum::<f64>() / without.len().max(1) as f64;
    let rms_ratio = (with.iter().map(|a| (a.1 / a.2).powi(2)).sum::<f64>() / n).sqrt();
    println!("rms of error / stated uncertainty: {rms_ratio:.2}");
    println!(
        "30 perspective captures (balls up to {widest:.1}° off the axis): {refused} refused; {} lights accepted, mean error {mean:.3}°, worst {worst:.3}°, 2σ covers {:.1}%; as if orthographic: mean {ortho:.3}° over {} lights",
        with.len(),
        covered * 100.0,
        without.len()
    );
    assert!(refused <= 3, "{refused} captures refused");
    assert!(mean <= 0.2, "mean {mean:.3}°");
    assert!(worst <= 2.0, "worst {worst:.3}°");
    assert!(covered >= 0.9, "2σ covers {:.1}%", covered * 100.0);
    assert!(
        ortho >= 5.0 * mean,
        "orthographic {ortho:.3}° vs {mean:.3}°"
    );
}

/// A rig of two balls 110 px in radius, 520 px either side of the image centre (20° off the
/// axis, where their images are ellipses 7 px longer than wide), and LEDs 800–2500 units
/// off the axis, 400–2500 in front of the balls (balls of radius 236 at depth 3000, 2230
/// apart: the LEDs 0.5–1.5 baselines from them), from `seed`.
fn two_balls(seed: u64) -> ChromeCapture {
    let mut rng = rand::rngs::ChaCha8Rng::seed_from_u64(seed);
    let f = 1400.0;
    let k = Intrinsics {
        fx: f,
        fy: f,
        cx: 700.0,
        cy: 450.0,
    };
    // Centres at depth 3000 (units: pixels at the balls' depth).
    let distance = 3000.0;
    let lamps = (0..8)
        .map(|_| {
            let rho = rng.random_range(800.0..2500.0);
            let phi = rng.random_range(0.0..std::f64::consts::TAU);
            Lamp {
                place: LampPlace::Position(Vector3::new(
                    rho * phi.cos(),
                    rho * phi.sin(),
                    rng.random_range(-2600.0..-500.0),
                )),
                radius_deg: rng.random_range(2.5..4.5),
                radiance: rng.random_range(2.0..8.0),
            }
        })
        .collect();
    ChromeCapture {
        width: 1400,
        height: 900,
        balls: vec![
            Circle {
                cx: 180.0,
                cy: 450.0 + rng.random_range(-60.0..60.0),
                radius: 110.0,
            },
            Circle {
                cx: 1220.0,
                cy: 450.0 + rng.random_range(-60.0..60.0),
                radius: 110.0,
            },
        ],
        reflectance: 0.7,
        environment: 0.1,
        environment_slope: 0.03,
        wall: Wall::Plain {
            level: rng.random_range(0.2..0.5),
            slope: 0.05,
        },
        lamps,
        wall_gain: Vec::new(),
        table_reflection: 0.0,
        noise: rng.random_range(0.001..0.01),
        supersampling: 2,
        camera: Some((k, distance)),
        depth: Depth::Linear16,
        seed,
    }
}

/// Issue 25 part 4: two balls place each near light where its reflected rays meet. Twenty
/// seeded rigs of eight LEDs: accepted positions 0.5% of the light's distance off on average
/// and every one within 1%, the stated uncertainty covering twice over about 95% of the errors,
/// and most positions accepted (a position is accepted when twice its rms uncertainty — the
/// re-triangulated bound where that is larger — is within 1% of its distance).
#[test]
fn two_balls_place_near_lights_within_one_percent_of_their_distance() {
    let mut errors = Vec::new();
    let mut doubtful = Vec::new();
    for seed in 0..20u64 {
        let cap = two_balls(seed);
        let (k, distance) = cap.camera.unwrap();
        let radius = cap.balls[0].radius / k.fx * distance;
        let cal = calibrate_two_balls(&stack_of(&cap), None, &NearOptions::new(k, radius))
            .unwrap_or_else(|e| panic!("seed {seed}: {e}"));
        for (ball, c) in cal.centres.iter().enumerate() {
            let truth = cap.ball_centre(ball).unwrap();
            let off = (Vector3::from(*c) - truth).norm();
            assert!(
                off < 0.002 * truth.norm(),
                "seed {seed} ball {ball}: {off:.3} off"
            );
        }
        let mid = 0.5 * (cap.ball_centre(0).unwrap() + cap.ball_centre(1).unwrap());
        for (i, p) in cal.positions.iter().enumerate() {
            let LampPlace::Position(lamp) = cap.lamps[i].place else {
                unreachable!()
            };
            match p {
                Ok(p) if p.accepted => {
                    let d = (lamp - mid).norm();
                    errors.push((seed, i, (p.position - lamp).norm() / d, p.uncertainty / d));
                }
                Ok(p) => doubtful.push((seed, i, p.warnings.join("; "))),
                Err(e) => doubtful.push((seed, i, e.clone())),
            }
        }
    }
    for d in doubtful.iter().take(5) {
        println!("  seed {} light {}: {}", d.0, d.1, d.2);
    }
    let n = errors.len() as f64;
    let mean = errors.iter().map(|e| e.2).sum::<f64>() / n;
    let worst = errors
        .iter()
        .max_by(|a, b| a.2.total_cmp(&b.2))
        .expect("no position accepted");
    let covered = errors.iter().filter(|e| e.2 <= 2.0 * e.3).count() as f64 / n;
    let within_1 = errors.iter().filter(|e| e.2 <= 0.01).count() as f64 / n;
    println!(
        "20 two-ball rigs, 160 LEDs: {} positions accepted, {} in doubt or missing; error / distance mean {:.3}%, {:.1}% within 1%, worst {:.3}% (seed {} light {}, stated ±{:.3}%); 2σ covers {:.1}%",
        errors.len(),
        doubtful.len(),
        mean * 100.0,
        within_1 * 100.0,
        worst.2 * 100.0,
        worst.0,
        worst.1,
        worst.3 * 100.0,
        covered * 100.0
    );
    assert!(mean <= 0.005, "mean error {:.3}%", mean * 100.0);
    assert!(
        worst.2 <= 0.01,
        "a position {:.2}% off was accepted",
        worst.2 * 100.0
    );
    assert!(covered >= 0.9, "2σ covers {:.1}%", covered * 100.0);
    assert!(errors.len() >= 136, "{} of 160 accepted", errors.len());
}
