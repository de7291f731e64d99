//! The output files: their names ([`OUTPUT_FILES`]), EXR channels and header attributes, the
//! file contents of the per-pixel maps for any rows ([`map_rows`]), and the staging of the maps
//! and of the depth outputs.

use super::*;

/// Names of the files [`write_outputs`] writes, in order.
pub const OUTPUT_FILES: [&str; 10] = [
    "normal.exr",
    "albedo.exr",
    "depth.exr",
    "residual.exr",
    "curl.exr",
    "mask.png",
    "normal.png",
    "albedo.png",
    "depth.png",
    "report.json",
];

/// The `photostereo:units` header attribute of an orthographic depth map.
pub(super) const ORTHOGRAPHIC_UNITS: &str =
    "Z: height towards the camera in pixel units (orthographic), larger is nearer";

/// What the values of the EXR output `file` of a run under `config` are ([`exr_units`]).
pub(crate) fn units_of(file: &str, config: &Config) -> String {
    exr_units(
        file,
        config.integration.as_ref().and_then(|o| o.camera.as_ref()),
    )
}

/// What the values of the EXR output `file` (`normal.exr`, `albedo.exr`, `residual.exr`,
/// `curl.exr`, or a depth map for any other name) are, for its `photostereo:units` attribute:
/// each file says what its own channels hold; depth and curl under a pinhole `camera` differ
/// from the orthographic ones. ASCII only: EXR text attributes are Latin-1, and others are
/// dropped.
pub fn exr_units(file: &str, camera: Option<&crate::camera::Intrinsics>) -> String {
    match (file, camera) {
        ("normal.exr", _) => {
            "R, G, B: unit surface normal n_x, n_y, n_z (dimensionless), NaN where unsolved".into()
        }
        ("albedo.exr", _) => {
            "albedo rho = |g| of I = rho n.l: linear image intensity per unit light intensity at normal incidence".into()
        }
        ("residual.exr", _) => {
            "residual: RMS of I - rho n.l in linear image intensity; samples: images used; condition: condition number of their lights; robust, filled: 1 where a robust fit was used or the normal filled in".into()
        }
        ("curl.exr", None) => {
            "curl: dp/dy - dq/dx of the orthographic depth gradients p = -n_x/n_z, q = -n_y/n_z, per pixel (0 where integrable)".into()
        }
        ("curl.exr", Some(_)) => {
            "curl: dp/dy - dq/dx of the log-depth gradients under the pinhole camera, per pixel (0 where integrable)".into()
        }
        (_, None) => ORTHOGRAPHIC_UNITS.into(),
        (_, Some(k)) => format!(
            "Z: depth along the optical axis, up to scale (pinhole fx={} fy={} cx={} cy={}), larger is farther",
            k.fx, k.fy, k.cx, k.cy
        ),
    }
}

/// The string attributes of the EXR header of the output `file`: method, frame, units
/// ([`units_of`]), light count and the light directions (a JSON list of [x, y, z] in the
/// camera frame).
pub(crate) fn exr_attributes(
    lights: &crate::capture::lights::Lights,
    config: &Config,
    file: &str,
) -> Vec<(&'static str, String)> {
    vec![
        ("photostereo:method", config.solve.method.name().to_string()),
        (
            "photostereo:frame",
            "x right, y up, z towards the camera; row 0 at the top".to_string(),
        ),
        (
            "photostereo:units",
            match config.integration.as_ref().and_then(|o| o.camera.as_ref()) {
                Some(k)
                    if super::near_applies(lights, config)
                        && !matches!(
                            file,
                            "normal.exr" | "albedo.exr" | "residual.exr" | "curl.exr"
                        ) =>
                {
                    format!(
                        "Z: absolute depth along the optical axis, in the unit of the light positions (near-light model; pinhole fx={} fy={} cx={} cy={}), larger is farther",
                        k.fx, k.fy, k.cx, k.cy
                    )
                }
                _ => units_of(file, config),
            },
        ),
        ("photostereo:lights", lights.len().to_string()),
        (
            "photostereo:light_directions",
            serde_json::to_string(
                &lights
                    .directions()
                    .iter()
                    .map(|d| [d.x, d.y, d.z])
                    .collect::<Vec<_>>(),
            )
            .unwrap_or_default(),
        ),
    ]
}

/// Channel names of `normal.exr`.
pub(crate) const NORMAL_CHANNELS: [&str; 3] = ["R", "G", "B"];

/// Channel names of `residual.exr`.
pub(crate) const RESIDUAL_CHANNELS: [&str; 5] =
    ["residual", "samples", "condition", "robust", "filled"];

/// Channel names of `albedo.exr` for `channels` albedo maps (1 grey, 3 RGB).
pub(crate) fn albedo_channels(channels: usize) -> Result<&'static [&'static str]> {
    match channels {
        1 => Ok(&["Y"]),
        3 => Ok(&["R", "G", "B"]),
        n => Err(Error::param(
            "albedo",
            format!("{n} albedo channels: 1 or 3 expected"),
        )),
    }
}

/// The contents of the files made from the per-pixel maps, for any rows of them (the whole
/// image, or a band written as it is solved).
pub(crate) struct MapRows {
    /// `normal.exr`: n_x, n_y, n_z.
    pub normal: Vec<Vec<f32>>,
    /// `albedo.exr`: per channel, NaN where not solved.
    pub albedo: Vec<Vec<f32>>,
    /// `residual.exr`: residual, samples, condition, robust, filled (NaN outside the mask).
    pub residual: Vec<Vec<f32>>,
    /// `mask.png`.
    pub mask: Vec<u8>,
    /// `normal.png`.
    pub normal_png: Vec<u8>,
}

/// The file contents of maps `m` (any rows).
pub(crate) fn map_rows(m: &PixelMaps) -> MapRows {
    let n = m.status.len();
    let albedo = m
        .albedo
        .iter()
        .map(|a| nan_outside(a, &m.solved).into_data())
        .collect();
    let in_mask = |i: usize| m.status.data()[i] != PixelStatus::Outside;
    let samples = (0..n)
        .map(|i| {
            if in_mask(i) {
                f32::from(m.samples.data()[i])
            } else {
                f32::NAN
            }
        })
        .collect();
    let condition = (0..n)
        .map(|i| {
            if in_mask(i) {
                m.condition.data()[i]
            } else {
                f32::NAN
            }
        })
        .collect();
    let robust = (0..n)
        .map(|i| {
            if !in_mask(i) {
                f32::NAN
            } else if m.robust.data()[i] {
                1.0
            } else {
                0.0
            }
        })
        .collect();
    let filled = (0..n)
        .map(|i| match m.status.data()[i] {
            PixelStatus::Outside => f32::NAN,
            PixelStatus::Filled => 1.0,
            _ => 0.0,
        })
        .collect();
    MapRows {
        normal: normal_planes(&m.normals).into(),
        albedo,
        residual: vec![
            m.residual.data().to_vec(),
            samples,
            condition,
            robust,
            filled,
        ],
        mask: mask_bytes(&m.solved),
        normal_png: normal_preview(&m.normals),
    }
}

/// `albedo.png`: each albedo channel (NaN where not solved) scaled by its own 99th percentile
/// ([`scalar_preview`]), grey or interleaved RGB.
pub(crate) fn albedo_png(albedo: &[ScalarMap]) -> Vec<u8> {
    if let [grey] = albedo {
        return scalar_preview(grey);
    }
    let planes: Vec<Vec<u8>> = albedo.iter().map(scalar_preview).collect();
    let n = albedo.first().map_or(0, |a| a.len());
    (0..n)
        .flat_map(|i| planes.iter().map(move |p| p[i]))
        .collect()
}

/// Named channels of planes `planes` under `names`.
pub(super) fn named<'a>(names: &[&'a str], planes: &'a [Vec<f32>]) -> Vec<ExrChannel<'a>> {
    names
        .iter()
        .zip(planes)
        .map(|(n, p)| (*n, p.as_slice()))
        .collect()
}

/// Stages every output that does not depend on depth: `normal.exr`, `albedo.exr`,
/// `residual.exr`, `curl.exr`, `mask.png`, `normal.png`, `albedo.png`.
pub(super) fn stage_maps(
    out: &mut OutputDir,
    recon: &Reconstruction,
    source: &Described,
    config: &Config,
) -> Result<()> {
    let (w, h) = (recon.maps.normals.width(), recon.maps.normals.height());
    let attrs = |file: &str| exr_attributes(source.lights, config, file);
    let rows = map_rows(&recon.maps);
    out.stage_exr(
        "normal.exr",
        w,
        h,
        &named(&NORMAL_CHANNELS, &rows.normal),
        &attrs("normal.exr"),
    )?;
    out.stage_exr(
        "albedo.exr",
        w,
        h,
        &named(albedo_channels(rows.albedo.len())?, &rows.albedo),
        &attrs("albedo.exr"),
    )?;
    out.stage_exr(
        "residual.exr",
        w,
        h,
        &named(&RESIDUAL_CHANNELS, &rows.residual),
        &attrs("residual.exr"),
    )?;
    out.stage_exr(
        "curl.exr",
        w,
        h,
        &[("curl", recon.curl.data())],
        &attrs("curl.exr"),
    )?;
    out.stage_png8("mask.png", w, h, 1, &rows.mask)?;
    out.stage_png8("normal.png", w, h, 3, &rows.normal_png)?;
    let albedo: Vec<ScalarMap> = rows
        .albedo
        .into_iter()
        .map(|a| Grid::from_vec(w, h, a))
        .collect::<Result<_>>()?;
    out.stage_png8("albedo.png", w, h, albedo.len(), &albedo_png(&albedo))?;
    Ok(())
}

/// Stages the outputs that depend on depth: `depth.exr` (with the integration residual and
/// weights), `depth.png`, and `mesh.ply` when asked for. Without integration nothing is
/// staged: no depth file is written that holds no depth.
pub(crate) fn stage_depth(
    out: &mut OutputDir,
    normals: &NormalMap,
    integration: Option<&Integration>,
    source: &Described,
    config: &Config,
) -> Result<()> {
    let Some(i) = integration else {
        return Ok(());
    };
    let (w, h) = (normals.width(), normals.height());
    let mut depth_channels: Vec<(&str, &[f32])> =
        vec![("Z", i.depth.data()), ("residual", i.residual.data())];
    if let Some((wu, wv)) = &i.weights {
        depth_channels.push(("wu", wu.data()));
        depth_channels.push(("wv", wv.data()));
    }
    let mut depth_attrs = exr_attributes(source.lights, config, "depth.exr");
    let camera = config.integration.as_ref().and_then(|o| o.camera);
    if let Some(options) = &config.integration {
        depth_attrs.push(("photostereo:integration", options.method.name().to_string()));
    }
    out.stage_exr("depth.exr", w, h, &depth_channels, &depth_attrs)?;
    if config.mesh {
        let mesh = crate::io::mesh::Mesh::from_depth(&i.depth, normals, camera.as_ref())?;
        out.stage_bytes("mesh.ply", &mesh.to_ply())?;
    }
    out.stage_png8(
        "depth.png",
        w,
        h,
        1,
        &depth_preview(&i.depth, camera.as_ref()),
    )?;
    Ok(())
}
