//! Block-sparse Cholesky of the pose graph's normal equations, in 6×6
//! blocks (one block row per vehicle), and the diagonal blocks of the
//! inverse.
//!
//! The pose graph of a fleet is sparse: each vehicle sees its few
//! neighbours. A profile (skyline) Cholesky stores and factors everything
//! inside the envelope of a band ordering, which for a fleet on a grid
//! `w` vehicles wide is `O(n·w²)` blocks of work and, for the marginals,
//! forward substitutions through the whole band per vehicle. Here the
//! vehicles are ordered by minimum degree (fill-reducing), the factor's
//! pattern is the elimination graph's (so no envelope is filled), and the
//! marginals are the diagonal blocks of a Takahashi selected inversion over
//! that pattern only: the same work as one factorization.
//!
//! [`Symbolic`] (order, pattern, update targets) is built once per graph
//! and reused by every Levenberg–Marquardt iteration; [`Factor`] is the
//! numeric part.

use nalgebra::{Matrix6, Vector6};
use std::cmp::Reverse;
use std::collections::BinaryHeap;

/// One 6×6 block.
pub(crate) type Block = Matrix6<f64>;

/// Elimination order and the factor's pattern for a graph over `m` block
/// variables. Variables are renumbered by their elimination position; slot
/// `p` (`p < m`) is the diagonal block of position `p`, slots from `m` on
/// the off-diagonal blocks, column by column.
#[derive(Debug, Clone)]
pub(crate) struct Symbolic {
    /// Variable (caller's numbering) → elimination position.
    pub position: Vec<usize>,
    /// Column `j`'s off-diagonal rows are `rows[col_start[j]..col_start[j + 1]]`
    /// (positions `> j`, ascending), at slots `m + col_start[j]..`.
    col_start: Vec<usize>,
    rows: Vec<usize>,
    /// Per column, for every pair `(a, b)`, `a ≥ b`, of its off-diagonal
    /// rows (local indices, row-major over the lower triangle), the slot of
    /// block `(rows[a], rows[b])`: the targets of the column's update.
    pair_start: Vec<usize>,
    pair_slot: Vec<usize>,
}

/// Neighbour lists sorted, deduplicated, without self-loops.
fn sorted_adjacency(neighbours: &[Vec<usize>]) -> Vec<Vec<usize>> {
    neighbours
        .iter()
        .enumerate()
        .map(|(v, n)| {
            let mut n: Vec<usize> = n.iter().copied().filter(|&u| u != v).collect();
            n.sort_unstable();
            n.dedup();
            n
        })
        .collect()
}

/// `a ∪ b` without `skip` (both sorted), into `out`.
fn merge_into(a: &[usize], b: &[usize], skip: [usize; 2], out: &mut Vec<usize>) {
    out.clear();
    let (mut i, mut k) = (0, 0);
    while i < a.len() || k < b.len() {
        let next = match (a.get(i), b.get(k)) {
            (Some(&x), Some(&y)) if x == y => {
                i += 1;
                k += 1;
                x
            }
            (Some(&x), Some(&y)) if x < y => {
                i += 1;
                x
            }
            (Some(&x), None) => {
                i += 1;
                x
            }
            (_, Some(&y)) => {
                k += 1;
                y
            }
            (None, None) => break,
        };
        if !skip.contains(&next) {
            out.push(next);
        }
    }
}

/// Eliminate the variables of `adj` (sorted lists) in the given `order`, or
/// by minimum degree (ties by variable number) when `None`: the order and,
/// per variable, its neighbours when eliminated (the rows of its column of
/// the factor).
fn eliminate(mut adj: Vec<Vec<usize>>, order: Option<&[usize]>) -> (Vec<usize>, Vec<Vec<usize>>) {
    let m = adj.len();
    let mut heap: BinaryHeap<Reverse<(usize, usize)>> = match order {
        Some(_) => BinaryHeap::new(),
        None => adj
            .iter()
            .enumerate()
            .map(|(v, n)| Reverse((n.len(), v)))
            .collect(),
    };
    let mut given = order.unwrap_or(&[]).iter();
    let mut eliminated = vec![false; m];
    let mut out = Vec::with_capacity(m);
    let mut structure: Vec<Vec<usize>> = vec![Vec::new(); m];
    let mut merged = Vec::new();
    loop {
        let v = if order.is_some() {
            match given.next() {
                Some(&v) => v,
                None => break,
            }
        } else {
            match heap.pop() {
                Some(Reverse((deg, v))) if eliminated[v] || deg != adj[v].len() => continue,
                Some(Reverse((_, v))) => v,
                None => break,
            }
        };
        eliminated[v] = true;
        out.push(v);
        let nbrs = std::mem::take(&mut adj[v]);
        for &u in &nbrs {
            // u loses v and gains the other neighbours of v (a clique).
            merge_into(&adj[u], &nbrs, [v, u], &mut merged);
            std::mem::swap(&mut adj[u], &mut merged);
            if order.is_none() {
                heap.push(Reverse((adj[u].len(), u)));
            }
        }
        structure[v] = nbrs;
    }
    (out, structure)
}

/// Parts this small are ordered as they come by [`nested_dissection`].
const DISSECTION_LEAF: usize = 8;

/// Nested-dissection order of the graph `adj`: each part split by a level
/// of a breadth-first search from a pseudo-peripheral vertex (the level
/// where half the part lies below, minus its vertices with no neighbour
/// above), the two sides ordered first, the separator last.
fn nested_dissection(adj: &[Vec<usize>]) -> Vec<usize> {
    let m = adj.len();
    let mut order = Vec::with_capacity(m);
    let mut level = vec![usize::MAX; m];
    dissect(adj, (0..m).collect(), &mut level, &mut order);
    order
}

/// Breadth-first levels of `start` within the vertices whose `level` is
/// `usize::MAX - 1` (the part); returns the levels (vertex lists).
fn bfs_levels(adj: &[Vec<usize>], start: usize, level: &mut [usize]) -> Vec<Vec<usize>> {
    let mut levels = vec![vec![start]];
    level[start] = 0;
    loop {
        let d = levels.len();
        let mut next = Vec::new();
        for &v in &levels[d - 1] {
            for &u in &adj[v] {
                if level[u] == usize::MAX - 1 {
                    level[u] = d;
                    next.push(u);
                }
            }
        }
        if next.is_empty() {
            return levels;
        }
        next.sort_unstable();
        levels.push(next);
    }
}

fn dissect(adj: &[Vec<usize>], part: Vec<usize>, level: &mut [usize], order: &mut Vec<usize>) {
    if part.len() <= DISSECTION_LEAF {
        order.extend(part);
        return;
    }
    let in_part = usize::MAX - 1;
    let reset = |level: &mut [usize]| part.iter().for_each(|&v| level[v] = in_part);
    let degree =
        |v: usize, level: &[usize]| adj[v].iter().filter(|&&u| level[u] != usize::MAX).count();
    reset(level);
    let mut start = *part
        .iter()
        .min_by_key(|&&v| (degree(v, level), v))
        .unwrap_or(&part[0]);
    let mut levels = bfs_levels(adj, start, level);
    // Pseudo-peripheral start: restart from the far end while the search deepens.
    for _ in 0..4 {
        let far = levels.last().map_or(start, |l| {
            *l.iter()
                .min_by_key(|&&v| (degree(v, level), v))
                .unwrap_or(&start)
        });
        reset(level);
        let again = bfs_levels(adj, far, level);
        if again.len() <= levels.len() {
            reset(level);
            levels = bfs_levels(adj, start, level);
            break;
        }
        (start, levels) = (far, again);
    }
    let reached: usize = levels.iter().map(Vec::len).sum();
    if reached < part.len() {
        // Disconnected: the component, then the rest.
        let (comp, rest): (Vec<usize>, Vec<usize>) =
            part.iter().partition(|&&v| level[v] < in_part);
        part.iter().for_each(|&v| level[v] = usize::MAX);
        dissect(adj, comp, level, order);
        dissect(adj, rest, level, order);
        return;
    }
    if levels.len() < 3 {
        part.iter().for_each(|&v| level[v] = usize::MAX);
        order.extend(part);
        return;
    }
    // The separating level: half the part below it, both sides non-empty.
    let mut below = 0;
    let mut k = 1;
    while k + 2 < levels.len() && below + levels[k - 1].len() < part.len() / 2 {
        below += levels[k - 1].len();
        k += 1;
    }
    let (sep, loose): (Vec<usize>, Vec<usize>) = levels[k]
        .iter()
        .partition(|&&v| adj[v].iter().any(|&u| level[u] == k + 1));
    let lower: Vec<usize> = levels[..k].iter().flatten().copied().chain(loose).collect();
    let upper: Vec<usize> = levels[k + 1..].iter().flatten().copied().collect();
    part.iter().for_each(|&v| level[v] = usize::MAX);
    dissect(adj, lower, level, order);
    dissect(adj, upper, level, order);
    order.extend(sep);
}

/// Block products of a factorization with these columns: `Σ c(c+1)/2`.
fn work(structure: &[Vec<usize>]) -> usize {
    structure.iter().map(|s| s.len() * (s.len() + 1) / 2).sum()
}

impl Symbolic {
    /// A fill-reducing order of the graph `neighbours` (each list the other
    /// variables a variable shares a block with; symmetric) and the pattern
    /// of its Cholesky factor. Of minimum degree (ties by variable number)
    /// and nested dissection, the order whose factorization takes fewer
    /// block products (minimum degree on a tie); deterministic.
    pub fn new(neighbours: &[Vec<usize>]) -> Self {
        let m = neighbours.len();
        let adj = sorted_adjacency(neighbours);
        let nd = nested_dissection(&adj);
        let (md_order, md_structure) = eliminate(adj.clone(), None);
        let (nd_order, nd_structure) = eliminate(adj, Some(&nd));
        let (order, structure) = if work(&nd_structure) < work(&md_structure) {
            (nd_order, nd_structure)
        } else {
            (md_order, md_structure)
        };
        let mut position = vec![0; m];
        for (p, &v) in order.iter().enumerate() {
            position[v] = p;
        }
        let mut col_start = Vec::with_capacity(m + 1);
        let mut rows = Vec::new();
        for &v in &order {
            col_start.push(rows.len());
            let mut r: Vec<usize> = structure[v].iter().map(|&u| position[u]).collect();
            r.sort_unstable();
            rows.extend(r);
        }
        col_start.push(rows.len());
        let mut s = Self {
            position,
            col_start,
            rows,
            pair_start: Vec::with_capacity(m + 1),
            pair_slot: Vec::new(),
        };
        let (mut pair_start, mut pair_slot) = (Vec::with_capacity(m + 1), Vec::new());
        for j in 0..m {
            pair_start.push(pair_slot.len());
            let col = s.col(j);
            for a in 0..col.len() {
                for b in 0..=a {
                    // Closed under elimination: the rows of a column form a clique.
                    let slot = s
                        .slot(col[a], col[b])
                        .expect("the factor's pattern is closed");
                    pair_slot.push(slot);
                }
            }
        }
        pair_start.push(pair_slot.len());
        s.pair_start = pair_start;
        s.pair_slot = pair_slot;
        s
    }

    /// Block variables.
    pub fn m(&self) -> usize {
        self.col_start.len() - 1
    }

    /// Stored blocks (diagonal and off-diagonal).
    pub fn slots(&self) -> usize {
        self.m() + self.rows.len()
    }

    /// Column `j`'s off-diagonal rows.
    fn col(&self, j: usize) -> &[usize] {
        &self.rows[self.col_start[j]..self.col_start[j + 1]]
    }

    /// Slot of block `(i, j)` (positions, `i ≥ j`), if in the pattern.
    pub fn slot(&self, i: usize, j: usize) -> Option<usize> {
        debug_assert!(i >= j);
        if i == j {
            return Some(i);
        }
        let col = self.col(j);
        col.binary_search(&i)
            .ok()
            .map(|k| self.m() + self.col_start[j] + k)
    }
}

/// The Cholesky factor `L` (`A = L·Lᵀ`) on a [`Symbolic`] pattern.
#[derive(Debug, Clone)]
pub(crate) struct Factor {
    /// Per slot: the diagonal blocks `L_jj`, the off-diagonal `L_ij`.
    values: Vec<Block>,
    /// `L_jj⁻¹` per column.
    inv_diag: Vec<Block>,
}

/// Lower Cholesky factor of a symmetric 6×6 block (lower triangle read) and
/// its inverse; `None` unless positive definite.
fn chol6(a: &Block) -> Option<(Block, Block)> {
    let mut l = Block::zeros();
    for j in 0..6 {
        let mut d = a[(j, j)];
        for k in 0..j {
            d -= l[(j, k)] * l[(j, k)];
        }
        if !(d > 0.0 && d.is_finite()) {
            return None;
        }
        let ljj = d.sqrt();
        l[(j, j)] = ljj;
        for i in j + 1..6 {
            let mut s = a[(i, j)];
            for k in 0..j {
                s -= l[(i, k)] * l[(j, k)];
            }
            l[(i, j)] = s / ljj;
        }
    }
    let mut inv = Block::zeros();
    for i in 0..6 {
        inv[(i, i)] = 1.0 / l[(i, i)];
        for j in 0..i {
            let mut s = 0.0;
            for k in j..i {
                s -= l[(i, k)] * inv[(k, j)];
            }
            inv[(i, j)] = s * inv[(i, i)];
        }
    }
    Some((l, inv))
}

impl Factor {
    /// Factor `a` (per slot of `sym`, the lower blocks; diagonal blocks
    /// symmetric), consuming it; `None` if not positive definite.
    pub fn new(sym: &Symbolic, mut a: Vec<Block>) -> Option<Self> {
        let m = sym.m();
        debug_assert_eq!(a.len(), sym.slots());
        let mut inv_diag = vec![Block::zeros(); m];
        let mut col_l: Vec<Block> = Vec::new();
        for j in 0..m {
            let (l, inv) = chol6(&a[j])?;
            a[j] = l;
            inv_diag[j] = inv;
            let inv_t = inv.transpose();
            let base = m + sym.col_start[j];
            let n = sym.col(j).len();
            col_l.clear();
            for k in 0..n {
                let lij = a[base + k] * inv_t;
                a[base + k] = lij;
                col_l.push(lij);
            }
            // Right-looking update of the trailing blocks.
            let targets = &sym.pair_slot[sym.pair_start[j]..sym.pair_start[j + 1]];
            let mut t = 0;
            for x in 0..n {
                for y in 0..=x {
                    a[targets[t]] -= col_l[x] * col_l[y].transpose();
                    t += 1;
                }
            }
        }
        Some(Self {
            values: a,
            inv_diag,
        })
    }

    /// Solve `L·Lᵀ x = b` (`b` by position, 6 entries each).
    pub fn solve(&self, sym: &Symbolic, b: &[f64]) -> Vec<f64> {
        let m = sym.m();
        let mut y: Vec<Vector6<f64>> = (0..m)
            .map(|p| Vector6::from_column_slice(&b[6 * p..6 * p + 6]))
            .collect();
        for j in 0..m {
            let yj = self.inv_diag[j] * y[j];
            y[j] = yj;
            let base = m + sym.col_start[j];
            for (k, &i) in sym.col(j).iter().enumerate() {
                y[i] -= self.values[base + k] * yj;
            }
        }
        for j in (0..m).rev() {
            let base = m + sym.col_start[j];
            let mut s = y[j];
            for (k, &i) in sym.col(j).iter().enumerate() {
                s -= self.values[base + k].tr_mul(&y[i]);
            }
            y[j] = self.inv_diag[j].tr_mul(&s);
        }
        y.iter().flat_map(|v| v.iter().copied()).collect()
    }

    /// The diagonal blocks of `(L·Lᵀ)⁻¹`, by position: a Takahashi selected
    /// inversion over the factor's pattern, from the last column back.
    /// `Σ = A⁻¹` satisfies `Σ·L = L⁻ᵀ`; with `U_ij = L_ij·L_jj⁻¹`,
    /// `Σ_kj = −Σ_{i∈S(j)} Σ_ki·U_ij` for `k ∈ S(j)` and
    /// `Σ_jj = L_jj⁻ᵀ·L_jj⁻¹ − Σ_{i∈S(j)} Σ_ijᵀ·U_ij`, every `Σ_ki` needed
    /// lying in the pattern (it is closed under elimination).
    pub fn inverse_diagonal_blocks(&self, sym: &Symbolic) -> Vec<Block> {
        let m = sym.m();
        let mut sigma = vec![Block::zeros(); self.values.len()];
        let (mut u, mut acc) = (Vec::new(), Vec::new());
        for j in (0..m).rev() {
            let base = m + sym.col_start[j];
            let n = sym.col(j).len();
            u.clear();
            u.extend((0..n).map(|k| self.values[base + k] * self.inv_diag[j]));
            acc.clear();
            acc.resize(n, Block::zeros());
            let targets = &sym.pair_slot[sym.pair_start[j]..sym.pair_start[j + 1]];
            let mut t = 0;
            for x in 0..n {
                for y in 0..=x {
                    // s = Σ_{rows[x], rows[y]}.
                    let s = &sigma[targets[t]];
                    acc[x] -= s * u[y];
                    if x != y {
                        acc[y] -= s.tr_mul(&u[x]);
                    }
                    t += 1;
                }
            }
            let mut diag = self.inv_diag[j].tr_mul(&self.inv_diag[j]);
            for k in 0..n {
                diag -= acc[k].tr_mul(&u[k]);
                sigma[base + k] = acc[k];
            }
            sigma[j] = (diag + diag.transpose()) * 0.5;
        }
        sigma.truncate(m);
        sigma
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::DMatrix;
    use proto::splitmix::SplitMix64;

    /// A random SPD matrix on the graph of a `w`-wide grid with diagonal
    /// neighbours, and that graph.
    fn grid_problem(rows: usize, w: usize, seed: u64) -> (DMatrix<f64>, Vec<Vec<usize>>) {
        let m = rows * w;
        let mut rng = SplitMix64::new(seed);
        let mut nbrs = vec![Vec::new(); m];
        let mut dense = DMatrix::<f64>::zeros(6 * m, 6 * m);
        for v in 0..m {
            for u in 0..v {
                let (rv, cv, ru, cu) = (v / w, v % w, u / w, u % w);
                if rv.abs_diff(ru) <= 1 && cv.abs_diff(cu) <= 1 {
                    nbrs[v].push(u);
                    nbrs[u].push(v);
                    let b = Block::from_fn(|_, _| rng.unit() - 0.5);
                    // Adds [[I, B], [Bᵀ, BᵀB]]-like SPD coupling: J = [I, B].
                    let (pv, pu) = (6 * v, 6 * u);
                    for r in 0..6 {
                        for c in 0..6 {
                            dense[(pv + r, pu + c)] += b[(r, c)];
                            dense[(pu + c, pv + r)] += b[(r, c)];
                        }
                    }
                    let btb = b.transpose() * b;
                    let mut blk = dense.view_mut((pu, pu), (6, 6));
                    blk += btb;
                    let mut blk = dense.view_mut((pv, pv), (6, 6));
                    blk += Block::identity();
                }
            }
        }
        for i in 0..6 * m {
            dense[(i, i)] += 0.1;
        }
        (dense, nbrs)
    }

    #[test]
    fn factor_solve_and_marginals_match_the_dense_inverse() {
        for (rows, w) in [(1, 1), (2, 3), (5, 4), (7, 7)] {
            let (dense, nbrs) = grid_problem(rows, w, rows as u64 * 31 + w as u64);
            let sym = Symbolic::new(&nbrs);
            let m = sym.m();
            let mut a = vec![Block::zeros(); sym.slots()];
            for v in 0..m {
                for u in 0..m {
                    let (pv, pu) = (sym.position[v], sym.position[u]);
                    if pv < pu {
                        continue;
                    }
                    let blk: Block = dense.fixed_view::<6, 6>(6 * v, 6 * u).into_owned();
                    match sym.slot(pv, pu) {
                        Some(s) => a[s] = blk,
                        None => assert_eq!(blk, Block::zeros(), "({v}, {u}) is not in the pattern"),
                    }
                }
            }
            let f = Factor::new(&sym, a).expect("SPD");
            let inv = dense.clone().try_inverse().unwrap();
            let marginals = f.inverse_diagonal_blocks(&sym);
            for v in 0..m {
                let want = inv.fixed_view::<6, 6>(6 * v, 6 * v);
                let got = marginals[sym.position[v]];
                assert!((got - want).abs().max() < 1e-10, "{rows}x{w}, vehicle {v}");
            }
            // Solve, with b and x by position.
            let rhs: Vec<f64> = (0..6 * m).map(|i| (i % 7) as f64 - 3.0).collect();
            let mut b = vec![0.0; 6 * m];
            for v in 0..m {
                let p = sym.position[v];
                b[6 * p..6 * p + 6].copy_from_slice(&rhs[6 * v..6 * v + 6]);
            }
            let x = f.solve(&sym, &b);
            let mut xv = nalgebra::DVector::zeros(6 * m);
            for v in 0..m {
                let p = sym.position[v];
                for k in 0..6 {
                    xv[6 * v + k] = x[6 * p + k];
                }
            }
            let back = &dense * xv;
            for i in 0..6 * m {
                assert!((back[i] - rhs[i]).abs() < 1e-9, "{rows}x{w}: row {i}");
            }
        }
    }

    #[test]
    fn the_fill_reducing_order_takes_less_work_than_a_band() {
        // 20x20 grid with diagonal neighbours: a band order (row by row)
        // stores 21 blocks below the diagonal per column, 400·21·22/2
        // block products; the chosen order needs under four fifths of that.
        let (_, nbrs) = grid_problem(20, 20, 1);
        let sym = Symbolic::new(&nbrs);
        let structure: Vec<Vec<usize>> = (0..sym.m()).map(|j| sym.col(j).to_vec()).collect();
        let band = 400 * 21 * 22 / 2;
        assert!(
            work(&structure) * 5 < band * 4,
            "{} vs {band}",
            work(&structure)
        );
        // Every edge is in the pattern.
        for (v, n) in nbrs.iter().enumerate() {
            for &u in n {
                let (a, b) = (sym.position[v], sym.position[u]);
                assert!(sym.slot(a.max(b), a.min(b)).is_some());
            }
        }
        // Nested dissection is a permutation, and so is its elimination.
        let adj = sorted_adjacency(&nbrs);
        let mut nd = nested_dissection(&adj);
        nd.sort_unstable();
        assert_eq!(nd, (0..400).collect::<Vec<_>>());
    }

    #[test]
    fn an_indefinite_matrix_is_refused() {
        let sym = Symbolic::new(&[vec![1], vec![0]]);
        let mut a = vec![Block::identity(); sym.slots()];
        a[2] = Block::identity() * 2.0; // |off-diagonal| > diagonal
        assert!(Factor::new(&sym, a).is_none());
    }
}
