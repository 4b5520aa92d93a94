//! Errors as the HTTP API shows them: `{"error": "...", "field": "..."?}` with a 4xx
//! status for bad input; internal errors are logged and shown without internals.

use axum::{
    Json,
    http::StatusCode,
    response::{IntoResponse, Response},
};
use serde::Serialize;

/// An error a handler returns.
#[derive(Debug, thiserror::Error)]
pub enum AppError {
    /// Malformed or invalid input (400), optionally naming the field.
    #[error("{message}")]
    BadRequest {
        /// What was wrong, for a person.
        message: String,
        /// The field at fault, as a dotted path.
        field: Option<String>,
    },
    /// No such resource (404).
    #[error("{0}")]
    NotFound(String),
    /// Something went wrong inside the service (500); the details are logged only.
    #[error("internal error")]
    Internal(#[source] anyhow::Error),
}

#[derive(Serialize)]
struct Body<'a> {
    error: &'a str,
    #[serde(skip_serializing_if = "Option::is_none")]
    field: Option<&'a str>,
}

impl IntoResponse for AppError {
    fn into_response(self) -> Response {
        let (status, message, field) = match &self {
            Self::BadRequest { message, field } => {
                (StatusCode::BAD_REQUEST, message.as_str(), field.as_deref())
            }
            Self::NotFound(m) => (StatusCode::NOT_FOUND, m.as_str(), None),
            Self::Internal(e) => {
                tracing::error!(error = ?e, "internal error");
                (
                    StatusCode::INTERNAL_SERVER_ERROR,
                    "internal error (see the service log)",
                    None,
                )
            }
        };
        (
            status,
            Json(Body {
                error: message,
                field,
            }),
        )
            .into_response()
    }
}
