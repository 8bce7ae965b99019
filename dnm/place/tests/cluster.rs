//! Clustering against hand-computed and published values, and its invariants.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests: failing loudly is right

use dnm_place::cluster::{ClusterError, Constraints, Graph, greedy, refine};
use proptest::prelude::*;

/// Zachary's karate club (34 members, 78 friendships), 1-based as published.
const KARATE: [(usize, usize); 78] = [
    (2, 1),
    (3, 1),
    (3, 2),
    (4, 1),
    (4, 2),
    (4, 3),
    (5, 1),
    (6, 1),
    (7, 1),
    (7, 5),
    (7, 6),
    (8, 1),
    (8, 2),
    (8, 3),
    (8, 4),
    (9, 1),
    (9, 3),
    (10, 3),
    (11, 1),
    (11, 5),
    (11, 6),
    (12, 1),
    (13, 1),
    (13, 4),
    (14, 1),
    (14, 2),
    (14, 3),
    (14, 4),
    (17, 6),
    (17, 7),
    (18, 1),
    (18, 2),
    (20, 1),
    (20, 2),
    (22, 1),
    (22, 2),
    (26, 24),
    (26, 25),
    (28, 3),
    (28, 24),
    (28, 25),
    (29, 3),
    (30, 24),
    (30, 27),
    (31, 2),
    (31, 9),
    (32, 1),
    (32, 25),
    (32, 26),
    (32, 29),
    (33, 3),
    (33, 9),
    (33, 15),
    (33, 16),
    (33, 19),
    (33, 21),
    (33, 23),
    (33, 24),
    (33, 30),
    (33, 31),
    (33, 32),
    (34, 9),
    (34, 10),
    (34, 14),
    (34, 15),
    (34, 16),
    (34, 19),
    (34, 20),
    (34, 21),
    (34, 23),
    (34, 24),
    (34, 27),
    (34, 28),
    (34, 29),
    (34, 30),
    (34, 31),
    (34, 32),
    (34, 33),
];

fn karate() -> Graph {
    let mut g = Graph::new(34);
    for (a, b) in KARATE {
        g.add_edge(a - 1, b - 1, 1.0);
    }
    g
}

#[test]
fn karate_club_greedy_matches_the_published_value() {
    let g = karate();
    assert_eq!(g.total_weight(), 78.0);
    let c = greedy(&g, &Constraints::default()).unwrap();
    // Clauset, Newman & Moore's greedy: Q = 0.3807 with 3 communities.
    assert!((c.modularity - 0.3807).abs() < 5e-5, "{}", c.modularity);
    assert_eq!(c.communities(), 3);
    // The running total of merge gains equals the modularity recomputed from scratch.
    assert!((c.history.last().unwrap() - c.modularity).abs() < 1e-9);
}

#[test]
fn karate_club_refinement_approaches_the_optimum() {
    let g = karate();
    let mut c = greedy(&g, &Constraints::default()).unwrap();
    let before = c.modularity;
    refine(&g, &Constraints::default(), &mut c);
    // Never above the proven optimum 0.4198; never below the greedy result.
    assert!(c.modularity >= before - 1e-12);
    assert!(c.modularity <= 0.4198 + 5e-5, "{}", c.modularity);
    // The proven optimum (Brandes et al. 2008, four communities) scores 0.4198 here too.
    let optimum: [usize; 34] = [
        0, 0, 0, 0, 1, 1, 1, 0, 2, 2, 1, 0, 0, 0, 2, 2, 1, 0, 2, 0, 2, 0, 2, 3, 3, 3, 2, 3, 3, 2,
        2, 3, 2, 2,
    ];
    assert!(
        (g.modularity(&optimum) - 0.4198).abs() < 5e-5,
        "{}",
        g.modularity(&optimum)
    );
}

#[test]
fn weighted_modularity_by_hand() {
    // A path a - b - c with weights 3 and 1: m = 4, degrees 3, 4, 1.
    let mut g = Graph::new(3);
    g.add_edge(0, 1, 3.0);
    g.add_edge(1, 2, 1.0);
    // {a, b}, {c}: L = 3/4 − (7/8)² + 0 − (1/8)² = 0.75 − 0.765625 − 0.015625 = −0.03125.
    assert!((g.modularity(&[0, 0, 1]) + 0.03125).abs() < 1e-12);
    assert!(g.modularity(&[0, 0, 0]).abs() < 1e-12);
}

#[test]
fn impossible_constraints_fail_clearly() {
    let g = karate();
    let c = Constraints {
        pinned: (0..34).map(|i| (i < 5).then_some(i)).collect(),
        max_communities: Some(3),
        ..Constraints::default()
    };
    let e = greedy(&g, &c).unwrap_err();
    assert!(matches!(e, ClusterError::TooManyPins { groups: 5, max: 3 }));
    assert!(e.to_string().contains("raise the maximum or unpin"));
    let c = Constraints {
        capacity: Some(10),
        max_communities: Some(3),
        ..Constraints::default()
    };
    assert!(
        greedy(&g, &c)
            .unwrap_err()
            .to_string()
            .contains("do not fit")
    );
}

fn arb_graph() -> impl Strategy<Value = (usize, Vec<(usize, usize, f64)>)> {
    (2usize..25).prop_flat_map(|n| {
        (
            Just(n),
            prop::collection::vec((0..n, 0..n, 0.1f64..10.0), 1..80),
        )
    })
}

fn build(n: usize, edges: &[(usize, usize, f64)]) -> Graph {
    let mut g = Graph::new(n);
    for &(a, b, w) in edges {
        g.add_edge(a, b, w);
    }
    g
}

proptest! {
    #[test]
    fn merges_never_lower_modularity((n, edges) in arb_graph()) {
        let g = build(n, &edges);
        let c = greedy(&g, &Constraints::default()).unwrap();
        for w in c.history.windows(2) {
            prop_assert!(w[1] >= w[0] - 1e-12, "{:?}", c.history);
        }
        prop_assert!((c.history.last().unwrap() - c.modularity).abs() < 1e-9);
    }

    #[test]
    fn refinement_never_lowers_modularity((n, edges) in arb_graph(), cap in 1usize..10) {
        let g = build(n, &edges);
        let cons = Constraints { capacity: Some(cap.max(n.div_ceil(3))), ..Constraints::default() };
        let mut c = greedy(&g, &cons).unwrap();
        let before = c.modularity;
        refine(&g, &cons, &mut c);
        prop_assert!(c.modularity >= before - 1e-12);
        let mut sizes = vec![0; c.communities()];
        for &x in &c.community { sizes[x] += 1; }
        prop_assert!(sizes.iter().all(|s| *s <= cons.capacity.unwrap()));
    }

    #[test]
    fn pinned_nodes_stay_with_their_group_and_apart_from_others(
        (n, edges) in arb_graph(),
        pins in prop::collection::vec(prop::option::of(0usize..3), 25),
        max in 3usize..6,
    ) {
        let g = build(n, &edges);
        let cons = Constraints {
            pinned: pins[..n].to_vec(),
            max_communities: Some(max),
            ..Constraints::default()
        };
        let mut c = greedy(&g, &cons).unwrap();
        refine(&g, &cons, &mut c);
        prop_assert!(c.communities() <= max);
        for a in 0..n {
            for b in 0..n {
                if let (Some(x), Some(y)) = (cons.pinned[a], cons.pinned[b]) {
                    prop_assert_eq!(x == y, c.community[a] == c.community[b]);
                }
            }
        }
    }
}
