//! What a bake is asked for, written once so the two front ends cannot disagree: a
//! [`BakeRequest`] is both the `radiosity bake` command's options (clap) and the query of `POST
//! /v1/timelines` (serde), and [`BakeRequest::validate`] checks it against the [`Limits`] for
//! both. `radiosity bake --sky 1,1,1` and `POST /v1/timelines?sky=1,1,1` read the sky with one
//! parser, refuse 500 lines with one message, and take one default preset.
//!
//! The loader checks the rest of [`LoadOptions`] itself (finite times, positive `patch_size`,
//! the reflectance cap), whoever calls it.

use std::fmt::Display;
use std::str::FromStr;

use serde::de::Error as _;
use serde::{Deserialize, Deserializer};

use crate::adaptive::Adaptive;
use crate::loader::LoadOptions;
use crate::timeline::{LineParams, Preset};

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
    /// `fps` is outside (0, [`MAX_FPS`]].
    #[error("fps must be in (0, {MAX_FPS}], not {0}")]
    Fps(f64),
    /// `lines` is outside [[`MIN_LINES`], the limit].
    #[error("lines must be a whole number from {MIN_LINES} to {max}, not {lines}")]
    Lines {
        /// The lines asked for.
        lines: u64,
        /// The limit ([`Limits::max_lines`]).
        max: u64,
    },
    /// Both `lines` and `preset` are given.
    #[error("give lines or preset, not both")]
    LinesAndPreset,
    /// `patch_budget` is 0.
    #[error("patch_budget must be at least 1")]
    NoPatches,
    /// `patch_budget` is given with a `patch_size` other than `auto`.
    #[error("patch_budget applies to patch_size=auto only, not {0}")]
    BudgetWithoutAuto(PatchSize),
}

/// The highest frame rate a timeline may have.
pub const MAX_FPS: f64 = 1000.0;

/// The fewest lines a bake may have: fewer estimate nothing.
pub const MIN_LINES: u64 = 1_000;

/// What one bake may ask for at most: the service's configuration holds them, the command line
/// takes the defaults.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Limits {
    /// Most lines of one bake, and of the lines one refine adds.
    pub max_lines: u64,
    /// Most frames of one timeline ([`LoadOptions::max_frames`]).
    pub max_frames: usize,
    /// Most patches of one scene ([`LoadOptions::max_patches`]; `auto`'s budget is capped by it
    /// too).
    pub max_patches: usize,
}

impl Default for Limits {
    fn default() -> Self {
        let load = LoadOptions::default();
        Self {
            max_lines: 100_000_000,
            max_frames: load.max_frames,
            max_patches: load.max_patches,
        }
    }
}

/// A bake asked for, as the command line and the HTTP API both take it: every field is optional
/// and [`BakeRequest::validate`] gives the defaults (the same for both). The command line reads
/// `--patch-size`, the query string `patch_size`; values are read from text by the same
/// parsers ([`Sky`], [`PatchSize`], [`Preset`]). A query parameter it does not have is refused.
#[derive(Clone, Debug, Default, PartialEq, clap::Args, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BakeRequest {
    /// Frames per second of the timeline, in (0, 1000]; 24 by default.
    #[arg(long)]
    #[serde(default, deserialize_with = "number")]
    pub fps: Option<f64>,
    /// Number of lines, from 1,000 to the limit (100,000,000 by default); exclusive with
    /// preset.
    #[arg(long, conflicts_with = "preset")]
    #[serde(default, deserialize_with = "whole")]
    pub lines: Option<u64>,
    /// Line budget by name: draft, default or final; default when neither it nor lines is
    /// given.
    #[arg(long)]
    #[serde(default, deserialize_with = "parsed")]
    pub preset: Option<Preset>,
    /// Seed of the lines; 1 by default.
    #[arg(long)]
    #[serde(default, deserialize_with = "whole")]
    pub seed: Option<u64>,
    /// How patches are made: source (one per side of each source triangle, solved on finer
    /// pieces; the default), auto (cut after tracing where the light needs them, merged where
    /// it does not; the default with a patch budget) or a length (every edge at most that
    /// long, scene units).
    #[arg(long, value_name = "auto|source|LENGTH")]
    #[serde(default, deserialize_with = "parsed")]
    pub patch_size: Option<PatchSize>,
    /// With patch size auto (implied when no patch size is given): most patches (the cuts
    /// neighbours need included; merges bring a scene of more triangles down to it where they
    /// can); one per 200 lines by default.
    #[arg(long)]
    #[serde(default, deserialize_with = "whole")]
    pub patch_budget: Option<u64>,
    /// Play only this animation (name or index); all play together by default.
    #[arg(long)]
    pub animation: Option<String>,
    /// The previews' camera: a camera node's name or index, or auto (the automatic view); the
    /// scene's first camera by default.
    #[arg(long)]
    pub camera: Option<String>,
    /// Radiance of the sky that lines leaving the scene see, r,g,b (such as 1,1,1); black by
    /// default.
    #[arg(long, value_name = "R,G,B")]
    #[serde(default, deserialize_with = "parsed")]
    pub sky: Option<Sky>,
    /// Time of the first frame (seconds); the first keyframe by default.
    #[arg(long, allow_negative_numbers = true)]
    #[serde(default, deserialize_with = "number")]
    pub start: Option<f64>,
    /// Time of the last frame (seconds); the last keyframe by default.
    #[arg(long, allow_negative_numbers = true)]
    #[serde(default, deserialize_with = "number")]
    pub end: Option<f64>,
    /// Largest diffuse reflectance, in (0, 1]: higher ones are lowered to it, with a warning;
    /// 0.999 by default.
    #[arg(long)]
    #[serde(default, deserialize_with = "number")]
    pub max_reflectance: Option<f64>,
}

/// A [`BakeRequest`] checked, with its defaults filled in.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct BakeSettings {
    /// What to load ([`Limits::max_frames`] and [`Limits::max_patches`] included).
    pub load: LoadOptions,
    /// How patches are made.
    #[serde(with = "patch_size_text")]
    pub patch_size: PatchSize,
    /// The patch budget asked for, if one was (`auto` only): [`BakeSettings::adaptive`].
    pub patch_budget: Option<usize>,
    /// Lines and seed.
    pub lines: LineParams,
    /// Radiance of the sky.
    pub sky: [f64; 3],
}

impl BakeSettings {
    /// With `auto`, how its patches are cut and merged for a scene loaded with `patches`
    /// patches: one patch per 200 lines and at least the scene's own ([`Adaptive::for_lines`]),
    /// or the budget asked for (below the scene's patches, merges bring it down to it where
    /// they can), within [`LoadOptions::max_patches`].
    #[must_use]
    pub fn adaptive(&self, patches: usize) -> Option<Adaptive> {
        (self.patch_size == PatchSize::Auto).then(|| {
            Adaptive::for_lines(self.lines.lines, patches)
                .with_budget(self.patch_budget)
                .within(self.load.max_patches)
        })
    }
}

impl BakeRequest {
    /// The bake asked for, its defaults filled in, checked against itself and `limits`.
    ///
    /// # Errors
    /// The first rule broken ([`ParamError`]).
    pub fn validate(self, limits: &Limits) -> Result<BakeSettings, ParamError> {
        let fps = self.fps.unwrap_or(24.0);
        if !(fps > 0.0 && fps <= MAX_FPS) {
            return Err(ParamError::Fps(fps));
        }
        let lines = match (self.lines, self.preset) {
            (Some(_), Some(_)) => return Err(ParamError::LinesAndPreset),
            (Some(lines), None) if !(MIN_LINES..=limits.max_lines).contains(&lines) => {
                return Err(ParamError::Lines {
                    lines,
                    max: limits.max_lines,
                });
            }
            (Some(lines), None) => lines,
            (None, preset) => preset.unwrap_or_default().lines(),
        };
        // A patch budget alone asks for `auto`, the one way of making patches it applies to.
        let patch_size = (self.patch_size).unwrap_or(match self.patch_budget {
            Some(_) => PatchSize::Auto,
            None => PatchSize::default(),
        });
        let patch_budget = match (patch_size, self.patch_budget) {
            (_, Some(0)) => return Err(ParamError::NoPatches),
            (PatchSize::Auto, budget) => budget.map(|b| usize::try_from(b).unwrap_or(usize::MAX)),
            (_, None) => None,
            (other, Some(_)) => return Err(ParamError::BudgetWithoutAuto(other)),
        };
        let load = LoadOptions {
            fps,
            animation: self.animation,
            camera: self.camera,
            start: self.start,
            end: self.end,
            patch_size: patch_size.length(),
            max_frames: limits.max_frames,
            max_patches: limits.max_patches,
            max_reflectance: (self.max_reflectance).unwrap_or(crate::loader::MAX_REFLECTANCE),
            ..LoadOptions::default()
        };
        validate_load(&load)?;
        Ok(BakeSettings {
            load,
            patch_size,
            patch_budget,
            lines: LineParams {
                lines,
                seed: self.seed.unwrap_or(1),
            },
            sky: self.sky.unwrap_or_default().0,
        })
    }
}

/// A finite number, read from text.
pub(crate) fn number<'de, D: Deserializer<'de>>(d: D) -> Result<Option<f64>, D::Error> {
    let text = String::deserialize(d)?;
    match text.parse::<f64>() {
        Ok(v) if v.is_finite() => Ok(Some(v)),
        _ => Err(D::Error::custom(format!("{text:?} is not a finite number"))),
    }
}

/// A whole number ≥ 0 of an integer type, read from text.
pub(crate) fn whole<'de, D, T>(d: D) -> Result<Option<T>, D::Error>
where
    D: Deserializer<'de>,
    T: FromStr,
    T::Err: Display,
{
    let text = String::deserialize(d)?;
    text.parse()
        .map(Some)
        .map_err(|e| D::Error::custom(format!("{text:?} is not a whole number ≥ 0 ({e})")))
}

/// A value read by its type's `FromStr`, whose errors quote it (a preset, a sky).
fn parsed<'de, D, T>(d: D) -> Result<Option<T>, D::Error>
where
    D: Deserializer<'de>,
    T: FromStr,
    T::Err: Display,
{
    let text = String::deserialize(d)?;
    text.parse().map(Some).map_err(D::Error::custom)
}

/// How a scene is cut into patches, written `auto`, `source` or a length (the `patch_size`
/// parameter of both front ends).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub enum PatchSize {
    /// Patches cut after tracing where the light needs them and merged where it does not,
    /// from the lines ([`crate::adaptive`]), starting from the source's triangles; the default
    /// when a patch budget is given.
    Auto,
    /// One patch per side of each of the source's triangles (solved on finer pieces,
    /// [`crate::bake::Bake::split`], and the outputs evaluated at their points). The default:
    /// as close to the path tracer as `auto` at the sample scenes' vertices, at a third of its
    /// time or less (README, "Presets").
    #[default]
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

/// A [`PatchSize`] always as its text (`auto`, `source` or the length), read back by its
/// parser: for encodings that do not describe themselves, where the JSON form (a length as a
/// number) cannot be told from the others.
mod patch_size_text {
    use super::PatchSize;

    pub fn serialize<S: serde::Serializer>(size: &PatchSize, s: S) -> Result<S::Ok, S::Error> {
        s.collect_str(size)
    }

    pub fn deserialize<'de, D: serde::Deserializer<'de>>(d: D) -> Result<PatchSize, D::Error> {
        let text = <String as serde::Deserialize>::deserialize(d)?;
        text.parse().map_err(serde::de::Error::custom)
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
