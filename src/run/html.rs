//! `report.html`: one self-contained page beside a run's outputs, to look at a result without
//! a notebook — the previews, the report's figures, two charts (the lights as seen from the
//! camera, the noise estimated in each image) and a 3-D view of the depth as a shaded mesh
//! that turns with the mouse. Everything is inside the file (images as data URIs, the mesh as
//! JSON, the viewer as a few lines of script drawing on a 2-D canvas): it opens from disk with
//! no network and no WebGL.
//!
//! It is made from the files the run wrote (the PNG previews, `depth.exr`, the light directions
//! in the EXR headers) and its [`Report`], and is part of the run's output set.

use crate::error::{Error, Result};
use crate::io::output::OutputDir;
use crate::run::pipeline::Report;
use base64::Engine as _;
use std::fmt::Write as _;
use std::path::Path;

/// Longest side of the mesh in the 3-D view: the depth map is averaged over blocks to at most
/// this many vertices a side (a few ten thousand triangles stay interactive on a 2-D canvas).
pub const MESH_SIDE: usize = 128;

/// Stages `report.html` in the set `out`, made from the files staged there and `report`.
///
/// # Errors
/// [`Error::Io`] or [`Error::Decode`] when an output of the run cannot be read back, and the
/// errors of writing.
pub fn stage_report_html(out: &mut OutputDir, report: &Report) -> Result<()> {
    let html = report_html(out.staging_path(), report)?;
    out.stage_bytes("report.html", html.as_bytes())
}

/// The page's text (see the module documentation).
///
/// # Errors
/// As [`stage_report_html`].
pub fn report_html(dir: &Path, report: &Report) -> Result<String> {
    let image = |name: &str| -> Result<Option<String>> {
        let path = dir.join(name);
        if !path.is_file() {
            return Ok(None);
        }
        let bytes = std::fs::read(&path).map_err(|e| Error::io(&path, e))?;
        Ok(Some(format!(
            "data:image/png;base64,{}",
            base64::engine::general_purpose::STANDARD.encode(bytes)
        )))
    };
    let lights: Vec<[f64; 3]> =
        crate::io::decode::read_exr_text(&dir.join("normal.exr"), "photostereo:light_directions")?
            .and_then(|t| serde_json::from_str(&t).ok())
            .unwrap_or_default();
    let depth = dir.join("depth.exr");
    let mesh = if depth.is_file() {
        let z = crate::io::decode::read_exr_channel(&depth, "Z")?;
        let camera = report
            .config
            .integration
            .as_ref()
            .and_then(|o| o.camera.as_ref());
        Some(mesh_json(&z, camera))
    } else {
        None
    };
    let i = &report.inputs;
    let c = &report.pixels;
    let mut h = String::new();
    let _ = write!(
        h,
        r#"<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>photostereo report</title>
<style>
body {{ margin: 0; font: 14px/1.45 sans-serif; color: #222; background: #fafafa; }}
header {{ height: 56px; box-sizing: border-box; padding: 14px 16px; background: #1f4e9c; color: white; font-size: 20px; }}
main {{ padding: 16px; }}
#view {{ display: block; width: 640px; height: 480px; background: white; border: 1px solid #ccc; cursor: grab; }}
.row {{ display: flex; flex-wrap: wrap; gap: 16px; margin: 16px 0; }}
figure {{ margin: 0; }} figure img {{ max-width: 300px; image-rendering: pixelated; border: 1px solid #ccc; background: black; }}
figcaption {{ color: #555; }}
table {{ border-collapse: collapse; }} td, th {{ border: 1px solid #ddd; padding: 3px 8px; text-align: left; }}
.warn {{ color: #8a4b00; }}
</style></head><body>
<header>photostereo {version}: {count} images {w}x{h}, method {method}, integration {integration}</header>
<main>
"#,
        version = report.version,
        count = i.count,
        w = i.width,
        h = i.height,
        method = report.config.solve.method.name(),
        integration = report.integration.as_ref().map_or("none", |s| s.method),
    );
    match &mesh {
        Some(_) => h.push_str(
            "<canvas id=\"view\" width=\"640\" height=\"480\"></canvas>\n<p>Depth as a mesh: drag to turn it, scroll to zoom.</p>\n",
        ),
        None => h.push_str("<p>No depth: the run did not integrate the normals.</p>\n"),
    }
    h.push_str("<div class=\"row\">\n");
    for (file, caption) in [
        ("normal.png", "normals (RGB = (n + 1)/2)"),
        ("albedo.png", "albedo"),
        ("depth.png", "depth (shaded relief)"),
        ("mask.png", "mask"),
    ] {
        if let Some(uri) = image(file)? {
            let _ = writeln!(
                h,
                "<figure><img src=\"{uri}\" alt=\"{file}\"><figcaption>{caption}</figcaption></figure>"
            );
        }
    }
    h.push_str("</div>\n<div class=\"row\">\n");
    h.push_str(&lights_svg(&lights));
    if let Some(noise) = first_channel(&report.model.noise) {
        h.push_str(&bars_svg("noise σ estimated per image", &noise));
    }
    h.push_str("</div>\n<table>\n");
    let rows: Vec<(&str, String)> = vec![
        (
            "pixels",
            format!(
                "{} in the mask, {} solved, {} filled, {} too few samples, {} ill-conditioned, {} dark",
                c.masked, c.solved, c.filled, c.too_few_samples, c.ill_conditioned, c.dark
            ),
        ),
        (
            "robust fit",
            format!(
                "{:.1}% of solved pixels",
                100.0 * report.model.robust_fraction
            ),
        ),
        (
            "residual",
            format!(
                "mean {:.4}, median {:.4}",
                report.residual.mean, report.residual.median
            ),
        ),
        (
            "integrability (|curl|)",
            format!(
                "mean {:.3e}, median {:.3e}, 95th pct {:.3e}",
                report.integrability.mean_abs_curl,
                report.integrability.median_abs_curl,
                report.integrability.p95_abs_curl
            ),
        ),
        (
            "integration",
            report.integration.as_ref().map_or("none".into(), |s| {
                s.auto.as_ref().map_or(s.method.to_string(), |a| {
                    format!("{} ({})", s.method, a.reason)
                })
            }),
        ),
        (
            "time (s)",
            format!(
                "load {:.3}, solve {:.3}, normals {:.3}, integrate {:.3}, write {:.3}",
                report.timings_s.load,
                report.timings_s.solve,
                report.timings_s.normals,
                report.timings_s.integrate,
                report.timings_s.write
            ),
        ),
    ];
    for (k, v) in rows {
        let _ = writeln!(h, "<tr><th>{}</th><td>{}</td></tr>", escape(k), escape(&v));
    }
    h.push_str("</table>\n");
    if !report.warnings.is_empty() {
        h.push_str("<h3>Warnings</h3>\n<ul>\n");
        for w in &report.warnings {
            let _ = writeln!(h, "<li class=\"warn\">{}</li>", escape(&w.to_string()));
        }
        h.push_str("</ul>\n");
    }
    let json = serde_json::to_string_pretty(report).map_err(|e| Error::Encode {
        path: dir.join("report.html"),
        reason: e.to_string(),
    })?;
    let _ = writeln!(
        h,
        "<details><summary>report.json</summary><pre>{}</pre></details>",
        escape(&json)
    );
    h.push_str("</main>\n");
    if let Some(mesh) = mesh {
        let _ = writeln!(h, "<script>const MESH = {mesh};\n{VIEWER}</script>");
    }
    h.push_str("</body></html>\n");
    Ok(h)
}

/// The first channel's value per image (`values[image][channel]`).
fn first_channel(values: &[Vec<f32>]) -> Option<Vec<f32>> {
    let v: Vec<f32> = values.iter().filter_map(|c| c.first().copied()).collect();
    (!v.is_empty()).then_some(v)
}

fn escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// The light directions seen from the camera: (x, y) on the unit disk (the rim is the horizon),
/// each numbered by its image.
fn lights_svg(lights: &[[f64; 3]]) -> String {
    let (size, r) = (300.0, 120.0);
    let c = size / 2.0;
    let mut s = format!(
        r##"<svg xmlns="http://www.w3.org/2000/svg" width="{size}" height="{size}" font-size="10"><text x="8" y="16" font-size="13">lights seen from the camera (rim: horizon)</text><circle cx="{c}" cy="{c}" r="{r}" fill="white" stroke="#888"/><circle cx="{c}" cy="{c}" r="{h}" fill="none" stroke="#ccc" stroke-dasharray="3 3"/>"##,
        h = r * 30f64.to_radians().cos()
    );
    for (k, l) in lights.iter().enumerate() {
        let (x, y) = (c + r * l[0], c - r * l[1]);
        let _ = write!(
            s,
            r##"<circle cx="{x:.1}" cy="{y:.1}" r="4" fill="#e08000"><title>light {k}: ({:.3}, {:.3}, {:.3})</title></circle><text x="{:.1}" y="{:.1}">{k}</text>"##,
            l[0],
            l[1],
            l[2],
            x + 5.0,
            y - 4.0
        );
    }
    s.push_str("</svg>\n");
    s
}

/// A bar per value, scaled to the largest.
fn bars_svg(title: &str, values: &[f32]) -> String {
    let (w, h, top) = (420.0, 300.0, 40.0);
    let max = values
        .iter()
        .copied()
        .fold(0.0f32, f32::max)
        .max(f32::MIN_POSITIVE);
    let step = (w - 60.0) / values.len().max(1) as f64;
    let mut s = format!(
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" font-size="10"><text x="8" y="16" font-size="13">{}</text><text x="8" y="30">largest {max:.4}</text>"#,
        escape(title)
    );
    for (k, v) in values.iter().enumerate() {
        let bh = f64::from(v / max) * (h - top - 30.0);
        let _ = write!(
            s,
            r##"<rect x="{:.1}" y="{:.1}" width="{:.1}" height="{bh:.1}" fill="#1f4e9c"><title>image {k}: {v}</title></rect>"##,
            40.0 + step * k as f64,
            h - 20.0 - bh,
            (step * 0.6).max(1.0)
        );
    }
    let _ = write!(
        s,
        r#"<text x="40" y="{}">image 0</text><text x="{}" y="{}" text-anchor="end">{}</text></svg>"#,
        h - 6.0,
        w - 20.0,
        h - 6.0,
        values.len().saturating_sub(1)
    );
    s.push('\n');
    s
}

/// The depth map averaged over blocks to at most [`MESH_SIDE`] a side, as JSON
/// `{"w", "h", "step", "z": [… or null]}` with z a height towards the camera in pixel units
/// (a perspective depth is converted at the median distance, as `depth.png` does).
fn mesh_json(z: &crate::grid::ScalarMap, camera: Option<&crate::camera::Intrinsics>) -> String {
    let (w, h) = (z.width(), z.height());
    let step = w.max(h).div_ceil(MESH_SIDE).max(1);
    let (mw, mh) = (w.div_ceil(step), h.div_ceil(step));
    let scale = crate::io::output::height_scale(z, camera);
    let mut out = format!("{{\"w\":{mw},\"h\":{mh},\"step\":{step},\"z\":[");
    for my in 0..mh {
        for mx in 0..mw {
            let (mut sum, mut n) = (0.0f64, 0u32);
            for y in my * step..((my + 1) * step).min(h) {
                for x in mx * step..((mx + 1) * step).min(w) {
                    let v = z.data()[y * w + x];
                    if v.is_finite() {
                        sum += f64::from(v * scale);
                        n += 1;
                    }
                }
            }
            if my + mx > 0 {
                out.push(',');
            }
            // Blocks mostly outside the object are left out, so the outline stays sharp.
            if n as usize * 2 >= step * step || (n > 0 && step == 1) {
                let _ = write!(out, "{:.3}", sum / f64::from(n));
            } else {
                out.push_str("null");
            }
        }
    }
    out.push_str("]}");
    out
}

/// The viewer: a painter's-algorithm renderer of the mesh on a 2-D canvas, lit from the
/// viewer's upper left, turned by dragging and zoomed by the wheel. When it has drawn, it
/// records the triangle count on the canvas (`data-triangles`), which the tests read.
const VIEWER: &str = r#"
(function () {
  const cv = document.getElementById('view'); if (!cv) return;
  const g = cv.getContext('2d'), W = MESH.w, H = MESH.h, s = MESH.step, Z = MESH.z;
  let mean = 0, n = 0; for (const v of Z) if (v !== null) { mean += v; n++; } mean /= Math.max(n, 1);
  // Centred on the object's bounding box, which the view fits.
  let x0 = W, x1 = 0, y0 = H, y1 = 0;
  for (let y = 0; y < H; y++) for (let x = 0; x < W; x++) if (Z[y * W + x] !== null) {
    x0 = Math.min(x0, x); x1 = Math.max(x1, x); y0 = Math.min(y0, y); y1 = Math.max(y1, y); }
  const mx = (x0 + x1) / 2, my = (y0 + y1) / 2;
  const P = []; for (let y = 0; y < H; y++) for (let x = 0; x < W; x++) {
    const v = Z[y * W + x]; P.push(v === null ? null : [(x - mx) * s, -(y - my) * s, v - mean]); }
  const T = []; const at = (x, y) => P[y * W + x];
  for (let y = 0; y + 1 < H; y++) for (let x = 0; x + 1 < W; x++) {
    const a = y * W + x, b = a + 1, c = a + W, d = c + 1;
    if (P[a] && P[b] && P[c]) T.push([a, c, b]); if (P[b] && P[c] && P[d]) T.push([b, c, d]); }
  let yaw = -0.5, pitch = 0.6, zoom = 1;
  const span = Math.max(x1 - x0 + 1, y1 - y0 + 1, 1) * s * 1.2;
  function draw() {
    g.fillStyle = 'white'; g.fillRect(0, 0, cv.width, cv.height);
    const cy = Math.cos(yaw), sy = Math.sin(yaw), cp = Math.cos(pitch), sp = Math.sin(pitch);
    const V = P.map(p => { if (!p) return null;
      const x1 = cy * p[0] + sy * p[1], y1 = -sy * p[0] + cy * p[1];
      return [x1, cp * y1 + sp * p[2], -sp * y1 + cp * p[2]]; });
    const k = 0.85 * zoom * Math.min(cv.width, cv.height) / span;
    const L = [-0.4, 0.5, 0.77], tris = [];
    for (const t of T) { const a = V[t[0]], b = V[t[1]], c = V[t[2]];
      const u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]], v = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
      let nx = u[1] * v[2] - u[2] * v[1], ny = u[2] * v[0] - u[0] * v[2], nz = u[0] * v[1] - u[1] * v[0];
      const m = Math.hypot(nx, ny, nz) || 1; if (nz < 0) { nx = -nx; ny = -ny; nz = -nz; }
      const sh = 0.15 + 0.85 * Math.max(0, (nx * L[0] + ny * L[1] + nz * L[2]) / m);
      tris.push([a[2] + b[2] + c[2], a, b, c, sh]); }
    tris.sort((p, q) => p[0] - q[0]);
    const X = p => cv.width / 2 + k * p[0], Y = p => cv.height / 2 - k * p[1];
    for (const t of tris) { const c = Math.round(255 * t[4]);
      g.fillStyle = g.strokeStyle = 'rgb(' + c + ',' + c + ',' + c + ')';
      g.beginPath(); g.moveTo(X(t[1]), Y(t[1])); g.lineTo(X(t[2]), Y(t[2])); g.lineTo(X(t[3]), Y(t[3]));
      g.closePath(); g.fill(); g.stroke(); }
    cv.dataset.triangles = tris.length;
  }
  let drag = null;
  cv.addEventListener('mousedown', e => { drag = [e.clientX, e.clientY]; });
  window.addEventListener('mouseup', () => { drag = null; });
  window.addEventListener('mousemove', e => { if (!drag) return;
    yaw += (e.clientX - drag[0]) * 0.01; pitch += (e.clientY - drag[1]) * 0.01; drag = [e.clientX, e.clientY]; draw(); });
  cv.addEventListener('wheel', e => { e.preventDefault(); zoom *= Math.exp(-e.deltaY * 0.001); draw(); });
  draw();
})();
"#;
