//! Criterion benches behind `mapless bench sim`: one vectorised step of 64 vehicles in env2,
//! per scan preset and ray caster; throughput in vehicle-steps.

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use mapless_sim::bench::{SCAN_PRESETS, bench_env, random_actions};
use mapless_sim::{RaycastMethod, VecStep};

const VEHICLES: usize = 64;

fn vec_step(c: &mut Criterion) {
    let mut g = c.benchmark_group("env2_vec_step");
    g.throughput(Throughput::Elements(VEHICLES as u64));
    for preset in SCAN_PRESETS {
        for method in [RaycastMethod::PerBeam, RaycastMethod::Fan] {
            let mut env = bench_env("env2", preset, method, VEHICLES).expect("env2 builds");
            let actions = random_actions(VEHICLES, 64, 1);
            let mut out = VecStep::default();
            let mut k = 0;
            let id = BenchmarkId::new(format!("{method:?}"), format!("{}beams", preset.beams));
            g.bench_function(id, |b| {
                b.iter(|| {
                    env.step(&actions[k * 2 * VEHICLES..(k + 1) * 2 * VEHICLES], &mut out).expect("valid actions");
                    k = (k + 1) % 64;
                })
            });
        }
    }
    g.finish();
}

criterion_group!(benches, vec_step);
criterion_main!(benches);
