//! `photostereo sfs`: shape from shading of one image.

use crate::args::{SfsArgs, SfsBrdfArg, SfsMethodArg};
use anyhow::{Context, Result, bail};
use photostereo::capture::stack::GREY_WEIGHTS;
use photostereo::grid::Grid;
use photostereo::io::decode::{read_image, read_mask, srgb_to_linear};
use photostereo::io::output::{OutputDir, depth_preview, normal_planes, normal_preview};
use photostereo::nalgebra::Vector3;
use photostereo::sfs::estimate::illumination;
use photostereo::sfs::perspective::{PerspectiveOptions, PointLight, RefineOptions};
use photostereo::sfs::{
    SfsOptions, SfsResult, object_mask, shape_from_shading_from, shape_from_shading_with_progress,
};
use photostereo::synth::reflectance::{
    BlinnPhong, Diffuse, Material, Phong, Specular, TorranceSparrow, Ward,
};

/// Contour levels of the reflectance-map drawing.
const CONTOUR_LEVELS: [f64; 9] = [0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9];

pub fn run(a: SfsArgs, progress: &dyn photostereo::progress::Progress) -> Result<()> {
    let inputs: Vec<&std::path::Path> = std::iter::once(a.image.as_path())
        .chain(a.mask.as_deref())
        .chain(a.camera.as_deref())
        .chain(a.start.as_deref())
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
    let material = material(&a)?;
    let method = a.method.unwrap_or(if a.light_position.is_some() {
        SfsMethodArg::Perspective
    } else {
        SfsMethodArg::Horn
    });
    if a.no_outline_repair && method != SfsMethodArg::Horn {
        bail!(
            "--no-outline-repair is for --method horn (the only method that repairs the outline)"
        );
    }
    if a.no_restarts && method != SfsMethodArg::Horn {
        bail!("--no-restarts is for --method horn (the only method that repeats its continuation)");
    }
    if a.start.is_some() && method != SfsMethodArg::Horn {
        bail!("--start is for --method horn (the only method that refines a given surface)");
    }
    if a.start.is_some() && (a.single_resolution || a.no_restarts || a.no_outline_repair) {
        bail!(
            "--start refines the given surface at the final smoothness alone: there is no \
             coarse-to-fine start, repeat or outline repair to turn off"
        );
    }
    if a.single_resolution && method != SfsMethodArg::Horn {
        bail!(
            "--single-resolution is for --method horn (the only method whose coarse-to-fine start can be turned off)"
        );
    }
    if method == SfsMethodArg::Perspective {
        return perspective(&a, &image, &mask, mask_source, material);
    }
    for (flag, given) in [
        ("--camera", a.camera.is_some()),
        ("--light-position", a.light_position.is_some()),
        ("--light-intensity", a.light_intensity.is_some()),
        ("--no-refine", a.no_refine),
        ("--refine-smoothness", a.refine_smoothness.is_some()),
        ("--refine-iterations", a.refine_iterations != 0),
    ] {
        if given {
            bail!(
                "{flag} is for --method perspective; {} assumes a distant light and an \
                 orthographic camera",
                photostereo::sfs::SfsMethod::from(method).name()
            );
        }
    }
    if a.brdf != SfsBrdfArg::Lambertian && (a.light.is_none() || a.albedo.is_none()) {
        bail!(
            "--brdf {}: the light and albedo are estimated for a Lambertian surface only; give \
             --light and --albedo",
            brdf_name(a.brdf)
        );
    }
    let depth_units = photostereo::run::pipeline::exr_units("depth.exr", None);
    // The start surface, read and brought to the image's grid (another resolution, holes
    // filled) before anything is estimated, so that a start that cannot be used is refused
    // first; the library's errors are told with the file.
    let start = match &a.start {
        Some(path) => {
            // A file that says what its values are is read as what it says: perspective depth
            // (along the optical axis, up to scale) is not a height in pixels.
            if let Some(units) = photostereo::io::decode::read_exr_text(path, "photostereo:units")?
                && units != depth_units
            {
                bail!(
                    "{}: holds \"{units}\"; --start takes heights towards the camera in pixels \
                     (an orthographic depth.exr)",
                    path.display()
                );
            }
            let z = photostereo::io::decode::read_exr_channel(path, "Z")?;
            let z = photostereo::sfs::start::prepare_start(&z, &mask)
                .with_context(|| format!("start surface {}", path.display()))?;
            Some((path, z))
        }
        None => None,
    };
    let prepared = start.as_ref().map(|(_, z)| (z.scale, z.filled));
    let (rmap, lit) = illumination(
        &image,
        &mask,
        a.light.map(Vector3::from),
        a.albedo,
        material,
    )?;
    let (light, albedo, estimate) = (Vector3::from(lit.light), lit.albedo, lit.estimate);
    let options = SfsOptions {
        method: method.into(),
        boundary: a.boundary.into(),
        max_iterations: a.iterations,
        smoothness: a.smoothness,
        shadow_level: a.shadow_level,
        coarse_to_fine: !a.single_resolution,
        outline_repair: !a.no_outline_repair,
        restarts: !a.no_restarts,
    };
    let r = match &start {
        Some((path, start)) => shape_from_shading_from(
            &image,
            &mask,
            &rmap,
            albedo,
            &options,
            &start.heights,
            progress,
        )
        .with_context(|| format!("start surface {}", path.display()))?,
        None => shape_from_shading_with_progress(&image, &mask, &rmap, albedo, &options, progress)?,
    };
    let (w, h) = (image.width(), image.height());
    let method = options.method.name();
    let svg = rmap.contour_svg(3.0, &CONTOUR_LEVELS, 241)?;
    let report = serde_json::json!({
        "image": a.image,
        "mask": mask_source,
        "start": a.start,
        "start_scale": prepared.map(|(scale, _)| scale),
        "start_filled": prepared.map(|(_, filled)| filled),
        "light_source": if estimate.is_some() { "estimated (Zheng–Chellappa, sphere-like normals assumed)" } else { "given" },
        "albedo_source": if a.albedo.is_some() { "given" } else { "estimated (sphere-like normals assumed)" },
        "brdf": brdf_name(a.brdf),
        "estimate": estimate,
        "result": r.report,
    });
    write(&a, &r, light, &depth_units, Some(&svg), &report)?;
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
        "  {} iterations{}{}{} in {:.3} s; mean |E/ρ − R| {:.4}; median |curl| {:.2e}",
        rep.iterations,
        if rep.coarse_iterations > 0 {
            format!(" (after {} at lower resolutions)", rep.coarse_iterations)
        } else {
            String::new()
        },
        match rep.restarts {
            0 => String::new(),
            1 => ", the continuation repeated once from its result".to_string(),
            k => format!(", the continuation repeated {k} times from its result"),
        },
        if rep.converged {
            ""
        } else {
            " (not converged)"
        },
        rep.seconds,
        rep.mean_abs_residual,
        rep.median_abs_curl
    );
    if let (Some(path), Some((scale, filled))) = (&a.start, prepared) {
        let mut how = Vec::new();
        if scale != 1.0 {
            how.push(format!("resampled ×{}", fmt_scale(scale)));
        }
        if filled > 0 {
            // A start finer than the image was averaged to its pixels first.
            let what = if scale < 1.0 {
                "pixels of its average"
            } else {
                "of its samples"
            };
            how.push(format!(
                "{filled} {what} inside the mask without a height filled"
            ));
        }
        let how = if how.is_empty() {
            String::new()
        } else {
            format!(" ({})", how.join(", "))
        };
        say!(
            "  refined from the start surface {}{how} at the final smoothness",
            path.display()
        );
    }
    say_outline(rep);
    if let Some(r) = &rep.outline_repair {
        say!(
            "  outline repair: the first solve had {:.0}% misaligned; solved again upsampled 2× \
             ({} iterations{}): {}",
            100.0 * r.first.misaligned_fraction,
            r.iterations,
            if r.converged { "" } else { ", not converged" },
            match (r.kept, r.upsampled) {
                (true, Some(u)) =>
                    format!("{:.0}% misaligned, kept", 100.0 * u.misaligned_fraction),
                (false, Some(u)) =>
                    format!("{:.0}% misaligned, not kept", 100.0 * u.misaligned_fraction),
                (_, None) => "no result, not kept".to_string(),
            }
        );
    }
    tell(rep, &a.output);
    Ok(())
}

/// Writes depth.exr, normal.exr, their previews, the reflectance map's drawing (distant light)
/// and report.json into the output folder, atomically.
fn write(
    a: &SfsArgs,
    r: &SfsResult,
    light: Vector3<f64>,
    depth_units: &str,
    svg: Option<&str>,
    report: &serde_json::Value,
) -> Result<()> {
    let (w, h) = (r.depth.width(), r.depth.height());
    let attrs = [
        ("photostereo:sfs-method", r.report.method.name().to_string()),
        (
            "photostereo:light_direction",
            format!("{:.6} {:.6} {:.6}", light.x, light.y, light.z),
        ),
        ("photostereo:units", depth_units.to_string()),
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
    if let Some(svg) = svg {
        out.stage_bytes("reflectance_map.svg", svg.as_bytes())?;
    }
    out.stage_bytes(
        "report.json",
        serde_json::to_string_pretty(report)
            .context("report")?
            .as_bytes(),
    )?;
    out.commit()?;
    Ok(())
}

/// `--method perspective`: a pinhole camera and a point light with fall-off.
fn perspective(
    a: &SfsArgs,
    image: &photostereo::grid::ScalarMap,
    mask: &photostereo::grid::Mask,
    mask_source: &str,
    material: Material,
) -> Result<()> {
    let Some(camera) = &a.camera else {
        bail!("--method perspective needs the camera's intrinsics: --camera K.txt");
    };
    let Some(position) = a.light_position else {
        bail!(
            "--method perspective needs the light's position: --light-position x,y,z (camera \
             frame; 0,0,0 for a light at the camera centre)"
        );
    };
    if a.light.is_some() {
        bail!(
            "--light is a distant light's direction; --method perspective takes --light-position"
        );
    }
    let k = photostereo::camera::Intrinsics::from_file(camera)?;
    if a.light_intensity.is_none() || a.albedo.is_none() {
        eprintln!(
            "warning: {} not given, 1 assumed: the depth's scale goes with 1/√(albedo × \
             intensity), and a wrong value bends the shape too",
            match (a.light_intensity.is_none(), a.albedo.is_none()) {
                (true, true) => "--light-intensity and --albedo",
                (true, false) => "--light-intensity",
                _ => "--albedo",
            }
        );
    }
    let light = PointLight {
        position: Vector3::from(position),
        intensity: a.light_intensity.unwrap_or(1.0),
    };
    let options = PerspectiveOptions {
        material,
        albedo: a.albedo.unwrap_or(1.0),
        shadow_level: a.shadow_level,
        max_sweeps: a.iterations,
        tolerance: 0.0,
        start: None,
        refine: (!a.no_refine).then(|| RefineOptions {
            smoothness: a
                .refine_smoothness
                .unwrap_or(photostereo::sfs::perspective::refine::DEFAULT_SMOOTHNESS),
            max_iterations: if a.refine_iterations > 0 {
                a.refine_iterations
            } else {
                photostereo::sfs::perspective::refine::DEFAULT_MAX_ITERATIONS
            },
            ..RefineOptions::default()
        }),
    };
    let r = photostereo::sfs::perspective::solve(image, mask, &k, &light, &options)?;
    let units = format!(
        "Z: depth along the optical axis in the light position's units (absolute), pinhole \
         fx={} fy={} cx={} cy={}, larger is farther; residual: (I - I_model) d^2 / (Phi F(1))",
        k.fx, k.fy, k.cx, k.cy
    );
    let report = serde_json::json!({
        "image": a.image,
        "mask": mask_source,
        "camera": camera,
        "light_position": position,
        "light_intensity": light.intensity,
        "albedo_source": if a.albedo.is_some() { "given" } else { "1 (not given)" },
        "brdf": brdf_name(a.brdf),
        "result": r.report,
    });
    let dir = Vector3::from(r.report.light);
    write(a, &r, dir, &units, None, &report)?;
    let rep = &r.report;
    say!(
        "perspective: {}x{} image, {} pixels ({} in shadow), light at ({:.4}, {:.4}, {:.4}), {:.1}° \
         from the view at the surface's centre, albedo {:.4}, intensity {:.4}",
        image.width(),
        image.height(),
        rep.pixels,
        rep.shadow_pixels,
        position[0],
        position[1],
        position[2],
        rep.light_slant_deg,
        options.albedo,
        light.intensity
    );
    say!(
        "  {} sweeps{} in {:.3} s; mean relative residual {:.4}",
        rep.iterations,
        if rep.converged {
            ""
        } else {
            " (not converged)"
        },
        rep.seconds,
        rep.mean_abs_residual
    );
    let from = |f: &photostereo::sfs::perspective::RefineReport| {
        if f.coarse_iterations > 0 {
            format!(
                " (from a start refined in {} steps at lower resolutions)",
                f.coarse_iterations
            )
        } else {
            String::new()
        }
    };
    match &rep.refinement {
        Some(f) if f.discarded => say!(
            "  refinement discarded after {} steps in {:.3} s{}: they moved the whole surface \
             by {:+.1}%; the depth is their start",
            f.iterations,
            f.seconds,
            from(f),
            100.0 * (f.shift.exp() - 1.0)
        ),
        Some(f) => say!(
            "  refined: {} steps{} in {:.3} s{} over {} cells, energy {:.3e} -> {:.3e}, rms \
             relative residual {:.4}",
            f.iterations,
            if f.converged { "" } else { " (not converged)" },
            f.seconds,
            from(f),
            f.cells,
            f.energy_start,
            f.energy_end,
            f.rms_residual
        ),
        None => {}
    }
    say_outline(rep);
    tell(rep, &a.output);
    Ok(())
}

/// The lines on the mask's outline: where the image says it is no occluding contour, and how
/// the normals beside it agree with one, when the method measured them.
fn say_outline(rep: &photostereo::sfs::SfsReport) {
    if let Some(t) = &rep.occluding
        && t.contradicted > 0
    {
        say!(
            "  outline test: {} of {} outline pixels brighter than an occluding contour can be \
             ({:.0}%)",
            t.contradicted,
            t.pixels,
            100.0 * t.fraction
        );
    }
    if let Some(o) = &rep.outline {
        say!(
            "  outline: {:.0}% of {} pixels with normals more than {:.0}° from its outward \
             direction (mean {:.1}°)",
            100.0 * o.misaligned_fraction,
            o.pixels,
            photostereo::sfs::OUTLINE_TOLERANCE_DEG,
            o.mean_angle_deg
        );
    }
}

/// The material of `--brdf` and its parameters; a parameter the model does not use is refused.
fn material(a: &SfsArgs) -> Result<Material> {
    use SfsBrdfArg as B;
    let uses = |flag: &str| match a.brdf {
        B::Lambertian => false,
        B::OrenNayar => flag == "--roughness",
        B::Phong | B::BlinnPhong => matches!(flag, "--shininess" | "--specular"),
        B::TorranceSparrow => matches!(flag, "--roughness" | "--specular" | "--f0"),
        B::Ward => matches!(flag, "--roughness" | "--specular"),
    };
    for (flag, given) in [
        ("--roughness", a.roughness.is_some()),
        ("--shininess", a.shininess.is_some()),
        ("--specular", a.specular.is_some()),
        ("--f0", a.f0.is_some()),
    ] {
        if given && !uses(flag) {
            bail!("{flag} has no effect with --brdf {}", brdf_name(a.brdf));
        }
    }
    let ks = a.specular.unwrap_or(0.5);
    let m = match a.brdf {
        B::Lambertian => Material::lambertian(),
        B::OrenNayar => Material {
            diffuse: Diffuse::OrenNayar {
                sigma: a.roughness.unwrap_or(20.0).to_radians(),
            },
            ..Material::lambertian()
        },
        B::Phong => Material::with_specular(Specular::Phong(Phong {
            ks,
            exponent: a.shininess.unwrap_or(40.0),
        })),
        B::BlinnPhong => Material::with_specular(Specular::BlinnPhong(BlinnPhong {
            ks,
            exponent: a.shininess.unwrap_or(40.0),
        })),
        B::TorranceSparrow => Material::with_specular(Specular::TorranceSparrow(TorranceSparrow {
            ks,
            roughness: a.roughness.unwrap_or(0.3),
            f0: a.f0.unwrap_or(0.04),
        })),
        B::Ward => {
            let alpha = a.roughness.unwrap_or(0.2);
            Material::with_specular(Specular::Ward(Ward {
                ks,
                alpha_x: alpha,
                alpha_y: alpha,
            }))
        }
    };
    m.validate()?;
    Ok(m)
}

/// The command-line name of a `--brdf` value.
fn brdf_name(b: SfsBrdfArg) -> String {
    use clap::ValueEnum;
    b.to_possible_value()
        .map_or_else(|| format!("{b:?}"), |v| v.get_name().to_string())
}

/// Prints a run's assumptions and warnings and where it wrote.
fn tell(rep: &photostereo::sfs::SfsReport, output: &std::path::Path) {
    for s in &rep.assumptions {
        say!("  assumed: {s}");
    }
    for s in &rep.warnings {
        eprintln!("warning: {}", crate::printable(&s.to_string()));
    }
    say!("  wrote {}", output.display());
}

/// A resampling factor for the summary: "4" for 4, "2.5" for 2.5, "0.333" for a third; to
/// four digits where three would round it to 1.
fn fmt_scale(scale: f64) -> String {
    let trim = |s: String| s.trim_end_matches('0').trim_end_matches('.').to_string();
    match trim(format!("{scale:.3}")) {
        one if one == "1" => format!("{scale:.4}"),
        s => s,
    }
}
