//! The models folder against the real binary: a graph linked to /dev/zero, a FIFO graph, a
//! renderer whose weights lie in `weights.bin`, and a folder of self-links neither stop the
//! start nor a reload; the bundle with external data is never served, so truncating its
//! `weights.bin` (which ONNX Runtime would have memory-mapped: SIGBUS at the next request)
//! leaves the process serving.

use std::path::{Path, PathBuf};
use std::time::Duration;

use scnerf_e2e::{http_request, repo_root, server_binary, ServerProcess};
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
    manifest["model_id"] = format!("scnerf-{}-{}", manifest["variant"].as_str().unwrap(), &sha[..12]).into();
    manifest["graphs"]["renderer"]["sha256"] = sha.into();
    std::fs::write(&path, serde_json::to_vec(&manifest).unwrap()).unwrap();
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
