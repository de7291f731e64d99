//! `photostereo bench`: end-to-end timing on a DiLiGenT folder beside the numpy peer, in one run.
//!
//! Both tools are timed as whole processes (start-up, load, solve, and for photostereo also
//! integration and writing every output), alternating runs so that machine load hits both alike;
//! photostereo's stages are also timed in-process, with the time to stream the loaded stack
//! through memory once as the yardstick for the solve.

use crate::args::BenchArgs;
use anyhow::{Context, Result};
use photostereo::dataset::Capture;
use photostereo::input::LoadOptions;
use photostereo::pipeline::{reconstruct, write_outputs};
use photostereo::progress::Silent;
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

/// Runs the benchmark and prints JSON.
pub fn run(a: BenchArgs) -> Result<()> {
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
        let mut recon = reconstruct(&capture, &config, &Silent)?;
        recon.timings.load = load_s;
        write_outputs(&mut recon, &capture, &config, &tmp, None)?;
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
        "integrator": config.integrator.map_or("none", |i| i.name()),
        "photostereo": ours,
    });
    // Whole-process timings, ours and the peer's, interleaved.
    let exe = std::env::current_exe().context("locating the photostereo executable")?;
    let method = config.solve.method.name();
    let integrate = config.integrator.map_or("none", |i| i.name());
    let peer = a.peer.is_file();
    let (mut ours_wall, mut peer_wall, mut peer_internal) = (vec![], vec![], vec![]);
    for _ in 0..repeat {
        let t = Instant::now();
        let o = Command::new(&exe)
            .arg(&a.dir)
            .args(["--method", method, "--integrate", integrate, "-q", "-o"])
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
            let o = Command::new(&a.python)
                .arg(&a.peer)
                .arg("diligent")
                .arg(&a.dir)
                .output()
                .with_context(|| format!("running {} {}", a.python, a.peer.display()))?;
            peer_wall.push(t.elapsed().as_secs_f64());
            anyhow::ensure!(
                o.status.success(),
                "peer failed: {}",
                String::from_utf8_lossy(&o.stderr)
            );
            let v: serde_json::Value = serde_json::from_slice(&o.stdout)?;
            peer_internal.push(
                v["load_s"].as_f64().unwrap_or(f64::NAN)
                    + v["solve_s"].as_f64().unwrap_or(f64::NAN),
            );
        }
    }
    let _ = std::fs::remove_dir_all(&tmp);
    let ours_process = median(ours_wall);
    out["photostereo"]["process_wall_s"] = json!(ours_process);
    if peer {
        let (pw, pi) = (median(peer_wall), median(peer_internal));
        out["peer"] = json!({
            "script": a.peer,
            "process_wall_s": pw,
            "load_plus_solve_s": pi,
        });
        out["speedup_process_vs_process"] = json!(pw / ours_process);
        out["speedup_vs_peer_load_plus_solve"] = json!(pi / ours_process);
    } else {
        out["peer"] = json!(format!("not found: {}", a.peer.display()));
    }
    say!("{}", serde_json::to_string_pretty(&out)?);
    Ok(())
}
