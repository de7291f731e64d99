//! `photostereo bench diligent | integration | specularity | stream | scaling`: flags into the
//! options of [`photostereo::eval::bench`], its measurements, and their formatting (JSON, CSV,
//! Markdown, charts). What runs as a child process stays here: the command line itself (whole-
//! process timing, peak memory) and the numpy peer.

use crate::args::{
    BenchArgs, IntegrateArg, IntegrationBenchArgs, InterreflectionBenchArgs, MethodArg, PeerArgs,
    ScalingBenchArgs, SpecularityBenchArgs, StreamBenchArgs,
};
use crate::chart::{Chart, Legend, Series, Style};
use anyhow::{Context, Result};
use clap::ValueEnum;
use photostereo::eval::bench::PowerLaw;
use photostereo::eval::bench::integration::{
    self, IntegrationBenchOptions, IntegratorRow, PeerPoissonRow, integrator_rows,
    time_poisson_on_peaks,
};
use photostereo::eval::bench::interreflections::{
    InterreflectionBenchOptions, InterreflectionReport, interreflections as run_interreflections,
};
use photostereo::eval::bench::scaling::{self, ScalingOptions, ScalingReport};
use photostereo::eval::bench::specularity::{SpecularityOptions, specularity as run_specularity};
use photostereo::eval::bench::stages::{PeerRun, ProcessComparison, Speedups, measure_stages};
use photostereo::eval::bench::stream::{Measurement, StreamBenchPlan, StreamRun};
use photostereo::integrate::Integrator;
use photostereo::run::pipeline::Config;
use serde_json::{Value, json};
use std::fmt::Write as _;
use std::path::Path;
use std::process::Command;
use std::time::Instant;

/// `bench diligent`: end-to-end timing on a DiLiGenT folder beside the numpy peer.
pub fn run(a: &BenchArgs) -> Result<Value> {
    diligent(&a.dir, &a.method.config()?, a.repeat, &a.peer)
}

/// Times `dir` with `config`, `repeat` times: in-process stage times, then whole processes —
/// ours and, when its script exists, the peer's, alternating so that machine load hits both
/// alike — and the peer's time over ours per stage (load, solve) and per process; as JSON.
pub fn diligent(dir: &Path, config: &Config, repeat: usize, peer: &PeerArgs) -> Result<Value> {
    let repeat = repeat.max(1);
    let tmp = std::env::temp_dir().join(format!("photostereo-bench-{}", std::process::id()));
    let stages = measure_stages(dir, config, repeat, &tmp)?;
    let method = config.solve.method.name();
    let integrate = config.integration.map_or("none", |o| o.method.name());
    let mut out = json!({
        "dataset": dir,
        "repeat": repeat,
        "threads": rayon::current_num_threads(),
        "method": method,
        "integrator": integrate,
        "photostereo": stages,
    });
    // Whole-process timings, ours and the peer's, interleaved.
    let exe = std::env::current_exe().context("locating the photostereo executable")?;
    let has_peer = peer.script.is_file();
    let mut ours_wall = Vec::new();
    let mut peer_runs = Vec::new();
    for _ in 0..repeat {
        let t = Instant::now();
        let o = Command::new(&exe)
            .arg(dir)
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
        if has_peer {
            let t = Instant::now();
            let o = Command::new(&peer.python)
                .arg(&peer.script)
                .arg("diligent")
                .arg(dir)
                .output()
                .with_context(|| format!("running {} {}", peer.python, peer.script.display()))?;
            let wall_s = t.elapsed().as_secs_f64();
            anyhow::ensure!(
                o.status.success(),
                "peer failed: {}",
                String::from_utf8_lossy(&o.stderr)
            );
            let v: Value = serde_json::from_slice(&o.stdout)?;
            peer_runs.push(PeerRun {
                wall_s,
                load_s: v["load_s"].as_f64().unwrap_or(f64::NAN),
                solve_s: v["solve_s"].as_f64().unwrap_or(f64::NAN),
            });
        }
    }
    let _ = std::fs::remove_dir_all(&tmp);
    let processes = ProcessComparison::from_runs(ours_wall, &peer_runs);
    out["photostereo"]["process_wall_s"] = json!(processes.ours_wall_s);
    match &processes.peer {
        Some(p) => {
            let mut peer_json = json!(p);
            peer_json["script"] = json!(peer.script);
            peer_json["method"] = json!(photostereo::eval::bench::stages::PEER_METHOD.name());
            out["peer"] = peer_json;
            // Peer time over ours: above 1, photostereo is faster. The solve ratio compares
            // like with like only for --method ls (the peer's method).
            let s = Speedups::new(&stages, processes.ours_wall_s, p);
            out["speedup_per_stage"] = json!({
                "load": s.load,
                "solve": s.solve,
                "load_plus_solve": s.load_plus_solve,
                "solve_methods": format!("{method} vs ls"),
            });
            out["speedup_process_vs_process"] = json!(s.process_vs_process);
            out["speedup_vs_peer_load_plus_solve"] = json!(s.vs_peer_load_plus_solve);
        }
        None => out["peer"] = json!(format!("not found: {}", peer.script.display())),
    }
    Ok(out)
}

/// `bench integration`: [`integration_report`] of the options `a` describes.
pub fn integration(a: &IntegrationBenchArgs) -> Result<Value> {
    let options = IntegrationBenchOptions {
        sizes: a.sizes.clone(),
        methods: if a.methods.is_empty() {
            Integrator::ALL.to_vec()
        } else {
            a.methods
                .iter()
                .filter_map(|m| IntegrateArg::method(*m))
                .collect()
        },
        repeat: a.repeat,
    };
    integration_report(&options, &a.peer, a.csv.as_deref(), a.chart.as_deref())
}

/// Time and accuracy of each integrator on the sphere per size, and DCT Poisson beside
/// `numpy_ps.py poisson N` on the peer's own field when its script exists; JSON with the
/// Markdown table under `table`, the rows as CSV at `csv` and the chart at `chart` (stem).
pub fn integration_report(
    options: &IntegrationBenchOptions,
    peer: &PeerArgs,
    csv: Option<&Path>,
    chart: Option<&Path>,
) -> Result<Value> {
    let rows = integrator_rows(options)?;
    // DCT Poisson against the peer on its own test field.
    let mut peer_rows = Vec::new();
    if peer.script.is_file() {
        for &n in &options.sizes {
            let ours = time_poisson_on_peaks(n, options.repeat)?;
            let mut theirs = Vec::new();
            for _ in 0..options.repeat.max(1) {
                let o = Command::new(&peer.python)
                    .arg(&peer.script)
                    .arg("poisson")
                    .arg(n.to_string())
                    .output()?;
                anyhow::ensure!(
                    o.status.success(),
                    "peer failed: {}",
                    String::from_utf8_lossy(&o.stderr)
                );
                let v: Value = serde_json::from_slice(&o.stdout)?;
                theirs.push(v["solve_s"].as_f64().unwrap_or(f64::NAN));
            }
            peer_rows.push(PeerPoissonRow::new(n, ours, theirs));
        }
    }
    let slopes = integration::slopes(&rows, &options.methods);
    if let Some(stem) = chart {
        power_law_chart(
            slopes
                .iter()
                .map(|s| (s.method, s.points.as_slice(), s.fit)),
            format!(
                "Integration time vs pixels (sphere, disk mask, {} threads)",
                rayon::current_num_threads()
            ),
            "pixels in mask",
            "integration time (s)",
            stem,
        )?;
    }
    let rows_json: Vec<Value> = rows.iter().map(|r| json!(r)).collect();
    if let Some(path) = csv {
        crate::sweep::write_csv(
            path,
            &rows_json,
            &["method", "size", "pixels", "time_s", "rmse_over_range"],
        )?;
    }
    Ok(json!({
        "threads": rayon::current_num_threads(),
        "integrators": rows_json,
        "slopes": slopes,
        "poisson_vs_numpy": peer_rows,
        "table": integration_table(&rows),
    }))
}

/// The integrator rows as a Markdown table.
fn integration_table(rows: &[IntegratorRow]) -> String {
    let mut table = String::from(
        "| method | pixels | time (s) | depth RMSE / range |\n| --- | --- | --- | --- |\n",
    );
    for r in rows {
        let _ = writeln!(
            table,
            "| {} | {}² ({} in mask) | {:.3} | {:.2}% |",
            r.method,
            r.size,
            r.pixels,
            r.time_s,
            100.0 * r.rmse_over_range
        );
    }
    table
}

/// A log-log chart of measured points per named series, each with its fitted power law.
fn power_law_chart<'a>(
    fits: impl Iterator<Item = (&'a str, &'a [(f64, f64)], PowerLaw)>,
    title: String,
    x_label: &str,
    y_label: &str,
    stem: &Path,
) -> Result<()> {
    let series = fits
        .enumerate()
        .flat_map(|(k, (name, points, fit))| fitted_series(name, points, fit, k))
        .collect();
    crate::chart::write(
        &Chart {
            title,
            x_label: x_label.into(),
            y_label: y_label.into(),
            log: (true, true),
            series,
            legend: Legend::UpperLeft,
        },
        stem,
    )
}

/// The measurements `points` of `name` as markers, with the slope of `fit` in the legend, and
/// the fitted power law as a line of the same palette colour `color` over their span.
fn fitted_series(name: &str, points: &[(f64, f64)], fit: PowerLaw, color: usize) -> [Series; 2] {
    let (lo, hi) = points
        .iter()
        .map(|p| p.0.ln())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
            (a.min(v), b.max(v))
        });
    let line = [lo, hi]
        .iter()
        .map(|v| (v.exp(), (fit.intercept + fit.slope * v).exp()))
        .collect();
    [
        Series::line(
            format!("{name} (slope {:.2})", fit.slope),
            points.to_vec(),
            color,
        )
        .styled(Style::Markers),
        Series::line("", line, color).styled(Style::Fit),
    ]
}

/// `bench specularity`: mean angular error of each estimator against the specular strength;
/// JSON rows to standard output, and a Markdown table of the mean errors to standard error
/// with `--markdown`.
pub fn specularity(a: SpecularityBenchArgs) -> Result<()> {
    // Without --methods, every estimator in the order `--help` lists them.
    let methods: Vec<MethodArg> = if a.methods.is_empty() {
        MethodArg::value_variants().to_vec()
    } else {
        a.methods.clone()
    };
    let report = run_specularity(&SpecularityOptions {
        size: a.size,
        lights: a.lights,
        ks: a.ks.clone(),
        noise: a.noise,
        highlight_fraction: a.highlight_fraction,
        methods: methods.iter().map(|m| m.method()).collect(),
    })?;
    let value = json!(report);
    if a.markdown {
        let names: Vec<&str> = methods.iter().map(|m| m.method().name()).collect();
        eprintln!("| lobe | k_s | {} |", names.join(" | "));
        eprintln!("|---|---|{}", "---:|".repeat(names.len()));
        let rows = value["rows"].as_array().cloned().unwrap_or_default();
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
    say!("{}", serde_json::to_string_pretty(&value)?);
    Ok(())
}

/// `bench interreflections`: each concave scene's normal error without and with
/// compensation; JSON to standard output, a Markdown table to standard error with
/// `--markdown`, and the JSON and a chart in `--out`.
pub fn interreflections(a: InterreflectionBenchArgs) -> Result<()> {
    let report = run_interreflections(&InterreflectionBenchOptions {
        size: a.size,
        lights: a.lights,
        albedo: a.albedo,
    })?;
    if a.markdown {
        eprint!("{}", interreflection_table(&report));
    }
    let text = serde_json::to_string_pretty(&report)?;
    if let Some(dir) = &a.out {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        crate::write_file_atomic(&dir.join("interreflections.json"), text.as_bytes())?;
        interreflection_chart(&report, &dir.join("interreflections"))?;
    }
    say!("{text}");
    Ok(())
}

/// `bench near`: both models' errors against the LEDs' distance.
pub fn near(a: crate::args::NearBenchArgs) -> Result<()> {
    let report = photostereo::eval::near::sweep(&photostereo::eval::near::NearSweepOptions {
        size: a.size,
        lights: a.lights,
        noise: a.noise,
        mu: a.mu,
        distances: a.distances.clone(),
    })?;
    if a.markdown {
        eprint!("{}", near_table(&report));
    }
    let text = serde_json::to_string_pretty(&report)?;
    if let Some(dir) = &a.out {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        crate::write_file_atomic(&dir.join("near.json"), text.as_bytes())?;
        near_chart(&report, &dir.join("near"))?;
    }
    say!("{text}");
    Ok(())
}

/// `bench from-object`: lights recovered from the object against light count and noise.
pub fn from_object(a: crate::args::FromObjectBenchArgs) -> Result<()> {
    use photostereo::eval::from_object::{FromObjectSweepOptions, SWEEP_SCENES, sweep};
    let report = sweep(&FromObjectSweepOptions {
        size: a.size,
        counts: a.counts.clone(),
        noises: a.noises.clone(),
    })?;
    if a.markdown {
        let mut s = String::from(
            "| scene | lights | noise | lights: mean (°) | lights: max (°) | normals (°) | normals, true lights (°) | halves' spread (°) | time (s) |\n\
             |---|---:|---:|---:|---:|---:|---:|---:|---:|\n",
        );
        let f = |v: Option<f64>| v.map_or_else(|| "refused".to_string(), |v| format!("{v:.2}"));
        for r in &report.rows {
            let _ = writeln!(
                s,
                "| {} | {} | {} | {} | {} | {} | {:.2} | {} | {:.2} |",
                r.scene,
                r.lights,
                r.noise,
                f(r.light_deg),
                f(r.light_max_deg),
                match (r.light_deg, r.normals_deg) {
                    (Some(_), None) => "pipeline failed".to_string(),
                    _ => f(r.normals_deg),
                },
                r.calibrated_deg,
                f(r.reported_deg),
                r.seconds
            );
        }
        eprint!("{s}");
    }
    let text = serde_json::to_string_pretty(&report)?;
    if let Some(dir) = &a.out {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        crate::write_file_atomic(&dir.join("from_object.json"), text.as_bytes())?;
        let mut series = Vec::new();
        for (k, scene) in SWEEP_SCENES.iter().enumerate() {
            for (j, &noise) in a.noises.iter().enumerate() {
                let points: Vec<(f64, f64)> = report
                    .rows
                    .iter()
                    .filter(|r| r.scene == scene.name() && r.noise == noise)
                    .filter_map(|r| r.light_deg.map(|e| (r.lights as f64, e)))
                    .collect();
                let s = Series::line(format!("{} noise {}", scene.name(), noise), points, j);
                series.push(if k == 0 {
                    s
                } else {
                    s.styled(crate::chart::Style::Markers)
                });
            }
        }
        crate::chart::write(
            &Chart {
                title: format!(
                    "Lights from the object: light error against light count ({}², two albedos)",
                    a.size
                ),
                x_label: "lights".into(),
                y_label: "mean light direction error (°)".into(),
                log: (true, true),
                series,
                legend: Legend::UpperRight,
            },
            &dir.join("from_object"),
        )?;
    }
    say!("{text}");
    Ok(())
}

/// `bench sfs`: every shape-from-shading method on rendered shapes, error against time.
pub fn sfs(a: crate::args::SfsBenchArgs) -> Result<()> {
    use photostereo::eval::sfs::{SfsSweepOptions, sweep};
    let defaults = SfsSweepOptions::default();
    let report = sweep(&SfsSweepOptions {
        size: a.size,
        slants: a.slants.clone(),
        azimuths: a.azimuths.clone(),
        methods: if a.methods.is_empty() {
            defaults.methods
        } else {
            a.methods.iter().map(|&m| m.into()).collect()
        },
    })?;
    if a.markdown {
        eprint!("{}", sfs_table(&report));
    }
    let text = serde_json::to_string_pretty(&report)?;
    if let Some(dir) = &a.out {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        crate::write_file_atomic(&dir.join("sfs.json"), text.as_bytes())?;
        sfs_chart(&report, &dir.join("sfs"))?;
    }
    say!("{text}");
    Ok(())
}

/// The rows of a shape-from-shading sweep as a Markdown table.
pub(crate) fn sfs_table(report: &photostereo::eval::sfs::SfsSweepReport) -> String {
    let mut s = String::from(
        "| scene | light | method | normals, mean (°) | depth RMSE / range | absolute | iterations (+ refinement steps) | time (s) |\n\
         |---|---|---|---:|---:|---:|---:|---:|\n",
    );
    for r in &report.rows {
        let light = sfs_light(r, &report.options.azimuths);
        match (&r.refused, r.normals_deg, r.depth) {
            (Some(_), _, _) => {
                let _ = writeln!(
                    s,
                    "| {} | {light} | {} | not applicable | | | | |",
                    r.scene,
                    r.label()
                );
            }
            (None, Some(n), Some(d)) => {
                let _ = writeln!(
                    s,
                    "| {} | {light} | {} | {n:.2} | {:.2}% | {} | {}{}{} | {:.2} |",
                    r.scene,
                    r.label(),
                    100.0 * d,
                    r.depth_absolute
                        .map_or_else(String::new, |v| format!("{:.2}%", 100.0 * v)),
                    r.iterations,
                    match (r.refined, r.refined_coarse) {
                        (Some(k), 0) => format!(" + {k}"),
                        (Some(k), c) => format!(" + {k} (after {c} at lower resolutions)"),
                        (None, 0) => String::new(),
                        (None, c) => format!(" (after {c} at lower resolutions)"),
                    },
                    if r.discarded {
                        " (refinement discarded)"
                    } else if r.converged {
                        ""
                    } else {
                        " (not converged)"
                    },
                    r.seconds
                );
            }
            _ => {}
        }
    }
    s
}

/// A row's light in words: "frontal", "30° oblique" (a sweep at the default azimuth), or "30°
/// oblique at 120°" (a sweep over `azimuths` other than the default).
fn sfs_light(r: &photostereo::eval::sfs::SfsRow, azimuths: &[f64]) -> String {
    if r.slant_deg == 0.0 {
        "frontal".to_string()
    } else if azimuths == photostereo::eval::sfs::DEFAULT_AZIMUTHS {
        format!("{}° oblique", r.slant_deg)
    } else {
        format!("{}° oblique at {}°", r.slant_deg, r.azimuth_deg)
    }
}

/// The chart of a shape-from-shading sweep (`STEM.svg/.png`): each method's normal error
/// against its solve time, one series per method and light.
pub(crate) fn sfs_chart(
    report: &photostereo::eval::sfs::SfsSweepReport,
    stem: &std::path::Path,
) -> Result<()> {
    let mut series = Vec::new();
    let mut labels: Vec<String> = Vec::new();
    let mut lights: Vec<String> = Vec::new();
    for r in &report.rows {
        if !labels.contains(&r.label()) {
            labels.push(r.label());
        }
        let light = sfs_light(r, &report.options.azimuths);
        if !lights.contains(&light) {
            lights.push(light);
        }
    }
    for (k, label) in labels.iter().enumerate() {
        for (j, light) in lights.iter().enumerate() {
            let points: Vec<(f64, f64)> = report
                .rows
                .iter()
                .filter(|r| r.label() == *label && sfs_light(r, &report.options.azimuths) == *light)
                .filter_map(|r| r.normals_deg.map(|e| (r.seconds.max(1e-3), e)))
                .collect();
            if points.is_empty() {
                continue;
            }
            let name = format!("{label}, {light}");
            series.push(
                Series::line(name, points, k * lights.len() + j)
                    .styled(crate::chart::Style::Markers),
            );
        }
    }
    crate::chart::write(
        &Chart {
            title: format!(
                "Shape from shading: normal error against solve time ({}², five shapes)",
                report.options.size
            ),
            x_label: "solve time (s)".into(),
            y_label: "mean normal error (°)".into(),
            log: (true, true),
            series,
            legend: Legend::UpperRight,
        },
        stem,
    )?;
    Ok(())
}

/// The rows of a near-light sweep as a Markdown table.
pub(crate) fn near_table(report: &photostereo::eval::near::NearReport) -> String {
    let mut s = String::from(
        "| scene | LEDs at (object sizes) | near: normals (°) | near: depth (% of range) | distant: normals (°) | distant: depth (% of range, scale fitted) | alternations | near (s) | distant (s) |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|---:|\n",
    );
    for r in &report.rows {
        let x = &r.result;
        let _ = writeln!(
            s,
            "| {} | {} | {:.3} | {:.3} | {:.2} | {:.2} | {} | {:.2} | {:.2} |",
            r.scene,
            r.distance,
            x.near_normal_deg,
            100.0 * x.near_depth,
            x.distant_normal_deg,
            100.0 * x.distant_depth,
            x.iterations,
            x.near_seconds,
            x.distant_seconds
        );
    }
    s
}

/// The near-light charts: mean normal error (`STEM.svg/.png`) and RMS depth error
/// (`STEM_depth.svg/.png`) against the LEDs' distance (log-log), near and distant per scene.
pub(crate) fn near_chart(report: &photostereo::eval::near::NearReport, stem: &Path) -> Result<()> {
    type Pick = fn(&photostereo::eval::near::NearResult) -> (f64, f64);
    let charts: [(&str, &str, Pick); 2] = [
        ("", "mean angular error (°)", |r| {
            (r.near_normal_deg, r.distant_normal_deg)
        }),
        (
            "_depth",
            "RMS depth error (% of the depth range; distant: scale fitted)",
            |r| (100.0 * r.near_depth, 100.0 * r.distant_depth),
        ),
    ];
    for (suffix, y_label, pick) in charts {
        let mut series = Vec::new();
        for (k, scene) in photostereo::eval::near::SWEEP_SCENES.iter().enumerate() {
            let rows: Vec<_> = report
                .rows
                .iter()
                .filter(|r| r.scene == scene.name())
                .collect();
            series.push(Series::line(
                format!("{} near", scene.name()),
                rows.iter()
                    .map(|r| (r.distance, pick(&r.result).0))
                    .collect(),
                k,
            ));
            series.push(
                Series::line(
                    format!("{} distant", scene.name()),
                    rows.iter()
                        .map(|r| (r.distance, pick(&r.result).1))
                        .collect(),
                    k,
                )
                .styled(crate::chart::Style::Fit),
            );
        }
        let mut path = stem.as_os_str().to_owned();
        path.push(suffix);
        crate::chart::write(
            &Chart {
                title: format!(
                    "Near lights: {} against LED distance ({}², {} LEDs, cos^{} profile, noise {})",
                    if suffix.is_empty() {
                        "normal error"
                    } else {
                        "depth error"
                    },
                    report.options.size,
                    report.options.lights,
                    report.options.mu,
                    report.options.noise
                ),
                x_label: "LED distance from the object (object sizes)".into(),
                y_label: y_label.into(),
                log: (true, true),
                series,
                legend: Legend::UpperRight,
            },
            Path::new(&path),
        )?;
    }
    Ok(())
}

/// The rows of `report` as a Markdown table.
pub(crate) fn interreflection_table(report: &InterreflectionReport) -> String {
    let mut s = String::from(
        "| scene | step | mean (°) | median (°) | p95 (°) | reflectance used | occlusion | time (s) |\n\
         |---|---|---:|---:|---:|---:|---:|---:|\n",
    );
    for r in &report.rows {
        let _ = writeln!(
            s,
            "| {} | {} | {:.2} | {:.2} | {:.2} | {:.2} | {:.3} | {:.2} |",
            r.scene,
            r.step,
            r.mean_deg,
            r.median_deg,
            r.p95_deg,
            r.reflectance,
            r.occlusion,
            r.seconds
        );
    }
    s
}

/// Mean angular error per scene (x: the scenes in order), one line per step.
pub(crate) fn interreflection_chart(report: &InterreflectionReport, stem: &Path) -> Result<()> {
    let mut steps: Vec<&str> = Vec::new();
    let mut scenes: Vec<&str> = Vec::new();
    for r in &report.rows {
        if !steps.contains(&r.step) {
            steps.push(r.step);
        }
        if !scenes.contains(&r.scene) {
            scenes.push(r.scene);
        }
    }
    let series = steps
        .iter()
        .enumerate()
        .map(|(k, step)| {
            let rows: Vec<_> = report.rows.iter().filter(|r| r.step == *step).collect();
            let points = rows
                .iter()
                .map(|r| {
                    let x = scenes.iter().position(|s| *s == r.scene).unwrap_or(0);
                    (x as f64, r.mean_deg)
                })
                .collect();
            Series::line(*step, points, k).labelled(
                rows.iter()
                    .map(|r| {
                        if k == 0 {
                            r.scene.to_string()
                        } else {
                            String::new()
                        }
                    })
                    .collect(),
            )
        })
        .collect();
    crate::chart::write(
        &Chart {
            title: format!(
                "Interreflections: mean normal error ({}², {} lights, albedo {})",
                report.size, report.lights, report.albedo
            ),
            x_label: format!("scene ({})", scenes.join(", ")),
            y_label: "mean angular error (°)".into(),
            log: (false, false),
            series,
            legend: Legend::UpperRight,
        },
        stem,
    )
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

/// `bench stream`: the runs of the library's [`StreamBenchPlan`] as child processes of this
/// program (the in-memory run, and the streamed one within `--max-memory`), measured from
/// outside; medians of wall time and peak resident memory, and their ratios, as JSON.
pub fn stream(a: StreamBenchArgs) -> Result<()> {
    let budget = photostereo::run::stream::parse_size(&a.max_memory)?;
    let plan = StreamBenchPlan::new(&a.dir, budget, !a.no_mask, a.integrate.method(), a.repeat)?;
    let exe = std::env::current_exe().context("locating the photostereo executable")?;
    let out = std::env::temp_dir().join(format!("photostereo-bench-stream-{}", std::process::id()));
    let command = |run: StreamRun| {
        let mut c = Command::new(&exe);
        c.args(&plan.images)
            .arg("--lights")
            .arg(&plan.lights)
            .args(["--integrate", plan.integrate_name(), "-q", "--force", "-o"])
            .arg(&out);
        if let Some(mask) = &plan.mask {
            c.arg("--mask").arg(mask);
        }
        if run == StreamRun::Streamed {
            c.args(["--max-memory", &a.max_memory]);
        }
        c
    };
    let mut measurements = Vec::new();
    for run in plan.runs() {
        let (wall_s, peak_rss_bytes) = run_measured(&mut command(run))?;
        measurements.push(Measurement {
            run,
            wall_s,
            peak_rss_bytes,
        });
    }
    let report: Value = serde_json::from_slice(&std::fs::read(out.join("report.json"))?)?;
    let _ = std::fs::remove_dir_all(&out);
    let result = plan.report(&measurements, report["streaming"].clone());
    say!("{}", serde_json::to_string_pretty(&json!(result))?);
    Ok(())
}

/// `bench scaling`: [`scaling_report`] of the options `a` describes.
pub fn scaling(a: &ScalingBenchArgs) -> Result<Value> {
    let options = ScalingOptions {
        sizes: a.sizes.clone(),
        lights: a.lights.clone(),
        methods: if a.methods.is_empty() {
            scaling::DEFAULT_METHODS.to_vec()
        } else {
            a.methods.iter().map(|m| m.method()).collect()
        },
        repeat: a.repeat,
    };
    scaling_report(&options, a.csv.as_deref(), a.chart.as_deref())
}

/// The library's [`scaling::scaling`] as JSON, with the rows as CSV at `csv` and the chart of
/// time against samples at `chart` (stem).
pub fn scaling_report(
    options: &ScalingOptions,
    csv: Option<&Path>,
    chart: Option<&Path>,
) -> Result<Value> {
    let report = scaling::scaling(options)?;
    if let Some(stem) = chart {
        scaling_chart(&report, options, stem)?;
    }
    let value = json!(report);
    if let Some(path) = csv {
        crate::sweep::write_csv(
            path,
            value["rows"].as_array().map_or(&[][..], Vec::as_slice),
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
    Ok(value)
}

/// Solve time against samples per estimator (log-log), the fitted power laws beside.
fn scaling_chart(report: &ScalingReport, options: &ScalingOptions, stem: &Path) -> Result<()> {
    power_law_chart(
        report
            .slopes
            .iter()
            .map(|s| (s.method, s.points.as_slice(), s.fit)),
        format!(
            "Solve time against samples ({} threads; sizes {:?}, lights {:?})",
            rayon::current_num_threads(),
            options.sizes,
            options.lights
        ),
        "samples = pixels in mask × lights",
        "solve time (s)",
        stem,
    )
}
