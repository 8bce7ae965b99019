//! Placement at scale: 10,000 modules and 50,000 links (200 planted groups of 50 modules, most
//! links inside a group), clustered by the greedy merge and refined. Target: under a second.
//!
//! Run: `cargo bench -p dnm-place --bench scale`.

#![allow(clippy::unwrap_used)] // a benchmark harness

use std::time::Instant;

use dnm_place::cluster::{Constraints, Graph, greedy, refine};

/// xorshift64*: a fixed, dependency-free random source.
struct Rng(u64);

impl Rng {
    fn next(&mut self, n: usize) -> usize {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        (self.0.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 33) as usize % n
    }
}

fn main() {
    let (nodes, links, group) = (10_000usize, 50_000usize, 50usize);
    let mut rng = Rng(0x9E37_79B9_7F4A_7C15);
    let mut g = Graph::new(nodes);
    for _ in 0..links {
        let a = rng.next(nodes);
        // 90 % of links stay inside the planted group, with traffic-like weights.
        let b = if rng.next(10) < 9 {
            a / group * group + rng.next(group)
        } else {
            rng.next(nodes)
        };
        g.add_edge(a, b, 1.0 + rng.next(100) as f64);
    }
    let mut best = f64::MAX;
    let mut summary = String::new();
    for _ in 0..3 {
        let t = Instant::now();
        let mut c = greedy(&g, &Constraints::default()).unwrap();
        let greedy_s = t.elapsed().as_secs_f64();
        let greedy_q = c.modularity;
        let moves = refine(&g, &Constraints::default(), &mut c);
        let total = t.elapsed().as_secs_f64();
        if total < best {
            best = total;
            summary = format!(
                "| {nodes} modules, {links} links | {:.3} s | {:.3} s | {greedy_q:.4} | {:.4} ({moves} moves) | {} |",
                greedy_s,
                total,
                c.modularity,
                c.communities()
            );
        }
    }
    println!("| graph | greedy | greedy + refine | modularity greedy | refined | communities |");
    println!("|---|---|---|---|---|---|");
    println!("{summary}");
    println!(
        "\ntarget: under 1 s for greedy + refine: {}",
        if best < 1.0 { "met" } else { "NOT met" }
    );
}
