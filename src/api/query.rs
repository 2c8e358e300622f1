//! The query string of a request read into a typed query. A query that does not fit its type
//! is this API's own refusal (422 `invalid_request` naming the field), taken from the
//! deserialiser's path to the field, never from the framework's wording.

use super::error::{ApiError, ErrorCode};
use axum::extract::FromRequestParts;
use axum::http::StatusCode;
use axum::http::request::Parts;
use serde::de::DeserializeOwned;

/// A typed query string (`?from=...&to=...`).
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct Query<T>(pub(crate) T);

impl<T: DeserializeOwned, S: Send + Sync> FromRequestParts<S> for Query<T> {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, _state: &S) -> Result<Self, ApiError> {
        parse(parts.uri.query().unwrap_or("")).map(Query)
    }
}

/// Reads `query` (without its `?`) into `T`.
pub(crate) fn parse<T: DeserializeOwned>(query: &str) -> Result<T, ApiError> {
    let fields = serde_urlencoded::Deserializer::new(form_urlencoded::parse(query.as_bytes()));
    serde_path_to_error::deserialize(fields).map_err(|e| {
        let field = e.path().to_string();
        let why = e.inner().to_string();
        if field.is_empty() || field == "." {
            // Not one field's value: a missing field or a query of the wrong shape.
            ApiError::new(
                StatusCode::UNPROCESSABLE_ENTITY,
                ErrorCode::InvalidRequest,
                format!("the query does not fit: {why}"),
            )
        } else {
            ApiError::invalid_field(&field, why)
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, serde::Deserialize, PartialEq)]
    struct Window {
        from: Option<String>,
        limit: Option<i64>,
    }

    #[test]
    fn a_query_is_read_and_a_bad_value_names_its_field() {
        assert_eq!(
            parse::<Window>("from=2026-01-01T00%3A00%3A00Z&limit=5").unwrap(),
            Window {
                from: Some("2026-01-01T00:00:00Z".into()),
                limit: Some(5)
            }
        );
        assert_eq!(
            parse::<Window>("").unwrap(),
            Window {
                from: None,
                limit: None
            }
        );
        let e = parse::<Window>("limit=ten").unwrap_err();
        assert_eq!(e.status, StatusCode::UNPROCESSABLE_ENTITY);
        assert_eq!(e.code, ErrorCode::InvalidRequest);
        assert_eq!(e.details.len(), 1);
        assert_eq!(e.details[0].field.as_deref(), Some("limit"));
        assert!(e.details[0].message.contains("invalid digit"), "{e:?}");
    }
}
