//! The model endpoints: `GET /v1/models` (every model served, the default marked) and
//! `POST /v1/models/reload` (a rescan of `--models DIR` that loads the bundle folders not served
//! yet). Both are behind the bearer token when one is set (auth.rs guards every route but its
//! public ones).

use axum::extract::State;
use axum::Json;
use serde::Serialize;

use super::openapi::refusals::{ReloadRefusals, TokenRefusals};
use super::state::AppState;
use crate::error::ApiError;
use crate::models::{ModelInfo, Reloaded};

/// `GET /v1/models` body.
#[derive(Debug, Serialize, serde::Deserialize, utoipa::ToSchema)]
pub struct ModelList {
    /// In the order they were loaded: the `--bundle` flags', then `--models DIR`'s by path.
    pub models: Vec<ModelInfo>,
    /// The model of requests that name none.
    pub default: String,
}

/// The models this server serves; requests choose one with `"model"`.
#[utoipa::path(get, path = "/v1/models", tag = "render", operation_id = "models", responses(
    (status = 200, description = "The models served", body = ModelList),
    TokenRefusals,
), security((), ("bearer" = [])))]
pub async fn list(State(state): State<AppState>) -> Json<ModelList> {
    let default = state.models.default_model().name.to_string();
    Json(ModelList { models: state.models.describe(), default })
}

/// Rescans `--models DIR` and loads every bundle folder not served yet (each verified, its
/// graphs loaded and warmed up); a folder that cannot serve is skipped with the reason, and
/// nothing already served changes. Without `--models`, nothing is rescanned. The reload runs
/// as a task of its own: a client that leaves does not cut a model's load short (whose slot
/// would otherwise have to be emptied), and the model is served once loaded.
#[utoipa::path(post, path = "/v1/models/reload", tag = "render", operation_id = "reload_models", responses(
    (status = 200, description = "What the rescan loaded and skipped", body = Reloaded),
    ReloadRefusals,
), security((), ("bearer" = [])))]
pub async fn reload(State(state): State<AppState>) -> Result<Json<Reloaded>, ApiError> {
    let models = state.models.clone();
    let reloaded = tokio::spawn(async move { models.reload().await }).await;
    reloaded.map(Json).map_err(|e| ApiError::Internal(format!("the reload failed: {e}")))
}
