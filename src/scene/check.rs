//! Range checks for configuration values: one row per field (name, value,
//! allowed range, the range as the error states it), and the one error shape
//! a failed check produces, shared by the scene sections and the
//! `[simulation]` section.

/// A configuration value outside its allowed range.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{field} = {value} is out of range: allowed {allowed}")]
pub struct FieldError {
    /// Dotted field name, e.g. `detector.pfa` or `simulation.targets[1].range_m`.
    pub field: String,
    /// The offending value, as the user wrote it (or with the related values it was checked against).
    pub value: String,
    /// The allowed range or set.
    pub allowed: &'static str,
}

impl FieldError {
    /// The error naming `field`, its `value` and the `allowed` range.
    pub fn new(field: impl Into<String>, value: impl ToString, allowed: &'static str) -> FieldError {
        FieldError {
            field: field.into(),
            value: value.to_string(),
            allowed,
        }
    }
}

/// One end of a [`Range`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Bound {
    /// The end value is allowed.
    Closed(f64),
    /// The end value is not allowed.
    Open(f64),
}

/// An interval of allowed values. NaN is never inside, and infinities only
/// where a closed bound is infinite, so `(0, inf)` also demands a finite value.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Range {
    /// Lower end.
    pub lo: Bound,
    /// Upper end.
    pub hi: Bound,
}

impl Range {
    /// `[lo, hi]`.
    pub const fn closed(lo: f64, hi: f64) -> Range {
        Range { lo: Bound::Closed(lo), hi: Bound::Closed(hi) }
    }

    /// `(lo, hi]`.
    pub const fn open_closed(lo: f64, hi: f64) -> Range {
        Range { lo: Bound::Open(lo), hi: Bound::Closed(hi) }
    }

    /// `[lo, hi)`.
    pub const fn closed_open(lo: f64, hi: f64) -> Range {
        Range { lo: Bound::Closed(lo), hi: Bound::Open(hi) }
    }

    /// `(lo, hi)`.
    pub const fn open(lo: f64, hi: f64) -> Range {
        Range { lo: Bound::Open(lo), hi: Bound::Open(hi) }
    }

    /// `(0, max]`.
    pub const fn positive_max(max: f64) -> Range {
        Range::open_closed(0.0, max)
    }

    /// `(0, inf)`: positive and finite.
    pub const fn positive() -> Range {
        Range::open(0.0, f64::INFINITY)
    }

    /// `[0, inf)`: non-negative and finite.
    pub const fn non_negative() -> Range {
        Range::closed_open(0.0, f64::INFINITY)
    }

    /// `[min, inf)` for counts.
    pub const fn at_least(min: f64) -> Range {
        Range::closed_open(min, f64::INFINITY)
    }

    /// Whether `x` lies inside.
    pub fn contains(&self, x: f64) -> bool {
        let above = match self.lo {
            Bound::Closed(lo) => x >= lo,
            Bound::Open(lo) => x > lo,
        };
        let below = match self.hi {
            Bound::Closed(hi) => x <= hi,
            Bound::Open(hi) => x < hi,
        };
        above && below
    }
}

/// A value to check: real numbers and counts print as the user wrote them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Value {
    /// A real number.
    Real(f64),
    /// A count (compared as a real number: every bound here is far below 2^53).
    Count(u64),
}

impl Value {
    fn as_f64(self) -> f64 {
        match self {
            Value::Real(x) => x,
            Value::Count(n) => n as f64,
        }
    }
}

impl std::fmt::Display for Value {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Value::Real(x) => x.fmt(f),
            Value::Count(n) => n.fmt(f),
        }
    }
}

impl From<f64> for Value {
    fn from(x: f64) -> Value {
        Value::Real(x)
    }
}

impl From<usize> for Value {
    fn from(n: usize) -> Value {
        Value::Count(n as u64)
    }
}

impl From<u32> for Value {
    fn from(n: u32) -> Value {
        Value::Count(u64::from(n))
    }
}

/// One row of a check table: field name, value, allowed range, and the
/// allowed range as the error message states it.
pub type Row<'a> = (&'a str, Value, Range, &'static str);

/// Checks the rows in order; the first value outside its range is the error.
pub fn check(rows: &[Row<'_>]) -> Result<(), FieldError> {
    match rows.iter().find(|(_, v, r, _)| !r.contains(v.as_f64())) {
        Some(&(field, value, _, allowed)) => Err(FieldError::new(field, value, allowed)),
        None => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bounds_nan_and_infinity() {
        let r = Range::positive_max(1.0);
        assert!(r.contains(1.0) && r.contains(1e-300));
        assert!(!r.contains(0.0) && !r.contains(f64::NAN) && !r.contains(1.0 + 1e-15));
        assert!(!Range::positive().contains(f64::INFINITY));
        assert!(Range::non_negative().contains(0.0) && !Range::non_negative().contains(-0.1));
        assert!(!Range::closed(-1.0, 1.0).contains(f64::NEG_INFINITY));
    }

    #[test]
    fn first_failing_row_names_field_value_and_range() {
        let e = check(&[
            ("a.x", 0.5.into(), Range::open(0.0, 1.0), "(0, 1)"),
            ("a.n", 0usize.into(), Range::at_least(2.0), "[2, inf)"),
            ("a.y", 7.0.into(), Range::closed(0.0, 1.0), "[0, 1]"),
        ])
        .unwrap_err();
        assert_eq!(e.to_string(), "a.n = 0 is out of range: allowed [2, inf)");
    }
}
