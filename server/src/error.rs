//! Errors as the HTTP API shows them: `{"error": "...", "field": "..."?, "reason": "..."?}`
//! with a 4xx status for bad input; internal errors are logged and shown without
//! internals.

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
    /// No or a wrong bearer token on a command endpoint (401).
    #[error("{0}")]
    Unauthorized(String),
    /// A browser page from another origin tried to command the lab (403).
    #[error("{0}")]
    Forbidden(String),
    /// No such resource (404).
    #[error("{0}")]
    NotFound(String),
    /// The lab refused the command in its current state (409).
    #[error("{message}")]
    Conflict {
        /// What was refused and why, for a person.
        message: String,
        /// The field at fault, if the refusal is about one.
        field: Option<String>,
        /// A machine-readable reason (snake_case).
        reason: Option<&'static str>,
    },
    /// The request body is larger than the limit (413).
    #[error("{0}")]
    PayloadTooLarge(String),
    /// The request body is not of a media type the endpoint accepts (415).
    #[error("{0}")]
    UnsupportedMediaType(String),
    /// The lab is not running (503).
    #[error("{0}")]
    Unavailable(String),
    /// The control loop did not answer the command in time (503, reason
    /// `no_answer`). For a trial's start, `trial` is its record: the
    /// loop's late answer settles it (it runs and finishes as any other, or
    /// the record goes when the loop refused it).
    #[error("the control loop did not answer in time")]
    Unanswered {
        /// The trial whose start is unanswered.
        trial: Option<u64>,
    },
    /// Something went wrong inside the service (500); the details are logged only.
    #[error("internal error")]
    Internal(#[source] anyhow::Error),
}

impl AppError {
    /// A 400 naming a field.
    pub fn field(field: impl Into<String>, message: impl Into<String>) -> Self {
        Self::BadRequest {
            message: message.into(),
            field: Some(field.into()),
        }
    }

    /// The HTTP status this error answers with.
    pub fn status(&self) -> StatusCode {
        match self {
            Self::BadRequest { .. } => StatusCode::BAD_REQUEST,
            Self::Unauthorized(_) => StatusCode::UNAUTHORIZED,
            Self::Forbidden(_) => StatusCode::FORBIDDEN,
            Self::NotFound(_) => StatusCode::NOT_FOUND,
            Self::Conflict { .. } => StatusCode::CONFLICT,
            Self::PayloadTooLarge(_) => StatusCode::PAYLOAD_TOO_LARGE,
            Self::UnsupportedMediaType(_) => StatusCode::UNSUPPORTED_MEDIA_TYPE,
            Self::Unavailable(_) | Self::Unanswered { .. } => StatusCode::SERVICE_UNAVAILABLE,
            Self::Internal(_) => StatusCode::INTERNAL_SERVER_ERROR,
        }
    }
}

impl From<anyhow::Error> for AppError {
    fn from(e: anyhow::Error) -> Self {
        Self::Internal(e)
    }
}

/// The JSON body of every error.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct ErrorBody {
    /// What was wrong, for a person.
    pub error: String,
    /// The field at fault, as a dotted path (`task.movement_time_s`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub field: Option<String>,
    /// A machine-readable reason for refusals (`busy`, `motion_running`, ...).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
    /// With reason `no_answer` on `POST /api/trials`: the trial whose start
    /// the control loop has not answered yet. Its record
    /// (`GET /api/trials/{id}`) settles when the loop answers: the trial
    /// runs and finishes, or the record goes (404) when the loop refused it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub id: Option<u64>,
}

impl IntoResponse for AppError {
    fn into_response(self) -> Response {
        let status = self.status();
        let mut body = ErrorBody {
            error: self.to_string(),
            field: None,
            reason: None,
            id: None,
        };
        match self {
            Self::BadRequest { field, .. } => body.field = field,
            Self::Conflict { field, reason, .. } => {
                body.field = field;
                body.reason = reason.map(str::to_owned);
            }
            Self::Unauthorized(_) => body.field = Some("authorization".into()),
            Self::Unanswered { trial } => {
                body.reason = Some("no_answer".into());
                body.id = trial;
            }
            Self::Internal(e) => {
                tracing::error!(error = ?e, "internal error");
                body.error = "internal error (see the service log)".into();
            }
            _ => {}
        }
        let mut resp = (status, Json(body)).into_response();
        if status == StatusCode::UNAUTHORIZED {
            resp.headers_mut().insert(
                axum::http::header::WWW_AUTHENTICATE,
                axum::http::HeaderValue::from_static("Bearer"),
            );
        }
        resp
    }
}
