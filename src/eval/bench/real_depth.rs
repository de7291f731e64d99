//! Every integrator on the shared integration data ([`real_depth`]): DiLiGenT cat and bear
//! (their true normals integrated with the perspective camera `K.txt`; mean absolute depth
//! error in mm after the median scale fit, the bilateral-normal-integration benchmark's metric)
//! and the vase (its exact gradients, and with Gaussian noise of [`VASE_NOISE`] of the largest
//! gradient, one draw; RMSE after the mean offset, pixel units; bilateral integration, which
//! takes normals, gets (−p, −q, 1) normalised). Missing sets are skipped and listed.

use super::diligent::OBJECTS;
use crate::camera::Intrinsics;
use crate::error::{Error, Result};
use crate::eval::metrics::{depth_errors, scaled_depth_errors};
use crate::grid::{Grid, ScalarMap};
use crate::integrate::{
    Censoring, IntegrationOptions, Integrator, LinearSolver, integrate_censored_gradients,
    integrate_normals,
};
use crate::io::decode::{read_exr_channel, read_image, read_mask, read_normal_map};
use crate::progress::Silent;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Relative gradient noise of the noisy vase: this fraction of the largest gradient.
pub const VASE_NOISE: f32 = 0.005;
/// The metric of the DiLiGenT rows.
pub const DILIGENT_METRIC: &str = "mean abs. depth error after median scale (mm)";
/// The metric of the vase rows.
pub const VASE_METRIC: &str = "RMSE after the mean offset (px)";

/// One integrator on one data set.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RealDepthRow {
    /// The data set: `cat`, `bear`, `vase` or `vase with 0.5% noise`.
    pub dataset: String,
    /// Integrator name.
    pub method: &'static str,
    /// The error, in the units of `metric`.
    pub error: f64,
    /// What `error` measures.
    pub metric: &'static str,
    /// Wall time of the integration, seconds.
    pub seconds: f64,
}

/// A data set that was not there.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Absent {
    /// The data set, as a phrase (`cat`, `the vase`).
    pub name: String,
    /// The folder or file that is missing.
    pub path: PathBuf,
}

/// The rows, and the data sets skipped.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct RealDepth {
    /// Data sets outer, integrators ([`Integrator::ALL`]) inner.
    pub rows: Vec<RealDepthRow>,
    /// The data sets not found, in the order they were looked for.
    pub absent: Vec<Absent>,
}

/// The folder of DiLiGenT `object`'s integration data under a data folder:
/// `data/integration/<object>` (`normal_map.png`, `mask.png`, `depth_gt.exr`, `K.txt`).
pub fn object_dir(data: &Path, object: &str) -> PathBuf {
    data.join("integration").join(object)
}

/// The vase's file under a data folder: `data/integration/vase/vase.exr` (channels Z, p, q and
/// mask).
pub fn vase_path(data: &Path) -> PathBuf {
    data.join("integration/vase/vase.exr")
}

/// Every integrator on the DiLiGenT objects ([`OBJECTS`]) and the vase under `data`, skipping
/// those absent.
///
/// # Errors
/// Any error of reading a data set that is present, or of integrating it.
pub fn real_depth(data: &Path) -> Result<RealDepth> {
    let mut out = RealDepth::default();
    for object in OBJECTS {
        let dir = object_dir(data, object);
        if !dir.join("K.txt").is_file() {
            out.absent.push(Absent {
                name: object.to_string(),
                path: dir,
            });
            continue;
        }
        out.rows.extend(diligent_rows(&dir, object)?);
    }
    let vase = vase_path(data);
    if vase.is_file() {
        out.rows.extend(vase_rows(&vase)?);
    } else {
        out.absent.push(Absent {
            name: "the vase".into(),
            path: vase,
        });
    }
    Ok(out)
}

/// Every integrator on one DiLiGenT object's folder `dir` (see [`object_dir`]), named `name`.
///
/// # Errors
/// Any error of reading the folder or integrating.
pub fn diligent_rows(dir: &Path, name: &str) -> Result<Vec<RealDepthRow>> {
    let normals = read_normal_map(&dir.join("normal_map.png"))?;
    let mask = read_mask(&dir.join("mask.png"))?;
    let gt = read_image(&dir.join("depth_gt.exr"))?;
    let gt = Grid::from_vec(gt.width, gt.height, gt.data)?;
    let camera = Intrinsics::from_file(&dir.join("K.txt"))?;
    let mut rows = Vec::new();
    for m in Integrator::ALL {
        let o = IntegrationOptions {
            method: m,
            camera: Some(camera),
            ..IntegrationOptions::default()
        };
        let t = Instant::now();
        let r = integrate_normals(&normals, &mask, &o, &Silent)?;
        let seconds = t.elapsed().as_secs_f64();
        let e = scaled_depth_errors(&r.depth, &gt, &mask)?;
        rows.push(RealDepthRow {
            dataset: name.to_string(),
            method: m.name(),
            error: e.mean_abs,
            metric: DILIGENT_METRIC,
            seconds,
        });
    }
    Ok(rows)
}

/// Every integrator on the vase `path` (see [`vase_path`]): its exact gradients, then with
/// noise.
///
/// # Errors
/// Any error of reading the file or integrating.
pub fn vase_rows(path: &Path) -> Result<Vec<RealDepthRow>> {
    let exr = |name: &str| read_exr_channel(path, name);
    let (z, pv, qv, mv) = (exr("Z")?, exr("p")?, exr("q")?, exr("mask")?);
    let mask = mv.map(|v| *v > 0.5);
    // The file's p = ∂Z/∂row and q = ∂Z/∂column; ours: p = ∂z/∂x, q = ∂z/∂y (y up).
    let (p, q): (ScalarMap, ScalarMap) = (qv.clone(), pv.map(|v| -v));
    let max = p
        .data()
        .iter()
        .chain(q.data())
        .filter(|v| v.is_finite())
        .fold(0f32, |m, v| m.max(v.abs()));
    // The file's gradients are clipped at their largest magnitude (±10).
    let clipped = Censoring::ClippedAt(max);
    let noise = Normal::new(0.0f32, VASE_NOISE * max).map_err(|e| Error::Dataset {
        path: path.to_path_buf(),
        reason: format!("gradient noise of {VASE_NOISE} × {max}: {e}"),
    })?;
    let mut rng = rand::rngs::ChaCha8Rng::seed_from_u64(0);
    let noisy = (
        p.map(|v| v + noise.sample(&mut rng)),
        q.map(|v| v + noise.sample(&mut rng)),
    );
    let mut rows = Vec::new();
    for (name, (p, q)) in [
        ("vase", (&p, &q)),
        ("vase with 0.5% noise", (&noisy.0, &noisy.1)),
    ] {
        // Bilateral integration takes normals: n ∝ (−p, −q, 1).
        let normals = Grid::from_fn(p.width(), p.height(), |c, r| {
            let (a, b) = (*p.at(c, r), *q.at(c, r));
            if *mask.at(c, r) && a.is_finite() && b.is_finite() {
                crate::nalgebra::Vector3::new(-a, -b, 1.0).normalize()
            } else {
                crate::nalgebra::Vector3::repeat(f32::NAN)
            }
        });
        for m in Integrator::ALL {
            let t = Instant::now();
            let d = if matches!(m, Integrator::Bilateral | Integrator::Auto) {
                let o = IntegrationOptions {
                    method: m,
                    ..IntegrationOptions::default()
                };
                integrate_normals(&normals, &mask, &o, &Silent)?.depth
            } else {
                integrate_censored_gradients(p, q, &clipped, &mask, m, LinearSolver::Auto)?.0
            };
            let seconds = t.elapsed().as_secs_f64();
            let e = depth_errors(&d, &z, &mask)?;
            rows.push(RealDepthRow {
                dataset: name.to_string(),
                method: m.name(),
                error: e.rmse,
                metric: VASE_METRIC,
                seconds,
            });
        }
    }
    Ok(rows)
}
