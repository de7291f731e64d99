//! Aggregation-based algebraic multigrid for the integration systems, used as the
//! preconditioner of conjugate gradients ([`super::sparse::pcg`]).
//!
//! Every system the masked integrators solve is a weighted graph Laplacian on the mask's pixels:
//! Σ over edges ω_ij (z_j − z_i − d_ij)², so A = Σ ω_ij (e_i − e_j)(e_i − e_j)ᵀ with ω_ij > 0
//! (uniform for masked least squares; the reweighted, perspective-scaled and cut weights of the
//! bilateral integrator, which span many orders of magnitude). The hierarchy follows the
//! aggregation multigrid of Notay ("An aggregation-based algebraic multigrid method", ETNA 37,
//! 2010; Napov & Notay, SIAM J. Sci. Comput. 34, 2012):
//! - **aggregates** by two passes of pairwise matching: each node is paired with the unpaired
//!   neighbour it is most strongly coupled to, when that coupling is at least
//!   [`STRONG`] of the node's strongest one, so aggregates hold up to four nodes and never join
//!   two sides of a weak (cut) edge — which is what lets the same hierarchy serve the bilateral
//!   integrator, whose weights across a depth jump are near zero;
//! - **piecewise-constant prolongation** P and the Galerkin coarse matrix PᵀAP, which for a graph
//!   Laplacian is again a graph Laplacian: the weight between two aggregates is the sum of the
//!   weights between their nodes;
//! - a **K-cycle** (Notay 2010): one forward Gauss–Seidel sweep before the coarse correction,
//!   one backward sweep after it, and the coarse correction itself up to two steps of flexible
//!   conjugate gradients on the next level, preconditioned by that level's cycle (a nonlinear
//!   preconditioner, hence the flexible outer conjugate gradients); the coarsest level (at most
//!   [`COARSEST`] nodes) is solved by dense Cholesky with one node per connected part pinned.
//!
//! Time and memory are linear in the pixels (each level has about a quarter of the previous
//! one's nodes). Measured iteration counts and times are in `docs/integration.md`.
//!
//! Fails where: coarsening stalls (a graph with very many tiny disconnected parts — each part is
//! at least one coarse node); the coarsest level is then smoothed instead of solved, and
//! conjugate gradients take more iterations, never a wrong answer.

use super::sparse::{NONE, Stencil, Unknowns};
use faer::linalg::solvers::{Llt, Solve};
use faer::{Mat, MatMut, Side};

pub(crate) mod blocks;
pub(crate) mod grid;

/// The members of each of `m` aggregates (`agg`: each node's aggregate) by a counting sort, in
/// node order: those of aggregate k are `members[first[k]..first[k + 1]]`. Returns (`first`,
/// `members`); the Galerkin products build their coarse rows one aggregate at a time from it.
pub(super) fn aggregate_members(agg: &[u32], m: usize) -> (Vec<usize>, Vec<u32>) {
    let mut first = vec![0usize; m + 1];
    for &a in agg {
        first[a as usize + 1] += 1;
    }
    for k in 0..m {
        first[k + 1] += first[k];
    }
    let mut fill = first.clone();
    let mut members = vec![0u32; agg.len()];
    for (i, &a) in agg.iter().enumerate() {
        members[fill[a as usize]] = i as u32;
        fill[a as usize] += 1;
    }
    (first, members)
}

/// A Galerkin matrix of a graph Laplacian in compressed rows, built one coarse row at a time:
/// the contributions to a column of the row being built are summed in the order they come, the
/// columns kept in the order first met, and each diagonal is minus the sum of its row's
/// contributions, in the same order (see [`Csr::galerkin`] for why it is not taken from the
/// members' diagonals).
pub(super) struct CoarseRows {
    diag: Vec<f64>,
    /// The diagonal of the row being built.
    row_diag: f64,
    start: Vec<usize>,
    col: Vec<u32>,
    val: Vec<f64>,
    /// Position of each coarse column in the row being built (`usize::MAX`: not in it).
    slot: Vec<usize>,
    /// Where the row being built starts in `col`.
    row_start: usize,
}

impl CoarseRows {
    /// Rows of a matrix of order `m`, with room for `capacity` entries.
    pub(super) fn new(m: usize, capacity: usize) -> Self {
        CoarseRows {
            diag: Vec::with_capacity(m),
            row_diag: 0.0,
            start: {
                let mut s = Vec::with_capacity(m + 1);
                s.push(0);
                s
            },
            col: Vec::with_capacity(capacity),
            val: Vec::with_capacity(capacity),
            slot: vec![usize::MAX; m],
            row_start: 0,
        }
    }

    /// Adds `v` (a coupling to another aggregate, −weight) to column `c` of the row being built.
    pub(super) fn add(&mut self, c: usize, v: f64) {
        self.row_diag -= v;
        if self.slot[c] == usize::MAX {
            self.slot[c] = self.col.len();
            self.col.push(c as u32);
            self.val.push(v);
        } else {
            self.val[self.slot[c]] += v;
        }
    }

    /// Closes the row being built; the next `add` starts the next row.
    pub(super) fn end_row(&mut self) {
        for &c in &self.col[self.row_start..] {
            self.slot[c as usize] = usize::MAX;
        }
        self.row_start = self.col.len();
        self.start.push(self.col.len());
        self.diag.push(std::mem::take(&mut self.row_diag));
    }

    /// The matrix.
    pub(super) fn finish(self) -> Csr {
        Csr::new(self.diag, self.start, self.col, self.val)
    }
}

/// A coupling is strong when its weight is at least this fraction of the node's strongest
/// coupling (Notay 2010 uses 0.25 for the same test).
pub(crate) const STRONG: f64 = 0.25;
/// Levels stop when a level has at most this many nodes; it is solved exactly.
pub(crate) const COARSEST: usize = 64;
/// Coarsening is considered stalled when a level keeps more than this fraction of its nodes.
const STALL: f64 = 0.8;
/// The K-cycle's second inner step is skipped when the first leaves at most this fraction of
/// the residual (Notay 2010).
pub(super) const KCYCLE_T: f64 = 0.25;
/// The K-cycle's second inner step is taken only on levels at least this many times larger
/// than the next (a second visit doubles the work below; with four-node aggregates the ratio is
/// near 4, and where coarsening slows down the cycle falls back to one step).
pub(super) const KCYCLE_MIN_RATIO: f64 = 2.5;
/// Symmetric Gauss–Seidel sweeps on a stalled coarsest level too large for a dense solve.
pub(super) const STALLED_SWEEPS: usize = 8;

/// A symmetric matrix in compressed rows: the diagonal, and the off-diagonal entries of each
/// row (columns and values; the values of a graph Laplacian are −ω ≤ 0).
pub(super) struct Csr {
    diag: Vec<f64>,
    /// 1/diag where the diagonal is positive, 0 elsewhere (a node without couplings).
    inv_diag: Vec<f64>,
    start: Vec<usize>,
    col: Vec<u32>,
    val: Vec<f64>,
}

impl Csr {
    pub(super) fn new(diag: Vec<f64>, start: Vec<usize>, col: Vec<u32>, val: Vec<f64>) -> Self {
        let inv_diag = diag
            .iter()
            .map(|&d| if d > 0.0 { 1.0 / d } else { 0.0 })
            .collect();
        Csr {
            diag,
            inv_diag,
            start,
            col,
            val,
        }
    }

    fn len(&self) -> usize {
        self.diag.len()
    }

    /// Σ_j a_ij x_j over the off-diagonal entries of row i.
    #[inline(always)]
    fn off_diagonal(&self, i: usize, x: &[f64]) -> f64 {
        let (s, e) = (self.start[i], self.start[i + 1]);
        let (col, val) = (&self.col[s..e], &self.val[s..e]);
        let mut sum = 0.0;
        for k in 0..col.len() {
            sum += val[k] * x[col[k] as usize];
        }
        sum
    }

    #[inline]
    fn row(&self, i: usize) -> impl Iterator<Item = (usize, f64)> + '_ {
        let (s, e) = (self.start[i], self.start[i + 1]);
        self.col[s..e]
            .iter()
            .zip(&self.val[s..e])
            .map(|(&c, &v)| (c as usize, v))
    }

    /// The rows of a [`Stencil`] on its unknowns (entries that are exactly zero are dropped).
    fn from_stencil(u: &Unknowns, a: &Stencil) -> Self {
        let n = u.len();
        let mut start = Vec::with_capacity(n + 1);
        let mut col = Vec::with_capacity(4 * n);
        let mut val = Vec::with_capacity(4 * n);
        start.push(0);
        for i in 0..n {
            let entries = [
                (
                    u.up[i],
                    if u.up[i] != NONE {
                        a.down[u.up[i] as usize]
                    } else {
                        0.0
                    },
                ),
                (
                    u.left[i],
                    if u.left[i] != NONE {
                        a.right[u.left[i] as usize]
                    } else {
                        0.0
                    },
                ),
                (u.right[i], a.right[i]),
                (u.down[i], a.down[i]),
            ];
            for (j, v) in entries {
                if j != NONE && v != 0.0 {
                    col.push(j);
                    val.push(v);
                }
            }
            start.push(col.len());
        }
        Csr::new(a.diag.clone(), start, col, val)
    }

    /// Pairwise matching: `agg[i]` is the pair of node i, numbered in order of first node.
    /// A node is paired with its unpaired neighbour of largest weight −a_ij, when that weight is
    /// at least [`STRONG`] of its largest; otherwise it stays alone.
    fn pairs(&self) -> (Vec<u32>, usize) {
        let n = self.len();
        let mut agg = vec![NONE; n];
        let mut count = 0u32;
        for i in 0..n {
            if agg[i] != NONE {
                continue;
            }
            let strongest = self.row(i).map(|(_, v)| -v).fold(0.0, f64::max);
            let mut best: Option<(usize, f64)> = None;
            for (j, v) in self.row(i) {
                let w = -v;
                if j != i
                    && agg[j] == NONE
                    && w > 0.0
                    && w >= STRONG * strongest
                    && best.is_none_or(|(_, b)| w > b)
                {
                    best = Some((j, w));
                }
            }
            agg[i] = count;
            if let Some((j, _)) = best {
                agg[j] = count;
            }
            count += 1;
        }
        (agg, count as usize)
    }

    /// The Galerkin matrix PᵀAP for the piecewise-constant prolongation of `agg` (`m` aggregates).
    /// A is a graph Laplacian (every row sums to 0), and so is PᵀAP: each diagonal is the sum of
    /// the aggregate's couplings to the others, summed from them rather than as the members'
    /// diagonals less their inner edges. The two are equal in exact arithmetic, but the
    /// difference leaves a rounding residue of either sign where the aggregate is nearly or
    /// wholly cut off from the rest (a whole connected part, as each one-pixel column of a comb
    /// becomes a few levels down; a region joined to its part by cut edges only): the smoothing
    /// divided by that residue and the coarsest level pinned at it, the part's correction became
    /// a constant far larger than the residual, and the conjugate gradients stalled or broke
    /// down. Summed from the couplings, a wholly cut-off aggregate's diagonal is exactly 0
    /// (inactive in the smoothing, pinned on the coarsest level) and a nearly cut-off one's is
    /// its few weak couplings, as it should be.
    fn galerkin(&self, agg: &[u32], m: usize) -> Csr {
        let (first, members) = aggregate_members(agg, m);
        let mut rows = CoarseRows::new(m, self.col.len() / 2);
        for big in 0..m {
            for &i in &members[first[big]..first[big + 1]] {
                for (j, v) in self.row(i as usize) {
                    let c = agg[j] as usize;
                    if c != big {
                        rows.add(c, v);
                    }
                }
            }
            rows.end_row();
        }
        rows.finish()
    }

    /// One Gauss–Seidel sweep on A x = b, forward or backward.
    fn sweep(&self, b: &[f64], x: &mut [f64], forward: bool) {
        let n = self.len();
        let mut step = |i: usize| {
            x[i] = (b[i] - self.off_diagonal(i, x)) * self.inv_diag[i];
        };
        if forward {
            (0..n).for_each(&mut step);
        } else {
            (0..n).rev().for_each(&mut step);
        }
    }

    /// y = A x.
    fn multiply(&self, x: &[f64], y: &mut [f64]) {
        for (i, y) in y.iter_mut().enumerate() {
            *y = self.diag[i] * x[i] + self.off_diagonal(i, x);
        }
    }

    /// The residual b − A x summed over each aggregate of `agg`, into `rc` (one entry per
    /// aggregate), without storing it.
    fn restricted_residual(&self, b: &[f64], x: &[f64], agg: &[u32], rc: &mut [f64]) {
        rc.iter_mut().for_each(|v| *v = 0.0);
        for (i, &c) in agg.iter().enumerate() {
            rc[c as usize] += b[i] - self.diag[i] * x[i] - self.off_diagonal(i, x);
        }
    }

    /// Connected parts (through nonzero couplings): a label per node.
    fn parts(&self) -> Vec<u32> {
        let n = self.len();
        let mut part = vec![NONE; n];
        let mut stack = Vec::new();
        let mut count = 0;
        for s in 0..n {
            if part[s] != NONE {
                continue;
            }
            part[s] = count;
            stack.push(s);
            while let Some(i) = stack.pop() {
                for (j, _) in self.row(i) {
                    if part[j] == NONE {
                        part[j] = count;
                        stack.push(j);
                    }
                }
            }
            count += 1;
        }
        part
    }
}

/// The solve on the coarsest level.
pub(super) enum Coarsest {
    /// Dense Cholesky factor of the matrix with one node per connected part pinned.
    Dense(Llt<f64>),
    /// Coarsening stalled above a size worth factorising: symmetric Gauss–Seidel sweeps.
    Sweeps,
}

/// A multigrid hierarchy for one matrix (see the module documentation).
pub(crate) struct Multigrid {
    /// Matrices, finest first.
    levels: Vec<Csr>,
    /// `aggregates[l][i]`: the node of level l + 1 that node i of level l belongs to.
    aggregates: Vec<Vec<u32>>,
    coarsest: Coarsest,
}

impl Multigrid {
    /// The hierarchy of the stencil `a` on the unknowns `u`.
    pub fn new(u: &Unknowns, a: &Stencil) -> Self {
        Self::from_finest(Csr::from_stencil(u, a))
    }

    /// The hierarchy whose finest level is `finest`.
    fn from_finest(finest: Csr) -> Self {
        let mut levels = vec![finest];
        let mut aggregates = Vec::new();
        loop {
            let fine = levels.last().expect("at least the finest level");
            let n = fine.len();
            if n <= COARSEST {
                break;
            }
            // Two passes of pairwise matching: aggregates of up to four nodes.
            let (first, m1) = fine.pairs();
            let middle = fine.galerkin(&first, m1);
            let (second, m2) = middle.pairs();
            if m2 as f64 > STALL * n as f64 {
                break;
            }
            let agg: Vec<u32> = first.iter().map(|&a| second[a as usize]).collect();
            levels.push(middle.galerkin(&second, m2));
            aggregates.push(agg);
        }
        let coarsest = dense_factor(levels.last().expect("at least the finest level"));
        Multigrid {
            levels,
            aggregates,
            coarsest,
        }
    }

    /// Nodes of each level, finest first.
    #[cfg(test)]
    pub fn sizes(&self) -> Vec<usize> {
        self.levels.iter().map(Csr::len).collect()
    }

    /// The scratch vectors of the cycle, allocated once and kept between cycles: for each
    /// level below the finest, its restricted residual, its correction and the K-cycle's five
    /// vectors.
    pub fn work(&self) -> Vec<Work<f64>> {
        self.levels[1..]
            .iter()
            .map(|level| Work::zeros(level.len()))
            .collect()
    }

    /// z = M⁻¹ r: one symmetric cycle from zero, with the scratch of [`Self::work`].
    pub fn apply(&self, r: &[f64], z: &mut [f64], work: &mut [Work<f64>]) {
        self.cycle(0, r, z, work);
    }

    /// The coarse correction of Notay's K-cycle on `level` (above the coarsest): up to two
    /// steps of flexible conjugate gradients on A x = b preconditioned by the level's cycle
    /// (from zero), the second only where the level is at least [`KCYCLE_MIN_RATIO`] times
    /// the next and the first step leaves more than [`KCYCLE_T`] of the residual; with `k` as
    /// its vectors (c₁, v₁ = A c₁, r₂, c₂, v₂ = A c₂) and `deeper` as the scratch of the levels
    /// below. On the coarsest level, its solve.
    fn krylov(
        &self,
        level: usize,
        b: &[f64],
        x: &mut [f64],
        k: &mut KVectors<f64>,
        deeper: &mut [Work<f64>],
    ) {
        if level + 1 == self.levels.len() {
            self.cycle(level, b, x, deeper);
            return;
        }
        let a = &self.levels[level];
        let dot = |p: &[f64], q: &[f64]| p.iter().zip(q).map(|(a, b)| a * b).sum::<f64>();
        // The second inner step doubles the visits of every coarser level: affordable only
        // where coarsening is fast enough for the work to stay linear.
        let second = a.len() as f64 / self.levels[level + 1].len() as f64 >= KCYCLE_MIN_RATIO;
        let KVectors { c1, v1, r2, c2, v2 } = k;
        self.cycle(level, b, c1, deeper);
        a.multiply(c1, v1);
        let rho1 = dot(c1, v1);
        let alpha1 = dot(c1, b);
        if rho1.is_nan() || rho1 <= 0.0 {
            x.copy_from_slice(c1);
            return;
        }
        let s1 = alpha1 / rho1;
        let first_only = |x: &mut [f64], c1: &[f64]| {
            for (x, &c) in x.iter_mut().zip(c1) {
                *x = s1 * c;
            }
        };
        for ((r, &b), &v) in r2.iter_mut().zip(b).zip(v1.iter()) {
            *r = b - s1 * v;
        }
        if !second || dot(r2, r2) <= KCYCLE_T * KCYCLE_T * dot(b, b) {
            first_only(x, c1);
            return;
        }
        self.cycle(level, r2, c2, deeper);
        a.multiply(c2, v2);
        let gamma = dot(c2, v1);
        let beta = dot(c2, v2);
        let alpha2 = dot(c2, r2);
        let Some((k1, k2)) = second_step(alpha1, rho1, gamma, beta, alpha2) else {
            first_only(x, c1);
            return;
        };
        for ((x, &c1), &c2) in x.iter_mut().zip(c1.iter()).zip(c2.iter()) {
            *x = k1 * c1 + k2 * c2;
        }
    }

    /// One cycle on `level` from x = 0; `work` holds the scratch of the levels below it.
    fn cycle(&self, level: usize, b: &[f64], x: &mut [f64], work: &mut [Work<f64>]) {
        let a = &self.levels[level];
        x.iter_mut().for_each(|v| *v = 0.0);
        if level + 1 == self.levels.len() {
            match &self.coarsest {
                Coarsest::Dense(llt) => {
                    x.copy_from_slice(b);
                    llt.solve_in_place(MatMut::from_column_major_slice_mut(x, b.len(), 1));
                }
                Coarsest::Sweeps => {
                    for _ in 0..STALLED_SWEEPS {
                        a.sweep(b, x, true);
                        a.sweep(b, x, false);
                    }
                }
            }
            return;
        }
        let Some((next, deeper)) = work.split_first_mut() else {
            return;
        };
        a.sweep(b, x, true);
        a.restricted_residual(b, x, &self.aggregates[level], &mut next.rc);
        let Work { rc, xc, k } = next;
        self.krylov(level + 1, rc, xc, k, deeper);
        for (x, &c) in x.iter_mut().zip(&self.aggregates[level]) {
            *x += xc[c as usize];
        }
        a.sweep(b, x, false);
    }
}

/// The K-cycle's combination x = k₁c₁ + k₂c₂ after its second step, from α₁ = c₁ᵀb,
/// ρ₁ = c₁ᵀAc₁, γ = c₂ᵀAc₁, β = c₂ᵀAc₂ and α₂ = c₂ᵀr₂ (the minimiser of the energy over the two
/// corrections, Notay 2010), for both hierarchies; `None` where the second correction adds no
/// positive curvature (ρ₂ = β − γ²/ρ₁ ≤ 0 or not a number), so that only the first is kept.
pub(super) fn second_step(
    alpha1: f64,
    rho1: f64,
    gamma: f64,
    beta: f64,
    alpha2: f64,
) -> Option<(f64, f64)> {
    let rho2 = beta - gamma * gamma / rho1;
    if rho2.is_nan() || rho2 <= 0.0 {
        return None;
    }
    Some((
        alpha1 / rho1 - gamma * alpha2 / (rho1 * rho2),
        alpha2 / rho2,
    ))
}

/// The scratch of one coarse level in a cycle of either hierarchy, kept between cycles: the
/// residual restricted to it and the correction solved on it (by the finer level's cycle), and
/// the K-cycle's vectors on it.
pub(crate) struct Work<T> {
    rc: Vec<T>,
    xc: Vec<T>,
    k: KVectors<T>,
}

/// The K-cycle's vectors on one level: two cycles' corrections, their products with A, and the
/// residual after the first.
pub(crate) struct KVectors<T> {
    c1: Vec<T>,
    v1: Vec<T>,
    r2: Vec<T>,
    c2: Vec<T>,
    v2: Vec<T>,
}

impl<T: Copy + Default> Work<T> {
    /// Zeros for a level of `n` nodes.
    fn zeros(n: usize) -> Self {
        let z = || vec![T::default(); n];
        Work {
            rc: z(),
            xc: z(),
            k: KVectors {
                c1: z(),
                v1: z(),
                r2: z(),
                c2: z(),
                v2: z(),
            },
        }
    }

    /// The same as [`Self::zeros`] in the storage already held: every vector resized to `n`
    /// and set to zero (no fresh pages for the kernel to fault in and clear).
    fn reset(&mut self, n: usize) {
        let Work { rc, xc, k } = self;
        let KVectors { c1, v1, r2, c2, v2 } = k;
        for v in [rc, xc, c1, v1, r2, c2, v2] {
            v.clear();
            v.resize(n, T::default());
        }
    }
}

/// Largest coarsest level factorised densely (a stalled hierarchy may end above [`COARSEST`]).
const DENSE_MAX: usize = 2048;

/// The dense Cholesky factor of `a` with one node per connected part pinned (its diagonal
/// doubled), or sweeps when `a` is too large or the factorisation fails.
pub(super) fn dense_factor(a: &Csr) -> Coarsest {
    let n = a.len();
    if n > DENSE_MAX {
        return Coarsest::Sweeps;
    }
    let mut m = Mat::<f64>::zeros(n, n);
    for i in 0..n {
        m[(i, i)] = a.diag[i];
        for (j, v) in a.row(i) {
            m[(i, j)] = v;
        }
    }
    // One pinned node per connected part: the first of each.
    let parts = a.parts();
    let mut part_seen = vec![false; n];
    let pinned: Vec<bool> = parts
        .iter()
        .map(|&p| !std::mem::replace(&mut part_seen[p as usize], true))
        .collect();
    let mean_diag = a.diag.iter().sum::<f64>() / n.max(1) as f64;
    for (i, &pin) in pinned.iter().enumerate() {
        if pin {
            m[(i, i)] += if a.diag[i] > 0.0 {
                a.diag[i]
            } else {
                mean_diag.max(1.0)
            };
        }
    }
    match m.llt(Side::Lower) {
        Ok(c) => Coarsest::Dense(c),
        Err(_) => Coarsest::Sweeps,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::Grid;
    use crate::integrate::sparse::{Convergence, Preconditioner, solve_known};

    /// A disk with a hole, and a separate bar: two parts.
    fn mask(n: usize) -> crate::grid::Mask {
        let c = n as f64 * 0.35;
        Grid::from_fn(n, n, |x, y| {
            let (dx, dy) = (x as f64 - c, y as f64 - c);
            let r2 = dx * dx + dy * dy;
            (r2 < (0.3 * n as f64).powi(2) && r2 > 4.0) || (x > 3 * n / 4 && y > n / 8 && y < n - 4)
        })
    }

    /// The graph Laplacian of `u` with weight `weight(unknown, along_rows)` on each edge.
    fn laplacian(u: &Unknowns, weight: impl Fn(usize, usize, bool) -> f64) -> Stencil {
        let mut a = Stencil::zeros(u.len());
        let mut rhs = vec![0.0; u.len()];
        for i in 0..u.len() {
            for (nb, along) in [(u.right[i], true), (u.down[i], false)] {
                if nb != NONE {
                    a.add_edge(
                        &mut rhs,
                        (i, nb as usize),
                        along,
                        weight(i, nb as usize, along),
                        0.0,
                    );
                }
            }
        }
        a
    }

    /// Solves A x = A·truth by multigrid-preconditioned CG to 1e-10; returns the iterations and
    /// the largest error against truth (both zero-mean per part).
    fn solve(u: &Unknowns, a: &Stencil) -> (usize, f64) {
        let m = Multigrid::new(u, a);
        let (its, _, err) = solve_known(u, a, &Preconditioner::Multigrid(&m), 500);
        (its, err)
    }

    #[test]
    fn coarsening_quarters_each_level() {
        let u = Unknowns::new(&mask(256));
        let m = Multigrid::new(&u, &laplacian(&u, |_, _, _| 1.0));
        let sizes = m.sizes();
        assert!(sizes.len() >= 4, "{sizes:?}");
        for pair in sizes.windows(2).take(3) {
            assert!(pair[0] as f64 >= 3.0 * pair[1] as f64, "{sizes:?}");
        }
        assert!(*sizes.last().unwrap() <= COARSEST, "{sizes:?}");
    }

    /// Uniform weights: exact to 1e-7 and the iteration count does not grow with the size (a
    /// Jacobi preconditioner's grows linearly with the side).
    #[test]
    fn iterations_do_not_grow_with_the_grid() {
        let mut counts = Vec::new();
        for n in [64, 256] {
            let u = Unknowns::new(&mask(n));
            assert_eq!(u.parts, 2);
            let (its, err) = solve(&u, &laplacian(&u, |_, _, _| 1.0));
            assert!(err < 1e-7, "n {n}: error {err}");
            counts.push(its);
        }
        assert!(counts[1] <= counts[0] + 3 && counts[1] <= 25, "{counts:?}");
    }

    /// Weights over three orders of magnitude and a line of near-zero (cut) weights, as in the
    /// bilateral integrator: still exact, in a few tens of iterations.
    #[test]
    fn cut_and_uneven_weights_converge() {
        let n = 128;
        let u = Unknowns::new(&mask(n));
        let a = laplacian(&u, |i, _, along| {
            let pix = u.pixel[i] as usize;
            let (x, y) = (pix % n, pix / n);
            if along && x == n / 3 && y % 9 != 0 {
                1e-6
            } else {
                10f64.powi((((x * 31 + y * 17) % 4) as i32) - 3)
            }
        });
        let (its, err) = solve(&u, &a);
        assert!(err < 1e-5, "error {err}");
        assert!(its <= 60, "{its} iterations");
    }

    /// A comb of 48 one-pixel-wide columns (every other column of 96 × 160, as many parts),
    /// weights over three orders of magnitude: a few levels down each column is one aggregate
    /// with no coupling left. Its diagonal was the rounding residue of its members' diagonals
    /// less their inner edges (either sign), which the smoothing divided by and the coarsest
    /// level pinned at: each part's correction became a huge constant, and the conjugate
    /// gradients did not converge in 500 iterations. Now summed from the couplings: exactly 0.
    #[test]
    fn many_thin_parts_converge() {
        let (w, h) = (96, 160);
        let u = Unknowns::new(&Grid::from_fn(w, h, |x, _| x % 2 == 0));
        assert_eq!(u.parts, w / 2);
        let a = laplacian(&u, |i, _, _| {
            let pix = u.pixel[i] as usize;
            10f64.powi((((pix * 7919) % 4) as i32) - 3)
        });
        let m = Multigrid::new(&u, &a);
        let (its, convergence, err) = solve_known(&u, &a, &Preconditioner::Multigrid(&m), 500);
        assert_eq!(convergence, Convergence::Residual, "after {its} iterations");
        assert!(err < 1e-6, "error {err}");
    }
}
