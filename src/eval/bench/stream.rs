//! The same stack solved in memory and streamed in row bands within a memory budget (`bench
//! stream`): wall time and peak resident memory of each, and their ratios. A process's peak
//! memory is only measurable from outside it, so both runs are child processes of the caller,
//! alternating so that machine load hits both alike; [`StreamBenchPlan`] says what they run
//! ([`StreamBenchPlan::runs`]) and turns their measurements into a [`StreamBenchReport`].

use crate::error::{Error, Result};
use crate::integrate::Integrator;
use crate::stats::median;
use serde::Serialize;
use std::path::{Path, PathBuf};

/// Runs of each kind by default; medians are reported.
pub const DEFAULT_REPEAT: usize = 1;
/// The budget of the streamed run by default, as a size text (see
/// [`crate::run::stream::parse_size`]).
pub const DEFAULT_MAX_MEMORY: &str = "2G";
/// Prefix of the image files a benchmark folder holds.
pub const IMAGE_PREFIX: &str = "img_";

/// What to run: a folder of `img_*` images with `lights.json` and optionally `mask.png` (as
/// `cargo run --release --example large_stack` writes), solved whole and in row bands.
#[derive(Debug, Clone, PartialEq)]
pub struct StreamBenchPlan {
    /// The folder.
    pub dir: PathBuf,
    /// Its `img_*` files, sorted by name.
    pub images: Vec<PathBuf>,
    /// Its lights file.
    pub lights: PathBuf,
    /// Its mask, when present and wanted.
    pub mask: Option<PathBuf>,
    /// The streamed run's memory budget, bytes.
    pub max_memory: u64,
    /// The integrator of both runs (`None`: normals only).
    pub integrator: Option<Integrator>,
    /// Runs of each kind, at least one.
    pub repeat: usize,
}

/// One child run of the plan.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StreamRun {
    /// The stack loaded whole.
    InMemory,
    /// The stack streamed in row bands within [`StreamBenchPlan::max_memory`].
    Streamed,
}

/// What one child run measured.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Measurement {
    /// Which run.
    pub run: StreamRun,
    /// Wall time, seconds.
    pub wall_s: f64,
    /// Peak resident memory, bytes (0 where the system does not tell).
    pub peak_rss_bytes: u64,
}

/// Medians of one kind of run.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct RunSummary {
    /// Median wall time, seconds.
    pub wall_s: f64,
    /// Median peak resident memory, bytes.
    pub peak_rss_bytes: f64,
}

/// The comparison.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct StreamBenchReport {
    /// The folder.
    pub dir: PathBuf,
    /// Number of images.
    pub images: usize,
    /// Worker threads.
    pub threads: usize,
    /// The integrator's name, or `none`.
    pub integrate: &'static str,
    /// Whether the runs used the folder's mask.
    pub mask: bool,
    /// The streamed run's budget, bytes.
    pub max_memory_bytes: u64,
    /// The streamed run's memory plan, as its report gives it.
    pub plan: serde_json::Value,
    /// The runs with the stack in memory.
    pub in_memory: RunSummary,
    /// The streamed runs.
    pub streamed: RunSummary,
    /// Streamed wall time over in-memory wall time.
    pub time_ratio_streamed_over_in_memory: f64,
    /// Whether the streamed run's peak stayed within the budget.
    pub peak_under_budget: bool,
}

impl StreamBenchPlan {
    /// The plan for the folder `dir`: its `img_*` files, `lights.json`, and `mask.png` when
    /// `use_mask` and present.
    ///
    /// # Errors
    /// [`Error::Io`] when the folder cannot be listed; [`Error::Dataset`] when it holds no
    /// `img_*` file.
    pub fn new(
        dir: &Path,
        max_memory: u64,
        use_mask: bool,
        integrator: Option<Integrator>,
        repeat: usize,
    ) -> Result<Self> {
        let mut images: Vec<PathBuf> = std::fs::read_dir(dir)
            .map_err(|e| Error::io(dir, e))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| {
                p.file_name()
                    .and_then(|n| n.to_str())
                    .is_some_and(|n| n.starts_with(IMAGE_PREFIX))
            })
            .collect();
        images.sort();
        if images.is_empty() {
            return Err(Error::Dataset {
                path: dir.to_path_buf(),
                reason: format!("no {IMAGE_PREFIX}* files"),
            });
        }
        let mask = dir.join("mask.png");
        Ok(StreamBenchPlan {
            dir: dir.to_path_buf(),
            images,
            lights: dir.join("lights.json"),
            mask: (use_mask && mask.is_file()).then_some(mask),
            max_memory,
            integrator,
            repeat: repeat.max(1),
        })
    }

    /// The integrator's name, or `none`.
    pub fn integrate_name(&self) -> &'static str {
        self.integrator.map_or("none", |m| m.name())
    }

    /// The child runs, in order: in memory then streamed, [`Self::repeat`] times.
    pub fn runs(&self) -> Vec<StreamRun> {
        (0..self.repeat)
            .flat_map(|_| [StreamRun::InMemory, StreamRun::Streamed])
            .collect()
    }

    /// The report from the runs' `measurements` and the streamed run's memory plan `plan`.
    pub fn report(
        &self,
        measurements: &[Measurement],
        plan: serde_json::Value,
    ) -> StreamBenchReport {
        let summary = |run: StreamRun| {
            let of: Vec<&Measurement> = measurements.iter().filter(|m| m.run == run).collect();
            RunSummary {
                wall_s: median(of.iter().map(|m| m.wall_s).collect()),
                peak_rss_bytes: median(of.iter().map(|m| m.peak_rss_bytes as f64).collect()),
            }
        };
        let (in_memory, streamed) = (summary(StreamRun::InMemory), summary(StreamRun::Streamed));
        StreamBenchReport {
            dir: self.dir.clone(),
            images: self.images.len(),
            threads: rayon::current_num_threads(),
            integrate: self.integrate_name(),
            mask: self.mask.is_some(),
            max_memory_bytes: self.max_memory,
            plan,
            in_memory,
            streamed,
            time_ratio_streamed_over_in_memory: streamed.wall_s / in_memory.wall_s,
            peak_under_budget: streamed.peak_rss_bytes <= self.max_memory as f64,
        }
    }
}
