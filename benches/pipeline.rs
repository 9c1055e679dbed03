//! Whole-pipeline throughput on 2500-sample i16 frames. Run: `cargo bench --bench pipeline`.

use criterion::{Criterion, criterion_group, criterion_main};

fn pipeline(_c: &mut Criterion) {}

criterion_group!(benches, pipeline);
criterion_main!(benches);
