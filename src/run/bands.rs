//! The band loop every run goes through: a [`BandSource`] gives the capture-wide image model
//! and then bands of rows, each band is solved under that model, and a [`BandSink`] takes the
//! solved bands top to bottom.
//!
//! An in-memory run is a source of one band, the whole stack ([`WholeStack`]); a streamed run
//! is a source of many, decoded from the files a band at a time
//! ([`crate::run::stream`]). Where the bands go is the sink's choice: [`Assemble`] keeps the
//! whole solution (what [`crate::run::pipeline::reconstruct`] returns), the band writer of
//! `band_output.rs` writes each band's rows of the per-pixel files and keeps only what needs
//! the whole image.

use crate::capture::lights::Lights;
use crate::capture::stack::ImageStack;
use crate::error::Result;
use crate::grid::Mask;
use crate::progress::{Progress, Silent};
use crate::ps::color::{ColorSolve, solve_shared_normal_with_grey};
use crate::ps::solve::{ImageModel, Solution, SolveOptions, solve_with_model};
use crate::run::pipeline::Config;
use std::borrow::Cow;
use std::time::Instant;

/// One band of rows: its stack (the band's rows, the window's columns), its mask rows and,
/// when the source already has it, the grey mix of the stack for the shared-normal colour
/// solve.
pub(crate) struct Band<'a> {
    /// The band's first image row.
    pub y0: usize,
    /// The band's samples.
    pub stack: Cow<'a, ImageStack>,
    /// The band's mask rows (full width).
    pub mask: Cow<'a, Mask>,
    /// The grey mix of `stack`, when the source made it already.
    pub grey: Option<&'a ImageStack>,
}

/// Where the bands of a run come from.
pub(crate) trait BandSource {
    /// Image width and height.
    fn size(&self) -> (usize, usize);
    /// Channels of the stack (1 grey, 3 RGB).
    fn channels(&self) -> usize;
    /// Rows per band (the last may have fewer).
    fn band_rows(&self) -> usize;
    /// Number of bands.
    fn bands(&self) -> usize;
    /// The capture-wide image model of each solved channel (one for the shared-normal solve):
    /// estimated before any pixel is fitted, so that every band is fitted under the same one.
    fn models(&mut self, lights: &Lights, config: &Config) -> Result<Vec<ImageModel>>;
    /// The next band, top to bottom; `None` after the last.
    fn next_band(&mut self) -> Result<Option<Band<'_>>>;
}

/// What a [`BandSink`] is told before the first band.
pub(crate) struct Setup {
    /// Image width.
    pub width: usize,
    /// Image height.
    pub height: usize,
    /// Rows per band.
    pub band_rows: usize,
    /// Solutions of rows with no pixel in the mask.
    pub blank: Blank,
}

/// Makes solutions of rows with every pixel outside the mask, under the run's models: what the
/// rows outside the mask's bounding box hold.
#[derive(Clone)]
pub(crate) struct Blank {
    width: usize,
    channels: usize,
    models: Vec<ImageModel>,
    shared: bool,
    options: SolveOptions,
}

impl Blank {
    /// Per-channel solutions of `rows` full-width rows outside the mask.
    pub(crate) fn rows(&self, rows: usize) -> Vec<Solution> {
        (0..self.channels)
            .map(|c| {
                let m = &self.models[if self.shared { 0 } else { c }];
                Solution::empty(
                    self.width,
                    rows,
                    m.gains.clone(),
                    m.sigma.clone(),
                    &self.options,
                )
            })
            .collect()
    }
}

impl Setup {
    /// [`Blank::rows`].
    pub(crate) fn empty(&self, rows: usize) -> Vec<Solution> {
        self.blank.rows(rows)
    }
}

/// Where the solved bands of a run go, top to bottom.
pub(crate) trait BandSink {
    /// Takes the per-channel solutions of the full-width rows from `y0` on.
    fn band(&mut self, y0: usize, solutions: Vec<Solution>) -> Result<()>;
}

/// Seconds spent in each part of the band loop.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct BandTimes {
    /// Estimating the image model.
    pub model: f64,
    /// Solving the bands.
    pub solve: f64,
    /// In the sink.
    pub sink: f64,
}

/// Whether `config` solves an RGB stack of `channels` channels for one shared normal.
pub(crate) fn shared_normal(channels: usize, config: &Config) -> bool {
    channels == 3 && config.color == ColorSolve::SharedNormal
}

/// The band loop: the model, then each band solved and handed to the sink that `start` makes.
/// A source of one band reports the solve's own progress; a source of many, one step a band.
pub(crate) fn solve_bands<S: BandSink>(
    source: &mut dyn BandSource,
    lights: &Lights,
    config: &Config,
    progress: &dyn Progress,
    start: impl FnOnce(&Setup) -> Result<S>,
) -> Result<(S, BandTimes)> {
    let t = Instant::now();
    let models = source.models(lights, config)?;
    let mut times = BandTimes {
        model: t.elapsed().as_secs_f64(),
        ..BandTimes::default()
    };
    let (width, height) = source.size();
    let channels = source.channels();
    let shared = shared_normal(channels, config);
    let setup = Setup {
        width,
        height,
        band_rows: source.band_rows(),
        blank: Blank {
            width,
            channels,
            models: models.clone(),
            shared,
            options: config.solve,
        },
    };
    let mut sink = start(&setup)?;
    let single = source.bands() == 1;
    let band_progress: &dyn Progress = if single { progress } else { &Silent };
    if !single {
        progress.begin("bands", source.bands() as u64);
    }
    while let Some(band) = source.next_band()? {
        let t = Instant::now();
        let y0 = band.y0;
        let solutions = solve_band(&band, lights, config, &models, shared, band_progress)?;
        drop(band);
        times.solve += t.elapsed().as_secs_f64();
        let t = Instant::now();
        sink.band(y0, solutions)?;
        times.sink += t.elapsed().as_secs_f64();
        if !single {
            progress.advance(1);
        }
    }
    if !single {
        progress.end();
    }
    Ok((sink, times))
}

/// The per-channel solutions of one band under the run's models.
fn solve_band(
    band: &Band,
    lights: &Lights,
    config: &Config,
    models: &[ImageModel],
    shared: bool,
    progress: &dyn Progress,
) -> Result<Vec<Solution>> {
    let (stack, mask) = (band.stack.as_ref(), band.mask.as_ref());
    if shared {
        let made;
        let grey = match band.grey {
            Some(g) => g,
            None => {
                made = stack.grey_mix();
                &made
            }
        };
        return solve_shared_normal_with_grey(
            stack,
            grey,
            lights,
            mask,
            &config.solve,
            models[0].clone(),
            progress,
        );
    }
    (0..stack.channels())
        .map(|c| {
            solve_with_model(
                stack,
                c,
                lights,
                mask,
                &config.solve,
                models[c].clone(),
                progress,
            )
        })
        .collect()
}

/// The source of an in-memory run: the whole stack as one band, its model estimated from all
/// of it.
pub(crate) struct WholeStack<'a> {
    stack: &'a ImageStack,
    mask: &'a Mask,
    /// The grey mix, made for the shared-normal model and kept for its solve.
    grey: Option<ImageStack>,
    done: bool,
}

impl<'a> WholeStack<'a> {
    /// The source of `stack` under `mask` (of the stack's full size).
    pub(crate) fn new(stack: &'a ImageStack, mask: &'a Mask) -> Self {
        WholeStack {
            stack,
            mask,
            grey: None,
            done: false,
        }
    }
}

impl BandSource for WholeStack<'_> {
    fn size(&self) -> (usize, usize) {
        (self.stack.width(), self.stack.height())
    }

    fn channels(&self) -> usize {
        self.stack.channels()
    }

    fn band_rows(&self) -> usize {
        self.stack.height()
    }

    fn bands(&self) -> usize {
        1
    }

    fn models(&mut self, lights: &Lights, config: &Config) -> Result<Vec<ImageModel>> {
        let (stack, mask, options) = (self.stack, self.mask, &config.solve);
        if shared_normal(stack.channels(), config) {
            crate::ps::color::check_rgb_inputs(stack, lights, mask, options)?;
            let grey = self.grey.insert(stack.grey_mix());
            return Ok(vec![ImageModel::estimate(grey, 0, lights, mask, options)?]);
        }
        (0..stack.channels())
            .map(|c| ImageModel::estimate(stack, c, lights, mask, options))
            .collect()
    }

    fn next_band(&mut self) -> Result<Option<Band<'_>>> {
        if std::mem::replace(&mut self.done, true) {
            return Ok(None);
        }
        Ok(Some(Band {
            y0: 0,
            stack: Cow::Borrowed(self.stack),
            mask: Cow::Borrowed(self.mask),
            grey: self.grey.as_ref(),
        }))
    }
}

/// The sink that assembles the whole solution: a band covering the whole image is taken as it
/// is, others are pasted into full-size solutions that start blank.
pub(crate) struct Assemble {
    height: usize,
    blank: Blank,
    full: Option<Vec<Solution>>,
}

impl Assemble {
    /// An assembly for a run set up as `setup`.
    pub(crate) fn new(setup: &Setup) -> Self {
        Assemble {
            height: setup.height,
            blank: setup.blank.clone(),
            full: None,
        }
    }

    /// The assembled per-channel solutions (all blank when no band came).
    pub(crate) fn into_solutions(self) -> Vec<Solution> {
        let height = self.height;
        self.full.unwrap_or_else(|| self.blank.rows(height))
    }
}

impl BandSink for Assemble {
    fn band(&mut self, y0: usize, solutions: Vec<Solution>) -> Result<()> {
        let whole = y0 == 0
            && solutions
                .first()
                .is_some_and(|s| s.status.height() == self.height);
        match &mut self.full {
            None if whole => self.full = Some(solutions),
            full => {
                let full = full.get_or_insert_with(|| self.blank.rows(self.height));
                for (f, b) in full.iter_mut().zip(&solutions) {
                    f.paste_rows(b, y0)?;
                }
            }
        }
        Ok(())
    }
}
