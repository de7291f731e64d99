//! `photostereo calibrate`: lights from a chrome sphere (and a matte reference).

use crate::args::CalibrateArgs;
use anyhow::{Result, bail};
use photostereo::calibrate::from_object::{FromObjectOptions, lights_from_stack};
use photostereo::calibrate::intensity::{
    MatteOptions, intensities_from_card, intensities_from_sphere,
};
use photostereo::calibrate::near::{NearOptions, calibrate_two_balls, near_lights_file_json};
use photostereo::calibrate::{
    ChromeOptions, HighlightResult, IntensityCalibration, calibrate_chrome, find_sphere,
    lights_file_json, load_reference_images, read_grey_mask,
};
use photostereo::camera::Intrinsics;
use photostereo::capture::dataset::{is_image_list, read_image_list};
use photostereo::capture::lights::{Light, Lights};
use photostereo::capture::stack::Transfer;
use photostereo::io::decode::read_mask;
use photostereo::io::output::ensure_fresh_file;
use photostereo::nalgebra::Vector3;
use photostereo::progress::Progress;
use std::path::{Path, PathBuf};

/// Angle (degrees) between the matte sphere's and the chrome sphere's direction of a light
/// above which the two references are said to disagree.
const DISAGREEMENT_DEG: f64 = 5.0;

/// Images from the command line: the files, or one image list with its mask.
fn expand(paths: &[PathBuf]) -> Result<(Vec<PathBuf>, Option<PathBuf>)> {
    if let [one] = paths
        && is_image_list(one)
    {
        let list = read_image_list(one)?;
        return Ok((list.images, list.mask));
    }
    Ok((paths.to_vec(), None))
}

/// `e`, with the flag `flag` that gives the sphere's mask when the sphere was not found.
fn mask_hint(e: photostereo::Error, flag: &str) -> anyhow::Error {
    match e {
        photostereo::Error::SphereNotFound { .. } => {
            anyhow::anyhow!("{e}; give the sphere's mask with {flag}")
        }
        e => e.into(),
    }
}

pub fn run(a: CalibrateArgs, progress: &dyn Progress) -> Result<()> {
    let mut inputs: Vec<&std::path::Path> = a.images.iter().map(|p| p.as_path()).collect();
    inputs.extend(a.matte.iter().map(|p| p.as_path()));
    inputs.extend(
        [&a.mask, &a.matte_mask, &a.card_mask, &a.camera]
            .into_iter()
            .flatten()
            .map(|p| p.as_path()),
    );
    photostereo::io::output::ensure_apart(&a.output, &inputs)?;
    if !a.force {
        ensure_fresh_file(&a.output)?;
    }
    let transfer = if a.linear {
        Transfer::Linear
    } else {
        Transfer::Auto
    };
    let (chrome_paths, list_mask) = expand(&a.images)?;
    let chrome_mask = a.mask.clone().or(list_mask);
    if let Some(level) = a.saturation
        && !(level > 0.0 && level.is_finite())
    {
        bail!("--saturation {level}: must be a positive level");
    }
    if let Some(r) = a.ball_radius
        && !(r > 0.0 && r.is_finite())
    {
        bail!("--ball-radius {r}: must be a positive length");
    }
    let camera = a.camera.as_deref().map(Intrinsics::from_file).transpose()?;
    if a.from_object && chrome_mask.is_none() {
        bail!(
            "--from-object needs the object's mask (--mask): the outline decides between the \
             convex and the concave surface"
        );
    }
    let stack = load_reference_images(&chrome_paths, transfer, a.saturation, progress)?;
    if a.from_object {
        return run_from_object(&a, &stack, chrome_mask.as_deref());
    }
    let mask = chrome_mask.as_deref().map(read_grey_mask).transpose()?;
    let options = ChromeOptions {
        camera,
        ..ChromeOptions::default()
    };
    if let (Some(k), Some(radius)) = (camera, a.ball_radius) {
        return run_near(
            &a,
            &stack,
            mask.as_ref().zip(chrome_mask.as_deref()),
            k,
            radius,
            transfer,
            progress,
        );
    }
    let cal = calibrate_chrome(&stack, mask.as_ref().zip(chrome_mask.as_deref()), &options)
        .map_err(|e| mask_hint(e, "--mask"))?;
    report_ball(&cal, None);
    let lights = chosen(a.keep_doubtful, || cal.all_lights(), || cal.lights())?;
    let directions = lights.directions();
    let (lights, intensity) =
        measure_intensities(&a, &stack, lights, &directions, transfer, progress)?;
    let json = lights_file_json(&lights, &cal, intensity.as_ref());
    photostereo::io::output::write_bytes(&a.output, crate::overwrite(a.force), json.as_bytes())?;
    say!("wrote {} ({} lights)", a.output.display(), lights.len());
    Ok(())
}

/// Lights recovered from the object's own images (`--from-object`).
fn run_from_object(
    a: &CalibrateArgs,
    stack: &photostereo::capture::stack::ImageStack,
    mask: Option<&Path>,
) -> Result<()> {
    let Some(mask_path) = mask else {
        bail!(
            "--from-object needs the object's mask (--mask): the outline decides between the \
             convex and the concave surface"
        );
    };
    let mask = read_mask(mask_path)?;
    let options = FromObjectOptions {
        min_rank3_gap: if a.keep_doubtful {
            0.0
        } else {
            FromObjectOptions::default().min_rank3_gap
        },
        ..FromObjectOptions::default()
    };
    let got = lights_from_stack(stack, &mask, &options).map_err(|e| {
        if e.to_string().contains("not clearly rank 3") {
            anyhow::anyhow!("{e} (--keep-doubtful writes them anyway)")
        } else {
            e.into()
        }
    })?;
    say!(
        "lights from the object: {} pixels lit in every image, rank-3 gap {:.1}, bas-relief \
         (μ, ν, λ) = ({:.3}, {:.3}, {:.3}), entropy drop {:.3} nats, {:.0}% of the outline \
         facing outwards",
        got.lit_pixels,
        got.rank3_gap,
        got.gbr[0],
        got.gbr[1],
        got.gbr[2],
        got.entropy_drop,
        100.0 * got.outline_outward
    );
    for (k, ((d, i), u)) in got
        .directions
        .iter()
        .zip(&got.intensities)
        .zip(&got.uncertainty_deg)
        .enumerate()
    {
        let image = file_name(&stack.info()[k].path);
        let spread = if u.is_finite() {
            format!("halves {:.2}° apart", 2.0 * u)
        } else {
            "no split-half spread".to_string()
        };
        say!(
            "  {k:>3} {image}: direction ({:.4}, {:.4}, {:.4}), intensity {:.4}, {spread}",
            d[0],
            d[1],
            d[2],
            i
        );
    }
    for s in &got.assumptions {
        say!("  assumed: {s}");
    }
    eprintln!(
        "note: lights recovered from the object are only as good as its Lambertian fit: on \
         real objects expect errors of several degrees (the spread between halves is not a \
         bound: it misses errors both halves share); a chrome ball is better when one can be \
         photographed"
    );
    for w in &got.warnings {
        eprintln!("warning: {}", crate::printable(w));
    }
    let json = got.lights_file_json();
    photostereo::io::output::write_bytes(&a.output, crate::overwrite(a.force), json.as_bytes())?;
    say!(
        "wrote {} ({} lights)",
        a.output.display(),
        got.directions.len()
    );
    Ok(())
}

/// Near lights from two balls (`--ball-radius`).
fn run_near(
    a: &CalibrateArgs,
    stack: &photostereo::capture::stack::ImageStack,
    mask: Option<(&photostereo::grid::ScalarMap, &Path)>,
    camera: Intrinsics,
    radius: f64,
    transfer: Transfer,
    progress: &dyn Progress,
) -> Result<()> {
    let two = calibrate_two_balls(stack, mask, &NearOptions::new(camera, radius)).map_err(|e| {
        match e {
            // One ball found: a mask would not add the other.
            photostereo::Error::SphereNotFound { ref reason } if reason.contains("need two") => {
                e.into()
            }
            e => mask_hint(e, "--mask (outlining both balls)"),
        }
    })?;
    if !a.matte.is_empty() || a.matte_mask.is_some() || a.card_mask.is_some() {
        eprintln!(
            "warning: the intensities are measured at the matte reference, without the near lights' fall-off with distance"
        );
    }
    for w in &two.warnings {
        eprintln!("warning: {}", crate::printable(w));
    }
    for (b, cal) in two.balls.iter().enumerate() {
        report_ball(cal, Some((b, two.centres[b])));
    }
    for (k, p) in two.positions.iter().enumerate() {
        let image = file_name(&two.balls[0].lights[k].image);
        match p {
            Ok(p) => {
                say!(
                    "  {k:>3} {image}: position ({:.4}, {:.4}, {:.4}) ± {:.4} (rms), {:.4} from the balls' midpoint, rays {:.2}σ apart{}",
                    p.position.x,
                    p.position.y,
                    p.position.z,
                    p.uncertainty,
                    p.distance,
                    p.miss_sigmas,
                    if p.accepted { "" } else { ", in doubt" }
                );
                for w in &p.warnings {
                    eprintln!("warning: image {k} ({image}): {w}");
                }
            }
            Err(why) => eprintln!("warning: image {k} ({image}): no position: {why}"),
        }
    }
    let lights = chosen(a.keep_doubtful, || two.all_lights(), || two.lights())?;
    let directions = lights.directions();
    let (lights, intensity) =
        measure_intensities(a, stack, lights, &directions, transfer, progress)?;
    let json = near_lights_file_json(&lights, &two, radius, intensity.as_ref());
    photostereo::io::output::write_bytes(&a.output, crate::overwrite(a.force), json.as_bytes())?;
    say!(
        "wrote {} ({} lights with positions, in the unit of the ball radius {radius})",
        a.output.display(),
        lights.len()
    );
    Ok(())
}

/// The lights to write: all of them with `--keep-doubtful`, else the accepted ones (an error
/// naming those in doubt, with the flag that keeps them).
fn chosen(
    keep_doubtful: bool,
    all: impl FnOnce() -> photostereo::Result<Lights>,
    accepted: impl FnOnce() -> photostereo::Result<Lights>,
) -> Result<Lights> {
    if keep_doubtful {
        return Ok(all()?);
    }
    accepted().map_err(|e| match e {
        photostereo::Error::BadImage { ref reason, .. } if reason.contains("in doubt") => {
            anyhow::anyhow!("{e}; --keep-doubtful writes them anyway")
        }
        e => e.into(),
    })
}

/// Prints one ball's outline and highlights (`ball`: its index and centre, for two balls).
fn report_ball(cal: &photostereo::calibrate::ChromeCalibration, ball: Option<(usize, [f64; 3])>) {
    let c = cal.sphere.circle;
    if let Some((b, centre)) = ball {
        say!(
            "ball {b}: centre ({:.4}, {:.4}, {:.4}) in the unit of the radius",
            centre[0],
            centre[1],
            centre[2]
        );
    }
    if let Some(k) = &cal.cone {
        let f = 0.5 * (k.camera.fx + k.camera.fy);
        say!(
            "  seen by the camera: axis ({:+.5}, {:+.5}, {:+.5}), half-angle {:.4}° ± {:.4}°, outline rms {:.2} px over {} edge points ({} outliers), tilt errors ({:.2}, {:.2}) px",
            k.axis.x,
            k.axis.y,
            k.axis.z,
            k.half_angle.to_degrees(),
            k.std_err[2].to_degrees(),
            k.rms_px,
            k.points,
            k.outliers,
            k.std_err[0] * f,
            k.std_err[1] * f
        );
    }
    say!(
        "chrome sphere ({}): centre ({:.2}, {:.2}) px, radius {:.2} px, ± ({:.2}, {:.2}, {:.2}) px, edge rms {:.2} px, {} edge points ({} outliers)",
        match cal.sphere_source {
            photostereo::calibrate::SphereSource::Mask => "from its mask",
            photostereo::calibrate::SphereSource::Detected => "detected",
        },
        c.cx,
        c.cy,
        c.radius,
        cal.sphere.std_err[0],
        cal.sphere.std_err[1],
        cal.sphere.std_err[2],
        cal.sphere.rms_px,
        cal.sphere.points,
        cal.sphere.outliers
    );
    for w in &cal.warnings {
        eprintln!("warning: {}", crate::printable(w));
    }
    for o in &cal.lights {
        match &o.result {
            HighlightResult::Found(h) => {
                say!(
                    "  {:>3} {}: l = ({:+.4}, {:+.4}, {:+.4}), highlight ({:.2}, {:.2}), {} px, ±{:.2}°, confidence {:.2}{}",
                    o.index,
                    file_name(&o.image),
                    h.direction.x,
                    h.direction.y,
                    h.direction.z,
                    h.centroid[0],
                    h.centroid[1],
                    h.pixels,
                    h.uncertainty_deg,
                    h.confidence,
                    if h.accepted { "" } else { ", in doubt" }
                );
                for w in &h.warnings {
                    eprintln!("warning: image {} ({}): {w}", o.index, file_name(&o.image));
                }
            }
            HighlightResult::Missing(m) => {
                eprintln!(
                    "warning: image {} ({}): {}",
                    o.index,
                    file_name(&o.image),
                    m.reason
                );
            }
        }
    }
}

/// Relative intensities from the matte sphere or card, when one is given.
fn measure_intensities(
    a: &CalibrateArgs,
    chrome: &photostereo::capture::stack::ImageStack,
    lights: Lights,
    directions: &[Vector3<f64>],
    transfer: Transfer,
    progress: &dyn Progress,
) -> Result<(Lights, Option<IntensityCalibration>)> {
    if a.matte.is_empty() && a.matte_mask.is_none() && a.card_mask.is_none() {
        return Ok((lights, None));
    }
    let (matte_stack, list_mask) = if a.matte.is_empty() {
        (None, None)
    } else {
        let (paths, mask) = expand(&a.matte)?;
        if paths.len() != directions.len() {
            bail!(
                "{} matte images for {} chrome images: the references must be photographed under the same lights, in the same order",
                paths.len(),
                directions.len()
            );
        }
        (
            Some(load_reference_images(
                &paths,
                transfer,
                a.saturation,
                progress,
            )?),
            mask,
        )
    };
    let stack = matte_stack.as_ref().unwrap_or(chrome);
    // Samples the loader flags saturated (at --saturation, or the maximum code) are skipped by
    // the fits, besides those at 0.98 of full scale once linear.
    let matte_options = MatteOptions::default();
    let (intensities, report) = if let Some(card) = &a.card_mask {
        let m = read_mask(card)?;
        let n = Vector3::from(a.card_normal);
        let e = intensities_from_card(stack, &m, n, directions, matte_options.saturation)?;
        (
            e,
            IntensityCalibration::GreyCard {
                pixels: m.count(),
                normal: a.card_normal,
            },
        )
    } else {
        let mask_path = a.matte_mask.clone().or(list_mask);
        let mask = mask_path.as_deref().map(read_grey_mask).transpose()?;
        let (sphere, sphere_source) = find_sphere(stack, mask.as_ref().zip(mask_path.as_deref()))
            .map_err(|e| mask_hint(e, "--matte-mask"))?;
        let fits = intensities_from_sphere(stack, &sphere.circle, directions, &matte_options)?;
        let c = sphere.circle;
        say!(
            "matte sphere: centre ({:.2}, {:.2}) px, radius {:.2} px",
            c.cx,
            c.cy,
            c.radius
        );
        for (k, f) in fits.iter().enumerate() {
            say!(
                "  {k:>3}: intensity ({:.4}, {:.4}, {:.4}), shading direction {:.2}° from the chrome one, fit rms {:.1}%",
                f.intensity[0],
                f.intensity[1],
                f.intensity[2],
                f.angle_to_given_deg,
                f.relative_rms * 100.0
            );
            if f.angle_to_given_deg > DISAGREEMENT_DEG {
                eprintln!(
                    "warning: light {k}: the matte sphere's shading points {:.1}° away from the chrome highlight's direction; check that both references saw the same light",
                    f.angle_to_given_deg
                );
            }
        }
        (
            fits.iter().map(|f| f.intensity).collect(),
            IntensityCalibration::MatteSphere {
                sphere,
                sphere_source,
                fits,
            },
        )
    };
    let lights = Lights::new(
        lights
            .lights()
            .iter()
            .zip(intensities)
            .map(|(l, e)| Light {
                intensity: e,
                ..l.clone()
            })
            .collect(),
    )?;
    Ok((lights, Some(report)))
}

fn file_name(p: &Path) -> String {
    p.file_name().map_or_else(
        || p.display().to_string(),
        |n| n.to_string_lossy().into_owned(),
    )
}
