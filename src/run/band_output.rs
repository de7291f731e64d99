//! The outputs of a streamed run, written band by band as the bands are solved
//! ([`crate::run::stream::reconstruct_and_write_streamed`]).
//!
//! Each band's per-pixel maps become rows of `normal.exr`, `albedo.exr`, `residual.exr`,
//! `mask.png` and `normal.png` on writer threads ([`crate::io::encode`]) and are then dropped.
//! Rows outside the mask's bounding box, which no band covers, are written as the empty
//! solution an in-memory run has there. What needs the whole image is kept: the normals and
//! solved mask (integrability, integration), the albedo (the 99th-percentile scaling of
//! `albedo.png`) and the finite residuals (their median).

use crate::error::Result;
use crate::grid::{Grid, Mask, NormalMap, ScalarMap};
use crate::io::exr::ExrRows;
use crate::io::output::OutputDir;
use crate::io::png::PngRows;
use crate::ps::solve::Solution;
use crate::run::bands::{BandSink, Setup};
use crate::run::pipeline::{
    ChannelModel, NORMAL_CHANNELS, RESIDUAL_CHANNELS, ResidualSummary, Tallies, albedo_channels,
    albedo_png, map_rows, pixel_maps,
};
use crate::stats::summarize_values;

/// Writes the per-pixel outputs of a streamed run band by band.
pub(crate) struct BandOutput {
    width: usize,
    height: usize,
    /// The next row to write.
    next: usize,
    /// Rows of the blank bands written outside the mask's bounding box.
    blank_rows: usize,
    /// Blank solutions of `blank_rows` rows, made once.
    blank: Vec<Solution>,
    normal: ExrRows,
    albedo: ExrRows,
    residual: ExrRows,
    mask: PngRows,
    normal_png: PngRows,
    normals: NormalMap,
    solved: Mask,
    albedo_maps: Vec<ScalarMap>,
    residuals: Vec<f32>,
    tallies: Tallies,
    models: Vec<ChannelModel>,
}

/// What the band-by-band writing kept for the rest of the run.
pub(crate) struct Written {
    /// Unit normals of the whole image.
    pub normals: NormalMap,
    /// Pixels with a normal.
    pub solved: Mask,
    /// Counts over the whole image.
    pub tallies: Tallies,
    /// Mean and median residual over the solved pixels.
    pub residual: ResidualSummary,
    /// What each channel's solve assumed.
    pub models: Vec<ChannelModel>,
}

impl BandOutput {
    /// Opens the files of `out` that are written band by band, for a run set up as `setup`;
    /// `attributes(file)` are the EXR header attributes of `file`.
    ///
    /// # Errors
    /// [`crate::Error::Io`] when a temporary cannot be made or a writer cannot start.
    pub(crate) fn start(
        out: &OutputDir,
        setup: &Setup,
        attributes: &dyn Fn(&str) -> Vec<(&'static str, String)>,
    ) -> Result<Self> {
        let (w, h) = (setup.width, setup.height);
        let blank_rows = setup.band_rows.clamp(1, h.max(1));
        let blank = setup.empty(blank_rows);
        let models = ChannelModel::of(&blank);
        // One albedo map per solved channel (grey, or R, G, B for either colour solve).
        let albedo_count = blank.len();
        let exr = |name: &str, names: &[&str]| -> Result<ExrRows> {
            ExrRows::start(out.begin(name)?, w, h, names, &attributes(name))
        };
        Ok(BandOutput {
            width: w,
            height: h,
            next: 0,
            blank_rows,
            blank,
            normal: exr("normal.exr", &NORMAL_CHANNELS)?,
            albedo: exr("albedo.exr", albedo_channels(albedo_count)?)?,
            residual: exr("residual.exr", &RESIDUAL_CHANNELS)?,
            mask: PngRows::start(out.begin("mask.png")?, w, h, 1)?,
            normal_png: PngRows::start(out.begin("normal.png")?, w, h, 3)?,
            normals: Grid::new(w, h, nalgebra::Vector3::repeat(f32::NAN)),
            solved: Grid::new(w, h, false),
            albedo_maps: vec![Grid::new(w, h, f32::NAN); albedo_count],
            residuals: Vec::new(),
            tallies: Tallies::default(),
            models,
        })
    }

    /// Writes the rows of `solutions` (full width) from row `self.next` on.
    fn emit(&mut self, solutions: &[Solution]) -> Result<()> {
        let maps = pixel_maps(solutions);
        let rows = maps.status.height();
        let span = self.next * self.width..(self.next + rows) * self.width;
        self.tallies.add(&Tallies::of(&maps));
        self.residuals.extend(
            maps.residual
                .data()
                .iter()
                .copied()
                .filter(|v| v.is_finite()),
        );
        self.normals.data_mut()[span.clone()].copy_from_slice(maps.normals.data());
        self.solved.data_mut()[span.clone()].copy_from_slice(maps.solved.data());
        let file = map_rows(&maps);
        drop(maps);
        for (full, band) in self.albedo_maps.iter_mut().zip(&file.albedo) {
            full.data_mut()[span.clone()].copy_from_slice(band);
        }
        self.normal.write(file.normal)?;
        self.albedo.write(file.albedo)?;
        self.residual.write(file.residual)?;
        self.mask.write(file.mask)?;
        self.normal_png.write(file.normal_png)?;
        self.next += rows;
        Ok(())
    }

    /// Writes blank rows up to row `y`.
    fn fill_to(&mut self, y: usize) -> Result<()> {
        while self.next < y {
            let rows = (y - self.next).min(self.blank_rows);
            if rows == self.blank_rows {
                let blank = std::mem::take(&mut self.blank);
                let result = self.emit(&blank);
                self.blank = blank;
                result?;
            } else {
                let part: Vec<Solution> = self.blank.iter().map(|s| s.top_rows(rows)).collect();
                self.emit(&part)?;
            }
        }
        Ok(())
    }

    /// Writes the rows below the last band, waits for every writer and stages the files and
    /// `albedo.png` in `out`; returns what the rest of the run needs.
    ///
    /// # Errors
    /// The first writer's error.
    pub(crate) fn finish(mut self, out: &mut OutputDir) -> Result<Written> {
        self.fill_to(self.height)?;
        out.add(self.normal.finish()?);
        out.add(self.albedo.finish()?);
        out.add(self.residual.finish()?);
        out.add(self.mask.finish()?);
        out.add(self.normal_png.finish()?);
        let preview = albedo_png(&self.albedo_maps);
        out.stage_png8(
            "albedo.png",
            self.width,
            self.height,
            self.albedo_maps.len(),
            &preview,
        )?;
        let summary = summarize_values(self.residuals);
        Ok(Written {
            normals: self.normals,
            solved: self.solved,
            tallies: self.tallies,
            residual: ResidualSummary {
                mean: summary.mean,
                median: summary.median,
            },
            models: self.models,
        })
    }
}

impl BandSink for BandOutput {
    fn band(&mut self, y0: usize, solutions: Vec<Solution>) -> Result<()> {
        self.fill_to(y0)?;
        for (m, s) in self.models.iter_mut().zip(&solutions) {
            m.add_band_passes(s);
        }
        self.emit(&solutions)
    }
}
