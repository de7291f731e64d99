//! `photostereo bench sweep`: the speed–accuracy sweeps of [`photostereo::eval::sweep`], written as
//! CSV and JSON tables and drawn as charts (error against noise, lights and specularity; the
//! Pareto fronts of error against time; shape from shading beside photometric stereo; depth
//! error against normal noise per integrator).

use crate::args::SweepBenchArgs;
use crate::chart::{Chart, Legend, Series, Style, write};
use anyhow::Result;
use photostereo::eval::sweep::{
    Axis, DEPTH_PARETO_NOISE, DepthRow, GLOSSY_KS, NormalRow, SweepOptions, depth_sweep,
    normal_sweep, pareto_front, sfs_sweep,
};
use photostereo::progress::Progress;
use serde_json::{Value, json};
use std::path::Path;

/// Writes `rows` as CSV with `columns` to `path`, atomically.
pub fn write_csv(path: &Path, rows: &[Value], columns: &[&str]) -> Result<()> {
    crate::write_file_atomic(path, csv(rows, columns).as_bytes())
}

/// `rows` as CSV with `columns` (JSON strings unquoted, null as empty).
fn csv(rows: &[Value], columns: &[&str]) -> String {
    let mut out = columns.join(",") + "\n";
    for r in rows {
        let cells: Vec<String> = columns
            .iter()
            .map(|c| match &r[*c] {
                // RFC 4180: a field holding a comma, quote or line break is quoted.
                Value::String(s) if s.contains([',', '"', '\n']) => {
                    format!("\"{}\"", s.replace('"', "\"\""))
                }
                Value::String(s) => s.clone(),
                Value::Null => String::new(),
                Value::Number(n) => match n.as_f64() {
                    Some(v) if n.is_f64() => format!("{v:.6}"),
                    _ => n.to_string(),
                },
                v => v.to_string(),
            })
            .collect();
        out += &cells.join(",");
        out += "\n";
    }
    out
}

/// Distinct values in first-seen order.
fn distinct<T: PartialEq + Clone>(items: impl Iterator<Item = T>) -> Vec<T> {
    let mut out: Vec<T> = Vec::new();
    for i in items {
        if !out.contains(&i) {
            out.push(i);
        }
    }
    out
}

/// One line per method of `rows` on `axis`: (x(row), mean error).
fn per_method(rows: &[NormalRow], axis: Axis, x: impl Fn(&NormalRow) -> f64) -> Vec<Series> {
    let picked: Vec<&NormalRow> = rows.iter().filter(|r| r.axis == axis).collect();
    distinct(picked.iter().map(|r| r.method.clone()))
        .into_iter()
        .enumerate()
        .map(|(k, m)| {
            let pts = picked
                .iter()
                .filter(|r| r.method == m)
                .map(|r| (x(r), r.mean_deg))
                .collect();
            Series::line(m, pts, k)
        })
        .collect()
}

fn chart(
    title: String,
    x_label: &str,
    y_label: &str,
    log: (bool, bool),
    series: Vec<Series>,
    legend: Legend,
) -> Chart {
    Chart {
        title,
        x_label: x_label.into(),
        y_label: y_label.into(),
        log,
        series,
        legend,
    }
}

/// The normal charts: error against noise, lights (with coverage) and specularity, and the
/// Pareto front of error against time over the light counts.
fn normal_charts(rows: &[NormalRow], o: &SweepOptions, out: &Path) -> Result<()> {
    let scene = format!("sphere on ground {0}²", o.size);
    write(
        &chart(
            format!("Normals vs image noise ({scene}, {} lights)", o.lights),
            "image noise σ (brightest pixel ≈ 0.7)",
            "mean angular error (°)",
            (false, true),
            per_method(rows, Axis::Noise, |r| f64::from(r.noise)),
            Legend::LowerRight,
        ),
        &out.join("normals_vs_noise"),
    )?;
    write(
        &chart(
            format!("Normals vs light count ({scene}, σ = {})", o.noise),
            "lights (images)",
            "mean angular error over solved pixels (°)",
            (true, true),
            per_method(rows, Axis::Lights, |r| r.images as f64),
            Legend::LowerLeft,
        ),
        &out.join("normals_vs_lights"),
    )?;
    let coverage = per_method(rows, Axis::Lights, |r| r.images as f64)
        .into_iter()
        .map(|mut s| {
            let m = s.name.clone();
            s.points = rows
                .iter()
                .filter(|r| r.axis == Axis::Lights && r.method == m)
                .map(|r| (r.images as f64, 100.0 * r.coverage))
                .collect();
            s
        })
        .collect();
    write(
        &chart(
            format!("Pixels solved vs light count ({scene}, σ = {})", o.noise),
            "lights (images)",
            "mask pixels with a normal (%)",
            (true, false),
            coverage,
            Legend::LowerRight,
        ),
        &out.join("coverage_vs_lights"),
    )?;
    write(
        &chart(
            format!(
                "Normals vs specularity (Blinn–Phong n = 50, {} lights, σ = {})",
                o.lights, o.noise
            ),
            "specular reflectance k_s (diffuse albedo 0.7)",
            "mean angular error (°)",
            (false, true),
            per_method(rows, Axis::Specularity, |r| r.ks),
            Legend::LowerRight,
        ),
        &out.join("normals_vs_specularity"),
    )?;
    // Pareto: every (method, light count) of the light sweep.
    let lights: Vec<&NormalRow> = rows.iter().filter(|r| r.axis == Axis::Lights).collect();
    let mut series: Vec<Series> = per_method(rows, Axis::Lights, |r| r.seconds)
        .into_iter()
        .map(|s| s.styled(Style::Line))
        .collect();
    let pts: Vec<(f64, f64)> = lights.iter().map(|r| (r.seconds, r.mean_deg)).collect();
    let front = pareto_front(&pts);
    series.push(
        Series::line("Pareto front", front.iter().map(|&i| pts[i]).collect(), 0)
            .styled(Style::Front)
            .labelled(
                front
                    .iter()
                    .map(|&i| format!("{} ×{}", lights[i].method, lights[i].images))
                    .collect(),
            ),
    );
    write(
        &chart(
            format!(
                "Normals: error vs time, {}–{} lights ({scene}, σ = {}, {} threads)",
                o.light_counts.iter().min().unwrap_or(&0),
                o.light_counts.iter().max().unwrap_or(&0),
                o.noise,
                rayon::current_num_threads()
            ),
            "solve + normals time (s)",
            "mean angular error over solved pixels (°)",
            (true, true),
            series,
            Legend::UpperRight,
        ),
        &out.join("normals_pareto"),
    )?;
    // Pareto at one specular strength: where rejecting highlights pays for its time.
    let glossy: Vec<&NormalRow> = rows
        .iter()
        .filter(|r| r.axis == Axis::Specularity && (r.ks - GLOSSY_KS).abs() < 1e-12)
        .collect();
    if !glossy.is_empty() {
        let pts: Vec<(f64, f64)> = glossy.iter().map(|r| (r.seconds, r.mean_deg)).collect();
        let front = pareto_front(&pts);
        let series = vec![
            Series::line("methods", pts.clone(), 0)
                .styled(Style::Markers)
                .labelled(glossy.iter().map(|r| r.method.clone()).collect()),
            Series::line("Pareto front", front.iter().map(|&i| pts[i]).collect(), 0)
                .styled(Style::Front),
        ];
        write(
            &chart(
                format!(
                    "Normals: error vs time, glossy (k_s = {GLOSSY_KS}, {} lights, σ = {}, {}²)",
                    o.lights, o.noise, o.size
                ),
                "solve + normals time (s)",
                "mean angular error (°)",
                (true, true),
                series,
                Legend::UpperRight,
            ),
            &out.join("normals_pareto_glossy"),
        )?;
    }
    Ok(())
}

/// Shape from shading beside photometric stereo on the sphere, against noise.
fn sfs_chart(rows: &[NormalRow], o: &SweepOptions, out: &Path) -> Result<()> {
    let keys = distinct(rows.iter().map(|r| {
        (
            r.method.clone(),
            r.light_slant_deg.map(|s| s as i64),
            r.images,
        )
    }));
    let series = keys
        .iter()
        .enumerate()
        .map(|(k, (m, slant, images))| {
            let name = match slant {
                Some(s) => format!("{m} (1 image, light {s}° off the view)"),
                None => format!("{m} ({images} images)"),
            };
            let pts = rows
                .iter()
                .filter(|r| {
                    &r.method == m
                        && r.light_slant_deg.map(|s| s as i64) == *slant
                        && r.images == *images
                })
                .map(|r| (f64::from(r.noise), r.mean_deg))
                .collect();
            Series::line(name, pts, k)
        })
        .collect();
    write(
        &chart(
            format!(
                "Shape from shading vs photometric stereo (sphere {0}², known albedo)",
                o.sfs_size
            ),
            "image noise σ (brightest pixel 0.8)",
            "mean angular error (°)",
            (false, true),
            series,
            Legend::LowerRight,
        ),
        &out.join("sfs_vs_noise"),
    )
}

/// Depth error against normal noise per integrator, one chart per scene; and error against
/// time at [`DEPTH_PARETO_NOISE`] on both scenes.
fn depth_charts(rows: &[DepthRow], o: &SweepOptions, out: &Path) -> Result<()> {
    let methods = distinct(rows.iter().map(|r| r.method));
    for scene in distinct(rows.iter().map(|r| r.scene)) {
        let series = methods
            .iter()
            .enumerate()
            .map(|(k, m)| {
                let pts = rows
                    .iter()
                    .filter(|r| r.scene == scene && r.method == *m)
                    .map(|r| (r.normal_error_deg, 100.0 * r.shape_rmse_over_range))
                    .collect();
                Series::line(*m, pts, k)
            })
            .collect();
        write(
            &chart(
                format!("Depth vs normal noise: {scene} {0}²", o.size),
                "mean angular error of the input normals (°)",
                "depth RMSE / depth range, offset removed per object (%)",
                (false, true),
                series,
                Legend::LowerRight,
            ),
            &out.join(format!("depth_vs_noise_{scene}")),
        )?;
    }
    let at: Vec<&DepthRow> = rows
        .iter()
        .filter(|r| (r.normal_noise - DEPTH_PARETO_NOISE).abs() < 1e-12)
        .collect();
    if at.is_empty() {
        return Ok(());
    }
    let series = distinct(at.iter().map(|r| r.scene))
        .into_iter()
        .enumerate()
        .map(|(k, scene)| {
            let of: Vec<&&DepthRow> = at.iter().filter(|r| r.scene == scene).collect();
            Series::line(
                scene,
                of.iter()
                    .map(|r| (r.seconds, 100.0 * r.shape_rmse_over_range))
                    .collect(),
                k,
            )
            .styled(Style::Markers)
            .labelled(of.iter().map(|r| r.method.to_string()).collect())
        })
        .collect();
    write(
        &chart(
            format!(
                "Integrators: error vs time (normal noise σ = {DEPTH_PARETO_NOISE}, {0}², {1} threads)",
                o.size,
                rayon::current_num_threads()
            ),
            "integration time (s)",
            "depth RMSE / depth range, offset removed per object (%)",
            (true, true),
            series,
            Legend::UpperRight,
        ),
        &out.join("depth_pareto"),
    )
}

/// The options `a` asks for.
fn options(a: &SweepBenchArgs) -> SweepOptions {
    let mut o = SweepOptions {
        size: a.size,
        sfs_size: a.sfs_size,
        repeat: a.repeat,
        ..SweepOptions::default()
    };
    if !a.methods.is_empty() {
        o.methods = a.methods.iter().map(|m| m.method()).collect();
    }
    if a.quick {
        o = o.quick();
    }
    o
}

/// Runs the three sweeps `a` asks for, writes the tables and charts into `a.out`, and returns
/// a summary.
pub fn run(a: &SweepBenchArgs, progress: &dyn Progress) -> Result<Value> {
    write_sweeps(&options(a), &a.out, progress)
}

/// Runs the three sweeps of `o`, writes the tables and charts into `out`, and returns a
/// summary.
pub fn write_sweeps(o: &SweepOptions, out: &Path, progress: &dyn Progress) -> Result<Value> {
    o.validate()?;
    std::fs::create_dir_all(out)?;
    let normals = normal_sweep(o, progress)?;
    let sfs = sfs_sweep(o, progress)?;
    let depth = depth_sweep(o, progress)?;
    let nv: Vec<Value> = normals.iter().map(|r| json!(r)).collect();
    let sv: Vec<Value> = sfs.iter().map(|r| json!(r)).collect();
    let dv: Vec<Value> = depth.iter().map(|r| json!(r)).collect();
    let normal_columns = [
        "axis",
        "scene",
        "family",
        "method",
        "images",
        "light_slant_deg",
        "noise",
        "ks",
        "mean_deg",
        "median_deg",
        "p95_deg",
        "coverage",
        "seconds",
    ];
    write_csv(&out.join("sweep_normals.csv"), &nv, &normal_columns)?;
    write_csv(&out.join("sweep_sfs.csv"), &sv, &normal_columns)?;
    write_csv(
        &out.join("sweep_depth.csv"),
        &dv,
        &[
            "scene",
            "method",
            "normal_noise",
            "normal_error_deg",
            "rmse_over_range",
            "shape_rmse_over_range",
            "pixels",
            "seconds",
        ],
    )?;
    normal_charts(&normals, o, out)?;
    sfs_chart(&sfs, o, out)?;
    depth_charts(&depth, o, out)?;
    let lights: Vec<(f64, f64)> = normals
        .iter()
        .filter(|r| r.axis == Axis::Lights)
        .map(|r| (r.seconds, r.mean_deg))
        .collect();
    let lights_rows: Vec<&NormalRow> = normals.iter().filter(|r| r.axis == Axis::Lights).collect();
    let front: Vec<Value> = pareto_front(&lights)
        .into_iter()
        .map(|i| {
            json!({"method": lights_rows[i].method, "images": lights_rows[i].images,
                "seconds": lights_rows[i].seconds, "mean_deg": lights_rows[i].mean_deg})
        })
        .collect();
    let summary = json!({
        "size": o.size,
        "reference_lights": o.lights,
        // Through its shortest decimal form, so that 0.01 stays 0.01 in f64.
        "reference_noise": o.noise.to_string().parse::<f64>().unwrap_or(f64::NAN),
        "threads": rayon::current_num_threads(),
        "repeat": o.repeat.max(1),
        "normals_pareto_front": front,
        "normals": nv,
        "sfs": sv,
        "depth": dv,
    });
    crate::write_file_atomic(
        &out.join("sweep.json"),
        serde_json::to_string_pretty(&summary)?.as_bytes(),
    )?;
    Ok(summary)
}
