//! Hostile input: more than fifty distinct malformed or abusive requests against the real router
//! over the real ONNX Runtime graphs (the committed parity-fixture bundle), each answered with
//! the expected 4xx and a JSON error naming the field; none answered with a 5xx. Afterwards the
//! same server still renders the parity case correctly (one-shot and cached).

mod common;

use std::path::{Path, PathBuf};
use std::time::Duration;

use axum::body::Body;
use axum::http::Request;
use axum::Router;
use base64::Engine;
use common::*;
use prost::Message;
use scnerf_proto::v1 as pb;
use scnerf_server::auth::Auth;
use scnerf_server::http::{router, AppState, ServiceOptions};
use scnerf_server::request::Limits;
use scnerf_server::testing::{ort_pipeline, png_header, ready_state};
use serde_json::{json, Value};

const TOKEN: &str = "hostile-suite-token-5e1f";
const OTHER_TOKEN: &str = "another-client-token-77aa";

fn parity_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/fixtures/parity")
}

fn case_dir() -> PathBuf {
    parity_dir().join("cases/opencv_64x96")
}

/// Limits small enough that "too large" is cheap to send, large enough for the parity case.
fn limits() -> Limits {
    Limits {
        max_body_bytes: 2 << 20,
        max_source_pixels: 256 * 256,
        max_target_pixels: 512 * 512,
        max_json_bytes: 64 << 10,
        max_json_depth: 16,
        max_scene_views: 16,
        max_capture_bytes: 4 << 20,
        max_capture_metadata_bytes: 1 << 20,
    }
}

fn app() -> (Router, AppState) {
    let pipeline = ort_pipeline(&parity_dir().join("bundle"), limits(), 8);
    let options = ServiceOptions {
        request_timeout: Duration::from_secs(600),
        auth: Auth::from_tokens(&[TOKEN, OTHER_TOKEN]),
        ..Default::default()
    };
    let state = ready_state(pipeline, options);
    (router(state.clone()), state)
}

/// The parity case: request JSON (without images) and its three PNGs.
fn parity_request() -> (Value, Vec<Vec<u8>>) {
    let json = serde_json::from_slice(&std::fs::read(case_dir().join("request.json")).unwrap()).unwrap();
    let images = (0..3).map(|i| std::fs::read(case_dir().join(format!("source_{i}.png"))).unwrap()).collect();
    (json, images)
}

fn auth() -> String {
    format!("Bearer {TOKEN}")
}

/// Builds the requests of the suite.
struct Make {
    request: Value,
    images: Vec<Vec<u8>>,
    auth: String,
}

impl Make {
    fn new() -> Make {
        let (request, images) = parity_request();
        Make { request, images, auth: auth() }
    }

    fn headers(&self) -> Vec<(&str, &str)> {
        vec![("authorization", self.auth.as_str())]
    }

    /// The parity request with `edit` applied to its JSON.
    fn edited(&self, edit: impl FnOnce(&mut Value)) -> Value {
        let mut v = self.request.clone();
        edit(&mut v);
        v
    }

    /// A multipart render with the given JSON and the three parity images.
    fn multipart(&self, json: &Value) -> Request<Body> {
        let bytes = serde_json::to_vec(json).unwrap();
        self.parts(&[
            ("request", &bytes),
            ("source_0", &self.images[0]),
            ("source_1", &self.images[1]),
            ("source_2", &self.images[2]),
        ])
    }

    /// The parity multipart render with source `i` replaced by `data`.
    fn with_image(&self, i: usize, data: &[u8]) -> Request<Body> {
        let bytes = serde_json::to_vec(&self.request).unwrap();
        let mut imgs: Vec<&[u8]> = self.images.iter().map(Vec::as_slice).collect();
        imgs[i] = data;
        self.parts(&[("request", &bytes), ("source_0", imgs[0]), ("source_1", imgs[1]), ("source_2", imgs[2])])
    }

    fn parts(&self, parts: &[(&str, &[u8])]) -> Request<Body> {
        multipart_to("/v1/render", parts, &self.headers())
    }

    fn raw(&self, method: &str, path: &str, ctype: &str, body: Vec<u8>) -> Request<Body> {
        raw_to(method, path, ctype, body, &self.headers())
    }

    /// The parity request as an `application/json` body with base64 images.
    fn json_body(&self, edit: impl FnOnce(&mut Value)) -> Request<Body> {
        let mut v = self.request.clone();
        for (i, img) in self.images.iter().enumerate() {
            v["sources"][i]["image"] = json!(b64(img));
        }
        edit(&mut v);
        json_to("/v1/render", &v, &self.headers())
    }

    fn proto(&self, edit: impl FnOnce(&mut pb::RenderRequest)) -> Request<Body> {
        let mut msg = proto_parity(&self.request, &self.images);
        edit(&mut msg);
        self.raw("POST", "/v1/render", "application/x-protobuf", msg.encode_to_vec())
    }
}

/// The parity request as protobuf: RGB only, default background.
fn proto_parity(r: &Value, images: &[Vec<u8>]) -> pb::RenderRequest {
    pb::RenderRequest { background: vec![], outputs: vec!["rgb".into()], ..proto_request(r, images) }
}

/// A JPEG of the given size.
fn jpeg(w: u32, h: u32) -> Vec<u8> {
    let img = image::RgbImage::from_pixel(w, h, image::Rgb([10, 200, 30]));
    let mut out = Vec::new();
    image::DynamicImage::ImageRgb8(img)
        .write_to(&mut std::io::Cursor::new(&mut out), image::ImageFormat::Jpeg)
        .unwrap();
    out
}

struct Case {
    name: &'static str,
    request: Request<Body>,
    status: u16,
    code: &'static str,
    field: Option<&'static str>,
}

fn case(name: &'static str, request: Request<Body>, status: u16, code: &'static str, field: &'static str) -> Case {
    Case { name, request, status, code, field: Some(field) }
}

const BAD: &str = "malformed_request";
const INVALID: &str = "invalid_request";
const MEDIA: &str = "unsupported_media_type";
const LARGE: &str = "payload_too_large";
const NO_SCENE: &str = "scene_not_found";
const UNAUTHORIZED: &str = "unauthorized";

fn cases() -> Vec<Case> {
    let m = Make::new();
    let boundary_ct = format!("multipart/form-data; boundary={BOUNDARY}");
    let req_bytes = serde_json::to_vec(&m.request).unwrap();
    let unknown_scene = "/v1/scenes/0123456789abcdef0123456789abcdef";
    let mut truncated_png = m.images[1].clone();
    truncated_png.truncate(truncated_png.len() / 2);
    let mut truncated_jpeg = jpeg(96, 64);
    truncated_jpeg.truncate(300);
    let deep = format!("{}1{}", "[".repeat(10_000), "]".repeat(10_000));
    let view = json!({"target": m.request["target"], "outputs": ["rgb"]});
    let deadline_header = |v: &'static str| {
        let bytes = serde_json::to_vec(&m.request).unwrap();
        let body = multipart_body(&[
            ("request", &bytes),
            ("source_0", &m.images[0]),
            ("source_1", &m.images[1]),
            ("source_2", &m.images[2]),
        ]);
        raw_to("POST", "/v1/render", &boundary_ct, body, &[("authorization", &m.auth), ("x-scnerf-deadline-ms", v)])
    };
    let deadline_twice = {
        let body = multipart_body(&[
            ("request", &req_bytes),
            ("source_0", &m.images[0]),
            ("source_1", &m.images[1]),
            ("source_2", &m.images[2]),
        ]);
        let headers =
            [("authorization", m.auth.as_str()), ("x-scnerf-deadline-ms", "1"), ("x-scnerf-deadline-ms", "600000")];
        raw_to("POST", "/v1/render", &boundary_ct, body, &headers)
    };
    let request_text = serde_json::to_string(&m.request).unwrap();
    let no_auth = |auth: Option<&str>| {
        let body = multipart_body(&[("request", &req_bytes), ("source_0", &m.images[0])]);
        let headers: Vec<(&str, &str)> = auth.map(|a| ("authorization", a)).into_iter().collect();
        raw_to("POST", "/v1/render", &boundary_ct, body, &headers)
    };
    vec![
        // --- content types and multipart framing
        case(
            "no content type",
            Request::post("/v1/render").header("authorization", auth()).body(Body::from("{}")).unwrap(),
            415,
            MEDIA,
            "content-type",
        ),
        case(
            "text/plain body",
            m.raw("POST", "/v1/render", "text/plain", b"sources=3".to_vec()),
            415,
            MEDIA,
            "content-type",
        ),
        case(
            "unparsable content type",
            m.raw("POST", "/v1/render", "///;;;", b"{}".to_vec()),
            415,
            MEDIA,
            "content-type",
        ),
        case(
            "form-urlencoded body",
            m.raw("POST", "/v1/render", "application/x-www-form-urlencoded", b"a=b".to_vec()),
            415,
            MEDIA,
            "content-type",
        ),
        case(
            "multipart without boundary",
            m.raw("POST", "/v1/render", "multipart/form-data", b"--x--".to_vec()),
            400,
            BAD,
            "content-type",
        ),
        case(
            "multipart cut inside the request part",
            m.raw(
                "POST",
                "/v1/render",
                &boundary_ct,
                format!("--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"request\"\r\n\r\n{{\"sou").into_bytes(),
            ),
            400,
            BAD,
            "request",
        ),
        case(
            "multipart body without any boundary line",
            m.raw("POST", "/v1/render", &boundary_ct, b"just some bytes".to_vec()),
            400,
            BAD,
            "body",
        ),
        case(
            "multipart part without a name",
            m.raw(
                "POST",
                "/v1/render",
                &boundary_ct,
                format!("--{BOUNDARY}\r\nContent-Disposition: form-data\r\n\r\nx\r\n--{BOUNDARY}--\r\n").into_bytes(),
            ),
            400,
            BAD,
            "body",
        ),
        case(
            "request part sent twice",
            m.parts(&[("request", &req_bytes), ("request", &req_bytes)]),
            400,
            BAD,
            "request",
        ),
        case("unknown multipart part", m.parts(&[("request", &req_bytes), ("evil", b"x")]), 400, BAD, "evil"),
        case("no request part", m.parts(&[("source_0", &m.images[0])]), 400, BAD, "request"),
        case(
            "source part beyond the sources",
            m.parts(&[
                ("request", &req_bytes),
                ("source_0", &m.images[0]),
                ("source_1", &m.images[1]),
                ("source_2", &m.images[2]),
                ("source_7", &m.images[2]),
            ]),
            400,
            BAD,
            "source_7",
        ),
        case(
            "missing source part",
            m.parts(&[("request", &req_bytes), ("source_0", &m.images[0]), ("source_2", &m.images[2])]),
            400,
            BAD,
            "source_1",
        ),
        case("request part is not JSON", m.parts(&[("request", b"<xml/>")]), 400, BAD, "request"),
        case(
            "inline image in a multipart request",
            m.multipart(&m.edited(|v| v["sources"][0]["image"] = json!("AAAA"))),
            400,
            BAD,
            "sources[0].image",
        ),
        // --- images
        case("truncated PNG", m.with_image(1, &truncated_png), 400, BAD, "source_1"),
        case("garbage image bytes", m.with_image(0, b"\x00\x01\x02 definitely not an image"), 415, MEDIA, "source_0"),
        case("GIF image", m.with_image(2, b"GIF89a\x01\x00\x01\x00\x00\x00\x00;"), 415, MEDIA, "source_2"),
        case("empty image part", m.with_image(0, b""), 400, BAD, "source_0"),
        case(
            "100000x100000 PNG header (decompression bomb)",
            m.with_image(1, &png_header(100_000, 100_000)),
            422,
            INVALID,
            "source_1",
        ),
        case("1x1 PNG header for a 96x64 camera", m.with_image(0, &png_header(1, 1)), 422, INVALID, "source_0"),
        case(
            "PNG of the wrong size",
            m.with_image(2, &scnerf_server::testing::png(64, 96, [1, 2, 3, 255])),
            422,
            INVALID,
            "source_2",
        ),
        case("truncated JPEG", m.with_image(0, &truncated_jpeg), 400, BAD, "source_0"),
        case(
            "sources of different sizes",
            m.multipart(&m.edited(|v| v["sources"][1]["camera"]["width"] = json!(64))),
            422,
            INVALID,
            "sources[1].camera.width",
        ),
        // --- cameras and numbers
        case(
            "NaN in a pose (protobuf)",
            m.proto(|p| p.sources[0].camera.as_mut().unwrap().pose.as_mut().unwrap().matrix[5] = f64::NAN),
            422,
            INVALID,
            "sources[0].camera.pose.matrix",
        ),
        case("infinite far (protobuf)", m.proto(|p| p.far = f64::INFINITY), 422, INVALID, "far"),
        case(
            "NaN focal length (protobuf)",
            m.proto(|p| {
                if let Some(pb::camera::IntrinsicsKind::Intrinsics(i)) = &mut p.target.as_mut().unwrap().intrinsics_kind
                {
                    i.fx = f64::NAN
                }
            }),
            422,
            INVALID,
            "target.intrinsics",
        ),
        case(
            "singular pose",
            m.multipart(&m.edited(|v| {
                v["target"]["pose"]["matrix"] = json!([[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 1]])
            })),
            422,
            INVALID,
            "target.pose.matrix",
        ),
        case(
            "non-orthonormal rotation",
            m.multipart(&m.edited(|v| v["sources"][2]["camera"]["pose"]["matrix"][0] = json!([2.0, 0.0, 0.0, 0.0]))),
            422,
            INVALID,
            "sources[2].camera.pose.matrix",
        ),
        case(
            "projective last pose row",
            m.multipart(&m.edited(|v| v["target"]["pose"]["matrix"][3] = json!([0, 0, 1, 1]))),
            422,
            INVALID,
            "target.pose.matrix",
        ),
        case(
            "zero focal length",
            m.multipart(&m.edited(|v| v["target"]["intrinsics"]["fx"] = json!(0.0))),
            422,
            INVALID,
            "target.intrinsics",
        ),
        case(
            "negative focal length",
            m.multipart(&m.edited(|v| v["sources"][0]["camera"]["intrinsics"]["fy"] = json!(-100.0))),
            422,
            INVALID,
            "sources[0].camera.intrinsics",
        ),
        case(
            "K with a bad last row",
            m.multipart(&m.edited(|v| {
                let t = v["target"].as_object_mut().unwrap();
                t.remove("intrinsics");
                t.insert("K".into(), json!([[100, 0, 48], [0, 100, 32], [1, 1, 1]]));
            })),
            422,
            INVALID,
            "target.intrinsics",
        ),
        case(
            "both intrinsics and K",
            m.multipart(&m.edited(|v| v["target"]["K"] = json!([[100, 0, 48], [0, 100, 32], [0, 0, 1]]))),
            400,
            BAD,
            "target.K",
        ),
        case(
            "camera without intrinsics",
            m.multipart(&m.edited(|v| {
                v["target"].as_object_mut().unwrap().remove("intrinsics");
            })),
            400,
            BAD,
            "target.intrinsics",
        ),
        case(
            "number beyond f64 (1e400)",
            m.parts(&[(
                "request",
                serde_json::to_string(&m.request).unwrap().replacen("\"near\":", "\"near\":1e400,\"x\":", 1).as_bytes(),
            )]),
            400,
            BAD,
            "near",
        ),
        case(
            "duplicate fx in intrinsics",
            m.parts(&[("request", request_text.replacen("\"fx\":", "\"fx\":1,\"fx\":", 1).as_bytes())]),
            400,
            BAD,
            "sources[0].camera.intrinsics",
        ),
        case(
            "focal length 1e-300",
            m.multipart(&m.edited(|v| v["target"]["intrinsics"]["fx"] = json!(1e-300))),
            422,
            INVALID,
            "target.intrinsics",
        ),
        case(
            "principal point 1e300",
            m.multipart(&m.edited(|v| v["sources"][1]["camera"]["intrinsics"]["cx"] = json!(1e300))),
            422,
            INVALID,
            "sources[1].camera.intrinsics",
        ),
        case(
            "translation 1e300",
            m.multipart(&m.edited(|v| v["target"]["pose"]["matrix"][2][3] = json!(1e300))),
            422,
            INVALID,
            "target.pose.matrix",
        ),
        case(
            "near 1e-300, far 1e300",
            m.multipart(&m.edited(|v| {
                v["near"] = json!(1e-300);
                v["far"] = json!(1e300);
            })),
            422,
            INVALID,
            "near",
        ),
        case("far 1e300", m.proto(|p| p.far = 1e300), 422, INVALID, "far"),
        case(
            "near 1e308 beyond far 1e307 (a 309-digit echo)",
            m.multipart(&m.edited(|v| {
                v["near"] = json!(1e308);
                v["far"] = json!(1e307);
            })),
            422,
            INVALID,
            "far",
        ),
        case(
            "a 309-digit width",
            m.multipart(&m.edited(|v| v["target"]["width"] = json!(1e308))),
            400,
            BAD,
            "target.width",
        ),
        case(
            "protobuf with 100000 empty sources",
            m.raw("POST", "/v1/render", "application/x-protobuf", [0x0a, 0x00].repeat(100_000)),
            422,
            INVALID,
            "sources",
        ),
        case(
            "protobuf scene with 17 sources",
            m.raw("POST", "/v1/scenes", "application/x-protobuf", {
                let mut msg = proto_parity(&m.request, &m.images);
                msg.sources = (0..17).map(|_| msg.sources[0].clone()).collect();
                msg.encode_to_vec()
            }),
            422,
            INVALID,
            "sources",
        ),
        case("protobuf with 4 outputs", m.proto(|p| p.outputs = vec!["rgb".into(); 4]), 422, INVALID, "outputs"),
        case(
            "3x3 pose matrix",
            m.multipart(&m.edited(|v| v["target"]["pose"]["matrix"] = json!([[1, 0, 0], [0, 1, 0], [0, 0, 1]]))),
            400,
            BAD,
            "target.pose.matrix[0]",
        ),
        case(
            "unknown pose kind",
            m.multipart(&m.edited(|v| v["target"]["pose"]["kind"] = json!("camera_to_sky"))),
            400,
            BAD,
            "target.pose.kind",
        ),
        case(
            "missing pose axes",
            m.multipart(&m.edited(|v| {
                v["sources"][2]["camera"]["pose"].as_object_mut().unwrap().remove("axes");
            })),
            400,
            BAD,
            "sources[2].camera.pose.axes",
        ),
        case(
            "negative width",
            m.multipart(&m.edited(|v| v["sources"][0]["camera"]["width"] = json!(-96))),
            400,
            BAD,
            "sources[0].camera.width",
        ),
        case(
            "string where a number belongs",
            m.multipart(&m.edited(|v| v["far"] = json!("far away"))),
            400,
            BAD,
            "far",
        ),
        case(
            "zero-width target",
            m.multipart(&m.edited(|v| v["target"]["width"] = json!(0))),
            422,
            INVALID,
            "target.width",
        ),
        case(
            "100000x100000 target",
            m.multipart(&m.edited(|v| {
                v["target"]["width"] = json!(100_000);
                v["target"]["height"] = json!(100_000);
            })),
            422,
            INVALID,
            "target.width",
        ),
        case(
            "100000x100000 source camera",
            m.multipart(&m.edited(|v| {
                for i in 0..3 {
                    v["sources"][i]["camera"]["width"] = json!(100_000);
                    v["sources"][i]["camera"]["height"] = json!(100_000);
                }
            })),
            422,
            INVALID,
            "sources[0].camera.width",
        ),
        // --- view counts, depth range, background, outputs, negotiation
        case(
            "two source views",
            m.json_body(|v| {
                v["sources"].as_array_mut().unwrap().pop();
            }),
            422,
            INVALID,
            "sources",
        ),
        case(
            "four source views",
            m.json_body(|v| {
                let s = v["sources"][0].clone();
                v["sources"].as_array_mut().unwrap().push(s);
            }),
            422,
            INVALID,
            "sources",
        ),
        case("no source views", m.json_body(|v| v["sources"] = json!([])), 422, INVALID, "sources"),
        case(
            "near equal to far",
            m.multipart(&m.edited(|v| {
                v["near"] = json!(3.0);
                v["far"] = json!(3.0);
            })),
            422,
            INVALID,
            "far",
        ),
        case(
            "near below far in f64, equal in f32 (a NaN render before)",
            m.multipart(&m.edited(|v| {
                v["near"] = json!(2.0);
                v["far"] = json!(2.0000001);
            })),
            422,
            INVALID,
            "far",
        ),
        case(
            "near beyond far",
            m.multipart(&m.edited(|v| {
                v["near"] = json!(5.0);
                v["far"] = json!(2.0);
            })),
            422,
            INVALID,
            "far",
        ),
        case("zero near", m.multipart(&m.edited(|v| v["near"] = json!(0.0))), 422, INVALID, "near"),
        case("negative near", m.multipart(&m.edited(|v| v["near"] = json!(-1.0))), 422, INVALID, "near"),
        case(
            "background out of range",
            m.multipart(&m.edited(|v| v["background"] = json!([0.0, 1.5, 0.0]))),
            422,
            INVALID,
            "background",
        ),
        case(
            "background of two numbers",
            m.multipart(&m.edited(|v| v["background"] = json!([0.0, 1.0]))),
            422,
            INVALID,
            "background",
        ),
        case("empty outputs", m.multipart(&m.edited(|v| v["outputs"] = json!([]))), 422, INVALID, "outputs"),
        case(
            "duplicate output",
            m.multipart(&m.edited(|v| v["outputs"] = json!(["rgb", "rgb"]))),
            422,
            INVALID,
            "outputs[1]",
        ),
        case(
            "unknown output",
            m.multipart(&m.edited(|v| v["outputs"] = json!(["rgb", "normals"]))),
            400,
            BAD,
            "outputs[1]",
        ),
        case(
            "PNG response asked for depth",
            multipart_to(
                "/v1/render",
                &[
                    ("request", &req_bytes),
                    ("source_0", &m.images[0]),
                    ("source_1", &m.images[1]),
                    ("source_2", &m.images[2]),
                ],
                &[("authorization", &m.auth), ("accept", "image/png")],
            ),
            422,
            INVALID,
            "outputs",
        ),
        case(
            "unproducible Accept",
            multipart_to(
                "/v1/render",
                &[
                    ("request", &req_bytes),
                    ("source_0", &m.images[0]),
                    ("source_1", &m.images[1]),
                    ("source_2", &m.images[2]),
                ],
                &[("authorization", &m.auth), ("accept", "text/html")],
            ),
            406,
            "not_acceptable",
            "accept",
        ),
        // --- JSON and body abuse
        case("deeply nested JSON in the request part", m.parts(&[("request", deep.as_bytes())]), 400, BAD, "request"),
        case(
            "deeply nested JSON body",
            m.raw("POST", "/v1/render", "application/json", deep.clone().into_bytes()),
            400,
            BAD,
            "body",
        ),
        case(
            "request part over the JSON limit",
            m.multipart(&m.edited(|v| v["padding"] = json!("x".repeat(70_000)))),
            413,
            LARGE,
            "request",
        ),
        case("unknown top-level field", m.multipart(&m.edited(|v| v["seed"] = json!(7))), 400, BAD, "seed"),
        case(
            "bad base64 image in a JSON body",
            m.json_body(|v| v["sources"][2]["image"] = json!("%%% not base64 %%%")),
            400,
            BAD,
            "sources[2].image",
        ),
        case(
            "JSON body that is not JSON",
            m.raw("POST", "/v1/render", "application/json", b"sources: 3".to_vec()),
            400,
            BAD,
            "body",
        ),
        case(
            "truncated JSON body",
            m.raw("POST", "/v1/render", "application/json", br#"{"sources": [{"camera": {"width": 9"#.to_vec()),
            400,
            BAD,
            "sources[0].camera",
        ),
        case(
            "JSON body with trailing garbage",
            m.raw(
                "POST",
                "/v1/render",
                "application/json",
                [serde_json::to_vec(&m.request).unwrap(), b"}}}".to_vec()].concat(),
            ),
            400,
            BAD,
            "body",
        ),
        case(
            "body over the size limit",
            m.raw("POST", "/v1/render", "application/json", vec![b' '; 3 << 20]),
            413,
            LARGE,
            "body",
        ),
        case(
            "multipart body over the size limit",
            m.parts(&[("request", &req_bytes), ("source_0", &vec![0u8; 3 << 20])]),
            413,
            LARGE,
            "body",
        ),
        case(
            "protobuf garbage",
            m.raw("POST", "/v1/render", "application/x-protobuf", vec![0xff; 64]),
            400,
            BAD,
            "body",
        ),
        case("protobuf without a target", m.proto(|p| p.target = None), 400, BAD, "target"),
        case(
            "protobuf with an unspecified pose kind",
            m.proto(|p| p.sources[1].camera.as_mut().unwrap().pose.as_mut().unwrap().kind = 0),
            400,
            BAD,
            "sources[1].camera.pose.kind",
        ),
        case(
            "protobuf 4x3 pose matrix",
            m.proto(|p| {
                p.target.as_mut().unwrap().pose.as_mut().unwrap().matrix.truncate(12);
            }),
            400,
            BAD,
            "target.pose.matrix",
        ),
        // --- scenes
        case(
            "scene id with path traversal",
            m.raw(
                "POST",
                "/v1/scenes/..%2F..%2Fetc%2Fpasswd/render",
                "application/json",
                serde_json::to_vec(&view).unwrap(),
            ),
            400,
            BAD,
            "scene_id",
        ),
        case(
            "scene id with a character outside A-Za-z0-9._-",
            m.raw("POST", "/v1/scenes/scene%20one/render", "application/json", serde_json::to_vec(&view).unwrap()),
            400,
            BAD,
            "scene_id",
        ),
        case(
            "scene id of dots only",
            m.raw("PUT", "/v1/scenes/..", "application/json", serde_json::to_vec(&view).unwrap()),
            400,
            BAD,
            "scene_id",
        ),
        case(
            "pinned source out of range",
            m.raw(
                "POST",
                &format!("{unknown_scene}/render"),
                "application/json",
                serde_json::to_vec(&serde_json::json!({"target": view["target"], "sources": [0, 1, "2"]})).unwrap(),
            ),
            400,
            BAD,
            "sources[2]",
        ),
        case(
            "scene id too long",
            m.raw("DELETE", &format!("/v1/scenes/{}", "a".repeat(5000)), "application/json", vec![]),
            400,
            BAD,
            "scene_id",
        ),
        case(
            "unknown scene",
            m.raw("POST", &format!("{unknown_scene}/render"), "application/json", serde_json::to_vec(&view).unwrap()),
            404,
            NO_SCENE,
            "scene_id",
        ),
        case(
            "delete an unknown scene",
            m.raw("DELETE", unknown_scene, "application/json", vec![]),
            404,
            NO_SCENE,
            "scene_id",
        ),
        case(
            "scene render sent as multipart",
            multipart_to(&format!("{unknown_scene}/render"), &[("request", b"{}")], &m.headers()),
            415,
            MEDIA,
            "content-type",
        ),
        case(
            "scene render without a target",
            m.raw("POST", &format!("{unknown_scene}/render"), "application/json", br#"{"outputs": ["rgb"]}"#.to_vec()),
            400,
            BAD,
            "target",
        ),
        case(
            "scene creation with a target",
            multipart_to(
                "/v1/scenes",
                &[(
                    "request",
                    &serde_json::to_vec(&m.edited(|v| {
                        v.as_object_mut().unwrap().remove("outputs");
                    }))
                    .unwrap(),
                )],
                &m.headers(),
            ),
            400,
            BAD,
            "target",
        ),
        // --- tokens and headers
        case("no bearer token", no_auth(None), 401, UNAUTHORIZED, "authorization"),
        case("wrong bearer token", no_auth(Some("Bearer not-the-token")), 401, UNAUTHORIZED, "authorization"),
        case(
            "token of the wrong scheme",
            no_auth(Some(&format!("Basic {}", base64::engine::general_purpose::STANDARD.encode(TOKEN)))),
            401,
            UNAUTHORIZED,
            "authorization",
        ),
        case(
            "truncated bearer token",
            no_auth(Some(&format!("Bearer {}", &TOKEN[..TOKEN.len() - 1]))),
            401,
            UNAUTHORIZED,
            "authorization",
        ),
        case("non-numeric deadline header", deadline_header("tomorrow"), 400, BAD, "x-scnerf-deadline-ms"),
        case("deadline header sent twice", deadline_twice, 400, BAD, "x-scnerf-deadline-ms"),
        case("zero deadline header", deadline_header("0"), 400, BAD, "x-scnerf-deadline-ms"),
        case(
            "GET on the render route",
            m.raw("GET", "/v1/render", "application/json", vec![]),
            405,
            "method_not_allowed",
            "method",
        ),
        case("unknown route", m.raw("POST", "/v1/../../admin", "application/json", vec![]), 404, "not_found", "path"),
    ]
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hostile_requests_get_named_4xx_and_the_server_still_renders_correctly() {
    let (app, state) = app();
    let cases = cases();
    let mut names: Vec<&str> = cases.iter().map(|c| c.name).collect();
    names.sort();
    names.dedup();
    assert_eq!(names.len(), cases.len(), "case names must be distinct");
    assert!(cases.len() >= 50, "only {} cases", cases.len());

    let mut failures = Vec::new();
    for c in cases {
        let got = send(app.clone(), c.request).await;
        let body: Value = serde_json::from_slice(&got.2).unwrap_or(Value::Null);
        let ok = got.0.as_u16() == c.status
            && got.1.get("content-type").is_some_and(|v| v == "application/json")
            && body["error"]["code"] == c.code
            && body["error"]["field"].as_str() == c.field
            && body["error"]["message"].as_str().is_some_and(|m| !m.is_empty());
        assert!(got.0.as_u16() < 500, "{}: server error {}: {}", c.name, got.0, String::from_utf8_lossy(&got.2));
        let message = body["error"]["message"].as_str().unwrap_or_default();
        let longest_number = message.split(|c: char| !c.is_ascii_digit()).map(str::len).max().unwrap_or(0);
        assert!(longest_number <= 32, "{}: the message echoes a {longest_number}-digit number", c.name);
        if !ok {
            failures.push(format!(
                "{}: expected {} {} {:?}, got {} {}",
                c.name,
                c.status,
                c.code,
                c.field,
                got.0,
                String::from_utf8_lossy(&got.2)
            ));
        }
    }
    assert!(failures.is_empty(), "{} cases failed:\n{}", failures.len(), failures.join("\n"));
    assert_eq!(state.pipeline().executor().stats().admitted, 0, "no hostile request may hold the executor");

    // Afterwards: the parity case, one-shot and from the cache, matches PyTorch.
    let m = Make::new();
    let accept = [("authorization", m.auth.as_str()), ("accept", "application/json")];
    // The fixture's outputs are PyTorch's full sampling.
    let one_shot = m.edited(|v| {
        v.as_object_mut().unwrap().insert("sampling".into(), json!("full"));
    });
    let bytes = serde_json::to_vec(&one_shot).unwrap();
    let parts: [(&str, &[u8]); 4] =
        [("request", &bytes), ("source_0", &m.images[0]), ("source_1", &m.images[1]), ("source_2", &m.images[2])];
    let got = send(app.clone(), multipart_to("/v1/render", &parts, &accept)).await;
    assert_eq!(got.0, 200, "{}", String::from_utf8_lossy(&got.2));
    check_against_pytorch(&json_of(&got));

    let scene = m.edited(|v| {
        let o = v.as_object_mut().unwrap();
        o.remove("target");
        o.remove("outputs");
    });
    let bytes = serde_json::to_vec(&scene).unwrap();
    let parts: [(&str, &[u8]); 4] =
        [("request", &bytes), ("source_0", &m.images[0]), ("source_1", &m.images[1]), ("source_2", &m.images[2])];
    let created = send(app.clone(), multipart_to("/v1/scenes", &parts, &m.headers())).await;
    assert_eq!(created.0, 201, "{}", String::from_utf8_lossy(&created.2));
    let path = format!("/v1/scenes/{}/render", json_of(&created)["scene_id"].as_str().unwrap());
    let view = json!({"target": m.request["target"], "outputs": m.request["outputs"], "sampling": "full"});
    // Another client's token cannot see the scene.
    let other = format!("Bearer {OTHER_TOKEN}");
    let got = send(app.clone(), json_to(&path, &view, &[("authorization", &other)])).await;
    assert_error(&got, 404, NO_SCENE, Some("scene_id"));
    let got = send(app.clone(), json_to(&path, &view, &accept)).await;
    assert_eq!(got.0, 200, "{}", String::from_utf8_lossy(&got.2));
    check_against_pytorch(&json_of(&got));
}

/// The 8-bit RGB and the depth of a JSON render response against the fixture's PyTorch output.
fn check_against_pytorch(response: &Value) {
    let b64d = |v: &Value| base64::engine::general_purpose::STANDARD.decode(v.as_str().unwrap()).unwrap();
    let read = |name: &str| -> Vec<f32> {
        std::fs::read(case_dir().join(name))
            .unwrap()
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
            .collect()
    };
    let png = image::load_from_memory(&b64d(&response["rgb"]["data"])).unwrap().into_rgb8();
    let rgb: Vec<f32> = png.as_raw().iter().map(|&b| f32::from(b) / 255.0).collect();
    let expected = read("rgb.f32");
    let err = rgb.iter().zip(&expected).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
    assert_eq!(rgb.len(), expected.len());
    assert!(err <= 0.5 / 255.0 + 1e-3, "rgb differs from PyTorch by {err}");
    let depth: Vec<f32> =
        b64d(&response["depth"]["data"]).chunks_exact(4).map(|b| f32::from_le_bytes(b.try_into().unwrap())).collect();
    let expected = read("depth.f32");
    let err = depth.iter().zip(&expected).map(|(a, b)| (a - b).abs() / b.abs().max(1e-3)).fold(0.0f32, f32::max);
    assert!(err <= 1e-3, "depth differs from PyTorch by {err} (relative)");
}
