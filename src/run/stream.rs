//! Out-of-core reconstruction: image stacks larger than memory, streamed in row bands.
//!
//! The Lambertian solve is per pixel, so the stack never has to be held whole. Every image is
//! opened once (`bands.rs`); a band of rows is decoded from all of them at once
//! (images in parallel), converted exactly as [`crate::capture::stack::load_stack`] converts whole
//! images, and solved, and the band's memory is reused for the next. Where the solved band
//! goes is the caller's choice: [`reconstruct_and_write_streamed`] writes its rows of every
//! per-pixel output file at once and keeps only what needs the whole image (normals, mask,
//! albedo and residuals: [`RESIDENT_BYTES_PER_PIXEL`]); [`reconstruct_streamed`] pastes it
//! into the full-size solution and returns that. Integration then runs on the assembled
//! field as in [`crate::run::pipeline`].
//!
//! What is estimated over the whole capture before pixels are fitted — each image's noise σ
//! and intensity gain ([`ImageModel`]) — is estimated once from a sample of row blocks spread
//! over the mask (a first pass), so every band is fitted under the same model. Methods that
//! need no such model take one pass.
//!
//! The band height comes from a memory budget ([`StreamOptions::max_memory`]): the resident
//! maps are taken off first, the rest holds the band (with, when writing, its rows in flight to
//! the writers). A written run's finishing stage (integration) comes after the bands and must
//! fit in the budget on its own. The plan is reported ([`StreamPlan`]).

use crate::capture::dataset::CaptureFiles;
use crate::capture::lights::{Lights, MAX_LIGHT_CONDITION};
use crate::capture::stack::{
    ColorMode, Convert, ImageInfo, ImageStack, LoadOptions, convert_into, srgb_lut,
    subtract_ambient,
};
use crate::error::{Error, Result};
use crate::grid::{Grid, Mask, Window};
use crate::integrate::Integrator;
use crate::io::bands::BandReader;
use crate::io::decode::read_mask;
use crate::io::output::OutputDir;
use crate::progress::Progress;
use crate::ps::solve::ImageModel;
use crate::run::band_output::BandOutput;
use crate::run::bands::{Assemble, Band, BandSink, BandSource, Setup, shared_normal, solve_bands};
use crate::run::pipeline::{
    Config, Described, InputFacts, InputSummary, Reconstruction, Report, RunSummary, Timings,
    assemble, commit_with_report, exr_attributes, finish, integrability_of, model_summary,
};
use crate::run::warnings::warnings;
use rayon::prelude::*;
use serde::Serialize;
use std::borrow::Cow;
use std::path::Path;
use std::time::Instant;

/// Bytes per image pixel held for the whole of a run that writes its outputs band by band
/// ([`reconstruct_and_write_streamed`]), besides the integrator, one colour channel. While the
/// bands run: the normals (12 B) and the solved mask (1 B) for integration, the albedo (4 B)
/// for the scaling of `albedo.png` and the finite residuals (4 B, then 8 B sorted) for their
/// median: 29 B. After them, with the albedo and residuals freed: the normals and mask, and
/// the gradients, curl and sorted |curl| of the integrability check (20 B): 33 B. The larger,
/// with 10% added; `bench stream` measures the peak.
pub const RESIDENT_BYTES_PER_PIXEL: u64 = 36;
/// Bytes per image pixel for each further colour channel of a written run (its albedo).
pub const RESIDENT_BYTES_PER_EXTRA_CHANNEL: u64 = 4;
/// Bytes per image pixel held by [`reconstruct_streamed`], which assembles the whole solution
/// (g, residual, samples, condition, status, robust flag: 24 B per channel), the maps derived
/// from it (albedo, normals, curl, summaries) and the output buffers staged while writing.
/// Measured: 79 B per pixel at the peak of a streamed 4000×3000 run without integration
/// (970 MB); 10% is added.
pub const ASSEMBLED_BYTES_PER_PIXEL: u64 = 88;
/// Bytes per image pixel for each further colour channel of an assembled run (solution and
/// albedo).
pub const ASSEMBLED_BYTES_PER_EXTRA_CHANNEL: u64 = 32;
/// Bands of file rows that may be in flight to each writer besides the one being made: the
/// one a writer is encoding and the one queued for it.
const OUTPUT_QUEUE_BANDS: u64 = 2;
/// Bytes per pixel of a band row while the outputs are written band by band, one colour
/// channel: the band's per-pixel maps (29 B) and its file rows (36 B) being made, and
/// [`OUTPUT_QUEUE_BANDS`] more bands of file rows in flight.
const OUTPUT_ROW_BYTES_PER_PIXEL: u64 = 29 + 36 * (1 + OUTPUT_QUEUE_BANDS);
/// Bytes the process needs whatever the image size (code, thread stacks, allocator slack).
pub const BASE_BYTES: u64 = 64 << 20;
/// Rows per sampled block of the model pass: neighbouring rows are needed by the noise
/// estimate.
pub const SAMPLE_BLOCK_ROWS: usize = 4;
/// Most rows the model pass samples (in [`SAMPLE_BLOCK_ROWS`] blocks spread over the mask).
pub const MAX_SAMPLE_ROWS: usize = 96;
/// Fewest rows a band may have: a budget that leaves less is refused.
pub const MIN_BAND_ROWS: usize = 4;

/// How to stream.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct StreamOptions {
    /// Memory budget of the whole run in bytes (resident maps, integration and one band),
    /// counted as the maps each stage holds; with glibc, a process holds freed maps beyond
    /// that unless [`return_freed_maps_promptly`] was called.
    pub max_memory: u64,
    /// Rows per band; `None`: as many as the budget allows.
    pub band_rows: Option<usize>,
}

/// How a streamed run uses memory: reported with the run.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct StreamPlan {
    /// Image width and height.
    pub width: usize,
    /// Image height.
    pub height: usize,
    /// Images.
    pub count: usize,
    /// Channels solved (1 grey, 3 per channel).
    pub channels: usize,
    /// The rows and columns read: the mask's bounding box.
    pub window: Window,
    /// Rows per band.
    pub band_rows: usize,
    /// Bands.
    pub bands: usize,
    /// Bytes one band's stack takes.
    pub band_bytes: u64,
    /// Bytes held while the bands run, besides the band: the resident maps.
    pub resident_bytes: u64,
    /// Bytes held while the run finishes after the bands (their memory freed): the normals and
    /// the integrator's working memory (0 for a run that integrates nothing here).
    pub finish_bytes: u64,
    /// Bytes the whole stack would take in memory ([`crate::capture::stack::ImageStack`], f32).
    pub in_memory_stack_bytes: u64,
    /// Rows sampled by the model pass (0: the method needs no model pass).
    pub sample_rows: usize,
    /// The budget.
    pub max_memory: u64,
}

/// Bytes a run that holds everything at once needs besides its stack, on a `width`×`height`
/// image with `channels` solved channels and `masked` pixels in the mask spanning `window`:
/// the resident maps of a written run plus the integrator's working memory (its
/// [`Integrator::working_bytes`]; `auto` as the bilateral integrator it may run). A streamed
/// run needs less: its integration comes after the bands ([`StreamPlan::finish_bytes`]).
pub fn resident_bytes(
    width: usize,
    height: usize,
    channels: usize,
    masked: usize,
    window: Window,
    config: &Config,
) -> u64 {
    resident_for(
        Keep::Written,
        width,
        height,
        channels,
        (masked, window),
        config,
    )
}

/// The resident maps of a run that keeps `keep`, without integration.
fn maps_bytes(keep: Keep, width: usize, height: usize, channels: usize) -> u64 {
    let pixels = (width * height) as u64;
    let (base, extra) = match keep {
        Keep::Written => (RESIDENT_BYTES_PER_PIXEL, RESIDENT_BYTES_PER_EXTRA_CHANNEL),
        Keep::Assembled => (ASSEMBLED_BYTES_PER_PIXEL, ASSEMBLED_BYTES_PER_EXTRA_CHANNEL),
    };
    BASE_BYTES + (base + extra * (channels.saturating_sub(1) as u64)) * pixels
}

/// [`maps_bytes`] plus the integrator's working memory on the mask (`masked` pixels spanning
/// `window`); `auto` is counted as the bilateral integrator it may run (no cap applies).
fn resident_for(
    keep: Keep,
    width: usize,
    height: usize,
    channels: usize,
    (masked, window): (usize, Window),
    config: &Config,
) -> u64 {
    let integration = config.integration.as_ref().map_or(0, |o| {
        o.method
            .working_bytes(width, height, masked, window, o.solver)
    });
    maps_bytes(keep, width, height, channels) + integration
}

/// The integrator's working memory in a written streamed run, where integration is capped
/// ([`capped`]): `auto` then keeps masked least squares where bilateral integration would not
/// fit, so it needs the larger of its decision (the gradients, 8 B, the normal factor, 8 B, and
/// the domain, 1 B, a pixel; over the cells of the mask's window, the cropped gradients and
/// domain, 9 B, the loops' edge differences, 16 B, and their circulations for the median, 8 B)
/// and masked least squares.
fn capped_integration_bytes(
    width: usize,
    height: usize,
    (masked, window): (usize, Window),
    config: &Config,
) -> u64 {
    config.integration.as_ref().map_or(0, |o| match o.method {
        Integrator::Auto => {
            let decision = 17 * (width * height) as u64 + 33 * window.len() as u64;
            decision
                .max(Integrator::MaskedLs.working_bytes(width, height, masked, window, o.solver))
        }
        m => m.working_bytes(width, height, masked, window, o.solver),
    })
}

/// Smallest block, in bytes, that [`return_freed_maps_promptly`] has the allocator take from
/// and give back to the system directly: a 512×512 map of `f32`. Every per-pixel map of a
/// capture large enough to be streamed is far above it, the per-thread scratch of rows and
/// pixel blocks below it.
pub const DIRECT_BLOCK_BYTES: usize = 1 << 20;

/// Has the C allocator (glibc) give every block of [`DIRECT_BLOCK_BYTES`] or more back to the
/// system as soon as it is freed, for the rest of the process; elsewhere it does nothing and
/// the allocator's own policy applies. Returns whether the allocator took the setting. Call it
/// before a streamed run whose budget must hold, while no other thread is allocating (glibc's
/// `mallopt` changes parameters its other calls read unlocked), as the `photostereo` command
/// does; it changes the whole process's allocator.
///
/// Why: a streamed run's budget ([`StreamOptions::max_memory`]) counts the maps a stage holds.
/// By default glibc raises its mmap threshold to the size of each large block freed (up to
/// 32 MiB), after which freed maps of a few MiB stay in its heap and are reused only by blocks
/// that fit them, so the process's resident memory follows what it once held. Measured on 48
/// images of 1732×1732 under a 256 MiB budget: a peak of 189–240 MiB from run to run without
/// this (freed memory is handed back between stages only), 170 MiB with it. The price is fresh
/// pages for every large block: 5–10% more time there, 1–4% on 48 images of 5000×5000
/// (`docs/inputs-and-outputs.md`).
pub fn return_freed_maps_promptly() -> bool {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        const _: () = assert!(DIRECT_BLOCK_BYTES <= libc::c_int::MAX as usize);
        // SAFETY: mallopt only sets an allocator parameter; it takes no pointers. The caller
        // runs it while no other thread allocates (see above). A fixed threshold also turns off
        // glibc's adjustment of it, which is the point.
        #[allow(unsafe_code)]
        let taken =
            unsafe { libc::mallopt(libc::M_MMAP_THRESHOLD, DIRECT_BLOCK_BYTES as libc::c_int) };
        taken == 1
    }
    #[cfg(not(all(target_os = "linux", target_env = "gnu")))]
    false
}

/// Hands the memory freed so far back to the system before a stage whose budget assumes it is
/// gone: glibc keeps freed blocks below its mmap threshold in its arenas, one per thread, which
/// measured 116 MiB more than the maps held after the bands of 48 images of 1732×1732
/// (`malloc_trim`; elsewhere the allocator's own policy applies).
fn release_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        // SAFETY: malloc_trim only returns free heap memory to the system; it takes no
        // pointers and is safe to call at any time from any thread.
        #[allow(unsafe_code)]
        unsafe {
            libc::malloc_trim(0);
        }
    }
}

/// Bytes per image pixel held while a written run finishes after the bands, besides
/// [`BASE_BYTES`] and the integrator: the normals (12 B), the solved mask and the mask read
/// (1 B each) and the curl (4 B), written beside the integration; 18 B, with 10% added.
/// Measured on 48 images of 1732×1732 with freed maps returned
/// ([`return_freed_maps_promptly`]): 62 MiB resident as integration starts (without it,
/// 112 MiB), of which these 18 B a pixel are 51 MiB and the process's own code, stacks and
/// small allocations the rest.
pub const FINISH_BYTES_PER_PIXEL: u64 = 20;

/// The two phases of a run that keeps `keep`, in bytes: while the bands run (the resident
/// maps, without the band itself) and while it finishes (a written run's integration, which
/// starts after the bands have freed their memory; 0 for an assembled run, which integrates
/// nothing). What each phase holds is described at [`RESIDENT_BYTES_PER_PIXEL`] and
/// [`FINISH_BYTES_PER_PIXEL`].
fn phases(
    keep: Keep,
    width: usize,
    height: usize,
    channels: usize,
    domain: (usize, Window),
    config: &Config,
) -> (u64, u64) {
    match keep {
        Keep::Written => (
            maps_bytes(keep, width, height, channels),
            BASE_BYTES
                + FINISH_BYTES_PER_PIXEL * (width * height) as u64
                + capped_integration_bytes(width, height, domain, config),
        ),
        Keep::Assembled => (
            resident_for(keep, width, height, channels, domain, config),
            0,
        ),
    }
}

/// `config` with integration capped at what the budget leaves beside what the finishing stage
/// holds, so that `auto` keeps masked least squares where bilateral integration would not fit.
fn capped(config: &Config, options: &StreamOptions, plan: &StreamPlan) -> Config {
    let mut config = *config;
    if let Some(o) = config.integration.as_mut() {
        let held = BASE_BYTES + FINISH_BYTES_PER_PIXEL * (plan.width * plan.height) as u64;
        let left = options.max_memory.saturating_sub(held);
        o.max_memory = Some(o.max_memory.map_or(left, |m| m.min(left)));
    }
    config
}

/// Parses a memory size: bytes, or a number with K, M, G or T (powers of 1024; a trailing
/// `B` or `iB` is allowed), e.g. `2G`, `1536MiB`, `750M`.
///
/// # Errors
/// [`Error::InvalidParameter`] naming `max-memory` for anything else.
pub fn parse_size(text: &str) -> Result<u64> {
    let t = text.trim();
    let upper = t.to_ascii_uppercase();
    let body = upper
        .strip_suffix("IB")
        .or_else(|| upper.strip_suffix('B'))
        .unwrap_or(&upper);
    let (number, shift) = match body.chars().last() {
        Some('K') => (&body[..body.len() - 1], 10),
        Some('M') => (&body[..body.len() - 1], 20),
        Some('G') => (&body[..body.len() - 1], 30),
        Some('T') => (&body[..body.len() - 1], 40),
        _ => (body, 0),
    };
    let value: f64 = number.trim().parse().map_err(|_| {
        Error::param(
            "max-memory",
            format!("{text:?} is not a size (e.g. 2G, 1536M, 500000000)"),
        )
    })?;
    if !(value.is_finite() && value > 0.0) {
        return Err(Error::param("max-memory", format!("{text:?} must be > 0")));
    }
    Ok((value * (1u64 << shift) as f64) as u64)
}

/// The opened images of a capture, checked against each other.
struct Opened {
    readers: Vec<BandReader>,
    /// The ambient image's reader, when one is subtracted.
    ambient: Option<BandReader>,
    width: usize,
    height: usize,
    /// Channels solved.
    channels: usize,
    mask: Mask,
    window: Window,
}

fn open_all(
    files: &CaptureFiles,
    load: &LoadOptions,
    floor: &dyn Fn(usize, usize, usize) -> Result<()>,
) -> Result<Opened> {
    if files.images.len() != files.lights.len() {
        return Err(Error::LightsMismatch {
            reason: format!(
                "{} images for {} lights",
                files.images.len(),
                files.lights.len()
            ),
        });
    }
    if files.images.is_empty() {
        return Err(Error::TooFewImages { count: 0 });
    }
    let readers: Vec<BandReader> = files
        .images
        .par_iter()
        .map(|p| BandReader::open(p))
        .collect::<Result<_>>()?;
    let (width, height) = readers[0].size();
    let first_channels = readers[0].channels();
    for (index, (r, path)) in readers.iter().zip(&files.images).enumerate() {
        let (w, h) = r.size();
        if (w, h) != (width, height) {
            return Err(Error::SizeMismatch {
                path: path.clone(),
                index,
                width,
                height,
                found_width: w,
                found_height: h,
            });
        }
        if r.channels() != first_channels {
            return Err(Error::BadImage {
                path: path.clone(),
                index,
                reason: format!(
                    "it has {} colour channel(s) but image 0 ({}) has {first_channels}; all images must be grey or all RGB",
                    r.channels(),
                    files.images[0].display()
                ),
            });
        }
    }
    let channels = match load.color {
        ColorMode::Grey => 1,
        ColorMode::PerChannel => {
            if first_channels != 3 {
                return Err(Error::UnsupportedImage {
                    path: files.images[0].clone(),
                    reason: format!(
                        "image 0 has {first_channels} channel(s); a per-channel solve needs RGB images"
                    ),
                });
            }
            3
        }
    };
    // The budget is checked on the declared size before the mask (a byte a pixel) is
    // allocated.
    floor(width, height, channels)?;
    let mask = match &files.mask_source {
        Some(path) => {
            let m = read_mask(path)?;
            if (m.width(), m.height()) != (width, height) {
                return Err(Error::Mask {
                    path: path.clone(),
                    reason: format!(
                        "size {}x{} differs from the images' {width}x{height}",
                        m.width(),
                        m.height()
                    ),
                });
            }
            m
        }
        None => Grid::new(width, height, true),
    };
    let window = mask
        .bounding_box()
        .unwrap_or(Window::full(width, height))
        .clamp(width, height);
    let ambient = open_ambient(files, width, height)?;
    Ok(Opened {
        readers,
        ambient,
        width,
        height,
        channels,
        mask,
        window,
    })
}

/// The error of a budget that cannot hold `what` of a `size` image (`resident` bytes: the
/// resident maps, or the finishing stage with integration) plus, where known, a band of [`MIN_BAND_ROWS`] rows of `count` images (`row_bytes` a
/// row). Besides raising the budget it suggests only what would fit (`fits` tells whether a
/// run with another configuration would): Poisson integration, or none.
fn over_budget(
    options: &StreamOptions,
    config: &Config,
    (width, height): (usize, usize),
    (what, resident): (&str, u64),
    band: Option<(u64, usize)>,
    fits: &dyn Fn(&Config) -> bool,
) -> Error {
    let mut remedies = vec!["raise it"];
    if let Some(o) = config.integration
        && o.method != Integrator::Poisson
    {
        let poisson = Config {
            integration: Some(crate::integrate::IntegrationOptions {
                method: Integrator::Poisson,
                ..o
            }),
            ..*config
        };
        if fits(&poisson) {
            remedies.push("integrate with a method that needs less memory (Poisson)");
        }
    }
    if config.integration.is_some()
        && fits(&Config {
            integration: None,
            ..*config
        })
    {
        remedies.push("leave out integration");
    }
    let last = remedies.pop().unwrap_or("raise it");
    let remedy = if remedies.is_empty() {
        last.to_string()
    } else {
        format!("{}, or {last}", remedies.join(", "))
    };
    Error::param(
        "max-memory",
        format!(
            "{} MiB cannot hold {what} of a {width}x{height} image ({} MiB){}; {remedy}",
            options.max_memory >> 20,
            resident >> 20,
            match band {
                Some((row_bytes, count)) => format!(
                    " plus a band of {MIN_BAND_ROWS} rows of {count} images ({} MiB)",
                    (row_bytes * MIN_BAND_ROWS as u64) >> 20
                ),
                None => String::new(),
            },
        ),
    )
}

/// The check [`open_all`] makes on the declared size before allocating the mask: the
/// resident maps with no pixel masked, the least a run of that size can need, within the
/// budget.
fn budget_floor<'a>(
    config: &'a Config,
    options: &'a StreamOptions,
    keep: Keep,
) -> impl Fn(usize, usize, usize) -> Result<()> + 'a {
    move |width, height, channels| {
        let none = Window {
            x0: 0,
            y0: 0,
            x1: 0,
            y1: 0,
        };
        let need = |c: &Config| {
            let (bands, finish) = phases(keep, width, height, channels, (0, none), c);
            bands.max(finish)
        };
        let resident = need(config);
        if resident > options.max_memory {
            let what = if config.integration.is_some() {
                "the outputs and integration"
            } else {
                "the outputs"
            };
            return Err(over_budget(
                options,
                config,
                (width, height),
                (what, resident),
                None,
                &|c| need(c) <= options.max_memory,
            ));
        }
        Ok(())
    }
}

/// Plans a streamed run of `files` that writes its outputs band by band
/// ([`reconstruct_and_write_streamed`]): band height and memory use.
///
/// # Errors
/// The errors of opening the images and the mask (sizes, formats); [`Error::InvalidParameter`]
/// naming `max-memory` when the budget cannot hold the resident maps and a band of
/// [`MIN_BAND_ROWS`] rows.
pub fn plan(
    files: &CaptureFiles,
    load: &LoadOptions,
    config: &Config,
    options: &StreamOptions,
) -> Result<StreamPlan> {
    let opened = open_all(files, load, &budget_floor(config, options, Keep::Written))?;
    plan_for(&opened, files.images.len(), config, options, Keep::Written)
}

fn plan_for(
    o: &Opened,
    count: usize,
    config: &Config,
    options: &StreamOptions,
    keep: Keep,
) -> Result<StreamPlan> {
    let win = o.window;
    let phases_of = |c: &Config| {
        phases(
            keep,
            o.width,
            o.height,
            o.channels,
            (o.mask.count(), win),
            c,
        )
    };
    let (resident, finish) = phases_of(config);
    // One band row: the stack row (f32 per image and channel), saturation flags, the band's
    // solution, the rows being decoded (at most one image per thread at a time, 16 bytes a
    // pixel covers RGBA float) and, when the outputs are written band by band, the band's
    // maps and file rows in flight to the writers.
    let threads = rayon::current_num_threads() as u64;
    let outputs = match keep {
        Keep::Written => {
            OUTPUT_ROW_BYTES_PER_PIXEL + 4 * (OUTPUT_QUEUE_BANDS + 1) * (o.channels as u64 - 1)
        }
        Keep::Assembled => 0,
    };
    // An ambient image's rows are decoded once a band and converted for each image being
    // converted (its planes and flags, one per thread).
    let ambient = if o.ambient.is_some() {
        o.width as u64 * 16
            + threads
                * (o.channels as u64 * win.width() as u64 * 4 + (o.width as u64).div_ceil(64) * 8)
    } else {
        0
    };
    let row_bytes = count as u64 * o.channels as u64 * win.width() as u64 * 4
        + count as u64 * (o.width as u64).div_ceil(64) * 8
        + 24 * o.channels as u64 * o.width as u64
        + threads * o.width as u64 * 16
        + outputs * o.width as u64
        + ambient;
    let in_memory = count as u64 * o.channels as u64 * win.len() as u64 * 4;
    let fits = |c: &Config| {
        let (bands, finish) = phases_of(c);
        bands + MIN_BAND_ROWS as u64 * row_bytes <= options.max_memory
            && finish <= options.max_memory
    };
    if finish > options.max_memory {
        return Err(over_budget(
            options,
            config,
            (o.width, o.height),
            (
                if config.integration.is_some() {
                    "the normals and integration"
                } else {
                    "the normals"
                },
                finish,
            ),
            None,
            &fits,
        ));
    }
    let available = options.max_memory.saturating_sub(resident);
    let fit = (available / row_bytes.max(1)) as usize;
    if fit < MIN_BAND_ROWS {
        return Err(over_budget(
            options,
            config,
            (o.width, o.height),
            ("the outputs", resident),
            Some((row_bytes, count)),
            &fits,
        ));
    }
    let rows = win.height().max(1);
    let band_rows = match options.band_rows {
        Some(0) => return Err(Error::param("band-rows", "must be at least 1")),
        Some(b) => b.min(rows),
        None => fit.min(rows),
    };
    let needs_model = ImageModel::needed(&config.solve, count);
    let sample_rows = if needs_model {
        let cap = (fit.min(MAX_SAMPLE_ROWS) / SAMPLE_BLOCK_ROWS).max(1) * SAMPLE_BLOCK_ROWS;
        cap.min(rows)
    } else {
        0
    };
    Ok(StreamPlan {
        width: o.width,
        height: o.height,
        count,
        channels: o.channels,
        window: win,
        band_rows,
        bands: rows.div_ceil(band_rows),
        band_bytes: row_bytes * band_rows as u64,
        resident_bytes: resident,
        finish_bytes: finish,
        in_memory_stack_bytes: in_memory,
        sample_rows,
        max_memory: options.max_memory,
    })
}

/// Per image, what the bands found: summed over bands.
#[derive(Clone)]
struct Tally {
    info: Option<ImageInfo>,
    lit: bool,
    saturated: usize,
    non_finite: usize,
    pixels: usize,
}

/// The reader of `files`' ambient image, checked against the images' size, when there is one.
fn open_ambient(files: &CaptureFiles, width: usize, height: usize) -> Result<Option<BandReader>> {
    let Some(path) = &files.ambient_source else {
        return Ok(None);
    };
    let reader = BandReader::open(path)?;
    crate::capture::stack::check_ambient_size(path, reader.size(), (width, height))?;
    Ok(Some(reader))
}

/// Decodes rows `rows` of every image into a band stack (`window`'s columns only), less the
/// same rows of the ambient image when `ambient` reads one.
#[allow(clippy::too_many_arguments)]
fn read_band(
    readers: &mut [BandReader],
    ambient: Option<&mut BandReader>,
    files: &CaptureFiles,
    load: &LoadOptions,
    channels: usize,
    window: Window,
    rows: std::ops::Range<usize>,
    lut: &[f32; 256],
) -> Result<(ImageStack, Vec<ImageInfo>)> {
    let width = readers.first().map_or(0, |r| r.size().0);
    let band = Window {
        x0: window.x0,
        x1: window.x1,
        y0: 0,
        y1: rows.len(),
    };
    let n = band.len();
    let ambient = match (ambient, &files.ambient_source) {
        (Some(reader), Some(path)) => Some((path, reader.read(rows.clone())?)),
        _ => None,
    };
    let mut data = crate::buffer::zeroed_f32(readers.len() * channels * n);
    let results: Vec<Result<(Option<Vec<u64>>, ImageInfo)>> = data
        .par_chunks_mut(channels * n)
        .zip(readers.par_iter_mut())
        .enumerate()
        .map(|(index, (out, reader))| {
            let path = &files.images[index];
            let raw = reader.read(rows.clone())?;
            let cv = Convert::new(load, &files.lights, index, lut);
            let mut r = convert_into(&raw, &cv, out, path, band);
            if let Some((apath, araw)) = &ambient {
                subtract_ambient(araw, apath, &raw, &cv, out, band, &mut r)?;
            }
            Ok(r)
        })
        .collect();
    let mut saturated = Vec::with_capacity(readers.len());
    let mut info = Vec::with_capacity(readers.len());
    for r in results {
        let (s, i) = r?;
        saturated.push(s);
        info.push(i);
    }
    let stack = ImageStack::from_parts(
        width,
        rows.len(),
        channels,
        data,
        saturated,
        info.clone(),
        band,
    );
    Ok((stack, info))
}

/// The mask rows `rows`, as a band mask.
fn mask_rows(mask: &Mask, rows: std::ops::Range<usize>) -> Mask {
    let w = mask.width();
    let mut band = Grid::new(w, rows.len(), false);
    band.data_mut()
        .copy_from_slice(&mask.data()[rows.start * w..rows.end * w]);
    band
}

/// The model pass: per channel, noise and gains estimated from `plan.sample_rows` rows in
/// blocks spread evenly over the window (for the shared-normal colour solve, one model from
/// the grey mix).
fn estimate_models(
    files: &CaptureFiles,
    load: &LoadOptions,
    config: &Config,
    o: &Opened,
    plan: &StreamPlan,
    lut: &[f32; 256],
) -> Result<Vec<ImageModel>> {
    let count = files.images.len();
    let solved_channels = if shared_normal(o.channels, config) {
        1
    } else {
        o.channels
    };
    if plan.sample_rows == 0 {
        return Ok(vec![ImageModel::unit(count); solved_channels]);
    }
    let win = o.window;
    let blocks = (plan.sample_rows / SAMPLE_BLOCK_ROWS).max(1);
    let span = win.height();
    let mut starts: Vec<usize> = (0..blocks)
        .map(|b| {
            let centre = win.y0 + (2 * b + 1) * span / (2 * blocks);
            centre
                .saturating_sub(SAMPLE_BLOCK_ROWS / 2)
                .clamp(win.y0, win.y1.saturating_sub(SAMPLE_BLOCK_ROWS).max(win.y0))
        })
        .collect();
    starts.dedup();
    // Fresh readers: the pass reads top to bottom and the band pass starts again at the top.
    let mut readers: Vec<BandReader> = files
        .images
        .par_iter()
        .map(|p| BandReader::open(p))
        .collect::<Result<_>>()?;
    let mut ambient = open_ambient(files, o.width, o.height)?;
    let mut parts: Vec<(ImageStack, Mask)> = Vec::new();
    let mut last_end = 0;
    for s in starts {
        let s = s.max(last_end);
        let e = (s + SAMPLE_BLOCK_ROWS).min(win.y1);
        if e <= s {
            continue;
        }
        last_end = e;
        let (stack, _) = read_band(
            &mut readers,
            ambient.as_mut(),
            files,
            load,
            o.channels,
            win,
            s..e,
            lut,
        )?;
        parts.push((stack, mask_rows(&o.mask, s..e)));
    }
    drop(readers);
    drop(ambient);
    let (stack, mask) = stack_rows(parts, o.channels)?;
    if solved_channels == 1 && o.channels == 3 {
        let grey = stack.grey_mix();
        return Ok(vec![ImageModel::estimate(
            &grey,
            0,
            &files.lights,
            &mask,
            &crate::run::bands::shared_model_options(&config.solve),
        )?]);
    }
    (0..o.channels)
        .map(|c| ImageModel::estimate(&stack, c, &files.lights, &mask, &config.solve))
        .collect()
}

/// Stacks band stacks of equal width on top of each other.
fn stack_rows(parts: Vec<(ImageStack, Mask)>, channels: usize) -> Result<(ImageStack, Mask)> {
    let Some((first, _)) = parts.first() else {
        return Err(Error::param("sample", "no rows were sampled"));
    };
    let (width, count, window) = (first.width(), first.count(), first.window());
    let info = first.info().to_vec();
    let height: usize = parts.iter().map(|(s, _)| s.height()).sum();
    let ww = window.width();
    let n = ww * height;
    let mut data = crate::buffer::zeroed_f32(count * channels * n);
    let mut sat: Vec<Vec<u64>> = vec![vec![0u64; (width * height).div_ceil(64)]; count];
    let mut any_sat = vec![false; count];
    let mut mask = Grid::new(width, height, false);
    let mut y = 0;
    for (s, m) in &parts {
        let (h, pn) = (s.height(), s.window().len());
        for k in 0..count {
            for c in 0..channels {
                let dst = (k * channels + c) * n + y * ww;
                data[dst..dst + pn].copy_from_slice(s.plane(k, c));
            }
            if s.saturation_bits(k).is_some() {
                any_sat[k] = true;
                for p in 0..width * h {
                    if s.is_saturated(k, p) {
                        let q = y * width + p;
                        sat[k][q >> 6] |= 1 << (q & 63);
                    }
                }
            }
        }
        mask.data_mut()[y * width..(y + h) * width].copy_from_slice(m.data());
        y += h;
    }
    let saturated = sat
        .into_iter()
        .zip(any_sat)
        .map(|(b, any)| any.then_some(b))
        .collect();
    let win = Window {
        x0: window.x0,
        x1: window.x1,
        y0: 0,
        y1: height,
    };
    Ok((
        ImageStack::from_parts(width, height, channels, data, saturated, info, win),
        mask,
    ))
}

/// The source of a streamed run: every image opened once, the model estimated from sampled
/// row blocks, then bands decoded from all images at once; what each image held is tallied
/// over the bands.
struct FileBands<'a> {
    files: &'a CaptureFiles,
    load: &'a LoadOptions,
    opened: Opened,
    plan: StreamPlan,
    lut: [f32; 256],
    /// The next band's first row.
    next: usize,
    /// The band being solved.
    band: Option<(ImageStack, Mask)>,
    tally: Vec<Tally>,
    /// Seconds decoding, model pass included.
    read_s: f64,
}

impl<'a> FileBands<'a> {
    /// Opens every image and plans the run within `options`' budget.
    fn open(
        files: &'a CaptureFiles,
        load: &'a LoadOptions,
        config: &Config,
        options: &StreamOptions,
        keep: Keep,
    ) -> Result<Self> {
        files.lights.check_usable(MAX_LIGHT_CONDITION)?;
        config.solve.validate()?;
        let opened = open_all(files, load, &budget_floor(config, options, keep))?;
        let plan = plan_for(&opened, files.images.len(), config, options, keep)?;
        let next = opened.window.y0;
        Ok(FileBands {
            files,
            load,
            opened,
            plan,
            lut: srgb_lut(),
            next,
            band: None,
            tally: vec![
                Tally {
                    info: None,
                    lit: false,
                    saturated: 0,
                    non_finite: 0,
                    pixels: 0,
                };
                files.images.len()
            ],
            read_s: 0.0,
        })
    }

    /// Per image, what the bands held; [`Error::BadImage`] for an image that is dark
    /// everywhere in the mask's rows or saturated everywhere.
    fn finish(self) -> Result<(StreamPlan, Vec<ImageInfo>, InputSummary, f64)> {
        let files = self.files;
        let mut info = Vec::with_capacity(self.tally.len());
        for (index, t) in self.tally.into_iter().enumerate() {
            let path = &files.images[index];
            if !t.lit {
                return Err(Error::BadImage {
                    path: path.clone(),
                    index,
                    reason: "the image is entirely dark in the rows the mask spans: no sample above 0, so it says nothing about the shape; check the exposure, or remove it and its light".into(),
                });
            }
            if t.saturated >= t.pixels {
                return Err(Error::BadImage {
                    path: path.clone(),
                    index,
                    reason: "every pixel is saturated in the rows the mask spans; lower the exposure, or remove the image and its light".into(),
                });
            }
            let mut i = t
                .info
                .ok_or_else(|| Error::param("bands", "no band was read"))?;
            i.saturated = t.saturated;
            i.non_finite = t.non_finite;
            info.push(i);
        }
        let mut summary = InputSummary::of_files(
            &files.images,
            &files.lights,
            files.lights_source.as_deref(),
            files.mask_source.as_deref(),
            &info,
        );
        summary.width = self.opened.width;
        summary.height = self.opened.height;
        summary.color = self.load.color;
        summary.ambient.clone_from(&files.ambient_source);
        Ok((self.plan, info, summary, self.read_s))
    }
}

impl BandSource for FileBands<'_> {
    fn size(&self) -> (usize, usize) {
        (self.opened.width, self.opened.height)
    }

    fn channels(&self) -> usize {
        self.opened.channels
    }

    fn band_rows(&self) -> usize {
        self.plan.band_rows
    }

    fn bands(&self) -> usize {
        self.plan.bands
    }

    fn models(&mut self, _lights: &Lights, config: &Config) -> Result<Vec<ImageModel>> {
        let t = Instant::now();
        let models = estimate_models(
            self.files,
            self.load,
            config,
            &self.opened,
            &self.plan,
            &self.lut,
        );
        self.read_s += t.elapsed().as_secs_f64();
        models
    }

    fn next_band(&mut self) -> Result<Option<Band<'_>>> {
        self.band = None;
        let win = self.opened.window;
        let y = self.next;
        if y >= win.y1 {
            for r in self
                .opened
                .readers
                .iter_mut()
                .chain(&mut self.opened.ambient)
            {
                r.verify_rest()?;
            }
            return Ok(None);
        }
        let e = (y + self.plan.band_rows).min(win.y1);
        let t = Instant::now();
        let o = &mut self.opened;
        let (stack, info) = read_band(
            &mut o.readers,
            o.ambient.as_mut(),
            self.files,
            self.load,
            o.channels,
            win,
            y..e,
            &self.lut,
        )?;
        for (k, (tl, i)) in self.tally.iter_mut().zip(info).enumerate() {
            tl.lit |= (0..o.channels).any(|c| stack.plane(k, c).iter().any(|v| *v > 0.0));
            tl.saturated += i.saturated;
            tl.non_finite += i.non_finite;
            tl.pixels += stack.window().len();
            tl.info.get_or_insert(i);
        }
        let mask = mask_rows(&o.mask, y..e);
        self.read_s += t.elapsed().as_secs_f64();
        self.next = e;
        let (stack, mask) = self.band.insert((stack, mask));
        Ok(Some(Band {
            y0: y,
            stack: Cow::Borrowed(stack),
            mask: Cow::Borrowed(mask),
            grey: None,
        }))
    }
}

/// The near-light solve ([`crate::ps::near`]) alternates over the whole capture, so it is not
/// streamed.
fn refuse_near(files: &CaptureFiles, config: &Config) -> Result<()> {
    if crate::run::pipeline::near_applies(&files.lights, config) {
        return Err(Error::param(
            "max_memory",
            "near-light photometric stereo alternates normals and depth over the whole capture, which must then fit in memory; it does not stream in row bands (raise the memory budget, or solve the lights as distant ones)",
        ));
    }
    Ok(())
}

/// Interreflection compensation predicts the light each pixel receives from the whole
/// surface, so it is not streamed.
fn refuse_interreflections(config: &Config) -> Result<()> {
    if config.interreflections.is_some() {
        return Err(Error::param(
            "interreflections",
            "compensation needs the whole stack in memory; a run streamed in row bands cannot \
             compensate them",
        ));
    }
    Ok(())
}

/// Whether a run of `files` with `config` can be streamed in row bands at all, besides the
/// images being readable in bands ([`plan`] opens them): not with near lights or
/// interreflection compensation, which need the whole capture at once.
///
/// # Errors
/// [`Error::InvalidParameter`]: naming `max_memory` for near lights, `interreflections` for
/// the compensation.
pub fn streamable(files: &CaptureFiles, config: &Config) -> Result<()> {
    refuse_near(files, config)?;
    refuse_interreflections(config)
}

/// What a streamed run found besides the solutions.
struct BandRun {
    plan: StreamPlan,
    /// Per image, what loading found (summed over bands).
    info: Vec<ImageInfo>,
    /// The report's input section.
    summary: InputSummary,
    /// Seconds decoding (model pass included).
    read_s: f64,
    /// Seconds solving.
    solve_s: f64,
    /// Seconds in the sink.
    sink_s: f64,
}

impl BandRun {
    /// What the warnings need to know of the input.
    fn facts(&self, files: &CaptureFiles) -> InputFacts<'_> {
        InputFacts {
            info: &self.info,
            count: self.info.len(),
            unmasked_files: files.mask_source.is_none(),
            behind: files.lights.behind(),
            positioned: files.lights.positioned(),
            ambient_subtracted: files.ambient_source.is_some(),
        }
    }
}

/// What a streamed run keeps for the whole run besides the band: the assembled solution
/// ([`reconstruct_streamed`]) or only what the outputs written band by band still need
/// ([`reconstruct_and_write_streamed`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Keep {
    Assembled,
    Written,
}

/// The band loop ([`solve_bands`]) over the files of a capture, with the sink `start` makes.
fn run_bands<S: BandSink>(
    files: &CaptureFiles,
    load: &LoadOptions,
    config: &Config,
    options: &StreamOptions,
    keep: Keep,
    progress: &dyn Progress,
    start: impl FnOnce(&Setup) -> Result<S>,
) -> Result<(S, BandRun)> {
    refuse_interreflections(config)?;
    let mut source = FileBands::open(files, load, config, options, keep)?;
    let solve_config =
        super::pipeline::fill_only_inside_a_mask(config, files.mask_source.is_none());
    let (sink, times) = solve_bands(&mut source, &files.lights, &solve_config, progress, start)?;
    source.band = None;
    drop(std::mem::take(&mut source.opened.readers));
    drop(source.opened.ambient.take());
    let (plan, info, summary, read_s) = source.finish()?;
    Ok((
        sink,
        BandRun {
            plan,
            info,
            summary,
            read_s,
            solve_s: times.solve,
            sink_s: times.sink,
        },
    ))
}

/// Solves a capture streamed in row bands: the same [`Reconstruction`] as
/// [`crate::run::pipeline::reconstruct_normals`] (without depth), within `options.max_memory`.
/// The whole solution is held ([`ASSEMBLED_BYTES_PER_PIXEL`]); to write the outputs of a
/// stack whose maps are large too, use [`reconstruct_and_write_streamed`], which writes them
/// band by band. Returns the reconstruction with the plan, the per-image load records and the
/// seconds spent decoding.
///
/// # Errors
/// The errors of [`plan`], of decoding any band (naming the file), and of the solve;
/// [`Error::BadImage`] for an image that is dark everywhere in the mask's rows or saturated
/// everywhere.
pub fn reconstruct_streamed(
    files: &CaptureFiles,
    load: &LoadOptions,
    config: &Config,
    options: &StreamOptions,
    progress: &dyn Progress,
) -> Result<Streamed> {
    refuse_near(files, config)?;
    let t_all = Instant::now();
    let (sink, run) = run_bands(
        files,
        load,
        config,
        options,
        Keep::Assembled,
        progress,
        |setup| Ok(Assemble::new(setup)),
    )?;
    let mut recon = assemble(
        sink.into_solutions(),
        run.solve_s + run.sink_s,
        &run.facts(files),
        config,
    );
    recon.timings.load = run.read_s;
    Ok(Streamed {
        recon,
        plan: run.plan,
        summary: run.summary,
        seconds: t_all.elapsed().as_secs_f64(),
    })
}

/// A streamed solve: the reconstruction (without depth), the plan it followed and the
/// report's input section.
#[derive(Debug, Clone)]
pub struct Streamed {
    /// Normals, albedo and the per-pixel maps.
    pub recon: Reconstruction,
    /// How memory was used.
    pub plan: StreamPlan,
    /// The report's `inputs`.
    pub summary: InputSummary,
    /// Wall time of the streamed solve.
    pub seconds: f64,
}

/// Solves a capture streamed in row bands and writes the outputs of
/// [`crate::run::pipeline::reconstruct_and_write`] (atomically) as the bands are solved: the
/// per-pixel maps (`normal.exr`, `albedo.exr`, `residual.exr`, `mask.png`, `normal.png`) go
/// to their files a band at a time and are not kept. What is kept for the whole run is what
/// needs the whole image ([`RESIDENT_BYTES_PER_PIXEL`]): the normals and the solved mask for
/// the integrability check and integration, the albedo for the 99th-percentile scaling of
/// `albedo.png`, and the residuals for their median. After the bands, the finishing stage of
/// every run (`run::pipeline::finish`): integration beside `curl.exr`, then
/// `depth.exr`, `depth.png`, `mesh.ply` and `report.json`, whose `streaming` section holds the
/// plan. Returns the report and the plan.
///
/// # Errors
/// The errors of [`reconstruct_streamed`], of integration and of writing; nothing is left in
/// `dir` on failure.
pub fn reconstruct_and_write_streamed(
    files: &CaptureFiles,
    load: &LoadOptions,
    config: &Config,
    options: &StreamOptions,
    dir: &Path,
    progress: &dyn Progress,
) -> Result<(Report, StreamPlan)> {
    refuse_near(files, config)?;
    let mut out = OutputDir::create(dir)?;
    let attrs = |file: &str| exr_attributes(&files.lights, config, file);
    let (sink, run) = run_bands(
        files,
        load,
        config,
        options,
        Keep::Written,
        progress,
        |setup| BandOutput::start(&out, setup, &attrs),
    )?;
    let t = Instant::now();
    let written = sink.finish(&mut out)?;
    release_freed_memory();
    let facts = run.facts(files);
    let t_normals = Instant::now();
    let integ = integrability_of(&written.normals, &written.solved, config);
    // The check's gradients and sorted |curl| are freed: hand them back before integration.
    release_freed_memory();
    let normals_s = t_normals.elapsed().as_secs_f64();
    let model = model_summary(&written.models, &written.tallies, facts.count, config);
    let warnings = warnings(
        &facts,
        &written.tallies,
        &written.models,
        &integ.summary,
        config,
    );
    let write_s = run.sink_s + t.elapsed().as_secs_f64() - normals_s;
    let source = Described {
        lights: &files.lights,
        summary: run.summary.clone(),
        streaming: serde_json::to_value(run.plan).ok(),
    };
    let (w, h) = (written.normals.width(), written.normals.height());
    let integrability = integ.summary;
    let curl = integ.curl;
    let finished = finish(
        &mut out,
        (&written.normals, &written.solved, None),
        &source,
        &capped(config, options, &run.plan),
        progress,
        |out| {
            out.stage_exr(
                "curl.exr",
                w,
                h,
                &[("curl", curl.data())],
                &attrs("curl.exr"),
            )
        },
    )?;
    drop(curl);
    let summary = RunSummary {
        pixels: written.tallies.counts,
        model,
        albedo_above_one: written.tallies.albedo_above_one,
        residual: written.residual,
        integrability,
        interreflections: None,
        near: None,
        timings: Timings {
            load: run.read_s,
            solve: run.solve_s,
            normals: normals_s,
            integrate: finished.integrate_s,
            write: write_s + finished.write_s,
        },
        warnings,
    };
    let report = commit_with_report(
        out,
        summary,
        finished.integration.as_ref(),
        &source,
        config,
        None,
    )?;
    Ok((report, run.plan))
}

impl Integrator {
    /// Bytes of working memory this integrator needs on a `width`×`height` image with `masked`
    /// pixels in the domain, whose bounding box is `window`. Masked least squares on the pixel
    /// grid (the default beyond the direct limit) is counted ([`grid_masked_bytes`]); each other
    /// figure is a line fitted to the peak resident memory of `integrate_normals` alone (the
    /// growth of the process's peak over the call) on a 1732×1732 rendered normal map under
    /// discs of radius 400, 600 and 800 px, rounded up by about 10%: the gradients, domain,
    /// depth and residual maps over the image, plus the solver's arrays over the unknowns or the
    /// window's cells.
    pub fn working_bytes(
        self,
        width: usize,
        height: usize,
        masked: usize,
        window: Window,
        solver: crate::integrate::LinearSolver,
    ) -> u64 {
        use crate::integrate::LinearSolver;
        let (n, m, cells) = ((width * height) as u64, masked as u64, window.len() as u64);
        match self {
            // The gradients, depth and the transform buffers over the image: 46 B measured.
            Integrator::Poisson | Integrator::FrankotChellappa => 50 * n,
            Integrator::Path => 50 * n,
            // The bilateral integrator (and `auto`, which may run it) holds per unknown its
            // neighbours, equation coefficients, weights and depth (80 B), a reweighting step's
            // system and its conjugate gradients' vectors (64 B) and one multigrid hierarchy at
            // a time: during the steps the grid hierarchy over the unknowns' bounding box
            // (`GRID_PRECONDITIONER_BYTES_PER_CELL` a cell and 4 B an unknown), during the
            // re-integration the grid's finest level with a coarse aggregation hierarchy
            // (`multigrid/blocks.rs`; it replaced an aggregation hierarchy over all the unknowns,
            // under which the plan below was measured: the peaks fell since, 2048² sphere 745 →
            // 654 MB, a 1024² torus on a ground 350 → 314 MB). Measured, the growth of the
            // `integrate` process's peak over the integration on spheres of 1024² and 2048²
            // (0.53 and 2.1 M unknowns) and a 1024² ball floating above a ground (1.05 M
            // unknowns, cut all around the ball) less 48 B a pixel: 222, 216 and 289 B an
            // unknown, with 10% added (before the hierarchies were freed as soon as they were
            // done with and the re-integration's edges were no longer listed, the peaks were
            // 369, 1366 and 643 MiB against 185, 705 and 359 MiB now; planned at 640 B). Where
            // a step or the re-integration is solved directly (up to 100 000 unknowns by
            // default), a sparse factor besides, counted as masked least squares' (DiLiGenT
            // cat: 522 B an unknown in all, measured). During the steps the grid hierarchy is
            // counted beside the arrays an unknown then holds, counted: the 80 B above, the
            // step's system and right-hand side (32 B), the conjugate gradients' seven vectors
            // (56 B) and the unknown's window cell (4 B); the larger of the two phases, which
            // is the steps where the bounding box holds many cells besides the unknowns (a
            // thin diagonal object). On the spheres and the ball above the re-integration's
            // peak is the larger (the measured peaks fell by 0–8% when the steps moved to the
            // grid).
            Integrator::Bilateral | Integrator::Auto => {
                let factor = if solver.direct_for(masked) {
                    900 * m
                } else {
                    0
                };
                let steps = 172 * m + crate::integrate::GRID_PRECONDITIONER_BYTES_PER_CELL * cells;
                48 * n + (320 * m).max(steps) + factor
            }
            Integrator::MaskedLs => {
                if solver.direct_for(masked) {
                    // 26 B a pixel and 850 B an unknown measured (0.5 M unknowns; the
                    // factor's fill-in grows like n log n).
                    28 * n + 900 * m
                } else if solver == LinearSolver::ConjugateGradient {
                    // The DCT preconditioner works on the whole image: 53 B a pixel and 80 B
                    // an unknown measured.
                    58 * n + 88 * m
                } else {
                    grid_masked_bytes(n, cells)
                }
            }
        }
    }
}

/// Bytes [`crate::integrate::integrate_normals`] holds at most for masked least squares by
/// multigrid on the window's grid, `pixels` in the image and `cells` in the domain's bounding
/// box, counted, besides the normals: during the solve, the domain (1 B a pixel) and the
/// solver's [`crate::integrate::GRID_BYTES_PER_CELL`] (the gradients are freed once the
/// window's depth differences are taken); after it, the depth, the gradients again, the domain
/// and the residual (17 B a pixel) with the residual's window differences (25 B a cell). The
/// larger of the two.
fn grid_masked_bytes(pixels: u64, cells: u64) -> u64 {
    (pixels + crate::integrate::GRID_BYTES_PER_CELL * cells).max(17 * pixels + 25 * cells)
}

/// Memory sizes parsed and refused; the plan's band height and band count from the budget on a
/// small capture written as 16-bit PNGs, down to the refusal below [`MIN_BAND_ROWS`] rows;
/// the resident bytes growing with the image and its channels; and a streamed solve in several
/// bands giving the in-memory solve bit for bit.
#[cfg(test)]
mod tests {
    use super::*;
    use crate::integrate::IntegrationOptions;
    use crate::progress::Silent;
    use crate::ps::solve::{Method, SolveOptions};
    use crate::synth::render::{RenderOptions, render};
    use crate::synth::scene::{Albedo, Scene};
    use crate::synth::test_support::assert_same_bits;
    use crate::synth::write::{ImageFormat, write_synthetic};

    /// Images of the written capture.
    const LIGHTS: usize = 8;

    /// A 40×40 sphere of radius 14 (mask rows well inside the image), albedo 0.7, under 8
    /// lights, noise σ = 0.004, written to `dir` as 16-bit PNGs with its mask; the capture's
    /// files and the mask.
    fn capture(dir: &Path) -> (CaptureFiles, Mask) {
        let lights = Lights::fibonacci(LIGHTS, 30.0).unwrap();
        let scene = Scene::sphere(40, 14.0, Albedo::Constant(0.7));
        let options = RenderOptions {
            noise_sigma: 0.004,
            seed: 11,
            ..RenderOptions::default()
        };
        let rendering = render(&scene, &lights, &options).unwrap();
        write_synthetic(&rendering, &lights, dir, ImageFormat::Png16).unwrap();
        let images: Vec<_> = (0..LIGHTS)
            .map(|k| dir.join(format!("img_{k:03}.png")))
            .collect();
        let files = CaptureFiles::from_files(
            &images,
            &dir.join("lights.json"),
            Some(&dir.join("mask.png")),
        )
        .unwrap();
        (files, rendering.truth.mask)
    }

    fn threshold() -> Config {
        Config {
            solve: SolveOptions::with_method(Method::Threshold),
            integration: None,
            ..Config::default()
        }
    }

    /// Binary units with or without `B`/`iB`, any case, fractions and plain bytes; anything
    /// else refused naming `max-memory` and quoting the text.
    #[test]
    fn parse_size_reads_binary_units_and_quotes_bad_text() {
        assert_eq!(parse_size("300M").unwrap(), 300 << 20);
        assert_eq!(parse_size("2G").unwrap(), 2 << 30);
        assert_eq!(parse_size("2gb").unwrap(), 2 << 30);
        assert_eq!(parse_size("1536MiB").unwrap(), 1536 << 20);
        assert_eq!(parse_size(" 4k ").unwrap(), 4096);
        assert_eq!(parse_size("1T").unwrap(), 1 << 40);
        assert_eq!(parse_size("1.5G").unwrap(), 3 << 29);
        assert_eq!(parse_size("123456789").unwrap(), 123_456_789);
        for bad in ["lots", "", "G", "2X", "1.2.3M", "-1G", "0", "NaN", "inf"] {
            let e = parse_size(bad).unwrap_err();
            match &e {
                Error::InvalidParameter { name, reason } => {
                    assert_eq!(*name, "max-memory", "{bad:?}");
                    assert!(reason.contains(&format!("{bad:?}")), "{bad:?}: {reason}");
                }
                _ => panic!("{bad:?}: {e}"),
            }
        }
    }

    /// On the written capture: the window is the mask's bounding box; bands of a given height
    /// cover its rows (clamped to them); without one, the band height is what the budget holds
    /// beyond the resident bytes, one band row at a time, down to [`MIN_BAND_ROWS`], below
    /// which the plan is refused naming the budget; the model pass samples whole blocks of
    /// what a band holds, only for a method that needs a model.
    #[test]
    fn plan_bands_follow_the_budget() {
        let dir = tempfile::tempdir().unwrap();
        let (files, mask) = capture(dir.path());
        let load = LoadOptions::default();
        let config = threshold();
        let plan_with = |max_memory, band_rows, config: &Config| {
            plan(
                &files,
                &load,
                config,
                &StreamOptions {
                    max_memory,
                    band_rows,
                },
            )
        };
        let p = plan_with(1 << 30, Some(7), &config).unwrap();
        let win = mask.bounding_box().unwrap();
        assert_eq!(p.window, win);
        assert!(win.y0 > 0 && win.y1 < 40, "{win:?}");
        let rows = win.height();
        assert_eq!(
            (p.width, p.height, p.count, p.channels),
            (40, 40, LIGHTS, 1)
        );
        assert_eq!((p.band_rows, p.bands), (7, rows.div_ceil(7)));
        assert_eq!(p.sample_rows, 0, "threshold needs no model");
        assert_eq!(
            p.resident_bytes,
            resident_bytes(40, 40, 1, mask.count(), win, &config)
        );
        assert_eq!(
            p.in_memory_stack_bytes,
            (LIGHTS * win.width() * rows * 4) as u64
        );
        let row = p.band_bytes / 7;
        assert_eq!(row * 7, p.band_bytes);
        // A band height above the window's rows is clamped: one band.
        let p = plan_with(1 << 30, Some(1000), &config).unwrap();
        assert_eq!((p.band_rows, p.bands), (rows, 1));
        assert!(plan_with(1 << 30, Some(0), &config).is_err());
        // From the budget: 9 rows fit (not 10), or exactly MIN_BAND_ROWS, or one fewer.
        let resident = p.resident_bytes;
        let p = plan_with(resident + 10 * row - 1, None, &config).unwrap();
        assert_eq!((p.band_rows, p.bands), (9, rows.div_ceil(9)));
        let auto = Config {
            solve: SolveOptions::default(),
            ..config
        };
        let pa = plan_with(resident + 10 * row - 1, None, &auto).unwrap();
        assert_eq!(pa.sample_rows, 8, "whole blocks of what 9 rows hold");
        let p = plan_with(resident + MIN_BAND_ROWS as u64 * row, None, &config).unwrap();
        assert_eq!(p.band_rows, MIN_BAND_ROWS);
        let e = plan_with(resident + MIN_BAND_ROWS as u64 * row - 1, None, &config).unwrap_err();
        assert!(
            matches!(&e, Error::InvalidParameter { name: "max-memory", reason } if reason.contains(&format!("{MIN_BAND_ROWS} rows"))),
            "{e}"
        );
    }

    /// The resident bytes grow with the image and with its channels, with integration or
    /// without; without, they are the base plus [`RESIDENT_BYTES_PER_PIXEL`] a pixel and
    /// [`RESIDENT_BYTES_PER_EXTRA_CHANNEL`] a pixel for each further channel.
    #[test]
    fn resident_bytes_grow_with_size_and_channels() {
        let none = Config {
            integration: None,
            ..Config::default()
        };
        let poisson = Config {
            integration: Some(IntegrationOptions {
                method: crate::integrate::Integrator::Poisson,
                ..IntegrationOptions::default()
            }),
            ..Config::default()
        };
        for config in [none, Config::default(), poisson] {
            let mut last = 0;
            for size in [16, 64, 256, 1024] {
                let masked = size * size / 2;
                let window = Window {
                    x0: 0,
                    y0: size / 4,
                    x1: size,
                    y1: size / 4 + size / 2,
                };
                let grey = resident_bytes(size, size, 1, masked, window, &config);
                let rgb = resident_bytes(size, size, 3, masked, window, &config);
                assert!(grey > last && rgb > grey, "{size}: {last} {grey} {rgb}");
                last = rgb;
            }
        }
        let (w, h) = (300, 200);
        let window = Window {
            x0: 10,
            y0: 10,
            x1: 60,
            y1: 30,
        };
        assert_eq!(
            resident_bytes(w, h, 1, 1000, window, &none),
            BASE_BYTES + RESIDENT_BYTES_PER_PIXEL * (w * h) as u64
        );
        assert_eq!(
            resident_bytes(w, h, 3, 1000, window, &none)
                - resident_bytes(w, h, 1, 1000, window, &none),
            2 * RESIDENT_BYTES_PER_EXTRA_CHANNEL * (w * h) as u64
        );
    }

    /// The capture streamed in bands of 5 and of 7 rows gives the in-memory normals, albedo,
    /// residual, samples, condition and status bit for bit.
    #[test]
    fn streamed_bands_equal_the_in_memory_solve() {
        let dir = tempfile::tempdir().unwrap();
        let (files, _) = capture(dir.path());
        let load = LoadOptions::default();
        let config = threshold();
        let capture = files.load(&load, &Silent).unwrap();
        let whole = crate::run::pipeline::reconstruct(&capture, &config, &Silent).unwrap();
        assert!(whole.counts.solved > 300, "{:?}", whole.counts);
        for band_rows in [5, 7] {
            let options = StreamOptions {
                max_memory: 1 << 30,
                band_rows: Some(band_rows),
            };
            let s = reconstruct_streamed(&files, &load, &config, &options, &Silent).unwrap();
            let what = format!("bands of {band_rows}");
            assert!(s.plan.bands > 2, "{what}: {:?}", s.plan);
            let r = &s.recon;
            let flat = |n: &crate::grid::NormalMap| -> Vec<f32> {
                n.data().iter().flat_map(|v| [v.x, v.y, v.z]).collect()
            };
            assert_same_bits(
                &flat(&r.maps.normals),
                &flat(&whole.maps.normals),
                &format!("{what}: normals"),
            );
            assert_same_bits(
                r.maps.albedo[0].data(),
                whole.maps.albedo[0].data(),
                &format!("{what}: albedo"),
            );
            assert_same_bits(
                r.maps.residual.data(),
                whole.maps.residual.data(),
                &format!("{what}: residual"),
            );
            assert_same_bits(
                r.maps.condition.data(),
                whole.maps.condition.data(),
                &format!("{what}: condition"),
            );
            assert_eq!(r.maps.samples, whole.maps.samples, "{what}");
            assert_eq!(r.maps.status, whole.maps.status, "{what}");
            assert_eq!(r.counts, whole.counts, "{what}");
        }
    }
}
