//! `ParamError` and the small validation helpers shared by every
//! `*Params::validate()`: a leaf module (it imports nothing of the crate), so
//! every part may use it without importing the scenario.
//!
//! Each returns a [`ParamError`] that names the field (as a dotted path such as
//! `pendulum.length_m`), the offending value and the bound it broke.

use serde::{Deserialize, Serialize};

/// A parameter that was refused, naming the field, the value and the bound.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum ParamError {
    /// A value outside its allowed range.
    #[error("{field} = {value} is out of range: {bound}")]
    OutOfRange {
        /// Dotted path of the field, e.g. `pendulum.length_m`.
        field: String,
        /// The refused value.
        value: Value,
        /// The bound it broke, e.g. `must be > 0`.
        bound: Bound,
    },
    /// NaN or an infinity.
    #[error("{field} = {value} is not a finite number")]
    NotFinite {
        /// Dotted path of the field.
        field: String,
        /// The refused value.
        value: String,
    },
    /// A `[lo, hi]` range with `lo > hi`.
    #[error("{field} = [{lo}, {hi}] is reversed: the first value must not exceed the second")]
    Reversed {
        /// Dotted path of the field.
        field: String,
        /// First value.
        lo: f64,
        /// Second value.
        hi: f64,
    },
    /// The file could not be parsed (syntax, wrong type, unknown key): the
    /// parser's message and, when known, the file, the line and the key.
    #[error(
        "{}{}{}{message}",
        prefix(path.as_deref()),
        line.map_or_else(String::new, |l| format!("line {l}: ")),
        prefix(key.as_deref())
    )]
    Parse {
        /// The file, when the text came from one.
        path: Option<String>,
        /// The line, 1-based, when the parser says where.
        line: Option<usize>,
        /// The dotted key (`section.key`) on that line, when there is one.
        key: Option<String>,
        /// The parser's message (one line).
        message: String,
    },
    /// The file could not be read.
    #[error("cannot read {path}: {reason}")]
    Io {
        /// The path that was asked for.
        path: String,
        /// The operating system's reason.
        reason: String,
    },
}

/// A refused value, kept as the type it had (a number stays a number).
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub enum Value {
    /// A real number.
    Number(f64),
    /// An integer.
    Integer(i64),
    /// A text (a name, a port, an origin, a size such as `1280x720`).
    Text(String),
}

impl std::fmt::Display for Value {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Number(v) => write!(f, "{v}"),
            Self::Integer(v) => write!(f, "{v}"),
            Self::Text(v) => write!(f, "{v:?}"),
        }
    }
}

/// The bound a value broke: its limits as numbers where it has them, a rule
/// in words where it relates the value to another field.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub enum Bound {
    /// Must be greater than this.
    Above(f64),
    /// Must be at least this.
    AtLeast(f64),
    /// Must be in `[lo, hi]`.
    Within {
        /// Lowest allowed value.
        lo: f64,
        /// Highest allowed value.
        hi: f64,
    },
    /// Must be 0 (the effect off) or at least this.
    ZeroOrAtLeast(f64),
    /// A rule that relates the value to others, in words.
    Rule(String),
}

impl std::fmt::Display for Bound {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Above(v) => write!(f, "must be > {v}"),
            Self::AtLeast(v) => write!(f, "must be >= {v}"),
            Self::Within { lo, hi } => write!(f, "must be in [{lo}, {hi}]"),
            Self::ZeroOrAtLeast(v) => write!(f, "must be 0 (off) or >= {v}"),
            Self::Rule(r) => f.write_str(r),
        }
    }
}

impl Bound {
    /// A rule in words.
    pub fn rule(text: impl Into<String>) -> Self {
        Self::Rule(text.into())
    }
}

impl ParamError {
    /// The dotted field path this error is about, when it is about one field.
    pub fn field(&self) -> Option<&str> {
        match self {
            Self::OutOfRange { field, .. }
            | Self::NotFinite { field, .. }
            | Self::Reversed { field, .. } => Some(field),
            Self::Parse { .. } | Self::Io { .. } => None,
        }
    }

    /// A parse error with the parser's message only (its newlines made spaces).
    pub fn parse(message: impl std::fmt::Display) -> Self {
        Self::Parse {
            path: None,
            line: None,
            key: None,
            message: message.to_string().replace('\n', " "),
        }
    }

    /// This error, read from the file `path` (a parse error then names it).
    #[must_use]
    pub fn in_file(self, path: &std::path::Path) -> Self {
        match self {
            Self::Parse {
                path: None,
                line,
                key,
                message,
            } => Self::Parse {
                path: Some(path.display().to_string()),
                line,
                key,
                message,
            },
            other => other,
        }
    }
}

/// `"{s}: "`, or nothing.
fn prefix(s: Option<&str>) -> String {
    s.map_or_else(String::new, |s| format!("{s}: "))
}

/// Refuses NaN and infinities.
///
/// # Errors
///
/// [`ParamError::NotFinite`] when `value` is NaN or infinite.
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
///
/// # Errors
///
/// [`ParamError::NotFinite`] when `value` is not finite; [`ParamError::OutOfRange`]
/// when it is not `> 0`.
pub fn positive(field: &str, value: f64) -> Result<(), ParamError> {
    finite(field, value)?;
    if value > 0.0 {
        Ok(())
    } else {
        Err(out_of_range(field, value, Bound::Above(0.0)))
    }
}

/// Requires `value >= 0` (and finite).
///
/// # Errors
///
/// [`ParamError::NotFinite`] when `value` is not finite; [`ParamError::OutOfRange`]
/// when it is negative.
pub fn non_negative(field: &str, value: f64) -> Result<(), ParamError> {
    finite(field, value)?;
    if value >= 0.0 {
        Ok(())
    } else {
        Err(out_of_range(field, value, Bound::AtLeast(0.0)))
    }
}

/// Requires `lo <= value <= hi` (and finite).
///
/// ```
/// use rt_core::check::within;
/// assert!(within("task.distance_m", 0.7, 0.1, 1.2).is_ok());
/// let e = within("task.distance_m", f64::NAN, 0.1, 1.2).unwrap_err();
/// assert_eq!(e.field(), Some("task.distance_m"));
/// ```
///
/// # Errors
///
/// [`ParamError::NotFinite`] when `value` is not finite; [`ParamError::OutOfRange`]
/// when it is outside `[lo, hi]`.
pub fn within(field: &str, value: f64, lo: f64, hi: f64) -> Result<(), ParamError> {
    finite(field, value)?;
    if (lo..=hi).contains(&value) {
        Ok(())
    } else {
        Err(out_of_range(field, value, Bound::Within { lo, hi }))
    }
}

/// Requires a probability in `[0, 1]`.
///
/// # Errors
///
/// [`ParamError::NotFinite`] when `value` is not finite; [`ParamError::OutOfRange`]
/// when it is outside `[0, 1]`.
pub fn probability(field: &str, value: f64) -> Result<(), ParamError> {
    within(field, value, 0.0, 1.0)
}

/// Requires an integer within `lo..=hi`.
///
/// # Errors
///
/// [`ParamError::OutOfRange`] when `value` is outside `lo..=hi`.
pub fn within_u32(field: &str, value: u32, lo: u32, hi: u32) -> Result<(), ParamError> {
    if (lo..=hi).contains(&value) {
        Ok(())
    } else {
        Err(ParamError::OutOfRange {
            field: field.to_owned(),
            value: Value::Integer(i64::from(value)),
            bound: Bound::Within {
                lo: f64::from(lo),
                hi: f64::from(hi),
            },
        })
    }
}

/// Builds an out-of-range error.
pub fn out_of_range(field: &str, value: f64, bound: Bound) -> ParamError {
    ParamError::OutOfRange {
        field: field.to_owned(),
        value: Value::Number(value),
        bound,
    }
}

/// A closed interval `[lo, hi]` from which a value is drawn per trial.
///
/// In TOML it is written `[lo, hi]` or as a single number (then `lo == hi`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
#[serde(into = "[f64; 2]")]
pub struct RangeParam {
    /// Lower end (inclusive).
    pub lo: f64,
    /// Upper end (inclusive).
    pub hi: f64,
}

impl RangeParam {
    /// A range from `lo` to `hi`.
    pub const fn new(lo: f64, hi: f64) -> Self {
        Self { lo, hi }
    }

    /// A range holding one value.
    pub const fn fixed(v: f64) -> Self {
        Self { lo: v, hi: v }
    }

    /// Checks both ends with `each` and that the range is not reversed.
    ///
    /// # Errors
    ///
    /// The first error `each` returns for `lo` or `hi`; [`ParamError::Reversed`] when
    /// `lo > hi`.
    pub fn validate_with(
        &self,
        field: &str,
        each: impl Fn(&str, f64) -> Result<(), ParamError>,
    ) -> Result<(), ParamError> {
        each(field, self.lo)?;
        each(field, self.hi)?;
        if self.lo > self.hi {
            return Err(ParamError::Reversed {
                field: field.to_owned(),
                lo: self.lo,
                hi: self.hi,
            });
        }
        Ok(())
    }

    /// The point at fraction `u` in `[0, 1]` of the range.
    pub fn lerp(&self, u: f64) -> f64 {
        self.lo + (self.hi - self.lo) * u
    }
}

impl From<RangeParam> for [f64; 2] {
    fn from(r: RangeParam) -> Self {
        [r.lo, r.hi]
    }
}

impl<'de> Deserialize<'de> for RangeParam {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        #[derive(Deserialize)]
        #[serde(untagged)]
        enum Repr {
            One(f64),
            Two([f64; 2]),
        }
        match Repr::deserialize(d) {
            Ok(Repr::One(v)) => Ok(Self::fixed(v)),
            Ok(Repr::Two([lo, hi])) => Ok(Self::new(lo, hi)),
            Err(_) => Err(serde::de::Error::custom(
                "expected a number or a two-element array [lo, hi]",
            )),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_refusal_keeps_its_value_and_limits_as_numbers_and_says_them() {
        let e = within("pendulum.length_m", 7.5, 0.1, 5.0).unwrap_err();
        assert_eq!(
            e,
            ParamError::OutOfRange {
                field: "pendulum.length_m".into(),
                value: Value::Number(7.5),
                bound: Bound::Within { lo: 0.1, hi: 5.0 },
            }
        );
        assert_eq!(
            e.to_string(),
            "pendulum.length_m = 7.5 is out of range: must be in [0.1, 5]"
        );
        assert_eq!(
            positive("a", -1.0).unwrap_err().to_string(),
            "a = -1 is out of range: must be > 0"
        );
        let e = within_u32("magnet.baud", 12, 300, 2_000_000).unwrap_err();
        assert!(matches!(
            e,
            ParamError::OutOfRange { value: Value::Integer(12), bound: Bound::Within { lo, hi }, .. }
                if lo == 300.0 && hi == 2_000_000.0
        ));
        // A NaN is refused as not finite before any bound is looked at.
        assert!(matches!(
            within("x", f64::NAN, 0.0, 1.0),
            Err(ParamError::NotFinite { .. })
        ));
        assert_eq!(Value::Text("ttyACM0".into()).to_string(), "\"ttyACM0\"");
    }
}
