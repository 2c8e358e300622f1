//! Composition with covariance along chains of 2 to 20 links, and fusion of 2 and 4 paths.
//!
//! Run: `cargo bench --bench chain`.

use brokenray::chain::{Topology, compose_path, fuse};
use brokenray::geometry::{Mat6, Pose, PoseCov, Rotation, se3_exp};
use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use nalgebra::{Quaternion, Translation3, Vector6};
use std::hint::black_box;

/// Deterministic pseudo-random numbers in [-1, 1) (no RNG dependency in the hot loop).
fn lcg(state: &mut u64) -> f64 {
    *state = state
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    ((*state >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
}

fn link(state: &mut u64) -> PoseCov {
    let q = Quaternion::new(lcg(state) + 2.0, lcg(state), lcg(state), lcg(state));
    let pose = Pose::from_parts(
        Translation3::new(
            lcg(state) * 3000.0,
            lcg(state) * 3000.0,
            lcg(state) * 3000.0,
        ),
        Rotation::new_normalize(q),
    );
    let a = Mat6::from_fn(|_, _| lcg(state));
    PoseCov {
        pose,
        cov: a * a.transpose() * 1e-4 + Mat6::identity() * 1e-6,
    }
}

/// A chain of n links alternating forwards and inverted steps (as camera/marker relays do).
fn chain(n: usize) -> (Topology, Vec<PoseCov>) {
    let mut topo = Topology::new();
    let mut state = 42;
    for i in 0..n {
        let (a, b) = (format!("F{i}"), format!("F{}", i + 1));
        if i % 2 == 0 {
            topo.add_link(&format!("{b}_from_{a}"), &b, &a).unwrap();
        } else {
            topo.add_link(&format!("{a}_from_{b}"), &a, &b).unwrap();
        }
    }
    let links = (0..n).map(|_| link(&mut state)).collect();
    (topo, links)
}

fn bench_compose(c: &mut Criterion) {
    let mut group = c.benchmark_group("compose_with_covariance");
    for n in [2usize, 5, 10, 20] {
        let (topo, links) = chain(n);
        let path = topo
            .resolve("F0", &format!("F{n}"))
            .unwrap()
            .paths
            .remove(0);
        group.bench_with_input(BenchmarkId::from_parameter(n), &n, |b, _| {
            b.iter(|| compose_path(black_box(&path), |id| links[id.0]))
        });
    }
    group.finish();
}

fn bench_fuse(c: &mut Criterion) {
    let mut group = c.benchmark_group("fuse_paths");
    let mut state = 7;
    let truth = link(&mut state);
    for k in [2usize, 4] {
        let estimates: Vec<PoseCov> = (0..k)
            .map(|_| {
                let d = Vector6::from_fn(|_, _| lcg(&mut state) * 1e-3);
                let e = link(&mut state);
                PoseCov {
                    pose: se3_exp(&d) * truth.pose,
                    cov: e.cov,
                }
            })
            .collect();
        group.bench_with_input(BenchmarkId::from_parameter(k), &k, |b, _| {
            b.iter(|| fuse(black_box(&estimates), 0.999).unwrap())
        });
    }
    group.finish();
}

criterion_group!(benches, bench_compose, bench_fuse);
criterion_main!(benches);
