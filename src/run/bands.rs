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
    /// The models given instead of estimated (a part of a capture solved under the whole's).
    given: Option<&'a [ImageModel]>,
    done: bool,
}

impl<'a> WholeStack<'a> {
    /// The source of `stack` under `mask` (of the stack's full size).
    pub(crate) fn new(stack: &'a ImageStack, mask: &'a Mask) -> Self {
        WholeStack {
            stack,
            mask,
            grey: None,
            given: None,
            done: false,
        }
    }

    /// The source with its models given rather than estimated from `stack`.
    pub(crate) fn with_models(mut self, models: Option<&'a [ImageModel]>) -> Self {
        self.given = models;
        self
    }
}

/// The models a solve of `stack` under `config` uses (one per solved channel, one for the
/// shared-normal colour solve), estimated over `mask`; the grey mix, when one was made, goes
/// to `grey`.
pub(crate) fn estimate_models(
    stack: &ImageStack,
    mask: &Mask,
    lights: &Lights,
    config: &Config,
    grey: &mut Option<ImageStack>,
) -> Result<Vec<ImageModel>> {
    let options = &config.solve;
    if shared_normal(stack.channels(), config) {
        crate::ps::color::check_rgb_inputs(stack, lights, mask, options)?;
        let grey = grey.insert(stack.grey_mix());
        return Ok(vec![ImageModel::estimate(
            grey,
            0,
            lights,
            mask,
            &shared_model_options(options),
        )?]);
    }
    (0..stack.channels())
        .map(|c| ImageModel::estimate(stack, c, lights, mask, options))
        .collect()
}

/// The options a shared-normal colour solve's model is estimated under: those of the solve,
/// without the lobe refit, which that solve does not run (its capture-wide limit would be
/// estimated for nothing: about 4000 sampled pixels fitted).
pub(crate) fn shared_model_options(options: &SolveOptions) -> SolveOptions {
    SolveOptions {
        lobes: false,
        ..*options
    }
}

/// How many models a solve of a `channels`-channel stack under `config` uses.
pub(crate) fn model_count(channels: usize, config: &Config) -> usize {
    if shared_normal(channels, config) {
        1
    } else {
        channels
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
        let Some(given) = self.given else {
            return estimate_models(self.stack, self.mask, lights, config, &mut self.grey);
        };
        let want = model_count(self.stack.channels(), config);
        if given.len() != want {
            return Err(crate::Error::param(
                "models",
                format!(
                    "{} model(s) given; this solve uses {want} (one per solved channel, one for the shared-normal colour solve)",
                    given.len()
                ),
            ));
        }
        let count = self.stack.count();
        let needs_sigma = ImageModel::needed(&config.solve, count);
        for (m, model) in given.iter().enumerate() {
            let bad = |what: String| {
                Err(crate::Error::param(
                    "models",
                    format!("model {m}: {what}; pass models estimated from the capture"),
                ))
            };
            if model.sigma.len() != count || model.gains.gains.len() != count {
                return bad(format!(
                    "{} noise σ and {} gains for {count} images",
                    model.sigma.len(),
                    model.gains.gains.len()
                ));
            }
            if let Some(k) = model
                .gains
                .gains
                .iter()
                .position(|g| !(g.is_finite() && *g > 0.0))
            {
                return bad(format!("image {k}'s gain is {}", model.gains.gains[k]));
            }
            if needs_sigma
                && let Some(k) = model
                    .sigma
                    .iter()
                    .position(|s| !(s.is_finite() && *s > 0.0))
            {
                return bad(format!(
                    "image {k}'s noise σ is {}, and the method weighs samples by it",
                    model.sigma[k]
                ));
            }
        }
        if shared_normal(self.stack.channels(), config) {
            crate::ps::color::check_rgb_inputs(self.stack, lights, self.mask, &config.solve)?;
            self.grey = Some(self.stack.grey_mix());
        }
        Ok(given.to_vec())
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

/// The band loop: a stack served in row bands, each solved under the model estimated on the
/// whole stack, assembles to the one-band solution bit for bit (grey, per channel and shared
/// normal), with one progress step a band; [`Assemble`] keeps a whole band as it is and pastes
/// partial ones into blank rows; [`shared_normal`] holds only for RGB under the shared solve.
#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::Grid;
    use crate::ps::color::ColorSolve;
    use crate::ps::intensities::GainEstimate;
    use crate::ps::solve::{PixelSolution, PixelStatus};
    use crate::synth::test_support::{
        assert_same_solutions, hand_made_solution, lambertian_stack, sphere,
    };
    use std::sync::Mutex;

    /// A source serving rows `rows` of an in-memory stack (full window) in bands of
    /// `band_rows` rows, with the models of the whole stack ([`WholeStack::models`]): what a
    /// streamed run does, without files.
    struct RowBands<'a> {
        stack: &'a ImageStack,
        mask: &'a Mask,
        rows: std::ops::Range<usize>,
        band_rows: usize,
        next: usize,
    }

    impl<'a> RowBands<'a> {
        fn new(
            stack: &'a ImageStack,
            mask: &'a Mask,
            rows: std::ops::Range<usize>,
            band_rows: usize,
        ) -> Self {
            let next = rows.start;
            RowBands {
                stack,
                mask,
                rows,
                band_rows,
                next,
            }
        }
    }

    impl BandSource for RowBands<'_> {
        fn size(&self) -> (usize, usize) {
            (self.stack.width(), self.stack.height())
        }

        fn channels(&self) -> usize {
            self.stack.channels()
        }

        fn band_rows(&self) -> usize {
            self.band_rows
        }

        fn bands(&self) -> usize {
            self.rows.len().div_ceil(self.band_rows)
        }

        fn models(&mut self, lights: &Lights, config: &Config) -> Result<Vec<ImageModel>> {
            WholeStack::new(self.stack, self.mask).models(lights, config)
        }

        fn next_band(&mut self) -> Result<Option<Band<'_>>> {
            let y0 = self.next;
            if y0 >= self.rows.end {
                return Ok(None);
            }
            let y1 = (y0 + self.band_rows).min(self.rows.end);
            self.next = y1;
            let (w, s) = (self.stack.width(), self.stack);
            let images = (0..s.count())
                .map(|k| {
                    (0..s.channels())
                        .flat_map(|c| s.plane(k, c)[y0 * w..y1 * w].iter().copied())
                        .collect()
                })
                .collect();
            let stack = ImageStack::from_images(w, y1 - y0, s.channels(), images)?;
            let mask = Grid::from_fn(w, y1 - y0, |x, y| *self.mask.at(x, y0 + y));
            Ok(Some(Band {
                y0,
                stack: Cow::Owned(stack),
                mask: Cow::Owned(mask),
                grey: None,
            }))
        }
    }

    /// The band loop over `source` into an [`Assemble`]: the per-channel solutions.
    fn assembled(source: &mut dyn BandSource, lights: &Lights, config: &Config) -> Vec<Solution> {
        let (sink, _) = solve_bands(source, lights, config, &Silent, |setup| {
            Ok(Assemble::new(setup))
        })
        .unwrap();
        sink.into_solutions()
    }

    /// A 32×32 sphere (normals up to 60° from the view: rows above and below it are outside
    /// the mask) under 12 lights, four of whose images read 10–25% off their stated intensity,
    /// solved by the default method (noise model and intensity gains estimated from the whole
    /// stack), grey, per channel and for one shared normal: bands of 5 rows over every row, and
    /// of 7 rows over the mask's rows only, give the solutions of the one-band run bit for bit
    /// (rows no band covers stay outside, as they are in the one-band run).
    #[test]
    fn bands_solve_like_one_band_bit_for_bit() {
        let (normals, mask) = sphere(32, 60.0);
        let bbox = mask.bounding_box().unwrap();
        assert!(bbox.y0 > 0 && bbox.y1 < 32, "{bbox:?}");
        let lights = Lights::fibonacci(12, 30.0).unwrap();
        let mut scale = [1.0; 12];
        for (k, s) in [(1, 0.8), (4, 1.25), (7, 0.9), (10, 1.15)] {
            scale[k] = s;
        }
        let grey = lambertian_stack(&normals, &mask, &lights, &[0.7], &scale);
        let rgb = lambertian_stack(&normals, &mask, &lights, &[0.8, 0.5, 0.25], &scale);
        let cases = [
            ("grey", &grey, ColorSolve::SharedNormal),
            ("per channel", &rgb, ColorSolve::PerChannel),
            ("shared normal", &rgb, ColorSolve::SharedNormal),
        ];
        for (name, stack, color) in cases {
            let config = Config {
                color,
                integration: None,
                ..Config::default()
            };
            let whole = assembled(&mut WholeStack::new(stack, &mask), &lights, &config);
            assert_eq!(
                whole.len(),
                if name == "grey" { 1 } else { 3 },
                "{name}: channels"
            );
            // The model is not trivial: the wrong intensities were corrected.
            assert!(whole[0].gains.applied, "{name}: {:?}", whole[0].gains);
            assert_eq!(
                whole[0].status.map(|s| *s == PixelStatus::Solved).count(),
                mask.count(),
                "{name}"
            );
            for (rows, band_rows) in [(0..32, 5), (bbox.y0..bbox.y1, 7)] {
                let mut source = RowBands::new(stack, &mask, rows.clone(), band_rows);
                assert!(source.bands() > 2);
                let banded = assembled(&mut source, &lights, &config);
                assert_same_solutions(
                    &banded,
                    &whole,
                    &format!("{name}, rows {rows:?} in bands of {band_rows}"),
                );
            }
        }
    }

    /// Records the progress calls it receives.
    #[derive(Default)]
    struct Recorder(Mutex<Vec<String>>);

    impl Progress for Recorder {
        fn begin(&self, stage: &str, total: u64) {
            self.0
                .lock()
                .unwrap()
                .push(format!("begin {stage} {total}"));
        }
        fn advance(&self, units: u64) {
            self.0.lock().unwrap().push(format!("advance {units}"));
        }
        fn end(&self) {
            self.0.lock().unwrap().push("end".into());
        }
    }

    /// A source of many bands reports one step a band (and not the solves within a band); a
    /// source of one band reports the solve's own stage instead.
    #[test]
    fn progress_is_one_step_a_band_or_the_solve_itself() {
        let (normals, mask) = sphere(24, 60.0);
        let lights = Lights::fibonacci(8, 30.0).unwrap();
        let stack = lambertian_stack(&normals, &mask, &lights, &[0.6], &[1.0; 8]);
        let config = Config {
            integration: None,
            ..Config::default()
        };
        let many = Recorder::default();
        let mut source = RowBands::new(&stack, &mask, 0..24, 5);
        solve_bands(&mut source, &lights, &config, &many, |s| {
            Ok(Assemble::new(s))
        })
        .unwrap();
        let mut expected = vec!["begin bands 5".to_string()];
        expected.extend(std::iter::repeat_n("advance 1".to_string(), 5));
        expected.push("end".into());
        assert_eq!(*many.0.lock().unwrap(), expected);

        let one = Recorder::default();
        let mut source = WholeStack::new(&stack, &mask);
        solve_bands(&mut source, &lights, &config, &one, |s| {
            Ok(Assemble::new(s))
        })
        .unwrap();
        let events = one.0.lock().unwrap();
        assert!(events[0].starts_with("begin solve "), "{events:?}");
        assert!(!events.iter().any(|e| e.contains("bands")), "{events:?}");
        assert_eq!(events.last().map(String::as_str), Some("end"));
    }

    /// The setup of a `width`×`height` grey run of `count` images with unit models.
    fn setup(width: usize, height: usize, count: usize) -> Setup {
        Setup {
            width,
            height,
            band_rows: height,
            blank: Blank {
                width,
                channels: 1,
                models: vec![ImageModel::unit(count)],
                shared: false,
                options: SolveOptions::default(),
            },
        }
    }

    /// A solved pixel whose numbers identify it: g = (x, y, 1 + band), residual, samples and
    /// condition from the same.
    fn solved(x: usize, y: usize, band: usize) -> PixelSolution {
        PixelSolution {
            g: nalgebra::Vector3::new(x as f64, y as f64, 1.0 + band as f64),
            residual: 0.01 * (1 + x + y) as f64,
            samples: 3 + x + band,
            condition: 1.5 + y as f64,
            status: PixelStatus::Solved,
            robust: (x + y + band).is_multiple_of(2),
        }
    }

    /// A `width`×`rows` band with every pixel solved ([`solved`]) but (0, 0), left too dark.
    fn band(width: usize, rows: usize, count: usize, id: usize) -> Solution {
        let mut pixels: Vec<_> = (0..rows)
            .flat_map(|y| (0..width).map(move |x| (x, y, solved(x, y, id))))
            .collect();
        pixels[0].2.status = PixelStatus::Dark;
        hand_made_solution(width, rows, count, &pixels)
    }

    /// A band that covers the whole image is kept as it is (its own gains included); with no
    /// band at all the assembly is all blank.
    #[test]
    fn assemble_keeps_a_whole_band_as_it_is() {
        let s = setup(4, 3, 5);
        let mut whole = band(4, 3, 5, 1);
        whole.gains = GainEstimate {
            gains: vec![0.9, 1.1, 1.0, 1.2, 0.8],
            applied: true,
            ..GainEstimate::unit(5)
        };
        let mut a = Assemble::new(&s);
        a.band(0, vec![whole.clone()]).unwrap();
        let out = a.into_solutions();
        // The band's gains (not the blank rows' unit ones) and every map, bit for bit.
        assert_same_solutions(&out, std::slice::from_ref(&whole), "whole band");
        assert!(out[0].gains.applied);

        let empty = Assemble::new(&s).into_solutions();
        assert_eq!(empty.len(), 1);
        assert_eq!((empty[0].status.width(), empty[0].status.height()), (4, 3));
        assert!(
            empty[0]
                .status
                .data()
                .iter()
                .all(|p| *p == PixelStatus::Outside)
        );
        assert!(
            empty[0]
                .g
                .data()
                .iter()
                .all(|g| g.iter().all(|v| v.is_nan()))
        );
    }

    /// Partial bands — one starting at row 0 but shorter than the image, one further down —
    /// are pasted row for row into a blank assembly: their rows hold their values, every other
    /// row stays outside the mask (NaN g, residual and condition, no samples, not robust), and
    /// the gains are the run's models', not the bands'. A band past the last row is refused.
    #[test]
    fn assemble_pastes_partial_bands_into_blank_rows() {
        let (w, h) = (3, 9);
        let s = setup(w, h, 4);
        let mut a = Assemble::new(&s);
        let mut top = band(w, 2, 4, 1);
        top.gains.gains = vec![2.0; 4];
        let middle = band(w, 3, 4, 2);
        a.band(0, vec![top.clone()]).unwrap();
        a.band(5, vec![middle.clone()]).unwrap();
        let err = a.band(8, vec![band(w, 2, 4, 3)]).unwrap_err();
        assert!(
            matches!(err, crate::Error::DimensionMismatch { .. }),
            "{err}"
        );
        let out = a.into_solutions();
        let out = &out[0];
        assert_eq!((out.status.width(), out.status.height()), (w, h));
        assert_eq!(out.gains.gains, vec![1.0; 4]);
        for y in 0..h {
            let from = match y {
                0..=1 => Some((&top, y)),
                5..=7 => Some((&middle, y - 5)),
                _ => None,
            };
            for x in 0..w {
                let got = (
                    *out.g.at(x, y),
                    *out.residual.at(x, y),
                    *out.samples.at(x, y),
                    *out.condition.at(x, y),
                    *out.status.at(x, y),
                    *out.robust.at(x, y),
                );
                match from {
                    Some((b, by)) => {
                        let want = (
                            *b.g.at(x, by),
                            *b.residual.at(x, by),
                            *b.samples.at(x, by),
                            *b.condition.at(x, by),
                            *b.status.at(x, by),
                            *b.robust.at(x, by),
                        );
                        // Bit patterns: the dark pixel's NaNs count as equal.
                        let bits =
                            |t: &(nalgebra::Vector3<f32>, f32, u16, f32, PixelStatus, bool)| {
                                (
                                    t.0.map(f32::to_bits),
                                    t.1.to_bits(),
                                    t.2,
                                    t.3.to_bits(),
                                    t.4,
                                    t.5,
                                )
                            };
                        assert_eq!(bits(&got), bits(&want), "pixel ({x}, {y})");
                    }
                    None => {
                        assert_eq!(got.4, PixelStatus::Outside, "pixel ({x}, {y})");
                        assert!(
                            got.0.iter().all(|v| v.is_nan()) && got.1.is_nan() && got.3.is_nan()
                        );
                        assert_eq!((got.2, got.5), (0, false), "pixel ({x}, {y})");
                    }
                }
            }
        }
        // The bands' own rows were not all alike: the paste kept each band's numbers.
        assert_ne!(out.g.at(1, 1).z, out.g.at(1, 6).z);
    }

    /// One shared normal only for three channels under [`ColorSolve::SharedNormal`].
    #[test]
    fn shared_normal_only_for_rgb_under_the_shared_solve() {
        let with = |color| Config {
            color,
            ..Config::default()
        };
        assert!(shared_normal(3, &with(ColorSolve::SharedNormal)));
        assert!(!shared_normal(3, &with(ColorSolve::PerChannel)));
        assert!(!shared_normal(1, &with(ColorSolve::SharedNormal)));
        assert!(!shared_normal(1, &with(ColorSolve::PerChannel)));
    }
}
