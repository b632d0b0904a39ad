//! `POST /v1/timelines/{id}/materials`: new emission or reflectance per material and new
//! intensity or colour per light, checked as one change and re-solved from the kept tallies
//! without tracing.

use axum::body::Bytes;
use axum::extract::{Path, State};
use axum::response::Response;

use super::jobs::{LightSetting, Work};
use super::query::{NoParameters, StrictQuery};
use super::{ApiError, AppState, job, rerun};
use crate::scene::Material;

/// One material change of `POST /v1/timelines/{id}/materials`.
#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct MaterialChange {
    /// The material, by name or index.
    material: serde_json::Value,
    /// New emission, RGB, in the scene's emission units.
    emission: Option<[f64; 3]>,
    /// New diffuse reflectance, RGB in [0, 1], at most the timeline's `max_reflectance`.
    reflectance: Option<[f64; 3]>,
}

/// One light's change in `POST /v1/timelines/{id}/materials`.
#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct LightChange {
    /// The light, by name or index (in the file's `KHR_lights_punctual` order of use).
    light: serde_json::Value,
    /// New intensity: candela for point and spot lights, lux for directional ones.
    intensity: Option<f64>,
    /// New linear RGB colour.
    color: Option<[f64; 3]>,
}

/// The body of `POST /v1/timelines/{id}/materials`.
#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct Relight {
    #[serde(default)]
    materials: Vec<MaterialChange>,
    #[serde(default)]
    lights: Vec<LightChange>,
}

impl Relight {
    /// Applies the changes to `materials` and `lights`; the first that is invalid (an unknown
    /// name or index, a value out of range, a reflectance above `max_reflectance`) is a 400
    /// naming it, and what was changed before it is the caller's to discard.
    fn apply(
        self,
        materials: &mut [Material],
        lights: &mut [LightSetting],
        max_reflectance: f64,
    ) -> Result<(), ApiError> {
        let names: Vec<Option<String>> = materials.iter().map(|m| m.name.clone()).collect();
        for change in self.materials {
            let index = find_by_name_or_index(&change.material, &names, "material")?;
            if let Some(e) = change.emission {
                materials[index].emission = non_negative_rgb("emission", e)?;
            }
            if let Some(r) = change.reflectance {
                if r.iter().any(|v| !(0.0..=1.0).contains(v)) {
                    return Err(ApiError::Parameter(format!(
                        "reflectance must be three numbers in [0, 1], not {r:?}"
                    )));
                }
                materials[index].reflectance = r;
                // Refused, not lowered as a file's would be: a request is done as sent or not.
                if materials[index].reflects_above(max_reflectance) {
                    return Err(ApiError::Parameter(format!(
                        "material {} ({}): reflectance {r:?} is above the timeline's \
                         max_reflectance {}; a closed scene that reflects everything has no \
                         steady state (post the scene with a higher max_reflectance, at most 1, \
                         to allow it)",
                        index,
                        names[index].as_deref().unwrap_or("unnamed"),
                        max_reflectance
                    )));
                }
            }
        }
        let names: Vec<Option<String>> = lights.iter().map(|l| l.name.clone()).collect();
        for change in self.lights {
            let first = find_by_name_or_index(&change.light, &names, "light")?;
            // A light used by several nodes is several lights of one name: a name changes them all.
            let indices: Vec<usize> = match &change.light {
                serde_json::Value::String(_) => (0..names.len())
                    .filter(|&i| names[i] == names[first])
                    .collect(),
                _ => vec![first],
            };
            for index in indices {
                if let Some(i) = change.intensity {
                    if !i.is_finite() || i < 0.0 {
                        return Err(ApiError::Parameter(format!(
                            "intensity must be a finite number ≥ 0, not {i}"
                        )));
                    }
                    lights[index].intensity = i;
                }
                if let Some(c) = change.color {
                    lights[index].colour = non_negative_rgb("color", c)?;
                }
                if lights[index].power().iter().any(|p| !p.is_finite()) {
                    return Err(ApiError::Parameter(format!(
                        "light {}: color × intensity overflows",
                        change.light
                    )));
                }
            }
        }
        Ok(())
    }
}

/// `rgb` if its three values are finite and ≥ 0; otherwise a 400 naming the field.
fn non_negative_rgb(field: &str, rgb: [f64; 3]) -> Result<[f64; 3], ApiError> {
    if rgb.iter().all(|v| v.is_finite() && *v >= 0.0) {
        Ok(rgb)
    } else {
        Err(ApiError::Parameter(format!(
            "{field} must be three finite numbers ≥ 0, not {rgb:?}"
        )))
    }
}

/// The index in `names` of `wanted` (a number or a name); `what` names the kind in the error.
fn find_by_name_or_index(
    wanted: &serde_json::Value,
    names: &[Option<String>],
    what: &str,
) -> Result<usize, ApiError> {
    match wanted {
        serde_json::Value::Number(n) => n.as_u64().map(|i| i as usize).filter(|&i| i < names.len()),
        serde_json::Value::String(name) => names
            .iter()
            .position(|m| m.as_deref() == Some(name.as_str())),
        _ => None,
    }
    .ok_or_else(|| {
        let listed: Vec<String> = names
            .iter()
            .enumerate()
            .map(|(i, m)| format!("{i} ({})", m.as_deref().unwrap_or("unnamed")))
            .collect();
        ApiError::Parameter(format!(
            "no {what} {wanted}; the scene has {}",
            if listed.is_empty() {
                "none".to_string()
            } else {
                listed.join(", ")
            }
        ))
    })
}

/// `POST /v1/timelines/{id}/materials`: new emission or reflectance per material, re-solved
/// from the kept tallies without tracing.
pub(super) async fn relight_timeline(
    State(state): State<AppState>,
    Path(id): Path<String>,
    _: StrictQuery<NoParameters>,
    body: Bytes,
) -> Result<Response, ApiError> {
    let job = job(&state, &id)?;
    let relight: Relight = serde_json::from_slice(&body).map_err(|e| {
        ApiError::Parameter(format!(
            "the body must be {{\"materials\": [{{\"material\", \"emission\", \"reflectance\"}}], \
             \"lights\": [{{\"light\", \"intensity\", \"color\"}}]}}: {e}"
        ))
    })?;
    let target = job.clone();
    let change = move || {
        target.change_lighting(|materials, lights| {
            relight.apply(materials, lights, target.max_reflectance)
        })
    };
    rerun(&state, job, Work::Relight, change)
}

#[cfg(test)]
mod tests {
    use super::Relight;
    use crate::loader::{LoadOptions, load};
    use crate::service::jobs::Job;
    use crate::solve::SolveParams;
    use crate::timeline::LineParams;

    fn cornell_job() -> Job {
        let sample = crate::samples::all().swap_remove(0);
        let scene = load(sample.gltf.as_bytes(), &LoadOptions::default()).unwrap();
        let lines = LineParams {
            lines: 1000,
            seed: 1,
        };
        let table = serde_json::Value::Null;
        Job::new(
            "t".into(),
            scene,
            lines,
            SolveParams::default(),
            0.99,
            table,
            None,
        )
    }

    /// The materials a job would solve with next, read through a change that makes none.
    fn materials(job: &Job) -> Vec<crate::scene::Material> {
        let mut seen = Vec::new();
        job.change_lighting(|m, _| {
            seen = m.to_vec();
            Ok::<(), ()>(())
        })
        .unwrap();
        seen
    }

    #[test]
    fn a_relight_is_kept_whole_or_not_at_all() {
        let job = cornell_job();
        let before = materials(&job);
        let change = |body: serde_json::Value| -> Relight { serde_json::from_value(body).unwrap() };
        // A valid change followed by an unknown material: refused, the first change not kept.
        let partly = change(serde_json::json!({"materials": [
            {"material": 0, "emission": [5, 5, 5]},
            {"material": "nope", "emission": [1, 1, 1]},
        ]}));
        let refused = job.change_lighting(|m, l| partly.apply(m, l, job.max_reflectance));
        let message = refused.unwrap_err().to_string();
        assert!(message.contains("no material \"nope\""), "{message}");
        assert_eq!(materials(&job), before);
        // Above the timeline's max_reflectance: refused.
        let bright =
            change(serde_json::json!({"materials": [{"material": 0, "reflectance": [1, 1, 1]}]}));
        assert!(
            job.change_lighting(|m, l| bright.apply(m, l, job.max_reflectance))
                .is_err()
        );
        assert_eq!(materials(&job), before);
        // Valid: kept.
        let valid =
            change(serde_json::json!({"materials": [{"material": 0, "emission": [5, 5, 5]}]}));
        job.change_lighting(|m, l| valid.apply(m, l, job.max_reflectance))
            .unwrap();
        assert_eq!(materials(&job)[0].emission, [5.0; 3]);
        assert_eq!(materials(&job)[1..], before[1..]);
    }
}
