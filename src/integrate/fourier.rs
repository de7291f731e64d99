//! Frankot–Chellappa integration ("A method for enforcing integrability in shape from shading
//! algorithms", PAMI 1988): the least-squares integrable field in the Fourier basis,
//! Z(ω) = (−i ω_u P(ω) − i ω_v Q(ω)) / (ω_u² + ω_v²), by FFT over the whole image.
//!
//! Assumes a periodic surface: the image's opposite edges are treated as neighbours, so depth is
//! distorted near the image border unless the surface is flat there; gradients outside the mask are
//! taken as zero (a flat background), like DCT Poisson.

use super::finish_depth;
use crate::grid::{Mask, ScalarMap};
use rayon::prelude::*;
use rustdct::rustfft::FftPlanner;
use rustdct::rustfft::num_complex::Complex;

/// Transposes a row-major `w`×`h` complex array.
fn transpose(a: &[Complex<f64>], w: usize, h: usize) -> Vec<Complex<f64>> {
    let mut t = vec![Complex::new(0.0, 0.0); w * h];
    for y in 0..h {
        for x in 0..w {
            t[x * h + y] = a[y * w + x];
        }
    }
    t
}

/// Integrates (p, q) on `domain` (pixels where both are finite) by Frankot–Chellappa.
pub fn integrate_fourier(p: &ScalarMap, q: &ScalarMap, domain: &Mask) -> ScalarMap {
    let (w, h) = (p.width(), p.height());
    let mut planner = FftPlanner::<f64>::new();
    let (fw, iw) = (planner.plan_fft_forward(w), planner.plan_fft_inverse(w));
    let (fh, ih) = (planner.plan_fft_forward(h), planner.plan_fft_inverse(h));
    let field = |f: &dyn Fn(usize) -> f64| -> Vec<Complex<f64>> {
        (0..w * h)
            .map(|i| Complex::new(if domain.data()[i] { f(i) } else { 0.0 }, 0.0))
            .collect()
    };
    // Derivatives along columns (u) and rows (v, downwards: ∂z/∂v = −q).
    let mut pu = field(&|i| f64::from(p.data()[i]));
    let mut qv = field(&|i| -f64::from(q.data()[i]));
    let fft2 = |data: &mut Vec<Complex<f64>>,
                rows: &dyn rustdct::rustfft::Fft<f64>,
                cols: &dyn rustdct::rustfft::Fft<f64>| {
        data.par_chunks_mut(w).for_each(|r| rows.process(r));
        let mut t = transpose(data, w, h);
        t.par_chunks_mut(h).for_each(|c| cols.process(c));
        *data = t; // column-major (h-long columns)
    };
    fft2(&mut pu, fw.as_ref(), fh.as_ref());
    fft2(&mut qv, fw.as_ref(), fh.as_ref());
    let omega = |k: usize, n: usize| {
        let k = if k <= n / 2 {
            k as f64
        } else {
            k as f64 - n as f64
        };
        2.0 * std::f64::consts::PI * k / n as f64
    };
    // Data are indexed [u frequency][v frequency].
    let mut z: Vec<Complex<f64>> = (0..w * h)
        .into_par_iter()
        .map(|i| {
            let (ku, kv) = (i / h, i % h);
            let (wu, wv) = (omega(ku, w), omega(kv, h));
            let d = wu * wu + wv * wv;
            if d == 0.0 {
                Complex::new(0.0, 0.0)
            } else {
                (Complex::new(0.0, -wu) * pu[i] + Complex::new(0.0, -wv) * qv[i]) / d
            }
        })
        .collect();
    z.par_chunks_mut(h).for_each(|c| ih.process(c));
    let mut back = transpose(&z, h, w);
    back.par_chunks_mut(w).for_each(|r| iw.process(r));
    let scale = 1.0 / (w * h) as f64;
    finish_depth(back.iter().map(|c| c.re * scale).collect(), domain)
}
