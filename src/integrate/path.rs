//! Path integration: depth accumulated along paths of edge differences.
//!
//! Each connected part of the domain is covered by a spanning tree grown from a seed;
//! z(child) = z(parent) + the depth difference along the tree edge. The tree is grown in
//! order of edge quality (the quality-guided path following of phase unwrapping: the frontier
//! edge whose end pixels have the gentlest slopes is taken first), so steep, error-prone pixels —
//! grazing rims, creases — become leaves and their errors do not propagate to the rest.
//! Several trees from different seeds near the part's centre are averaged (each made zero-mean
//! over the part), which reduces the dependence on the path.
//!
//! Failure modes: noise and non-integrable errors accumulate along paths (the error grows like
//! √(path length) for white noise); a wrong gradient on a bridge between two regions shifts the
//! whole region behind it; depth discontinuities are integrated over as if they were slopes.

use super::{Censoring, edge_differences, finish_depth};
use crate::grid::{Mask, ScalarMap};
use std::cmp::Reverse;
use std::collections::{BinaryHeap, VecDeque};

/// Integrates (p, q) on `domain` by averaging `paths` (≥ 1) quality-guided spanning-tree
/// integrations per connected part. `domain` must contain only pixels where p and q are finite.
/// `censoring` marks samples that are only bounds ([`Censoring`]).
pub fn integrate_path(
    p: &ScalarMap,
    q: &ScalarMap,
    censoring: &Censoring,
    domain: &Mask,
    paths: usize,
) -> ScalarMap {
    let (w, h) = (p.width(), p.height());
    let (right, down) = edge_differences(p, q, domain, censoring);
    let m = domain.data();
    let paths = paths.max(1);
    // Steepness of each pixel: the larger of |p| and |q|.
    let steep: Vec<f32> = p
        .data()
        .iter()
        .zip(q.data())
        .map(|(a, b)| a.abs().max(b.abs()))
        .collect();
    let neighbours = |i: usize| -> [Option<(usize, f64)>; 4] {
        let (x, y) = (i % w, i / w);
        [
            (x + 1 < w && !right[i].is_nan()).then(|| (i + 1, right[i])),
            (y + 1 < h && !down[i].is_nan()).then(|| (i + w, down[i])),
            (x > 0 && !right[i - 1].is_nan()).then(|| (i - 1, -right[i - 1])),
            (y > 0 && !down[i - w].is_nan()).then(|| (i - w, -down[i - w])),
        ]
    };
    // Depth change from pixel `a` to its 4-neighbour `b`.
    let step = |a: usize, b: usize| -> f64 {
        if b == a + 1 {
            right[a]
        } else if a == b + 1 {
            -right[b]
        } else if b == a + w {
            down[a]
        } else {
            -down[b]
        }
    };
    let mut label = vec![false; w * h];
    let mut sum = vec![0f64; w * h];
    let mut z = vec![0f64; w * h];
    let mut seen = vec![0u32; w * h];
    let mut stamp = 0u32;
    let mut queue = VecDeque::new();
    let mut heap = BinaryHeap::new();
    let mut part = Vec::new();
    for start in 0..w * h {
        if !m[start] || label[start] {
            continue;
        }
        // Collect the connected part.
        part.clear();
        label[start] = true;
        queue.push_back(start);
        while let Some(i) = queue.pop_front() {
            part.push(i);
            for (j, _) in neighbours(i).into_iter().flatten() {
                if !label[j] {
                    label[j] = true;
                    queue.push_back(j);
                }
            }
        }
        // Seeds: the pixels nearest the centroid and nearest points on a circle around it.
        let n = part.len() as f64;
        let (cx, cy) = part.iter().fold((0.0, 0.0), |(a, b), &i| {
            (a + (i % w) as f64 / n, b + (i / w) as f64 / n)
        });
        let radius = 0.25 * (n / std::f64::consts::PI).sqrt();
        let nearest = |tx: f64, ty: f64| {
            part.iter()
                .copied()
                .min_by(|&a, &b| {
                    let d =
                        |i: usize| ((i % w) as f64 - tx).powi(2) + ((i / w) as f64 - ty).powi(2);
                    d(a).total_cmp(&d(b))
                })
                .unwrap_or(start)
        };
        for k in 0..paths {
            let seed = if k == 0 {
                nearest(cx, cy)
            } else {
                let a = 2.0 * std::f64::consts::PI * (k - 1) as f64 / (paths - 1) as f64;
                nearest(cx + radius * a.cos(), cy + radius * a.sin())
            };
            stamp += 1;
            z[seed] = 0.0;
            seen[seed] = stamp;
            let push = |heap: &mut BinaryHeap<_>, i: usize, seen: &[u32]| {
                for (j, _) in neighbours(i).into_iter().flatten() {
                    if seen[j] != stamp {
                        // Non-negative floats order like their bit patterns.
                        let cost = steep[i].max(steep[j]).to_bits();
                        heap.push(Reverse((cost, j, i)));
                    }
                }
            };
            push(&mut heap, seed, &seen);
            while let Some(Reverse((_, j, parent))) = heap.pop() {
                if seen[j] == stamp {
                    continue;
                }
                seen[j] = stamp;
                z[j] = z[parent] + step(parent, j);
                push(&mut heap, j, &seen);
            }
            let mean = part.iter().map(|&i| z[i]).sum::<f64>() / n;
            for &i in &part {
                sum[i] += (z[i] - mean) / paths as f64;
            }
        }
    }
    finish_depth(sum, domain)
}
