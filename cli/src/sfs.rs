//! `photostereo sfs`: shape from shading of one image.

use crate::args::SfsArgs;
use anyhow::{Context, Result, bail};
use photostereo::capture::stack::GREY_WEIGHTS;
use photostereo::grid::Grid;
use photostereo::io::decode::{read_image, read_mask, srgb_to_linear};
use photostereo::io::output::{OutputDir, depth_preview, normal_planes, normal_preview};
use photostereo::nalgebra::Vector3;
use photostereo::sfs::estimate::{estimate_albedo, estimate_light};
use photostereo::sfs::reflectance_map::ReflectanceMap;
use photostereo::sfs::{SfsOptions, object_mask, shape_from_shading_with_progress};

/// Contour levels of the reflectance-map drawing.
const CONTOUR_LEVELS: [f64; 9] = [0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9];

pub fn run(a: SfsArgs, progress: &dyn photostereo::progress::Progress) -> Result<()> {
    let inputs: Vec<&std::path::Path> = std::iter::once(a.image.as_path())
        .chain(a.mask.as_deref())
        .collect();
    photostereo::io::output::ensure_apart(&a.output, &inputs)?;
    let _lock = crate::lock_output(&a.output, a.force)?;
    let img = read_image(&a.image)?;
    let eight_bit = matches!(img.format, photostereo::io::decode::SampleFormat::U8);
    let grey: Vec<f32> = img
        .data
        .chunks(img.channels)
        .map(|px| {
            let v = if px.len() == 3 {
                px.iter().zip(GREY_WEIGHTS).map(|(v, w)| v * w).sum()
            } else {
                px[0]
            };
            if eight_bit && !a.linear {
                srgb_to_linear(v)
            } else {
                v
            }
        })
        .collect();
    let image = Grid::from_vec(img.width, img.height, grey)?;
    let (mask, mask_source) = match &a.mask {
        Some(m) => {
            let m = read_mask(m)?;
            image.check_same_size(&m, "mask")?;
            (m, "file")
        }
        None => {
            eprintln!(
                "warning: no --mask: the object is every pixel but the black background touching \
                 the border, so attached shadows that touch it are left out; give a mask for \
                 shadowed objects"
            );
            (
                object_mask(&image),
                "non-black pixels connected inside the border",
            )
        }
    };
    if mask.count() == 0 {
        bail!(
            "{}: no object pixel (the image is black)",
            a.image.display()
        );
    }
    let estimate = if a.light.is_none() {
        Some(estimate_light(&image, &mask)?)
    } else {
        None
    };
    let light = match (a.light, &estimate) {
        (Some(l), _) => Vector3::from(l),
        (None, Some(e)) => e.light(),
        (None, None) => bail!("no light direction given and none estimated"),
    };
    let rmap = ReflectanceMap::lambertian(light)?;
    let albedo = match (a.albedo, &estimate) {
        (Some(v), _) => v,
        (None, Some(e)) => e.albedo,
        (None, None) => estimate_albedo(&image, &mask, rmap.slant_deg())?,
    };
    let options = SfsOptions {
        method: a.method.into(),
        boundary: a.boundary.into(),
        max_iterations: a.iterations,
        smoothness: a.smoothness,
        shadow_level: a.shadow_level,
    };
    let r = shape_from_shading_with_progress(&image, &mask, &rmap, albedo, &options, progress)?;
    let (w, h) = (image.width(), image.height());
    let method = options.method.name();
    let attrs = [
        ("photostereo:sfs-method", method.to_string()),
        (
            "photostereo:light_direction",
            format!("{:.6} {:.6} {:.6}", light.x, light.y, light.z),
        ),
        (
            "photostereo:units",
            photostereo::run::pipeline::exr_units("depth.exr", None),
        ),
    ];
    let mut normal_attrs = attrs.clone();
    normal_attrs[2].1 = photostereo::run::pipeline::exr_units("normal.exr", None);
    let mut out = OutputDir::create(&a.output)?;
    out.stage_exr(
        "depth.exr",
        w,
        h,
        &[("Z", r.depth.data()), ("residual", r.residual.data())],
        &attrs,
    )?;
    let [nx, ny, nz] = normal_planes(&r.normals);
    out.stage_exr(
        "normal.exr",
        w,
        h,
        &[("R", &nx), ("G", &ny), ("B", &nz)],
        &normal_attrs,
    )?;
    out.stage_png8("normal.png", w, h, 3, &normal_preview(&r.normals))?;
    out.stage_png8("depth.png", w, h, 1, &depth_preview(&r.depth, None))?;
    let svg = rmap.contour_svg(3.0, &CONTOUR_LEVELS, 241)?;
    out.stage_bytes("reflectance_map.svg", svg.as_bytes())?;
    let report = serde_json::json!({
        "image": a.image,
        "mask": mask_source,
        "light_source": if estimate.is_some() { "estimated (Zheng–Chellappa, sphere-like normals assumed)" } else { "given" },
        "albedo_source": if a.albedo.is_some() { "given" } else { "estimated (sphere-like normals assumed)" },
        "estimate": estimate,
        "result": r.report,
    });
    out.stage_bytes(
        "report.json",
        serde_json::to_string_pretty(&report)
            .context("report")?
            .as_bytes(),
    )?;
    out.commit()?;
    let rep = &r.report;
    say!(
        "{method}: {}x{} image, {} pixels ({} in shadow), light ({:.3}, {:.3}, {:.3}) {} at {:.1}° from the view, albedo {:.4} {}",
        w,
        h,
        rep.pixels,
        rep.shadow_pixels,
        light.x,
        light.y,
        light.z,
        if estimate.is_some() {
            "estimated"
        } else {
            "given"
        },
        rep.light_slant_deg,
        albedo,
        if a.albedo.is_some() {
            "given"
        } else {
            "estimated"
        },
    );
    say!(
        "  {} iterations{} in {:.3} s; mean |E/ρ − R| {:.4}; median |curl| {:.2e}",
        rep.iterations,
        if rep.converged {
            ""
        } else {
            " (not converged)"
        },
        rep.seconds,
        rep.mean_abs_residual,
        rep.median_abs_curl
    );
    for s in &rep.assumptions {
        say!("  assumed: {s}");
    }
    for s in &rep.warnings {
        eprintln!("warning: {}", crate::printable(&s.to_string()));
    }
    say!("  wrote {}", a.output.display());
    Ok(())
}
