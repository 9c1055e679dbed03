//! Roots of monotone scalar functions: a bracket grown from a guess, then
//! Illinois false position on it.
//!
//! Halving a bracket costs one evaluation per bit (60 for a double from a
//! unit bracket, more from a wide one); false position with the Illinois
//! modification (the retained end's value halved when the same end is kept
//! twice) converges superlinearly on smooth monotone functions, typically in
//! 6–10 evaluations to the bracket's last ulps, and never leaves the bracket.

/// Evaluations [`illinois`] spends at most before it returns the best point
/// of the bracket it holds.
const MAX_EVALUATIONS: usize = 200;

/// The root of `f` in `[lo, hi]`, where `f(lo)` and `f(hi)` have opposite
/// signs (either order), to `tol` absolute in x (0: to the last ulps).
/// With both ends of one sign it returns the end where |f| is smaller; a NaN
/// evaluation stops it at the midpoint of the bracket held then.
pub fn illinois(mut lo: f64, mut hi: f64, tol: f64, f: impl Fn(f64) -> f64) -> f64 {
    let (mut flo, mut fhi) = (f(lo), f(hi));
    if flo == 0.0 {
        return lo;
    }
    if fhi == 0.0 {
        return hi;
    }
    if flo.is_nan() || fhi.is_nan() {
        return 0.5 * (lo + hi);
    }
    if (flo > 0.0) == (fhi > 0.0) {
        return if flo.abs() <= fhi.abs() { lo } else { hi };
    }
    let mut side = 0i8;
    for _ in 0..MAX_EVALUATIONS {
        let width = (hi - lo).abs();
        if width <= tol || width <= 4.0 * f64::EPSILON * lo.abs().max(hi.abs()).max(f64::MIN_POSITIVE) {
            break;
        }
        let mut x = hi - fhi * (hi - lo) / (fhi - flo);
        // Outside the open bracket (rounding at its last ulps): halve instead.
        if !(x > lo.min(hi) && x < lo.max(hi)) {
            x = 0.5 * (lo + hi);
            if !(x > lo.min(hi) && x < lo.max(hi)) {
                break;
            }
        }
        let fx = f(x);
        if fx == 0.0 {
            return x;
        }
        if fx.is_nan() {
            break;
        }
        if (fx > 0.0) == (flo > 0.0) {
            (lo, flo) = (x, fx);
            if side == 1 {
                fhi *= 0.5;
            }
            side = 1;
        } else {
            (hi, fhi) = (x, fx);
            if side == -1 {
                flo *= 0.5;
            }
            side = -1;
        }
    }
    // Interpolated within the last bracket (the halved end values only
    // weight it; both ends still straddle the root).
    let x = hi - fhi * (hi - lo) / (fhi - flo);
    if x.is_finite() && x >= lo.min(hi) && x <= lo.max(hi) { x } else { 0.5 * (lo + hi) }
}

/// The root of a monotone `f`, searched from `guess`: the bracket
/// `guess ± step` is doubled outwards (within `[min, max]`) until `f` changes
/// sign, then solved by [`illinois`] to `tol` absolute in x (0: last ulps).
/// Where `f` keeps its sign up to a limit, that limit is returned.
pub fn illinois_from(guess: f64, step: f64, min: f64, max: f64, tol: f64, f: impl Fn(f64) -> f64) -> f64 {
    let guess = guess.clamp(min, max);
    let f0 = f(guess);
    if f0 == 0.0 || f0.is_nan() {
        return guess;
    }
    let mut step = step.abs().max(f64::MIN_POSITIVE);
    let mut near = guess;
    loop {
        // Walk the way that brings f towards zero: try one step each way first.
        let up = (near + step).min(max);
        let fu = f(up);
        if (fu > 0.0) != (f0 > 0.0) || fu == 0.0 {
            return illinois(near, up, tol, &f);
        }
        let down = (near - step).max(min);
        let fd = f(down);
        if (fd > 0.0) != (f0 > 0.0) || fd == 0.0 {
            return illinois(down, near, tol, &f);
        }
        if up >= max && down <= min {
            return if fu.abs() <= fd.abs() { up } else { down };
        }
        // Move the near end to the side where |f| fell.
        near = if fu.abs() < fd.abs() { up } else { down };
        step *= 2.0;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn halve(mut lo: f64, mut hi: f64, f: impl Fn(f64) -> f64) -> f64 {
        let flo = f(lo);
        for _ in 0..400 {
            let mid = 0.5 * (lo + hi);
            if mid <= lo || mid >= hi {
                break;
            }
            if (f(mid) > 0.0) == (flo > 0.0) {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        0.5 * (lo + hi)
    }

    #[test]
    fn illinois_equals_halving_on_smooth_monotone_functions() {
        let cases: [(&str, fn(f64) -> f64, f64, f64); 4] = [
            ("cubic", |x| x * x * x - 2.0, 0.0, 5.0),
            ("exp", |x| (x).exp() - 1e-30, -200.0, 10.0),
            ("decreasing", |x| (-x).exp_m1() + 0.3, -3.0, 30.0),
            ("flat then steep", |x| x.powi(9) - 0.5, 0.0, 2.0),
        ];
        for (name, f, lo, hi) in cases {
            let (a, b) = (illinois(lo, hi, 0.0, f), halve(lo, hi, f));
            assert!((a - b).abs() <= 1e-13 * b.abs().max(1.0), "{name}: {a} vs {b}");
        }
    }

    #[test]
    fn illinois_from_finds_brackets_on_either_side_of_the_guess() {
        let f = |x: f64| x.tanh() - 0.999_999;
        let want = 0.999_999f64.atanh();
        for guess in [-50.0, -1.0, 0.0, 3.0, 7.0, 40.0] {
            let x = illinois_from(guess, 0.5, -745.0, 745.0, 0.0, f);
            assert!((x - want).abs() < 1e-9, "guess {guess}: {x} vs {want}");
        }
        // No sign change within the limits: the limit nearer the root.
        assert_eq!(illinois_from(0.0, 1.0, -10.0, 10.0, 0.0, |x: f64| x - 100.0), 10.0);
        // Degenerate ends.
        assert_eq!(illinois(1.0, 2.0, 0.0, |x| x - 1.0), 1.0);
        assert_eq!(illinois(1.0, 2.0, 0.0, |x| x + 5.0), 1.0);
    }
}
