//! Writes a large photometric-stereo stack to disk, row by row, without holding it: the input
//! of the out-of-core measurements (`photostereo --max-memory`, see the README).
//!
//! The scene is a sphere of radius 0.45·min(W, H) in front of a tilted plane, Lambertian
//! (albedo 0.8 on the sphere, 0.5 on the plane), under `COUNT` lights spread over the upper
//! hemisphere (Fibonacci, elevation ≥ 30°), with attached shadows and Gaussian noise σ = 0.002,
//! stored as 16-bit grey PNGs (`img_000.png` …), with `lights.json` and `mask.png` (the
//! sphere) beside them.
//!
//! Run: `cargo run --release --example large_stack -- OUT_DIR [WIDTH HEIGHT COUNT]`
//! (default 4000 3000 96: 2.3 GB of samples, 4.6 GB as f32 in memory).

use photostereo::capture::lights::Lights;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use rayon::prelude::*;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

/// Albedo of the sphere and of the plane behind it.
const SPHERE_ALBEDO: f64 = 0.8;
const PLANE_ALBEDO: f64 = 0.5;
/// Noise standard deviation of the stored values.
const NOISE: f64 = 0.002;

fn normal_at(x: usize, y: usize, w: usize, h: usize) -> ([f64; 3], bool) {
    let (cx, cy) = (w as f64 / 2.0, h as f64 / 2.0);
    let r = 0.45 * w.min(h) as f64;
    let (dx, dy) = (x as f64 + 0.5 - cx, cy - (y as f64 + 0.5));
    let d2 = dx * dx + dy * dy;
    if d2 < r * r {
        let nz = (r * r - d2).sqrt();
        ([dx / r, dy / r, nz / r], true)
    } else {
        // The plane z = 0.2·x + 0.1·y (slopes), normal (−0.2, −0.1, 1) normalised.
        let n = (0.04f64 + 0.01 + 1.0).sqrt();
        ([-0.2 / n, -0.1 / n, 1.0 / n], false)
    }
}

fn write_image(path: &Path, w: usize, h: usize, l: [f64; 3], seed: u64) -> std::io::Result<()> {
    let file = std::fs::File::create(path)?;
    let mut enc = png::Encoder::new(BufWriter::new(file), w as u32, h as u32);
    enc.set_color(png::ColorType::Grayscale);
    enc.set_depth(png::BitDepth::Sixteen);
    enc.set_compression(png::Compression::Fast);
    let mut writer = enc.write_header().map_err(std::io::Error::other)?;
    let mut stream = writer.stream_writer().map_err(std::io::Error::other)?;
    let mut rng = rand::rngs::ChaCha8Rng::seed_from_u64(seed);
    let noise = Normal::new(0.0, NOISE).map_err(std::io::Error::other)?;
    let mut row = vec![0u8; 2 * w];
    for y in 0..h {
        for x in 0..w {
            let (n, sphere) = normal_at(x, y, w, h);
            let rho = if sphere { SPHERE_ALBEDO } else { PLANE_ALBEDO };
            let shade = (n[0] * l[0] + n[1] * l[1] + n[2] * l[2]).max(0.0);
            let v = (rho * shade + noise.sample(&mut rng)).clamp(0.0, 1.0);
            let code = (v * 65535.0).round() as u16;
            row[2 * x..2 * x + 2].copy_from_slice(&code.to_be_bytes());
        }
        std::io::Write::write_all(&mut stream, &row)?;
    }
    stream.finish().map_err(std::io::Error::other)?;
    Ok(())
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let out = PathBuf::from(
        args.first()
            .ok_or("usage: large_stack OUT_DIR [W H COUNT]")?,
    );
    let num = |i: usize, d: usize| -> Result<usize, Box<dyn std::error::Error>> {
        Ok(args.get(i).map(|s| s.parse()).transpose()?.unwrap_or(d))
    };
    let (w, h, count) = (num(1, 4000)?, num(2, 3000)?, num(3, 96)?);
    std::fs::create_dir_all(&out)?;
    let names: Vec<String> = (0..count).map(|k| format!("img_{k:03}.png")).collect();
    let lights = Lights::fibonacci(count, 30.0)?.with_files(&names)?;
    std::fs::write(out.join("lights.json"), lights.to_json())?;
    let mut mask = vec![0u8; w * h];
    for y in 0..h {
        for x in 0..w {
            if normal_at(x, y, w, h).1 {
                mask[y * w + x] = 255;
            }
        }
    }
    image::save_buffer(
        out.join("mask.png"),
        &mask,
        w as u32,
        h as u32,
        image::ExtendedColorType::L8,
    )?;
    let dirs = lights.directions();
    names.par_iter().enumerate().try_for_each(|(k, name)| {
        let d = dirs[k];
        write_image(&out.join(name), w, h, [d.x, d.y, d.z], k as u64)
    })?;
    eprintln!("wrote {count} images of {w}x{h} to {}", out.display());
    Ok(())
}
