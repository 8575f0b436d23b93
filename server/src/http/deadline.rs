//! The start of every POST handler, as an extractor: the service must be ready (503
//! otherwise), and the request gets its deadline, within which its whole handling (body,
//! decoding, inference, encoding) must finish (504 past it).

use std::future::Future;
use std::time::{Duration, Instant};

use axum::extract::FromRequestParts;
use axum::http::request::Parts;
use axum::http::HeaderMap;
use utoipa::openapi::path::{Parameter, ParameterBuilder, ParameterIn};
use utoipa::openapi::schema::{KnownFormat, ObjectBuilder, SchemaFormat, Type};
use utoipa::openapi::Required;

use super::state::AppState;
use crate::auth::Principal;
use crate::backend::{Client, Due};
use crate::error::ApiError;

/// Header with which a client shortens its request's deadline (milliseconds).
pub const DEADLINE_HEADER: &str = "x-scnerf-deadline-ms";

/// When a request started, how long it may take, whether its client chose that, and whose it is
/// (the executor shares its time fairly between clients).
#[derive(Debug, Clone, Copy)]
pub struct Deadline {
    started: Instant,
    budget: Duration,
    chosen: bool,
    client: Client,
}

impl FromRequestParts<AppState> for Deadline {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &AppState) -> Result<Deadline, ApiError> {
        let started = Instant::now();
        state.check_ready()?;
        let chosen = client_budget(&parts.headers)?;
        let budget = chosen.map_or(state.request_timeout, |b| b.min(state.request_timeout));
        let client = parts.extensions.get::<Principal>().and_then(Principal::owner);
        Ok(Deadline { started, budget, chosen: chosen.is_some(), client })
    }
}

/// The header, in the annotation of every handler that takes a `Deadline` (`params(Deadline)`).
impl utoipa::IntoParams for Deadline {
    fn into_params(_: impl Fn() -> Option<ParameterIn>) -> Vec<Parameter> {
        let milliseconds =
            ObjectBuilder::new().schema_type(Type::Integer).format(Some(SchemaFormat::KnownFormat(KnownFormat::Int64)));
        let header = ParameterBuilder::new()
            .name(DEADLINE_HEADER)
            .parameter_in(ParameterIn::Header)
            .required(Required::False)
            .description(Some("Shortens the server's deadline for this request (ms)"))
            .schema(Some(milliseconds.minimum(Some(1))));
        vec![header.build()]
    }
}

impl Deadline {
    pub fn started(&self) -> Instant {
        self.started
    }

    /// When the request is due, for admission to the executor.
    pub fn due(&self) -> Due {
        Due { at: self.started + self.budget, chosen: self.chosen, client: self.client }
    }

    /// Runs a request's handling within its budget. On timeout the work is dropped, and with it
    /// its ticket: the executor drops the request's waiting graph runs.
    pub async fn run<T>(self, work: impl Future<Output = Result<T, ApiError>>) -> Result<T, ApiError> {
        let ms = u64::try_from(self.budget.as_millis()).unwrap_or(u64::MAX);
        match tokio::time::timeout(self.budget, work).await {
            Ok(Err(ApiError::DeadlineExceeded { .. })) | Err(_) => Err(ApiError::DeadlineExceeded { ms }),
            Ok(result) => result,
        }
    }
}

/// Digits alone without a leading zero, as the API document's integer is written: `u64`'s parser
/// would also take `+5000` and `05000`, which a client cannot have meant as a plain number.
fn plain_number(value: &[u8]) -> Option<u64> {
    let digits = !value.is_empty() && value.iter().all(u8::is_ascii_digit) && (value[0] != b'0' || value.len() == 1);
    std::str::from_utf8(value).ok().filter(|_| digits)?.parse().ok()
}

/// The time budget the client asks for, if it does (the configured timeout bounds it). The
/// header sent twice is refused rather than one of its values picked.
fn client_budget(headers: &HeaderMap) -> Result<Option<Duration>, ApiError> {
    let malformed = |message| ApiError::malformed(Some(DEADLINE_HEADER.to_string()), message);
    let mut values = headers.get_all(DEADLINE_HEADER).iter();
    let Some(value) = values.next() else { return Ok(None) };
    if values.next().is_some() {
        return Err(malformed("sent more than once"));
    }
    let ms = plain_number(value.as_bytes())
        .filter(|&ms| ms > 0)
        .ok_or_else(|| malformed("expected a whole number of milliseconds > 0, in plain digits"))?;
    Ok(Some(Duration::from_millis(ms)))
}
