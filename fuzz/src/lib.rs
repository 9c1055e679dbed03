//! Fuzz entry points of tofwave's untrusted-input parsers.
//!
//! The code lives in `entry.rs`, which `tests/suite/fuzz_corpus.rs` also
//! compiles (`#[path]`), so the stable regression test replays the committed
//! corpora through exactly the functions the fuzz targets call.

pub mod entry;
