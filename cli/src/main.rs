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
mod bench_all;
mod calibrate;
mod chart;
mod sfs;
mod sweep;

use anyhow::{Context, Result};
use args::{Cli, Command, DemoArgs, DepthAlign, EvalArgs, IntegrateArgs, RunConfig, Source};
use clap::Parser;
use photostereo::capture::dataset::Capture;
use photostereo::capture::dataset::CaptureFiles;
use photostereo::eval::demo;
use photostereo::eval::metrics::{angular_errors, depth_errors, scaled_depth_errors};
use photostereo::grid::Grid;
use photostereo::grid::Mask;
use photostereo::integrate::{SolveMethod, integrate_normals};
use photostereo::io::decode::read_normal_map;
use photostereo::io::mesh::Mesh;
use photostereo::io::output::{OutputLock, Overwrite};
use photostereo::progress::{Progress, Silent};
use photostereo::run::pipeline::{Config, Report, reconstruct, reconstruct_and_write};
use photostereo::run::stream::{StreamOptions, reconstruct_and_write_streamed};
use std::path::Path;
use std::time::Instant;

fn main() {
    let cli = Cli::parse();
    if let Err(e) = run(cli) {
        eprintln!("error: {}{}", printable(&format!("{e:#}")), hint(&e));
        std::process::exit(1);
    }
}

/// `text` with its control characters (other than line breaks and tabs) shown as escapes:
/// messages quote file names and file contents, and an escape sequence in a lights file must
/// not reach the terminal.
pub fn printable(text: &str) -> std::borrow::Cow<'_, str> {
    if !text
        .chars()
        .any(|c| c.is_control() && c != '\n' && c != '\t')
    {
        return text.into();
    }
    text.chars()
        .map(|c| {
            if c.is_control() && c != '\n' && c != '\t' {
                c.escape_default().to_string()
            } else {
                c.to_string()
            }
        })
        .collect::<String>()
        .into()
}

/// The flag that avoids the library error behind `e`, for the errors the command line has one
/// for (the library says what is wrong, in its own terms).
fn hint(e: &anyhow::Error) -> &'static str {
    match e
        .chain()
        .find_map(|c| c.downcast_ref::<photostereo::Error>())
    {
        Some(photostereo::Error::OutputExists { .. }) => {
            "; choose another output, or pass --force to replace a previous output set"
        }
        Some(photostereo::Error::NotBandReadable { .. }) => {
            " (to load the images whole instead, run without --max-memory)"
        }
        _ => "",
    }
}

/// Most worker threads per core `--threads` starts (more only contend; a few per core can
/// hide waits on files).
const MAX_THREADS_PER_CORE: usize = 4;

/// Exit status of a run stopped by Ctrl-C (128 + SIGINT), as shells report it.
const INTERRUPTED_EXIT: i32 = 130;

/// Ctrl-C (and SIGTERM): let a commit in progress finish, so the outputs are all in place or
/// none is, then exit. The temporaries are unnamed files, which vanish with the process.
fn stop_cleanly_on_interrupt() {
    let handler = || {
        let _held = photostereo::io::output::hold_commits();
        photostereo::io::output::discard_uncommitted();
        eprintln!(
            "interrupted: stopped; outputs are written all at once at the end, so none from this run is left half-written"
        );
        std::process::exit(INTERRUPTED_EXIT);
    };
    if let Err(e) = ctrlc::set_handler(handler) {
        eprintln!(
            "warning: cannot catch Ctrl-C ({e}); an interrupt will still leave no partial file"
        );
    }
}

fn run(cli: Cli) -> Result<()> {
    stop_cleanly_on_interrupt();
    if let Some(asked) = cli.threads {
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        let cap = MAX_THREADS_PER_CORE * cores;
        let n = if asked > cap {
            eprintln!(
                "note: --threads {asked} capped at {cap} ({MAX_THREADS_PER_CORE} × the {cores} cores): more threads than that only contend for the cores and memory"
            );
            cap
        } else {
            asked
        };
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
        Some(Command::Integrate(a)) => run_integrate(a, progress),
        Some(Command::Sfs(a)) => sfs::run(a, progress),
        Some(Command::Calibrate(a)) => calibrate::run(a, progress),
        Some(Command::Bench(args::BenchCommand::Diligent(a))) => {
            say!("{}", serde_json::to_string_pretty(&bench::run(&a)?)?);
            Ok(())
        }
        Some(Command::Bench(args::BenchCommand::Integration(a))) => {
            let mut out = bench::integration(&a)?;
            let table = out["table"].take();
            say!("{}", serde_json::to_string_pretty(&out)?);
            say!("{}", table.as_str().unwrap_or(""));
            Ok(())
        }
        Some(Command::Bench(args::BenchCommand::Specularity(a))) => bench::specularity(a),
        Some(Command::Bench(args::BenchCommand::Interreflections(a))) => bench::interreflections(a),
        Some(Command::Bench(args::BenchCommand::Near(a))) => bench::near(a),
        Some(Command::Bench(args::BenchCommand::FromObject(a))) => bench::from_object(a),
        Some(Command::Bench(args::BenchCommand::Sfs(a))) => bench::sfs(a),
        Some(Command::Bench(args::BenchCommand::Stream(a))) => bench::stream(a),
        Some(Command::Bench(args::BenchCommand::Scaling(a))) => {
            say!("{}", serde_json::to_string_pretty(&bench::scaling(&a)?)?);
            Ok(())
        }
        Some(Command::Bench(args::BenchCommand::All(a))) => {
            say!(
                "{}",
                serde_json::to_string_pretty(&bench_all::run(&a, progress)?)?
            );
            Ok(())
        }
        Some(Command::Bench(args::BenchCommand::Sweep(a))) => {
            let summary = sweep::run(&a, progress)?;
            say!(
                "{}",
                serde_json::to_string_pretty(&serde_json::json!({
                    "out": a.out,
                    "threads": summary["threads"],
                    "normals_pareto_front": summary["normals_pareto_front"],
                }))?
            );
            Ok(())
        }
        None => run_main(cli.run.validate()?, progress),
    }
}

/// Writes `bytes` to the file `path` atomically, replacing it if it exists.
pub fn write_file_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    Ok(photostereo::io::output::write_bytes(
        path,
        Overwrite::PreviousSet,
        bytes,
    )?)
}

/// The commit policy of `--force`.
pub fn overwrite(force: bool) -> Overwrite {
    if force {
        Overwrite::PreviousSet
    } else {
        Overwrite::Never
    }
}

/// Locks the output folder `dir` for the run (a second run into it is refused at once), after
/// checking, before any work, that it can take the outputs: without `force` it must be new or
/// empty; with it, it may hold only a previous output set; and a folder can be created beside
/// it.
pub fn lock_output(dir: &Path, force: bool) -> Result<OutputLock> {
    // The checks are made under the lock, where no other run touches the folder.
    let lock = OutputLock::acquire(dir, overwrite(force))?;
    if force {
        photostereo::io::output::ensure_replaceable(dir)?;
    } else {
        photostereo::io::output::ensure_fresh_dir(dir)?;
    }
    photostereo::io::output::ensure_writable_dir(dir)?;
    Ok(lock)
}

/// The capture's files, resolved without decoding.
fn capture_files(rc: &RunConfig) -> Result<CaptureFiles> {
    let files = match &rc.source {
        Source::Diligent(dir) => CaptureFiles::from_diligent(dir, rc.mask.as_deref())?,
        Source::Files {
            images,
            lights,
            order,
        } => CaptureFiles::from_files_ordered(images, lights, rc.mask.as_deref(), *order)
            .map_err(|e| match e {
                photostereo::Error::ImageOrder { .. } => anyhow::anyhow!(
                    "{e}; or pass --image-order natural to sort them numerically (--image-order given keeps the order)"
                ),
                e => e.into(),
            })?,
    };
    Ok(match &rc.ambient {
        Some(path) => files.with_ambient(path)?,
        None => files,
    })
}

/// The default memory budget (without `--max-memory`): a run whose in-memory plan needs more
/// is streamed within it (or within half the available memory where that is less), unless
/// even streaming needs more, then within the least budget it can stream in, up to half the
/// available memory ([`streaming_budget`]). A whole-pipeline footprint that a laptop or a
/// shared node can give without swapping; streaming costs 1.09–1.21× the time of an in-memory
/// run on the 12 and 48 Mpx stacks measured, and is faster on the 25 Mpx one
/// (`docs/inputs-and-outputs.md`).
const DEFAULT_MAX_MEMORY: u64 = 2 << 30;

/// Memory the system can still give (Linux `MemAvailable`), when known.
fn available_memory() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

/// Bytes an in-memory run of `files` needs: the stack (the mask's window of every image, f32
/// per channel) and the maps, integration included.
/// With `window_only` false the mask is not read and the whole frame is counted: an upper
/// bound, enough when it already fits.
fn in_memory_bytes(rc: &RunConfig, files: &CaptureFiles, window_only: bool) -> Result<Option<u64>> {
    let Some(first) = files.images.first() else {
        return Ok(None);
    };
    let (w, h) = photostereo::io::decode::image_size(first)?;
    let channels: u64 = if rc.load.color == photostereo::capture::stack::ColorMode::PerChannel {
        3
    } else {
        1
    };
    // Only the window the mask spans is stored; the mask is small to read.
    // Under a budget that cannot hold even the maps of a run with no masked pixel, the mask
    // is not read: the run is refused on the declared size when it is planned.
    let none = photostereo::grid::Window {
        x0: 0,
        y0: 0,
        x1: 0,
        y1: 0,
    };
    let floor =
        photostereo::run::stream::resident_bytes(w, h, channels as usize, 0, none, &rc.config);
    let hopeless = rc.stream.is_some_and(|o| floor > o.max_memory);
    let (window, masked) = match &files.mask_source {
        Some(m) if window_only && !hopeless => {
            let mask = photostereo::io::decode::read_mask(m)?;
            let window = mask.bounding_box().unwrap_or(none);
            (window, mask.count())
        }
        _ => (photostereo::grid::Window::full(w, h), w * h),
    };
    let stack = files.images.len() as u64 * channels * window.len() as u64 * 4
        // An ambient image is held decoded (at most 16 bytes a pixel: RGBA float).
        + files.ambient_source.as_ref().map_or(0, |_| w as u64 * h as u64 * 16);
    let resident = photostereo::run::stream::resident_bytes(
        w,
        h,
        channels as usize,
        masked,
        window,
        &rc.config,
    );
    Ok(Some(stack + resident))
}

/// Streaming options. `--max-memory` streams when the in-memory run would not fit in it (a
/// run that fits is loaded whole, and says so); `--band-rows` streams in any case (within
/// `--max-memory`, else half the available memory, or without a cap where that is unknown);
/// with neither, the run is loaded whole when it needs at most [`default_cap`] (2 GiB, or half
/// the available memory where that is less), else streamed within that cap, or within the least
/// budget it can stream in where that is more ([`streaming_budget`]); a run that cannot stream
/// (near lights, interreflections, images not readable in bands), or whose least streaming
/// budget is beyond half the available memory, is loaded whole where that needs at most 80% of
/// the available memory, and refused otherwise.
fn streaming(rc: &RunConfig, files: &CaptureFiles) -> Result<Option<StreamOptions>> {
    if let Some(options) = rc.stream {
        if rc.band_rows.is_none()
            && let Some(need) = in_memory_bytes(rc, files, true)?
            && need <= options.max_memory
        {
            say!(
                "the stack and outputs need about {} MiB, within --max-memory {} MiB: loading the images whole (--band-rows streams in any case)",
                need.div_ceil(1 << 20),
                options.max_memory >> 20
            );
            return Ok(None);
        }
        return Ok(Some(options));
    }
    let available = available_memory();
    if let Some(rows) = rc.band_rows {
        let max_memory = available.map_or(u64::MAX, |a| a / 2);
        say!(
            "--band-rows {rows} without --max-memory: streaming within {}",
            available.map_or("no memory cap".to_string(), |a| format!(
                "{} MiB (half the available memory)",
                (a / 2) >> 20
            ))
        );
        return Ok(Some(StreamOptions {
            max_memory,
            band_rows: Some(rows),
        }));
    }
    let cap = default_cap(available);
    // Most runs fit by the whole-frame bound, without reading the mask an extra time.
    let fits = |need: Option<u64>| need.is_none_or(|n| n <= cap);
    if fits(in_memory_bytes(rc, files, false)?) {
        return Ok(None);
    }
    let Some(need) = in_memory_bytes(rc, files, true)? else {
        return Ok(None);
    };
    if need <= cap {
        return Ok(None);
    }
    // A run that cannot stream (near lights, interreflection compensation, images not
    // readable in row bands) is loaded whole where the memory holds it; any other error of
    // the plan (a missing file, mismatched sizes) is the run's own.
    let whole_fits = available.is_none_or(|a| need as f64 <= 0.8 * a as f64);
    let load_whole = |why: &dyn std::fmt::Display| -> Result<Option<StreamOptions>> {
        if whole_fits {
            say!(
                "the run may need up to {} MiB in memory, more than {}, but it cannot be streamed in row bands ({why}): loading the images whole",
                need.div_ceil(1 << 20),
                cap_name(available)
            );
            Ok(None)
        } else {
            Err(anyhow::anyhow!(
                "the run cannot be streamed in row bands ({why}), and loading the images whole may need up to {} MiB, more than 80% of the {} MiB available (--max-memory {}M loads them whole anyway)",
                need.div_ceil(1 << 20),
                available.unwrap_or(0) >> 20,
                need.div_ceil(1 << 20)
            ))
        }
    };
    if let Err(e) = photostereo::run::stream::streamable(files, &rc.config) {
        return load_whole(&e);
    }
    // The least budget a streamed run can have: its finishing stage, or its resident maps and
    // a band of the fewest rows.
    let unbounded = match photostereo::run::stream::plan(
        files,
        &rc.load,
        &rc.config,
        &StreamOptions {
            max_memory: u64::MAX,
            band_rows: None,
        },
    ) {
        Ok(plan) => plan,
        Err(e @ photostereo::Error::NotBandReadable { .. }) => return load_whole(&e),
        Err(e) => return Err(e.into()),
    };
    let row_bytes = unbounded.band_bytes / unbounded.band_rows.max(1) as u64;
    let least = unbounded
        .finish_bytes
        .max(unbounded.resident_bytes + photostereo::run::stream::MIN_BAND_ROWS as u64 * row_bytes);
    let max_memory = streaming_budget(cap, least, available);
    if least > max_memory && whole_fits {
        // Streaming would need more than half the available memory; loading whole fits.
        return load_whole(&format_args!(
            "that needs at least {} MiB, more than half the available memory",
            least.div_ceil(1 << 20)
        ));
    }
    say!(
        "the run may need up to {} MiB in memory, more than {}: streaming the images in row bands within {} MiB{} (set the budget with --max-memory)",
        need.div_ceil(1 << 20),
        cap_name(available),
        max_memory >> 20,
        if max_memory > cap {
            ", the least this run can stream in"
        } else {
            ""
        }
    );
    Ok(Some(StreamOptions {
        max_memory,
        band_rows: rc.band_rows,
    }))
}

/// How the default cap is described: the default budget, or half the available memory.
fn cap_name(available: Option<u64>) -> String {
    match available {
        Some(a) if a / 2 < DEFAULT_MAX_MEMORY => {
            format!("half the {} MiB available", a >> 20)
        }
        _ => format!("the default budget of {} MiB", DEFAULT_MAX_MEMORY >> 20),
    }
}

/// What a run may hold by default: [`DEFAULT_MAX_MEMORY`], or half the available memory where
/// that is less.
fn default_cap(available: Option<u64>) -> u64 {
    available.map_or(DEFAULT_MAX_MEMORY, |a| DEFAULT_MAX_MEMORY.min(a / 2))
}

/// The budget of a run streamed by default: the cap, or the `least` budget the run can stream
/// in where that is more and within half the available memory (else the cap, which the plan
/// then refuses with its remedies).
fn streaming_budget(cap: u64, least: u64, available: Option<u64>) -> u64 {
    if least > cap && available.is_none_or(|a| least <= a / 2) {
        least
    } else {
        cap
    }
}

fn run_main(rc: RunConfig, progress: &dyn Progress) -> Result<()> {
    let files = capture_files(&rc)?;
    if let Some(options) = streaming(&rc, &files)? {
        // The budget counts the maps a stage holds: freed maps go back to the system at once
        // (about 5% more time on a 3 Mpx capture, for a peak that follows the count). Nothing
        // else runs now: the planning's worker threads are idle.
        photostereo::run::stream::return_freed_maps_promptly();
        let (report, plan) = reconstruct_and_write_streamed(
            &files, &rc.load, &rc.config, &options, &rc.output, progress,
        )?;
        say!(
            "streamed {} bands of {} rows ({} MiB a band, {} MiB resident, {} MiB to finish; the stack in memory would be {} MiB)",
            plan.bands,
            plan.band_rows,
            plan.band_bytes >> 20,
            plan.resident_bytes >> 20,
            plan.finish_bytes >> 20,
            plan.in_memory_stack_bytes >> 20
        );
        print_summary(&report, &rc.output);
        return Ok(());
    }
    let t = Instant::now();
    let capture = files.load(&rc.load, progress)?;
    let load_s = t.elapsed().as_secs_f64();
    // Integration runs beside the writing of the maps that do not need depth.
    let (_, report) =
        reconstruct_and_write(&capture, &rc.config, &rc.output, load_s, progress, |_| {
            Ok(None)
        })?;
    print_summary(&report, &rc.output);
    Ok(())
}

fn run_demo(a: DemoArgs, progress: &dyn Progress) -> Result<()> {
    let config = a.method.config()?;
    let _lock = lock_output(&a.output, a.force)?;
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
    // The error against ground truth is measured once depth exists and goes into the report.
    let mut evaluation = None;
    let (_, report) = reconstruct_and_write(
        &synth.capture,
        &config,
        &a.output,
        render_s,
        progress,
        |recon| {
            let eval = demo::evaluate(recon, &synth.truth)?;
            let json = serde_json::to_value(&eval).map_err(|e| photostereo::Error::Encode {
                path: a.output.join("report.json"),
                reason: e.to_string(),
            })?;
            evaluation = Some(eval);
            Ok(Some(json))
        },
    )?;
    let eval = evaluation.context("the demo's evaluation did not run")?;
    photostereo::synth::write::write_synthetic(
        &synth.rendering,
        &synth.capture.lights,
        &a.output.join("scene"),
        photostereo::synth::write::ImageFormat::Exr,
    )?;
    print_summary(&report, &a.output);
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
    if !a.diligent.is_empty() {
        return eval_diligent(&a);
    }
    let mask_for = |w: usize, h: usize| -> Result<Mask> {
        Ok(match &a.mask {
            Some(m) => photostereo::io::decode::read_mask(m)?,
            None => Grid::new(w, h, true),
        })
    };
    let normals = match (&a.normals, &a.gt) {
        (Some(n), Some(g)) => {
            let (est, gt) = (read_normal_map(n)?, read_normal_map(g)?);
            Some(serde_json::to_value(angular_errors(
                &est,
                &gt,
                &mask_for(gt.width(), gt.height())?,
            )?)?)
        }
        _ => None,
    };
    let mut warnings: Vec<String> = Vec::new();
    let depth = match (&a.depth, &a.depth_gt) {
        (Some(d), Some(g)) => {
            warnings.extend(depth_unit_warnings(d, g, a.align)?);
            let (est, gt) = (read_depth(d)?, read_depth(g)?);
            let mask = mask_for(gt.width(), gt.height())?;
            Some(match a.align {
                DepthAlign::Offset => serde_json::to_value(depth_errors(&est, &gt, &mask)?)?,
                DepthAlign::MedianScale => {
                    serde_json::to_value(scaled_depth_errors(&est, &gt, &mask)?)?
                }
            })
        }
        _ => None,
    };
    let mut out = match (normals, depth) {
        (Some(n), None) => n,
        (None, Some(d)) => d,
        (Some(n), Some(d)) => serde_json::json!({ "normals": n, "depth": d }),
        (None, None) => anyhow::bail!(
            "nothing to evaluate: give --normals and --gt, and/or --depth and --depth-gt"
        ),
    };
    if !warnings.is_empty() {
        out["warnings"] = serde_json::to_value(&warnings)?;
    }
    say!("{}", serde_json::to_string_pretty(&out)?);
    for w in &warnings {
        eprintln!("warning: {}", printable(&w.to_string()));
    }
    Ok(())
}

/// What a depth map's `photostereo:units` says it holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum DepthKind {
    /// Orthographic height in pixel units, larger nearer.
    Height,
    /// Depth along the optical axis, up to scale or in world units, larger farther.
    AxisDepth,
}

fn depth_kind(path: &Path) -> Result<Option<(DepthKind, String)>> {
    let units = photostereo::io::decode::read_exr_text(path, "photostereo:units")?;
    Ok(units.and_then(|u| {
        if u.contains("orthographic") {
            Some((DepthKind::Height, u))
        } else if u.contains("optical axis") {
            Some((DepthKind::AxisDepth, u))
        } else {
            None
        }
    }))
}

/// Warnings when the two depth maps, or the alignment, do not fit what the headers say: an
/// orthographic height in pixels compared with depth along the axis (in mm, or up to scale),
/// a median-scale alignment of a height (it assumes depths from the camera), an offset
/// alignment of a depth known only up to scale.
fn depth_unit_warnings(est: &Path, gt: &Path, align: DepthAlign) -> Result<Vec<String>> {
    let (e, g) = (depth_kind(est)?, depth_kind(gt)?);
    let mut out = Vec::new();
    if let (Some((ek, eu)), Some((gk, gu))) = (&e, &g)
        && ek != gk
    {
        out.push(format!(
            "{} holds \"{eu}\" but {} holds \"{gu}\": the two maps measure different things, so the figures are not a depth error",
            est.display(),
            gt.display()
        ));
    }
    match (&e, align) {
        (Some((DepthKind::Height, _)), DepthAlign::MedianScale) => out.push(format!(
            "{} is an orthographic height in pixel units (larger is nearer); median-scale alignment assumes depths along the optical axis from the camera (as written with --camera K.txt), so the figures are not a depth error",
            est.display()
        )),
        (Some((DepthKind::AxisDepth, u)), DepthAlign::Offset) if u.contains("up to scale") => {
            out.push(format!(
                "{} is a depth known only up to scale; an offset alignment does not fix the scale: use --align median-scale",
                est.display()
            ))
        }
        _ => {}
    }
    Ok(out)
}

/// `eval --diligent`: reconstruct DiLiGenT-layout folders with each method, compare with the
/// ground truth, print JSON.
fn eval_diligent(a: &EvalArgs) -> Result<()> {
    use photostereo::capture::stack::LoadOptions;
    use photostereo::ps::solve::SolveOptions;
    let mut rows = Vec::new();
    for dir in &a.diligent {
        let t = std::time::Instant::now();
        let capture = Capture::from_diligent(dir, &LoadOptions::default(), &Silent)?;
        let load_s = t.elapsed().as_secs_f64();
        let gt_path = dir.join("normal_gt.exr");
        let gt = read_normal_map(&gt_path)
            .with_context(|| format!("{}: the ground truth for --diligent", gt_path.display()))?;
        for m in &a.methods {
            let config = Config {
                solve: SolveOptions {
                    shadow_labels: a.shadows.options(),
                    lobes: !a.no_lobes,
                    ..SolveOptions::with_method(m.method())
                },
                integration: None,
                ..Config::default()
            };
            config.solve.validate()?;
            let recon = reconstruct(&capture, &config, &Silent)?;
            let e = angular_errors(&recon.maps.normals, &gt, &capture.mask)?;
            let moved = recon
                .model
                .gains
                .iter()
                .flatten()
                .filter(|g| (**g - 1.0).abs() > photostereo::run::pipeline::GAIN_WARNING)
                .count();
            let mut row = serde_json::json!({
                "dataset": dir,
                "method": m.method().name(),
                "mean_deg": e.mean_deg,
                "median_deg": e.median_deg,
                "below_5deg": e.below_5deg,
                "below_10deg": e.below_10deg,
                "below_20deg": e.below_20deg,
                "pixels": e.pixels,
                "unsolved": e.missing,
                "robust_fraction": recon.model.robust_fraction,
                "intensities_corrected_over_10pct": moved,
                "timings_s": { "load": load_s, "solve": recon.timings.solve },
            });
            if !recon.model.shadow_labels.is_empty() {
                row["shadow_labels"] = serde_json::to_value(&recon.model.shadow_labels)?;
            }
            if !recon.model.lobes.is_empty() {
                row["lobes"] = serde_json::to_value(&recon.model.lobes)?;
                row["timings_s"]["lobes"] = recon
                    .model
                    .lobes
                    .iter()
                    .map(|l| l.seconds)
                    .sum::<f64>()
                    .into();
            }
            rows.push(row);
        }
    }
    say!(
        "{}",
        serde_json::to_string_pretty(&serde_json::json!({ "results": rows }))?
    );
    Ok(())
}

/// A single-channel depth map (EXR channel Z or any single channel).
fn read_depth(path: &Path) -> Result<photostereo::grid::ScalarMap> {
    let img = photostereo::io::decode::read_image(path)?;
    anyhow::ensure!(
        img.channels == 1,
        "{}: a depth map needs one channel (Z), found {}",
        path.display(),
        img.channels
    );
    Ok(Grid::from_vec(img.width, img.height, img.data)?)
}

fn run_integrate(a: IntegrateArgs, progress: &dyn Progress) -> Result<()> {
    let inputs: Vec<&Path> = std::iter::once(a.normals.as_path())
        .chain(a.mask.as_deref())
        .chain(a.integration.camera.as_deref())
        .collect();
    for out in std::iter::once(&a.output).chain(a.ply.as_ref()) {
        photostereo::io::output::ensure_apart(out, &inputs)?;
    }
    if !a.force {
        photostereo::io::output::ensure_fresh_file(&a.output)?;
        if let Some(ply) = &a.ply {
            photostereo::io::output::ensure_fresh_file(ply)?;
        }
    }
    let normals = read_normal_map(&a.normals)?;
    let (w, h) = (normals.width(), normals.height());
    let mask = match &a.mask {
        Some(m) => {
            let m = photostereo::io::decode::read_mask(m)?;
            anyhow::ensure!(
                m.width() == w && m.height() == h,
                "mask {}x{} differs from the normal map's {w}x{h}",
                m.width(),
                m.height()
            );
            m
        }
        // Where the normal map holds a vector (not NaN or zero), less a uniform background.
        None => {
            let domain = photostereo::integrate::normal_domain(&normals);
            if domain.off_unit > 0 {
                eprintln!(
                    "warning: no --mask: {} of the {} pixels taken hold vectors that are not of unit length (read as their directions); if the map is a fit's g = ρn over the whole frame, its background is taken too: pass --mask to choose the pixels",
                    domain.off_unit,
                    domain.mask.count()
                );
            }
            if let Some(b) = domain.background {
                eprintln!(
                    "warning: no --mask: {} pixels with the border's normal ({:.3}, {:.3}, {:.3}) are taken as background and left out; pass --mask to choose the pixels",
                    domain.background_pixels, b[0], b[1], b[2]
                );
            } else if domain.mask.count() == w * h {
                eprintln!(
                    "warning: no --mask and every pixel has a normal: the whole image is integrated as one surface, background included; pass --mask to integrate the object alone"
                );
            }
            domain.mask
        }
    };
    let method = a
        .method
        .method()
        .context("--method none: nothing to integrate")?;
    let options = a.integration.options(method)?;
    let t = Instant::now();
    let r = integrate_normals(&normals, &mask, &options, progress)?;
    let secs = t.elapsed().as_secs_f64();
    let mut channels: Vec<(&str, &[f32])> =
        vec![("Z", r.depth.data()), ("residual", r.residual.data())];
    if let Some((wu, wv)) = &r.weights {
        channels.push(("wu", wu.data()));
        channels.push(("wv", wv.data()));
    }
    let units = photostereo::run::pipeline::exr_units("depth.exr", options.camera.as_ref());
    // `auto` names its choice.
    let used = match &r.auto {
        Some(d) => format!("auto ({})", d.chosen.name()),
        None => method.name().to_string(),
    };
    let attrs = [
        ("photostereo:integration", used.clone()),
        ("photostereo:units", units),
    ];
    photostereo::io::output::write_exr_file(
        &a.output,
        overwrite(a.force),
        (w, h),
        &channels,
        &attrs,
    )?;
    if let Some(ply) = &a.ply {
        let mesh = Mesh::from_depth(&r.depth, &normals, options.camera.as_ref())?;
        photostereo::io::output::write_bytes(ply, overwrite(a.force), &mesh.to_ply())?;
    }
    let mean_res = photostereo::stats::summarize(&r.residual).mean;
    say!(
        "{}: {} pixels, {} in {:.3} s{}; mean integration residual {:.3e}",
        used,
        mask.count(),
        if options.camera.is_some() {
            "perspective"
        } else {
            "orthographic"
        },
        secs,
        match (&r.solve, r.iterations) {
            (Some(s), it) if it > 0 => format!(
                " ({} reweighting iterations, final solve {})",
                it,
                s.method.name()
            ),
            (Some(s), _) if s.method == SolveMethod::Direct => " (direct solver)".to_string(),
            (Some(s), _) => format!(
                " ({}, {} iterations, {})",
                s.method.name(),
                s.iterations,
                s.convergence.describe()
            ),
            _ => String::new(),
        },
        mean_res
    );
    if let Some(d) = &r.auto {
        say!("  auto: {}", d.reason());
    }
    for w in photostereo::run::Warning::of_integration(&normals, &mask, &r) {
        eprintln!("warning: {}", printable(&w.to_string()));
    }
    say!(
        "  wrote {}{}",
        a.output.display(),
        a.ply
            .as_ref()
            .map(|p| format!(" and {}", p.display()))
            .unwrap_or_default()
    );
    Ok(())
}

fn print_summary(report: &Report, dir: &Path) {
    let i = &report.inputs;
    let c = &report.pixels;
    let config = &report.config;
    say!(
        "{} images {}x{}, method {}, integration {}",
        i.count,
        i.width,
        i.height,
        config.solve.method.name(),
        config.integration.map_or("none", |o| o.method.name())
    );
    say!(
        "  pixels: {} in mask, {} solved, {} filled, {} too few samples, {} ill-conditioned, {} dark",
        c.masked,
        c.solved,
        c.filled,
        c.too_few_samples,
        c.ill_conditioned,
        c.dark
    );
    let m = &report.model;
    if m.robust_pixels > 0 || m.recalibrated {
        let lobes: (usize, usize, f64) = m.lobes.iter().fold((0, 0, 0.0), |(a, r, t), l| {
            (a + l.applied, r + l.refitted, t + l.seconds)
        });
        say!(
            "  model: {:.1}% of solved pixels needed the robust fit{}{}",
            100.0 * m.robust_fraction,
            if lobes.1 > 0 {
                format!(
                    ", {:.1}% are explained by specular lobes ({} of {} refitted, in {:.2} s of the solve)",
                    100.0 * lobes.0 as f64 / c.solved.max(1) as f64,
                    lobes.0,
                    lobes.1,
                    lobes.2
                )
            } else {
                String::new()
            },
            match (m.recalibrated, m.gains_applied.iter().all(|&a| a)) {
                (true, true) =>
                    "; light intensities corrected from the data (gains in report.json)",
                (true, false) =>
                    "; light intensities estimated from the data but kept as stated (report.json)",
                (false, _) => "",
            }
        );
    }
    if let Some(n) = &report.near {
        say!(
            "  near lights: {} alternations of normals and depth{}; the largest part's geometric-mean depth {:.4} (the lights' units), from a start plane at {:.4}; the distant approximation would move the normals by {:.2}° on average (95th pct {:.2}°)",
            n.iterations,
            if n.converged {
                ", converged"
            } else {
                ", NOT converged"
            },
            n.distance,
            n.start_distance,
            n.distant_deviation_deg,
            n.distant_deviation_p95_deg
        );
    }
    // Under a camera the gradients are of log-depth, a thousand times smaller than pixel
    // slopes: four decimals would print zeros.
    let curl = |v: f64| {
        if v != 0.0 && v.abs() < 1e-3 {
            format!("{v:.2e}")
        } else {
            format!("{v:.4}")
        }
    };
    let perspective = config
        .integration
        .as_ref()
        .is_some_and(|o| o.camera.is_some());
    say!(
        "  integrability: mean |curl| {}, median {}, 95th pct {} ({})",
        curl(report.integrability.mean_abs_curl),
        curl(report.integrability.median_abs_curl),
        curl(report.integrability.p95_abs_curl),
        if perspective {
            "log-depth gradients, per pixel"
        } else {
            "per pixel"
        }
    );
    if let Some(a) = report.integration.as_ref().and_then(|i| i.auto.as_ref()) {
        say!("  integration: {}", a.reason);
        if let Some((h, budget)) = a.decision.held_back.zip(
            report
                .streaming
                .as_ref()
                .and_then(|p| p["max_memory"].as_u64()),
        ) {
            // Integration was allowed what the budget left beside the finishing stage.
            let enough = budget.saturating_sub(h.allowed) + h.needed;
            say!(
                "  (--max-memory {}M leaves the discontinuity-preserving integrator the {} MiB it needs{})",
                (enough >> 20) + 1,
                h.needed.div_ceil(1 << 20),
                if available_memory().is_some_and(|a| enough > a) {
                    ", more than the memory now available"
                } else {
                    ""
                }
            );
        }
    }
    let t = &report.timings_s;
    say!(
        "  time: load {:.3} s, solve {:.3} s, normals {:.3} s, integrate {:.3} s, write {:.3} s",
        t.load,
        t.solve,
        t.normals,
        t.integrate,
        t.write
    );
    say!("  wrote {} ({})", dir.display(), report.outputs.join(", "));
    for w in &report.warnings {
        eprintln!("warning: {}{}", printable(&w.to_string()), flag_hint(w));
    }
}

/// What the user can pass to act on a warning, in this tool's flags.
fn flag_hint(w: &photostereo::run::Warning) -> &'static str {
    use photostereo::run::Warning;
    match w {
        Warning::SrgbDecoded { .. } => " (pass --linear)",
        Warning::Unsolved { no_mask: true, .. } => "; pass --mask to solve the object only",
        Warning::Filled { .. } => " (--strict leaves them without a normal)",
        Warning::IntensitiesCorrected { .. } => " (--no-recalibrate keeps it as given)",
        Warning::PoorIntegrability { .. } => " (--integrate bilateral)",
        Warning::ShadowLight {
            level,
            ambient_subtracted: false,
            ..
        } if *level > 0.0 => " (--ambient FILE)",
        Warning::NearLights { .. } => {
            " (the near-light model needs every light's position, --camera K.txt and depth; --distant-lights turns it off)"
        }
        Warning::NearNotConverged { .. } => " (--near-iterations raises the cap)",
        Warning::LightsDisagree {
            positions: false, ..
        } => {
            " (`photostereo calibrate --from-object` recovers the lights from the images themselves)"
        }
        Warning::LightsDisagree {
            positions: true, ..
        } => " (`photostereo calibrate --ball-radius` places near lights from two mirror balls)",
        _ => "",
    }
}

/// The default memory policy: the cap is 2 GiB or half the available memory, whichever is
/// less; a run streamed by default gets the cap, or the least budget it can stream in when that
/// is more and within half the available memory.
#[cfg(test)]
mod tests {
    use super::*;

    const GIB: u64 = 1 << 30;

    #[test]
    fn the_default_budget_is_two_gib_or_half_the_available_memory() {
        assert_eq!(default_cap(None), 2 * GIB);
        assert_eq!(default_cap(Some(64 * GIB)), 2 * GIB);
        assert_eq!(default_cap(Some(3 * GIB)), 3 * GIB / 2);
        // Within the cap: the cap.
        assert_eq!(streaming_budget(2 * GIB, GIB, Some(64 * GIB)), 2 * GIB);
        // A run that cannot stream in the cap gets the least it needs, if available.
        let least = 2253 << 20;
        assert_eq!(streaming_budget(2 * GIB, least, Some(64 * GIB)), least);
        assert_eq!(streaming_budget(2 * GIB, least, None), least);
        // Beyond half the available memory: the cap, which the plan refuses with its remedies.
        assert_eq!(streaming_budget(2 * GIB, least, Some(4 * GIB)), 2 * GIB);
        assert_eq!(streaming_budget(GIB, least, Some(2 * GIB)), GIB);
    }
}
