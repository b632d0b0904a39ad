//! Query strings: each route's parameters as a struct that refuses the ones it does not have,
//! read by [`StrictQuery`], whose rejections are the API's problem+json 400s naming the
//! parameter (and the value, when it cannot be read).
//!
//! A struct reads each value from its text (with messages that quote it); its `validate`
//! checks the values against each other and the server's limits. The rules the command line
//! shares (the sky, start and end) are in [`crate::params`].

use std::fmt::Display;
use std::str::FromStr;

use axum::extract::rejection::QueryRejection;
use axum::extract::{FromRequestParts, Query};
use axum::http::request::Parts;
use serde::de::{DeserializeOwned, Error as _};
use serde::{Deserialize, Deserializer};

use super::{ApiError, Config};
use crate::adaptive::Adaptive;
use crate::loader::LoadOptions;
use crate::params::{self, PatchSize, Sky};
use crate::timeline::{LineParams, Preset};

/// axum's [`Query`] with the API's errors: a parameter `T` does not take, or a value it cannot
/// read, is a 400 problem that names it.
pub(super) struct StrictQuery<T>(pub T);

impl<T: DeserializeOwned, S: Send + Sync> FromRequestParts<S> for StrictQuery<T> {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, _state: &S) -> Result<Self, Self::Rejection> {
        Query::try_from_uri(&parts.uri)
            .map(|Query(query)| Self(query))
            .map_err(|rejection| ApiError::Parameter(describe(&rejection)))
    }
}

/// The deserializer's message (`fps: "abc" is not a finite number`, `unknown field ...`)
/// without axum's "Failed to deserialize query string" before it, and serde's words for a
/// struct in the API's: a query string has parameters, not fields.
fn describe(rejection: &QueryRejection) -> String {
    let message = std::error::Error::source(rejection)
        .map_or_else(|| rejection.body_text(), ToString::to_string);
    // serde_path_to_error may put the parameter's name first: "side: unknown field `side`, ...".
    let serde = message
        .split_once(": ")
        .map(|(_, after)| after)
        .filter(|after| {
            ["unknown field ", "duplicate field "]
                .iter()
                .any(|w| after.starts_with(w))
        })
        .unwrap_or(&message);
    if let Some(rest) = serde.strip_prefix("unknown field ") {
        return match rest.strip_suffix(", there are no fields") {
            Some(name) => format!("unknown parameter {name}: this request takes no parameters"),
            None => format!("unknown parameter {rest}"),
        };
    }
    if let Some(name) = serde.strip_prefix("duplicate field ") {
        return format!("parameter {name} is given more than once");
    }
    message
}

/// A finite number.
fn number<'de, D: Deserializer<'de>>(d: D) -> Result<Option<f64>, D::Error> {
    let text = String::deserialize(d)?;
    match text.parse::<f64>() {
        Ok(v) if v.is_finite() => Ok(Some(v)),
        _ => Err(D::Error::custom(format!("{text:?} is not a finite number"))),
    }
}

/// A whole number ≥ 0 of an integer type.
fn whole<'de, D, T>(d: D) -> Result<Option<T>, D::Error>
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

/// The query of a request that takes no parameters.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct NoParameters {}

/// The query of `POST /v1/timelines`: what to load, how many lines, the sky.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct CreateQuery {
    /// Frames per second of the timeline, in (0, 1000]; 24 by default.
    #[serde(default, deserialize_with = "number")]
    fps: Option<f64>,
    /// Number of lines, from 1000 to the server's limit; exclusive with `preset`.
    #[serde(default, deserialize_with = "whole")]
    lines: Option<u64>,
    /// Line budget by name; `default` when neither it nor `lines` is given.
    #[serde(default, deserialize_with = "parsed")]
    preset: Option<Preset>,
    /// Seed of the lines; 1 by default.
    #[serde(default, deserialize_with = "whole")]
    seed: Option<u64>,
    /// How patches are made: `auto`, `source` or the longest edge in scene units
    /// ([`PatchSize`]); `auto` by default.
    #[serde(default, deserialize_with = "parsed")]
    patch_size: Option<PatchSize>,
    /// The animation to play, by name or index; all by default.
    animation: Option<String>,
    /// The previews' camera: a camera node's name or index, or `auto`; the scene's first
    /// camera by default.
    camera: Option<String>,
    /// Radiance of the sky; black by default.
    #[serde(default, deserialize_with = "parsed")]
    sky: Option<Sky>,
    /// Time of the first frame, seconds.
    #[serde(default, deserialize_with = "number")]
    start: Option<f64>,
    /// Time of the last frame, seconds.
    #[serde(default, deserialize_with = "number")]
    end: Option<f64>,
    /// Highest diffuse reflectance, in (0, 1]; [`crate::loader::MAX_REFLECTANCE`] by default.
    #[serde(default, deserialize_with = "number")]
    max_reflectance: Option<f64>,
    /// With `patch_size=auto`: most patches (cuts stop at it, merges bring a scene of more
    /// triangles down to it where they can); one per 200 lines by default.
    #[serde(default, deserialize_with = "whole")]
    patch_budget: Option<u64>,
}

impl CreateQuery {
    /// The load options, lines and sky asked for, checked against each other and `config`'s
    /// limits.
    pub(super) fn validate(
        self,
        config: &Config,
    ) -> Result<(LoadOptions, LineParams, [f64; 3], Option<Adaptive>), ApiError> {
        let fps = self.fps.unwrap_or(24.0);
        if !(fps > 0.0 && fps <= 1000.0) {
            return Err(ApiError::Parameter(format!(
                "fps must be in (0, 1000], not {fps}"
            )));
        }
        let max = config.max_lines;
        let lines = match (self.lines, self.preset) {
            (Some(_), Some(_)) => {
                return Err(ApiError::Parameter("give lines or preset, not both".into()));
            }
            (Some(n), None) if (1_000..=max).contains(&n) => n,
            (Some(n), None) => {
                return Err(ApiError::Parameter(format!(
                    "lines must be an integer in [1000, {max}], not {n}"
                )));
            }
            (None, preset) => preset.unwrap_or(Preset::Default).lines(),
        };
        let patch_size = self.patch_size.unwrap_or_default();
        let auto = match (patch_size, self.patch_budget) {
            (PatchSize::Auto, budget) => Some(
                Adaptive::for_lines(lines, 0)
                    .with_budget(budget.map(|b| b.min(usize::MAX as u64) as usize))
                    .within(config.max_patches),
            ),
            (_, None) => None,
            (_, Some(_)) => {
                return Err(ApiError::Parameter(
                    "patch_budget applies to patch_size=auto only".into(),
                ));
            }
        };
        let options = LoadOptions {
            fps,
            animation: self.animation,
            camera: self.camera,
            start: self.start,
            end: self.end,
            patch_size: patch_size.length(),
            max_frames: config.max_frames,
            max_patches: config.max_patches,
            max_reflectance: self
                .max_reflectance
                .unwrap_or(crate::loader::MAX_REFLECTANCE),
            ..LoadOptions::default()
        };
        params::validate_load(&options)?;
        let lines = LineParams {
            lines,
            seed: self.seed.unwrap_or(1),
        };
        Ok((options, lines, self.sky.unwrap_or_default().0, auto))
    }
}

/// The query of `POST /v1/timelines/{id}/lines`.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RefineQuery {
    /// About how many lines to add, from 1000 to the server's limit.
    #[serde(default, deserialize_with = "whole")]
    add: Option<u64>,
}

impl RefineQuery {
    /// The lines to add, checked against `config`'s limit.
    pub(super) fn validate(self, config: &Config) -> Result<u64, ApiError> {
        let max = config.max_lines;
        self.add
            .filter(|n| (1_000..=max).contains(n))
            .ok_or_else(|| ApiError::Parameter(format!("add must be an integer in [1000, {max}]")))
    }
}

/// The query of `GET /v1/timelines/{id}/stats`.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct StatsQuery {
    /// The frame whose crossings are measured; the first by default.
    #[serde(default, deserialize_with = "whole")]
    frame: Option<usize>,
    /// Whether to list every patch's share of the information gap (off by default: one
    /// number per patch).
    #[serde(default)]
    patches: bool,
}

impl StatsQuery {
    /// The frame, checked against the timeline's `frames`, and whether every patch's share
    /// of the gap is wanted.
    pub(super) fn validate(self, frames: usize) -> Result<(usize, bool), ApiError> {
        let patches = self.patches;
        match self.frame {
            None => Ok((0, patches)),
            Some(f) if f < frames => Ok((f, patches)),
            Some(f) => Err(ApiError::Parameter(format!(
                "frame must be in 0..{frames}, not {f}"
            ))),
        }
    }
}

/// The query of `GET /v1/timelines/{id}/frames/{frame}/preview.png`.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct PreviewQuery {
    /// Width in pixels; 640 by default.
    #[serde(default, deserialize_with = "whole")]
    width: Option<u32>,
    /// Height in pixels; 480 by default.
    #[serde(default, deserialize_with = "whole")]
    height: Option<u32>,
    /// The tone map's exposure; the timeline's by default.
    #[serde(default, deserialize_with = "number")]
    exposure: Option<f64>,
    /// `smooth` (the default: per-vertex, as the baked glTF) or `flat` (per patch).
    #[serde(default)]
    shading: Option<crate::output::Shading>,
}

/// A preview asked for: its size, the exposure if one is asked for, and the shading.
pub(super) struct Preview {
    pub size: (u32, u32),
    pub exposure: Option<f64>,
    pub shading: crate::output::Shading,
}

impl PreviewQuery {
    /// Width, height (each from 1 to [`crate::output::preview::MAX_PREVIEW_SIDE`]), the
    /// exposure (> 0) if one is asked for, and the shading.
    pub(super) fn validate(self) -> Result<Preview, ApiError> {
        let max = crate::output::preview::MAX_PREVIEW_SIDE;
        let side = |name: &str, value: Option<u32>, default: u32| match value {
            None => Ok(default),
            Some(s) if (1..=max).contains(&s) => Ok(s),
            Some(s) => Err(ApiError::Parameter(format!(
                "{name} must be a whole number from 1 to {max}, not {s}"
            ))),
        };
        let (width, height) = (
            side("width", self.width, 640)?,
            side("height", self.height, 480)?,
        );
        match self.exposure {
            Some(e) if e <= 0.0 => Err(ApiError::Parameter(format!(
                "exposure must be a positive number, not {e}"
            ))),
            exposure => Ok(Preview {
                size: (width, height),
                exposure,
                shading: self.shading.unwrap_or_default(),
            }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What [`StrictQuery`] answers for `query`: the value, or the problem's detail.
    fn read<T: DeserializeOwned>(query: &str) -> Result<T, String> {
        let mut parts = axum::http::Request::get(format!("/x?{query}"))
            .body(())
            .unwrap()
            .into_parts()
            .0;
        let extracted = futures_util::FutureExt::now_or_never(
            StrictQuery::<T>::from_request_parts(&mut parts, &()),
        )
        .unwrap();
        match extracted {
            Ok(StrictQuery(value)) => Ok(value),
            Err(ApiError::Parameter(detail)) => Err(detail),
            Err(other) => panic!("{query}: {other:?}"),
        }
    }

    #[test]
    fn unknown_parameters_are_refused_by_name() {
        assert_eq!(
            read::<NoParameters>("side=x").err().unwrap(),
            "unknown parameter `side`: this request takes no parameters"
        );
        assert!(read::<NoParameters>("").is_ok());
        let detail = read::<PreviewQuery>("width=10&side=x").err().unwrap();
        assert!(
            detail.starts_with("unknown parameter `side`, expected one of `width`"),
            "{detail}"
        );
        assert_eq!(
            read::<RefineQuery>("add=1000&add=2000").err().unwrap(),
            "parameter `add` is given more than once"
        );
    }

    #[test]
    fn values_that_cannot_be_read_are_named_and_quoted() {
        for (query, detail) in [
            ("fps=abc", "fps: \"abc\" is not a finite number"),
            ("fps=NaN", "fps: \"NaN\" is not a finite number"),
            ("start=inf", "start: \"inf\" is not a finite number"),
            (
                "preset=ultra",
                "preset: unknown preset \"ultra\": draft, default or final",
            ),
            (
                "patch_size=-1",
                "patch_size: \"-1\" is not auto, source or a positive length in scene units, \
                 such as 0.25",
            ),
        ] {
            assert_eq!(read::<CreateQuery>(query).err().unwrap(), detail);
        }
        let detail = read::<CreateQuery>("seed=-1").err().unwrap();
        assert!(
            detail.starts_with("seed: \"-1\" is not a whole number"),
            "{detail}"
        );
        let detail = read::<CreateQuery>("sky=1,x,2,3").err().unwrap();
        assert!(
            detail.starts_with("sky: \"1,x,2,3\" is not r,g,b"),
            "{detail}"
        );
    }

    #[test]
    fn a_create_query_is_checked_against_the_limits_and_the_shared_rules() {
        let config = Config::default();
        let create = |query: &str| read::<CreateQuery>(query).unwrap().validate(&config);
        let (options, lines, sky, auto) =
            create("fps=12&preset=draft&sky=1,0.5,0&start=0&end=1").unwrap();
        // Patches are cut where the light needs them unless asked otherwise.
        assert_eq!(auto.map(|a| a.budget), Some(500));
        assert_eq!(
            (options.fps, options.start, options.end),
            (12.0, Some(0.0), Some(1.0))
        );
        assert_eq!((lines.lines, lines.seed), (Preset::Draft.lines(), 1));
        assert_eq!(sky, [1.0, 0.5, 0.0]);
        let (_, lines, sky, _) = create("").unwrap();
        assert_eq!((lines.lines, sky), (Preset::Default.lines(), [0.0; 3]));
        let (options, _, _, auto) = create("patch_size=auto&lines=200000").unwrap();
        assert_eq!(auto.map(|a| a.budget), Some(1000));
        assert!(options.patch_size.is_none());
        let (options, _, _, auto) = create("patch_size=source").unwrap();
        assert!(auto.is_none() && options.patch_size.is_none());
        let (_, _, _, auto) = create("patch_size=auto&patch_budget=5000").unwrap();
        assert_eq!(auto.map(|a| a.budget), Some(5000));
        let (options, _, _, auto) = create("patch_size=0.5").unwrap();
        assert!(auto.is_none() && options.patch_size == Some(0.5));
        for (query, needle) in [
            ("start=2&end=1", "start (2 s) is after end (1 s)"),
            ("lines=5", "lines must be"),
            ("lines=2000&preset=draft", "not both"),
            ("fps=0", "fps must be"),
            (
                "patch_size=source&patch_budget=100",
                "patch_budget applies to patch_size=auto",
            ),
        ] {
            let Err(ApiError::Parameter(detail)) = create(query) else {
                panic!("{query} accepted");
            };
            assert!(detail.contains(needle), "{query}: {detail}");
        }
    }
}
