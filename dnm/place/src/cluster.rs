//! Community detection on an undirected weighted graph: modularity, Newman's fast greedy
//! agglomeration in the Clauset–Newman–Moore form, and a Louvain-style refinement that only
//! ever raises modularity. Constraints: nodes pinned to a group (two groups never share a
//! community), a capacity (nodes per community) and a maximum number of communities.

use std::cmp::Ordering;
use std::collections::{BinaryHeap, HashMap};

/// An undirected graph with positive edge weights; parallel edges are summed.
#[derive(Debug, Clone, Default)]
pub struct Graph {
    adj: Vec<HashMap<usize, f64>>,
    /// Weighted degree of each node.
    degree: Vec<f64>,
    /// Total edge weight (each edge once).
    total: f64,
}

impl Graph {
    pub fn new(nodes: usize) -> Self {
        Self {
            adj: vec![HashMap::new(); nodes],
            degree: vec![0.0; nodes],
            total: 0.0,
        }
    }

    /// Adds weight `w` between `a` and `b` (self-loops and non-positive weights are ignored:
    /// a module's link to itself never crosses DNMs).
    pub fn add_edge(&mut self, a: usize, b: usize, w: f64) {
        if a == b || w <= 0.0 || !w.is_finite() {
            return;
        }
        *self.adj[a].entry(b).or_default() += w;
        *self.adj[b].entry(a).or_default() += w;
        self.degree[a] += w;
        self.degree[b] += w;
        self.total += w;
    }

    pub fn nodes(&self) -> usize {
        self.adj.len()
    }

    pub fn total_weight(&self) -> f64 {
        self.total
    }

    pub fn neighbors(&self, v: usize) -> impl Iterator<Item = (usize, f64)> + '_ {
        self.adj[v].iter().map(|(&u, &w)| (u, w))
    }

    /// Newman's modularity of `community` (node → community id):
    /// Q = Σ_c [ L_c / m − (D_c / 2m)² ], with L_c the weight inside c, D_c its total degree.
    pub fn modularity(&self, community: &[usize]) -> f64 {
        if self.total <= 0.0 {
            return 0.0;
        }
        let k = community.iter().copied().max().map_or(0, |c| c + 1);
        let (mut inside, mut degree) = (vec![0.0; k], vec![0.0; k]);
        for (v, nbrs) in self.adj.iter().enumerate() {
            degree[community[v]] += self.degree[v];
            for (&u, &w) in nbrs {
                if community[u] == community[v] {
                    inside[community[v]] += w / 2.0;
                }
            }
        }
        let m = self.total;
        inside
            .iter()
            .zip(&degree)
            .map(|(l, d)| l / m - (d / (2.0 * m)).powi(2))
            .sum()
    }

    /// Weight of the edges whose ends are in different communities.
    pub fn cut(&self, community: &[usize]) -> f64 {
        let mut cut = 0.0;
        for (v, nbrs) in self.adj.iter().enumerate() {
            for (&u, &w) in nbrs {
                if u > v && community[u] != community[v] {
                    cut += w;
                }
            }
        }
        cut
    }
}

/// What a clustering must respect.
#[derive(Debug, Clone, Default)]
pub struct Constraints {
    /// Per node: the group it is pinned to (e.g. a DNM index). Nodes of different groups never
    /// share a community; nodes of one group always do.
    pub pinned: Vec<Option<usize>>,
    /// Most nodes in one community.
    pub capacity: Option<usize>,
    /// Most communities.
    pub max_communities: Option<usize>,
}

/// Why no clustering fits the constraints.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ClusterError {
    #[error(
        "{groups} pinned groups must stay apart but at most {max} communities are allowed; raise the maximum or unpin modules"
    )]
    TooManyPins { groups: usize, max: usize },
    #[error(
        "pinned group {group} has {nodes} members, more than the capacity of {capacity}; raise the capacity or pin fewer modules there"
    )]
    PinnedOverCapacity {
        group: usize,
        nodes: usize,
        capacity: usize,
    },
    #[error(
        "{nodes} modules do not fit in {max} communities of at most {capacity}; raise the capacity or the maximum"
    )]
    DoesNotFit {
        nodes: usize,
        max: usize,
        capacity: usize,
    },
}

/// A clustering and how it was reached.
#[derive(Debug, Clone)]
pub struct Clustering {
    /// Node → community, numbered 0.. in order of first appearance.
    pub community: Vec<usize>,
    pub modularity: f64,
    /// Modularity after the initial partition and after each merge, in order.
    pub history: Vec<f64>,
}

impl Clustering {
    pub fn communities(&self) -> usize {
        self.community.iter().copied().max().map_or(0, |c| c + 1)
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
struct Candidate {
    dq: f64,
    a: usize,
    b: usize,
}

impl Eq for Candidate {}

impl Ord for Candidate {
    fn cmp(&self, other: &Self) -> Ordering {
        self.dq
            .total_cmp(&other.dq)
            // Deterministic among equal gains: prefer lower ids.
            .then_with(|| other.a.cmp(&self.a))
            .then_with(|| other.b.cmp(&self.b))
    }
}

impl PartialOrd for Candidate {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}

/// Renumbers communities 0.. in order of first appearance.
fn compact(community: &mut [usize]) {
    let mut map = HashMap::new();
    for c in community.iter_mut() {
        let next = map.len();
        *c = *map.entry(*c).or_insert(next);
    }
}

fn check(g: &Graph, c: &Constraints) -> Result<(), ClusterError> {
    let mut groups: HashMap<usize, usize> = HashMap::new();
    for p in c.pinned.iter().take(g.nodes()).flatten() {
        *groups.entry(*p).or_default() += 1;
    }
    if let Some(max) = c.max_communities
        && groups.len() > max
    {
        return Err(ClusterError::TooManyPins {
            groups: groups.len(),
            max,
        });
    }
    if let Some(cap) = c.capacity {
        if let Some((&group, &nodes)) = groups.iter().filter(|(_, n)| **n > cap).min() {
            return Err(ClusterError::PinnedOverCapacity {
                group,
                nodes,
                capacity: cap,
            });
        }
        let max = c.max_communities.unwrap_or(usize::MAX);
        if cap.saturating_mul(max) < g.nodes() {
            return Err(ClusterError::DoesNotFit {
                nodes: g.nodes(),
                max,
                capacity: cap,
            });
        }
    }
    Ok(())
}

/// Clauset–Newman–Moore greedy agglomeration: start from singletons (pinned nodes of one group
/// together), repeatedly merge the two adjacent communities whose merge raises modularity most,
/// stop when no merge raises it (or, under `max_communities`, when few enough remain).
/// A max-heap of candidate gains with lazy invalidation and per-community gain maps give
/// O(m d log n).
pub fn greedy(g: &Graph, c: &Constraints) -> Result<Clustering, ClusterError> {
    check(g, c)?;
    let mut state = Agglomeration::new(g, c);
    state.merge_adjacent();
    state.merge_remaining()?;
    Ok(state.finish())
}

/// The state of [`greedy`]'s agglomeration. A community is named by a node id: the first node
/// of its pinned group, or the node it started from; merges keep one of the two ids.
#[derive(Debug)]
struct Agglomeration<'a> {
    g: &'a Graph,
    c: &'a Constraints,
    /// Node → its initial community.
    community: Vec<usize>,
    /// Per community: the group pinned to it, if any.
    pin: Vec<Option<usize>>,
    /// Per community: how many nodes it holds.
    size: Vec<usize>,
    /// Per community: a_i, its total degree as a fraction of 2m.
    a: Vec<f64>,
    /// dq[i][j] = 2 (e_ij − a_i a_j) for adjacent communities.
    dq: Vec<HashMap<usize, f64>>,
    /// Candidate merges of adjacent communities; stale entries are skipped when popped.
    heap: BinaryHeap<Candidate>,
    /// Per community: not merged into another (yet).
    alive: Vec<bool>,
    /// Communities alive.
    count: usize,
    /// Modularity of the current partition.
    q: f64,
    /// Modularity after the initial partition and after each merge, in order.
    history: Vec<f64>,
    /// `parent[i]`: the community that i was merged into (i itself while alive), for the final
    /// labels.
    parent: Vec<usize>,
}

impl<'a> Agglomeration<'a> {
    /// The initial partition, its modularity and the gains of merging adjacent communities.
    fn new(g: &'a Graph, c: &'a Constraints) -> Self {
        let n = g.nodes();
        let two_m = 2.0 * g.total;
        // Initial communities: one per node, except pinned groups which start merged.
        let community = initial_communities(n, &c.pinned);
        let mut pin: Vec<Option<usize>> = vec![None; n];
        let mut size = vec![0usize; n];
        let mut a = vec![0.0f64; n];
        for v in 0..n {
            size[community[v]] += 1;
            if two_m > 0.0 {
                a[community[v]] += g.degree[v] / two_m;
            }
            if let Some(p) = c.pinned.get(v).copied().flatten() {
                pin[community[v]] = Some(p);
            }
        }
        let e = between_fractions(g, &community, two_m);
        let alive: Vec<bool> = (0..n).map(|v| community[v] == v).collect();
        let count = alive.iter().filter(|x| **x).count();
        let q = g.modularity(&community);
        let (dq, heap) = initial_gains(&e, &a);
        Self {
            g,
            c,
            parent: community.clone(),
            community,
            pin,
            size,
            a,
            dq,
            heap,
            alive,
            count,
            q,
            history: vec![q],
        }
    }

    /// Whether communities `i` and `j` may merge: not two different pins, and within capacity.
    /// Never becomes true once false: sizes only grow, pins only appear.
    fn compatible(&self, i: usize, j: usize) -> bool {
        let pins_ok = match (self.pin[i], self.pin[j]) {
            (Some(x), Some(y)) => x == y,
            _ => true,
        };
        pins_ok
            && self
                .c
                .capacity
                .is_none_or(|cap| self.size[i] + self.size[j] <= cap)
    }

    /// More communities remain than `max_communities` allows.
    fn must_shrink(&self) -> bool {
        self.c.max_communities.is_some_and(|max| self.count > max)
    }

    /// The greedy phase: merges the adjacent pair of largest gain while a merge raises
    /// modularity (or while there are too many communities).
    fn merge_adjacent(&mut self) {
        while let Some(Candidate { dq: d, a: i, b: j }) = self.heap.pop() {
            if !self.alive[i]
                || !self.alive[j]
                || self.dq[i]
                    .get(&j)
                    .is_none_or(|x| x.to_bits() != d.to_bits())
            {
                continue; // stale
            }
            if d <= 0.0 && !self.must_shrink() {
                break;
            }
            if !self.compatible(i, j) {
                continue; // never becomes compatible: sizes only grow, pins only appear
            }
            // Merge the smaller gain map into the larger one.
            let (keep, gone) = if self.dq[i].len() >= self.dq[j].len() {
                (i, j)
            } else {
                (j, i)
            };
            let gone_map = std::mem::take(&mut self.dq[gone]);
            let keep_map = std::mem::take(&mut self.dq[keep]);
            let merged = merged_gains(&keep_map, &gone_map, keep, gone, &self.a);
            for (&k, &v) in &merged {
                self.dq[k].remove(&gone);
                self.dq[k].insert(keep, v);
                let (x, y) = if keep < k { (keep, k) } else { (k, keep) };
                self.heap.push(Candidate { dq: v, a: x, b: y });
            }
            self.dq[keep] = merged;
            self.absorb(keep, gone, d);
            self.a[gone] = 0.0;
        }
    }

    /// Still too many (disconnected parts, or merges the constraints forbid): merges the
    /// compatible pair that costs least, adjacent or not, until few enough remain.
    fn merge_remaining(&mut self) -> Result<(), ClusterError> {
        while self.must_shrink() {
            let Some((d, keep, gone)) = self.cheapest_pair() else {
                let n = self.g.nodes();
                return Err(ClusterError::DoesNotFit {
                    nodes: n,
                    max: self.c.max_communities.unwrap_or(self.count),
                    capacity: self.c.capacity.unwrap_or(n),
                });
            };
            let gone_map = std::mem::take(&mut self.dq[gone]);
            for (k, dg) in gone_map {
                if k == keep {
                    continue;
                }
                let v = self.dq[keep]
                    .get(&k)
                    .map_or(dg - 2.0 * self.a[keep] * self.a[k], |dk| dk + dg);
                self.dq[keep].insert(k, v);
                self.dq[k].remove(&gone);
                self.dq[k].insert(keep, v);
            }
            self.dq[keep].remove(&gone);
            self.absorb(keep, gone, d);
        }
        Ok(())
    }

    /// The compatible pair of live communities whose merge gains most (costs least), adjacent
    /// or not, as `(gain, i, j)` with `i < j`; the first found among equal gains.
    fn cheapest_pair(&self) -> Option<(f64, usize, usize)> {
        let live: Vec<usize> = (0..self.g.nodes()).filter(|&i| self.alive[i]).collect();
        let mut best: Option<(f64, usize, usize)> = None;
        for (x, &i) in live.iter().enumerate() {
            for &j in &live[x + 1..] {
                if !self.compatible(i, j) {
                    continue;
                }
                let d = self.dq[i]
                    .get(&j)
                    .copied()
                    .unwrap_or(-2.0 * self.a[i] * self.a[j]);
                if best.is_none_or(|(b, _, _)| d > b) {
                    best = Some((d, i, j));
                }
            }
        }
        best
    }

    /// Merges community `gone` into `keep`, which gains `d` modularity; the gain maps are the
    /// caller's to update.
    fn absorb(&mut self, keep: usize, gone: usize, d: f64) {
        self.a[keep] += self.a[gone];
        self.size[keep] += self.size[gone];
        self.pin[keep] = self.pin[keep].or(self.pin[gone]);
        self.alive[gone] = false;
        self.parent[gone] = keep;
        self.count -= 1;
        self.q += d;
        self.history.push(self.q);
    }

    /// Final labels: each node's community after the merges, isolated nodes placed, numbered
    /// 0.. in order of first appearance.
    fn finish(self) -> Clustering {
        let root = |mut x: usize| {
            while self.parent[x] != x {
                x = self.parent[x];
            }
            x
        };
        let mut labels: Vec<usize> = self.community.iter().map(|&c| root(c)).collect();
        place_isolated(self.g, self.c, &mut labels);
        compact(&mut labels);
        let modularity = self.g.modularity(&labels);
        Clustering {
            community: labels,
            modularity,
            history: self.history,
        }
    }
}

/// Node → initial community: each node its own, except that the nodes pinned to one group all
/// start in the community of its first node.
fn initial_communities(n: usize, pinned: &[Option<usize>]) -> Vec<usize> {
    let mut community: Vec<usize> = (0..n).collect();
    let mut group_first: HashMap<usize, usize> = HashMap::new();
    for (v, slot) in community.iter_mut().enumerate() {
        if let Some(p) = pinned.get(v).copied().flatten() {
            *slot = *group_first.entry(p).or_insert(v);
        }
    }
    community
}

/// e_ij between communities (each direction), as fractions of 2m.
fn between_fractions(g: &Graph, community: &[usize], two_m: f64) -> Vec<HashMap<usize, f64>> {
    let mut e: Vec<HashMap<usize, f64>> = vec![HashMap::new(); g.nodes()];
    for v in 0..g.nodes() {
        for (u, w) in g.neighbors(v) {
            let (cv, cu) = (community[v], community[u]);
            if cv != cu {
                *e[cv].entry(cu).or_default() += w / two_m;
            }
        }
    }
    e
}

/// dq[i][j] = 2 (e_ij − a_i a_j) for adjacent communities, and a heap holding each pair once.
fn initial_gains(
    e: &[HashMap<usize, f64>],
    a: &[f64],
) -> (Vec<HashMap<usize, f64>>, BinaryHeap<Candidate>) {
    let mut dq: Vec<HashMap<usize, f64>> = vec![HashMap::new(); e.len()];
    let mut heap = BinaryHeap::new();
    for i in 0..e.len() {
        for (&j, &eij) in &e[i] {
            let d = 2.0 * (eij - a[i] * a[j]);
            dq[i].insert(j, d);
            if i < j {
                heap.push(Candidate { dq: d, a: i, b: j });
            }
        }
    }
    (dq, heap)
}

/// The gain map of `keep` after `gone` merges into it, from the two maps before: a neighbour
/// of both gains the sum, a neighbour of one loses what it would have gained by joining the
/// other, 2 a_other a_k.
fn merged_gains(
    keep_map: &HashMap<usize, f64>,
    gone_map: &HashMap<usize, f64>,
    keep: usize,
    gone: usize,
    a: &[f64],
) -> HashMap<usize, f64> {
    let mut merged: HashMap<usize, f64> = HashMap::with_capacity(keep_map.len() + gone_map.len());
    for (&k, &dk) in keep_map {
        if k == gone {
            continue;
        }
        let v = match gone_map.get(&k) {
            Some(&dg) => dk + dg,
            None => dk - 2.0 * a[gone] * a[k],
        };
        merged.insert(k, v);
    }
    for (&k, &dg) in gone_map {
        if k == keep || keep_map.contains_key(&k) {
            continue;
        }
        merged.insert(k, dg - 2.0 * a[keep] * a[k]);
    }
    merged
}

/// Modules with no links change no modularity wherever they go: puts each unpinned one in
/// the largest community that has room, instead of a DNM of its own.
fn place_isolated(g: &Graph, c: &Constraints, labels: &mut [usize]) {
    let mut sizes: HashMap<usize, usize> = HashMap::new();
    for &l in labels.iter() {
        *sizes.entry(l).or_default() += 1;
    }
    for (v, label) in labels.iter_mut().enumerate() {
        let isolated = g.degree[v] == 0.0
            && c.pinned.get(v).copied().flatten().is_none()
            && sizes.get(label) == Some(&1);
        if !isolated {
            continue;
        }
        let own = *label;
        let target = sizes
            .iter()
            .filter(|(l, s)| **l != own && c.capacity.is_none_or(|cap| **s < cap))
            .max_by_key(|(l, s)| (**s, std::cmp::Reverse(**l)))
            .map(|(l, _)| *l);
        if let Some(t) = target {
            sizes.remove(&own);
            *sizes.entry(t).or_default() += 1;
            *label = t;
        }
    }
}

/// Louvain's local moving: each unpinned node moves to the neighbouring community that raises
/// modularity most, while any move raises it; constraints hold throughout. Never lowers
/// modularity. Returns the number of moves.
pub fn refine(g: &Graph, c: &Constraints, clustering: &mut Clustering) -> usize {
    let n = g.nodes();
    let m = g.total;
    if m <= 0.0 {
        return 0;
    }
    let comm = &mut clustering.community;
    let k = comm.iter().copied().max().map_or(0, |x| x + 1);
    let mut tot = vec![0.0; k];
    let mut size = vec![0usize; k];
    let mut pin: Vec<Option<usize>> = vec![None; k];
    for v in 0..n {
        tot[comm[v]] += g.degree[v];
        size[comm[v]] += 1;
        if let Some(p) = c.pinned.get(v).copied().flatten() {
            pin[comm[v]] = Some(p);
        }
    }
    let mut moves = 0;
    let mut improved = true;
    let mut passes = 0;
    while improved && passes < 100 {
        improved = false;
        passes += 1;
        for v in 0..n {
            if c.pinned.get(v).copied().flatten().is_some() {
                continue;
            }
            let own = comm[v];
            let kv = g.degree[v];
            // Ordered, so ties go to the lowest community id and results repeat.
            let mut links: std::collections::BTreeMap<usize, f64> = Default::default();
            for (u, w) in g.neighbors(v) {
                *links.entry(comm[u]).or_default() += w;
            }
            // Gain of putting v (taken out of `own`) into community x.
            let gain = |x: usize, tot_x: f64| {
                links.get(&x).copied().unwrap_or(0.0) / m - tot_x * kv / (2.0 * m * m)
            };
            let stay = gain(own, tot[own] - kv);
            let mut best = (stay, own);
            for (&x, _) in links.iter() {
                if x == own || c.capacity.is_some_and(|cap| size[x] + 1 > cap) {
                    continue;
                }
                let g_x = gain(x, tot[x]);
                if g_x > best.0 + 1e-12 {
                    best = (g_x, x);
                }
            }
            // A community must keep at least one node while it holds a pin.
            if best.1 != own && (size[own] > 1 || pin[own].is_none()) {
                let to = best.1;
                tot[own] -= kv;
                tot[to] += kv;
                size[own] -= 1;
                size[to] += 1;
                comm[v] = to;
                moves += 1;
                improved = true;
            }
        }
    }
    compact(comm);
    clustering.modularity = g.modularity(comm);
    moves
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two triangles joined by one edge.
    fn barbell() -> Graph {
        let mut g = Graph::new(6);
        for (a, b) in [(0, 1), (1, 2), (0, 2), (3, 4), (4, 5), (3, 5), (2, 3)] {
            g.add_edge(a, b, 1.0);
        }
        g
    }

    #[test]
    fn modularity_by_hand() {
        let g = barbell();
        // m = 7; each triangle: L = 3, D = 7 → 2 · (3/7 − (7/14)²) = 6/7 − 1/2.
        let q = g.modularity(&[0, 0, 0, 1, 1, 1]);
        assert!((q - (6.0 / 7.0 - 0.5)).abs() < 1e-12);
        assert!(g.modularity(&[0; 6]).abs() < 1e-12);
        assert_eq!(g.cut(&[0, 0, 0, 1, 1, 1]), 1.0);
        let c = greedy(&g, &Constraints::default()).unwrap();
        assert_eq!(c.community, [0, 0, 0, 1, 1, 1]);
        assert!((c.modularity - q).abs() < 1e-12);
    }

    #[test]
    fn unlinked_nodes_join_a_community_instead_of_their_own() {
        let mut g = Graph::new(8);
        for (a, b) in [(0, 1), (1, 2), (0, 2), (3, 4), (4, 5), (3, 5), (2, 3)] {
            g.add_edge(a, b, 1.0);
        }
        let c = greedy(&g, &Constraints::default()).unwrap();
        assert_eq!(c.communities(), 2);
        assert!((c.modularity - (6.0 / 7.0 - 0.5)).abs() < 1e-12);
    }

    #[test]
    fn pinned_groups_start_in_their_first_node() {
        let pinned = [None, Some(1), None, Some(1), Some(0)];
        assert_eq!(initial_communities(5, &pinned), [0, 1, 2, 1, 4]);
        // Nodes past the end of `pinned` are unpinned.
        assert_eq!(initial_communities(3, &[Some(0)]), [0, 1, 2]);
        assert_eq!(initial_communities(0, &[]), Vec::<usize>::new());
    }

    #[test]
    fn merged_gains_add_shared_neighbours_and_charge_the_others() {
        let a = [0.1, 0.2, 0.3, 0.4, 0.5];
        let keep_map = HashMap::from([(1, 0.9), (2, 0.5), (4, 0.0625)]);
        let gone_map = HashMap::from([(0, 0.9), (2, 0.25), (3, 0.125)]);
        let merged = merged_gains(&keep_map, &gone_map, 0, 1, &a);
        let expected = HashMap::from([
            (2, 0.5 + 0.25),
            (3, 0.125 - 2.0 * a[0] * a[3]),
            (4, 0.0625 - 2.0 * a[1] * a[4]),
        ]);
        assert_eq!(merged, expected);
    }

    #[test]
    fn initial_state_merges_pinned_groups() {
        let g = barbell();
        let c = Constraints {
            pinned: vec![Some(0), None, None, None, None, Some(0)],
            capacity: Some(3),
            ..Constraints::default()
        };
        let s = Agglomeration::new(&g, &c);
        assert_eq!(s.community, [0, 1, 2, 3, 4, 0]);
        assert_eq!((s.count, s.size[0], s.pin[0]), (5, 2, Some(0)));
        assert_eq!(s.history, [g.modularity(&s.community)]);
        // 0 and 5 are adjacent to 1, 2, 3 and 4.
        assert_eq!(s.dq[0].len(), 4);
        assert!(s.compatible(0, 1));
        assert!(s.compatible(1, 2));
        let mut s = s;
        s.size[1] = 2;
        assert!(
            !s.compatible(0, 1),
            "2 + 2 nodes are over the capacity of 3"
        );
    }

    #[test]
    fn leftover_components_merge_at_least_cost() {
        // Two separate edges: no adjacent merge gains, so only `max_communities` joins them.
        let mut g = Graph::new(4);
        g.add_edge(0, 1, 1.0);
        g.add_edge(2, 3, 1.0);
        let c = Constraints {
            max_communities: Some(1),
            ..Constraints::default()
        };
        let mut s = Agglomeration::new(&g, &c);
        s.merge_adjacent();
        // The adjacent merges gain (each keeps the lower id); then one more is forced.
        assert_eq!(s.count, 2);
        assert_eq!(s.cheapest_pair(), Some((-0.5, 0, 2)));
        s.merge_remaining().unwrap();
        assert_eq!(s.count, 1);
        assert_eq!(s.finish().community, [0; 4]);
    }

    #[test]
    fn isolated_nodes_join_the_largest_community_with_room() {
        let mut g = Graph::new(7);
        for (a, b) in [(0, 1), (1, 2), (0, 2), (3, 4)] {
            g.add_edge(a, b, 1.0);
        }
        let mut c = Constraints {
            pinned: vec![None, None, None, None, None, None, Some(0)],
            ..Constraints::default()
        };
        let mut labels = [0, 0, 0, 3, 3, 5, 6];
        place_isolated(&g, &c, &mut labels);
        // 6 is pinned: it stays.
        assert_eq!(labels, [0, 0, 0, 3, 3, 0, 6]);
        c.capacity = Some(3);
        let mut labels = [0, 0, 0, 3, 3, 5, 6];
        place_isolated(&g, &c, &mut labels);
        assert_eq!(labels, [0, 0, 0, 3, 3, 3, 6]);
        // Among equally large communities, the lowest label.
        let mut g = Graph::new(5);
        g.add_edge(0, 1, 1.0);
        g.add_edge(2, 3, 1.0);
        let mut labels = [2, 2, 0, 0, 4];
        place_isolated(&g, &Constraints::default(), &mut labels);
        assert_eq!(labels, [2, 2, 0, 0, 0]);
    }

    #[test]
    fn pins_and_limits_hold() {
        let g = barbell();
        let mut c = Constraints {
            pinned: vec![Some(0), None, None, None, None, Some(0)],
            ..Constraints::default()
        };
        let r = greedy(&g, &c).unwrap();
        assert_eq!(r.community[0], r.community[5]);
        c.pinned = vec![Some(0), Some(1), None, None, None, None];
        let r = greedy(&g, &c).unwrap();
        assert_ne!(r.community[0], r.community[1]);
        c.max_communities = Some(1);
        assert!(matches!(
            greedy(&g, &c),
            Err(ClusterError::TooManyPins { .. })
        ));
        let c = Constraints {
            capacity: Some(2),
            max_communities: Some(2),
            ..Constraints::default()
        };
        assert!(matches!(
            greedy(&g, &c),
            Err(ClusterError::DoesNotFit { .. })
        ));
        let c = Constraints {
            max_communities: Some(1),
            ..Constraints::default()
        };
        assert_eq!(greedy(&g, &c).unwrap().communities(), 1);
    }
}
