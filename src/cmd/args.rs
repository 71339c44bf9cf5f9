//! Numeric command-line values checked where they are parsed, so every
//! command refuses a rate, size, spacing or duration that is zero, negative,
//! infinite or NaN with clap's message naming the flag (`invalid value 'inf'
//! for '--rate <RATE>': …`), instead of dividing by it, flipping a pose or
//! falling back to a default in silence.

/// A finite number greater than zero (rates, durations, sizes, spacings).
pub fn positive(s: &str) -> Result<f64, String> {
    let v = finite(s)?;
    if v > 0.0 {
        Ok(v)
    } else {
        Err(format!("{v} is not greater than zero"))
    }
}

/// A finite number of zero or more (water attenuation, offsets, limits where 0 means "off").
pub fn non_negative(s: &str) -> Result<f64, String> {
    let v = finite(s)?;
    if v >= 0.0 {
        Ok(v)
    } else {
        Err(format!("{v} is negative"))
    }
}

/// A probability, 0 to 1.
pub fn probability(s: &str) -> Result<f64, String> {
    let v = finite(s)?;
    if (0.0..=1.0).contains(&v) {
        Ok(v)
    } else {
        Err(format!("{v} is not a probability (0 to 1)"))
    }
}

fn finite(s: &str) -> Result<f64, String> {
    let v: f64 = s
        .trim()
        .parse()
        .map_err(|_| format!("{s:?} is not a number"))?;
    if v.is_finite() {
        Ok(v)
    } else {
        Err(format!("{v} is not a finite number"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn refuses_zero_negative_infinite_and_nan_where_a_positive_number_is_needed() {
        for bad in ["0", "-1", "inf", "1e400", "NaN", "-0", "abc", ""] {
            assert!(positive(bad).is_err(), "{bad:?} accepted");
        }
        assert_eq!(positive("1e10"), Ok(1e10));
        assert_eq!(positive(" 2.5"), Ok(2.5));
    }

    #[test]
    fn zero_is_allowed_where_it_means_off_and_probabilities_stay_in_0_1() {
        assert_eq!(non_negative("0"), Ok(0.0));
        assert!(non_negative("-0.1").is_err());
        assert!(non_negative("NaN").is_err());
        assert_eq!(probability("1"), Ok(1.0));
        assert!(probability("1.01").is_err());
        assert!(probability("-0.01").is_err());
    }
}
