//! `photostereo._native`: the library's stages for Python, on numpy arrays.
//!
//! Every function checks its arguments and returns the library's errors as Python exceptions
//! (`photostereo.Error`, a `ValueError`, or `OSError` for files; `TypeError` for an array of
//! the wrong type); none of them can abort the interpreter. Work runs with the GIL released.
//! The friendly signatures, docstrings and type stubs live in the Python package
//! (`python/photostereo/__init__.py`, `_native.pyi`); this module takes its arguments as
//! that package passes them.

use ndarray::{Array2, ArrayView2, ArrayViewD, Ix2, Ix3, Ix4};
use numpy::{
    IntoPyArray, PyArray2, PyReadonlyArray2, PyReadonlyArray3, PyReadonlyArrayDyn,
    PyUntypedArrayMethods,
};
use photostereo::calibrate::near::{NearOptions, calibrate_two_balls};
use photostereo::calibrate::{ChromeOptions, calibrate_chrome};
use photostereo::capture::arrays::{Sample, normals_from_array, normals_to_array};
use photostereo::capture::stack::{ColorMode, GREY_WEIGHTS, LoadOptions, Transfer};
use photostereo::capture::{Capture, CaptureFiles, ImageStack, Lights};
use photostereo::grid::{Grid, Mask, ScalarMap};
use photostereo::integrate::{IntegrationOptions, Integrator, integrate_normals, usable_normal};
use photostereo::io::decode::{ImageArray, MAX_IMAGE_SAMPLES, read_array, read_exr_channels};
use photostereo::io::output::{Overwrite, write_exr_file};
use photostereo::progress::Silent;
use photostereo::ps::color::ColorSolve;
use photostereo::ps::intensities::GainEstimate;
use photostereo::ps::solve::{ImageModel, Method, PixelStatus};
use photostereo::run::pipeline::{Config, estimate_models, reconstruct_normals_with_models};
use photostereo::run::{CaptureChecks, Warning};
use photostereo::sfs::reflectance_map::ReflectanceMap;
use photostereo::synth::reflectance::{
    BlinnPhong, Diffuse, Material, Mirror, Phong, Specular, TorranceSparrow, Ward,
};
use photostereo::synth::render::{RenderOptions, render as render_scene};
use photostereo::synth::scene::{Albedo, SceneKind};
use photostereo::{Error as LibError, Intrinsics};
use pyo3::create_exception;
use pyo3::exceptions::{
    PyFileExistsError, PyFileNotFoundError, PyOSError, PyTypeError, PyValueError,
};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use std::path::{Path, PathBuf};

create_exception!(
    _native,
    Error,
    PyValueError,
    "An error of photostereo's: bad input, or a capture it cannot solve. The message names the parameter, image or file."
);

/// The library's error as a Python exception: files → `OSError` (`FileNotFoundError` when
/// missing), everything else → [`Error`] (a `ValueError`).
fn py_err(e: LibError) -> PyErr {
    let msg = e.to_string();
    match &e {
        LibError::Io { cause, .. } if cause.kind() == std::io::ErrorKind::NotFound => {
            PyFileNotFoundError::new_err(msg)
        }
        LibError::Io { .. } => PyOSError::new_err(msg),
        LibError::OutputExists { .. } => PyFileExistsError::new_err(msg),
        _ => Error::new_err(msg),
    }
}

type PyRes<T> = PyResult<T>;

fn lib<T>(r: photostereo::Result<T>) -> PyRes<T> {
    r.map_err(py_err)
}

/// The dtype of `obj` as numpy prints it, or its Python type when it is not an array.
fn describe(obj: &Bound<'_, PyAny>) -> String {
    match obj.getattr("dtype") {
        Ok(d) => format!(
            "an array of dtype {}",
            d.str().map_or("?".into(), |s| s.to_string())
        ),
        Err(_) => format!(
            "a {}",
            obj.get_type().name().map_or("?".into(), |s| s.to_string())
        ),
    }
}

/// Image samples of one of the accepted types.
enum Samples<'py> {
    U8(PyReadonlyArrayDyn<'py, u8>),
    U16(PyReadonlyArrayDyn<'py, u16>),
    F32(PyReadonlyArrayDyn<'py, f32>),
    F64(PyReadonlyArrayDyn<'py, f64>),
}

impl<'py> Samples<'py> {
    /// An image stack argument: samples of an accepted type, `N×H×W` or `N×H×W×C`, of a size
    /// that may be read.
    fn images(obj: &Bound<'py, PyAny>, name: &str) -> PyRes<Self> {
        let s = Samples::extract(obj, name)?;
        check_image_ndim(&s, name)?;
        Ok(s)
    }

    fn extract(obj: &Bound<'py, PyAny>, name: &str) -> PyRes<Self> {
        if let Ok(a) = obj.extract::<PyReadonlyArrayDyn<'py, u16>>() {
            return Ok(Samples::U16(a));
        }
        if let Ok(a) = obj.extract::<PyReadonlyArrayDyn<'py, f32>>() {
            return Ok(Samples::F32(a));
        }
        if let Ok(a) = obj.extract::<PyReadonlyArrayDyn<'py, u8>>() {
            return Ok(Samples::U8(a));
        }
        if let Ok(a) = obj.extract::<PyReadonlyArrayDyn<'py, f64>>() {
            return Ok(Samples::F64(a));
        }
        Err(PyTypeError::new_err(format!(
            "{name}: got {}; a numpy array of uint8, uint16, float32 or float64 expected",
            describe(obj)
        )))
    }

    fn ndim(&self) -> usize {
        match self {
            Samples::U8(a) => a.ndim(),
            Samples::U16(a) => a.ndim(),
            Samples::F32(a) => a.ndim(),
            Samples::F64(a) => a.ndim(),
        }
    }

    fn shape(&self) -> Vec<usize> {
        match self {
            Samples::U8(a) => a.shape().to_vec(),
            Samples::U16(a) => a.shape().to_vec(),
            Samples::F32(a) => a.shape().to_vec(),
            Samples::F64(a) => a.shape().to_vec(),
        }
    }
}

/// Views of samples of one of the accepted types: what the work, without the GIL, reads.
enum Views<'a> {
    U8(ArrayViewD<'a, u8>),
    U16(ArrayViewD<'a, u16>),
    F32(ArrayViewD<'a, f32>),
    F64(ArrayViewD<'a, f64>),
}

impl Samples<'_> {
    fn views(&self) -> Views<'_> {
        match self {
            Samples::U8(a) => Views::U8(a.as_array()),
            Samples::U16(a) => Views::U16(a.as_array()),
            Samples::F32(a) => Views::F32(a.as_array()),
            Samples::F64(a) => Views::F64(a.as_array()),
        }
    }
}

/// Runs `$body` with `$v` bound to the view, whatever its type.
macro_rules! with_view {
    ($s:expr, $v:ident => $body:expr) => {
        match $s {
            Views::U8($v) => $body,
            Views::U16($v) => $body,
            Views::F32($v) => $body,
            Views::F64($v) => $body,
        }
    };
}

/// `images` as a stack: N×H×W or N×H×W×C.
fn stack_of<S: Sample>(
    images: ArrayViewD<'_, S>,
    lights: &Lights,
    options: &LoadOptions,
) -> photostereo::Result<ImageStack> {
    ImageStack::from_array_channels(four_d(images)?, lights, options)
}

/// `images` as `N×H×W×C`: grey `N×H×W` gains a channel axis of 1.
fn four_d<S>(images: ArrayViewD<'_, S>) -> photostereo::Result<ndarray::ArrayView4<'_, S>> {
    Ok(match images.ndim() {
        3 => shape_ok(images.into_dimensionality::<Ix3>())?.insert_axis(ndarray::Axis(3)),
        _ => shape_ok(images.into_dimensionality::<Ix4>())?,
    })
}

/// `images`, `lights` and `mask` as a capture (storing the part the mask spans).
/// `part`: the images are a part (a tile) of a larger capture solved under its models, so an
/// image dark or saturated in this part alone is kept. `ambient_last`: the last image is the
/// ambient frame (taken with every lamp off), subtracted from the others.
fn capture_of<S: Sample>(
    images: ArrayViewD<'_, S>,
    lights: Lights,
    mask: Option<ArrayView2<'_, bool>>,
    options: &LoadOptions,
    part: bool,
    ambient_last: bool,
) -> photostereo::Result<Capture> {
    let images = four_d(images)?;
    if ambient_last {
        let n = images.len_of(ndarray::Axis(0));
        if n < 2 {
            return Err(LibError::param(
                "ambient",
                "no image besides the ambient frame",
            ));
        }
        let (lit, frame) = (
            images.slice_axis(ndarray::Axis(0), ndarray::Slice::from(0..n - 1)),
            images.index_axis(ndarray::Axis(0), n - 1),
        );
        return if part {
            Capture::from_arrays_part_with_ambient(lit, frame, lights, mask, options)
        } else {
            Capture::from_arrays_channels_with_ambient(lit, frame, lights, mask, options)
        };
    }
    if part {
        Capture::from_arrays_part(images, lights, mask, options)
    } else {
        Capture::from_arrays_channels(images, lights, mask, options)
    }
}

fn shape_ok<T>(r: Result<T, ndarray::ShapeError>) -> photostereo::Result<T> {
    r.map_err(|e| LibError::param("images", e.to_string()))
}

/// Most samples `render` makes (4 GiB of float32 images).
const MAX_RENDERED_SAMPLES: usize = 1 << 30;

/// Most images a stack may have (far above any capture; it bounds what is allocated per
/// image before the images are read).
const MAX_IMAGES: usize = 1 << 16;

fn check_image_ndim(s: &Samples<'_>, name: &str) -> PyRes<()> {
    let nd = s.ndim();
    if nd != 3 && nd != 4 {
        return Err(PyValueError::new_err(format!(
            "{name}: shape {:?}; N×H×W (grey) or N×H×W×C (C = 1, 2, 3 or 4) expected, one image per light along the first axis",
            s.shape()
        )));
    }
    let shape = s.shape();
    let per_image = shape[1..].iter().try_fold(1usize, |a, &b| a.checked_mul(b));
    if shape[0] > MAX_IMAGES || per_image.is_none_or(|p| p > MAX_IMAGE_SAMPLES) {
        return Err(PyValueError::new_err(format!(
            "{name}: shape {shape:?}; at most {MAX_IMAGES} images of at most {MAX_IMAGE_SAMPLES} samples each are read"
        )));
    }
    Ok(())
}

/// Refuses an `H×W` (or `H×W×C`) map larger than an image may be, before it is copied.
fn check_map_size(shape: &[usize], name: &str) -> PyRes<()> {
    let n = shape.iter().try_fold(1usize, |a, &b| a.checked_mul(b));
    if n.is_none_or(|n| n > MAX_IMAGE_SAMPLES) {
        return Err(PyValueError::new_err(format!(
            "{name}: shape {shape:?}; at most {MAX_IMAGE_SAMPLES} values are read"
        )));
    }
    Ok(())
}

/// A mask argument: bool, or numbers (> 0 is set), H×W.
fn mask_arg(obj: Option<&Bound<'_, PyAny>>, name: &str) -> PyRes<Option<Array2<bool>>> {
    let Some(obj) = obj else { return Ok(None) };
    if obj.is_none() {
        return Ok(None);
    }
    if let Ok(a) = obj.extract::<PyReadonlyArrayDyn<'_, bool>>() {
        check_map_size(a.shape(), name)?;
        let v = a.as_array();
        let v = v.into_dimensionality::<Ix2>().map_err(|_| {
            PyValueError::new_err(format!("{name}: shape {:?}; H×W expected", a.shape()))
        })?;
        return Ok(Some(v.to_owned()));
    }
    let s = Samples::extract(obj, name).map_err(|_| {
        PyTypeError::new_err(format!(
            "{name}: got {}; a numpy array of bool (or of numbers, > 0 meaning set) expected",
            describe(obj)
        ))
    })?;
    if s.ndim() != 2 {
        return Err(PyValueError::new_err(format!(
            "{name}: shape {:?}; H×W expected",
            s.shape()
        )));
    }
    check_map_size(&s.shape(), name)?;
    Ok(Some(
        with_view!(s.views(), v => v.into_dimensionality::<Ix2>().map_err(|e| PyValueError::new_err(e.to_string()))?.map(|x| x.stored() > 0.0)),
    ))
}

fn lights_arg(
    directions: PyReadonlyArray2<'_, f64>,
    intensities: Option<PyReadonlyArray2<'_, f64>>,
) -> PyRes<Lights> {
    lib(Lights::from_array(
        directions.as_array(),
        intensities.as_ref().map(|i| i.as_array()),
    ))
}

/// The `transfer` argument: how sample values map to linear radiance.
fn transfer_arg(transfer: &str) -> PyRes<Transfer> {
    match transfer {
        "auto" => Ok(Transfer::Auto),
        "linear" => Ok(Transfer::Linear),
        "srgb" => Ok(Transfer::Srgb),
        other => Err(PyValueError::new_err(format!(
            "transfer: {other:?}; \"auto\" (sRGB for uint8, linear otherwise), \"linear\" or \"srgb\" expected"
        ))),
    }
}

fn load_options(
    color: &str,
    transfer: &str,
    saturation: Option<f32>,
) -> PyRes<(LoadOptions, ColorSolve)> {
    let (color, solve) = match color {
        "grey" | "gray" => (ColorMode::Grey, ColorSolve::default()),
        "shared" => (ColorMode::PerChannel, ColorSolve::SharedNormal),
        "per-channel" => (ColorMode::PerChannel, ColorSolve::PerChannel),
        other => {
            return Err(PyValueError::new_err(format!(
                "color: {other:?}; one of \"grey\", \"shared\" (one normal, RGB albedo) or \"per-channel\" (three solves) expected"
            )));
        }
    };
    let transfer = transfer_arg(transfer)?;
    if let Some(s) = saturation
        && !(s.is_finite() && s > 0.0)
    {
        return Err(PyValueError::new_err(format!(
            "saturation: {s}; a finite level > 0 (in stored units, integers scaled to [0, 1]) expected"
        )));
    }
    Ok((
        LoadOptions {
            color,
            transfer,
            saturation,
            window: None,
        },
        solve,
    ))
}

fn method_arg(name: &str) -> PyRes<Method> {
    Method::ALL
        .iter()
        .copied()
        .find(|m| m.name() == name)
        .ok_or_else(|| {
            let names: Vec<&str> = Method::ALL.iter().map(|m| m.name()).collect();
            PyValueError::new_err(format!("method: {name:?}; one of {names:?} expected"))
        })
}

/// The per-pixel configuration of a solve from its keyword arguments.
/// `fill`: fill holes from neighbouring normals (the library's default fills inside a mask).
fn solve_config(method: &str, color: ColorSolve, fill: bool) -> PyRes<Config> {
    let mut config = Config {
        integration: None,
        color,
        ..Config::default()
    };
    config.solve.method = method_arg(method)?;
    config.solve.fill = fill;
    lib(config.solve.validate())?;
    Ok(config)
}

/// A capture-wide model as a Python dict (picklable, for the tiles of a cluster run).
fn model_to_py<'py>(py: Python<'py>, m: &ImageModel) -> PyRes<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("sigma", m.sigma.clone().into_pyarray(py))?;
    let g = &m.gains;
    d.set_item("gains", g.gains.clone().into_pyarray(py))?;
    d.set_item("estimated_gains", g.estimated.clone().into_pyarray(py))?;
    d.set_item("gains_applied", g.applied)?;
    d.set_item("gain_rounds", g.rounds)?;
    d.set_item("gain_refits", g.refits)?;
    d.set_item("gains_converged", g.converged)?;
    d.set_item("gain_pixels", g.pixels)?;
    d.set_item("unit_misfit", g.unit_misfit)?;
    d.set_item("misfit", g.misfit)?;
    d.set_item("lobe_limit", m.lobe_limit)?;
    Ok(d)
}

fn model_from_py(d: &Bound<'_, PyAny>) -> PyRes<ImageModel> {
    let get = |k: &str| {
        d.get_item(k).map_err(|_| {
            PyValueError::new_err(format!(
                "model: no {k:?}; pass a model returned by estimate_model"
            ))
        })
    };
    let values = |k: &str| -> PyRes<Vec<f32>> {
        let a = get(k)?
            .extract::<PyReadonlyArrayDyn<'_, f32>>()
            .map_err(|_| {
                PyTypeError::new_err(format!(
                    "model: {k:?} is not a float32 array; pass a model returned by estimate_model"
                ))
            })?;
        Ok(a.as_array().iter().copied().collect())
    };
    let (sigma, gains, estimated) = (
        values("sigma")?,
        values("gains")?,
        values("estimated_gains")?,
    );
    if gains.len() != sigma.len() || estimated.len() != sigma.len() {
        return Err(PyValueError::new_err(format!(
            "model: {} sigmas, {} gains and {} estimated gains; one of each per image expected",
            sigma.len(),
            gains.len(),
            estimated.len()
        )));
    }
    let mut g = GainEstimate::unit(sigma.len());
    g.gains = gains;
    g.estimated = estimated;
    g.applied = get("gains_applied")?.extract()?;
    g.rounds = get("gain_rounds")?.extract()?;
    g.refits = get("gain_refits")?.extract()?;
    g.converged = get("gains_converged")?.extract()?;
    g.pixels = get("gain_pixels")?.extract()?;
    g.unit_misfit = get("unit_misfit")?.extract()?;
    g.misfit = get("misfit")?.extract()?;
    // Optional: models written before the refit with specular lobes have none.
    let lobe_limit =
        match d.get_item("lobe_limit") {
            Ok(v) if !v.is_none() => Some(v.extract::<f64>().map_err(|_| {
                PyTypeError::new_err("model: \"lobe_limit\" is not a float or None")
            })?),
            _ => None,
        };
    Ok(ImageModel {
        sigma,
        gains: g,
        lobe_limit,
    })
}

fn status_code(s: PixelStatus) -> u8 {
    match s {
        PixelStatus::Outside => 0,
        PixelStatus::Solved => 1,
        PixelStatus::TooFewSamples => 2,
        PixelStatus::IllConditioned => 3,
        PixelStatus::Dark => 4,
        PixelStatus::Filled => 5,
    }
}

fn json<T: serde::Serialize>(v: &T) -> PyRes<String> {
    serde_json::to_string(v).map_err(|e| PyValueError::new_err(e.to_string()))
}

/// The capture-wide checks of the parts of one solve (each a solve's `checks` text), added:
/// the shadow light, the lights' agreement and the pixel outcome counts as JSON text, and every
/// warning the parts give the whole solve (the counts' and the capture's as well as the
/// checks').
#[pyfunction]
#[pyo3(signature = (parts, ambient_subtracted=false))]
fn add_checks<'py>(
    py: Python<'py>,
    parts: Vec<String>,
    ambient_subtracted: bool,
) -> PyRes<Bound<'py, PyDict>> {
    let mut total = CaptureChecks::default();
    for (i, text) in parts.iter().enumerate() {
        let part =
            CaptureChecks::from_json(text).map_err(|e| Error::new_err(format!("part {i}: {e}")))?;
        total
            .add(&part)
            .map_err(|e| Error::new_err(format!("part {i}: {e}")))?;
    }
    let out = PyDict::new(py);
    out.set_item("shadow_light", json(&total.shadow_light)?)?;
    out.set_item("light_agreement", json(&total.light_agreement)?)?;
    out.set_item("counts", json(&total.counts.samples.pixels)?)?;
    out.set_item("warnings", total.sentences(ambient_subtracted))?;
    Ok(out)
}

/// Solve: images, lights, mask → the per-pixel maps, summaries as JSON text.
#[pyfunction]
#[pyo3(signature = (images, lights, mask=None, intensities=None, method="auto", color="grey", transfer="auto", saturation=None, fill=None, models=None, ambient_last=false))]
#[allow(clippy::too_many_arguments)]
fn solve<'py>(
    py: Python<'py>,
    images: &Bound<'py, PyAny>,
    lights: PyReadonlyArray2<'py, f64>,
    mask: Option<&Bound<'py, PyAny>>,
    intensities: Option<PyReadonlyArray2<'py, f64>>,
    method: &str,
    color: &str,
    transfer: &str,
    saturation: Option<f32>,
    fill: Option<bool>,
    models: Option<&Bound<'py, PyList>>,
    ambient_last: bool,
) -> PyRes<Bound<'py, PyDict>> {
    let samples = Samples::images(images, "images")?;
    let lights = lights_arg(lights, intensities)?;
    let mask = mask_arg(mask, "mask")?;
    let (load, color_solve) = load_options(color, transfer, saturation)?;
    // As the command-line tool: holes are filled inside a mask, not over a whole frame.
    let fill = fill.unwrap_or(mask.is_some());
    let config = solve_config(method, color_solve, fill)?;
    let part = models.is_some();
    let models: Option<Vec<ImageModel>> = match models {
        Some(list) => Some(
            list.iter()
                .map(|m| model_from_py(&m))
                .collect::<PyRes<_>>()?,
        ),
        None => None,
    };
    let views = samples.views();
    let recon = py.detach(|| {
        let capture = with_view!(views, v => capture_of(v, lights, mask.as_ref().map(|m| m.view()), &load, part, ambient_last))?;
        // The models are estimated here, once, as the solve itself would (so that the caller
        // gets the ones the solve used, without a second estimate).
        let models = match models {
            Some(m) => m,
            None => estimate_models(&capture, &config)?,
        };
        let recon = reconstruct_normals_with_models(&capture, &config, Some(&models), &Silent)?;
        Ok::<_, LibError>((recon, models))
    });
    let (recon, models) = lib(recon)?;
    // Before the maps are moved out: the counts are read from the whole run.
    let checks = CaptureChecks::of_run(&recon).to_json();
    let maps = recon.maps;
    let out = PyDict::new(py);
    out.set_item("normals", normals_to_array(&maps.normals).into_pyarray(py))?;
    let albedo = if maps.albedo.len() == 1 {
        maps.albedo
            .into_iter()
            .next()
            .map(|a| a.into_array().into_dyn())
    } else {
        let (w, h) = (maps.normals.width(), maps.normals.height());
        let planes: Vec<ScalarMap> = maps.albedo;
        Some(
            ndarray::Array3::from_shape_fn((h, w, planes.len()), |(y, x, c)| *planes[c].at(x, y))
                .into_dyn(),
        )
    };
    if let Some(a) = albedo {
        out.set_item("albedo", a.into_pyarray(py))?;
    }
    out.set_item("residual", maps.residual.into_array().into_pyarray(py))?;
    out.set_item("samples", maps.samples.into_array().into_pyarray(py))?;
    out.set_item("condition", maps.condition.into_array().into_pyarray(py))?;
    out.set_item(
        "status",
        maps.status
            .map(|s| status_code(*s))
            .into_array()
            .into_pyarray(py),
    )?;
    out.set_item("solved", maps.solved.into_array().into_pyarray(py))?;
    out.set_item("robust", maps.robust.into_array().into_pyarray(py))?;
    out.set_item("curl", recon.curl.into_array().into_pyarray(py))?;
    out.set_item("counts", json(&recon.counts)?)?;
    out.set_item("integrability", json(&recon.integrability)?)?;
    out.set_item("model_summary", json(&recon.model)?)?;
    out.set_item("checks", checks)?;
    let warnings: Vec<String> = recon.warnings.iter().map(|w| w.to_string()).collect();
    out.set_item("warnings", warnings)?;
    let list = PyList::empty(py);
    for m in &models {
        list.append(model_to_py(py, m)?)?;
    }
    out.set_item("models", list)?;
    out.set_item("solve_seconds", recon.timings.solve + recon.timings.normals)?;
    Ok(out)
}

/// The capture-wide models a solve of these images would estimate.
#[pyfunction]
#[pyo3(signature = (images, lights, mask=None, intensities=None, method="auto", color="grey", transfer="auto", saturation=None, ambient_last=false))]
#[allow(clippy::too_many_arguments)]
fn estimate_model<'py>(
    py: Python<'py>,
    images: &Bound<'py, PyAny>,
    lights: PyReadonlyArray2<'py, f64>,
    mask: Option<&Bound<'py, PyAny>>,
    intensities: Option<PyReadonlyArray2<'py, f64>>,
    method: &str,
    color: &str,
    transfer: &str,
    saturation: Option<f32>,
    ambient_last: bool,
) -> PyRes<Bound<'py, PyList>> {
    let samples = Samples::images(images, "images")?;
    let lights = lights_arg(lights, intensities)?;
    let mask = mask_arg(mask, "mask")?;
    let (load, color_solve) = load_options(color, transfer, saturation)?;
    let config = solve_config(method, color_solve, true)?;
    let views = samples.views();
    let models = py.detach(|| {
        let capture = with_view!(views, v => capture_of(v, lights, mask.as_ref().map(|m| m.view()), &load, false, ambient_last))?;
        estimate_models(&capture, &config)
    });
    let list = PyList::empty(py);
    for m in &lib(models)? {
        list.append(model_to_py(py, m)?)?;
    }
    Ok(list)
}

/// The images converted as a solve sees them (linear, divided by intensity, grey or RGB).
#[pyfunction]
#[pyo3(signature = (images, lights, intensities=None, color="grey", transfer="auto", saturation=None))]
fn convert<'py>(
    py: Python<'py>,
    images: &Bound<'py, PyAny>,
    lights: PyReadonlyArray2<'py, f64>,
    intensities: Option<PyReadonlyArray2<'py, f64>>,
    color: &str,
    transfer: &str,
    saturation: Option<f32>,
) -> PyRes<(Bound<'py, PyAny>, Bound<'py, PyAny>)> {
    let samples = Samples::images(images, "images")?;
    let lights = lights_arg(lights, intensities)?;
    let (load, _) = load_options(color, transfer, saturation)?;
    let views = samples.views();
    let stack = lib(py.detach(|| with_view!(views, v => stack_of(v, &lights, &load))))?;
    let (n, c, h, w) = (
        stack.count(),
        stack.channels(),
        stack.height(),
        stack.width(),
    );
    let data = ndarray::Array4::from_shape_vec((n, c, h, w), stack.data().to_vec())
        .map_err(|e| PyValueError::new_err(e.to_string()))?;
    let saturated =
        ndarray::Array3::from_shape_fn((n, h, w), |(k, y, x)| stack.is_saturated(k, y * w + x));
    let data = if c == 1 {
        data.index_axis_move(ndarray::Axis(1), 0).into_dyn()
    } else {
        data.permuted_axes([0, 2, 3, 1])
            .as_standard_layout()
            .to_owned()
            .into_dyn()
    };
    Ok((
        data.into_pyarray(py).into_any(),
        saturated.into_pyarray(py).into_any(),
    ))
}

/// The `mask` argument as a mask of `w`×`h` pixels, or a ValueError saying whose size it
/// differs from (`of`, e.g. "the image's").
fn sized_mask(obj: Option<&Bound<'_, PyAny>>, w: usize, h: usize, of: &str) -> PyRes<Option<Mask>> {
    let Some(m) = mask_arg(obj, "mask")? else {
        return Ok(None);
    };
    if m.dim() != (h, w) {
        return Err(PyValueError::new_err(format!(
            "mask: shape {:?} differs from {of} {h}×{w}",
            m.dim()
        )));
    }
    Ok(Some(Grid::from_array(m.view())))
}

fn integrator_arg(name: &str) -> PyRes<Integrator> {
    let all = [
        Integrator::Auto,
        Integrator::MaskedLs,
        Integrator::Poisson,
        Integrator::Path,
        Integrator::FrankotChellappa,
        Integrator::Bilateral,
    ];
    all.iter()
        .copied()
        .find(|m| m.name() == name)
        .ok_or_else(|| {
            let names: Vec<&str> = all.iter().map(|m| m.name()).collect();
            PyValueError::new_err(format!("method: {name:?}; one of {names:?} expected"))
        })
}

/// Normals (H×W×3) and a mask → depth and its diagnostics.
#[pyfunction]
#[pyo3(signature = (normals, mask=None, method="auto", k=None))]
fn integrate<'py>(
    py: Python<'py>,
    normals: PyReadonlyArray3<'py, f32>,
    mask: Option<&Bound<'py, PyAny>>,
    method: &str,
    k: Option<PyReadonlyArray2<'py, f64>>,
) -> PyRes<Bound<'py, PyDict>> {
    check_map_size(normals.shape(), "normals")?;
    let map = lib(normals_from_array(normals.as_array()))?;
    let mask = match sized_mask(mask, map.width(), map.height(), "the normals'")? {
        Some(m) => m,
        // The pixels with a normal: finite, and not the zero vectors that many maps hold
        // outside the object (integrated, they joined the object to a flat sheet, and stopped
        // `bilateral`'s solve before it cut them off). Vectors of any other length are kept:
        // the integration reads their directions (`integrate::unit_normals`).
        None => map.map(usable_normal),
    };
    let camera = intrinsics_arg(k.as_ref(), "K")?;
    let options = IntegrationOptions {
        method: integrator_arg(method)?,
        camera,
        ..IntegrationOptions::default()
    };
    let result = lib(py.detach(|| integrate_normals(&map, &mask, &options, &Silent)))?;
    // What the command warns of, in the library's words.
    let warnings: Vec<String> = Warning::of_integration(&map, &mask, &result)
        .iter()
        .map(|w| w.to_string())
        .collect();
    let out = PyDict::new(py);
    out.set_item("warnings", warnings)?;
    out.set_item(
        "method",
        result.auto.map_or(options.method, |a| a.chosen).name(),
    )?;
    out.set_item("auto", result.auto.as_ref().map(json).transpose()?)?;
    out.set_item("reason", result.auto.as_ref().map(|a| a.reason()))?;
    out.set_item("depth", result.depth.into_array().into_pyarray(py))?;
    out.set_item("residual", result.residual.into_array().into_pyarray(py))?;
    out.set_item("iterations", result.iterations)?;
    out.set_item("solve", result.solve.as_ref().map(json).transpose()?)?;
    out.set_item(
        "closed_off",
        result.closed_off.as_ref().map(json).transpose()?,
    )?;
    Ok(out)
}

/// A material from its model name and parameters (missing ones take the renderer's defaults).
fn material_arg(name: &str, params: Option<&Bound<'_, PyDict>>) -> PyRes<Material> {
    let get = |k: &str, default: f64| -> PyRes<f64> {
        match params.map(|p| p.get_item(k)).transpose()?.flatten() {
            Some(v) => v.extract(),
            None => Ok(default),
        }
    };
    if let Some(p) = params {
        let known = [
            "ks",
            "shininess",
            "roughness",
            "f0",
            "alpha_x",
            "alpha_y",
            "sigma",
        ];
        for key in p.keys() {
            let key: String = key.extract()?;
            if !known.contains(&key.as_str()) {
                return Err(PyValueError::new_err(format!(
                    "material parameter {key:?}; known ones are {known:?}"
                )));
            }
        }
    }
    let mut m = Material::lambertian();
    match name {
        "lambert" | "lambertian" => {}
        "oren-nayar" => {
            m.diffuse = Diffuse::OrenNayar {
                sigma: get("sigma", 0.3)?,
            }
        }
        "phong" => {
            m.specular = Some(Specular::Phong(Phong {
                ks: get("ks", 0.3)?,
                exponent: get("shininess", 30.0)?,
            }))
        }
        "blinn-phong" => {
            m.specular = Some(Specular::BlinnPhong(BlinnPhong {
                ks: get("ks", 0.3)?,
                exponent: get("shininess", 30.0)?,
            }))
        }
        "torrance-sparrow" => {
            m.specular = Some(Specular::TorranceSparrow(TorranceSparrow {
                ks: get("ks", 0.3)?,
                roughness: get("roughness", 0.3)?,
                f0: get("f0", 0.04)?,
            }))
        }
        "ward" => {
            let ax = get("alpha_x", 0.2)?;
            m.specular = Some(Specular::Ward(Ward {
                ks: get("ks", 0.3)?,
                alpha_x: ax,
                alpha_y: get("alpha_y", ax)?,
            }))
        }
        "mirror" => {
            m.diffuse = Diffuse::None;
            m.specular = Some(Specular::Mirror(Mirror {
                f0: get("f0", 0.9)?,
            }));
        }
        other => {
            return Err(PyValueError::new_err(format!(
                "material: {other:?}; one of \"lambert\", \"oren-nayar\", \"phong\", \"blinn-phong\", \"torrance-sparrow\", \"ward\", \"mirror\" expected"
            )));
        }
    }
    lib(m.validate())?;
    Ok(m)
}

/// Renders a named scene under `lights`: images and ground truth.
#[pyfunction]
#[pyo3(signature = (scene, size, lights, material="lambert", material_params=None, albedo=0.8, noise=0.0, seed=0, cast_shadows=true, light_radius_deg=None, ambient=0.0, pixel_samples=1))]
#[allow(clippy::too_many_arguments)]
fn render<'py>(
    py: Python<'py>,
    scene: &str,
    size: usize,
    lights: PyReadonlyArray2<'py, f64>,
    material: &str,
    material_params: Option<&Bound<'py, PyDict>>,
    albedo: f32,
    noise: f32,
    seed: u64,
    cast_shadows: bool,
    light_radius_deg: Option<f64>,
    ambient: f32,
    pixel_samples: usize,
) -> PyRes<Bound<'py, PyDict>> {
    let kind = SceneKind::ALL
        .iter()
        .copied()
        .find(|k| k.name() == scene)
        .ok_or_else(|| {
            let names: Vec<&str> = SceneKind::ALL.iter().map(|k| k.name()).collect();
            PyValueError::new_err(format!("scene: {scene:?}; one of {names:?} expected"))
        })?;
    if !(8..=8192).contains(&size) {
        return Err(PyValueError::new_err(format!(
            "size: {size}; 8 to 8192 pixels expected"
        )));
    }
    if !(albedo.is_finite() && albedo > 0.0) {
        return Err(PyValueError::new_err(format!(
            "albedo: {albedo}; a finite value > 0 expected"
        )));
    }
    let lights = lights_arg(lights, None)?;
    if lights.len().saturating_mul(size * size) > MAX_RENDERED_SAMPLES {
        return Err(PyValueError::new_err(format!(
            "{} lights × {size}² pixels: more than {MAX_RENDERED_SAMPLES} samples (4 GiB); fewer lights or a smaller size",
            lights.len()
        )));
    }
    let material = material_arg(material, material_params)?;
    let options = RenderOptions {
        cast_shadows,
        noise_sigma: noise,
        seed,
        light_radius_deg: light_radius_deg
            .unwrap_or(photostereo::synth::render::DEFAULT_LIGHT_RADIUS_DEG),
        ambient,
        pixel_samples,
        ..RenderOptions::default()
    };
    lib(options.validate())?;
    let built = kind.build(size, Albedo::Constant(albedo), material);
    let r = lib(py.detach(|| render_scene(&built, &lights, &options)))?;
    let (w, h) = (r.truth.mask.width(), r.truth.mask.height());
    let images = ndarray::Array3::from_shape_fn((r.images.len(), h, w), |(k, y, x)| {
        *r.images[k][0].at(x, y)
    });
    let out = PyDict::new(py);
    out.set_item("images", images.into_pyarray(py))?;
    out.set_item("lights", lights.directions_array().into_pyarray(py))?;
    out.set_item(
        "normals",
        normals_to_array(&r.truth.normals).into_pyarray(py),
    )?;
    out.set_item("depth", r.truth.depth.clone().into_array().into_pyarray(py))?;
    out.set_item(
        "albedo",
        r.truth.albedo.clone().into_array().into_pyarray(py),
    )?;
    out.set_item("mask", r.truth.mask.clone().into_array().into_pyarray(py))?;
    let stack =
        |m: &[Mask]| ndarray::Array3::from_shape_fn((m.len(), h, w), |(k, y, x)| *m[k].at(x, y));
    out.set_item("cast_shadows", stack(&r.cast).into_pyarray(py))?;
    out.set_item("attached_shadows", stack(&r.attached).into_pyarray(py))?;
    if let Some(ambient) = &r.ambient {
        out.set_item("ambient", ambient[0].clone().into_array().into_pyarray(py))?;
    }
    Ok(out)
}

/// Lights on a ring: `count` directions at `elevation_deg` above the image plane.
#[pyfunction]
#[pyo3(signature = (count, elevation_deg, azimuth0_deg=0.0))]
fn light_ring<'py>(
    py: Python<'py>,
    count: usize,
    elevation_deg: f64,
    azimuth0_deg: f64,
) -> PyRes<Bound<'py, PyArray2<f64>>> {
    if count > MAX_IMAGES {
        return Err(PyValueError::new_err(format!(
            "count: {count}; at most {MAX_IMAGES} lights"
        )));
    }
    Ok(lib(Lights::ring(count, elevation_deg, azimuth0_deg))?
        .directions_array()
        .into_pyarray(py))
}

/// R(p, q) of a material under one distant light, sampled on [-extent, extent]².
#[pyfunction]
#[pyo3(signature = (light, material="lambert", material_params=None, extent=2.0, size=256))]
fn reflectance_map<'py>(
    py: Python<'py>,
    light: [f64; 3],
    material: &str,
    material_params: Option<&Bound<'py, PyDict>>,
    extent: f64,
    size: usize,
) -> PyRes<Bound<'py, PyAny>> {
    if !(2..=8192).contains(&size) {
        return Err(PyValueError::new_err(format!(
            "size: {size}; 2 to 8192 samples a side expected"
        )));
    }
    let material = material_arg(material, material_params)?;
    let rm = lib(ReflectanceMap::new(nalgebra_vec(light), material))?;
    Ok(lib(py.detach(|| rm.sample(extent, size)))?
        .into_array()
        .into_pyarray(py)
        .into_any())
}

fn nalgebra_vec(v: [f64; 3]) -> photostereo::nalgebra::Vector3<f64> {
    photostereo::nalgebra::Vector3::new(v[0], v[1], v[2])
}

/// A 3×3 intrinsics matrix argument named `name`.
fn intrinsics_arg(k: Option<&PyReadonlyArray2<'_, f64>>, name: &str) -> PyRes<Option<Intrinsics>> {
    let Some(k) = k else {
        return Ok(None);
    };
    let k = k.as_array();
    if k.dim() != (3, 3) {
        return Err(PyValueError::new_err(format!(
            "{name}: shape {:?}; 3×3 expected",
            k.dim()
        )));
    }
    let m = [0, 1, 2].map(|r| [0, 1, 2].map(|c| k[[r, c]]));
    Ok(Some(lib(Intrinsics::from_matrix(m))?))
}

/// What `calibrate` returns: directions (N×3, `None` when some light is in doubt or missing),
/// positions (N×3, with two balls), and the report as JSON.
type Calibrated<'py> = (
    Option<Bound<'py, PyArray2<f64>>>,
    Option<Bound<'py, PyArray2<f64>>>,
    String,
);

/// Light directions from a chrome sphere's images (perspective with `camera`), or with
/// `ball_radius` light positions from two balls; and the report as JSON.
#[pyfunction]
#[pyo3(signature = (images, mask=None, camera=None, ball_radius=None))]
fn calibrate<'py>(
    py: Python<'py>,
    images: &Bound<'py, PyAny>,
    mask: Option<&Bound<'py, PyAny>>,
    camera: Option<PyReadonlyArray2<'py, f64>>,
    ball_radius: Option<f64>,
) -> PyRes<Calibrated<'py>> {
    let camera = intrinsics_arg(camera.as_ref(), "camera")?;
    let samples = Samples::images(images, "images")?;
    let n = samples.shape()[0];
    let mask = mask_arg(mask, "mask")?;
    let views = samples.views();
    let result = py.detach(|| {
        let unit = Lights::from_directions(&vec![photostereo::nalgebra::Vector3::z(); n])?;
        let stack = with_view!(views, v => stack_of(v, &unit, &LoadOptions::default()))?;
        let grey_mask: Option<ScalarMap> = match &mask {
            Some(m) => {
                if m.dim() != (stack.height(), stack.width()) {
                    return Err(LibError::param(
                        "mask",
                        format!(
                            "shape {:?} differs from the images' {}×{}",
                            m.dim(),
                            stack.height(),
                            stack.width()
                        ),
                    ));
                }
                Some(Grid::from_array(m.view()).map(|b| if *b { 1.0 } else { 0.0 }))
            }
            None => None,
        };
        let source = Path::new("<array mask>");
        let mask = grey_mask.as_ref().map(|m| (m, source));
        match (camera, ball_radius) {
            (Some(k), Some(r)) => {
                calibrate_two_balls(&stack, mask, &NearOptions::new(k, r)).map(Calibration::Two)
            }
            (None, Some(_)) => Err(LibError::param(
                "ball_radius",
                "light positions need the camera's intrinsics (camera)",
            )),
            (camera, None) => calibrate_chrome(
                &stack,
                mask,
                &ChromeOptions {
                    camera,
                    ..ChromeOptions::default()
                },
            )
            .map(Calibration::One),
        }
    });
    Ok(match lib(result)? {
        Calibration::One(cal) => (
            cal.lights()
                .ok()
                .map(|l| l.directions_array().into_pyarray(py)),
            None,
            json(&cal)?,
        ),
        Calibration::Two(two) => {
            let lights = two.lights().ok();
            let positions = lights.as_ref().map(|l| {
                let n = l.len();
                let p: Vec<f64> = l
                    .lights()
                    .iter()
                    .flat_map(|l| l.position.map_or([f64::NAN; 3], |p| [p.x, p.y, p.z]))
                    .collect();
                Array2::from_shape_vec((n, 3), p).unwrap_or_else(|_| Array2::zeros((n, 3)))
            });
            (
                lights.map(|l| l.directions_array().into_pyarray(py)),
                positions.map(|p| p.into_pyarray(py)),
                json(&two)?,
            )
        }
    })
}

/// One image as grey linear intensities, converted as the `sfs` command converts an image
/// file of the same samples: integers scaled to [0, 1] by their largest code, three channels
/// mixed to grey with [`GREY_WEIGHTS`], then decoded from sRGB where `transfer` says so
/// (`auto`: uint8 only).
fn grey_image_arg(obj: &Bound<'_, PyAny>, transfer: Transfer) -> PyRes<ScalarMap> {
    fn grey<T: numpy::Element + Copy>(
        a: PyReadonlyArrayDyn<'_, T>,
        scale: impl Fn(T) -> f32,
        srgb: bool,
    ) -> PyRes<ScalarMap> {
        let a = a.as_array();
        let (h, w, c) = match *a.shape() {
            [h, w] => (h, w, 0),
            [h, w, c @ (1 | 3)] => (h, w, c),
            ref other => {
                return Err(PyValueError::new_err(format!(
                    "image: shape {other:?}; one image, H x W or H x W x 3 (mixed to grey), \
                     expected"
                )));
            }
        };
        check_map_size(&[h, w], "image")?;
        Ok(Grid::from_fn(w, h, |x, y| {
            let v = match c {
                0 => scale(a[[y, x].as_slice()]),
                1 => scale(a[[y, x, 0].as_slice()]),
                _ => (0..3)
                    .map(|k| scale(a[[y, x, k].as_slice()]) * GREY_WEIGHTS[k])
                    .sum(),
            };
            if srgb {
                photostereo::io::decode::srgb_to_linear(v)
            } else {
                v
            }
        }))
    }
    let srgb = |eight_bit: bool| match transfer {
        Transfer::Auto => eight_bit,
        Transfer::Linear => false,
        Transfer::Srgb => true,
    };
    if let Ok(a) = obj.extract::<PyReadonlyArrayDyn<'_, f32>>() {
        return grey(a, |v| v, srgb(false));
    }
    if let Ok(a) = obj.extract::<PyReadonlyArrayDyn<'_, f64>>() {
        return grey(a, |v| v as f32, srgb(false));
    }
    if let Ok(a) = obj.extract::<PyReadonlyArrayDyn<'_, u16>>() {
        return grey(a, |v| f32::from(v) / 65535.0, srgb(false));
    }
    if let Ok(a) = obj.extract::<PyReadonlyArrayDyn<'_, u8>>() {
        return grey(a, |v| f32::from(v) / 255.0, srgb(true));
    }
    Err(PyTypeError::new_err(format!(
        "image: {}; a numpy array of uint8, uint16, float32 or float64 expected",
        describe(obj)
    )))
}

/// Shape from shading of one grey image: a distant light (`horn`, `tsai-shah`,
/// `fast-marching`; the light and albedo estimated where not given) or a pinhole camera with a
/// point light (`perspective`).
#[pyfunction]
#[pyo3(signature = (image, mask=None, light=None, albedo=None, method=None, material="lambert", material_params=None, transfer="auto", boundary="occluding", iterations=0, smoothness=None, shadow_level=None, camera=None, light_position=None, light_intensity=None, refine=true, refine_smoothness=None, refine_iterations=0, coarse_to_fine=true, outline_repair=true, restarts=true, start=None))]
#[allow(clippy::too_many_arguments)]
fn sfs<'py>(
    py: Python<'py>,
    image: &Bound<'py, PyAny>,
    mask: Option<&Bound<'py, PyAny>>,
    light: Option<[f64; 3]>,
    albedo: Option<f64>,
    method: Option<&str>,
    material: &str,
    material_params: Option<&Bound<'py, PyDict>>,
    transfer: &str,
    boundary: &str,
    iterations: usize,
    smoothness: Option<f64>,
    shadow_level: Option<f64>,
    camera: Option<PyReadonlyArray2<'py, f64>>,
    light_position: Option<[f64; 3]>,
    light_intensity: Option<f64>,
    refine: bool,
    refine_smoothness: Option<f64>,
    refine_iterations: usize,
    coarse_to_fine: bool,
    outline_repair: bool,
    restarts: bool,
    start: Option<PyReadonlyArray2<'py, f64>>,
) -> PyRes<Bound<'py, PyDict>> {
    use photostereo::sfs::perspective::{PerspectiveOptions, PointLight, RefineOptions, refine};
    use photostereo::sfs::{Boundary, SfsMethod, SfsOptions};
    let image = grey_image_arg(image, transfer_arg(transfer)?)?;
    let mut warnings: Vec<String> = Vec::new();
    let mask = match sized_mask(mask, image.width(), image.height(), "the image's")? {
        Some(m) => m,
        None => {
            warnings.push(
                "no mask: the object is every pixel but the black background touching the \
                 border, so attached shadows that touch it are left out; give a mask for \
                 shadowed objects"
                    .to_string(),
            );
            photostereo::sfs::object_mask(&image)
        }
    };
    let material = material_arg(material, material_params)?;
    let all: Vec<SfsMethod> = SfsMethod::ALL
        .into_iter()
        .chain([SfsMethod::Perspective])
        .collect();
    let method = match method {
        None if light_position.is_some() => SfsMethod::Perspective,
        None => SfsMethod::Horn,
        Some(name) => all
            .iter()
            .copied()
            .find(|m| m.name() == name)
            .ok_or_else(|| {
                let names: Vec<&str> = all.iter().map(|m| m.name()).collect();
                PyValueError::new_err(format!("method: {name:?}; one of {names:?} expected"))
            })?,
    };
    if !coarse_to_fine && method != SfsMethod::Horn {
        return Err(PyValueError::new_err(format!(
            "coarse_to_fine: for the horn method (the only method whose coarse-to-fine start can be turned off), not {}",
            method.name()
        )));
    }
    if !outline_repair && method != SfsMethod::Horn {
        return Err(PyValueError::new_err(format!(
            "outline_repair: for the horn method (the only method that repairs the outline), not {}",
            method.name()
        )));
    }
    if !restarts && method != SfsMethod::Horn {
        return Err(PyValueError::new_err(format!(
            "restarts: for the horn method (the only method that repeats its continuation), not {}",
            method.name()
        )));
    }
    // Any size: the library brings it to the image's grid (resampled, holes filled).
    let start = match start {
        Some(a) => {
            let (h, w) = (a.shape()[0], a.shape()[1]);
            Some(lib(Grid::from_vec(
                w,
                h,
                a.as_array().iter().map(|&v| v as f32).collect(),
            ))?)
        }
        None => None,
    };
    if start.is_some() && method != SfsMethod::Horn {
        return Err(PyValueError::new_err(format!(
            "start: for the horn method (the only method that refines a given surface), not {}",
            method.name()
        )));
    }
    if start.is_some() && !(coarse_to_fine && outline_repair && restarts) {
        return Err(PyValueError::new_err(
            "start: the given surface is refined at the final smoothness alone; there is no \
             coarse-to-fine start, repeat or outline repair to turn off",
        ));
    }
    let out = PyDict::new(py);
    // Set with a start (Horn) below.
    out.set_item("start_scale", py.None())?;
    out.set_item("start_filled", py.None())?;
    let result = if method == SfsMethod::Perspective {
        let Some(position) = light_position else {
            return Err(PyValueError::new_err(
                "light_position: the perspective method needs the light's position (camera \
                 frame, the unit of depth; (0, 0, 0) for a light at the camera centre)",
            ));
        };
        if light.is_some() {
            return Err(PyValueError::new_err(
                "light: a distant light's direction; the perspective method takes \
                 light_position",
            ));
        }
        if smoothness.is_some() || boundary != "occluding" {
            return Err(PyValueError::new_err(format!(
                "{}: for the distant-light methods; the perspective method's curvature weight \
                 is refine_smoothness",
                if smoothness.is_some() {
                    "smoothness"
                } else {
                    "boundary"
                }
            )));
        }
        if !refine && (refine_smoothness.is_some() || refine_iterations != 0) {
            return Err(PyValueError::new_err(format!(
                "{}: sets the refinement, which refine=False turns off",
                if refine_smoothness.is_some() {
                    "refine_smoothness"
                } else {
                    "refine_iterations"
                }
            )));
        }
        let Some(k) = intrinsics_arg(camera.as_ref(), "camera")? else {
            return Err(PyValueError::new_err(
                "camera: the perspective method needs the camera's 3 x 3 intrinsics",
            ));
        };
        let mut assumed = Vec::new();
        if light_intensity.is_none() {
            assumed.push("light_intensity");
        }
        if albedo.is_none() {
            assumed.push("albedo");
        }
        if !assumed.is_empty() {
            warnings.push(format!(
                "{} not given, 1 assumed: the depth's scale goes with 1/sqrt(albedo x \
                 intensity), and a wrong value bends the shape too",
                assumed.join(" and ")
            ));
        }
        let options = PerspectiveOptions {
            material,
            albedo: albedo.unwrap_or(1.0),
            shadow_level: shadow_level.unwrap_or(PerspectiveOptions::default().shadow_level),
            max_sweeps: iterations,
            refine: refine.then(|| RefineOptions {
                smoothness: refine_smoothness.unwrap_or(refine::DEFAULT_SMOOTHNESS),
                max_iterations: if refine_iterations > 0 {
                    refine_iterations
                } else {
                    refine::DEFAULT_MAX_ITERATIONS
                },
                ..RefineOptions::default()
            }),
            ..PerspectiveOptions::default()
        };
        let point = PointLight {
            position: nalgebra_vec(position),
            intensity: light_intensity.unwrap_or(1.0),
        };
        let r =
            lib(py.detach(|| {
                photostereo::sfs::perspective::solve(&image, &mask, &k, &point, &options)
            }))?;
        out.set_item("light", r.report.light)?;
        out.set_item("albedo", options.albedo)?;
        out.set_item("light_source", "given")?;
        out.set_item(
            "albedo_source",
            if albedo.is_some() { "given" } else { "assumed" },
        )?;
        out.set_item("estimate", py.None())?;
        r
    } else {
        for (name, given) in [
            ("camera", camera.is_some()),
            ("light_position", light_position.is_some()),
            ("light_intensity", light_intensity.is_some()),
            ("refine", !refine),
            ("refine_smoothness", refine_smoothness.is_some()),
            ("refine_iterations", refine_iterations != 0),
        ] {
            if given {
                return Err(PyValueError::new_err(format!(
                    "{name}: for the perspective method; {} assumes a distant light and an \
                     orthographic camera",
                    method.name()
                )));
            }
        }
        let boundary = match boundary {
            "occluding" => Boundary::Occluding,
            "free" => Boundary::Free,
            other => {
                return Err(PyValueError::new_err(format!(
                    "boundary: {other:?}; \"occluding\" or \"free\" expected"
                )));
            }
        };
        let defaults = SfsOptions::default();
        let options = SfsOptions {
            method,
            boundary,
            max_iterations: iterations,
            smoothness: smoothness.unwrap_or(defaults.smoothness),
            shadow_level: shadow_level.unwrap_or(defaults.shadow_level),
            coarse_to_fine,
            outline_repair,
            restarts,
        };
        let (r, lit, prepared) = lib(py.detach(|| {
            // The start first: one that cannot be used is refused before any estimate.
            let start = match &start {
                Some(z) => Some(photostereo::sfs::start::prepare_start(z, &mask)?),
                None => None,
            };
            let (rmap, lit) = photostereo::sfs::estimate::illumination(
                &image,
                &mask,
                light.map(nalgebra_vec),
                albedo,
                material,
            )?;
            match start {
                Some(z) => photostereo::sfs::shape_from_shading_from(
                    &image,
                    &mask,
                    &rmap,
                    lit.albedo,
                    &options,
                    &z.heights,
                    &photostereo::progress::Silent,
                )
                .map(|r| (r, lit, Some((z.scale, z.filled)))),
                None => {
                    photostereo::sfs::shape_from_shading(&image, &mask, &rmap, lit.albedo, &options)
                        .map(|r| (r, lit, None))
                }
            }
        }))?;
        out.set_item("start_scale", prepared.map(|(scale, _)| scale))?;
        out.set_item("start_filled", prepared.map(|(_, filled)| filled))?;
        out.set_item("light", lit.light)?;
        out.set_item("albedo", lit.albedo)?;
        out.set_item(
            "light_source",
            if lit.light_estimated {
                "estimated"
            } else {
                "given"
            },
        )?;
        out.set_item(
            "albedo_source",
            if lit.albedo_estimated {
                "estimated"
            } else {
                "given"
            },
        )?;
        out.set_item("estimate", lit.estimate.as_ref().map(json).transpose()?)?;
        r
    };
    warnings.extend(result.report.warnings.iter().cloned());
    out.set_item("method", method.name())?;
    out.set_item("depth", result.depth.into_array().into_pyarray(py))?;
    out.set_item(
        "normals",
        normals_to_array(&result.normals).into_pyarray(py),
    )?;
    out.set_item("residual", result.residual.into_array().into_pyarray(py))?;
    out.set_item("shadow", result.shadow.into_array().into_pyarray(py))?;
    out.set_item("mask", mask.into_array().into_pyarray(py))?;
    out.set_item("report", json(&result.report)?)?;
    out.set_item("warnings", warnings)?;
    Ok(out)
}

/// One ball's calibration, or two balls' with light positions.
enum Calibration {
    One(photostereo::calibrate::ChromeCalibration),
    Two(photostereo::calibrate::near::TwoBallCalibration),
}

/// An image file's samples as stored (H×W×C, uint8/uint16/float32).
#[pyfunction]
fn read_image<'py>(py: Python<'py>, path: PathBuf) -> PyRes<Bound<'py, PyAny>> {
    let a = lib(py.detach(|| read_array(&path)))?;
    Ok(match a {
        ImageArray::U8(a) => a.into_pyarray(py).into_any(),
        ImageArray::U16(a) => a.into_pyarray(py).into_any(),
        ImageArray::F32(a) => a.into_pyarray(py).into_any(),
    })
}

/// Image paths, light directions (N×3), intensities (N×3) and the mask's path.
type Resolved<'py> = (
    Vec<PathBuf>,
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray2<f64>>,
    Option<PathBuf>,
);

/// A capture folder or image list resolved: image paths, lights (N×3), intensities (N×3),
/// mask path.
#[pyfunction]
#[pyo3(signature = (inputs, lights=None, mask=None))]
fn resolve<'py>(
    py: Python<'py>,
    inputs: Vec<PathBuf>,
    lights: Option<PathBuf>,
    mask: Option<PathBuf>,
) -> PyRes<Resolved<'py>> {
    let files = lib(resolve_files(&inputs, lights.as_deref(), mask.as_deref()))?;
    Ok((
        files.images.clone(),
        files.lights.directions_array().into_pyarray(py),
        files.lights.intensities_array().into_pyarray(py),
        files.mask_source.clone(),
    ))
}

fn resolve_files(
    inputs: &[PathBuf],
    lights: Option<&Path>,
    mask: Option<&Path>,
) -> photostereo::Result<CaptureFiles> {
    if inputs.is_empty() {
        return Err(LibError::TooFewImages { count: 0 });
    }
    for p in inputs
        .iter()
        .map(PathBuf::as_path)
        .chain(lights)
        .chain(mask)
    {
        if !p.exists() {
            return Err(LibError::Io {
                path: p.to_path_buf(),
                cause: std::io::Error::from(std::io::ErrorKind::NotFound),
            });
        }
    }
    if let [one] = inputs
        && photostereo::capture::dataset::is_diligent_dir(one)
    {
        if lights.is_some() {
            return Err(LibError::param(
                "lights",
                "a DiLiGenT folder brings its own lights (light_directions.txt); give images and a lights file instead",
            ));
        }
        return CaptureFiles::from_diligent(one, mask);
    }
    if let [one] = inputs
        && photostereo::capture::dataset::is_image_list(one)
    {
        let list = photostereo::capture::dataset::read_image_list(one)?;
        let Some(lights) = lights else {
            return Err(LibError::param(
                "lights",
                "an image list needs a lights file",
            ));
        };
        return CaptureFiles::from_files(&list.images, lights, mask.or(list.mask.as_deref()));
    }
    let Some(lights) = lights else {
        return Err(LibError::param(
            "lights",
            "images need a lights file (JSON or `x y z` lines), unless the input is a DiLiGenT folder",
        ));
    };
    CaptureFiles::from_files(inputs, lights, mask)
}

/// A mask file as a bool array (H×W).
#[pyfunction]
fn read_mask<'py>(py: Python<'py>, path: PathBuf) -> PyRes<Bound<'py, PyAny>> {
    let m = lib(py.detach(|| photostereo::io::decode::read_mask(&path)))?;
    Ok(m.into_array().into_pyarray(py).into_any())
}

/// Every channel of an EXR file: a list of (name, H×W float32 array).
#[pyfunction]
fn read_exr<'py>(py: Python<'py>, path: PathBuf) -> PyRes<Vec<(String, Bound<'py, PyAny>)>> {
    let exr = lib(py.detach(|| read_exr_channels(&path)))?;
    let (w, h) = (exr.width, exr.height);
    exr.channels
        .into_iter()
        .map(|(name, v)| {
            let a = Array2::from_shape_vec((h, w), v)
                .map_err(|e| PyValueError::new_err(e.to_string()))?;
            Ok((name, a.into_pyarray(py).into_any()))
        })
        .collect()
}

/// Writes channels (name, H×W float32) to a float32 EXR atomically.
#[pyfunction]
#[pyo3(signature = (path, channels, overwrite=false))]
fn write_exr(
    py: Python<'_>,
    path: PathBuf,
    channels: Vec<(String, PyReadonlyArray2<'_, f32>)>,
    overwrite: bool,
) -> PyRes<()> {
    let Some((_, first)) = channels.first() else {
        return Err(PyValueError::new_err(
            "channels: none given; at least one (name, H×W float32 array) expected",
        ));
    };
    let dim = first.as_array().dim();
    let mut owned: Vec<(String, Vec<f32>)> = Vec::with_capacity(channels.len());
    for (name, a) in &channels {
        let v = a.as_array();
        if v.dim() != dim {
            return Err(PyValueError::new_err(format!(
                "channels: {name:?} is {:?} but {:?} is {dim:?}; all channels must have one shape",
                v.dim(),
                channels[0].0
            )));
        }
        owned.push((name.clone(), v.iter().copied().collect()));
    }
    let mode = if overwrite {
        Overwrite::PreviousSet
    } else {
        Overwrite::Never
    };
    lib(py.detach(|| {
        let refs: Vec<(&str, &[f32])> = owned
            .iter()
            .map(|(n, v)| (n.as_str(), v.as_slice()))
            .collect();
        write_exr_file(&path, mode, (dim.1, dim.0), &refs, &[])
    }))
}

/// The library's version.
#[pyfunction]
fn version() -> &'static str {
    env!("CARGO_PKG_VERSION")
}

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("Error", m.py().get_type::<Error>())?;
    m.add_function(wrap_pyfunction!(solve, m)?)?;
    m.add_function(wrap_pyfunction!(estimate_model, m)?)?;
    m.add_function(wrap_pyfunction!(add_checks, m)?)?;
    m.add_function(wrap_pyfunction!(convert, m)?)?;
    m.add_function(wrap_pyfunction!(integrate, m)?)?;
    m.add_function(wrap_pyfunction!(render, m)?)?;
    m.add_function(wrap_pyfunction!(light_ring, m)?)?;
    m.add_function(wrap_pyfunction!(reflectance_map, m)?)?;
    m.add_function(wrap_pyfunction!(calibrate, m)?)?;
    m.add_function(wrap_pyfunction!(sfs, m)?)?;
    m.add_function(wrap_pyfunction!(read_image, m)?)?;
    m.add_function(wrap_pyfunction!(read_mask, m)?)?;
    m.add_function(wrap_pyfunction!(resolve, m)?)?;
    m.add_function(wrap_pyfunction!(read_exr, m)?)?;
    m.add_function(wrap_pyfunction!(write_exr, m)?)?;
    m.add_function(wrap_pyfunction!(version, m)?)?;
    Ok(())
}
