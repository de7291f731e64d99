//! Every estimator on DiLiGenT objects (Shi et al. 2019): the mean, median and 95th-percentile
//! angular error against `normal_gt.exr` and the solve time with all 96 lights
//! ([`method_rows`]), and the error against the light count on well-spread subsets of them
//! ([`light_subset_rows`], [`crate::capture::lights::Lights::spread`]).

use crate::capture::dataset::{Capture, is_diligent_dir};
use crate::capture::stack::LoadOptions;
use crate::error::{Error, Result};
use crate::eval::metrics::angular_errors;
use crate::grid::NormalMap;
use crate::io::decode::read_normal_map;
use crate::progress::Silent;
use crate::ps::solve::{Method, SolveOptions};
use crate::run::pipeline::{Config, reconstruct};
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// The DiLiGenT objects of the benchmark pages, in the order of their rows.
pub const OBJECTS: [&str; 2] = ["cat", "bear"];

/// Light counts of the light-count sweep (well-spread subsets of the 96).
pub const LIGHT_COUNTS: [usize; 7] = [4, 6, 8, 12, 24, 48, 96];

/// The folder of `object` under a data folder: `data/diligent/<object>PNG`.
pub fn object_dir(data: &Path, object: &str) -> PathBuf {
    data.join("diligent").join(format!("{object}PNG"))
}

/// A DiLiGenT object loaded for measuring: its capture and true normals.
#[derive(Debug, Clone)]
pub struct Object {
    /// The object's name.
    pub name: String,
    /// The capture (images, lights, mask).
    pub capture: Capture,
    /// The true normals (`normal_gt.exr`).
    pub truth: NormalMap,
}

impl Object {
    /// Loads the DiLiGenT-layout folder `dir` as the object `name`.
    ///
    /// # Errors
    /// [`Error::Dataset`] when `dir` is not a DiLiGenT-layout folder; any error of loading it
    /// or its `normal_gt.exr`.
    pub fn load(dir: &Path, name: &str) -> Result<Self> {
        if !is_diligent_dir(dir) {
            return Err(Error::Dataset {
                path: dir.to_path_buf(),
                reason: "not a DiLiGenT-layout folder (filenames.txt, light_directions.txt)".into(),
            });
        }
        Ok(Object {
            name: name.to_string(),
            capture: Capture::from_diligent(dir, &LoadOptions::default(), &Silent)?,
            truth: read_normal_map(&dir.join("normal_gt.exr"))?,
        })
    }
}

/// One estimator on one object with all its lights.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MethodRow {
    /// The object.
    pub object: String,
    /// Estimator name.
    pub method: &'static str,
    /// Mean angular error, degrees.
    pub mean_deg: f64,
    /// Median angular error, degrees.
    pub median_deg: f64,
    /// 95th percentile, degrees.
    pub p95_deg: f64,
    /// Upper-median wall time of the solve and normals, seconds.
    pub seconds: f64,
}

/// Config of a normals-only run with estimator `m`.
fn normals_only(m: Method) -> Config {
    Config {
        solve: SolveOptions::with_method(m),
        integration: None,
        ..Config::default()
    }
}

/// Every estimator of [`Method::ALL`] on `object`: the error, and the upper median of `repeat`
/// timed runs (at least one).
///
/// # Errors
/// Any error of solving or comparing.
pub fn method_rows(object: &Object, repeat: usize) -> Result<Vec<MethodRow>> {
    let mut rows = Vec::new();
    for m in Method::ALL {
        let config = normals_only(m);
        let mut times = Vec::new();
        let mut error = None;
        for _ in 0..repeat.max(1) {
            let t = Instant::now();
            let recon = reconstruct(&object.capture, &config, &Silent)?;
            times.push(t.elapsed().as_secs_f64());
            error = Some(angular_errors(
                &recon.maps.normals,
                &object.truth,
                &object.capture.mask,
            )?);
        }
        times.sort_by(f64::total_cmp);
        let e = error.ok_or_else(|| Error::param("repeat", "no run"))?;
        rows.push(MethodRow {
            object: object.name.clone(),
            method: m.name(),
            mean_deg: e.mean_deg,
            median_deg: e.median_deg,
            p95_deg: e.p95_deg,
            seconds: times[times.len() / 2],
        });
    }
    Ok(rows)
}

/// One estimator on one object with a subset of its lights.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LightsRow {
    /// The object.
    pub object: String,
    /// Estimator name.
    pub method: &'static str,
    /// Number of lights (images) used.
    pub lights: usize,
    /// Mean angular error over the solved pixels, degrees.
    pub mean_deg: f64,
    /// Median angular error, degrees.
    pub median_deg: f64,
    /// Fraction of the mask with a normal.
    pub coverage: f64,
    /// Wall time of the solve and normals, seconds.
    pub seconds: f64,
}

/// Every estimator of [`Method::ALL`] on `object` with well-spread subsets of its lights, at
/// each of [`LIGHT_COUNTS`] it has: light counts outer, estimators inner.
///
/// # Errors
/// Any error of selecting, solving or comparing.
pub fn light_subset_rows(object: &Object) -> Result<Vec<LightsRow>> {
    let capture = &object.capture;
    let mut rows = Vec::new();
    for count in LIGHT_COUNTS {
        if count > capture.lights.len() {
            continue;
        }
        let subset = capture.select(&capture.lights.spread(count)?)?;
        for m in Method::ALL {
            let t = Instant::now();
            let recon = reconstruct(&subset, &normals_only(m), &Silent)?;
            let seconds = t.elapsed().as_secs_f64();
            let e = angular_errors(&recon.maps.normals, &object.truth, &subset.mask)?;
            rows.push(LightsRow {
                object: object.name.clone(),
                method: m.name(),
                lights: count,
                mean_deg: e.mean_deg,
                median_deg: e.median_deg,
                coverage: e.pixels as f64 / (e.pixels + e.missing).max(1) as f64,
                seconds,
            });
        }
    }
    Ok(rows)
}
