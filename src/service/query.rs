//! Query strings: each route's parameters as a struct that refuses the ones it does not have,
//! read by [`StrictQuery`], whose rejections are the API's problem+json 400s naming the
//! parameter (and the value, when it cannot be read).
//!
//! A struct reads each value from its text (with messages that quote it); its `validate`
//! checks the values against each other and the server's limits. `POST /v1/timelines` takes
//! the command line's own request type, [`crate::params::BakeRequest`].

use axum::extract::rejection::QueryRejection;
use axum::extract::{FromRequestParts, Query};
use axum::http::request::Parts;
use serde::Deserialize;
use serde::de::DeserializeOwned;

use super::{ApiError, Config};
use crate::output::lightmap::Quantity;
use crate::params::{MIN_LINES, number, whole};

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

/// The query of a request that takes no parameters.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct NoParameters {}

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
        let max = config.limits.max_lines;
        self.add
            .filter(|n| (MIN_LINES..=max).contains(n))
            .ok_or_else(|| {
                ApiError::Parameter(format!(
                    "add must be a whole number from {MIN_LINES} to {max}"
                ))
            })
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
        Ok(Preview {
            size: (width, height),
            exposure: positive_exposure(self.exposure)?,
            shading: self.shading.unwrap_or_default(),
        })
    }
}

/// The query of `GET /v1/timelines/{id}/frames/{frame}/baked.glb`.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct BakedQuery {
    /// The tone map's exposure of the vertex colours; the timeline's by default.
    #[serde(default, deserialize_with = "number")]
    exposure: Option<f64>,
}

impl BakedQuery {
    /// The exposure (> 0) if one is asked for.
    pub(super) fn validate(self) -> Result<Option<f64>, ApiError> {
        positive_exposure(self.exposure)
    }
}

/// The query of `GET /v1/timelines/{id}/frames/{f}/probes.json`.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct ProbesQuery {
    /// The probes' spacing in scene units; the scene's default if absent.
    #[serde(default, deserialize_with = "number")]
    spacing: Option<f64>,
}

impl ProbesQuery {
    /// The spacing (> 0) if one is asked for.
    pub(super) fn validate(self) -> Result<Option<f64>, ApiError> {
        match self.spacing {
            Some(s) if s <= 0.0 => Err(ApiError::Parameter(format!(
                "spacing must be a positive number, not {s}"
            ))),
            spacing => Ok(spacing),
        }
    }
}

/// The query of a lightmap's routes (`lightmap.glb`, a frame's `lightmap.exr`, `.ktx2`,
/// `.png`).
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct LightmapQuery {
    /// Texels per scene unit; [`crate::output::lightmap::TEXELS_PER_UNIT`] if absent.
    #[serde(default, deserialize_with = "number")]
    texels_per_unit: Option<f64>,
    /// What the texels hold: `radiance` (by default) or `light`.
    #[serde(default)]
    quantity: Quantity,
}

impl LightmapQuery {
    /// The density (> 0) and the quantity.
    pub(super) fn validate(self) -> Result<(f64, Quantity), ApiError> {
        match self.texels_per_unit {
            Some(t) if t <= 0.0 => Err(ApiError::Parameter(format!(
                "texels_per_unit must be a positive number, not {t}"
            ))),
            t => Ok((
                t.unwrap_or(crate::output::lightmap::TEXELS_PER_UNIT),
                self.quantity,
            )),
        }
    }
}

/// The query of `GET /v1/timelines/{id}/viewer`: the view the page opens with. Its script
/// reads them; they are checked here too, so a bad link is a 400 naming the parameter rather
/// than a page that quietly shows something else.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct ViewerQuery {
    /// The frame shown first.
    #[serde(default, deserialize_with = "whole")]
    #[allow(dead_code)] // read by the page
    frame: Option<u64>,
    /// The exposure; the timeline's by default.
    #[serde(default, deserialize_with = "number")]
    exposure: Option<f64>,
    /// `none`, `error` or `samples`.
    #[serde(default)]
    #[allow(dead_code)] // read by the page
    overlay: Option<Overlay>,
    /// `yaw,pitch,zoom`: degrees, degrees, distance over the one that frames the scene.
    #[serde(default)]
    orbit: Option<String>,
}

/// The viewer's false colours.
#[derive(Deserialize)]
#[serde(rename_all = "lowercase")]
enum Overlay {
    None,
    Error,
    Samples,
}

impl ViewerQuery {
    /// Checks the values the types do not: a positive exposure, an orbit of three finite
    /// numbers with a positive zoom.
    pub(super) fn validate(self) -> Result<(), ApiError> {
        positive_exposure(self.exposure)?;
        if let Some(orbit) = self.orbit {
            let numbers: Vec<Option<f64>> = (orbit.split(','))
                .map(|x| x.trim().parse::<f64>().ok().filter(|x| x.is_finite()))
                .collect();
            match numbers[..] {
                [Some(_), Some(_), Some(zoom)] if zoom > 0.0 => {}
                _ => {
                    return Err(ApiError::Parameter(format!(
                        "orbit: {orbit:?} is not yaw,pitch,zoom (degrees, degrees, and a zoom \
                         above 0, such as 35,-25,1)"
                    )));
                }
            }
        }
        Ok(())
    }
}

/// The query of `GET /v1/timelines/{id}/lightmapped`: the three.js example's first view and
/// the lightmap's and probes' parameters it passes on.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct LightmappedQuery {
    /// The frame shown first.
    #[serde(default, deserialize_with = "whole")]
    #[allow(dead_code)] // read by the page
    frame: Option<u64>,
    /// The exposure; the timeline's by default.
    #[serde(default, deserialize_with = "number")]
    exposure: Option<f64>,
    /// `yaw,pitch,zoom`, as the viewer's.
    #[serde(default)]
    orbit: Option<String>,
    /// Texels per scene unit.
    #[serde(default, deserialize_with = "number")]
    texels_per_unit: Option<f64>,
    /// The probes' spacing.
    #[serde(default, deserialize_with = "number")]
    probe_spacing: Option<f64>,
}

impl LightmappedQuery {
    /// Checks the view as the viewer's, and a positive density and spacing.
    pub(super) fn validate(self) -> Result<(), ApiError> {
        ViewerQuery {
            frame: self.frame,
            exposure: self.exposure,
            overlay: None,
            orbit: self.orbit,
        }
        .validate()?;
        LightmapQuery {
            texels_per_unit: self.texels_per_unit,
            quantity: Quantity::Light,
        }
        .validate()?;
        if let Some(s) = self.probe_spacing.filter(|&s| s <= 0.0) {
            return Err(ApiError::Parameter(format!(
                "probe_spacing must be a positive number, not {s}"
            )));
        }
        Ok(())
    }
}

/// An exposure asked for, if it is positive.
fn positive_exposure(exposure: Option<f64>) -> Result<Option<f64>, ApiError> {
    match exposure {
        Some(e) if e <= 0.0 => Err(ApiError::Parameter(format!(
            "exposure must be a positive number, not {e}"
        ))),
        exposure => Ok(exposure),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::params::{BakeRequest, Limits};
    use crate::timeline::Preset;

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
            assert_eq!(read::<BakeRequest>(query).err().unwrap(), detail);
        }
        let detail = read::<BakeRequest>("seed=-1").err().unwrap();
        assert!(
            detail.starts_with("seed: \"-1\" is not a whole number"),
            "{detail}"
        );
        let detail = read::<BakeRequest>("sky=1,x,2,3").err().unwrap();
        assert!(
            detail.starts_with("sky: \"1,x,2,3\" is not r,g,b"),
            "{detail}"
        );
    }

    #[test]
    fn a_create_query_is_checked_against_the_limits_and_the_shared_rules() {
        let limits = Limits::default();
        let create = |query: &str| read::<BakeRequest>(query).unwrap().validate(&limits);
        let settings = create("fps=12&preset=draft&sky=1,0.5,0&start=0&end=1").unwrap();
        // Patches are the source's triangles unless asked otherwise; a patch budget alone asks
        // for them to be cut where the light needs them.
        assert_eq!(settings.patch_size, crate::params::PatchSize::Source);
        assert!(settings.adaptive(0).is_none());
        let budgeted = create("preset=draft&patch_budget=700").unwrap();
        assert_eq!(budgeted.adaptive(0).map(|a| a.budget), Some(700));
        let load = &settings.load;
        assert_eq!(
            (load.fps, load.start, load.end),
            (12.0, Some(0.0), Some(1.0))
        );
        assert_eq!(
            (settings.lines.lines, settings.lines.seed),
            (Preset::Draft.lines(), 1)
        );
        assert_eq!(settings.sky, [1.0, 0.5, 0.0]);
        let settings = create("").unwrap();
        assert_eq!(
            (settings.lines.lines, settings.sky),
            (Preset::Default.lines(), [0.0; 3])
        );
        let settings = create("patch_size=auto&lines=200000").unwrap();
        assert_eq!(settings.adaptive(0).map(|a| a.budget), Some(1000));
        assert!(settings.load.patch_size.is_none());
        let settings = create("patch_size=source").unwrap();
        assert!(settings.adaptive(0).is_none() && settings.load.patch_size.is_none());
        let settings = create("patch_size=auto&patch_budget=5000").unwrap();
        assert_eq!(settings.adaptive(0).map(|a| a.budget), Some(5000));
        // A budget below the scene's own patches: merges bring it down to it.
        assert_eq!(settings.adaptive(9000).map(|a| a.budget), Some(5000));
        assert_eq!(
            create("patch_size=auto")
                .unwrap()
                .adaptive(9000)
                .map(|a| a.budget),
            Some(9000)
        );
        let settings = create("patch_size=0.5").unwrap();
        assert!(settings.adaptive(0).is_none() && settings.load.patch_size == Some(0.5));
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
            let detail = create(query).unwrap_err().to_string();
            assert!(detail.contains(needle), "{query}: {detail}");
        }
    }
}
