//! Exact minimisation of a binary Potts energy on a graph of pixels:
//!
//! E(x) = Σ_i [x_i = 0]·δ_i⁺ + [x_i = 1]·δ_i⁻ + λ Σ_{(i,j)} [x_i ≠ x_j],
//!
//! δ_i = D_i(0) − D_i(1) the unary preference of node i for label 1 (δ⁺ = max(δ, 0),
//! δ⁻ = max(−δ, 0)), with ±∞ for a label fixed by the data. Such an energy is submodular and
//! its minimum is a minimum s–t cut (Greig, Porteous & Seheult 1989; Kolmogorov & Zabih 2004,
//! "What energy functions can be minimized via graph cuts?", TPAMI 26(2)): an arc s → i of
//! capacity δ_i⁻, i → t of δ_i⁺, and i ↔ j of λ; the nodes left on the source side of the cut
//! take label 0. Label 0 (shadow) is the minority in photometric stereo, so the source's
//! nodes are few and every breadth-first search of the flow stops at the sink's level, near
//! them: a phase costs what the shadow candidates' neighbourhood holds, not the component.
//!
//! Two steps keep the cut small:
//! 1. **Persistency.** A node with |δ_i| ≥ λ·deg(i) has the label its unary prefers in every
//!    minimum (flipping it alone cannot lower E), so it is fixed without a flow; a fixed
//!    neighbour turns the pair term into a unary (±λ) of the other node, which may fix that
//!    one in turn. Most samples of a capture are decided here.
//! 2. **Components.** What remains free falls into connected components, each a small
//!    independent max-flow problem, solved by Dinic's blocking-flow algorithm (Dinitz 1970),
//!    with an iterative depth-first search (no recursion, whatever a component's size).
//!
//! Ties (a node indifferent between its labels) go to label 1: the source side of the cut is
//! the set of nodes reached from s in the residual graph, the smallest minimum cut.

/// Capacities at or below this are treated as saturated.
const EPS: f64 = 1e-12;

/// A graph of `n` nodes with undirected unit-weight edges (the 4-neighbour pairs): what the
/// labelling of every image shares.
pub(crate) struct PairGraph {
    /// Node i's neighbours are `adj[start[i]..start[i + 1]]`.
    start: Vec<u32>,
    adj: Vec<u32>,
}

impl PairGraph {
    /// The graph of `n` nodes with the undirected `edges` (each pair once).
    pub(crate) fn new(n: usize, edges: &[(u32, u32)]) -> Self {
        let mut degree = vec![0u32; n + 1];
        for &(a, b) in edges {
            degree[a as usize] += 1;
            degree[b as usize] += 1;
        }
        let mut start = vec![0u32; n + 1];
        for i in 0..n {
            start[i + 1] = start[i] + degree[i];
        }
        let mut fill = start.clone();
        let mut adj = vec![0u32; start[n] as usize];
        for &(a, b) in edges {
            adj[fill[a as usize] as usize] = b;
            fill[a as usize] += 1;
            adj[fill[b as usize] as usize] = a;
            fill[b as usize] += 1;
        }
        PairGraph { start, adj }
    }

    /// Number of nodes.
    pub(crate) fn len(&self) -> usize {
        self.start.len() - 1
    }

    /// The neighbours of node `i`.
    pub(crate) fn neighbours(&self, i: usize) -> &[u32] {
        &self.adj[self.start[i] as usize..self.start[i + 1] as usize]
    }
}

/// Reusable buffers of [`min_cut`].
#[derive(Default)]
pub(crate) struct CutScratch {
    /// Unary preference after fixed neighbours were folded in.
    delta: Vec<f64>,
    /// Free neighbours left per node.
    free_degree: Vec<u32>,
    /// Label state per node: 0, 1 fixed; [`FREE`] undecided.
    state: Vec<u8>,
    queue: Vec<u32>,
    /// Component-local index of a free node.
    local: Vec<u32>,
    members: Vec<u32>,
    flow: Flow,
}

const FREE: u8 = 2;

/// What one minimisation did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(crate) struct CutStats {
    /// Nodes decided by persistency.
    pub fixed: usize,
    /// Nodes decided by a max-flow.
    pub cut: usize,
    /// Free components solved.
    pub components: usize,
}

/// Minimises the energy of the module documentation over `graph` with unary preferences
/// `delta` (for label 1; ±∞ fixes a node) and pair weight `lambda` ≥ 0; writes the labels (0
/// or 1) to `labels`.
pub(crate) fn min_cut(
    graph: &PairGraph,
    delta: &[f64],
    lambda: f64,
    labels: &mut [u8],
    s: &mut CutScratch,
) -> CutStats {
    let n = graph.len();
    s.delta.clear();
    s.delta.extend_from_slice(delta);
    s.state.clear();
    s.state.resize(n, FREE);
    s.free_degree.clear();
    s.free_degree
        .extend((0..n).map(|i| graph.neighbours(i).len() as u32));
    // Persistency, in three steps so that each (free, fixed) pair is folded once: fix the
    // nodes whose preference outweighs all their pairs; fold the fixed neighbours of the nodes
    // left into their preferences; then fix what that decides, folding each newly fixed node
    // into its free neighbours as it goes.
    let decide = |d: f64, free: u32| -> u8 {
        let bound = lambda * f64::from(free);
        if d >= bound && d >= 0.0 {
            1
        } else if d <= -bound && d < 0.0 {
            0
        } else {
            FREE
        }
    };
    for i in 0..n {
        s.state[i] = decide(s.delta[i], s.free_degree[i]);
    }
    s.queue.clear();
    for i in 0..n {
        if s.state[i] != FREE {
            continue;
        }
        for &j in graph.neighbours(i) {
            match s.state[j as usize] {
                1 => s.delta[i] += lambda,
                0 => s.delta[i] -= lambda,
                _ => continue,
            }
            s.free_degree[i] -= 1;
        }
        s.queue.push(i as u32);
    }
    while let Some(i) = s.queue.pop() {
        let i = i as usize;
        if s.state[i] != FREE {
            continue;
        }
        let label = decide(s.delta[i], s.free_degree[i]);
        if label == FREE {
            continue;
        }
        s.state[i] = label;
        for &j in graph.neighbours(i) {
            let j = j as usize;
            if s.state[j] == FREE {
                s.free_degree[j] -= 1;
                s.delta[j] += if label == 1 { lambda } else { -lambda };
                s.queue.push(j as u32);
            }
        }
    }
    let fixed = s.state.iter().filter(|&&x| x != FREE).count();
    // The free nodes, component by component.
    s.local.clear();
    s.local.resize(n, u32::MAX);
    let mut stats = CutStats {
        fixed,
        ..CutStats::default()
    };
    for seed in 0..n {
        if s.state[seed] != FREE || s.local[seed] != u32::MAX {
            continue;
        }
        s.members.clear();
        s.members.push(seed as u32);
        s.local[seed] = 0;
        let mut head = 0;
        while head < s.members.len() {
            let i = s.members[head] as usize;
            head += 1;
            for &j in graph.neighbours(i) {
                let j = j as usize;
                if s.state[j] == FREE && s.local[j] == u32::MAX {
                    s.local[j] = s.members.len() as u32;
                    s.members.push(j as u32);
                }
            }
        }
        let CutScratch {
            delta,
            state,
            local,
            members,
            flow,
            ..
        } = s;
        flow.build(graph, members, local, state, delta, lambda);
        flow.max_flow();
        let source_side = flow.source_side();
        for (m, &i) in members.iter().enumerate() {
            state[i as usize] = u8::from(!source_side[m]);
        }
        stats.cut += members.len();
        stats.components += 1;
    }
    labels[..n].copy_from_slice(&s.state[..n]);
    stats
}

/// A flow network in arc-list form: arcs 2e and 2e + 1 are each other's reverse.
#[derive(Default)]
struct Flow {
    /// Node v's arcs are `arcs[first[v]..first[v + 1]]` (arc ids).
    first: Vec<u32>,
    arcs: Vec<u32>,
    to: Vec<u32>,
    cap: Vec<f64>,
    level: Vec<i32>,
    next_arc: Vec<u32>,
    queue: Vec<u32>,
    /// The arcs of the current search path.
    path: Vec<u32>,
    reached: Vec<bool>,
    /// Arcs per node while building.
    tails: Vec<u32>,
}

impl Flow {
    fn source(&self) -> usize {
        self.first.len() - 3
    }

    fn sink(&self) -> usize {
        self.first.len() - 2
    }

    /// The network of the free nodes `members` (with component-local indices `local`):
    /// terminal arcs from their preferences `delta`, λ arcs between free neighbours (fixed
    /// neighbours were folded into `delta`).
    fn build(
        &mut self,
        graph: &PairGraph,
        members: &[u32],
        local: &[u32],
        state: &[u8],
        delta: &[f64],
        lambda: f64,
    ) {
        let m = members.len();
        let (src, snk) = (m as u32, m as u32 + 1);
        self.to.clear();
        self.cap.clear();
        self.tails.clear();
        let mut add = |tail: u32, head: u32, c: f64, c_back: f64, to: &mut Vec<u32>| {
            to.push(head);
            to.push(tail);
            self.cap.push(c);
            self.cap.push(c_back);
            self.tails.push(tail);
            self.tails.push(head);
        };
        for (a, &i) in members.iter().enumerate() {
            let i = i as usize;
            // Label 0 on the source side: the nodes preferring it are the few (shadow
            // candidates), so the searches from the source stay near them.
            let d = delta[i];
            if d < 0.0 {
                add(src, a as u32, -d, 0.0, &mut self.to);
            } else if d > 0.0 {
                add(a as u32, snk, d, 0.0, &mut self.to);
            }
            for &j in graph.neighbours(i) {
                let j = j as usize;
                // Each free pair once, as one arc each way.
                if state[j] == FREE && j > i {
                    add(a as u32, local[j], lambda, lambda, &mut self.to);
                }
            }
        }
        // Group the arcs by tail (counting sort).
        let nodes = m + 2;
        self.first.clear();
        self.first.resize(nodes + 1, 0);
        for &t in &self.tails {
            self.first[t as usize + 1] += 1;
        }
        for v in 0..nodes {
            self.first[v + 1] += self.first[v];
        }
        self.arcs.clear();
        self.arcs.resize(self.tails.len(), 0);
        self.next_arc.clear();
        self.next_arc.extend_from_slice(&self.first[..nodes]);
        for (e, &t) in self.tails.iter().enumerate() {
            let slot = &mut self.next_arc[t as usize];
            self.arcs[*slot as usize] = e as u32;
            *slot += 1;
        }
        self.level.clear();
        self.level.resize(nodes, -1);
    }

    /// Breadth-first levels from the source over unsaturated arcs; whether the sink is reached.
    fn levels(&mut self) -> bool {
        self.level.fill(-1);
        let (s, t) = (self.source(), self.sink());
        self.level[s] = 0;
        self.queue.clear();
        self.queue.push(s as u32);
        let mut head = 0;
        while head < self.queue.len() {
            let v = self.queue[head] as usize;
            head += 1;
            // Nodes at the sink's level or beyond are on no shortest path: stop there, so a
            // phase explores only the neighbourhood of the source's nodes.
            if self.level[t] >= 0 && self.level[v] >= self.level[t] {
                break;
            }
            for &e in &self.arcs[self.first[v] as usize..self.first[v + 1] as usize] {
                let w = self.to[e as usize] as usize;
                if self.cap[e as usize] > EPS && self.level[w] < 0 {
                    self.level[w] = self.level[v] + 1;
                    self.queue.push(w as u32);
                }
            }
        }
        self.level[t] >= 0
    }

    /// Dinic's algorithm: blocking flows along the level graph until the sink is cut off.
    fn max_flow(&mut self) {
        let (s, t) = (self.source(), self.sink());
        while self.levels() {
            let nodes = self.first.len() - 1;
            self.next_arc.clear();
            self.next_arc.extend_from_slice(&self.first[..nodes]);
            self.path.clear();
            let mut v = s;
            loop {
                if v == t {
                    // Augment by the bottleneck, then back up to the first saturated arc.
                    let push = self
                        .path
                        .iter()
                        .map(|&e| self.cap[e as usize])
                        .fold(f64::INFINITY, f64::min);
                    let mut cut_at = self.path.len();
                    for (k, &e) in self.path.iter().enumerate() {
                        let e = e as usize;
                        self.cap[e] -= push;
                        self.cap[e ^ 1] += push;
                        if self.cap[e] <= EPS && cut_at == self.path.len() {
                            cut_at = k;
                        }
                    }
                    self.path.truncate(cut_at);
                    v = match self.path.last() {
                        Some(&e) => self.to[e as usize] as usize,
                        None => s,
                    };
                    continue;
                }
                // Advance along the next admissible arc of v, or retreat.
                let end = self.first[v + 1];
                let mut advanced = false;
                while self.next_arc[v] < end {
                    let e = self.arcs[self.next_arc[v] as usize] as usize;
                    let w = self.to[e] as usize;
                    if self.cap[e] > EPS && self.level[w] == self.level[v] + 1 {
                        self.path.push(e as u32);
                        v = w;
                        advanced = true;
                        break;
                    }
                    self.next_arc[v] += 1;
                }
                if advanced {
                    continue;
                }
                // Dead end: v leaves the level graph.
                self.level[v] = -1;
                match self.path.pop() {
                    None => break,
                    Some(e) => {
                        let u = self.to[e as usize ^ 1] as usize;
                        self.next_arc[u] += 1;
                        v = u;
                    }
                }
            }
        }
    }

    /// Per component node, whether the source reaches it in the residual graph.
    fn source_side(&mut self) -> &[bool] {
        let nodes = self.first.len() - 1;
        let s = self.source();
        self.reached.clear();
        self.reached.resize(nodes, false);
        self.reached[s] = true;
        self.queue.clear();
        self.queue.push(s as u32);
        let mut head = 0;
        while head < self.queue.len() {
            let v = self.queue[head] as usize;
            head += 1;
            for &e in &self.arcs[self.first[v] as usize..self.first[v + 1] as usize] {
                let w = self.to[e as usize] as usize;
                if self.cap[e as usize] > EPS && !self.reached[w] {
                    self.reached[w] = true;
                    self.queue.push(w as u32);
                }
            }
        }
        &self.reached[..nodes - 2]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};

    /// The energy of `labels`.
    fn energy(graph: &PairGraph, delta: &[f64], lambda: f64, labels: &[u8]) -> f64 {
        let mut e = 0.0;
        for i in 0..graph.len() {
            e += if labels[i] == 1 {
                (-delta[i]).max(0.0)
            } else {
                delta[i].max(0.0)
            };
            for &j in graph.neighbours(i) {
                if (j as usize) > i && labels[i] != labels[j as usize] {
                    e += lambda;
                }
            }
        }
        e
    }

    /// A `w`×`h` 4-connected grid.
    fn grid(w: usize, h: usize) -> PairGraph {
        let mut edges = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let i = (y * w + x) as u32;
                if x + 1 < w {
                    edges.push((i, i + 1));
                }
                if y + 1 < h {
                    edges.push((i, i + w as u32));
                }
            }
        }
        PairGraph::new(w * h, &edges)
    }

    /// On random 3×4 grids (4096 labellings each) the cut's energy equals the brute-force
    /// minimum, for weak, strong and mixed preferences, with fixed nodes among them.
    #[test]
    fn cut_is_the_exact_minimum_on_small_grids() {
        let (w, h) = (4, 3);
        let g = grid(w, h);
        let mut rng = rand::rngs::ChaCha8Rng::seed_from_u64(3);
        let mut s = CutScratch::default();
        let mut labels = vec![0u8; w * h];
        let mut cut_nodes = 0;
        for trial in 0..300 {
            let lambda = [0.0, 0.3, 1.0, 2.5][trial % 4];
            let scale = [0.5, 2.0, 6.0][trial % 3];
            let delta: Vec<f64> = (0..w * h)
                .map(|_| match rng.random_range(0..20) {
                    0 => f64::INFINITY,
                    1 => f64::NEG_INFINITY,
                    _ => rng.random_range(-scale..scale),
                })
                .collect();
            let stats = min_cut(&g, &delta, lambda, &mut labels, &mut s);
            cut_nodes += stats.cut;
            assert_eq!(stats.fixed + stats.cut, w * h);
            let got = energy(&g, &delta, lambda, &labels);
            let best = (0..1u32 << (w * h))
                .map(|bits| {
                    let l: Vec<u8> = (0..w * h).map(|i| (bits >> i & 1) as u8).collect();
                    energy(&g, &delta, lambda, &l)
                })
                .fold(f64::INFINITY, f64::min);
            assert!(
                (got - best).abs() < 1e-9,
                "trial {trial}: cut {got}, minimum {best}"
            );
        }
        // The flows were exercised, not only the persistency step.
        assert!(cut_nodes > 500, "{cut_nodes} nodes cut");
    }

    /// A lone dissenting pixel is outvoted by its four neighbours when its preference is below
    /// 4λ and keeps its label above; with λ = 0 every node takes its own preference.
    #[test]
    fn smoothing_outvotes_isolated_pixels_only_when_weak() {
        let g = grid(5, 5);
        let mut s = CutScratch::default();
        let mut labels = vec![0u8; 25];
        for (own, lambda, expect) in [(-3.0, 1.0, 1), (-5.0, 1.0, 0), (-3.0, 0.0, 0)] {
            let mut delta = vec![10.0; 25];
            delta[12] = own;
            min_cut(&g, &delta, lambda, &mut labels, &mut s);
            assert_eq!(labels[12], expect, "own {own}, λ {lambda}");
            assert!(labels.iter().enumerate().all(|(i, &l)| i == 12 || l == 1));
        }
    }
}
