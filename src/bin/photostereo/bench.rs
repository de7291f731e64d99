//! `photostereo bench`: end-to-end timing on a DiLiGenT folder beside the numpy peer, in one run.
//!
//! Both tools are timed as whole processes (start-up, load, solve, and for photostereo also
//! integration and writing every output), alternating runs so that machine load hits both alike;
//! photostereo's stages are also timed in-process, with the time to stream the loaded stack
//! through memory once as the yardstick for the solve.

use crate::args::{BenchArgs, IntegrateArg, IntegrationBenchArgs};
use anyhow::{Context, Result};
use photostereo::capture::dataset::Capture;
use photostereo::capture::stack::LoadOptions;
use photostereo::eval::metrics::depth_errors;
use photostereo::grid::Grid;
use photostereo::integrate::{
    IntegrationOptions, Integrator, LinearSolver, integrate_gradients, integrate_normals,
};
use photostereo::progress::Silent;
use photostereo::run::pipeline::{reconstruct, reconstruct_and_write};
use photostereo::synth::scene::{Albedo, Scene};
use rayon::prelude::*;
use serde_json::json;
use std::process::Command;
use std::time::Instant;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    if v.is_empty() {
        f64::NAN
    } else if v.len() % 2 == 1 {
        v[v.len() / 2]
    } else {
        (v[v.len() / 2 - 1] + v[v.len() / 2]) / 2.0
    }
}

/// Runs the benchmark; JSON with in-process stage times, whole-process times beside the peer's,
/// and the peer's time over ours per stage (load, solve) and per process.
pub fn run(a: &BenchArgs) -> Result<serde_json::Value> {
    let config = a.method.config()?;
    let repeat = a.repeat.max(1);
    let tmp = std::env::temp_dir().join(format!("photostereo-bench-{}", std::process::id()));
    let (mut total, mut load, mut solve, mut integrate, mut write, mut stream) =
        (vec![], vec![], vec![], vec![], vec![], vec![]);
    let mut bytes = 0usize;
    for _ in 0..repeat {
        let t = Instant::now();
        let capture = Capture::from_diligent(&a.dir, &LoadOptions::default(), &Silent)?;
        let load_s = t.elapsed().as_secs_f64();
        let (recon, _) =
            reconstruct_and_write(&capture, &config, &tmp, load_s, &Silent, |_| Ok(None))?;
        total.push(t.elapsed().as_secs_f64());
        load.push(load_s);
        solve.push(recon.timings.solve);
        integrate.push(recon.timings.integrate);
        write.push(recon.timings.write);
        // Memory-streaming reference: one parallel pass summing every sample of the stack.
        let data = capture.stack.data();
        bytes = std::mem::size_of_val(data);
        let t = Instant::now();
        let s: f64 = data
            .par_chunks(1 << 16)
            .map(|c| c.iter().map(|v| f64::from(*v)).sum::<f64>())
            .sum();
        stream.push(t.elapsed().as_secs_f64());
        std::hint::black_box(s);
    }
    let ours = json!({
        "in_process_total_s": median(total),
        "load_s": median(load),
        "solve_s": median(solve.clone()),
        "integrate_s": median(integrate),
        "write_s": median(write),
        "stream_stack_once_s": median(stream.clone()),
        "stack_bytes": bytes,
        "solve_over_stream": median(solve) / median(stream),
    });
    let mut out = json!({
        "dataset": a.dir,
        "repeat": repeat,
        "threads": rayon::current_num_threads(),
        "method": config.solve.method.name(),
        "integrator": config.integration.map_or("none", |o| o.method.name()),
        "photostereo": ours,
    });
    // Whole-process timings, ours and the peer's, interleaved.
    let exe = std::env::current_exe().context("locating the photostereo executable")?;
    let method = config.solve.method.name();
    let integrate = config.integration.map_or("none", |o| o.method.name());
    let peer = a.peer.script.is_file();
    let (mut ours_wall, mut peer_wall) = (vec![], vec![]);
    let (mut peer_load, mut peer_solve) = (vec![], vec![]);
    for _ in 0..repeat {
        let t = Instant::now();
        let o = Command::new(&exe)
            .arg(&a.dir)
            // The same scratch folder every time: --force lets each run overwrite the last.
            .args([
                "--method",
                method,
                "--integrate",
                integrate,
                "-q",
                "--force",
                "-o",
            ])
            .arg(&tmp)
            .output()?;
        ours_wall.push(t.elapsed().as_secs_f64());
        anyhow::ensure!(
            o.status.success(),
            "photostereo failed: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        if peer {
            let t = Instant::now();
            let o = Command::new(&a.peer.python)
                .arg(&a.peer.script)
                .arg("diligent")
                .arg(&a.dir)
                .output()
                .with_context(|| {
                    format!("running {} {}", a.peer.python, a.peer.script.display())
                })?;
            peer_wall.push(t.elapsed().as_secs_f64());
            anyhow::ensure!(
                o.status.success(),
                "peer failed: {}",
                String::from_utf8_lossy(&o.stderr)
            );
            let v: serde_json::Value = serde_json::from_slice(&o.stdout)?;
            peer_load.push(v["load_s"].as_f64().unwrap_or(f64::NAN));
            peer_solve.push(v["solve_s"].as_f64().unwrap_or(f64::NAN));
        }
    }
    let _ = std::fs::remove_dir_all(&tmp);
    let ours_process = median(ours_wall);
    out["photostereo"]["process_wall_s"] = json!(ours_process);
    if peer {
        let pw = median(peer_wall);
        let (pl, ps) = (median(peer_load), median(peer_solve));
        out["peer"] = json!({
            "script": a.peer.script,
            "method": "ls",
            "process_wall_s": pw,
            "load_s": pl,
            "solve_s": ps,
            "load_plus_solve_s": pl + ps,
        });
        // Peer time over ours: above 1, photostereo is faster. The solve ratio compares like
        // with like only for --method ls (the peer's method).
        let (ol, os) = (
            out["photostereo"]["load_s"].as_f64().unwrap_or(f64::NAN),
            out["photostereo"]["solve_s"].as_f64().unwrap_or(f64::NAN),
        );
        out["speedup_per_stage"] = json!({
            "load": pl / ol,
            "solve": ps / os,
            "load_plus_solve": (pl + ps) / (ol + os),
            "solve_methods": format!("{method} vs ls"),
        });
        out["speedup_process_vs_process"] = json!(pw / ours_process);
        out["speedup_vs_peer_load_plus_solve"] = json!((pl + ps) / ours_process);
    } else {
        out["peer"] = json!(format!("not found: {}", a.peer.script.display()));
    }
    Ok(out)
}

/// Time and accuracy of each integrator on a sphere (radius 0.45 N on an N×N image, disk mask)
/// per size, and DCT Poisson beside `numpy_ps.py poisson N` on the peer's own field (MATLAB's
/// peaks on the full N×N grid).
pub fn integration(a: &IntegrationBenchArgs) -> Result<serde_json::Value> {
    let methods: Vec<Integrator> = if a.methods.is_empty() {
        Integrator::ALL.to_vec()
    } else {
        a.methods
            .iter()
            .filter_map(|m| IntegrateArg::method(*m))
            .collect()
    };
    let mut rows = Vec::new();
    let mut table = String::from(
        "| method | pixels | time (s) | depth RMSE / range |\n| --- | --- | --- | --- |\n",
    );
    for &n in &a.sizes {
        let hf = Scene::sphere(n, 0.45 * n as f64, Albedo::Constant(0.5)).height_field();
        let reps = if n <= 512 { a.repeat.max(1) } else { 1 };
        for &m in &methods {
            let options = IntegrationOptions {
                method: m,
                ..IntegrationOptions::default()
            };
            let mut times = Vec::new();
            let mut err = f64::NAN;
            let mut solve = None;
            for _ in 0..reps {
                let t = Instant::now();
                let r = integrate_normals(
                    &hf.normals,
                    &hf.mask,
                    &options,
                    &photostereo::progress::Silent,
                )?;
                times.push(t.elapsed().as_secs_f64());
                err = depth_errors(&r.depth, &hf.depth, &hf.mask)?.rmse_over_range;
                solve = r.solve;
            }
            let t = median(times);
            table += &format!(
                "| {} | {n}² ({} in mask) | {t:.3} | {:.2}% |\n",
                m.name(),
                hf.mask.count(),
                100.0 * err
            );
            rows.push(
                json!({"method": m.name(), "size": n, "pixels": hf.mask.count(), "time_s": t,
                "rmse_over_range": err, "solve": solve}),
            );
        }
    }
    // DCT Poisson against the peer on its own test field.
    let mut peer_rows = Vec::new();
    if a.peer.script.is_file() {
        for &n in &a.sizes {
            let (p, q) = peaks_gradients(n);
            let mask = Grid::new(n, n, true);
            let mut ours = Vec::new();
            for _ in 0..a.repeat.max(1) {
                let t = Instant::now();
                integrate_gradients(&p, &q, &mask, Integrator::Poisson, LinearSolver::Auto)?;
                ours.push(t.elapsed().as_secs_f64());
            }
            let mut theirs = Vec::new();
            for _ in 0..a.repeat.max(1) {
                let o = Command::new(&a.peer.python)
                    .arg(&a.peer.script)
                    .arg("poisson")
                    .arg(n.to_string())
                    .output()?;
                anyhow::ensure!(
                    o.status.success(),
                    "peer failed: {}",
                    String::from_utf8_lossy(&o.stderr)
                );
                let v: serde_json::Value = serde_json::from_slice(&o.stdout)?;
                theirs.push(v["solve_s"].as_f64().unwrap_or(f64::NAN));
            }
            let (o, t) = (median(ours), median(theirs));
            peer_rows.push(json!({"size": n, "photostereo_poisson_s": o, "numpy_dct_poisson_s": t, "speedup": t / o}));
        }
    }
    let mut slopes = Vec::new();
    let mut series = Vec::new();
    for (k, m) in methods.iter().enumerate() {
        let (x, y): (Vec<f64>, Vec<f64>) = rows
            .iter()
            .filter(|r| r["method"] == m.name())
            .filter_map(|r| Some((r["pixels"].as_f64()?, r["time_s"].as_f64()?)))
            .unzip();
        let (lx, ly): (Vec<f64>, Vec<f64>) = (
            x.iter().map(|v| v.ln()).collect(),
            y.iter().map(|v| v.ln()).collect(),
        );
        let (slope, intercept) = fit_line(&lx, &ly);
        slopes.push(json!({"method": m.name(), "loglog_slope_vs_pixels": slope}));
        let (name, pts) = (
            format!("{} (slope {slope:.2})", m.name()),
            x.iter().copied().zip(y.iter().copied()).collect(),
        );
        series.push(crate::chart::Series::line(name, pts, k).styled(crate::chart::Style::Markers));
        series.push(power_law_fit(&lx, slope, intercept, k));
    }
    if let Some(stem) = &a.chart {
        crate::chart::write(
            &crate::chart::Chart {
                title: format!(
                    "Integration time vs pixels (sphere, disk mask, {} threads)",
                    rayon::current_num_threads()
                ),
                x_label: "pixels in mask".into(),
                y_label: "integration time (s)".into(),
                log: (true, true),
                series,
                legend: crate::chart::Legend::UpperLeft,
            },
            stem,
        )?;
    }
    if let Some(path) = &a.csv {
        crate::sweep::write_csv(
            path,
            &rows,
            &["method", "size", "pixels", "time_s", "rmse_over_range"],
        )?;
    }
    Ok(
        json!({"threads": rayon::current_num_threads(), "integrators": rows,
        "slopes": slopes, "poisson_vs_numpy": peer_rows, "table": table}),
    )
}

/// The fitted power law exp(intercept)·x^slope over the span of the logs `lx`, as a line in
/// palette colour `color`.
fn power_law_fit(lx: &[f64], slope: f64, intercept: f64, color: usize) -> crate::chart::Series {
    let (lo, hi) = lx
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
            (a.min(*v), b.max(*v))
        });
    let fit = [lo, hi]
        .iter()
        .map(|v| (v.exp(), (intercept + slope * v).exp()))
        .collect();
    crate::chart::Series::line("", fit, color).styled(crate::chart::Style::Fit)
}

/// The peer's test field: forward differences of MATLAB's peaks on [−3, 3]², converted to our
/// gradient convention (x right, y up).
fn peaks_gradients(n: usize) -> (photostereo::grid::ScalarMap, photostereo::grid::ScalarMap) {
    let f = |x: f64, y: f64| {
        3.0 * (1.0 - x).powi(2) * (-x * x - (y + 1.0).powi(2)).exp()
            - 10.0 * (x / 5.0 - x.powi(3) - y.powi(5)) * (-x * x - y * y).exp()
            - (-(x + 1.0).powi(2) - y * y).exp() / 3.0
    };
    let z = |c: usize, r: usize| {
        f(
            c as f64 / n as f64 * 6.0 - 3.0,
            r as f64 / n as f64 * 6.0 - 3.0,
        )
    };
    let p = Grid::from_fn(n, n, |c, r| {
        if c + 1 < n {
            (z(c + 1, r) - z(c, r)) as f32
        } else {
            0.0
        }
    });
    // The peer's rows run downwards; our q is ∂z/∂y with y up.
    let q = Grid::from_fn(n, n, |c, r| {
        if r + 1 < n {
            -(z(c, r + 1) - z(c, r)) as f32
        } else {
            0.0
        }
    });
    (p, q)
}

/// `bench specularity`: mean angular error of each estimator against the specular strength k_s
/// on [`Scene::sphere_on_ground`] rendered with Blinn–Phong (n = 50) and Torrance–Sparrow
/// (m = 0.2) lobes, cast shadows and noise, under one light set; JSON rows to standard output.
pub fn specularity(a: crate::args::SpecularityBenchArgs) -> Result<()> {
    use crate::args::MethodArg;
    use clap::ValueEnum;
    use photostereo::capture::lights::Lights;
    use photostereo::capture::stack::ColorMode;
    use photostereo::eval::metrics::angular_errors;
    use photostereo::ps::solve::SolveOptions;
    use photostereo::run::pipeline::Config;
    use photostereo::synth::reflectance::{BlinnPhong, Material, Specular, TorranceSparrow};
    use photostereo::synth::render::{RenderOptions, render};
    anyhow::ensure!(a.size >= 16, "--size {}: at least 16", a.size);
    anyhow::ensure!(a.lights >= 3, "--lights {}: at least 3", a.lights);
    let methods: Vec<MethodArg> = if a.methods.is_empty() {
        MethodArg::value_variants().to_vec()
    } else {
        a.methods.clone()
    };
    let lights = Lights::fibonacci(a.lights, 30.0)?;
    type Lobe = fn(f64) -> Specular;
    let lobes: [(&str, Lobe); 2] = [
        ("blinn-phong n=50", |ks| {
            Specular::BlinnPhong(BlinnPhong { ks, exponent: 50.0 })
        }),
        ("torrance-sparrow m=0.2", |ks| {
            Specular::TorranceSparrow(TorranceSparrow {
                ks,
                roughness: 0.2,
                f0: 1.0,
            })
        }),
    ];
    let mut rows = Vec::new();
    for (lobe, make) in lobes {
        for &ks in &a.ks {
            let material = if ks > 0.0 {
                Material::with_specular(make(ks))
            } else {
                Material::lambertian()
            };
            material.validate()?;
            let scene = Scene::sphere_on_ground(a.size, material);
            let options = RenderOptions {
                noise_sigma: a.noise,
                seed: 7,
                ..RenderOptions::default()
            };
            let rendering = render(&scene, &lights, &options)?;
            let stack = rendering.to_stack(&lights, ColorMode::Grey)?;
            let capture =
                Capture::from_stack(stack, lights.clone(), Some(rendering.truth.mask.clone()))?;
            for m in &methods {
                let config = Config {
                    solve: SolveOptions::with_method(m.method()),
                    integration: None,
                    ..Config::default()
                };
                let t = Instant::now();
                let recon = reconstruct(&capture, &config, &Silent)?;
                let seconds = t.elapsed().as_secs_f64();
                let e = angular_errors(&recon.normals, &rendering.truth.normals, &capture.mask)?;
                rows.push(json!({
                    "lobe": lobe,
                    "ks": ks,
                    "method": m.method().name(),
                    "mean_deg": e.mean_deg,
                    "median_deg": e.median_deg,
                    "p95_deg": e.p95_deg,
                    "unsolved": e.missing,
                    "robust_fraction": recon.model.robust_fraction,
                    "seconds": seconds,
                }));
            }
        }
    }
    if a.markdown {
        let names: Vec<&str> = methods.iter().map(|m| m.method().name()).collect();
        eprintln!("| lobe | k_s | {} |", names.join(" | "));
        eprintln!("|---|---|{}", "---:|".repeat(names.len()));
        for chunk in rows.chunks(methods.len()) {
            let cells: Vec<String> = chunk
                .iter()
                .map(|r| format!("{:.2}", r["mean_deg"].as_f64().unwrap_or(f64::NAN)))
                .collect();
            eprintln!(
                "| {} | {} | {} |",
                chunk[0]["lobe"].as_str().unwrap_or(""),
                chunk[0]["ks"],
                cells.join(" | ")
            );
        }
    }
    say!(
        "{}",
        serde_json::to_string_pretty(&json!({
            "scene": "sphere_on_ground",
            "size": a.size,
            "lights": a.lights,
            "noise_sigma": a.noise,
            "rows": rows,
        }))?
    );
    Ok(())
}

/// Runs `cmd` to completion; returns its wall time in seconds and its peak resident memory in
/// bytes (Linux: the child's `ru_maxrss` from `wait4`; elsewhere 0).
fn run_measured(cmd: &mut Command) -> Result<(f64, u64)> {
    let t = Instant::now();
    let child = cmd
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .context("starting photostereo")?;
    #[cfg(target_os = "linux")]
    {
        let pid = child.id() as libc::pid_t;
        let mut status = 0;
        // SAFETY: `rusage` is plain data that wait4 fills in; `pid` is our own child, waited
        // for once (the Child handle is not waited on again).
        let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
        let r = unsafe { libc::wait4(pid, &mut status, 0, &mut usage) };
        let seconds = t.elapsed().as_secs_f64();
        anyhow::ensure!(r == pid, "waiting for photostereo failed");
        let mut stderr = String::new();
        if let Some(mut e) = child.stderr {
            use std::io::Read;
            let _ = e.read_to_string(&mut stderr);
        }
        anyhow::ensure!(
            libc::WIFEXITED(status) && libc::WEXITSTATUS(status) == 0,
            "photostereo failed: {stderr}"
        );
        // ru_maxrss is in KiB on Linux.
        Ok((seconds, usage.ru_maxrss as u64 * 1024))
    }
    #[cfg(not(target_os = "linux"))]
    {
        let o = child.wait_with_output()?;
        anyhow::ensure!(
            o.status.success(),
            "photostereo failed: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        Ok((t.elapsed().as_secs_f64(), 0))
    }
}

/// `bench stream`: the same stack solved in memory and streamed within `--max-memory`, as
/// child processes (alternating, so machine load hits both alike); medians of wall time and
/// peak resident memory, and their ratios, as JSON.
pub fn stream(a: crate::args::StreamBenchArgs) -> Result<()> {
    let budget = photostereo::run::stream::parse_size(&a.max_memory)?;
    let mut images: Vec<std::path::PathBuf> = std::fs::read_dir(&a.dir)
        .with_context(|| format!("reading {}", a.dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with("img_"))
        })
        .collect();
    images.sort();
    anyhow::ensure!(!images.is_empty(), "no img_* files in {}", a.dir.display());
    let exe = std::env::current_exe().context("locating the photostereo executable")?;
    let out = std::env::temp_dir().join(format!("photostereo-bench-stream-{}", std::process::id()));
    let mask = a.dir.join("mask.png");
    let integrate = clap::ValueEnum::to_possible_value(&a.integrate)
        .map(|v| v.get_name().to_string())
        .unwrap_or_else(|| "none".into());
    let command = |streamed: bool| {
        let mut c = Command::new(&exe);
        c.args(&images)
            .arg("--lights")
            .arg(a.dir.join("lights.json"))
            .args(["--integrate", &integrate, "-q", "--force", "-o"])
            .arg(&out);
        if !a.no_mask && mask.is_file() {
            c.arg("--mask").arg(&mask);
        }
        if streamed {
            c.args(["--max-memory", &a.max_memory]);
        }
        c
    };
    let (mut mem_t, mut mem_m, mut str_t, mut str_m) = (vec![], vec![], vec![], vec![]);
    for _ in 0..a.repeat.max(1) {
        let (t, m) = run_measured(&mut command(false))?;
        mem_t.push(t);
        mem_m.push(m as f64);
        let (t, m) = run_measured(&mut command(true))?;
        str_t.push(t);
        str_m.push(m as f64);
    }
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("report.json"))?)?;
    let _ = std::fs::remove_dir_all(&out);
    let (mt, st) = (median(mem_t), median(str_t));
    let (mm, sm) = (median(mem_m), median(str_m));
    say!(
        "{}",
        serde_json::to_string_pretty(&json!({
            "dir": a.dir,
            "images": images.len(),
            "threads": rayon::current_num_threads(),
            "integrate": integrate,
            "mask": !a.no_mask && mask.is_file(),
            "max_memory_bytes": budget,
            "plan": report["streaming"],
            "in_memory": {"wall_s": mt, "peak_rss_bytes": mm},
            "streamed": {"wall_s": st, "peak_rss_bytes": sm},
            "time_ratio_streamed_over_in_memory": st / mt,
            "peak_under_budget": sm <= budget as f64,
        }))?
    );
    Ok(())
}

/// Least-squares slope and intercept of y against x.
fn fit_line(x: &[f64], y: &[f64]) -> (f64, f64) {
    let n = x.len() as f64;
    let (mx, my) = (x.iter().sum::<f64>() / n, y.iter().sum::<f64>() / n);
    let sxy: f64 = x.iter().zip(y).map(|(a, b)| (a - mx) * (b - my)).sum();
    let sxx: f64 = x.iter().map(|a| (a - mx).powi(2)).sum();
    let slope = sxy / sxx;
    (slope, my - slope * mx)
}

/// `bench scaling`: per estimator, the solve time on a Lambertian sphere (noise σ = 0.005,
/// attached shadows) for every size × light count, and the slope of log time against
/// log(pixels × lights) fitted over them: 1 means cost linear in the samples.
pub fn scaling(a: &crate::args::ScalingBenchArgs) -> Result<serde_json::Value> {
    use crate::args::MethodArg;
    use photostereo::capture::lights::Lights;
    use photostereo::capture::stack::ColorMode;
    use photostereo::ps::solve::{SolveOptions, solve};
    use photostereo::synth::render::{RenderOptions, render};
    let methods: Vec<MethodArg> = if a.methods.is_empty() {
        vec![
            MethodArg::Ls,
            MethodArg::Threshold,
            MethodArg::Auto,
            MethodArg::Trim,
            MethodArg::Huber,
        ]
    } else {
        a.methods.clone()
    };
    anyhow::ensure!(
        a.sizes.iter().all(|s| *s >= 16),
        "--sizes: each at least 16"
    );
    anyhow::ensure!(
        a.lights.iter().all(|l| *l >= 3),
        "--lights: each at least 3"
    );
    let mut rows = Vec::new();
    for &size in &a.sizes {
        for &count in &a.lights {
            let lights = Lights::fibonacci(count, 30.0)?;
            let scene = Scene::sphere(size, 0.45 * size as f64, Albedo::Constant(0.6));
            let options = RenderOptions {
                noise_sigma: 0.005,
                seed: 1,
                ..RenderOptions::default()
            };
            let rendering = render(&scene, &lights, &options)?;
            let stack = rendering.to_stack(&lights, ColorMode::Grey)?;
            let mask = rendering.truth.mask.clone();
            let samples = (mask.count() * count) as f64;
            for m in &methods {
                let o = SolveOptions::with_method(m.method());
                let mut times = Vec::new();
                for _ in 0..a.repeat.max(1) {
                    let t = Instant::now();
                    std::hint::black_box(solve(&stack, 0, &lights, &mask, &o, &Silent)?);
                    times.push(t.elapsed().as_secs_f64());
                }
                let t = median(times);
                rows.push(json!({
                    "method": m.method().name(),
                    "size": size,
                    "pixels": mask.count(),
                    "lights": count,
                    "samples": samples,
                    "solve_s": t,
                    "ns_per_sample": 1e9 * t / samples,
                }));
            }
        }
    }
    let mut slopes = Vec::new();
    let mut series = Vec::new();
    for (k, m) in methods.iter().enumerate() {
        let name = m.method().name();
        let pts: Vec<(f64, f64)> = rows
            .iter()
            .filter(|r| r["method"] == name)
            .filter_map(|r| Some((r["samples"].as_f64()?.ln(), r["solve_s"].as_f64()?.ln())))
            .collect();
        let (x, y): (Vec<f64>, Vec<f64>) = pts.into_iter().unzip();
        let (slope, intercept) = fit_line(&x, &y);
        // At each light count, the slope against pixels alone.
        let per_lights: Vec<serde_json::Value> = a
            .lights
            .iter()
            .map(|&l| {
                let (x, y): (Vec<f64>, Vec<f64>) = rows
                    .iter()
                    .filter(|r| r["method"] == name && r["lights"] == l)
                    .filter_map(|r| Some((r["pixels"].as_f64()?.ln(), r["solve_s"].as_f64()?.ln())))
                    .unzip();
                json!({"lights": l, "loglog_slope_vs_pixels": fit_line(&x, &y).0})
            })
            .collect();
        slopes.push(json!({"method": name, "loglog_slope_vs_samples": slope,
            "per_light_count": per_lights}));
        // Measurements as markers, the fitted power law as a line of the same colour.
        let points: Vec<(f64, f64)> = x.iter().zip(&y).map(|(a, b)| (a.exp(), b.exp())).collect();
        series.push(
            crate::chart::Series::line(format!("{name} (slope {slope:.2})"), points, k)
                .styled(crate::chart::Style::Markers),
        );
        series.push(power_law_fit(&x, slope, intercept, k));
    }
    if let Some(stem) = &a.chart {
        crate::chart::write(
            &crate::chart::Chart {
                title: format!(
                    "Solve time against samples ({} threads; sizes {:?}, lights {:?})",
                    rayon::current_num_threads(),
                    a.sizes,
                    a.lights
                ),
                x_label: "samples = pixels in mask × lights".into(),
                y_label: "solve time (s)".into(),
                log: (true, true),
                series: std::mem::take(&mut series),
                legend: crate::chart::Legend::UpperLeft,
            },
            stem,
        )?;
    }
    if let Some(path) = &a.csv {
        crate::sweep::write_csv(
            path,
            &rows,
            &[
                "method",
                "size",
                "pixels",
                "lights",
                "samples",
                "solve_s",
                "ns_per_sample",
            ],
        )?;
    }
    Ok(json!({
        "threads": rayon::current_num_threads(),
        "repeat": a.repeat.max(1),
        "slopes": slopes,
        "rows": rows,
    }))
}
