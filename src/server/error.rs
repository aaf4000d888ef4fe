//! API errors: every failure is JSON `{error, detail}` with its status.

use axum::extract::rejection::JsonRejection;
use axum::extract::{FromRequest, Request};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde::de::DeserializeOwned;
use serde::Serialize;
use utoipa::ToSchema;

/// Why the supervisor refused or failed a request; the HTTP layer maps each
/// kind to its status ([`ApiError`]).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SupervisorError {
    /// No such run or queue item.
    #[error("{0}")]
    NotFound(String),
    /// The request is malformed or does not fit the rig.
    #[error("{0}")]
    Invalid(String),
    /// The request conflicts with the rig's or the run's state.
    #[error("{0}")]
    Conflict(String),
    /// The daemon cannot take it now (shutting down, the engine busy).
    #[error("{0}")]
    Unavailable(String),
    /// Something failed inside the daemon (a run directory, the disk).
    #[error("{0}")]
    Internal(String),
    /// A device failed or did not answer (manual control, rig check).
    #[error("{0}")]
    Device(String),
}

impl SupervisorError {
    /// [`SupervisorError::NotFound`].
    pub fn not_found(detail: impl Into<String>) -> Self {
        SupervisorError::NotFound(detail.into())
    }
    /// [`SupervisorError::Invalid`].
    pub fn invalid(detail: impl Into<String>) -> Self {
        SupervisorError::Invalid(detail.into())
    }
    /// [`SupervisorError::Conflict`].
    pub fn conflict(detail: impl Into<String>) -> Self {
        SupervisorError::Conflict(detail.into())
    }
    /// [`SupervisorError::Unavailable`].
    pub fn unavailable(detail: impl Into<String>) -> Self {
        SupervisorError::Unavailable(detail.into())
    }
    /// [`SupervisorError::Internal`].
    pub fn internal(detail: impl Into<String>) -> Self {
        SupervisorError::Internal(detail.into())
    }
}

/// The body of every error answer.
#[derive(Debug, Clone, Serialize, serde::Deserialize, ToSchema)]
pub struct ErrorBody {
    /// A short machine-readable code: `bad_request`, `invalid`, `unauthorized`,
    /// `not_found`, `method_not_allowed`, `request_timeout`, `conflict`,
    /// `payload_too_large`, `unsupported_media_type`, `device` (a device
    /// failed), `unavailable` (shutting down, or too many connections),
    /// `internal`; from `/peers/{name}/…`, `peer_unreachable` (502) and
    /// `peer_timeout` (504).
    pub error: String,
    /// What went wrong, for a person.
    pub detail: String,
}

/// An error answer.
#[derive(Debug, Clone, thiserror::Error)]
#[error("{status}: {detail}")]
pub struct ApiError {
    /// HTTP status of the answer; it also picks `ErrorBody::error`.
    pub status: StatusCode,
    /// What went wrong, for a person (`ErrorBody::detail`).
    pub detail: String,
}

impl ApiError {
    /// An error answer with this status and detail.
    pub fn new(status: StatusCode, detail: impl Into<String>) -> Self {
        ApiError {
            status,
            detail: detail.into(),
        }
    }
    /// 400: the request cannot be read (malformed JSON, query or path).
    pub fn bad_request(detail: impl Into<String>) -> Self {
        Self::new(StatusCode::BAD_REQUEST, detail)
    }
    /// 422: the request reads fine but a value is unusable.
    pub fn invalid(detail: impl Into<String>) -> Self {
        Self::new(StatusCode::UNPROCESSABLE_ENTITY, detail)
    }
    /// 404: no such run, item, plan or file.
    pub fn not_found(detail: impl Into<String>) -> Self {
        Self::new(StatusCode::NOT_FOUND, detail)
    }
    /// 409: the rig's or a run's state does not allow it now.
    pub fn conflict(detail: impl Into<String>) -> Self {
        Self::new(StatusCode::CONFLICT, detail)
    }
    /// 401: the token is missing or wrong.
    pub fn unauthorized(detail: impl Into<String>) -> Self {
        Self::new(StatusCode::UNAUTHORIZED, detail)
    }
    /// 500: something failed inside the daemon.
    pub fn internal(detail: impl Into<String>) -> Self {
        Self::new(StatusCode::INTERNAL_SERVER_ERROR, detail)
    }

    /// The machine-readable code of a status.
    pub fn code(status: StatusCode) -> &'static str {
        match status.as_u16() {
            400 => "bad_request",
            401 => "unauthorized",
            404 => "not_found",
            405 => "method_not_allowed",
            408 => "request_timeout",
            409 => "conflict",
            413 => "payload_too_large",
            415 => "unsupported_media_type",
            422 => "invalid",
            502 => "device",
            503 => "unavailable",
            s if s >= 500 => "internal",
            _ => "error",
        }
    }
}

impl From<SupervisorError> for ApiError {
    fn from(e: SupervisorError) -> ApiError {
        use SupervisorError as S;
        match e {
            S::NotFound(d) => ApiError::not_found(d),
            S::Invalid(d) => ApiError::invalid(d),
            S::Conflict(d) => ApiError::conflict(d),
            S::Unavailable(d) => ApiError::new(StatusCode::SERVICE_UNAVAILABLE, d),
            S::Internal(d) => ApiError::internal(d),
            S::Device(d) => ApiError::new(StatusCode::BAD_GATEWAY, d),
        }
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let body = ErrorBody {
            error: Self::code(self.status).to_string(),
            detail: self.detail,
        };
        let mut resp = (self.status, Json(body)).into_response();
        if self.status == StatusCode::UNAUTHORIZED {
            resp.headers_mut().insert(
                axum::http::header::WWW_AUTHENTICATE,
                axum::http::HeaderValue::from_static("Bearer"),
            );
        }
        resp
    }
}

impl From<JsonRejection> for ApiError {
    fn from(r: JsonRejection) -> Self {
        // Syntax errors are 400, well-formed bodies with wrong fields 422, a
        // missing JSON content type 415, an oversized body 413.
        ApiError::new(r.status(), r.body_text())
    }
}

/// `Json<T>` whose rejections are JSON errors.
#[derive(Debug, Clone, Copy, Default)]
pub struct ApiJson<T>(pub T);

impl<T, S> FromRequest<S> for ApiJson<T>
where
    T: DeserializeOwned,
    S: Send + Sync,
{
    type Rejection = ApiError;

    async fn from_request(req: Request, state: &S) -> Result<Self, Self::Rejection> {
        match Json::<T>::from_request(req, state).await {
            Ok(Json(v)) => Ok(ApiJson(v)),
            Err(r) => Err(r.into()),
        }
    }
}

/// An optional JSON body (`Option<ApiJson<T>>`): none when the request
/// has no body; a body is read as [`ApiJson`] reads it, and one without
/// `Content-Type: application/json` is refused (415) rather than ignored.
impl<T, S> axum::extract::OptionalFromRequest<S> for ApiJson<T>
where
    T: DeserializeOwned,
    S: Send + Sync,
{
    type Rejection = ApiError;

    async fn from_request(req: Request, state: &S) -> Result<Option<Self>, Self::Rejection> {
        if req.headers().contains_key(axum::http::header::CONTENT_TYPE) {
            return <ApiJson<T> as FromRequest<S>>::from_request(req, state)
                .await
                .map(Some);
        }
        let bytes = axum::body::Bytes::from_request(req, state)
            .await
            .map_err(|r| ApiError::new(r.status(), r.body_text()))?;
        if bytes.is_empty() {
            Ok(None)
        } else {
            Err(ApiError::new(
                StatusCode::UNSUPPORTED_MEDIA_TYPE,
                "a body needs `Content-Type: application/json` (or send none)",
            ))
        }
    }
}

/// Unknown routes.
pub async fn not_found() -> ApiError {
    ApiError::not_found("no such route")
}

/// Known routes, wrong method.
pub async fn method_not_allowed() -> ApiError {
    ApiError::new(
        StatusCode::METHOD_NOT_ALLOWED,
        "this route does not take that method",
    )
}

/// `Path<T>` whose rejections (e.g. invalid UTF-8 after percent-decoding)
/// are JSON errors.
#[derive(Debug, Clone, Copy, Default)]
pub struct ApiPath<T>(pub T);

impl<T, S> axum::extract::FromRequestParts<S> for ApiPath<T>
where
    T: DeserializeOwned + Send,
    S: Send + Sync,
{
    type Rejection = ApiError;

    async fn from_request_parts(
        parts: &mut axum::http::request::Parts,
        state: &S,
    ) -> Result<Self, Self::Rejection> {
        match axum::extract::Path::<T>::from_request_parts(parts, state).await {
            Ok(axum::extract::Path(v)) => Ok(ApiPath(v)),
            Err(r) => Err(ApiError::new(r.status(), r.body_text())),
        }
    }
}

/// `Query<T>` whose rejections (a value of the wrong type, a missing
/// parameter) are JSON errors: 400 with the reason.
#[derive(Debug, Clone, Copy, Default)]
pub struct ApiQuery<T>(pub T);

impl<T, S> axum::extract::FromRequestParts<S> for ApiQuery<T>
where
    T: DeserializeOwned + Send,
    S: Send + Sync,
{
    type Rejection = ApiError;

    async fn from_request_parts(
        parts: &mut axum::http::request::Parts,
        state: &S,
    ) -> Result<Self, Self::Rejection> {
        match axum::extract::Query::<T>::from_request_parts(parts, state).await {
            Ok(axum::extract::Query(v)) => Ok(ApiQuery(v)),
            Err(r) => Err(ApiError::bad_request(r.body_text())),
        }
    }
}
