//! The models folder against the real binary: a graph linked to /dev/zero, a FIFO graph, a
//! renderer whose weights lie in `weights.bin`, and a folder of self-links neither stop the
//! start nor a reload; the bundle with external data is never served, so truncating its
//! `weights.bin` (which ONNX Runtime would have memory-mapped: SIGBUS at the next request)
//! leaves the process serving. A graph whose warm-up never ends (an endless `Loop`) is ended at
//! the warm-up's deadline, and the executor serves the other model.

use std::path::{Path, PathBuf};
use std::time::Duration;

use prost::Message;
use scnerf_e2e::{http_request, repo_root, server_binary, Case, ServerProcess};
use scnerf_server::bundle::Manifest;
use serde_json::Value;

/// A model whose graph has one initializer, `extra`, kept in `weights.bin` (ONNX's protobuf by
/// hand: ModelProto.graph (7) > GraphProto.initializer (5) > TensorProto name (8),
/// external_data (13) {key (1), value (2)}, data_location (14) = EXTERNAL). Appended to a
/// serialized model, protobuf merges it into that model's graph.
fn external_initializer() -> Vec<u8> {
    let field = |tag: u8, bytes: &[u8]| [&[tag, bytes.len() as u8][..], bytes].concat();
    let entry = [field(0x0a, b"location"), field(0x12, b"weights.bin")].concat();
    let tensor = [field(0x42, b"extra"), field(0x6a, &entry), vec![0x70, 1]].concat();
    field(0x3a, &field(0x2a, &tensor))
}

fn copy_bundle(to: &Path) {
    let from = repo_root().join("tests/fixtures/parity/bundle");
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap() {
        let path = entry.unwrap().path();
        std::fs::copy(&path, to.join(path.file_name().unwrap())).unwrap();
    }
}

/// `dir`'s renderer with the external initializer appended, its hash and model id updated.
fn with_external_weights(dir: &Path) {
    let renderer = dir.join("renderer.onnx");
    let mut bytes = std::fs::read(&renderer).unwrap();
    bytes.extend(external_initializer());
    std::fs::write(&renderer, bytes).unwrap();
    std::fs::write(dir.join("weights.bin"), vec![0u8; 1 << 16]).unwrap();
    let path = dir.join("manifest.json");
    let mut manifest: Value = serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
    let sha = scnerf_server::bundle::sha256_file(&renderer).unwrap();
    manifest["graphs"]["renderer"]["sha256"] = sha.into();
    write_manifest(&path, manifest);
}

fn mkfifo(path: &Path) {
    let c = std::ffi::CString::new(path.to_str().unwrap()).unwrap();
    // SAFETY: a valid NUL-terminated path.
    assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
}

fn hostile_folder() -> PathBuf {
    let dir = std::env::temp_dir().join(format!("scnerf-e2e-models-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    for name in ["good", "zero", "fifo", "external"] {
        copy_bundle(&dir.join(name));
    }
    std::fs::remove_file(dir.join("zero/renderer.onnx")).unwrap();
    std::os::unix::fs::symlink("/dev/zero", dir.join("zero/renderer.onnx")).unwrap();
    std::fs::remove_file(dir.join("fifo/encoder.onnx")).unwrap();
    mkfifo(&dir.join("fifo/encoder.onnx"));
    with_external_weights(&dir.join("external"));
    for i in 0..40 {
        std::os::unix::fs::symlink(".", dir.join(format!("self{i}"))).unwrap();
    }
    dir
}

fn get_json(server: &ServerProcess, method: &str, path: &str) -> Value {
    let got = http_request(server.addr, method, path, &[], b"", Duration::from_secs(60)).unwrap();
    assert_eq!(got.status, 200, "{path}: {}", String::from_utf8_lossy(&got.body));
    serde_json::from_slice(&got.body).unwrap()
}

fn names(list: &Value) -> Vec<&str> {
    list.as_array().unwrap().iter().map(|m| m["name"].as_str().unwrap()).collect()
}

#[test]
fn a_hostile_models_folder_stops_neither_the_start_nor_a_reload_nor_the_process() {
    let dir = hostile_folder();
    let args = ["--models", dir.to_str().unwrap(), "--skip-warmup"];
    let mut server = ServerProcess::start(&server_binary(), &args);
    server.wait_ready(Duration::from_secs(120));
    assert_eq!(names(&get_json(&server, "GET", "/v1/models")["models"]), ["good"]);

    std::fs::OpenOptions::new().write(true).open(dir.join("external/weights.bin")).unwrap().set_len(0).unwrap();
    let answer = get_json(&server, "POST", "/v1/models/reload");
    assert!(answer["loaded"].as_array().unwrap().is_empty(), "{answer}");
    let reason = |name: &str| {
        let skipped = answer["skipped"].as_array().unwrap();
        skipped.iter().find(|s| s["name"] == name).map(|s| s["reason"].as_str().unwrap().to_string())
    };
    assert!(reason("zero").unwrap().contains("is not a regular file"), "{answer}");
    assert!(reason("fifo").unwrap().contains("is not a regular file"), "{answer}");
    assert!(reason("external").unwrap().contains("keeps its data in an external file"), "{answer}");
    assert_eq!(get_json(&server, "GET", "/healthz")["status"], "ok");
    assert!(server.child.try_wait().unwrap().is_none(), "the server died");
    drop(server);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The ONNX messages an endless encoder needs (onnx.proto3's field numbers).
mod onnx {
    #[derive(Clone, PartialEq, prost::Message)]
    pub struct Model {
        #[prost(int64, tag = "1")]
        pub ir_version: i64,
        #[prost(message, optional, tag = "7")]
        pub graph: Option<Graph>,
        #[prost(message, repeated, tag = "8")]
        pub opset_import: Vec<OpSet>,
    }

    #[derive(Clone, PartialEq, prost::Message)]
    pub struct OpSet {
        #[prost(int64, tag = "2")]
        pub version: i64,
    }

    #[derive(Clone, PartialEq, prost::Message)]
    pub struct Graph {
        #[prost(message, repeated, tag = "1")]
        pub node: Vec<Node>,
        #[prost(string, tag = "2")]
        pub name: String,
        #[prost(message, repeated, tag = "5")]
        pub initializer: Vec<Tensor>,
        #[prost(message, repeated, tag = "11")]
        pub input: Vec<ValueInfo>,
        #[prost(message, repeated, tag = "12")]
        pub output: Vec<ValueInfo>,
    }

    #[derive(Clone, PartialEq, prost::Message)]
    pub struct Node {
        #[prost(string, repeated, tag = "1")]
        pub input: Vec<String>,
        #[prost(string, repeated, tag = "2")]
        pub output: Vec<String>,
        #[prost(string, tag = "4")]
        pub op_type: String,
        #[prost(message, repeated, tag = "5")]
        pub attribute: Vec<Attribute>,
    }

    /// `kind`: AttributeType, INT = 2, GRAPH = 5.
    #[derive(Clone, PartialEq, prost::Message)]
    pub struct Attribute {
        #[prost(string, tag = "1")]
        pub name: String,
        #[prost(int64, tag = "3")]
        pub i: i64,
        #[prost(message, optional, tag = "6")]
        pub g: Option<Graph>,
        #[prost(int32, tag = "20")]
        pub kind: i32,
    }

    /// `data_type`: FLOAT = 1, INT64 = 7, BOOL = 9; the values little-endian in `raw_data`.
    #[derive(Clone, PartialEq, prost::Message)]
    pub struct Tensor {
        #[prost(int64, repeated, tag = "1")]
        pub dims: Vec<i64>,
        #[prost(int32, tag = "2")]
        pub data_type: i32,
        #[prost(string, tag = "8")]
        pub name: String,
        #[prost(bytes = "vec", tag = "9")]
        pub raw_data: Vec<u8>,
    }

    #[derive(Clone, PartialEq, prost::Message)]
    pub struct ValueInfo {
        #[prost(string, tag = "1")]
        pub name: String,
        #[prost(message, optional, tag = "2")]
        pub r#type: Option<Type>,
    }

    #[derive(Clone, PartialEq, prost::Message)]
    pub struct Type {
        #[prost(message, optional, tag = "1")]
        pub tensor_type: Option<TensorType>,
    }

    #[derive(Clone, PartialEq, prost::Message)]
    pub struct TensorType {
        #[prost(int32, tag = "1")]
        pub elem_type: i32,
        #[prost(message, optional, tag = "2")]
        pub shape: Option<Shape>,
    }

    #[derive(Clone, PartialEq, prost::Message)]
    pub struct Shape {
        #[prost(message, repeated, tag = "1")]
        pub dim: Vec<Dim>,
    }

    #[derive(Clone, PartialEq, prost::Message)]
    pub struct Dim {
        #[prost(int64, optional, tag = "1")]
        pub dim_value: Option<i64>,
        #[prost(string, optional, tag = "2")]
        pub dim_param: Option<String>,
    }
}

const FLOAT: i32 = 1;
const INT64: i32 = 7;
const BOOL: i32 = 9;

fn node(op_type: &str, input: &[&str], output: &str, attribute: Vec<onnx::Attribute>) -> onnx::Node {
    let input = input.iter().map(|s| s.to_string()).collect();
    onnx::Node { input, output: vec![output.into()], op_type: op_type.into(), attribute }
}

fn tensor(name: &str, data_type: i32, dims: &[i64], raw_data: Vec<u8>) -> onnx::Tensor {
    onnx::Tensor { dims: dims.to_vec(), data_type, name: name.into(), raw_data }
}

/// A value of `elem_type` and shape `dims` (numbers, or named sizes).
fn value(name: &str, elem_type: i32, dims: &[&str]) -> onnx::ValueInfo {
    let dim = dims
        .iter()
        .map(|d| match d.parse() {
            Ok(n) => onnx::Dim { dim_value: Some(n), dim_param: None },
            Err(_) => onnx::Dim { dim_value: None, dim_param: Some(d.to_string()) },
        })
        .collect();
    let tensor_type = onnx::TensorType { elem_type, shape: Some(onnx::Shape { dim }) };
    onnx::ValueInfo { name: name.into(), r#type: Some(onnx::Type { tensor_type: Some(tensor_type) }) }
}

/// An encoder with the parity bundle's signature (`images` [3, 3, H, W] -> `features`
/// [3, 32, h, w]) that never returns: a `Loop` with no trip count whose condition stays true,
/// carrying the sum of the images (an input, so that ONNX Runtime cannot fold the loop away when
/// it loads the graph).
fn endless_encoder() -> Vec<u8> {
    let body = onnx::Graph {
        node: vec![node("Identity", &["go_in"], "go_out", vec![]), node("Add", &["sum_in", "one"], "sum_out", vec![])],
        name: "step".into(),
        initializer: vec![tensor("one", FLOAT, &[], 1f32.to_le_bytes().to_vec())],
        input: vec![value("i", INT64, &[]), value("go_in", BOOL, &[]), value("sum_in", FLOAT, &[])],
        output: vec![value("go_out", BOOL, &[]), value("sum_out", FLOAT, &[])],
    };
    let keepdims = onnx::Attribute { name: "keepdims".into(), i: 0, g: None, kind: 2 };
    let loop_body = onnx::Attribute { name: "body".into(), i: 0, g: Some(body), kind: 5 };
    let shape: Vec<u8> = [3i64, 32, 1, 1].iter().flat_map(|d| d.to_le_bytes()).collect();
    let graph = onnx::Graph {
        node: vec![
            node("ReduceSum", &["images"], "sum", vec![keepdims]),
            node("Loop", &["", "go", "sum"], "total", vec![loop_body]),
            node("Expand", &["total", "shape"], "features", vec![]),
        ],
        name: "endless_encoder".into(),
        initializer: vec![tensor("go", BOOL, &[], vec![1]), tensor("shape", INT64, &[4], shape)],
        input: vec![value("images", FLOAT, &["3", "3", "H", "W"])],
        output: vec![value("features", FLOAT, &["3", "32", "h", "w"])],
    };
    let model = onnx::Model { ir_version: 8, graph: Some(graph), opset_import: vec![onnx::OpSet { version: 17 }] };
    model.encode_to_vec()
}

/// `dir`'s encoder replaced by [`endless_encoder`], its hash updated.
fn with_endless_encoder(dir: &Path) {
    let encoder = dir.join("encoder.onnx");
    std::fs::write(&encoder, endless_encoder()).unwrap();
    let path = dir.join("manifest.json");
    let mut manifest: Value = serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
    manifest["graphs"]["encoder"]["sha256"] = scnerf_server::bundle::sha256_file(&encoder).unwrap().into();
    write_manifest(&path, manifest);
}

/// Writes `manifest` to `path` with the model id its graphs give.
fn write_manifest(path: &Path, manifest: Value) {
    let mut manifest: Manifest = serde_json::from_value(manifest).unwrap();
    manifest.model_id = manifest.expected_model_id();
    std::fs::write(path, serde_json::to_vec(&manifest).unwrap()).unwrap();
}

/// A model whose encoder never returns is refused at its warm-up's deadline, its run ended there
/// (ONNX Runtime's terminate flag): the other model's next render is answered, where the run
/// would have held the one executor thread for good.
#[test]
fn an_endless_graph_is_ended_at_its_warm_up_deadline_and_the_other_model_serves() {
    let dir = std::env::temp_dir().join(format!("scnerf-e2e-endless-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    copy_bundle(&dir.join("good"));
    let args = ["--models", dir.to_str().unwrap(), "--warmup-timeout-secs", "3"];
    let mut server = ServerProcess::start(&server_binary(), &args);
    server.wait_ready(Duration::from_secs(120));

    copy_bundle(&dir.join("endless"));
    with_endless_encoder(&dir.join("endless"));
    let answer = get_json(&server, "POST", "/v1/models/reload");
    assert!(answer["loaded"].as_array().unwrap().is_empty(), "{answer}");
    let skipped = answer["skipped"].as_array().unwrap();
    let endless = skipped.iter().find(|s| s["name"] == "endless").expect("endless skipped");
    assert!(endless["reason"].as_str().unwrap().contains("did not finish within 3 s"), "{answer}");

    let case = Case::load(&repo_root().join("tests/fixtures/parity/cases/opencv_64x96")).unwrap();
    let (content_type, body) = case.multipart(&case.request);
    let headers = [("content-type", content_type.as_str()), ("x-scnerf-deadline-ms", "60000")];
    let got = http_request(server.addr, "POST", "/v1/render", &headers, &body, Duration::from_secs(90)).unwrap();
    assert_eq!(got.status, 200, "{}", String::from_utf8_lossy(&got.body));
    assert_eq!(get_json(&server, "GET", "/readyz")["status"], "ready");
    drop(server);
    std::fs::remove_dir_all(&dir).unwrap();
}
