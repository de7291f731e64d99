//! `photostereo`: the command-line tool. Flags become a validated configuration
//! ([`args`]), which drives the library.

/// Prints a line to standard output; when the reader has gone (`photostereo … | head`), the
/// program ends quietly instead of panicking (the outputs are already written by then).
macro_rules! say {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        if let Err(e) = writeln!(std::io::stdout().lock(), $($arg)*) {
            if e.kind() == std::io::ErrorKind::BrokenPipe {
                std::process::exit(0);
            }
        }
    }};
}

mod args;
mod bar;
mod bench;

use anyhow::{Context, Result};
use args::{Cli, Command, DemoArgs, EvalArgs, RunConfig, Source};
use clap::Parser;
use photostereo::dataset::Capture;
use photostereo::demo;
use photostereo::grid::Grid;
use photostereo::input::read_normal_map;
use photostereo::metrics::angular_errors;
use photostereo::pipeline::{Config, Reconstruction, Report, reconstruct, write_outputs};
use photostereo::progress::{Progress, Silent};
use std::path::Path;
use std::time::Instant;

fn main() {
    let cli = Cli::parse();
    if let Err(e) = run(cli) {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

fn run(cli: Cli) -> Result<()> {
    if let Some(n) = cli.threads {
        rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build_global()
            .context("--threads: cannot start the thread pool")?;
    }
    let bars = bar::Bars::new(cli.quiet);
    let progress: &dyn Progress = if cli.quiet { &Silent } else { &bars };
    match cli.command {
        Some(Command::Demo(a)) => run_demo(a, progress),
        Some(Command::Eval(a)) => run_eval(a),
        Some(Command::Bench(a)) => bench::run(a),
        None => run_main(cli.run.validate()?, progress),
    }
}

/// Loads a capture as the configuration says; returns it with the load time.
pub fn load_capture(rc: &RunConfig, progress: &dyn Progress) -> Result<(Capture, f64)> {
    let t = Instant::now();
    let mut capture = match &rc.source {
        Source::Diligent(dir) => Capture::from_diligent(dir, &rc.load, progress)?,
        Source::Files { images, lights } => {
            Capture::from_files(images, lights, None, &rc.load, progress)?
        }
    };
    if let Some(mask) = &rc.mask {
        capture = capture.with_mask_file(mask)?;
    }
    Ok((capture, t.elapsed().as_secs_f64()))
}

fn run_main(rc: RunConfig, progress: &dyn Progress) -> Result<()> {
    let (capture, load_s) = load_capture(&rc, progress)?;
    let mut recon = reconstruct(&capture, &rc.config, progress)?;
    recon.timings.load = load_s;
    let report = write_outputs(&mut recon, &capture, &rc.config, &rc.output, None)?;
    print_summary(&recon, &report, &rc.config, &rc.output);
    Ok(())
}

fn run_demo(a: DemoArgs, progress: &dyn Progress) -> Result<()> {
    let config = a.method.config()?;
    let t = Instant::now();
    let synth = demo::default_capture(a.noise, a.seed)?;
    let render_s = t.elapsed().as_secs_f64();
    say!(
        "demo scene: {}x{} px, {} lights, noise σ = {}, rendered in {:.2} s",
        synth.capture.stack.width(),
        synth.capture.stack.height(),
        synth.capture.lights.len(),
        a.noise,
        render_s
    );
    let mut recon = reconstruct(&synth.capture, &config, progress)?;
    recon.timings.load = render_s;
    let eval = demo::evaluate(&recon, &synth.truth)?;
    let eval_json = serde_json::to_value(&eval)?;
    photostereo::dataset::write_synthetic(
        &synth.rendering,
        &synth.capture.lights,
        &a.output.join("scene"),
        photostereo::dataset::ImageFormat::Exr,
    )?;
    let report = write_outputs(
        &mut recon,
        &synth.capture,
        &config,
        &a.output,
        Some(eval_json),
    )?;
    print_summary(&recon, &report, &config, &a.output);
    say!("error against ground truth:");
    let n = &eval.normals;
    say!(
        "  normals: mean {:.3}°, median {:.3}°, 95th pct {:.3}° over {} px ({:.1}% under 5°)",
        n.mean_deg,
        n.median_deg,
        n.p95_deg,
        n.pixels,
        100.0 * n.below_5deg
    );
    say!(
        "  albedo:  mean relative error {:.3}%",
        100.0 * eval.albedo_mean_relative_error
    );
    if let Some(d) = &eval.depth {
        say!(
            "  depth:   RMSE {:.3} px after offset = {:.2}% of the {:.1} px depth range",
            d.rmse,
            100.0 * d.rmse_over_range,
            d.gt_range
        );
    }
    say!(
        "inputs in {0}/scene/, ground truth (normal_gt.exr, depth_gt.exr, albedo_gt.exr, shadow masks) in {0}/scene/gt/",
        a.output.display()
    );
    Ok(())
}

fn run_eval(a: EvalArgs) -> Result<()> {
    let est = read_normal_map(&a.normals)?;
    let gt = read_normal_map(&a.gt)?;
    let mask = match &a.mask {
        Some(m) => photostereo::input::read_mask(m)?,
        None => Grid::new(gt.width(), gt.height(), true),
    };
    let stats = angular_errors(&est, &gt, &mask)?;
    say!("{}", serde_json::to_string_pretty(&stats)?);
    Ok(())
}

fn print_summary(recon: &Reconstruction, report: &Report, config: &Config, dir: &Path) {
    let i = &report.inputs;
    let c = &recon.counts;
    say!(
        "{} images {}x{}, method {}, integration {}",
        i.count,
        i.width,
        i.height,
        config.solve.method.name(),
        config.integrator.map_or("none", |m| m.name())
    );
    say!(
        "  pixels: {} in mask, {} solved, {} too few samples, {} ill-conditioned, {} dark",
        c.masked,
        c.solved,
        c.too_few_samples,
        c.ill_conditioned,
        c.dark
    );
    say!(
        "  integrability: mean |curl| {:.4}, median {:.4}, 95th pct {:.4} (per pixel)",
        recon.integrability.mean_abs_curl,
        recon.integrability.median_abs_curl,
        recon.integrability.p95_abs_curl
    );
    let t = &recon.timings;
    say!(
        "  time: load {:.3} s, solve {:.3} s, normals {:.3} s, integrate {:.3} s, write {:.3} s",
        t.load,
        t.solve,
        t.normals,
        t.integrate,
        t.write
    );
    say!("  wrote {} ({})", dir.display(), report.outputs.join(", "));
    for w in &recon.warnings {
        eprintln!("warning: {w}");
    }
}
