//! Cross-correlation of a signal with a fixed template ("valid" part only).

/// How the correlation is computed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CorrelationMethod {
    /// Direct sum per output sample.
    Direct,
    /// FFT overlap-save.
    Fft,
}

/// Correlates signals with one template; built once per scene.
#[derive(Debug, Clone)]
pub struct Correlator {
    taps: Vec<f64>,
}

impl Correlator {
    /// Plans for `template` and inputs up to `max_input_len` samples.
    pub fn new(template: &[f64], max_input_len: usize) -> Correlator {
        let _ = max_input_len;
        Correlator { taps: template.to_vec() }
    }

    /// The template.
    pub fn taps(&self) -> &[f64] {
        &self.taps
    }

    /// The method chosen.
    pub fn method(&self) -> CorrelationMethod {
        CorrelationMethod::Direct
    }

    /// `out[k] = Σ_j taps[j] * x[k + j]` for `k` in `0..=x.len() - taps.len()`;
    /// `out` is cleared (and left empty when `x` is shorter than the template).
    pub fn correlate(&mut self, x: &[f64], out: &mut Vec<f64>) {
        out.clear();
        let l = self.taps.len();
        if x.len() < l || l == 0 {
            return;
        }
        out.extend((0..=x.len() - l).map(|k| self.taps.iter().zip(&x[k..k + l]).map(|(a, b)| a * b).sum::<f64>()));
    }
}
