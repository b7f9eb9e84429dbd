//! Criterion benchmarks for shocktwin live in this package's `[[bench]]`
//! targets; this library is empty on purpose (Cargo needs a target).
