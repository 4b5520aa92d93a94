//! Small validation helpers shared by every `*Params::validate()`.
//!
//! Each returns a [`ParamError`] that names the field (as a dotted path such as
//! `pendulum.length_m`), the offending value and the bound it broke.

use super::ParamError;

/// Refuses NaN and infinities.
pub fn finite(field: &str, value: f64) -> Result<(), ParamError> {
    if value.is_finite() {
        Ok(())
    } else {
        Err(ParamError::NotFinite {
            field: field.to_owned(),
            value: value.to_string(),
        })
    }
}

/// Requires `value > 0` (and finite).
pub fn positive(field: &str, value: f64) -> Result<(), ParamError> {
    finite(field, value)?;
    if value > 0.0 {
        Ok(())
    } else {
        Err(out_of_range(field, value, "must be > 0"))
    }
}

/// Requires `value >= 0` (and finite).
pub fn non_negative(field: &str, value: f64) -> Result<(), ParamError> {
    finite(field, value)?;
    if value >= 0.0 {
        Ok(())
    } else {
        Err(out_of_range(field, value, "must be >= 0"))
    }
}

/// Requires `lo <= value <= hi` (and finite).
pub fn within(field: &str, value: f64, lo: f64, hi: f64) -> Result<(), ParamError> {
    finite(field, value)?;
    if (lo..=hi).contains(&value) {
        Ok(())
    } else {
        Err(out_of_range(
            field,
            value,
            &format!("must be in [{lo}, {hi}]"),
        ))
    }
}

/// Requires a probability in `[0, 1]`.
pub fn probability(field: &str, value: f64) -> Result<(), ParamError> {
    within(field, value, 0.0, 1.0)
}

/// Requires an integer within `lo..=hi`.
pub fn within_u32(field: &str, value: u32, lo: u32, hi: u32) -> Result<(), ParamError> {
    if (lo..=hi).contains(&value) {
        Ok(())
    } else {
        Err(ParamError::OutOfRange {
            field: field.to_owned(),
            value: value.to_string(),
            bound: format!("must be in [{lo}, {hi}]"),
        })
    }
}

/// Builds an out-of-range error.
pub fn out_of_range(field: &str, value: f64, bound: &str) -> ParamError {
    ParamError::OutOfRange {
        field: field.to_owned(),
        value: value.to_string(),
        bound: bound.to_owned(),
    }
}
