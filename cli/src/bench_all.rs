//! `photostereo bench all`: every benchmark that feeds `docs/bench`, in one run, as the
//! library's [`SuitePlan`] lays it out (with `--quick`, its smoke-run settings). It writes
//! their tables (CSV, JSON) and charts (SVG, PNG), and a generated `README.md` that gathers
//! the numbers.
//!
//! The parts:
//! - the speed–accuracy sweeps (`bench sweep`);
//! - solver scaling (`bench scaling`);
//! - integrator timing and DCT Poisson beside numpy (`bench integration`);
//! - on DiLiGenT cat and bear, when `--data` holds them: every estimator's error and time, and
//!   the load and solve stages beside the numpy peer (`bench diligent --method ls`);
//! - every integrator on the shared depth data.
//!
//! Each part's defaults are the library's, which the command of the same name also uses.

use crate::args::AllBenchArgs;
use anyhow::{Context, Result};
use photostereo::capture::dataset::is_diligent_dir;
use photostereo::eval::bench::diligent::{
    OBJECTS as DILIGENT_OBJECTS, Object, light_subset_rows, method_rows, object_dir,
};
use photostereo::eval::bench::real_depth::real_depth;
use photostereo::eval::bench::suite::SuitePlan;
use photostereo::eval::sweep::pareto_front;
use photostereo::progress::Progress;
use photostereo::ps::solve::Method;
use serde_json::{Value, json};
use std::fmt::Write as _;
use std::path::Path;

fn write_json(path: &Path, v: &Value) -> Result<()> {
    crate::write_file_atomic(path, serde_json::to_string_pretty(v)?.as_bytes())
}

/// Each of `rows` as JSON.
fn values<T: serde::Serialize>(rows: &[T]) -> Vec<Value> {
    rows.iter().map(|r| json!(r)).collect()
}

/// Error against time of every integrator on DiLiGenT cat and bear (perspective).
fn integration_real_chart(rows: &[Value], out: &Path) -> Result<()> {
    use crate::chart::{Chart, Legend, Series, Style};
    let series: Vec<Series> = DILIGENT_OBJECTS
        .iter()
        .enumerate()
        .filter_map(|(k, object)| {
            let of: Vec<&Value> = rows.iter().filter(|r| r["dataset"] == *object).collect();
            (!of.is_empty()).then(|| {
                Series::line(
                    *object,
                    of.iter()
                        .filter_map(|r| Some((r["seconds"].as_f64()?, r["error"].as_f64()?)))
                        .collect(),
                    k,
                )
                .styled(Style::Markers)
                .labelled(
                    of.iter()
                        .map(|r| r["method"].as_str().unwrap_or("").to_string())
                        .collect(),
                )
            })
        })
        .collect();
    if series.is_empty() {
        return Ok(());
    }
    crate::chart::write(
        &Chart {
            title: format!(
                "Integrators on DiLiGenT depth (true normals, perspective K, {} threads)",
                rayon::current_num_threads()
            ),
            x_label: "integration time (s)".into(),
            y_label: "mean abs. depth error after median scale (mm)".into(),
            log: (true, true),
            series,
            legend: Legend::UpperRight,
        },
        &out.join("integration_diligent"),
    )
}

/// Error against light count per estimator, one chart per object.
fn diligent_lights_charts(rows: &[Value], out: &Path) -> Result<()> {
    use crate::chart::{Chart, Legend, Series};
    for object in DILIGENT_OBJECTS {
        let of: Vec<&Value> = rows.iter().filter(|r| r["object"] == object).collect();
        if of.is_empty() {
            continue;
        }
        let series = Method::ALL
            .iter()
            .enumerate()
            .map(|(k, m)| {
                let pts = of
                    .iter()
                    .filter(|r| r["method"] == m.name())
                    .filter_map(|r| Some((r["lights"].as_f64()?, r["mean_deg"].as_f64()?)))
                    .collect();
                Series::line(m.name(), pts, k)
            })
            .collect();
        crate::chart::write(
            &Chart {
                title: format!("DiLiGenT {object}: error vs light count (well-spread subsets)"),
                x_label: "lights (images)".into(),
                y_label: "mean angular error over solved pixels (°)".into(),
                log: (true, false),
                series,
                legend: Legend::UpperRight,
            },
            &out.join(format!("diligent_lights_{object}")),
        )?;
    }
    Ok(())
}

/// Error against time per estimator on each object, with each object's Pareto front.
fn diligent_chart(rows: &[Value], out: &Path) -> Result<()> {
    use crate::chart::{Chart, Legend, Series, Style};
    let mut series = Vec::new();
    for (k, object) in DILIGENT_OBJECTS.iter().enumerate() {
        let of: Vec<&Value> = rows.iter().filter(|r| r["object"] == *object).collect();
        if of.is_empty() {
            continue;
        }
        let pts: Vec<(f64, f64)> = of
            .iter()
            .map(|r| {
                (
                    r["seconds"].as_f64().unwrap_or(f64::NAN),
                    r["mean_deg"].as_f64().unwrap_or(f64::NAN),
                )
            })
            .collect();
        let front = pareto_front(&pts);
        series.push(
            Series::line(*object, pts.clone(), k)
                .styled(Style::Markers)
                .labelled(
                    of.iter()
                        .map(|r| r["method"].as_str().unwrap_or("").to_string())
                        .collect(),
                ),
        );
        series.push(
            Series::line(
                format!("{object}: Pareto front"),
                front.iter().map(|&i| pts[i]).collect(),
                k,
            )
            .styled(Style::Front),
        );
    }
    crate::chart::write(
        &Chart {
            title: format!(
                "DiLiGenT: error vs time per estimator (96 images, {} threads)",
                rayon::current_num_threads()
            ),
            x_label: "solve + normals time (s)".into(),
            y_label: "mean angular error (°)".into(),
            log: (true, false),
            series,
            legend: Legend::UpperRight,
        },
        &out.join("diligent_pareto"),
    )
}

/// A Markdown table.
fn table(header: &[&str], rows: &[Vec<String>]) -> String {
    let mut s = format!(
        "| {} |\n|{}\n",
        header.join(" | "),
        " --- |".repeat(header.len())
    );
    for r in rows {
        let _ = writeln!(s, "| {} |", r.join(" | "));
    }
    s
}

/// `v` × `scale` with `digits` decimals and `unit`, or a dash when `v` is not a number.
fn cell(v: &Value, scale: f64, digits: usize, unit: &str) -> String {
    v.as_f64()
        .map_or_else(|| "–".into(), |x| format!("{:.digits$}{unit}", x * scale))
}

/// `v` with `digits` decimals, or a dash.
fn num(v: &Value, digits: usize) -> String {
    cell(v, 1.0, digits, "")
}

/// Methods × levels of `axis` from the sweep's normal rows: mean error (and coverage when
/// below 100%).
fn sweep_table(rows: &[Value], axis: &str, key: &str, label: &str) -> String {
    let picked: Vec<&Value> = rows.iter().filter(|r| r["axis"] == axis).collect();
    let mut levels: Vec<&Value> = Vec::new();
    let mut methods: Vec<&str> = Vec::new();
    for r in &picked {
        if !levels.contains(&&r[key]) {
            levels.push(&r[key]);
        }
        let m = r["method"].as_str().unwrap_or("");
        if !methods.contains(&m) {
            methods.push(m);
        }
    }
    let header: Vec<String> = std::iter::once(format!("method \\ {label}"))
        .chain(levels.iter().map(|l| {
            let v = format!("{:.3}", l.as_f64().unwrap_or(f64::NAN));
            v.trim_end_matches('0').trim_end_matches('.').to_string()
        }))
        .collect();
    let body: Vec<Vec<String>> = methods
        .iter()
        .map(|m| {
            std::iter::once(m.to_string())
                .chain(levels.iter().map(|l| {
                    picked
                        .iter()
                        .find(|r| r["method"] == *m && &r[key] == *l)
                        .map_or("–".into(), |r| {
                            let c = r["coverage"].as_f64().unwrap_or(1.0);
                            if c < 0.999 {
                                format!("{} ({:.0}%)", num(&r["mean_deg"], 2), 100.0 * c)
                            } else {
                                num(&r["mean_deg"], 2)
                            }
                        })
                }))
                .collect()
        })
        .collect();
    let h: Vec<&str> = header.iter().map(String::as_str).collect();
    table(&h, &body)
}

/// The generated `README.md` of the bench folder.
fn summary(
    sweep: &Value,
    scaling: &Value,
    integration: &Value,
    diligent: &[(String, Value)],
    methods: &[Value],
    lights: &[Value],
    integration_rows: &[Value],
) -> String {
    let mut s = String::from(
        "# Benchmarks\n\nGenerated by `photostereo bench all --out docs/bench`; do not edit. \
         Every chart is here as SVG and PNG beside its CSV/JSON table. Times are medians on \
         the machine that ran it",
    );
    let _ = writeln!(
        s,
        " ({} threads); they are for ratios, not absolutes.\n",
        sweep["threads"]
    );
    let normals = sweep["normals"].as_array().cloned().unwrap_or_default();
    let _ = writeln!(
        s,
        "## Normals (`sweep_normals.csv`)\n\nScene: sphere on a ground plane beside a pyramid, \
         {0}×{0}, attached and cast shadows, Lambertian unless k_s > 0. Mean angular error in \
         degrees over the solved pixels; the percentage of pixels solved is given where it is \
         below 100%.\n\n### Against image noise σ ({1} lights)\n\n{2}\n### Against light \
         count (σ = {3})\n\n{4}\n### Against specular strength k_s (Blinn–Phong n = 50, {1} \
         lights, σ = {3})\n\n{5}",
        sweep["size"],
        sweep["reference_lights"],
        sweep_table(&normals, "noise", "noise", "σ"),
        sweep["reference_noise"],
        sweep_table(&normals, "lights", "images", "lights"),
        sweep_table(&normals, "specularity", "ks", "k_s"),
    );
    let front: Vec<Vec<String>> = sweep["normals_pareto_front"]
        .as_array()
        .map(|a| {
            a.iter()
                .map(|r| {
                    vec![
                        r["method"].as_str().unwrap_or("").to_string(),
                        r["images"].to_string(),
                        cell(&r["seconds"], 1e3, 2, ""),
                        num(&r["mean_deg"], 2),
                    ]
                })
                .collect()
        })
        .unwrap_or_default();
    let _ = writeln!(
        s,
        "### Pareto front over the light counts\n\n{}",
        table(&["method", "lights", "time (ms)", "mean error (°)"], &front)
    );
    let sfs = sweep["sfs"].as_array().cloned().unwrap_or_default();
    let sfs_rows: Vec<Vec<String>> = sfs
        .iter()
        .filter(|r| {
            [0.0, 0.01, 0.05]
                .iter()
                .any(|n| (r["noise"].as_f64().unwrap_or(-1.0) - n).abs() < 1e-6)
        })
        .map(|r| {
            vec![
                r["method"].as_str().unwrap_or("").to_string(),
                r["images"].to_string(),
                r["light_slant_deg"]
                    .as_f64()
                    .map_or("–".into(), |v| format!("{v:.0}°")),
                cell(&r["noise"], 1.0, 3, ""),
                num(&r["mean_deg"], 2),
                cell(&r["coverage"], 100.0, 0, "%"),
                cell(&r["seconds"], 1e3, 1, ""),
            ]
        })
        .collect();
    let _ = writeln!(
        s,
        "## Shape from shading beside photometric stereo (`sweep_sfs.csv`)\n\nA Lambertian \
         sphere with known albedo.\n\n{}",
        table(
            &[
                "method",
                "images",
                "light slant",
                "σ",
                "mean error (°)",
                "solved",
                "time (ms)"
            ],
            &sfs_rows
        )
    );
    let depth = sweep["depth"].as_array().cloned().unwrap_or_default();
    let depth_rows: Vec<Vec<String>> = depth
        .iter()
        .filter(|r| {
            [0.0, 0.05]
                .iter()
                .any(|n| (r["normal_noise"].as_f64().unwrap_or(-1.0) - n).abs() < 1e-9)
        })
        .map(|r| {
            vec![
                r["scene"].as_str().unwrap_or("").to_string(),
                r["method"].as_str().unwrap_or("").to_string(),
                cell(&r["normal_error_deg"], 1.0, 2, "°"),
                cell(&r["rmse_over_range"], 100.0, 2, "%"),
                cell(&r["shape_rmse_over_range"], 100.0, 2, "%"),
                cell(&r["seconds"], 1e3, 1, ""),
            ]
        })
        .collect();
    let _ = writeln!(
        s,
        "## Integrators (`sweep_depth.csv`)\n\nTrue normals with noise added. Depth RMSE over \
         the depth range, after removing one offset, and after removing one offset per object \
         (the height of a discontinuity is not in the normals).\n\n{}",
        table(
            &[
                "scene",
                "method",
                "normal error",
                "RMSE / range",
                "per object",
                "time (ms)"
            ],
            &depth_rows
        )
    );
    let slopes = |v: &Value, key: &str| -> Vec<Vec<String>> {
        v["slopes"]
            .as_array()
            .map(|a| {
                a.iter()
                    .map(|r| {
                        vec![
                            r["method"].as_str().unwrap_or("").to_string(),
                            num(&r[key], 2),
                        ]
                    })
                    .collect()
            })
            .unwrap_or_default()
    };
    let _ = writeln!(
        s,
        "## Cost against size\n\nLog-log slopes of time: 1 is linear.\n\nSolvers, against \
         pixels × lights (`scaling.csv`):\n\n{}\nIntegrators, against pixels in the mask \
         (`integration.csv`):\n\n{}",
        table(
            &["estimator", "slope"],
            &slopes(scaling, "loglog_slope_vs_samples")
        ),
        table(
            &["integrator", "slope"],
            &slopes(integration, "loglog_slope_vs_pixels")
        ),
    );
    if let Some(t) = integration["table"].as_str() {
        let _ = writeln!(s, "{t}");
    }
    let peer: Vec<Vec<String>> = integration["poisson_vs_numpy"]
        .as_array()
        .map(|a| {
            a.iter()
                .map(|r| {
                    vec![
                        format!("{}²", r["size"]),
                        cell(&r["photostereo_poisson_s"], 1e3, 1, ""),
                        cell(&r["numpy_dct_poisson_s"], 1e3, 1, ""),
                        cell(&r["speedup"], 1.0, 1, "×"),
                    ]
                })
                .collect()
        })
        .unwrap_or_default();
    if !peer.is_empty() {
        let _ = writeln!(
            s,
            "DCT Poisson beside `numpy_ps.py poisson N` (scipy's DCT):\n\n{}",
            table(
                &["size", "photostereo (ms)", "numpy (ms)", "speed-up"],
                &peer
            )
        );
    }
    if !integration_rows.is_empty() {
        let datasets = {
            let mut d: Vec<&str> = Vec::new();
            for r in integration_rows {
                let name = r["dataset"].as_str().unwrap_or("");
                if !d.contains(&name) {
                    d.push(name);
                }
            }
            d
        };
        let methods: Vec<&str> = photostereo::integrate::Integrator::ALL
            .iter()
            .map(|m| m.name())
            .collect();
        let body: Vec<Vec<String>> = datasets
            .iter()
            .map(|d| {
                let of = |m: &str| {
                    integration_rows
                        .iter()
                        .find(|r| r["dataset"] == *d && r["method"] == m)
                };
                std::iter::once(d.to_string())
                    .chain(of(methods[0]).map(|r| r["metric"].as_str().unwrap_or("").to_string()))
                    .chain(methods.iter().map(|m| {
                        of(m).map_or("–".into(), |r| {
                            format!("{} ({} s)", num(&r["error"], 3), num(&r["seconds"], 2))
                        })
                    }))
                    .collect()
            })
            .collect();
        let header: Vec<&str> = ["data", "metric"].into_iter().chain(methods).collect();
        let _ = writeln!(
            s,
            "## Integrators on the shared depth data (`integration_real.csv`)\n\nDiLiGenT \
             cat and bear: the ground-truth normals integrated with the perspective camera \
             `K.txt`; published bilateral figures 0.074 mm (cat) and 0.334 mm (bear). Vase: \
             its exact gradients, and with Gaussian noise of 0.5% of the largest gradient (one \
             draw). Error (time).\n\n{}",
            table(&header, &body)
        );
    }
    if diligent.is_empty() {
        let _ = writeln!(
            s,
            "## DiLiGenT\n\nNot run: the data folder was absent when this was generated.\n"
        );
        return s;
    }
    let stage: Vec<Vec<String>> = diligent
        .iter()
        .map(|(o, v)| {
            vec![
                o.clone(),
                cell(&v["photostereo"]["load_s"], 1.0, 3, ""),
                num(&v["peer"]["load_s"], 3),
                cell(&v["speedup_per_stage"]["load"], 1.0, 1, "×"),
                cell(&v["photostereo"]["solve_s"], 1.0, 3, ""),
                num(&v["peer"]["solve_s"], 3),
                cell(&v["speedup_per_stage"]["solve"], 1.0, 1, "×"),
                cell(&v["speedup_process_vs_process"], 1.0, 1, "×"),
            ]
        })
        .collect();
    let _ = writeln!(
        s,
        "## DiLiGenT beside the numpy peer (`diligent_<object>.json`)\n\nBoth solve plain \
         least squares (`--method ls`) over 96 images of 612×512. Load: read, divide by the \
         light intensities, grey. Speed-up: the peer's time over ours, same run.\n\n{}",
        table(
            &[
                "object",
                "load (s)",
                "peer load (s)",
                "load speed-up",
                "solve (s)",
                "peer solve (s)",
                "solve speed-up",
                "whole process"
            ],
            &stage
        )
    );
    let m: Vec<Vec<String>> = methods
        .iter()
        .map(|r| {
            vec![
                r["object"].as_str().unwrap_or("").to_string(),
                r["method"].as_str().unwrap_or("").to_string(),
                num(&r["mean_deg"], 2),
                num(&r["median_deg"], 2),
                cell(&r["seconds"], 1.0, 3, ""),
            ]
        })
        .collect();
    for object in DILIGENT_OBJECTS {
        let of: Vec<Value> = lights
            .iter()
            .filter(|r| r["object"] == object)
            .map(|r| {
                let mut r = r.clone();
                r["axis"] = json!("lights");
                r
            })
            .collect();
        if !of.is_empty() {
            let _ = writeln!(
                s,
                "### DiLiGenT {object} against light count (`diligent_lights.csv`)\n\nWell-spread \
                 subsets of the 96 lights (greedy farthest point). Mean angular error in \
                 degrees over the solved pixels, with the share solved where it is below \
                 100%.\n\n{}",
                sweep_table(&of, "lights", "lights", "lights")
            );
        }
    }
    let _ = writeln!(
        s,
        "### Every estimator on DiLiGenT (`diligent_methods.csv`)\n\n{}",
        table(
            &["object", "method", "mean (°)", "median (°)", "time (s)"],
            &m
        )
    );
    s
}

/// Runs every part and writes `docs/bench` (or `--out`).
pub fn run(a: &AllBenchArgs, progress: &dyn Progress) -> Result<Value> {
    let out = &a.out;
    let plan = SuitePlan::new(a.quick);
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    // 1. The sweeps.
    eprintln!("bench all: sweeps");
    let sweep = crate::sweep::write_sweeps(&plan.sweep, out, progress)?;
    // 2. Solver scaling.
    eprintln!("bench all: solver scaling");
    let scaling = crate::bench::scaling_report(
        &plan.scaling,
        Some(&out.join("scaling.csv")),
        Some(&out.join("scaling")),
    )?;
    write_json(&out.join("scaling.json"), &scaling)?;
    // 3. Integrators.
    eprintln!("bench all: integrators");
    let integration = crate::bench::integration_report(
        &plan.integration,
        &a.peer,
        Some(&out.join("integration.csv")),
        Some(&out.join("integration_time")),
    )?;
    write_json(&out.join("integration.json"), &integration)?;
    // 4. Interreflections on rendered concave scenes.
    eprintln!("bench all: interreflections");
    let interreflections =
        photostereo::eval::bench::interreflections::interreflections(&plan.interreflections)?;
    write_json(&out.join("interreflections.json"), &json!(interreflections))?;
    crate::bench::interreflection_chart(&interreflections, &out.join("interreflections"))?;
    // 5. Near lights against distant ones.
    eprintln!("bench all: near lights");
    let near = photostereo::eval::near::sweep(&plan.near)?;
    write_json(&out.join("near.json"), &json!(near))?;
    crate::bench::near_chart(&near, &out.join("near"))?;
    // 6. Shape from shading on rendered shapes.
    eprintln!("bench all: shape from shading");
    let sfs = photostereo::eval::sfs::sweep(&plan.sfs)?;
    write_json(&out.join("sfs.json"), &json!(sfs))?;
    crate::bench::sfs_chart(&sfs, &out.join("sfs"))?;
    // 7. Real data.
    let mut diligent = Vec::new();
    let mut methods = Vec::new();
    let mut lights = Vec::new();
    for object in DILIGENT_OBJECTS {
        let dir = object_dir(&a.data, object);
        if !is_diligent_dir(&dir) {
            eprintln!(
                "bench all: skipping DiLiGenT {object}: {} is absent",
                dir.display()
            );
            continue;
        }
        eprintln!("bench all: DiLiGenT {object}");
        let v = crate::bench::diligent(&dir, &plan.stages, plan.diligent_repeat, &a.peer)?;
        write_json(&out.join(format!("diligent_{object}.json")), &v)?;
        diligent.push((object.to_string(), v));
        let loaded = Object::load(&dir, object)?;
        methods.extend(values(&method_rows(&loaded, plan.diligent_repeat)?));
        lights.extend(values(&light_subset_rows(&loaded)?));
    }
    eprintln!("bench all: integrators on the shared depth data");
    let real = real_depth(&a.data)?;
    for absent in &real.absent {
        eprintln!(
            "bench all: skipping integration on {}: {} is absent",
            absent.name,
            absent.path.display()
        );
    }
    let integration_rows = values(&real.rows);
    if !integration_rows.is_empty() {
        crate::sweep::write_csv(
            &out.join("integration_real.csv"),
            &integration_rows,
            &["dataset", "method", "error", "metric", "seconds"],
        )?;
        integration_real_chart(&integration_rows, out)?;
    }
    if !lights.is_empty() {
        crate::sweep::write_csv(
            &out.join("diligent_lights.csv"),
            &lights,
            &[
                "object",
                "method",
                "lights",
                "mean_deg",
                "median_deg",
                "coverage",
                "seconds",
            ],
        )?;
        diligent_lights_charts(&lights, out)?;
    }
    if !methods.is_empty() {
        crate::sweep::write_csv(
            &out.join("diligent_methods.csv"),
            &methods,
            &[
                "object",
                "method",
                "mean_deg",
                "median_deg",
                "p95_deg",
                "seconds",
            ],
        )?;
        diligent_chart(&methods, out)?;
    }
    let mut text = summary(
        &sweep,
        &scaling,
        &integration,
        &diligent,
        &methods,
        &lights,
        &integration_rows,
    );
    let _ = writeln!(
        text,
        "## Interreflections (`interreflections.json`, `interreflections.svg`)\n\n\
         Lambertian scenes of albedo {} rendered at {}×{} under {} lights with {} bounces of \
         diffuse interreflection and cast shadows, solved by the default command without \
         compensation, with `--interreflections` and the reflectance scale known (1), and with \
         it estimated from the data; `no bounces` is the same scene rendered without \
         interreflections (what is left from other causes). The sphere is the convex control: \
         nothing to compensate.\n\n{}",
        interreflections.albedo,
        interreflections.size,
        interreflections.size,
        interreflections.lights,
        photostereo::eval::bench::interreflections::BOUNCES,
        crate::bench::interreflection_table(&interreflections)
    );
    let _ = writeln!(
        text,
        "## Near lights (`near.json`, `near.svg`, `near_depth.svg`)\n\n\
         Lambertian scenes at {}×{} under {} LEDs of profile cos^{} (half on a ring at 25°, half \
         at 45° from the optical axis, all at the given distance from the scene's centre, the \
         pinhole camera at the same distance), read noise {} of the mean level, solved by the \
         near-light model (absolute depth) and by the distant approximation (each LED's \
         direction from the centre; its depth's unknown scale fitted to the truth). The distant \
         model is within 1° from: {}.\n\n{}",
        near.options.size,
        near.options.size,
        near.options.lights,
        near.options.mu,
        near.options.noise,
        near.distant_within_1deg
            .iter()
            .map(|(s, d)| format!(
                "{s} {}",
                d.map_or("never in this sweep".to_string(), |d| format!(
                    "{d} object sizes"
                ))
            ))
            .collect::<Vec<_>>()
            .join(", "),
        crate::bench::near_table(&near)
    );
    let _ = writeln!(
        text,
        "## Shape from shading on rendered shapes (`sfs.json`, `sfs.svg`)\n\n\
         Every method on five shapes (sphere, vase, peaks, relief, bust) at {}×{}, Lambertian, \
         albedo 0.8, cast shadows, no noise, light and albedo known, the light {} from the \
         view; the distant-light methods on orthographic renderings, the \
         perspective method on perspective ones with the light's fall-off (a point light in \
         the camera's plane, seen at the same angle from the scene's centre). Normals over the \
         whole mask; depth RMSE after removing the mean offset, over the true range (absolute: \
         before removing it).\n\n{}",
        sfs.options.size,
        sfs.options.size,
        sfs.options
            .slants
            .iter()
            .map(|s| format!("{s}°"))
            .collect::<Vec<_>>()
            .join(", "),
        crate::bench::sfs_table(&sfs)
    );
    crate::write_file_atomic(&out.join("README.md"), text.as_bytes())?;
    Ok(json!({
        "out": out,
        "threads": rayon::current_num_threads(),
        "diligent_objects": diligent.iter().map(|(o, _)| o.clone()).collect::<Vec<_>>(),
        "normals_pareto_front": sweep["normals_pareto_front"],
    }))
}
