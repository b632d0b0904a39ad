//! The API's one error type: every failure becomes `application/problem+json` (RFC 9457) with a
//! 4xx for anything the client sent, and internal details are logged, not sent.

use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::Serialize;

use crate::loader::LoadError;
use crate::params::ParamError;

/// An error answered to a client.
#[derive(Debug, thiserror::Error)]
pub enum ApiError {
    /// A query parameter is unknown, missing or out of range.
    #[error("{0}")]
    Parameter(String),
    /// The body's content type is not a glTF one.
    #[error("{0}")]
    ContentType(String),
    /// The body is over the configured limit.
    #[error("the body exceeds the limit of {0} bytes")]
    TooLarge(usize),
    /// The scene could not be loaded.
    #[error("{0}")]
    Scene(#[from] LoadError),
    /// The job would exceed the memory budget.
    #[error("{0}")]
    Budget(String),
    /// No timeline (or frame) with that id.
    #[error("{0}")]
    NotFound(String),
    /// The resource exists but is not ready (a frame not solved yet, a job still running).
    #[error("{0}")]
    NotReady(String),
    /// The data directory could not store what the request needs kept (a full disk): nothing
    /// was accepted.
    #[error("{0}")]
    Storage(String),
    /// Something went wrong on our side; the detail is logged, not sent.
    #[error("internal error")]
    Internal(String),
}

impl From<ParamError> for ApiError {
    /// A shared rule on parameters ([`crate::params`]) is broken: a bad parameter.
    fn from(e: ParamError) -> Self {
        Self::Parameter(e.to_string())
    }
}

/// The problem document (RFC 9457).
#[derive(Serialize)]
struct Problem {
    #[serde(rename = "type")]
    kind: &'static str,
    title: &'static str,
    status: u16,
    detail: String,
}

impl ApiError {
    fn status_and_kind(&self) -> (StatusCode, &'static str, &'static str) {
        match self {
            Self::Parameter(_) => (
                StatusCode::BAD_REQUEST,
                "/problems/parameter",
                "Bad parameter",
            ),
            Self::ContentType(_) => (
                StatusCode::UNSUPPORTED_MEDIA_TYPE,
                "/problems/content-type",
                "Unsupported content type",
            ),
            Self::TooLarge(_) => (
                StatusCode::PAYLOAD_TOO_LARGE,
                "/problems/too-large",
                "Body too large",
            ),
            Self::Scene(LoadError::Limit(_)) => (
                StatusCode::UNPROCESSABLE_ENTITY,
                "/problems/scene-limit",
                "Scene exceeds a limit",
            ),
            Self::Scene(LoadError::Option(_)) => (
                StatusCode::BAD_REQUEST,
                "/problems/parameter",
                "Bad parameter",
            ),
            Self::Scene(_) => (
                StatusCode::BAD_REQUEST,
                "/problems/invalid-scene",
                "Invalid scene",
            ),
            Self::Budget(_) => (
                StatusCode::UNPROCESSABLE_ENTITY,
                "/problems/memory-budget",
                "Job exceeds the memory budget",
            ),
            Self::NotFound(_) => (StatusCode::NOT_FOUND, "/problems/not-found", "Not found"),
            Self::NotReady(_) => (StatusCode::CONFLICT, "/problems/not-ready", "Not ready"),
            Self::Storage(_) => (
                StatusCode::INSUFFICIENT_STORAGE,
                "/problems/storage",
                "Could not be stored",
            ),
            Self::Internal(_) => (
                StatusCode::INTERNAL_SERVER_ERROR,
                "/problems/internal",
                "Internal error",
            ),
        }
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let (status, kind, title) = self.status_and_kind();
        if let Self::Internal(detail) = &self {
            tracing::error!(%detail, "internal error");
        }
        let problem = Problem {
            kind,
            title,
            status: status.as_u16(),
            detail: self.to_string(),
        };
        let body = serde_json::to_vec(&problem).unwrap_or_default();
        let mut response = (status, body).into_response();
        response.headers_mut().insert(
            header::CONTENT_TYPE,
            HeaderValue::from_static("application/problem+json"),
        );
        response
    }
}
