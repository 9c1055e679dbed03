//! Receiver response models as continuous state-space systems, discretised
//! exactly.
//!
//! Every linear element of a channel (TIA pole, AC coupling, resonance,
//! digitiser bandwidth) is a small SISO state-space section; sections are
//! cascaded into one system `x' = A x + B u, y = C x + D u`. The discrete
//! system for a step `h` with the input held constant over each step
//! (zero-order hold) is `Φ = e^{A h}`, `Γ = ∫₀ʰ e^{A s} ds B`, both read off
//! one matrix exponential of the augmented matrix `[[A, B], [0, 0]] h`. That
//! is exact for piecewise-constant input whatever the ratio of time
//! constants, so a 0.1 ns rise against a 10 µs AC-coupling tail stays stable
//! and accurate (no explicit-Euler stiffness limit).

// Dense small-matrix kernels index several arrays in lockstep; index loops
// read closer to the maths than zipped iterators here.
#![allow(clippy::needless_range_loop)]

use crate::math::linalg;
use std::f64::consts::PI;

/// Dense row-major square matrix helpers for the small (≤ ~10 states) systems here.
mod mat {
    /// `n × n` identity.
    pub fn identity(n: usize) -> Vec<f64> {
        let mut m = vec![0.0; n * n];
        for i in 0..n {
            m[i * n + i] = 1.0;
        }
        m
    }

    /// `a · b`.
    pub fn mul(a: &[f64], b: &[f64], n: usize) -> Vec<f64> {
        let mut c = vec![0.0; n * n];
        for i in 0..n {
            for k in 0..n {
                let aik = a[i * n + k];
                if aik == 0.0 {
                    continue;
                }
                for j in 0..n {
                    c[i * n + j] += aik * b[k * n + j];
                }
            }
        }
        c
    }

    /// Max-row-sum norm.
    pub fn norm_inf(a: &[f64], n: usize) -> f64 {
        (0..n)
            .map(|i| a[i * n..(i + 1) * n].iter().map(|x| x.abs()).sum::<f64>())
            .fold(0.0, f64::max)
    }

    /// Matrix exponential by scaling and squaring with a Taylor series.
    /// After scaling the norm is ≤ 1/2, so 20 terms leave a truncation error
    /// below 0.5^21/21! ≈ 1e-26 relative: the result is accurate to rounding.
    pub fn expm(a: &[f64], n: usize) -> Vec<f64> {
        let norm = norm_inf(a, n);
        let mut s = 0u32;
        if norm > 0.5 {
            s = (norm / 0.5).log2().ceil() as u32;
        }
        let scale = 0.5f64.powi(s as i32);
        let a_s: Vec<f64> = a.iter().map(|x| x * scale).collect();
        let mut result = identity(n);
        let mut term = identity(n);
        for k in 1..=20 {
            term = mul(&term, &a_s, n);
            let inv = 1.0 / k as f64;
            for t in term.iter_mut() {
                *t *= inv;
            }
            for (r, t) in result.iter_mut().zip(&term) {
                *r += t;
            }
        }
        for _ in 0..s {
            result = mul(&result, &result, n);
        }
        result
    }
}

/// A continuous-time SISO state-space system `x' = A x + B u`, `y = C x + D u`.
#[derive(Debug, Clone, PartialEq)]
pub struct StateSpace {
    /// State count.
    pub n: usize,
    /// `A`, row-major `n × n`, 1/s.
    pub a: Vec<f64>,
    /// `B`, length `n`.
    pub b: Vec<f64>,
    /// `C`, length `n`.
    pub c: Vec<f64>,
    /// Direct feed-through `D`.
    pub d: f64,
}

impl StateSpace {
    /// The identity system (no states, `y = u`).
    pub fn identity() -> StateSpace {
        StateSpace {
            n: 0,
            a: vec![],
            b: vec![],
            c: vec![],
            d: 1.0,
        }
    }

    /// A single real pole at `bandwidth_hz` with unit DC gain: `ω/(s + ω)`.
    pub fn low_pass(bandwidth_hz: f64) -> StateSpace {
        let w = 2.0 * PI * bandwidth_hz;
        StateSpace {
            n: 1,
            a: vec![-w],
            b: vec![w],
            c: vec![1.0],
            d: 0.0,
        }
    }

    /// AC coupling with time constant `tau_s`: `s/(s + 1/τ)` (a zero at DC).
    pub fn ac_coupling(tau_s: f64) -> StateSpace {
        let w = 1.0 / tau_s;
        StateSpace {
            n: 1,
            a: vec![-w],
            b: vec![w],
            c: vec![-1.0],
            d: 1.0,
        }
    }

    /// A damped resonance added to the direct path:
    /// `1 + g (ω0/Q) s / (s² + (ω0/Q) s + ω0²)`. States are scaled by ω0 so
    /// the matrix entries stay of order ω0 (well conditioned).
    pub fn resonance(frequency_hz: f64, q: f64, amplitude: f64) -> StateSpace {
        let w0 = 2.0 * PI * frequency_hz;
        StateSpace {
            n: 2,
            a: vec![0.0, w0, -w0, -w0 / q],
            b: vec![0.0, w0],
            c: vec![0.0, amplitude / q],
            d: 1.0,
        }
    }

    /// `self` followed by `next` (series connection).
    pub fn then(&self, next: &StateSpace) -> StateSpace {
        let (n1, n2) = (self.n, next.n);
        let n = n1 + n2;
        let mut a = vec![0.0; n * n];
        for i in 0..n1 {
            for j in 0..n1 {
                a[i * n + j] = self.a[i * n1 + j];
            }
        }
        for i in 0..n2 {
            for j in 0..n1 {
                a[(n1 + i) * n + j] = next.b[i] * self.c[j];
            }
            for j in 0..n2 {
                a[(n1 + i) * n + n1 + j] = next.a[i * n2 + j];
            }
        }
        let mut b = self.b.clone();
        b.extend(next.b.iter().map(|x| x * self.d));
        let mut c: Vec<f64> = self.c.iter().map(|x| x * next.d).collect();
        c.extend_from_slice(&next.c);
        StateSpace {
            n,
            a,
            b,
            c,
            d: self.d * next.d,
        }
    }

    /// DC gain `D − C A⁻¹ B` (`None` when A is singular).
    pub fn dc_gain(&self) -> Option<f64> {
        if self.n == 0 {
            return Some(self.d);
        }
        let x = linalg::solve(&self.a, &self.b, self.n, 1e-300)?;
        Some(self.d - self.c.iter().zip(&x).map(|(c, x)| c * x).sum::<f64>())
    }

    /// Exact zero-order-hold discretisation at step `h_s`.
    pub fn discretise(&self, h_s: f64) -> Discrete {
        let n = self.n;
        let m = n + 1;
        let mut aug = vec![0.0; m * m];
        for i in 0..n {
            for j in 0..n {
                aug[i * m + j] = self.a[i * n + j] * h_s;
            }
            aug[i * m + n] = self.b[i] * h_s;
        }
        let e = mat::expm(&aug, m);
        let mut phi = vec![0.0; n * n];
        let mut gamma = vec![0.0; n];
        for i in 0..n {
            for j in 0..n {
                phi[i * n + j] = e[i * m + j];
            }
            gamma[i] = e[i * m + n];
        }
        Discrete {
            n,
            phi,
            gamma,
            c: self.c.clone(),
            d: self.d,
            h_s,
        }
    }

    /// `e^{A t}` (state transition over `t_s`).
    pub fn transition(&self, t_s: f64) -> Vec<f64> {
        let a: Vec<f64> = self.a.iter().map(|x| x * t_s).collect();
        mat::expm(&a, self.n)
    }
}

/// The exact discrete equivalent of a [`StateSpace`] for one step `h_s`.
#[derive(Debug, Clone, PartialEq)]
pub struct Discrete {
    /// State count.
    pub n: usize,
    /// `Φ = e^{A h}`, row-major.
    pub phi: Vec<f64>,
    /// `Γ = ∫₀ʰ e^{A s} ds B`.
    pub gamma: Vec<f64>,
    /// Output row `C`.
    pub c: Vec<f64>,
    /// Feed-through `D`.
    pub d: f64,
    /// Step, s.
    pub h_s: f64,
}

impl Discrete {
    /// One step: returns `y[k] = C x[k] + D u[k]` and advances `x` to `x[k+1]`.
    /// `scratch` must have length `n`.
    #[inline]
    pub fn step(&self, x: &mut [f64], u: f64, scratch: &mut [f64]) -> f64 {
        let n = self.n;
        let mut y = self.d * u;
        for i in 0..n {
            y += self.c[i] * x[i];
        }
        for i in 0..n {
            let row = &self.phi[i * n..(i + 1) * n];
            let mut s = self.gamma[i] * u;
            for j in 0..n {
                s += row[j] * x[j];
            }
            scratch[i] = s;
        }
        x.copy_from_slice(&scratch[..n]);
        y
    }

    /// Response to a unit step applied at t = 0 from rest, at t = k h for k in 0..len.
    pub fn step_response(&self, len: usize) -> Vec<f64> {
        let mut x = vec![0.0; self.n];
        let mut s = vec![0.0; self.n];
        (0..len).map(|_| self.step(&mut x, 1.0, &mut s)).collect()
    }

    /// Stationary state covariance for unit-variance white input held over each
    /// step: solves `P = Φ P Φᵀ + Γ Γᵀ` by the doubling iteration
    /// (`P ← P + M P Mᵀ`, `M ← M²`), which converges in log2 of the slowest time
    /// constant in steps.
    pub fn stationary_covariance(&self) -> Vec<f64> {
        let n = self.n;
        let mut p = vec![0.0; n * n];
        for i in 0..n {
            for j in 0..n {
                p[i * n + j] = self.gamma[i] * self.gamma[j];
            }
        }
        let mut m = self.phi.clone();
        for _ in 0..200 {
            let mp = mat::mul(&m, &p, n);
            let mt: Vec<f64> = (0..n * n).map(|k| m[(k % n) * n + k / n]).collect();
            let add = mat::mul(&mp, &mt, n);
            let mut change = 0.0f64;
            let mut size = 0.0f64;
            for (pi, ai) in p.iter_mut().zip(&add) {
                *pi += ai;
                change = change.max(ai.abs());
                size = size.max(pi.abs());
            }
            m = mat::mul(&m, &m, n);
            if change <= 1e-18 * size {
                break;
            }
        }
        p
    }

    /// Stationary output variance for unit-variance white input: `C P Cᵀ + D²`.
    pub fn stationary_output_variance(&self) -> f64 {
        let n = self.n;
        let p = self.stationary_covariance();
        let mut v = self.d * self.d;
        for i in 0..n {
            for j in 0..n {
                v += self.c[i] * p[i * n + j] * self.c[j];
            }
        }
        // The held input also correlates with the state only through the next
        // step, so no cross term: y[k] = C x[k] + D u[k] with x[k] ⟂ u[k].
        v
    }

    /// Lower-triangular Cholesky factor of the stationary covariance (for
    /// drawing a stationary initial state); tiny negative pivots from
    /// rounding are treated as zero.
    pub fn stationary_cholesky(&self) -> Vec<f64> {
        let n = self.n;
        let p = self.stationary_covariance();
        let mut l = vec![0.0; n * n];
        for j in 0..n {
            let mut s = p[j * n + j];
            for k in 0..j {
                s -= l[j * n + k] * l[j * n + k];
            }
            let diag = if s > 0.0 { s.sqrt() } else { 0.0 };
            l[j * n + j] = diag;
            for i in j + 1..n {
                let mut s = p[i * n + j];
                for k in 0..j {
                    s -= l[i * n + k] * l[j * n + k];
                }
                l[i * n + j] = if diag > 0.0 { s / diag } else { 0.0 };
            }
        }
        l
    }

    /// Impulse response of the held-input system (`len` samples): the
    /// response to u = [1, 0, 0, ...].
    pub fn impulse_response(&self, len: usize) -> Vec<f64> {
        let mut x = vec![0.0; self.n];
        let mut s = vec![0.0; self.n];
        (0..len)
            .map(|k| self.step(&mut x, if k == 0 { 1.0 } else { 0.0 }, &mut s))
            .collect()
    }
}

/// One channel's analogue chain in two linear stages with an optional
/// saturating amplifier between them: `input → stage1 → ×gain → clamp(±swing) → stage2`.
#[derive(Debug, Clone)]
pub struct Chain {
    /// The amplifier's own response (unit DC gain).
    pub stage1: StateSpace,
    /// Everything after the amplifier's output (AC coupling, ringing, digitiser bandwidth).
    pub stage2: StateSpace,
    /// Gain from the input quantity to the amplifier output, V per input unit.
    pub gain: f64,
    /// Symmetric output swing limit of the amplifier, V.
    pub swing_v: Option<f64>,
}

impl Chain {
    /// The whole chain as one linear system (ignoring the clamp), unit gain.
    pub fn linear(&self) -> StateSpace {
        self.stage1.then(&self.stage2)
    }
}

/// Runs a [`Chain`] over an input sampled on a fine grid (held over each
/// step), from initial states `x1`, `x2`; returns the output per step.
pub fn run_chain(
    chain: &Chain,
    d1: &Discrete,
    d2: &Discrete,
    x1: &mut [f64],
    x2: &mut [f64],
    input: &[f64],
) -> Vec<f64> {
    let mut s1 = vec![0.0; d1.n];
    let mut s2 = vec![0.0; d2.n];
    input
        .iter()
        .map(|&u| {
            let mut v = d1.step(x1, u, &mut s1) * chain.gain;
            if let Some(sw) = chain.swing_v {
                v = v.clamp(-sw, sw);
            }
            d2.step(x2, v, &mut s2)
        })
        .collect()
}

/// Advances the states of a chain with zero input over `t_s` exactly.
pub fn coast(chain: &Chain, x1: &mut [f64], x2: &mut [f64], t_s: f64) {
    // Stage 2 is driven by stage 1's (decaying) output: propagate the joint
    // linear system (the clamp is inactive once the input is zero and the
    // amplifier output decays below the swing, which the caller ensures by
    // coasting only through quiet gaps).
    let lin = chain.stage1.then(&scale_input(&chain.stage2, chain.gain));
    let e = lin.transition(t_s);
    let n = lin.n;
    let mut x: Vec<f64> = x1.iter().chain(x2.iter()).copied().collect();
    let mut y = vec![0.0; n];
    for i in 0..n {
        y[i] = (0..n).map(|j| e[i * n + j] * x[j]).sum();
    }
    x.copy_from_slice(&y);
    x1.copy_from_slice(&x[..x1.len()]);
    x2.copy_from_slice(&x[x1.len()..]);
}

/// `sys` with its input multiplied by `g`.
fn scale_input(sys: &StateSpace, g: f64) -> StateSpace {
    StateSpace {
        n: sys.n,
        a: sys.a.clone(),
        b: sys.b.iter().map(|b| b * g).collect(),
        c: sys.c.clone(),
        d: sys.d * g,
    }
}

/// Solves `(I − M) x = r` for the periodic steady state (`M = e^{A T}`).
pub fn periodic_state(chain: &Chain, period_s: f64, after_one_period: &[f64]) -> Vec<f64> {
    let lin = chain.stage1.then(&scale_input(&chain.stage2, chain.gain));
    let n = lin.n;
    let e = lin.transition(period_s);
    let mut a = vec![0.0; n * n];
    for i in 0..n {
        for j in 0..n {
            a[i * n + j] = if i == j { 1.0 } else { 0.0 } - e[i * n + j];
        }
    }
    linalg::solve(&a, after_one_period, n, 1e-300).unwrap_or_else(|| after_one_period.to_vec())
}
