//! Schema-only types: what the OpenAPI document says about bodies that no Rust type parses or
//! writes as a whole (multipart forms, raw bytes). The JSON bodies are described by the types
//! that parse them (`request::wire`, its camera `scnerf_capture::wire`) and write them
//! (`http::respond`).

use utoipa::ToSchema;

/// Raw bytes: a PNG/JPEG file, a PNG response, or a protobuf message.
#[derive(ToSchema)]
#[schema(value_type = String, format = Binary)]
#[allow(dead_code)]
pub struct Binary(Vec<u8>);

/// `multipart/form-data` body of `POST /v1/render`.
#[derive(ToSchema)]
#[allow(dead_code)]
pub struct RenderMultipart {
    /// The JSON request (RenderRequest) without `image` fields.
    #[schema(content_media_type = "application/json")]
    request: String,
    #[schema(value_type = String, format = Binary, content_media_type = "image/png")]
    source_0: Vec<u8>,
    #[schema(value_type = String, format = Binary, content_media_type = "image/png")]
    source_1: Vec<u8>,
    #[schema(value_type = String, format = Binary, content_media_type = "image/png")]
    source_2: Vec<u8>,
}

/// `multipart/form-data` body of `POST /v1/captures`: one part per file of the capture folder,
/// each named `file`, its filename the file's path in the folder (`images/r_0.png`).
#[derive(ToSchema)]
#[allow(dead_code)]
pub struct CaptureMultipart {
    #[schema(value_type = Vec<String>, format = Binary)]
    file: Vec<Vec<u8>>,
}

/// `multipart/form-data` body of `POST /v1/scenes` (parts `source_0` .. `source_{N-1}`, N up
/// to max_scene_views).
#[derive(ToSchema)]
#[allow(dead_code)]
pub struct SceneMultipart {
    /// The JSON scene request (SceneRequest) without `image` fields.
    #[schema(content_media_type = "application/json")]
    request: String,
    #[schema(value_type = String, format = Binary, content_media_type = "image/png")]
    source_0: Vec<u8>,
    #[schema(value_type = String, format = Binary, content_media_type = "image/png")]
    source_1: Vec<u8>,
    #[schema(value_type = String, format = Binary, content_media_type = "image/png")]
    source_2: Vec<u8>,
}
