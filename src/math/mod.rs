//! Numerics that know nothing about lidar: the bottom layer with `frame`,
//! depended on by `dsp`, `detect`, `physics` and above, depending on `std`
//! only. One home for each routine, so that a fix or a faster kernel reaches
//! every caller.

/// Gaussian tail Q(x), its logarithm and inverse, φ, erf/erfc; per-cell probabilities.
pub mod special;
/// e^x in exactly rounded arithmetic: inlined, vectorisable, the same bits on every CPU.
pub mod exp;
/// Incomplete beta/gamma, binomial and Poisson intervals, Jarque-Bera, Student-t quantile.
pub mod stats;
/// Dense linear solve (Gaussian elimination with partial pivoting).
pub mod linalg;
/// Sums in a fixed order of eight lanes: vectorised, the same bits on every CPU.
pub mod sum;
/// Lag-product sums and the pooled autocovariance accumulator.
pub mod autocov;
/// Roots of monotone functions: Illinois false position from a bracket or a guess.
pub mod roots;
/// Selection: median, high median, trimmed mean, MAD sigma.
pub mod select;
/// Robust sigma of samples on a quantisation grid (where the MAD is itself quantised).
pub mod quantised;
/// Integer ADC codes' extremes, grid and exact power sums.
pub mod code_stats;
