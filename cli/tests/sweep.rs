//! The speed–accuracy sweeps (`photostereo::eval::sweep`) and the `bench sweep` / `bench all`
//! commands: the sweeps show what they claim (noise hurts, shadows bias plain least squares,
//! three lights leave shadowed pixels unsolved, highlights need rejection, masks and
//! discontinuities hurt the global integrators), the Pareto front matches its definition, the
//! per-part depth error and the normal perturbation match closed forms, and the commands write
//! every table and chart.

#[path = "../../tests/common/mod.rs"]
mod common;

use photostereo::eval::metrics::{angular_errors, depth_errors, depth_rmse_per_part};
use photostereo::eval::sweep::{
    Axis, DepthRow, NormalRow, SweepOptions, depth_sweep, normal_sweep, pareto_front,
    perturb_normals, sfs_sweep,
};
use photostereo::grid::Grid;
use photostereo::integrate::Integrator;
use photostereo::ps::solve::Method;
use photostereo::sfs::SfsMethod;
use photostereo::synth::scene::{Albedo, Scene};
use rand::{RngExt, SeedableRng};

fn options() -> SweepOptions {
    SweepOptions {
        size: 96,
        sfs_size: 64,
        noise_levels: vec![0.0, 0.01, 0.05],
        light_counts: vec![3, 6, 96],
        ks_levels: vec![0.0, 0.2],
        normal_noise_levels: vec![0.0, 0.05],
        methods: vec![Method::LeastSquares, Method::Threshold, Method::Auto],
        ..SweepOptions::default()
    }
}

fn find<'a>(
    rows: &'a [NormalRow],
    axis: Axis,
    method: &str,
    pick: impl Fn(&NormalRow) -> bool,
) -> &'a NormalRow {
    rows.iter()
        .find(|r| r.axis == axis && r.method == method && pick(r))
        .unwrap_or_else(|| panic!("no {axis:?} row for {method}"))
}

/// Noise, light count and specularity on the sphere on the ground, each against what it
/// should show.
#[test]
fn normal_sweep_shows_noise_shadows_and_highlights() {
    let rows = normal_sweep(&options(), &photostereo::progress::Silent).unwrap();
    assert_eq!(rows.len(), 3 * (3 + 3 + 2));
    for r in &rows {
        assert!(r.mean_deg.is_finite() && r.seconds > 0.0, "{r:?}");
    }
    // Noise: error grows with σ; noise-free Lambertian with shadow rejection is exact.
    let th = |s: f32| find(&rows, Axis::Noise, "threshold", |r| r.noise == s).mean_deg;
    assert!(th(0.0) < 0.05, "threshold, no noise: {}", th(0.0));
    assert!(
        th(0.0) < th(0.01) && th(0.01) < th(0.05),
        "{} {} {}",
        th(0.0),
        th(0.01),
        th(0.05)
    );
    // Plain least squares counts shadowed zeros as Lambertian samples: degrees off, even
    // without noise.
    let ls = find(&rows, Axis::Noise, "ls", |r| r.noise == 0.0).mean_deg;
    assert!(ls > 3.0 && ls > th(0.0) + 3.0, "ls {ls}");
    // Light count: three lights leave every pixel shadowed in one image unsolved; 96 lights
    // solve all and average the noise down.
    let t3 = find(&rows, Axis::Lights, "threshold", |r| r.images == 3);
    let t96 = find(&rows, Axis::Lights, "threshold", |r| r.images == 96);
    assert!(t3.coverage < 0.9, "3 lights: {} solved", t3.coverage);
    assert!(t96.coverage > 0.99, "96 lights: {} solved", t96.coverage);
    let t6 = find(&rows, Axis::Lights, "threshold", |r| r.images == 6);
    assert!(
        t96.mean_deg < 0.5 * t6.mean_deg,
        "6: {} 96: {}",
        t6.mean_deg,
        t96.mean_deg
    );
    // ls solves every pixel whatever the light count.
    assert!(find(&rows, Axis::Lights, "ls", |r| r.images == 3).coverage > 0.999);
    // Highlights: auto rejects them, threshold does not.
    let glossy = |m: &str| find(&rows, Axis::Specularity, m, |r| r.ks == 0.2).mean_deg;
    assert!(
        glossy("auto") < glossy("threshold") / 3.0,
        "k_s 0.2: auto {} threshold {}",
        glossy("auto"),
        glossy("threshold")
    );
    let matte = find(&rows, Axis::Specularity, "auto", |r| r.ks == 0.0).mean_deg;
    assert!(
        glossy("auto") < matte + 0.5,
        "auto matte {matte} glossy {}",
        glossy("auto")
    );
}

/// Shape from shading: each method under the lights it accepts, accurate without noise on
/// the sphere it assumes, worse with noise; the photometric reference beside it.
#[test]
fn sfs_sweep_runs_each_method_where_it_applies() {
    let o = SweepOptions {
        noise_levels: vec![0.0, 0.05],
        ..options()
    };
    let rows = sfs_sweep(&o, &photostereo::progress::Silent).unwrap();
    for r in &rows {
        match r.method.as_str() {
            "fast-marching" => assert_eq!(r.light_slant_deg, Some(0.0)),
            "tsai-shah" => assert_eq!(r.light_slant_deg, Some(30.0)),
            "horn" => assert_eq!(r.images, 1),
            "auto" => assert!(r.light_slant_deg.is_none() && r.images >= 3),
            m => panic!("unexpected method {m}"),
        }
    }
    let horn = |s: f32| {
        rows.iter()
            .find(|r| r.method == "horn" && r.light_slant_deg == Some(0.0) && r.noise == s)
            .unwrap()
            .mean_deg
    };
    assert!(horn(0.0) < 2.0, "horn, frontal, no noise: {}", horn(0.0));
    assert!(horn(0.05) > horn(0.0) + 1.0, "{} {}", horn(0.0), horn(0.05));
    assert_eq!(
        rows.iter()
            .filter(|r| r.family == "photometric-stereo")
            .count(),
        2 * 2
    );
    // Restricting the methods restricts the rows.
    let only = SweepOptions {
        sfs: vec![SfsMethod::FastMarching],
        ..o
    };
    let rows = sfs_sweep(&only, &photostereo::progress::Silent).unwrap();
    assert!(
        rows.iter()
            .all(|r| r.method != "horn" && r.method != "tsai-shah")
    );
}

fn depth<'a>(rows: &'a [DepthRow], scene: &str, m: Integrator, noise: f64) -> &'a DepthRow {
    rows.iter()
        .find(|r| r.scene == scene && r.method == m.name() && r.normal_noise == noise)
        .unwrap()
}

/// The integrators: the vase's mask hurts Frankot–Chellappa (periodic) most and masked least
/// squares least; the floating sphere's discontinuity cannot be recovered in height, and the
/// discontinuity-preserving method keeps each object's shape best.
#[test]
fn depth_sweep_shows_masks_and_discontinuities() {
    let o = SweepOptions {
        size: 128,
        ..options()
    };
    let rows = depth_sweep(&o, &photostereo::progress::Silent).unwrap();
    assert_eq!(rows.len(), 2 * 2 * Integrator::ALL.len());
    let v = |m| depth(&rows, "vase", m, 0.0).rmse_over_range;
    assert!(
        v(Integrator::MaskedLs) < 0.75 * v(Integrator::Poisson),
        "{} {}",
        v(Integrator::MaskedLs),
        v(Integrator::Poisson)
    );
    assert!(v(Integrator::Poisson) < v(Integrator::FrankotChellappa));
    assert!(v(Integrator::FrankotChellappa) > 4.0 * v(Integrator::MaskedLs));
    assert!(
        v(Integrator::MaskedLs) < 0.015,
        "masked-ls on the vase: {}",
        v(Integrator::MaskedLs)
    );
    // Normal noise makes every method worse on the vase.
    for m in Integrator::ALL {
        let (a, b) = (depth(&rows, "vase", m, 0.0), depth(&rows, "vase", m, 0.05));
        assert!(b.normal_error_deg > 3.0 && a.normal_error_deg < 1e-4);
        assert!(
            b.rmse_over_range > a.rmse_over_range * 0.99,
            "{m:?}: {a:?} {b:?}"
        );
    }
    // The floating sphere: its height above the plane is not in the normals, so every
    // method is far off with one offset, and much closer with one offset per object.
    for m in Integrator::ALL {
        let r = depth(&rows, "floating-sphere", m, 0.0);
        assert!(r.rmse_over_range > 0.05, "{m:?}: {r:?}");
        assert!(
            r.shape_rmse_over_range < 0.5 * r.rmse_over_range,
            "{m:?}: {r:?}"
        );
    }
    let f = |m| depth(&rows, "floating-sphere", m, 0.0).shape_rmse_over_range;
    assert!(
        f(Integrator::Bilateral) < f(Integrator::Poisson),
        "bilateral {} poisson {}",
        f(Integrator::Bilateral),
        f(Integrator::Poisson)
    );
}

/// The front against its definition: a point is on it when no other point is at most as
/// costly and at most as wrong, and better in one.
#[test]
fn pareto_front_matches_brute_force() {
    let mut rng = rand::rngs::ChaCha8Rng::seed_from_u64(5);
    for trial in 0..200 {
        let n = 1 + trial % 17;
        // Coarse values so that ties happen.
        let pts: Vec<(f64, f64)> = (0..n)
            .map(|_| {
                (
                    f64::from(rng.random_range(0..8u32)),
                    f64::from(rng.random_range(0..8u32)),
                )
            })
            .collect();
        let front = pareto_front(&pts);
        let dominated = |i: usize| {
            (0..n).any(|j| {
                let (a, b) = (pts[j], pts[i]);
                (a.0 <= b.0 && a.1 <= b.1 && (a.0 < b.0 || a.1 < b.1)) || (a == b && j < i)
            })
        };
        let expect: Vec<usize> = (0..n).filter(|&i| !dominated(i)).collect();
        let mut got = front.clone();
        got.sort_unstable();
        assert_eq!(got, expect, "{pts:?}");
        // In order of increasing cost and decreasing error.
        for w in front.windows(2) {
            assert!(pts[w[0]].0 < pts[w[1]].0 && pts[w[0]].1 > pts[w[1]].1);
        }
    }
    assert!(pareto_front(&[(f64::NAN, 1.0), (1.0, f64::INFINITY)]).is_empty());
}

/// Per-part offsets vanish from the per-part RMSE and not from the global one; a known error
/// inside one part comes out exactly.
#[test]
fn depth_rmse_per_part_removes_each_parts_offset() {
    let (w, h) = (20, 10);
    let parts = Grid::from_fn(w, h, |c, _| u32::from(c >= 10));
    let mask = Grid::new(w, h, true);
    let gt = Grid::from_fn(w, h, |c, r| (c * r) as f32 * 0.1);
    let shifted = Grid::from_fn(w, h, |c, r| *gt.at(c, r) + if c >= 10 { 7.0 } else { -3.0 });
    assert!(depth_rmse_per_part(&shifted, &gt, &mask, &parts).unwrap() < 1e-5);
    // The global error of that shift: half the pixels at +5, half at −5 around the mean.
    let global = depth_errors(&shifted, &gt, &mask).unwrap().rmse;
    assert!((global - 5.0).abs() < 1e-4, "{global}");
    // ±1 alternating inside part 1 (zero mean): RMSE over all pixels √(1/2).
    let bumpy = Grid::from_fn(w, h, |c, r| {
        *gt.at(c, r)
            + if c >= 10 {
                if (c + r) % 2 == 0 { 1.0 } else { -1.0 }
            } else {
                0.0
            }
    });
    let e = depth_rmse_per_part(&bumpy, &gt, &mask, &parts).unwrap();
    assert!((e - 0.5f64.sqrt()).abs() < 1e-5, "{e}");
    // Sizes are checked.
    assert!(depth_rmse_per_part(&bumpy, &gt, &mask, &Grid::new(3, 3, 0)).is_err());
}

/// Isotropic noise σ on each component tilts a normal by about σ·√(π/2) radians on average
/// (the mean of a 2-D Rayleigh distribution) for small σ.
#[test]
fn perturbed_normals_have_the_expected_angular_error() {
    let hf = Scene::sphere(128, 50.0, Albedo::Constant(0.5)).height_field();
    for sigma in [0.01, 0.03] {
        let n = perturb_normals(&hf.normals, sigma, 3).unwrap();
        let e = angular_errors(&n, &hf.normals, &hf.mask).unwrap().mean_deg;
        let expect = (sigma * (std::f64::consts::PI / 2.0).sqrt()).to_degrees();
        assert!(
            (e / expect - 1.0).abs() < 0.03,
            "σ {sigma}: {e}° against {expect}°"
        );
    }
    let same = perturb_normals(&hf.normals, 0.0, 3).unwrap();
    // Unchanged: only the rounding of arccos near 1 remains.
    assert!(
        angular_errors(&same, &hf.normals, &hf.mask)
            .unwrap()
            .mean_deg
            < 1e-4
    );
    assert!(perturb_normals(&hf.normals, -1.0, 3).is_err());
}

/// Bad options are refused with the parameter's name.
#[test]
fn bad_sweep_options_name_the_parameter() {
    let cases: [(SweepOptions, &str); 4] = [
        (
            SweepOptions {
                size: 8,
                ..options()
            },
            "size",
        ),
        (
            SweepOptions {
                light_counts: vec![2],
                ..options()
            },
            "lights",
        ),
        (
            SweepOptions {
                noise_levels: vec![f32::NAN],
                ..options()
            },
            "noise",
        ),
        (
            SweepOptions {
                ks_levels: vec![1.5],
                ..options()
            },
            "ks",
        ),
    ];
    for (o, name) in cases {
        let e = normal_sweep(&o, &photostereo::progress::Silent).unwrap_err();
        assert!(e.to_string().contains(name), "{name}: {e}");
    }
}

/// Runs `photostereo bench all --quick -q` into `out` with `data` and `peer`.
fn bench_all_quick(
    out: &std::path::Path,
    data: &std::path::Path,
    peer: &std::path::Path,
) -> std::process::Output {
    common::run(&[
        common::os("bench"),
        common::os("all"),
        common::os("--quick"),
        common::os("-q"),
        common::os("--out"),
        out.as_os_str(),
        common::os("--data"),
        data.as_os_str(),
        common::os("--peer"),
        peer.as_os_str(),
    ])
}

/// `bench all --quick` without data or peer: every sweep table and chart, the scaling and
/// integration parts, DiLiGenT skipped with a message, and a generated README.
#[test]
fn bench_all_writes_every_table_and_chart() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("bench");
    let o = bench_all_quick(
        &out,
        &dir.path().join("no-data"),
        &dir.path().join("no-peer.py"),
    );
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    assert!(stderr.contains("skipping DiLiGenT cat"), "{stderr}");
    for stem in [
        "normals_vs_noise",
        "normals_vs_lights",
        "coverage_vs_lights",
        "normals_vs_specularity",
        "normals_pareto",
        "normals_pareto_glossy",
        "sfs_vs_noise",
        "depth_vs_noise_vase",
        "depth_vs_noise_floating-sphere",
        "depth_pareto",
        "scaling",
        "integration_time",
        "sfs",
    ] {
        let png = image::open(out.join(format!("{stem}.png"))).unwrap();
        assert_eq!((png.width(), png.height()), (900, 600), "{stem}");
        // Not blank: a chart has dark pixels (axes, text) on white.
        let dark = png.to_luma8().pixels().filter(|p| p.0[0] < 100).count();
        assert!(dark > 1000, "{stem}: {dark} dark pixels");
        let svg = std::fs::read_to_string(out.join(format!("{stem}.svg"))).unwrap();
        assert!(svg.starts_with("<svg") && svg.contains("</svg>"), "{stem}");
    }
    // The normals table: one row per method and condition, numbers that parse.
    let csv = std::fs::read_to_string(out.join("sweep_normals.csv")).unwrap();
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |name| header.iter().position(|h| *h == name).unwrap();
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    // --quick: 3 noise levels, 3 light counts, 2 k_s, all 9 methods.
    assert_eq!(rows.len(), (3 + 3 + 2) * Method::ALL.len());
    for r in &rows {
        let e: f64 = r[col("mean_deg")].parse().unwrap();
        let c: f64 = r[col("coverage")].parse().unwrap();
        assert!(
            e.is_finite() && e >= 0.0 && (0.0..=1.0).contains(&c),
            "{r:?}"
        );
    }
    for f in [
        "sweep_sfs.csv",
        "sweep_depth.csv",
        "scaling.csv",
        "integration.csv",
    ] {
        assert!(
            std::fs::read_to_string(out.join(f))
                .unwrap()
                .lines()
                .count()
                > 2,
            "{f}"
        );
    }
    let readme = std::fs::read_to_string(out.join("README.md")).unwrap();
    for section in [
        "## Normals",
        "## Shape from shading",
        "## Integrators",
        "## Cost against size",
        "## Shape from shading on rendered shapes",
        "Not run",
    ] {
        assert!(readme.contains(section), "{section}");
    }
    // Shape from shading: five shapes × two lights × (horn, tsai-shah, fast-marching, the
    // perspective method swept and refined), each refused or with finite errors.
    let sfs: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("sfs.json")).unwrap()).unwrap();
    let rows = sfs["rows"].as_array().unwrap();
    assert_eq!(rows.len(), 5 * 2 * 5);
    for r in rows {
        assert!(
            r["refused"].is_string()
                || (r["normals_deg"].as_f64().unwrap().is_finite()
                    && r["depth"].as_f64().unwrap().is_finite()),
            "{r}"
        );
    }
    // Nothing left half-written.
    assert!(
        std::fs::read_dir(&out).unwrap().all(|e| !e
            .unwrap()
            .file_name()
            .to_string_lossy()
            .starts_with('.')),
    );
}

/// `bench diligent` reports the load and solve stages beside the numpy peer's, as ratios.
#[test]
fn bench_diligent_reports_per_stage_ratios() {
    let dir = require_shared!("diligent/catPNG");
    let peer = common::repo().join("../shared/peers/numpy_ps.py");
    let o = common::run(&[
        common::os("bench"),
        common::os("diligent"),
        dir.as_os_str(),
        common::os("--method"),
        common::os("ls"),
        common::os("--integrate"),
        common::os("none"),
        common::os("--repeat"),
        common::os("1"),
        common::os("--peer"),
        peer.as_os_str(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    if v["peer"].is_string() {
        eprintln!("SKIPPED ratio check: {}", v["peer"]);
        return;
    }
    for stage in ["load", "solve"] {
        let ratio = v["speedup_per_stage"][stage].as_f64().unwrap();
        let ours = v["photostereo"][format!("{stage}_s")].as_f64().unwrap();
        let theirs = v["peer"][format!("{stage}_s")].as_f64().unwrap();
        assert!(ours > 0.0 && theirs > 0.0, "{stage}: {ours} {theirs}");
        assert!(
            (ratio - theirs / ours).abs() < 1e-9 * ratio.abs().max(1.0),
            "{stage}"
        );
    }
}

/// Smallest angle between two of `dirs`, in degrees.
fn min_angle(dirs: &[photostereo::nalgebra::Vector3<f64>]) -> f64 {
    let mut best = f64::INFINITY;
    for i in 0..dirs.len() {
        for j in i + 1..dirs.len() {
            best = best.min(
                dirs[i]
                    .normalize()
                    .dot(&dirs[j].normalize())
                    .clamp(-1.0, 1.0)
                    .acos(),
            );
        }
    }
    best.to_degrees()
}

/// Well-spread subsets: distinct sorted indices, every light at the full count, and a larger
/// smallest separation than the first or every k-th lights of a spiral.
#[test]
fn spread_lights_are_well_separated() {
    let lights = photostereo::capture::lights::Lights::fibonacci(96, 20.0).unwrap();
    let dirs = lights.directions();
    for count in [3usize, 6, 12, 24] {
        let pick = lights.spread(count).unwrap();
        assert_eq!(pick.len(), count);
        assert!(pick.windows(2).all(|w| w[0] < w[1]), "{pick:?}");
        let chosen: Vec<_> = pick.iter().map(|&k| dirs[k]).collect();
        let first: Vec<_> = dirs[..count].to_vec();
        let strided: Vec<_> = (0..count).map(|i| dirs[i * 96 / count]).collect();
        let (a, b, c) = (min_angle(&chosen), min_angle(&first), min_angle(&strided));
        assert!(
            a > b && a >= c * 0.9,
            "{count}: spread {a:.1}° first {b:.1}° strided {c:.1}°"
        );
    }
    assert_eq!(lights.spread(96).unwrap(), (0..96).collect::<Vec<_>>());
    assert!(lights.spread(0).is_err());
    assert!(lights.spread(97).unwrap_err().to_string().contains("count"));
}

/// A selected capture is the capture those lights would have given: solving it matches the
/// truth as well as a capture rendered under those lights alone, and indices are checked.
#[test]
fn a_selected_capture_matches_one_rendered_with_those_lights() {
    use photostereo::capture::stack::ColorMode;
    use photostereo::ps::solve::SolveOptions;
    use photostereo::run::pipeline::{Config, reconstruct};
    use photostereo::synth::render::{RenderOptions, render};
    let scene = Scene::sphere(64, 26.0, Albedo::Constant(0.6));
    let all = photostereo::capture::lights::Lights::fibonacci(48, 30.0).unwrap();
    let render_capture = |lights: &photostereo::capture::lights::Lights| {
        let r = render(&scene, lights, &RenderOptions::default()).unwrap();
        let stack = r.to_stack(lights, ColorMode::Grey).unwrap();
        (
            photostereo::capture::dataset::Capture::from_stack(
                stack,
                lights.clone(),
                Some(r.truth.mask.clone()),
            )
            .unwrap(),
            r.truth,
        )
    };
    let (capture, truth) = render_capture(&all);
    let pick = all.spread(6).unwrap();
    let sub = capture.select(&pick).unwrap();
    assert_eq!(sub.lights.len(), 6);
    assert_eq!(sub.stack.count(), 6);
    let direct = photostereo::capture::lights::Lights::new(
        pick.iter().map(|&k| all.lights()[k].clone()).collect(),
    )
    .unwrap();
    let (rendered, _) = render_capture(&direct);
    for k in 0..6 {
        assert_eq!(
            sub.stack.plane(k, 0),
            rendered.stack.plane(k, 0),
            "image {k}"
        );
    }
    // Exact over the pixels the six lights determine (the others are not filled).
    let config = Config {
        solve: SolveOptions {
            fill: false,
            ..SolveOptions::with_method(Method::Threshold)
        },
        integration: None,
        ..Config::default()
    };
    let e = angular_errors(
        &reconstruct(&sub, &config, &photostereo::progress::Silent)
            .unwrap()
            .maps
            .normals,
        &truth.normals,
        &truth.mask,
    )
    .unwrap();
    assert!(e.mean_deg < 0.01, "{}", e.mean_deg);
    assert!(capture.select(&[]).is_err());
    assert!(
        capture
            .select(&[0, 48])
            .unwrap_err()
            .to_string()
            .contains("48")
    );
}

/// `bench all --quick` on the shared DiLiGenT data: the per-stage peer comparison, every
/// estimator's error (plain least squares reproduces the benchmark's 8.41° and 8.39°), and the
/// light-count sweep on well-spread subsets, as tables and charts.
#[test]
fn bench_all_on_real_data() {
    let data = require_shared!("diligent/catPNG");
    let data = data
        .parent()
        .and_then(|p| p.parent())
        .unwrap()
        .to_path_buf();
    let peer = common::repo().join("../shared/peers/numpy_ps.py");
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("bench");
    let o = bench_all_quick(&out, &data, &peer);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let read = |f: &str| std::fs::read_to_string(out.join(f)).unwrap();
    let rows = |f: &str| -> Vec<std::collections::HashMap<String, String>> {
        let text = read(f);
        let mut lines = text.lines();
        let header: Vec<String> = lines.next().unwrap().split(',').map(String::from).collect();
        lines
            .map(|l| {
                header
                    .iter()
                    .cloned()
                    .zip(l.split(',').map(String::from))
                    .collect()
            })
            .collect()
    };
    let value =
        |r: &std::collections::HashMap<String, String>, k: &str| -> f64 { r[k].parse().unwrap() };
    let methods = rows("diligent_methods.csv");
    assert_eq!(methods.len(), 2 * Method::ALL.len());
    for (object, reference) in [("cat", 8.41), ("bear", 8.39)] {
        let of = |m: &str| {
            methods
                .iter()
                .find(|r| r["object"] == object && r["method"] == m)
                .unwrap()
        };
        let ls = value(of("ls"), "mean_deg");
        assert!((ls - reference).abs() < 0.02, "{object}: ls {ls}");
        assert!(value(of("auto"), "mean_deg") < ls - 2.0, "{object}");
        let stage: serde_json::Value =
            serde_json::from_str(&read(&format!("diligent_{object}.json"))).unwrap();
        if stage["peer"].is_object() {
            assert!(stage["speedup_per_stage"]["load"].as_f64().unwrap() > 0.0);
        }
    }
    let lights = rows("diligent_lights.csv");
    assert_eq!(lights.len(), 2 * 7 * Method::ALL.len());
    for r in &lights {
        let c = value(r, "coverage");
        assert!(
            (0.0..=1.0).contains(&c) && value(r, "mean_deg").is_finite(),
            "{r:?}"
        );
    }
    // All 96 lights: the same numbers as the per-method table.
    for r in lights.iter().filter(|r| r["lights"] == "96") {
        let m = methods
            .iter()
            .find(|m| m["object"] == r["object"] && m["method"] == r["method"])
            .unwrap();
        assert!(
            (value(r, "mean_deg") - value(m, "mean_deg")).abs() < 1e-4,
            "{r:?}"
        );
    }
    for stem in [
        "diligent_pareto",
        "diligent_lights_cat",
        "diligent_lights_bear",
    ] {
        assert!(
            out.join(format!("{stem}.png")).is_file() && out.join(format!("{stem}.svg")).is_file(),
            "{stem}"
        );
    }
    let readme = read("README.md");
    assert!(
        readme.contains("## DiLiGenT beside the numpy peer")
            && readme.contains("against light count")
    );

    // Every integrator on the shared depth data: cat and bear with K, the vase exact and
    // noisy.
    let depth = rows("integration_real.csv");
    assert_eq!(
        depth.len(),
        4 * photostereo::integrate::Integrator::ALL.len()
    );
    for r in &depth {
        assert!(
            value(r, "error") > 0.0 && value(r, "seconds") > 0.0,
            "{r:?}"
        );
    }
    let made = |object: &str, m: &str| {
        value(
            depth
                .iter()
                .find(|r| r["dataset"] == object && r["method"] == m)
                .unwrap(),
            "error",
        )
    };
    // Cat's occlusion edges: the discontinuity-preserving method is far better.
    assert!(made("cat", "bilateral") < 0.2 * made("cat", "masked-ls"));
    assert!(out.join("integration_diligent.png").is_file());
}
