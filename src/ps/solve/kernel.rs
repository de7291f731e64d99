//! The block kernel: pixels solved a block at a time with their samples gathered into
//! contiguous scratch, Gram matrices cached by lit-light set, and the shadow-weighted
//! accumulation specialised at compile time for weighting and saturation flags.

use super::*;

/// Pixels per work block: the block's samples for all images should stay in the L2 cache.
pub(super) const BLOCK_PIXELS: usize = 1024;

/// The condition number and inverse of the last Gram matrix seen: neighbouring pixels usually
/// use the same lights (plain least squares: all pixels), so the eigenvalues and inverse are
/// computed once per distinct light subset rather than per pixel.
pub(super) struct GramCache {
    pub(super) key: [f32; 6],
    pub(super) condition: f64,
    pub(super) inverse: Option<Matrix3<f64>>,
}

impl GramCache {
    pub(super) fn new() -> Self {
        GramCache {
            key: [f32::NAN; 6],
            condition: f64::NAN,
            inverse: None,
        }
    }

    pub(super) fn get(
        &mut self,
        key: [f32; 6],
        gram: &Matrix3<f64>,
    ) -> (f64, Option<Matrix3<f64>>) {
        if key != self.key {
            self.key = key;
            self.condition = condition_from_gram(gram);
            self.inverse = gram.try_inverse();
        }
        (self.condition, self.inverse)
    }
}

/// A run of consecutive masked pixels `[start, start + len)` in row-major order, at
/// `[local, local + len)` in the stack's planes.
#[derive(Clone, Copy)]
pub(super) struct Span {
    pub(super) start: usize,
    pub(super) local: usize,
    pub(super) len: usize,
}

/// Splits the mask into blocks of at most [`BLOCK_PIXELS`] masked pixels made of row spans;
/// `window` (the stack's, covering the mask) gives their place in the planes.
pub(super) fn blocks(mask: &Mask, window: Window) -> Vec<Vec<Span>> {
    let (w, h) = (mask.width(), mask.height());
    let mut out = Vec::new();
    let mut current = Vec::new();
    let mut filled = 0;
    for y in 0..h {
        let row = &mask.data()[y * w..(y + 1) * w];
        let mut x = 0;
        while x < w {
            if !row[x] {
                x += 1;
                continue;
            }
            let mut end = x;
            while end < w && row[end] {
                end += 1;
            }
            let mut s = x;
            while s < end {
                let take = (end - s).min(BLOCK_PIXELS - filled);
                current.push(Span {
                    start: y * w + s,
                    local: (y - window.y0) * window.width() + (s - window.x0),
                    len: take,
                });
                filled += take;
                s += take;
                if filled == BLOCK_PIXELS {
                    out.push(std::mem::take(&mut current));
                    filled = 0;
                }
            }
            x = end;
        }
    }
    if !current.is_empty() {
        out.push(current);
    }
    out
}

/// Per-block accumulators in structure-of-arrays form (one entry per block pixel).
#[derive(Default)]
pub(super) struct Scratch {
    pub(super) threshold: Vec<f32>,
    /// Unweighted Gram matrix of used directions: xx, xy, xz, yy, yz, zz.
    pub(super) gram: [Vec<f32>; 6],
    /// Weighted normal matrix (same order); equals `gram` for plain least squares.
    pub(super) a: [Vec<f32>; 6],
    /// Right-hand side.
    pub(super) b: [Vec<f32>; 3],
    pub(super) count: Vec<u32>,
    pub(super) g: Vec<[f32; 3]>,
    pub(super) ss: Vec<f32>,
    /// Σ r²/σ² over used samples (the fit-test statistic).
    pub(super) chi2: Vec<f32>,
    /// Gathered samples of the block, [pixel][image], for the per-pixel estimators.
    pub(super) values: Vec<f32>,
    /// Saturation flags, laid out as `values`.
    pub(super) saturated: Vec<bool>,
    /// The brightest usable samples of the block's pixels (pass 1): `top[q·len + i]` is the
    /// (q+1)-th brightest of block pixel i so far, −∞ while it has fewer.
    pub(super) top: Vec<f32>,
    /// Usable (finite, unclipped) samples of each block pixel (pass 1).
    pub(super) usable: Vec<u32>,
    /// The shadow threshold's reference level of each block pixel, over f32 samples (pass 1).
    pub(super) reference: Vec<f32>,
}

impl Scratch {
    pub(super) fn reset(&mut self, len: usize) {
        for v in self
            .gram
            .iter_mut()
            .chain(self.a.iter_mut())
            .chain(self.b.iter_mut())
            .chain([&mut self.ss, &mut self.chi2, &mut self.threshold])
        {
            v.clear();
            v.resize(len, 0.0);
        }
        self.count.clear();
        self.count.resize(len, 0);
        self.g.clear();
        self.g.resize(len, [f32::NAN; 3]);
    }
}

impl Scratch {
    /// Gathered samples and saturation flags of block pixel `i` (of `k` images).
    pub(super) fn pixel(&self, i: usize, k: usize) -> (&[f32], &[bool]) {
        (
            &self.values[i * k..(i + 1) * k],
            &self.saturated[i * k..(i + 1) * k],
        )
    }
}

/// Output of one block, scattered into the solution grids afterwards.
pub(super) struct BlockOut {
    pub(super) spans: Vec<Span>,
    pub(super) pixels: Vec<PixelSolution>,
    /// The samples of the block's unsolved pixels, for [`crate::ps::fill`].
    pub(super) unsolved: Vec<PixelData>,
}

/// The usable samples of the pixels of `out` left without an estimate (for
/// [`crate::ps::fill`]); `gathered` says whether `s` already holds the block's samples.
#[allow(clippy::too_many_arguments)]
pub(super) fn unsolved_data(
    stack: &ImageStack,
    channel: usize,
    per: &PerImage,
    options: &SolveOptions,
    spans: &[Span],
    out: &[PixelSolution],
    gathered: bool,
    s: &mut Scratch,
) -> Vec<PixelData> {
    let wanted: Vec<usize> = (0..out.len())
        .filter(|&i| !out[i].status.has_normal())
        .collect();
    if !options.fill || wanted.is_empty() {
        return Vec::new();
    }
    if !gathered {
        gather_block(stack, channel, spans, s);
    }
    let pixels: Vec<usize> = spans
        .iter()
        .flat_map(|sp| sp.start..sp.start + sp.len)
        .collect();
    let k = stack.count();
    let reject = options.method != Method::LeastSquares;
    let mut f = fitter(&per.dirs64, &per.gains, options);
    wanted
        .into_iter()
        .map(|i| {
            let (v, sat) = s.pixel(i, k);
            let (a, b, samples) = f.usable_normal_equations(v, sat, reject);
            PixelData {
                pixel: pixels[i],
                a,
                b,
                samples,
            }
        })
        .collect()
}

/// Whether sample `pixel` of an image with saturation `bits` is clipped.
#[inline(always)]
pub(super) fn sat_bit(bits: &[u64], pixel: usize) -> bool {
    bits[pixel / 64] >> (pixel % 64) & 1 == 1
}

/// Accumulator slices of one span (all of the span's length).
pub(super) struct Acc<'a> {
    pub(super) gram: [&'a mut [f32]; 6],
    pub(super) a: [&'a mut [f32]; 6],
    pub(super) b: [&'a mut [f32]; 3],
    pub(super) count: &'a mut [u32],
}

/// Adds one image's samples `src` (pixels `start..start + src.len()`) with light `l` to the
/// normal equations of the span. `WEIGHTED`: weights v² (diag(I) rows); `SAT`: consult `bits`.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
pub(super) fn accumulate<const WEIGHTED: bool, const SAT: bool>(
    src: &[f32],
    gain: f32,
    thr: &[f32],
    bits: &[u64],
    start: usize,
    l: &[f32; 3],
    ll: &[f32; 6],
    acc: Acc,
) {
    let n = src.len();
    let Acc { gram, a, b, count } = acc;
    let [g0, g1, g2, g3, g4, g5] = gram;
    let [a0, a1, a2, a3, a4, a5] = a;
    let [b0, b1, b2] = b;
    let (thr, count) = (&thr[..n], &mut count[..n]);
    let (g0, g1, g2, g3, g4, g5) = (
        &mut g0[..n],
        &mut g1[..n],
        &mut g2[..n],
        &mut g3[..n],
        &mut g4[..n],
        &mut g5[..n],
    );
    let (a0, a1, a2, a3, a4, a5) = (
        &mut a0[..n],
        &mut a1[..n],
        &mut a2[..n],
        &mut a3[..n],
        &mut a4[..n],
        &mut a5[..n],
    );
    let (b0, b1, b2) = (&mut b0[..n], &mut b1[..n], &mut b2[..n]);
    for j in 0..n {
        let v = src[j] * gain;
        let ok = v > thr[j] && !(SAT && sat_bit(bits, start + j));
        let u = if ok { 1.0 } else { 0.0 };
        let vv = if ok { v } else { 0.0 };
        count[j] += u32::from(ok);
        g0[j] += u * ll[0];
        g1[j] += u * ll[1];
        g2[j] += u * ll[2];
        g3[j] += u * ll[3];
        g4[j] += u * ll[4];
        g5[j] += u * ll[5];
        let w = if WEIGHTED {
            let w = vv * vv;
            a0[j] += w * ll[0];
            a1[j] += w * ll[1];
            a2[j] += w * ll[2];
            a3[j] += w * ll[3];
            a4[j] += w * ll[4];
            a5[j] += w * ll[5];
            w
        } else {
            u
        };
        let wv = w * vv;
        b0[j] += wv * l[0];
        b1[j] += wv * l[1];
        b2[j] += wv * l[2];
    }
}

/// Adds squared residuals of one image's used samples to `ss`, and divided by the image's
/// noise variance (1/`inv_var`) to `chi2`.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
pub(super) fn residuals<const SAT: bool>(
    src: &[f32],
    gain: f32,
    inv_var: f32,
    thr: &[f32],
    bits: &[u64],
    start: usize,
    l: &[f32; 3],
    g: &[[f32; 3]],
    ss: &mut [f32],
    chi2: &mut [f32],
) {
    let n = src.len();
    let (thr, g, ss, chi2) = (&thr[..n], &g[..n], &mut ss[..n], &mut chi2[..n]);
    for j in 0..n {
        let v = src[j] * gain;
        let ok = v > thr[j] && !(SAT && sat_bit(bits, start + j));
        let e = v - (g[j][0] * l[0] + g[j][1] * l[1] + g[j][2] * l[2]);
        // Unsolved pixels have NaN g; their sum is discarded.
        let e2 = if ok { e * e } else { 0.0 };
        ss[j] += e2;
        chi2[j] += e2 * inv_var;
    }
}

/// The per-image data of a solve: light directions, gains and noise.
pub(super) struct PerImage {
    pub(super) dirs: Vec<[f32; 3]>,
    pub(super) dirs64: Vec<Vector3<f64>>,
    pub(super) gains: Vec<f32>,
    /// Noise of the samples before gains (NaN when unused).
    pub(super) sigma: Vec<f32>,
    /// 1/(σ_k·gain_k)².
    pub(super) inv_var: Vec<f32>,
}

#[allow(clippy::too_many_arguments)]
pub(super) fn solve_block(
    stack: &ImageStack,
    channel: usize,
    per: &PerImage,
    rule: Rule,
    max_condition: f64,
    spans: &[Span],
    s: &mut Scratch,
) -> Vec<PixelSolution> {
    let len: usize = spans.iter().map(|sp| sp.len).sum();
    s.reset(len);
    s.threshold.fill(f32::NEG_INFINITY);
    // Pass 1: per-pixel threshold from the pixel's reference level, the ⌈f·n⌉-th brightest
    // of its n usable samples ([`reference_rank`]; a clipped sample's value says nothing of
    // the pixel's brightness and is dropped anyway), from each pixel's list of its brightest
    // usable samples ([`brightest`]).
    s.reference.clear();
    if rule.reject {
        let depth = reference_rank(stack.count(), rule.highlight_fraction);
        s.top.clear();
        s.top.resize(depth * len, f32::NEG_INFINITY);
        s.usable.clear();
        s.usable.resize(len, 0);
        let images: Vec<ImageSamples> = (0..stack.count())
            .map(|k| ImageSamples {
                plane: stack.plane(k, channel),
                gain: per.gains[k],
                bits: if rule.reject_saturated {
                    stack.saturation_bits(k)
                } else {
                    None
                },
            })
            .collect();
        brightest(&images, spans, depth, &mut s.top, &mut s.usable);
        for i in 0..len {
            let usable = s.usable[i] as usize;
            let level = if usable == 0 {
                f32::NEG_INFINITY
            } else {
                s.top[(reference_rank(usable, rule.highlight_fraction) - 1) * len + i]
            };
            s.threshold[i] = rule.threshold(level);
            s.reference.push(level);
        }
    }
    // Pass 2: accumulate the normal equations image by image.
    for (k, l) in per.dirs.iter().enumerate() {
        let gain = per.gains[k];
        let plane = stack.plane(k, channel);
        let bits = if rule.reject_saturated {
            stack.saturation_bits(k)
        } else {
            None
        };
        let ll = [
            l[0] * l[0],
            l[0] * l[1],
            l[0] * l[2],
            l[1] * l[1],
            l[1] * l[2],
            l[2] * l[2],
        ];
        let mut off = 0;
        for sp in spans {
            let src = &plane[sp.local..sp.local + sp.len];
            let r = off..off + sp.len;
            let [g0, g1, g2, g3, g4, g5] = &mut s.gram;
            let [a0, a1, a2, a3, a4, a5] = &mut s.a;
            let [b0, b1, b2] = &mut s.b;
            let acc = Acc {
                gram: [
                    &mut g0[r.clone()],
                    &mut g1[r.clone()],
                    &mut g2[r.clone()],
                    &mut g3[r.clone()],
                    &mut g4[r.clone()],
                    &mut g5[r.clone()],
                ],
                a: [
                    &mut a0[r.clone()],
                    &mut a1[r.clone()],
                    &mut a2[r.clone()],
                    &mut a3[r.clone()],
                    &mut a4[r.clone()],
                    &mut a5[r.clone()],
                ],
                b: [&mut b0[r.clone()], &mut b1[r.clone()], &mut b2[r.clone()]],
                count: &mut s.count[r.clone()],
            };
            let thr = &s.threshold[r];
            match (rule.intensity_weight, bits) {
                (true, Some(bits)) => {
                    accumulate::<true, true>(src, gain, thr, bits, sp.start, l, &ll, acc)
                }
                (true, None) => {
                    accumulate::<true, false>(src, gain, thr, &[], sp.start, l, &ll, acc)
                }
                (false, Some(bits)) => {
                    accumulate::<false, true>(src, gain, thr, bits, sp.start, l, &ll, acc)
                }
                (false, None) => {
                    accumulate::<false, false>(src, gain, thr, &[], sp.start, l, &ll, acc)
                }
            }
            off += sp.len;
        }
    }
    // Solve each pixel.
    let mut out = Vec::with_capacity(len);
    let mut cache = GramCache::new();
    for i in 0..len {
        let key = [0, 1, 2, 3, 4, 5].map(|q| s.gram[q][i]);
        let sym = |e: [f32; 6]| {
            let e = e.map(f64::from);
            Matrix3::new(e[0], e[1], e[2], e[1], e[3], e[4], e[2], e[4], e[5])
        };
        let gram = sym(key);
        let b = Vector3::new(
            f64::from(s.b[0][i]),
            f64::from(s.b[1][i]),
            f64::from(s.b[2][i]),
        );
        let n = s.count[i] as usize;
        let (condition, inverse) = if n >= MIN_SAMPLES {
            cache.get(key, &gram)
        } else {
            (f64::INFINITY, None)
        };
        let (g, condition, status) = finish_pixel(n, condition, max_condition, || {
            if rule.intensity_weight {
                solve_spd(sym([0, 1, 2, 3, 4, 5].map(|q| s.a[q][i])), b)
            } else {
                inverse.map(|m| m * b)
            }
        });
        if status == PixelStatus::Solved {
            s.g[i] = [g.x as f32, g.y as f32, g.z as f32];
        }
        out.push(PixelSolution {
            g,
            residual: f64::NAN,
            samples: n,
            condition,
            status,
            robust: false,
        });
    }
    // Pass 3: residuals over the used samples.
    for (k, l) in per.dirs.iter().enumerate() {
        let (gain, inv_var) = (per.gains[k], per.inv_var[k]);
        let plane = stack.plane(k, channel);
        let bits = if rule.reject_saturated {
            stack.saturation_bits(k)
        } else {
            None
        };
        let mut off = 0;
        for sp in spans {
            let src = &plane[sp.local..sp.local + sp.len];
            let r = off..off + sp.len;
            let (thr, g) = (&s.threshold[r.clone()], &s.g[r.clone()]);
            let (ss, chi2) = (&mut s.ss[r.clone()], &mut s.chi2[r]);
            match bits {
                Some(bits) => {
                    residuals::<true>(src, gain, inv_var, thr, bits, sp.start, l, g, ss, chi2)
                }
                None => residuals::<false>(src, gain, inv_var, thr, &[], sp.start, l, g, ss, chi2),
            }
            off += sp.len;
        }
    }
    for (i, p) in out.iter_mut().enumerate() {
        if p.status == PixelStatus::Solved {
            p.residual = (f64::from(s.ss[i]) / p.samples as f64).sqrt();
        }
    }
    out
}

/// One image's samples as pass 1 reads them.
pub(super) struct ImageSamples<'a> {
    /// The image's plane of the solved channel.
    pub(super) plane: &'a [f32],
    /// Its intensity correction.
    pub(super) gain: f32,
    /// Its saturation bits when clipped samples are rejected.
    pub(super) bits: Option<&'a [u64]>,
}

/// For every pixel of `spans` (block pixel i), its `depth` brightest usable samples (times the
/// image's gain; usable: finite, and unclipped where `bits` are given), in descending order,
/// into `top[q·len + i]` for q < `depth` (−∞ past its usable samples), and their count into
/// `usable[i]`; `top` and `usable` come filled with −∞ and 0.
///
/// Image by image, each sample is inserted by compare-exchange down its pixel's list (the
/// entry keeps the larger, the smaller moves on), one list entry at a time across all the
/// pixels of a span: no branches, and the loops vectorise.
pub(super) fn brightest(
    images: &[ImageSamples],
    spans: &[Span],
    depth: usize,
    top: &mut [f32],
    usable: &mut [u32],
) {
    let len = usable.len();
    let mut x = Vec::new();
    for img in images {
        let mut off = 0;
        for sp in spans {
            let src = &img.plane[sp.local..sp.local + sp.len];
            // Unusable samples become −∞, which no list takes.
            x.clear();
            x.extend(src.iter().enumerate().map(|(j, &v)| {
                let v = v * img.gain;
                let ok = v.is_finite() && !img.bits.is_some_and(|b| sat_bit(b, sp.start + j));
                usable[off + j] += u32::from(ok);
                if ok { v } else { f32::NEG_INFINITY }
            }));
            for q in 0..depth {
                compare_exchange(&mut top[q * len + off..q * len + off + sp.len], &mut x);
            }
            off += sp.len;
        }
    }
}

/// One step down the lists of brightest samples: each pixel's entry keeps the larger of
/// itself and the pixel's candidate, and the smaller moves on as the candidate for the next
/// entry. Applied to every entry from the brightest, it inserts each candidate into its
/// pixel's descending list and drops the list's smallest value.
#[inline(always)]
pub(super) fn compare_exchange(list: &mut [f32], candidates: &mut [f32]) {
    let n = list.len();
    let candidates = &mut candidates[..n];
    for j in 0..n {
        let (t, c) = (list[j], candidates[j]);
        let (hi, lo) = if t > c { (t, c) } else { (c, t) };
        list[j] = hi;
        candidates[j] = lo;
    }
}

/// Pixels gathered together by [`gather_block`]: their rows of samples (all images) stay in
/// the L1 cache while every image's values for them are written.
const GATHER_TILE: usize = 32;

/// Copies the block's samples into `s.values`/`s.saturated` as [pixel][image].
pub(super) fn gather_block(stack: &ImageStack, channel: usize, spans: &[Span], s: &mut Scratch) {
    let k = stack.count();
    let len: usize = spans.iter().map(|sp| sp.len).sum();
    s.values.clear();
    s.values.resize(len * k, f32::NAN);
    s.saturated.clear();
    s.saturated.resize(len * k, false);
    let mut i = 0;
    for sp in spans {
        let mut x = 0;
        while x < sp.len {
            let n = GATHER_TILE.min(sp.len - x);
            let (local, start) = (sp.local + x, sp.start + x);
            let values = &mut s.values[i * k..(i + n) * k];
            let saturated = &mut s.saturated[i * k..(i + n) * k];
            for img in 0..k {
                let src = &stack.plane(img, channel)[local..local + n];
                for (j, &v) in src.iter().enumerate() {
                    values[j * k + img] = v;
                }
                if let Some(bits) = stack.saturation_bits(img) {
                    for j in 0..n {
                        saturated[j * k + img] = sat_bit(bits, start + j);
                    }
                }
            }
            i += n;
            x += n;
        }
    }
}

/// Solves one block with the method of `options`, and collects the samples of the pixels it
/// leaves unsolved ([`unsolved_data`]).
pub(super) fn solve_any_block(
    stack: &ImageStack,
    channel: usize,
    per: &PerImage,
    options: &SolveOptions,
    spans: &[Span],
    s: &mut Scratch,
) -> (Vec<PixelSolution>, Vec<PixelData>) {
    let (out, gathered) = fit_block(stack, channel, per, options, spans, s);
    let unsolved = unsolved_data(stack, channel, per, options, spans, &out, gathered, s);
    (out, unsolved)
}

/// Fits one block with the method of `options`; also says whether the block's samples were
/// gathered into `s`.
fn fit_block(
    stack: &ImageStack,
    channel: usize,
    per: &PerImage,
    options: &SolveOptions,
    spans: &[Span],
    s: &mut Scratch,
) -> (Vec<PixelSolution>, bool) {
    let k = stack.count();
    let method = options.method;
    if method.is_linear() || method == Method::Auto {
        let rule = Rule::new(method, options);
        let mut out = solve_block(stack, channel, per, rule, options.max_condition, spans, s);
        if method != Method::Auto {
            return (out, false);
        }
        let escalated: Vec<usize> = (0..out.len())
            .filter(|&i| misfit(&out[i], f64::from(s.chi2[i]), options.fit_test_z))
            .collect();
        if escalated.is_empty() {
            return (out, false);
        }
        gather_block(stack, channel, spans, s);
        let mut f = fitter(&per.dirs64, &per.gains, options);
        for i in escalated {
            let (v, sat) = s.pixel(i, k);
            // The kernel's level over f32 samples spares the fitter its selection.
            let reference = Reference::Rounded(s.reference[i]);
            out[i] = escalate(&mut f, v, sat, out[i], options, reference);
        }
        return (out, true);
    }
    gather_block(stack, channel, spans, s);
    let mut f = fitter(&per.dirs64, &per.gains, options);
    let len = s.values.len() / k.max(1);
    let out = (0..len)
        .map(|i| {
            let (v, sat) = s.pixel(i, k);
            fit_with(&mut f, v, sat, &per.sigma, options)
        })
        .collect();
    (out, true)
}
