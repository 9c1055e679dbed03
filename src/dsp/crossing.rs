//! Level crossings on a leading edge, with linear interpolation between samples.

/// Position (fractional sample index) where `x` first rises through `level`
/// going backwards from `peak` towards `start`: the last sample at or below
/// `level` before the peak, interpolated linearly to the next one.
/// `None` when every sample in `start..=peak` is above `level`.
pub fn rising_before(x: &[f64], level: f64, start: usize, peak: usize) -> Option<f64> {
    let mut k = peak;
    while k > start {
        if x[k - 1] <= level && x[k] > level {
            let f = (level - x[k - 1]) / (x[k] - x[k - 1]);
            return Some((k - 1) as f64 + f);
        }
        k -= 1;
    }
    None
}

/// First index in `start..end` where `x` rises through `level` (comparator
/// behaviour, as a leading-edge discriminator): fractional position.
pub fn first_rising(x: &[f64], level: f64, start: usize, end: usize) -> Option<f64> {
    let end = end.min(x.len());
    (start.max(1)..end).find(|&k| x[k - 1] <= level && x[k] > level).map(|k| {
        let f = (level - x[k - 1]) / (x[k] - x[k - 1]);
        (k - 1) as f64 + f
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn interpolates_linearly() {
        let x = [0.0, 0.0, 1.0, 3.0, 2.0];
        assert_eq!(rising_before(&x, 2.0, 0, 3), Some(2.5));
        assert_eq!(first_rising(&x, 0.5, 0, 5), Some(1.5));
        assert_eq!(rising_before(&x, -1.0, 0, 3), None);
    }
}
