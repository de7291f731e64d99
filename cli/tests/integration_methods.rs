//! Normal integration: exactness on fields with known integrals, the survey vase with noise, the
//! DiLiGenT depth benchmark with its camera, discontinuities, and the `integrate` command.

#[path = "../../tests/common/mod.rs"]
mod common;

use nalgebra::Vector3;
use photostereo::camera::Intrinsics;
use photostereo::eval::metrics::{depth_errors, scaled_depth_errors};
use photostereo::grid::{Grid, Mask, NormalMap, ScalarMap};
use photostereo::integrate::{
    BilateralParams, Censoring, IntegrationOptions, Integrator, LinearSolver, SolveMethod,
    integrate_censored_gradients, integrate_gradients, integrate_normals,
};
use photostereo::io::decode::{read_image, read_mask, read_normal_map};
use photostereo::progress::Silent;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use std::process::Command;

fn options(method: Integrator) -> IntegrationOptions {
    IntegrationOptions {
        method,
        ..IntegrationOptions::default()
    }
}

/// Gradients and normals of the height field z = f(x, y) (x right, y up, pixel units).
fn field(
    w: usize,
    h: usize,
    f: impl Fn(f64, f64) -> (f64, f64, f64),
) -> (ScalarMap, ScalarMap, ScalarMap, NormalMap) {
    let xy = |c: usize, r: usize| {
        (
            c as f64 - (w as f64 - 1.0) / 2.0,
            (h as f64 - 1.0) / 2.0 - r as f64,
        )
    };
    let z = Grid::from_fn(w, h, |c, r| f(xy(c, r).0, xy(c, r).1).0 as f32);
    let p = Grid::from_fn(w, h, |c, r| f(xy(c, r).0, xy(c, r).1).1 as f32);
    let q = Grid::from_fn(w, h, |c, r| f(xy(c, r).0, xy(c, r).1).2 as f32);
    let n = Grid::from_fn(w, h, |c, r| {
        let (_, zx, zy) = f(xy(c, r).0, xy(c, r).1);
        Vector3::new(-zx, -zy, 1.0).normalize().cast::<f32>()
    });
    (z, p, q, n)
}

/// Least squares on the mask is exact for quadratics (the trapezoid rule is exact for linear
/// gradients), on a mask with two parts and a hole, with both solvers; the full-rectangle methods
/// are not, because they treat the background as flat.
#[test]
fn masked_least_squares_is_exact_on_quadratics_and_irregular_masks() {
    let (w, h) = (120, 90);
    let quad = |x: f64, y: f64| {
        (
            0.01 * x * x - 0.02 * x * y + 0.005 * y * y + 0.3 * x,
            0.02 * x - 0.02 * y + 0.3,
            -0.02 * x + 0.01 * y,
        )
    };
    let (z, p, q, _) = field(w, h, quad);
    let mask: Mask = Grid::from_fn(w, h, |c, r| {
        let (dx, dy) = (c as f64 - 35.0, r as f64 - 45.0);
        let disk = dx * dx + dy * dy < 900.0 && dx * dx + dy * dy > 25.0;
        disk || (c > 75 && c < 115 && r > 10 && r < 80)
    });
    for (solver, method) in [
        (LinearSolver::Direct, SolveMethod::Direct),
        (LinearSolver::ConjugateGradient, SolveMethod::DctCg),
        (LinearSolver::Multigrid, SolveMethod::GridMultigridCg),
    ] {
        let (est, info) = integrate_gradients(&p, &q, &mask, Integrator::MaskedLs, solver).unwrap();
        let info = info.unwrap();
        assert_eq!(info.method, method);
        // Per connected part, depth is known up to an offset: compare each part separately.
        for part in [
            Grid::from_fn(w, h, |c, r| *mask.at(c, r) && c < 70),
            Grid::from_fn(w, h, |c, r| *mask.at(c, r) && c > 70),
        ] {
            let e = depth_errors(&est, &z, &part).unwrap();
            assert!(
                e.rmse < 1e-4,
                "{solver:?} ({} CG iterations): RMSE {}",
                info.iterations,
                e.rmse
            );
        }
    }
    let (poisson, _) =
        integrate_gradients(&p, &q, &mask, Integrator::Poisson, LinearSolver::Auto).unwrap();
    assert!(depth_errors(&poisson, &z, &mask).unwrap().rmse > 0.1);
}

/// Occluding rims: a sphere and a flattened ellipsoid seen edge-on, whose depth goes like
/// √(distance) to the silhouette and whose gradients blow up there (to |p| ≈ 50 where n_z is
/// clamped). The normals are exact at the pixel centres. With the square-root rim profile masked
/// least squares is within 0.02 px (RMS) of the true depth: measured 0.016 px on the sphere and
/// 0.011 px on the ellipsoid, against 0.57 px on the sphere with the polynomial rules alone (the
/// build before the rim profile), the error then concentrating at the rim.
#[test]
fn occluding_rims_follow_the_square_root_profile() {
    let (w, h, r) = (100usize, 90usize, 40.0f64);
    for (name, sy, sz) in [("sphere", 1.0, 1.0), ("ellipsoid", 0.7, 0.6)] {
        // z = sz·r·√(1 − (x/r)² − (y/(sy·r))²), centre off the pixel grid.
        let inside = |x: f64, y: f64| 1.0 - (x / r).powi(2) - (y / (sy * r)).powi(2);
        let (z, _, _, normals) = field(w, h, |x, y| {
            let (x, y) = (x - 0.3, y + 0.2);
            let u = inside(x, y).max(1e-12);
            let zv = sz * r * u.sqrt();
            (
                zv,
                -sz * x / (r * u.sqrt()),
                -sz * y / (sy * sy * r * u.sqrt()),
            )
        });
        let mask = Grid::from_fn(w, h, |c, row| {
            let x = c as f64 - (w as f64 - 1.0) / 2.0 - 0.3;
            let y = (h as f64 - 1.0) / 2.0 - row as f64 + 0.2;
            inside(x, y) > 0.0
        });
        let depth = integrate_normals(&normals, &mask, &options(Integrator::MaskedLs), &Silent)
            .unwrap()
            .depth;
        let e = depth_errors(&depth, &z, &mask).unwrap();
        println!("{name}: masked-ls RMSE {:.4} px", e.rmse);
        assert!(e.rmse < 0.02, "{name}: RMSE {} px", e.rmse);
    }
}

/// Frankot–Chellappa recovers a periodic surface (up to discretisation) on the full image.
#[test]
fn frankot_chellappa_on_a_periodic_surface() {
    let (w, h) = (128, 96);
    let (kx, ky) = (
        2.0 * std::f64::consts::PI * 3.0 / w as f64,
        2.0 * std::f64::consts::PI * 2.0 / h as f64,
    );
    let (z, p, q, _) = field(w, h, |x, y| {
        (
            4.0 * (kx * x).sin() * (ky * y).cos(),
            4.0 * kx * (kx * x).cos() * (ky * y).cos(),
            -4.0 * ky * (kx * x).sin() * (ky * y).sin(),
        )
    });
    let mask = Grid::new(w, h, true);
    let (est, _) = integrate_gradients(
        &p,
        &q,
        &mask,
        Integrator::FrankotChellappa,
        LinearSolver::Auto,
    )
    .unwrap();
    let e = depth_errors(&est, &z, &mask).unwrap();
    assert!(e.rmse_over_range < 1e-3, "{e:?}");
}

/// The survey vase (Quéau, Durou & Aujol 2018), whose file stores the gradients clipped at ±10
/// (the largest magnitude, reached by many samples at the silhouette). With the clipped samples
/// marked as bounds, masked least squares reaches RMSE 0.069 on the exact gradients (0.094 with
/// polynomial rules only, 0.114 when the clipped samples are taken as exact); with Gaussian noise
/// of 0.5% of the largest gradient (σ = 0.05) the RMSE varies with the draw (the noise integrates
/// into large-scale tilts), so the test averages 8 draws. The rectangle methods, which assume a
/// flat background around the mask, are an order of magnitude off: this is why the mask matters.
#[test]
fn vase_with_noise() {
    let path = require_shared!("integration/vase/vase.exr");
    let exr = |name: &str| -> ScalarMap {
        photostereo::io::decode::read_exr_channel(&path, name).unwrap()
    };
    let (zg, pv, qv, mv) = (exr("Z"), exr("p"), exr("q"), exr("mask"));
    let mask = mv.map(|v| *v > 0.5);
    // The file's p = ∂Z/∂row, q = ∂Z/∂column; ours: p = ∂z/∂x (columns), q = ∂z/∂y (up).
    let values = || {
        pv.data()
            .iter()
            .chain(qv.data())
            .filter(|v| v.is_finite())
            .map(|v| v.abs())
    };
    let max = values().fold(0f32, f32::max);
    let at_max = values().filter(|v| *v == max).count();
    assert!(
        at_max > 100,
        "the clip level {max} is reached {at_max} times"
    );
    let clipped = Censoring::ClippedAt(max);
    let sigma = 0.005 * max;
    let noise = Normal::new(0.0f32, sigma).unwrap();
    let noisy = |seed: u64| {
        let mut rng = rand::rngs::ChaCha8Rng::seed_from_u64(seed);
        (
            qv.map(|v| v + noise.sample(&mut rng)),
            pv.map(|v| -v + noise.sample(&mut rng)),
        )
    };
    let integrate = |p: &ScalarMap, q: &ScalarMap, censoring: &Censoring, method| {
        let (z, _) =
            integrate_censored_gradients(p, q, censoring, &mask, method, LinearSolver::Auto)
                .unwrap();
        depth_errors(&z, &zg, &mask).unwrap().rmse
    };
    let (p, q) = (qv.clone(), pv.map(|v| -v));
    let exact = integrate(&p, &q, &clipped, Integrator::MaskedLs);
    let uncensored = integrate(&p, &q, &Censoring::None, Integrator::MaskedLs);
    println!("vase, exact gradients: masked-ls RMSE {exact:.4} ({uncensored:.4} uncensored)");
    assert!(
        exact <= 0.08,
        "masked least squares on exact gradients: RMSE {exact}"
    );
    let mut rmse = Vec::new();
    for method in [
        Integrator::MaskedLs,
        Integrator::Poisson,
        Integrator::FrankotChellappa,
        Integrator::Path,
    ] {
        let draws: Vec<f64> = (0..8)
            .map(|seed| {
                let (p, q) = noisy(seed);
                integrate(&p, &q, &clipped, method)
            })
            .collect();
        let mean = draws.iter().sum::<f64>() / draws.len() as f64;
        println!(
            "vase, σ = {sigma:.3}: {} RMSE mean {mean:.4} over 8 draws {draws:.3?}",
            method.name()
        );
        rmse.push(mean);
    }
    assert!(rmse[0] <= 0.1, "masked least squares mean RMSE {}", rmse[0]);
    assert!(
        rmse[1] > 10.0 * rmse[0] && rmse[2] > 10.0 * rmse[0],
        "{rmse:?}"
    );
}

/// DiLiGenT depth (Cao et al.'s benchmark): perspective integration of the ground-truth normals
/// with K, scaled by median(gt/estimate), mean absolute error in mm. Published figures of
/// bilateral normal integration: cat 0.074, bear 0.334. Bilateral integration with its
/// re-integration over the cut edges (the default) meets both, with either inner solver; the
/// published soft-weighted result is reproduced beside it.
#[test]
fn diligent_depth_with_the_camera() {
    for (obj, published) in [("cat", 0.074), ("bear", 0.334)] {
        let dir = require_shared!(format!("integration/{obj}"));
        let normals = read_normal_map(&dir.join("normal_map.png")).unwrap();
        let mask = read_mask(&dir.join("mask.png")).unwrap();
        let gt = read_image(&dir.join("depth_gt.exr")).unwrap();
        let gt = Grid::from_vec(gt.width, gt.height, gt.data).unwrap();
        let camera = Intrinsics::from_file(&dir.join("K.txt")).unwrap();
        let run = |name: &str, o: IntegrationOptions| {
            let r = integrate_normals(&normals, &mask, &o, &Silent).unwrap();
            let e = scaled_depth_errors(&r.depth, &gt, &mask).unwrap();
            println!(
                "{obj}: {name} MADE {:.4} mm (published bilateral {published})",
                e.mean_abs
            );
            e.mean_abs
        };
        let base = IntegrationOptions {
            method: Integrator::Bilateral,
            camera: Some(camera),
            ..IntegrationOptions::default()
        };
        let bilateral = run("bilateral", base);
        let exact = run(
            "bilateral, exact inner solves",
            IntegrationOptions {
                solver: LinearSolver::Direct,
                ..base
            },
        );
        let soft = run(
            "bilateral as published (no re-integration)",
            IntegrationOptions {
                bilateral: BilateralParams {
                    reintegrate: false,
                    ..BilateralParams::default()
                },
                ..base
            },
        );
        let masked = run(
            "masked-ls",
            IntegrationOptions {
                method: Integrator::MaskedLs,
                ..base
            },
        );
        // The default: the occlusions of both show in the circulation, so bilateral is chosen.
        let auto = run(
            "auto",
            IntegrationOptions {
                method: Integrator::Auto,
                ..base
            },
        );
        assert!(auto <= published, "{obj} auto {auto}");
        assert!(
            (auto - bilateral).abs() < 1e-12,
            "{obj} auto {auto} vs bilateral {bilateral}"
        );
        // Measured: cat 0.058 and 0.057 (exact inner solves), bear 0.029 and 0.027.
        assert!(bilateral <= published, "{obj} bilateral {bilateral}");
        assert!(
            exact <= published,
            "{obj} bilateral, exact inner solves {exact}"
        );
        match obj {
            // The soft-weighted result reproduces the published 0.074 (measured 0.0743);
            // masked least squares, which smooths over the cat's occlusion edges, is 20× worse.
            "cat" => {
                assert!(soft <= 0.0745, "cat bilateral as published {soft}");
                assert!(masked > 10.0 * bilateral, "cat masked-ls {masked}");
            }
            // Bear is smooth but for its chin: the soft weights leave the head's offset to the
            // weight that remains under the chin (measured 0.392, 0.21–0.43 mm with the
            // published code over inner tolerances); masked least squares measures 0.096.
            _ => {
                assert!(soft <= 0.40, "bear bilateral as published {soft}");
                assert!(masked <= published, "bear masked least squares {masked}");
                assert!(
                    bilateral < 0.5 * masked,
                    "bear bilateral {bilateral} vs {masked}"
                );
            }
        }
    }
}

/// Perspective integration recovers a smooth surface's metric depth up to scale: depth computed
/// from normals matches the true depth map to 1e-4 relative after the median scale fit.
#[test]
fn perspective_integration_recovers_depth_up_to_scale() {
    let (w, h) = (160, 120);
    let k = Intrinsics {
        fx: 400.0,
        fy: 410.0,
        cx: 83.0,
        cy: 57.5,
    };
    // A paraboloid bump in front of a tilted plane, in camera coordinates (z towards the viewer).
    let depth = |u: f64, v: f64| -> f64 {
        let (a, b) = ((u - k.cx) / k.fx, (v - k.cy) / k.fy);
        100.0 + 20.0 * a - 10.0 * b - 30.0 * (-(a * a + b * b) * 8.0).exp()
    };
    let point = |u: f64, v: f64| Vector3::from(k.unproject(u, v, depth(u, v)));
    let normals: NormalMap = Grid::from_fn(w, h, |c, r| {
        let (u, v) = (c as f64, r as f64);
        let eps = 1e-4;
        let du = (point(u + eps, v) - point(u - eps, v)) / (2.0 * eps);
        let dv = (point(u, v + eps) - point(u, v - eps)) / (2.0 * eps);
        // Outward normal, towards the camera (positive z).
        let n = dv.cross(&du).normalize();
        (if n.z < 0.0 { -n } else { n }).cast::<f32>()
    });
    let truth = Grid::from_fn(w, h, |c, r| depth(c as f64, r as f64) as f32);
    let mask = Grid::new(w, h, true);
    for method in [Integrator::MaskedLs, Integrator::Bilateral] {
        let o = IntegrationOptions {
            method,
            camera: Some(k),
            solver: LinearSolver::Direct,
            ..IntegrationOptions::default()
        };
        let r = integrate_normals(&normals, &mask, &o, &Silent).unwrap();
        let e = scaled_depth_errors(&r.depth, &truth, &mask).unwrap();
        println!(
            "perspective {}: MADE {:.2e} (depth ≈ 100)",
            method.name(),
            e.mean_abs
        );
        assert!(e.mean_abs < 1e-2, "{}: {e:?}", method.name());
    }
    // Orthographic integration of the same normals is not metric: worse by orders of magnitude.
    let r = integrate_normals(&normals, &mask, &options(Integrator::MaskedLs), &Silent).unwrap();
    let ortho = depth_errors(&r.depth.map(|v| -v), &truth, &mask).unwrap();
    assert!(ortho.mean_abs > 0.1, "{ortho:?}");
}

/// A ball floating over a ground plane, seen from above: its silhouette is an occlusion boundary
/// where the depth jumps by 25 px and the ball's normals graze. Depth across a jump is unknown
/// from normals, so each side is compared after removing its own offset: bilateral integration
/// keeps both shapes; continuous integrators bend the ball's rim and the ground around it to
/// bridge the jump.
#[test]
fn bilateral_preserves_a_depth_discontinuity() {
    let (w, h) = (96, 96);
    let (r, lift) = (28.0, 25.0);
    let on_ball = |x: f64, y: f64| x * x + y * y < r * r;
    let (z, _, _, normals) = field(w, h, |x, y| {
        if on_ball(x, y) {
            let s = (r * r - x * x - y * y).sqrt().max(1e-3);
            (lift + s, -x / s, -y / s)
        } else {
            (0.0, 0.0, 0.0)
        }
    });
    let mask = Grid::new(w, h, true);
    let ball: Mask = Grid::from_fn(w, h, |c, rr| {
        let (x, y) = (c as f64 - 47.5, 47.5 - rr as f64);
        on_ball(x, y)
    });
    let ground = ball.map(|b| !b);
    let mut errs = Vec::new();
    for method in [
        Integrator::Bilateral,
        Integrator::MaskedLs,
        Integrator::Poisson,
    ] {
        let res = integrate_normals(&normals, &mask, &options(method), &Silent).unwrap();
        let (eb, eg) = (
            depth_errors(&res.depth, &z, &ball).unwrap().rmse,
            depth_errors(&res.depth, &z, &ground).unwrap().rmse,
        );
        println!(
            "floating ball: {} RMSE ball {eb:.3}, ground {eg:.3}",
            method.name()
        );
        errs.push((eb, eg));
        if let Some((wu, _)) = &res.weights {
            // At the ball's left silhouette (columns 17–22 of the middle row) the weights mark
            // the jump, against 0.5 on the flat ground far from it. (The grazing rim pixel itself
            // is ambiguous: it may join either side.)
            let near = (17..23).map(|c| *wu.at(c, 48)).fold(1f32, f32::min);
            assert!(
                near < 0.25 && (wu.at(3, 48) - 0.5).abs() < 0.01,
                "weights {near}, {}",
                wu.at(3, 48)
            );
        }
    }
    // Measured: bilateral ball 0.25, ground 0.051; continuous methods ball 0.44, ground 0.31
    // (bent up towards the ball). Where the weights give a grazing rim pixel of the ball to the
    // ground, the re-integration uses that pixel's own steep gradient on the edge to the ground
    // (with a small weight), which lifts the ground next to it: the published soft-weighted
    // result, which holds it at ground level with the ground pixel's normal, measures ground
    // 0.007 and ball 0.27 on this scene.
    let (ball_b, ground_b) = errs[0];
    assert!(ground_b < 0.06 && ball_b < 0.3, "bilateral {errs:?}");
    for (ball, ground) in &errs[1..] {
        assert!(*ground > 5.0 * ground_b && *ball > ball_b, "{errs:?}");
    }
}

/// `photostereo integrate` end to end on an encoded PNG normal map with a camera, writing depth
/// (Z, residual) and a PLY mesh that parses.
#[test]
fn integrate_command_writes_depth_and_mesh() {
    let dir = require_shared!("integration/cat");
    let tmp = tempfile::tempdir().unwrap();
    let (depth, ply) = (
        tmp.path().join("d/depth.exr"),
        tmp.path().join("m/mesh.ply"),
    );
    let o = Command::new(common::bin())
        .args(["integrate", "--method", "bilateral", "-q", "--normals"])
        .arg(dir.join("normal_map.png"))
        .arg("--mask")
        .arg(dir.join("mask.png"))
        .arg("--camera")
        .arg(dir.join("K.txt"))
        .arg("-o")
        .arg(&depth)
        .arg("--ply")
        .arg(&ply)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let e = Command::new(common::bin())
        .args(["eval", "--align", "median-scale", "--depth"])
        .arg(&depth)
        .arg("--depth-gt")
        .arg(dir.join("depth_gt.exr"))
        .arg("--mask")
        .arg(dir.join("mask.png"))
        .output()
        .unwrap();
    let v: serde_json::Value = serde_json::from_slice(&e.stdout).unwrap();
    assert!(v["mean_abs"].as_f64().unwrap() < 0.08, "{v}");
    let bytes = std::fs::read(&ply).unwrap();
    let header = String::from_utf8_lossy(
        &bytes[..bytes
            .windows(11)
            .position(|w| w == b"end_header\n")
            .unwrap()],
    )
    .into_owned();
    let count = |what: &str| -> usize {
        header
            .lines()
            .find(|l| l.starts_with(&format!("element {what}")))
            .unwrap()
            .split(' ')
            .nth(2)
            .unwrap()
            .parse()
            .unwrap()
    };
    let mask = read_mask(&dir.join("mask.png")).unwrap();
    assert_eq!(count("vertex"), mask.count());
    assert!(count("face") > mask.count() * 3 / 2);
    // A Python mesh library reads it where one is installed.
    let probe = Command::new("python3")
        .args(["-c", "import trimesh"])
        .output();
    if probe.is_ok_and(|o| o.status.success()) {
        let r = Command::new("python3")
            .args(["-c", "import sys, trimesh; m = trimesh.load(sys.argv[1]); print(len(m.vertices), len(m.faces))"])
            .arg(&ply)
            .output()
            .unwrap();
        assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
        let out = String::from_utf8_lossy(&r.stdout);
        assert!(out.starts_with(&mask.count().to_string()), "{out}");
    } else {
        eprintln!("SKIPPED the trimesh check: python3 with trimesh is not available");
    }
}

/// Normals of `field` with N(0, σ) added to each component and renormalised (one fixed draw).
fn noisy(normals: &NormalMap, sigma: f32, seed: u64) -> NormalMap {
    let mut rng = rand::rngs::ChaCha8Rng::seed_from_u64(seed);
    let noise = Normal::new(0.0f32, sigma).unwrap();
    normals.map(|n| {
        let v = Vector3::new(
            n.x + noise.sample(&mut rng),
            n.y + noise.sample(&mut rng),
            n.z + noise.sample(&mut rng),
        );
        v.normalize()
    })
}

/// Normals of a depth jump: a ball of radius 28 floating 25 px above a ground tilted at slope
/// 0.3, so that the jump's height varies along the ball's occluding contour.
fn floating_ball(w: usize, h: usize) -> NormalMap {
    let r = 28.0;
    field(w, h, |x, y| {
        if x * x + y * y < r * r {
            let s = (r * r - x * x - y * y).sqrt().max(1e-3);
            (25.0 + s, -x / s, -y / s)
        } else {
            (0.3 * x, 0.3, 0.0)
        }
    })
    .3
}

/// `auto` keeps masked least squares on a smooth surface (its depth, bit for bit: a smooth
/// object pays nothing for discontinuities) and switches to bilateral integration where a ball
/// floats above a tilted ground, a depth jump whose height varies along the ball's occluding
/// contour — with normal noise in both, so that the test has noise to tell the jump from.
#[test]
fn auto_chooses_from_the_residual() {
    let (w, h) = (96, 96);
    let mask = Grid::new(w, h, true);
    // Smooth: a Gaussian bump on a tilted plane.
    let (_, _, _, smooth) = field(w, h, |x, y| {
        let g = 20.0 * (-(x * x + y * y) / 600.0).exp();
        (
            g + 0.2 * x,
            -2.0 * x / 600.0 * g + 0.2,
            -2.0 * y / 600.0 * g,
        )
    });
    let jump = floating_ball(w, h);
    for (name, normals, expect) in [
        ("bump", noisy(&smooth, 0.01, 1), Integrator::MaskedLs),
        (
            "floating ball",
            noisy(&jump, 0.01, 2),
            Integrator::Bilateral,
        ),
    ] {
        let auto = integrate_normals(&normals, &mask, &options(Integrator::Auto), &Silent).unwrap();
        let d = auto.auto.expect("auto reports its decision");
        println!("{name}: {}", d.reason());
        assert_eq!(d.chosen, expect, "{name}: {}", d.reason());
        let chosen = integrate_normals(&normals, &mask, &options(expect), &Silent).unwrap();
        assert_eq!(
            auto.depth.data(),
            chosen.depth.data(),
            "{name}: auto returns the chosen method's depth"
        );
    }
}

/// Under a memory cap too small for bilateral integration, `auto` still finds the floating
/// ball's depth jump but keeps masked least squares (its depth, bit for bit), and its decision
/// says so with the bytes needed and allowed; with room, it runs bilateral integration.
#[test]
fn auto_keeps_the_smooth_integrator_where_bilateral_would_not_fit() {
    let (w, h) = (96, 96);
    let mask = Grid::new(w, h, true);
    let jump = floating_ball(w, h);
    let normals = noisy(&jump, 0.01, 2);
    let capped = |bytes: u64| IntegrationOptions {
        max_memory: Some(bytes),
        ..options(Integrator::Auto)
    };
    let tight = integrate_normals(&normals, &mask, &capped(1 << 20), &Silent).unwrap();
    let d = tight.auto.expect("auto reports its decision");
    assert_eq!(d.chosen, Integrator::MaskedLs, "{}", d.reason());
    assert!(d.jumps(), "the jump is still found: {}", d.reason());
    let held = d.held_back.expect("held back by the cap");
    assert!(
        held.needed > held.allowed && held.allowed == 1 << 20,
        "{held:?}"
    );
    assert!(d.reason().contains("MiB"), "{}", d.reason());
    let smooth =
        integrate_normals(&normals, &mask, &options(Integrator::MaskedLs), &Silent).unwrap();
    assert_eq!(tight.depth.data(), smooth.depth.data());
    let roomy = integrate_normals(&normals, &mask, &capped(1 << 30), &Silent).unwrap();
    let d = roomy.auto.unwrap();
    assert_eq!((d.chosen, d.held_back), (Integrator::Bilateral, None));
}

/// Exact normals carry no noise to compare the circulation with, but a smooth surface's
/// gradients still do not close exactly under any quadrature rule, most where they vary fast:
/// near a rim and at high curvature. `auto` must not take that discretisation error for depth
/// jumps: on the exact normals of the rendered smooth scenes it keeps masked least squares, the
/// few loops left outlying (none on five of the six, 12 of 17 015 on the bust) carrying under 1%
/// of the non-integrability (before the discretisation bound, 17–23% of their loops were
/// outlying, carrying all of it, and every one chose bilateral integration), while a ball
/// floating above a tilted ground and the torus on its plane, real jumps, are still found in
/// exact normals.
#[test]
fn auto_does_not_take_discretisation_error_for_jumps() {
    use photostereo::synth::reflectance::Material;
    use photostereo::synth::scene::{Albedo, SceneKind};
    let decide = |normals: &NormalMap, mask: &Mask| {
        integrate_normals(normals, mask, &options(Integrator::Auto), &Silent)
            .unwrap()
            .auto
            .expect("auto reports its decision")
    };
    for kind in [
        SceneKind::Sphere,
        SceneKind::Ellipsoid,
        SceneKind::Vase,
        SceneKind::Peaks,
        SceneKind::Relief,
        SceneKind::Bust,
    ] {
        let truth = kind
            .build(192, Albedo::Constant(0.8), Material::default())
            .height_field();
        let d = decide(&truth.normals, &truth.mask);
        println!("{}: {}", kind.name(), d.reason());
        assert_eq!(
            d.chosen,
            Integrator::MaskedLs,
            "{}: {}",
            kind.name(),
            d.reason()
        );
        assert!(d.outlying_share < 0.01, "{}: {}", kind.name(), d.reason());
    }
    let truth = SceneKind::Torus
        .build(192, Albedo::Constant(0.8), Material::default())
        .height_field();
    let d = decide(&truth.normals, &truth.mask);
    println!("torus: {}", d.reason());
    assert_eq!(d.chosen, Integrator::Bilateral, "torus: {}", d.reason());
    let (w, h) = (96, 96);
    let d = decide(&floating_ball(w, h), &Grid::new(w, h, true));
    println!("floating ball: {}", d.reason());
    assert_eq!(
        d.chosen,
        Integrator::Bilateral,
        "floating ball: {}",
        d.reason()
    );
}

/// The bilateral integrator holds no more than its plan (`Integrator::working_bytes`, which
/// streamed runs and `auto`'s choice under a budget go by): `integrate --method bilateral` on
/// a 1024² ball floating above a curved ground (a depth jump all around it; 1.05 M unknowns)
/// peaks within the process's fixed allowance, the normal map the command holds and the plan,
/// and integrates the ball and the ground each to their own shape (the offset between them is
/// not in the normals). Before the hierarchies were freed as soon as they were done with and
/// the re-integration stopped listing its edges, the peak was 643 MiB, 1.45× what is planned
/// now; measured now, 359 MiB.
#[cfg(target_os = "linux")]
#[test]
fn bilateral_integration_holds_within_its_planned_memory() {
    let (w, h) = (1024, 1024);
    let r_ball = 420.0;
    let normals = field(w, h, |x, y| {
        if x * x + y * y < r_ball * r_ball {
            let s = (r_ball * r_ball - x * x - y * y).sqrt().max(1e-3);
            (400.0 + s, -x / s, -y / s)
        } else {
            // A curved ground, so that no one normal fills the border (a uniform one would be
            // taken for the background and left out).
            (0.3 * x + 2e-4 * x * x, 0.3 + 4e-4 * x, 0.0)
        }
    })
    .3;
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("normals.exr");
    let channel = |k: usize| -> Vec<f32> { normals.data().iter().map(|n| n[k]).collect() };
    let (x, y, z) = (channel(0), channel(1), channel(2));
    photostereo::io::output::write_exr(&path, w, h, &[("R", &x), ("G", &y), ("B", &z)], &[])
        .unwrap();
    let depth = tmp.path().join("depth.exr");
    let m = common::measured(&[
        "integrate".as_ref(),
        "--method".as_ref(),
        "bilateral".as_ref(),
        "--normals".as_ref(),
        path.as_os_str(),
        "-o".as_ref(),
        depth.as_os_str(),
    ]);
    assert_eq!(m.code, Some(0), "{}", m.stderr);
    let window = photostereo::grid::Window::full(w, h);
    let planned = Integrator::Bilateral.working_bytes(w, h, w * h, window, LinearSolver::Auto);
    let allowance = photostereo::run::stream::BASE_BYTES + 12 * (w * h) as u64;
    let peak = (m.peak_mb * f64::from(1 << 20)) as u64;
    assert!(
        peak <= allowance + planned,
        "peak {} MiB, planned {} MiB besides {} MiB",
        peak >> 20,
        planned >> 20,
        allowance >> 20
    );
    // The depth: differences within the ball and across it on the ground against the surface's
    // own (measured: 206.26 against 206.18 px, and -260.1 against -262.0 px).
    let z = read_image(&depth).unwrap();
    let at = |c: usize, r: usize| f64::from(z.data[(r * z.width + c) * z.channels]);
    let truth = |c: usize, r: usize| {
        let (x, y) = (
            c as f64 - (w as f64 - 1.0) / 2.0,
            (h as f64 - 1.0) / 2.0 - r as f64,
        );
        if x * x + y * y < r_ball * r_ball {
            400.0 + (r_ball * r_ball - x * x - y * y).sqrt()
        } else {
            0.3 * x + 2e-4 * x * x
        }
    };
    let difference = |a: (usize, usize), b: (usize, usize)| {
        (
            at(a.0, a.1) - at(b.0, b.1),
            truth(a.0, a.1) - truth(b.0, b.1),
        )
    };
    let (ball, ball_true) = difference((512, 512), (512, 150));
    assert!((ball - ball_true).abs() < 0.5, "{ball} against {ball_true}");
    let (ground, ground_true) = difference((82, 512), (950, 512));
    assert!(
        (ground - ground_true).abs() < 0.01 * ground_true.abs(),
        "{ground} against {ground_true}"
    );
    eprintln!(
        "bilateral 1024²: peak {} MiB, planned {} + {} MiB; {ball} / {ball_true}, {ground} / {ground_true}",
        peak >> 20,
        planned >> 20,
        allowance >> 20
    );
}

/// A goblet seen from the side: a ball (the cup, radius 30) in front of a stem (a cylinder of
/// radius 8) and a base (a low dome) 45–50 px behind it, only the object in the mask (as
/// DiLiGenT goblet). The depth jump runs along the cup's lower rim across the stem, and at its
/// two ends, where the stem's grazing sides meet the cup's silhouette, the weights fade: the
/// strong cuts alone leave a few edges there uncut, which then set the stem's offset. The
/// hysteresis closes the contour, so the stem and base are reported as a region closed off all
/// around, whose offset is a guess. Returns the scene's normals, true depth, mask, and the
/// cup's and the rest's masks.
fn goblet(w: usize, h: usize) -> (NormalMap, ScalarMap, Mask, Mask, Mask) {
    let (rc, yc, rs) = (30.0, 20.0, 8.0);
    let on_cup = |x: f64, y: f64| x * x + (y - yc) * (y - yc) < rc * rc;
    let on_stem = |x: f64, y: f64| x.abs() < rs && y > -50.0 && y < yc;
    let base = |x: f64, y: f64| (x / 36.0).powi(2) + ((y + 52.0) / 9.0).powi(2);
    let (z, _, _, normals) = field(w, h, |x, y| {
        if on_cup(x, y) {
            let s = (rc * rc - x * x - (y - yc).powi(2)).sqrt().max(1e-3);
            (70.0 + s, -x / s, -(y - yc) / s)
        } else if on_stem(x, y) {
            let s = (rs * rs - x * x).sqrt().max(1e-3);
            (20.0 + s, -x / s, 0.0)
        } else if base(x, y) < 1.0 {
            // z = 20 + 6 √(1 − u²), u² = (x/36)² + ((y + 52)/9)².
            let s = (1.0 - base(x, y)).sqrt().max(1e-3);
            (
                20.0 + 6.0 * s,
                -6.0 * x / 1296.0 / s,
                -6.0 * (y + 52.0) / 81.0 / s,
            )
        } else {
            (f64::NAN, 0.0, 0.0)
        }
    });
    let xy = |c: usize, r: usize| {
        (
            c as f64 - (w as f64 - 1.0) / 2.0,
            (h as f64 - 1.0) / 2.0 - r as f64,
        )
    };
    let part = |which: u8| -> Mask {
        Grid::from_fn(w, h, |c, r| {
            let (x, y) = xy(c, r);
            let cup = on_cup(x, y);
            let rest = !cup && (on_stem(x, y) || base(x, y) < 1.0);
            match which {
                0 => cup || rest,
                1 => cup,
                _ => rest,
            }
        })
    };
    (normals, z, part(0), part(1), part(2))
}

/// The bilateral integrator closes the cut between a goblet's cup and the stem and base behind
/// it, and says that the stem's offset is a guess; each part keeps its shape.
#[test]
fn bilateral_closes_a_jump_off_and_says_its_offset_is_a_guess() {
    let (w, h) = (128, 128);
    let (normals, z, mask, cup, rest) = goblet(w, h);
    let behind = rest.count();
    for (sigma, seed) in [(0.0, 0), (0.01, 7), (0.03, 7)] {
        let n = if sigma > 0.0 {
            noisy(&normals, sigma, seed)
        } else {
            normals.clone()
        };
        let res = integrate_normals(&n, &mask, &options(Integrator::Bilateral), &Silent).unwrap();
        let closed = res
            .closed_off
            .expect("bilateral reports closed-off regions");
        let (ec, er) = (
            depth_errors(&res.depth, &z, &cup).unwrap().rmse,
            depth_errors(&res.depth, &z, &rest).unwrap().rmse,
        );
        let mean = |g: &ScalarMap, m: &Mask| {
            let v: Vec<f64> = g
                .data()
                .iter()
                .zip(m.data())
                .filter(|(_, inside)| **inside)
                .map(|(&d, _)| f64::from(d))
                .collect();
            v.iter().sum::<f64>() / v.len() as f64
        };
        let offset =
            (mean(&res.depth, &rest) - mean(&res.depth, &cup)) - (mean(&z, &rest) - mean(&z, &cup));
        println!(
            "goblet, noise {sigma}: {closed:?} (stem and base {behind} px); RMSE cup {ec:.3}, stem and base {er:.3} px (each after its own offset); offset error {offset:.1} px"
        );
        // Measured: the largest region closed off is the stem and base, 1 532 of their 1 554
        // pixels at every noise level (the strong cuts alone closed off only regions of 10 px);
        // RMSE cup 0.075–0.13, stem and base 0.35–0.37 px; the offset is off by 46–47 px
        // whichever way it is set, as it is not in the normals.
        assert!(
            closed.largest as f64 > 0.95 * behind as f64 && closed.largest <= behind,
            "noise {sigma}: {closed:?}, stem and base {behind} px"
        );
        assert!(
            ec < 0.2 && er < 0.45,
            "noise {sigma}: cup {ec}, stem and base {er}"
        );
        let integrated = res.depth.data().iter().filter(|v| v.is_finite()).count();
        let warning = photostereo::run::Warning::of_closed_off(closed, integrated)
            .expect("a warning")
            .to_string();
        assert!(
            warning.contains("off all around") && warning.contains("a guess"),
            "{warning}"
        );
    }
}

/// The side and radius of the sphere the next two tests write.
const SPHERE: (usize, f64) = (96, 40.0);

/// The sphere's height and gradients at (x, y) from its centre (x right, y up).
fn sphere(x: f64, y: f64) -> (f64, f64, f64) {
    let r = SPHERE.1;
    let s = (r * r - x * x - y * y).max(0.0).sqrt();
    (s, -x / s.max(1e-3), -y / s.max(1e-3))
}

/// Whether pixel (column, row) is more than a pixel inside the sphere's rim.
fn inside_sphere(c: usize, rw: usize) -> bool {
    let centre = (SPHERE.0 as f64 - 1.0) / 2.0;
    let (x, y) = (c as f64 - centre, centre - rw as f64);
    x * x + y * y < (SPHERE.1 - 1.0) * (SPHERE.1 - 1.0)
}

/// Writes `normal(pixel index)` inside the sphere and zero vectors around it as an EXR normal
/// map, integrates it with the default command (and, with `masked`, the sphere's pixels as
/// `--mask`), and returns the depth and what the command said.
fn integrate_sphere_map(
    dir: &std::path::Path,
    name: &str,
    normal: &dyn Fn(usize) -> [f32; 3],
    masked: bool,
) -> (Vec<f32>, String) {
    let w = SPHERE.0;
    let channel = |k: usize| -> Vec<f32> {
        (0..w * w)
            .map(|i| {
                if inside_sphere(i % w, i / w) {
                    normal(i)[k]
                } else {
                    0.0
                }
            })
            .collect()
    };
    let path = dir.join(format!("{name}.exr"));
    let (x, y, z) = (channel(0), channel(1), channel(2));
    photostereo::io::output::write_exr(&path, w, w, &[("R", &x), ("G", &y), ("B", &z)], &[])
        .unwrap();
    let depth = dir.join(format!("{name}-depth.exr"));
    let mut command = Command::new(common::bin());
    command.args(["integrate", "--normals"]).arg(&path);
    if masked {
        let mask = dir.join(format!("{name}-mask.png"));
        image::GrayImage::from_fn(w as u32, w as u32, |c, rw| {
            image::Luma([255 * u8::from(inside_sphere(c as usize, rw as usize))])
        })
        .save(&mask)
        .unwrap();
        command.arg("--mask").arg(mask);
    }
    let o = command.arg("-o").arg(&depth).output().unwrap();
    let said = String::from_utf8_lossy(&o.stdout) + String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{said}");
    let d = read_image(&depth).unwrap();
    let depth = (0..w * w).map(|i| d.data[i * d.channels]).collect();
    (depth, said.into_owned())
}

/// A normal map with one normal exactly at a right angle to the view inside a sphere (n_z = 0:
/// an occluding rim seen edge-on, or a clamped estimate) and the usual zero vectors outside it,
/// integrated by the default command with no mask: `auto` found the loops that normal breaks
/// and chose `bilateral`, whose re-integration then failed ("parameter `solver`: sparse
/// factorisation failed: NonPositivePivot"), naming a parameter the user never set. Now the
/// depth is written, finite over the sphere, and the sphere's height is that of the truth.
#[test]
fn the_default_integration_takes_a_normal_at_a_right_angle_to_the_view() {
    let w = SPHERE.0;
    let (_, _, _, normals) = field(w, w, sphere);
    let tmp = tempfile::tempdir().unwrap();
    let (d, said) = integrate_sphere_map(
        tmp.path(),
        "normals",
        &|i| {
            if i == 40 * w + 60 {
                [1.0, 0.0, 0.0]
            } else {
                normals.data()[i].into()
            }
        },
        false,
    );
    assert!(said.contains("auto (bilateral)"), "{said}");
    let at = |c: usize, rw: usize| f64::from(d[rw * w + c]);
    for rw in 0..w {
        for c in 0..w {
            assert_eq!(at(c, rw).is_finite(), inside_sphere(c, rw), "({c}, {rw})");
        }
    }
    // The sphere's height from a pixel near its rim (10.8 px up) to its top (40 px up),
    // against the truth.
    let rise = at(48, 48) - at(48, 9);
    let truth = sphere(0.5, -0.5).0 - sphere(0.5, 38.5).0;
    assert!((rise - truth).abs() < 1.0, "{rise} against {truth}");
}

/// A normal map of vectors scaled by an albedo (0.05 to 1, pixel to pixel; what a
/// least-squares fit gives before it divides by the length), zeros around the object, through
/// the default command with no mask: every pixel of the sphere is integrated (before, vectors
/// shorter than 0.5 were left out of the domain as if they were no normal), and the depth is
/// that of the unit normals (before, the clamp of n_z and the equations' weights read the
/// lengths).
#[test]
fn the_command_reads_the_direction_of_a_scaled_normal_map() {
    let w = SPHERE.0;
    let (_, _, _, normals) = field(w, w, sphere);
    let albedo = |i: usize| 0.05 + 0.95 * ((i * 7919) % 1000) as f32 / 1000.0;
    let tmp = tempfile::tempdir().unwrap();
    let (unit, said) =
        integrate_sphere_map(tmp.path(), "unit", &|i| normals.data()[i].into(), false);
    assert!(!said.contains("not of unit length"), "{said}");
    let (scaled, said) = integrate_sphere_map(
        tmp.path(),
        "scaled",
        &|i| (normals.data()[i] * albedo(i)).into(),
        false,
    );
    let taken = (0..w * w).filter(|&i| inside_sphere(i % w, i / w)).count();
    assert!(
        said.contains("pixels taken hold vectors that are not of unit length")
            && said.contains(&format!("of the {taken} pixels taken")),
        "{said}"
    );
    let (mut lo, mut hi, mut worst) = (f32::INFINITY, f32::NEG_INFINITY, 0.0f32);
    for i in 0..w * w {
        let inside = inside_sphere(i % w, i / w);
        assert_eq!(scaled[i].is_finite(), inside, "pixel {i}");
        if inside {
            lo = lo.min(unit[i]);
            hi = hi.max(unit[i]);
            worst = worst.max((unit[i] - scaled[i]).abs());
        }
    }
    assert!(
        worst <= 1e-4 * (hi - lo),
        "depth moved by {worst} of a range of {}",
        hi - lo
    );
}

/// Zero vectors inside the given mask (a block of 6×6 on the sphere's slope, as a tool that
/// writes zeros for "no normal" leaves them): no depth there, a warning that counts them, and
/// the rest of the sphere integrated. Before, the default integrator took them as normals that
/// say nothing and filled them in (counted among the regions whose offset is a guess), and
/// `masked-ls` as a flat patch.
#[test]
fn zero_vectors_inside_the_mask_are_left_without_depth_and_counted() {
    let w = SPHERE.0;
    let (_, _, _, normals) = field(w, w, sphere);
    let block = |i: usize| (60..66).contains(&(i % w)) && (30..36).contains(&(i / w));
    let tmp = tempfile::tempdir().unwrap();
    let (d, said) = integrate_sphere_map(
        tmp.path(),
        "holes",
        &|i| {
            if block(i) {
                [0.0; 3]
            } else {
                normals.data()[i].into()
            }
        },
        true,
    );
    let masked = (0..w * w).filter(|&i| inside_sphere(i % w, i / w)).count();
    assert!(
        said.contains(&format!(
            "36 of the {masked} pixels of the mask have no normal"
        )),
        "{said}"
    );
    for (i, z) in d.iter().enumerate() {
        let has_depth = inside_sphere(i % w, i / w) && !block(i);
        assert_eq!(z.is_finite(), has_depth, "pixel {i}");
    }
}
