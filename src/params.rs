//! The rules on parameters that the command line and the HTTP API share, written once so the
//! two front ends cannot disagree: `radiosity bake --sky 1,1,1` and `POST
//! /v1/timelines?sky=1,1,1` read the sky with the same parser, and both refuse a timeline that
//! ends before it starts with the same message.
//!
//! The loader checks the rest of [`LoadOptions`] itself (positive `fps`, finite times, positive
//! `patch_size`), whoever calls it.

use std::str::FromStr;

use crate::loader::LoadOptions;

/// A parameter that breaks a shared rule; the message quotes the value.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum ParamError {
    /// The sky is not three finite numbers ≥ 0 separated by commas. The message leaves the
    /// parameter's name to the front ends, which both put it first (clap's `invalid value for
    /// '--sky'`, the service's `sky: ...`).
    #[error("{0:?} is not r,g,b: three finite numbers ≥ 0 separated by commas, such as 1,1,1")]
    Sky(String),
    /// `patch_size` is neither `auto`, `source` nor a positive length.
    #[error("{0:?} is not auto, source or a positive length in scene units, such as 0.25")]
    PatchSize(String),
    /// `start` is after `end`.
    #[error("start ({start} s) is after end ({end} s): the timeline would end before it starts")]
    StartAfterEnd {
        /// The requested time of the first frame, seconds.
        start: f64,
        /// The requested time of the last frame, seconds.
        end: f64,
    },
}

/// How a scene is cut into patches, written `auto`, `source` or a length (the `patch_size`
/// parameter of both front ends).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub enum PatchSize {
    /// Patches cut after tracing where the light needs them and merged where it does not,
    /// from the lines ([`crate::adaptive`]), starting from the source's triangles. The default: on every
    /// sample scene it is closer to the path-traced reference than the source's triangles
    /// (README, "Adaptive patches").
    #[default]
    Auto,
    /// One patch per side of each of the source's triangles.
    Source,
    /// Triangles subdivided until every edge is at most this long (scene units, > 0).
    Length(f64),
}

impl PatchSize {
    /// The longest edge the loader subdivides to, if any ([`LoadOptions::patch_size`]).
    #[must_use]
    pub fn length(self) -> Option<f64> {
        match self {
            Self::Length(l) => Some(l),
            Self::Auto | Self::Source => None,
        }
    }
}

impl FromStr for PatchSize {
    type Err = ParamError;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        match text.trim() {
            "auto" => Ok(Self::Auto),
            "source" => Ok(Self::Source),
            number => number
                .parse::<f64>()
                .ok()
                .filter(|l| l.is_finite() && *l > 0.0)
                .map(Self::Length)
                .ok_or_else(|| ParamError::PatchSize(text.to_string())),
        }
    }
}

impl std::fmt::Display for PatchSize {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Auto => f.write_str("auto"),
            Self::Source => f.write_str("source"),
            Self::Length(l) => write!(f, "{l}"),
        }
    }
}

/// `auto` and `source` as strings, a length as a number.
impl serde::Serialize for PatchSize {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match self {
            Self::Length(l) => s.serialize_f64(*l),
            other => s.collect_str(other),
        }
    }
}

/// The radiance of the sky, in the units of the scene's emission, written `r,g,b`: exactly
/// three finite numbers ≥ 0 separated by commas (spaces around a number are allowed). Lines
/// that leave the scene see it.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Sky(pub [f64; 3]);

impl FromStr for Sky {
    type Err = ParamError;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let refused = || ParamError::Sky(text.to_string());
        let mut rgb = [0.0; 3];
        let mut parts = text.split(',');
        for value in &mut rgb {
            *value = parts
                .next()
                .and_then(|p| p.trim().parse::<f64>().ok())
                .filter(|v| v.is_finite() && *v >= 0.0)
                .ok_or_else(refused)?;
        }
        match parts.next() {
            None => Ok(Self(rgb)),
            Some(_) => Err(refused()),
        }
    }
}

/// The rules both front ends apply to what they ask the loader for, before loading: a
/// timeline's `start` may not be after its `end` (equal times give one frame).
///
/// # Errors
/// [`ParamError::StartAfterEnd`] when both times are given and `start > end`.
pub fn validate_load(options: &LoadOptions) -> Result<(), ParamError> {
    match (options.start, options.end) {
        (Some(start), Some(end)) if start > end => Err(ParamError::StartAfterEnd { start, end }),
        _ => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_sky_is_exactly_three_finite_non_negative_numbers() {
        for (text, rgb) in [
            ("1,1,1", [1.0, 1.0, 1.0]),
            ("0,0.5,2", [0.0, 0.5, 2.0]),
            (" 0.25 , 1e3,0 ", [0.25, 1000.0, 0.0]),
        ] {
            assert_eq!(text.parse::<Sky>(), Ok(Sky(rgb)), "{text}");
        }
        // `1,x,2,3` was read as 1,2,3 by the service (issue 11).
        for text in [
            "1,x,2,3",
            "1,2",
            "1,2,3,4",
            "1,,2,3",
            "1,2,3,",
            ",1,2,3",
            "",
            "1 1 1",
            "1;1;1",
            "1,-2,3",
            "1,inf,3",
            "NaN,0,0",
            "1,2,1e999",
        ] {
            assert_eq!(
                text.parse::<Sky>(),
                Err(ParamError::Sky(text.to_string())),
                "{text}"
            );
        }
        let message = "1,x,2,3".parse::<Sky>().unwrap_err().to_string();
        assert!(
            message.contains("\"1,x,2,3\"") && message.contains("r,g,b"),
            "{message}"
        );
    }

    #[test]
    fn a_patch_size_is_auto_source_or_a_positive_length() {
        for (text, size) in [
            ("auto", PatchSize::Auto),
            ("source", PatchSize::Source),
            ("0.25", PatchSize::Length(0.25)),
            (" 2 ", PatchSize::Length(2.0)),
        ] {
            assert_eq!(text.parse::<PatchSize>(), Ok(size), "{text}");
        }
        for text in ["", "0", "-1", "inf", "NaN", "Auto", "0.25m", "1e999"] {
            assert_eq!(
                text.parse::<PatchSize>(),
                Err(ParamError::PatchSize(text.to_string())),
                "{text}"
            );
        }
        assert_eq!(
            serde_json::to_string(&[PatchSize::Auto, PatchSize::Length(0.5)]).unwrap(),
            r#"["auto",0.5]"#
        );
    }

    #[test]
    fn a_timeline_may_not_end_before_it_starts() {
        let options = |start, end| LoadOptions {
            start,
            end,
            ..LoadOptions::default()
        };
        for (start, end) in [
            (None, None),
            (Some(1.0), None),
            (None, Some(-1.0)),
            (Some(1.0), Some(1.0)),
            (Some(-1.0), Some(2.0)),
        ] {
            assert_eq!(
                validate_load(&options(start, end)),
                Ok(()),
                "{start:?} {end:?}"
            );
        }
        let refused = validate_load(&options(Some(2.0), Some(1.0))).unwrap_err();
        assert_eq!(
            refused,
            ParamError::StartAfterEnd {
                start: 2.0,
                end: 1.0
            }
        );
        let message = refused.to_string();
        assert!(
            message.contains("start (2 s)") && message.contains("end (1 s)"),
            "{message}"
        );
    }
}
