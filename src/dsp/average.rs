//! Exact accumulation for ensemble averages.

/// Adds integer codes into i64 sums (exact for any number of frames below 2^47 of i16).
pub fn add_codes_i16(acc: &mut [i64], x: &[i16]) {
    for (a, &v) in acc.iter_mut().zip(x) {
        *a += v as i64;
    }
}

/// Adds i8 codes into i64 sums.
pub fn add_codes_i8(acc: &mut [i64], x: &[i8]) {
    for (a, &v) in acc.iter_mut().zip(x) {
        *a += v as i64;
    }
}

/// Adds i32 codes into i64 sums.
pub fn add_codes_i32(acc: &mut [i64], x: &[i32]) {
    for (a, &v) in acc.iter_mut().zip(x) {
        *a += v as i64;
    }
}

/// Adds f64 values into f64 sums.
pub fn add_f64(acc: &mut [f64], x: &[f64]) {
    for (a, &v) in acc.iter_mut().zip(x) {
        *a += v;
    }
}
