//! Minimum s–t cut by maximum flow: the Boykov–Kolmogorov algorithm (Boykov & Kolmogorov,
//! "An Experimental Comparison of Min-Cut/Max-Flow Algorithms for Energy Minimization in
//! Vision", PAMI 2004), the algorithm graph-cut surface reconstruction uses.
//!
//! Why our own: no maintained Rust crate has it. `petgraph`'s `dinics` (0.8) resets an
//! O(nodes) visited map and allocates an O(nodes) array for every augmenting path (read in its
//! source, not measured), and the surface graphs here have 10⁵–10⁶ nodes; `rs-graph` is GPL.
//!
//! The graph: `n` nodes, each with a capacity from the source and one to the sink (the
//! "terminal links"), and directed arcs added in pairs (an edge `i → j` with capacity `c_ij`
//! and its reverse `j → i` with `c_ji`). Two search trees grow from the terminals through arcs
//! with residual capacity; where they touch, the path is augmented; nodes cut off from their
//! tree are adopted by another parent of the same tree or freed. When no tree can grow, the
//! source tree is the source side of a minimum cut.
//!
//! Determinism: the algorithm is sequential and its order is fixed by the node and arc order,
//! so the same graph gives the same cut bit for bit. Capacities are f64 and must be finite and
//! non-negative; a residual at or below [`EPS`] times the largest capacity counts as zero, so
//! rounding in the subtractions cannot leave dust arcs that grow trees forever.

/// Residuals at or below `EPS ×` the largest capacity are saturated.
const EPS: f64 = 1e-12;

const NO_ARC: u32 = u32::MAX;
/// Parent "arc" of a node whose tree root is the terminal itself.
const TERMINAL: u32 = u32::MAX - 1;
/// Parent of an orphan (removed from its tree during adoption).
const ORPHAN: u32 = u32::MAX - 2;

#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Tree {
    Free,
    Source,
    Sink,
}

/// A flow network for [`Graph::max_flow`].
#[derive(Clone, Debug, Default)]
pub struct Graph {
    /// Per node: residual terminal capacity (positive: from the source; negative: to the sink).
    tr: Vec<f64>,
    /// Arcs: head node and residual capacity; arc `a ^ 1` is the reverse of arc `a`.
    head: Vec<u32>,
    cap: Vec<f64>,
    /// Arcs grouped by tail node (built once before the flow).
    first: Vec<u32>,
    out: Vec<u32>,
    /// Per node: tree, parent arc (from the parent to the node in the source tree, from the node
    /// to its parent in the sink tree: we store the arc leaving the node towards its parent),
    /// distance to the root and the time that distance was checked.
    tree: Vec<Tree>,
    parent: Vec<u32>,
    dist: Vec<u32>,
    stamp: Vec<u32>,
    flow: f64,
    zero: f64,
}

impl Graph {
    /// A graph of `n` nodes and no arcs.
    pub fn new(n: usize) -> Graph {
        Graph {
            tr: vec![0.0; n],
            ..Graph::default()
        }
    }

    /// Number of nodes.
    pub fn len(&self) -> usize {
        self.tr.len()
    }

    /// Whether the graph has no nodes.
    pub fn is_empty(&self) -> bool {
        self.tr.is_empty()
    }

    /// Add capacity `source` from the source to node `i` and `sink` from it to the sink.
    pub fn add_terminal(&mut self, i: usize, source: f64, sink: f64) {
        debug_assert!(source >= 0.0 && sink >= 0.0);
        // Only the difference matters for the cut; the common part flows straight through.
        let common = source.min(sink);
        self.flow += common;
        self.tr[i] += source - sink;
    }

    /// Add an edge `i → j` of capacity `c_ij` and its reverse `j → i` of capacity `c_ji`.
    pub fn add_edge(&mut self, i: usize, j: usize, c_ij: f64, c_ji: f64) {
        debug_assert!(c_ij >= 0.0 && c_ji >= 0.0 && i != j);
        // The tail of arc a is the head of arc a ^ 1.
        self.head.push(j as u32);
        self.cap.push(c_ij);
        self.head.push(i as u32);
        self.cap.push(c_ji);
    }

    #[inline]
    fn tail(&self, a: u32) -> u32 {
        self.head[(a ^ 1) as usize]
    }

    fn build(&mut self) {
        let n = self.tr.len();
        let mut count = vec![0u32; n + 1];
        for a in 0..self.head.len() {
            count[self.tail(a as u32) as usize + 1] += 1;
        }
        for i in 0..n {
            count[i + 1] += count[i];
        }
        self.first = count.clone();
        self.out = vec![0; self.head.len()];
        for a in 0..self.head.len() as u32 {
            let t = self.tail(a) as usize;
            self.out[count[t] as usize] = a;
            count[t] += 1;
        }
        let big = self
            .cap
            .iter()
            .chain(self.tr.iter())
            .fold(0.0f64, |m, c| m.max(c.abs()));
        self.zero = EPS * big;
        self.tree = vec![Tree::Free; n];
        self.parent = vec![NO_ARC; n];
        self.dist = vec![0; n];
        self.stamp = vec![0; n];
    }

    /// Compute the maximum flow; returns its value. Afterwards [`Graph::source_side`] tells the
    /// minimum cut. Call once.
    pub fn max_flow(&mut self) -> f64 {
        self.build();
        let n = self.tr.len();
        let mut active: std::collections::VecDeque<u32> = std::collections::VecDeque::new();
        let mut time = 1u32;
        for i in 0..n {
            if self.tr[i] > self.zero {
                self.tree[i] = Tree::Source;
            } else if self.tr[i] < -self.zero {
                self.tree[i] = Tree::Sink;
            } else {
                continue;
            }
            self.parent[i] = TERMINAL;
            self.dist[i] = 1;
            self.stamp[i] = time;
            active.push_back(i as u32);
        }
        let mut orphans: Vec<u32> = Vec::new();
        while let Some(&i) = active.front() {
            let i = i as usize;
            if self.tree[i] == Tree::Free {
                active.pop_front();
                continue;
            }
            // Growth: the first arc from i that reaches the other tree, growing over free nodes.
            let mut meet = NO_ARC;
            for k in self.first[i]..self.first[i + 1] {
                let a = self.out[k as usize];
                let j = self.head[a as usize] as usize;
                // Residual in the tree's direction: out of i for the source tree, into i for
                // the sink tree.
                let res = if self.tree[i] == Tree::Source {
                    self.cap[a as usize]
                } else {
                    self.cap[(a ^ 1) as usize]
                };
                if res <= self.zero {
                    continue;
                }
                if self.tree[j] == Tree::Free {
                    self.tree[j] = self.tree[i];
                    self.parent[j] = a ^ 1;
                    self.dist[j] = self.dist[i] + 1;
                    self.stamp[j] = self.stamp[i];
                    active.push_back(j as u32);
                } else if self.tree[j] != self.tree[i] {
                    // Arc in the source→sink direction.
                    meet = if self.tree[i] == Tree::Source {
                        a
                    } else {
                        a ^ 1
                    };
                    break;
                }
            }
            if meet == NO_ARC {
                active.pop_front();
                continue;
            }
            time = time.wrapping_add(1);
            self.augment(meet, &mut orphans);
            self.adopt(&mut orphans, &mut active, time);
        }
        self.flow
    }

    /// Push the bottleneck through the path source → … → tail(meet) → head(meet) → … → sink.
    fn augment(&mut self, meet: u32, orphans: &mut Vec<u32>) {
        // Bottleneck.
        let mut b = self.cap[meet as usize];
        let mut i = self.tail(meet) as usize;
        loop {
            let a = self.parent[i];
            if a == TERMINAL {
                b = b.min(self.tr[i]);
                break;
            }
            // Source tree: parent[i] is the arc from i to its parent; flow goes parent → i,
            // on the reverse arc.
            b = b.min(self.cap[(a ^ 1) as usize]);
            i = self.head[a as usize] as usize;
        }
        let mut i = self.head[meet as usize] as usize;
        loop {
            let a = self.parent[i];
            if a == TERMINAL {
                b = b.min(-self.tr[i]);
                break;
            }
            b = b.min(self.cap[a as usize]);
            i = self.head[a as usize] as usize;
        }
        // Push.
        self.cap[meet as usize] -= b;
        self.cap[(meet ^ 1) as usize] += b;
        let mut i = self.tail(meet) as usize;
        loop {
            let a = self.parent[i];
            if a == TERMINAL {
                self.tr[i] -= b;
                if self.tr[i] <= self.zero {
                    self.parent[i] = ORPHAN;
                    orphans.push(i as u32);
                }
                break;
            }
            self.cap[(a ^ 1) as usize] -= b;
            self.cap[a as usize] += b;
            let up = self.head[a as usize] as usize;
            if self.cap[(a ^ 1) as usize] <= self.zero {
                self.parent[i] = ORPHAN;
                orphans.push(i as u32);
            }
            i = up;
        }
        let mut i = self.head[meet as usize] as usize;
        loop {
            let a = self.parent[i];
            if a == TERMINAL {
                self.tr[i] += b;
                if self.tr[i] >= -self.zero {
                    self.parent[i] = ORPHAN;
                    orphans.push(i as u32);
                }
                break;
            }
            self.cap[a as usize] -= b;
            self.cap[(a ^ 1) as usize] += b;
            let up = self.head[a as usize] as usize;
            if self.cap[a as usize] <= self.zero {
                self.parent[i] = ORPHAN;
                orphans.push(i as u32);
            }
            i = up;
        }
        self.flow += b;
    }

    /// Residual capacity of the arc joining node `j` to its would-be parent through arc `a`
    /// (an arc leaving `j`), in its tree's direction.
    #[inline]
    fn tree_res(&self, tree: Tree, a: u32) -> f64 {
        match tree {
            // Flow comes from the parent into j: the reverse of a.
            Tree::Source => self.cap[(a ^ 1) as usize],
            _ => self.cap[a as usize],
        }
    }

    /// Give each orphan a new parent in its tree, or free it.
    fn adopt(
        &mut self,
        orphans: &mut Vec<u32>,
        active: &mut std::collections::VecDeque<u32>,
        time: u32,
    ) {
        while let Some(o) = orphans.pop() {
            let o = o as usize;
            let tree = self.tree[o];
            let mut best = NO_ARC;
            let mut best_d = u32::MAX;
            for k in self.first[o]..self.first[o + 1] {
                let a = self.out[k as usize];
                if self.tree_res(tree, a) <= self.zero {
                    continue;
                }
                let j = self.head[a as usize] as usize;
                if self.tree[j] != tree {
                    continue;
                }
                // Does j's path reach the terminal (not through an orphan)?
                let mut d = 0u32;
                let mut x = j;
                let ok = loop {
                    if self.stamp[x] == time {
                        d += self.dist[x];
                        break true;
                    }
                    let pa = self.parent[x];
                    d += 1;
                    if pa == TERMINAL {
                        self.stamp[x] = time;
                        self.dist[x] = 1;
                        break true;
                    }
                    if pa == ORPHAN || pa == NO_ARC {
                        break false;
                    }
                    x = self.head[pa as usize] as usize;
                };
                if ok {
                    if d < best_d {
                        best_d = d;
                        best = a;
                    }
                    // Mark the path checked, with its distances.
                    let mut x = j;
                    let mut dd = d;
                    while self.stamp[x] != time {
                        self.stamp[x] = time;
                        self.dist[x] = dd;
                        dd -= 1;
                        x = self.head[self.parent[x] as usize] as usize;
                    }
                }
            }
            if best != NO_ARC {
                self.parent[o] = best;
                self.stamp[o] = time;
                self.dist[o] = best_d + 1;
                continue;
            }
            // No parent: o leaves its tree; its children become orphans, and neighbours that
            // could feed it become active.
            for k in self.first[o]..self.first[o + 1] {
                let a = self.out[k as usize];
                let j = self.head[a as usize] as usize;
                if self.tree[j] != tree {
                    continue;
                }
                let pj = self.parent[j];
                if self.tree_res(tree, a) > self.zero {
                    active.push_back(j as u32);
                }
                if pj != TERMINAL
                    && pj != ORPHAN
                    && pj != NO_ARC
                    && self.head[pj as usize] as usize == o
                {
                    self.parent[j] = ORPHAN;
                    orphans.push(j as u32);
                }
            }
            self.tree[o] = Tree::Free;
            self.parent[o] = NO_ARC;
        }
    }

    /// After [`Graph::max_flow`]: whether node `i` is on the source side of the minimum cut
    /// (reachable from the source through residual capacity).
    pub fn source_side(&self, i: usize) -> bool {
        self.tree[i] == Tree::Source
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::{below, uniform_f64, Purpose};

    struct Case {
        n: usize,
        terminals: Vec<(f64, f64)>,
        edges: Vec<(usize, usize, f64, f64)>,
    }

    fn cut_cost(c: &Case, side: &[bool]) -> f64 {
        let mut cost = 0.0;
        for (i, &(s, t)) in c.terminals.iter().enumerate() {
            cost += if side[i] { t } else { s };
        }
        for &(i, j, cij, cji) in &c.edges {
            if side[i] && !side[j] {
                cost += cij;
            }
            if side[j] && !side[i] {
                cost += cji;
            }
        }
        cost
    }

    fn random_case(seed: u64, n: usize, m: usize, integer: bool) -> Case {
        let r = |a: u64, b: u64| {
            let x = uniform_f64(seed, Purpose::Test, a, b);
            if integer {
                (x * 4.0).floor()
            } else {
                x
            }
        };
        let terminals = (0..n as u64)
            .map(|i| {
                // Many nodes without terminal links, as in a surface graph.
                if below(seed, Purpose::Test, 1000 + i, 0, 3) == 0 {
                    (r(i, 1) * 3.0, r(i, 2) * 3.0)
                } else {
                    (0.0, 0.0)
                }
            })
            .collect();
        let mut edges = Vec::new();
        for e in 0..m as u64 {
            let i = below(seed, Purpose::Test, 2000 + e, 0, n as u64) as usize;
            let mut j = below(seed, Purpose::Test, 2000 + e, 1, n as u64 - 1) as usize;
            if j >= i {
                j += 1;
            }
            edges.push((i, j, r(3000 + e, 0), r(3000 + e, 1)));
        }
        Case {
            n,
            terminals,
            edges,
        }
    }

    fn solve(c: &Case) -> (f64, Vec<bool>) {
        let mut g = Graph::new(c.n);
        for (i, &(s, t)) in c.terminals.iter().enumerate() {
            g.add_terminal(i, s, t);
        }
        for &(i, j, a, b) in &c.edges {
            g.add_edge(i, j, a, b);
        }
        let f = g.max_flow();
        (f, (0..c.n).map(|i| g.source_side(i)).collect())
    }

    /// Max flow equals the minimum over all 2^n cuts, and the returned side is such a cut.
    #[test]
    fn equals_brute_force_min_cut() {
        for seed in 0..400u64 {
            let n = 2 + (seed % 9) as usize;
            let m = (seed % 23) as usize;
            let c = random_case(seed, n, m, seed % 2 == 0);
            let (f, side) = solve(&c);
            let best = (0..1u32 << n)
                .map(|mask| {
                    let side: Vec<bool> = (0..n).map(|i| mask >> i & 1 == 1).collect();
                    cut_cost(&c, &side)
                })
                .fold(f64::INFINITY, f64::min);
            assert!(
                (f - best).abs() <= 1e-9 * (1.0 + best),
                "seed {seed}: flow {f}, min cut {best}"
            );
            let got = cut_cost(&c, &side);
            assert!(
                (got - best).abs() <= 1e-9 * (1.0 + best),
                "seed {seed}: cut {got}, min {best}"
            );
        }
    }

    /// A chain s → 0 → 1 → … → k → t: the flow is the smallest link, and the cut is there.
    #[test]
    fn chain_cut_at_the_bottleneck() {
        let k = 50;
        let mut g = Graph::new(k);
        g.add_terminal(0, 10.0, 0.0);
        g.add_terminal(k - 1, 0.0, 10.0);
        for i in 0..k - 1 {
            let c = if i == 31 { 0.25 } else { 1.0 + i as f64 };
            g.add_edge(i, i + 1, c, 0.0);
        }
        assert_eq!(g.max_flow(), 0.25);
        for i in 0..k {
            assert_eq!(g.source_side(i), i <= 31, "node {i}");
        }
    }

    /// A larger random graph: same cut whatever, the same twice (determinism), and the cut's
    /// cost equals the flow.
    #[test]
    fn larger_graph_cut_equals_flow() {
        let c = random_case(7, 3000, 12000, false);
        let (f, side) = solve(&c);
        let (f2, side2) = solve(&c);
        assert_eq!(f.to_bits(), f2.to_bits());
        assert_eq!(side, side2);
        let cost = cut_cost(&c, &side);
        assert!((cost - f).abs() <= 1e-9 * f, "{cost} vs {f}");
    }
}
