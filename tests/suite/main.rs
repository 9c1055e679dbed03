//! The integration tests, as one test binary (one link instead of one per
//! file: the cold CI build is minutes shorter). Each file is a module; run
//! one with `cargo test --release --test suite <module>::`.
//! `tests/alloc.rs` stays its own binary: it installs a counting global
//! allocator.

#[path = "../common/mod.rs"]
mod common;

mod averaging;
mod bench;
mod capture;
mod captures_scene;
mod cfar;
mod cli;
mod cluster;
mod dashboard;
mod coverage;
mod denoise;
mod deploy;
mod detection;
mod dsp;
mod duplicates;
mod events;
mod false_alarm;
mod false_alarm_coloured;
mod forgetting;
mod fuzz_corpus;
mod golden;
mod layering;
mod math_oracle;
mod numerics;
mod operate;
mod physics;
mod pipeline;
mod plot;
mod rough_edges;
mod roundtrip;
mod seedgen_check;
mod service;
mod soak;
mod stability;
mod threads;
mod walk;
mod whiten;
