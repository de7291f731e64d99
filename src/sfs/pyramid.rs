//! Levels of half resolution, for the coarse-to-fine starts of the shape-from-shading solvers
//! (the perspective sweeps and refinement, Horn's method): a coarse pixel is a 2×2 block of fine
//! pixels that are all in the level, and a fine value is interpolated bilinearly from the coarse
//! pixels around it.

/// The bilinear stencil of the fine pixel at column `c`, row `r` on the half-resolution grid of
/// `cw × ch` pixels (at least 2 × 2) whose pixel (x, y) is the 2×2 block of fine pixels from
/// (2x, 2y): the fine pixel sits at ((c − 0.5)/2, (r − 0.5)/2) there, clamped to the grid. The
/// four coarse pixels (column, row) around it and their weights, which sum to 1.
pub(crate) fn bilinear_from_half(
    c: usize,
    r: usize,
    cw: usize,
    ch: usize,
) -> [(usize, usize, f64); 4] {
    let x = ((c as f64 - 0.5) / 2.0).clamp(0.0, (cw - 1) as f64);
    let y = ((r as f64 - 0.5) / 2.0).clamp(0.0, (ch - 1) as f64);
    let (x0, y0) = ((x as usize).min(cw - 2), (y as usize).min(ch - 2));
    let (fx, fy) = (x - x0 as f64, y - y0 as f64);
    [
        (x0, y0, (1.0 - fx) * (1.0 - fy)),
        (x0 + 1, y0, fx * (1.0 - fy)),
        (x0, y0 + 1, (1.0 - fx) * fy),
        (x0 + 1, y0 + 1, fx * fy),
    ]
}

/// The coarse unknown nearest the fine pixel (column `c`, row `r`) among the coarse pixels of the
/// 3 × 3 around its own block (`cindex`: the coarse unknown of each coarse pixel, `usize::MAX`
/// where there is none); `None` when there is none.
fn nearest_coarse(c: usize, r: usize, cw: usize, ch: usize, cindex: &[usize]) -> Option<usize> {
    let (x, y) = ((c as f64 - 0.5) / 2.0, (r as f64 - 0.5) / 2.0);
    let (bx, by) = ((c / 2).min(cw - 1), (r / 2).min(ch - 1));
    let mut best: Option<(f64, usize)> = None;
    for cy in by.saturating_sub(1)..=(by + 1).min(ch - 1) {
        for cx in bx.saturating_sub(1)..=(bx + 1).min(cw - 1) {
            let j = cindex[cy * cw + cx];
            if j == usize::MAX {
                continue;
            }
            let d = (cx as f64 - x).powi(2) + (cy as f64 - y).powi(2);
            if best.is_none_or(|(bd, _)| d < bd) {
                best = Some((d, j));
            }
        }
    }
    best.map(|(_, j)| j)
}

/// Transfer between a level and the one of half its resolution: each coarse pixel is a 2×2
/// block of fine pixels all in the level; a fine pixel's value is the bilinear interpolation of
/// the coarse pixels around it, over those that exist.
pub(crate) struct Transfer {
    /// The fine unknowns of each coarse pixel's block.
    pub blocks: Vec<[usize; 4]>,
    /// Coarse grid positions (row, column), row-major.
    pub grid: Vec<(usize, usize)>,
    /// Coarse width.
    pub w: usize,
    /// Coarse height.
    pub h: usize,
    /// Each fine unknown's coarse unknowns and weights, summing to 1 (missing coarse pixels
    /// have weight 0 and the others are scaled up).
    weights: Vec<[(usize, f64); 4]>,
}

impl Transfer {
    /// The transfer from the level `grid` (row, column; row-major) of a `w × h` image; `None`
    /// when the half-resolution level would have fewer than `min_pixels` pixels, or when
    /// a pixel of the level has no coarse pixel next to its own block (a part of the mask
    /// thinner than a block: its change could not be interpolated, and leaving it unmoved
    /// would tear the depth there). A pixel whose bilinear stencil has no coarse pixel with a
    /// weight (at the frame's edge, where the stencil is clamped to one side, or at a jagged
    /// contour) takes the value of the nearest coarse pixel next to its block.
    pub fn new(grid: &[(usize, usize)], w: usize, h: usize, min_pixels: usize) -> Option<Self> {
        let (cw, ch) = (w / 2, h / 2);
        if grid.len() < 4 * min_pixels || cw < 2 || ch < 2 {
            // The half-resolution level has at most a quarter of the pixels.
            return None;
        }
        let mut index = vec![usize::MAX; w * h];
        for (k, &(r, c)) in grid.iter().enumerate() {
            index[r * w + c] = k;
        }
        let (mut blocks, mut cgrid) = (Vec::new(), Vec::new());
        let mut cindex = vec![usize::MAX; cw * ch];
        for cr in 0..ch {
            for cc in 0..cw {
                let block = [(0, 0), (0, 1), (1, 0), (1, 1)]
                    .map(|(dr, dc)| index[(2 * cr + dr) * w + 2 * cc + dc]);
                if block.contains(&usize::MAX) {
                    continue;
                }
                cindex[cr * cw + cc] = cgrid.len();
                cgrid.push((cr, cc));
                blocks.push(block);
            }
        }
        if cgrid.len() < min_pixels {
            return None;
        }
        let mut weights = Vec::with_capacity(grid.len());
        for &(r, c) in grid {
            let mut ws = bilinear_from_half(c, r, cw, ch).map(|(x, y, wt)| {
                let j = cindex[y * cw + x];
                if j == usize::MAX { (0, 0.0) } else { (j, wt) }
            });
            let total: f64 = ws.iter().map(|p| p.1).sum();
            if total <= 1e-9 {
                // No coarse pixel of the stencil exists with a weight (at the frame's edge the
                // clamped stencil reaches only one side): the nearest coarse pixel next to the
                // pixel's own block, held constant as at the far edges of odd sizes.
                ws = [(0, 0.0); 4];
                ws[0] = (nearest_coarse(c, r, cw, ch, &cindex)?, 1.0);
            } else {
                ws.iter_mut().for_each(|p| p.1 /= total);
            }
            weights.push(ws);
        }
        Some(Transfer {
            blocks,
            grid: cgrid,
            w: cw,
            h: ch,
            weights,
        })
    }

    /// Block means of the fine values `v`.
    pub fn restrict(&self, v: &[f64]) -> Vec<f64> {
        self.blocks
            .iter()
            .map(|b| b.iter().map(|&k| v[k]).sum::<f64>() / 4.0)
            .collect()
    }

    /// The fine values interpolated from the coarse ones `c`.
    pub fn prolong(&self, c: &[f64]) -> Vec<f64> {
        self.weights
            .iter()
            .map(|ws| ws.iter().map(|&(j, wt)| wt * c[j]).sum())
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The minimum coarse level of these tests (the perspective refinement's).
    const MIN: usize = 3000;

    /// Block means of a linear function, interpolated back, are the function itself wherever
    /// a fine pixel has coarse pixels on both sides (all but the outer ring); a level whose
    /// half would be under the minimum has no transfer.
    #[test]
    fn transfer_is_exact_on_linear_values() {
        let (w, h) = (128, 96);
        let grid: Vec<(usize, usize)> = (0..h).flat_map(|r| (0..w).map(move |c| (r, c))).collect();
        let t = Transfer::new(&grid, w, h, MIN).unwrap();
        assert_eq!((t.w, t.h, t.grid.len()), (64, 48, 64 * 48));
        let linear = |r: usize, c: usize| 0.3 + 0.017 * r as f64 - 0.011 * c as f64;
        let v: Vec<f64> = grid.iter().map(|&(r, c)| linear(r, c)).collect();
        let back = t.prolong(&t.restrict(&v));
        let worst = grid
            .iter()
            .zip(&back)
            .filter(|((r, c), _)| (1..h - 1).contains(r) && (1..w - 1).contains(c))
            .map(|(&(r, c), b)| (b - linear(r, c)).abs())
            .fold(0.0, f64::max);
        assert!(worst < 1e-12, "{worst}");
        let small: Vec<(usize, usize)> = (0..100)
            .flat_map(|r| (0..100).map(move |c| (r, c)))
            .collect();
        assert!(Transfer::new(&small, 100, 100, MIN).is_none());
        // Odd sizes and a hole: every pixel still has coarse pixels around it.
        let (wo, ho) = (129, 97);
        let holed: Vec<(usize, usize)> = (0..ho)
            .flat_map(|r| (0..wo).map(move |c| (r, c)))
            .filter(|&(r, c)| !((40..50).contains(&r) && (60..75).contains(&c)))
            .collect();
        let t = Transfer::new(&holed, wo, ho, MIN).unwrap();
        assert!(t.weights.iter().all(|ws| {
            (ws.iter().map(|p| p.1).sum::<f64>() - 1.0).abs() < 1e-12
                && ws.iter().all(|p| p.1 >= 0.0)
        }));
        // A one-pixel line apart from the body (column 120, the body ending at column 99): no
        // block holds it and no coarse pixel is near, so there is no transfer.
        let mut spur = grid.clone();
        spur.retain(|&(_, c)| c < 100);
        spur.extend((0..h).map(|r| (r, 120)));
        spur.sort_unstable();
        assert!(Transfer::new(&spur, w, h, MIN).is_none());
        // A frame-filling level whose left column is jagged (every other pixel out): the
        // clamped stencil of (1, 0) reaches only coarse column 0, whose blocks are all broken
        // there; it takes the nearest coarse pixel, and the level still has a transfer.
        let jagged: Vec<(usize, usize)> = grid
            .iter()
            .copied()
            .filter(|&(r, c)| !(c == 0 && r % 2 == 0))
            .collect();
        let t = Transfer::new(&jagged, w, h, MIN).unwrap();
        let at = jagged.iter().position(|&p| p == (1, 0)).unwrap();
        assert_eq!(
            t.weights[at][0],
            (t.grid.iter().position(|&p| p == (0, 1)).unwrap(), 1.0)
        );
        assert!(t.weights.iter().all(|ws| {
            (ws.iter().map(|p| p.1).sum::<f64>() - 1.0).abs() < 1e-12
                && ws.iter().all(|p| p.1 >= 0.0)
        }));
        let v: Vec<f64> = jagged
            .iter()
            .map(|&(r, c)| 1.0 + 0.01 * (r + c) as f64)
            .collect();
        let back = t.prolong(&t.restrict(&v));
        let worst = v
            .iter()
            .zip(&back)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        assert!(worst < 0.03, "{worst}");
    }
}
