//! The models folder as hostile or half-written content sees it: devices, FIFOs, links out of
//! the bundle or the folder, link loops, manifests that quote megabytes, bundles refused again
//! and again, a warm-up that never ends (ended at its deadline), a client that leaves mid-reload. Each reload answers,
//! bounded, and leaves the server serving.

mod common;

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use axum::Router;
use common::*;
use scnerf_server::backend::{ExecutorOptions, MemoryBudget};
use scnerf_server::http::{router, AppState};
use scnerf_server::models::{Deadlines, Refusals, Search};
use scnerf_server::testing::{models_state_with, reload_state, request_json, write_bundle, FakeModel};
use serde_json::Value;

fn scratch(test: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("scnerf-folder-{}-{test}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

async fn reload(app: &Router) -> Value {
    let got = send(app.clone(), raw_to("POST", "/v1/models/reload", "application/json", vec![], &[])).await;
    assert_eq!(got.0, 200, "{}", String::from_utf8_lossy(&got.2));
    json_of(&got)
}

fn names(list: &Value) -> Vec<String> {
    list.as_array().unwrap().iter().map(|m| m["name"].as_str().unwrap().to_string()).collect()
}

fn reason_of<'a>(answer: &'a Value, name: &str) -> &'a str {
    let skipped = answer["skipped"].as_array().unwrap();
    skipped.iter().find(|s| s["name"] == name).unwrap_or_else(|| panic!("{name} not skipped: {answer}"))["reason"]
        .as_str()
        .unwrap()
}

fn mkfifo(path: &Path) {
    let c = std::ffi::CString::new(path.to_str().unwrap()).unwrap();
    // SAFETY: a valid NUL-terminated path.
    assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
}

/// Rewrites a bundle's manifest through `edit` (the graphs and their hashes stay).
fn edit_manifest(dir: &Path, edit: impl FnOnce(&mut Value)) {
    let path = dir.join("manifest.json");
    let mut manifest: Value = serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
    edit(&mut manifest);
    std::fs::write(path, serde_json::to_vec(&manifest).unwrap()).unwrap();
}

/// A graph linked to /dev/zero, a FIFO graph, and a graph linked to a secret outside the bundle
/// are refused without being read: the reload answers, quotes no digest of the secret, and
/// loads the good bundle beside them. The start-up scan (`Search` without a memory budget)
/// follows the same rules.
#[tokio::test]
async fn a_reload_reads_no_device_no_fifo_and_nothing_outside_a_bundle() {
    let dir = scratch("hostile");
    let secrets = scratch("hostile-secrets");
    std::fs::write(secrets.join("shadow"), "root:$6$very-secret").unwrap();
    for name in ["zero", "fifo", "shadow", "good"] {
        write_bundle(&dir.join(name), 1.0).unwrap();
    }
    std::fs::remove_file(dir.join("zero/renderer.onnx")).unwrap();
    std::os::unix::fs::symlink("/dev/zero", dir.join("zero/renderer.onnx")).unwrap();
    std::fs::remove_file(dir.join("fifo/encoder.onnx")).unwrap();
    mkfifo(&dir.join("fifo/encoder.onnx"));
    std::fs::remove_file(dir.join("shadow/renderer.onnx")).unwrap();
    std::os::unix::fs::symlink(secrets.join("shadow"), dir.join("shadow/renderer.onnx")).unwrap();

    let app = router(reload_state(&dir, Deadlines::default()));
    let answer = reload(&app).await;
    assert_eq!(names(&answer["loaded"]), ["good"], "{answer}");
    assert!(reason_of(&answer, "zero").contains("graphs.renderer.file \"renderer.onnx\" is not a regular file"));
    assert!(reason_of(&answer, "fifo").contains("graphs.encoder.file \"encoder.onnx\" is not a regular file"));
    assert!(reason_of(&answer, "shadow").contains("leads outside the bundle"), "{answer}");
    let secret_digest = scnerf_server::bundle::sha256_file(&secrets.join("shadow")).unwrap();
    assert!(!answer.to_string().contains(&secret_digest), "{answer}");

    let search = |dir: &Path| Search {
        dir: dir.to_path_buf(),
        served: vec![],
        memory: None,
        refusals: Arc::new(Refusals::default()),
        timeout: Duration::from_secs(60),
    };
    let at_start = search(&dir).run().await;
    let found: Vec<_> = at_start.bundles.iter().map(|b| b.dir.clone()).collect();
    assert_eq!(found, [dir.join("good")]);
    assert_eq!(at_start.skipped.len(), 3);
    std::fs::remove_dir_all(&dir).unwrap();
    std::fs::remove_dir_all(&secrets).unwrap();
}

/// 80 links of the folder to itself and a link out of it: the reload visits each folder once,
/// loads the one bundle once, and says it did not follow the link out.
#[tokio::test]
async fn link_loops_cost_one_visit_and_links_out_of_the_folder_are_not_followed() {
    let dir = scratch("loops");
    let elsewhere = scratch("loops-elsewhere");
    write_bundle(&dir.join("lego"), 1.0).unwrap();
    write_bundle(&elsewhere.join("outside"), 1.0).unwrap();
    for i in 0..80 {
        std::os::unix::fs::symlink(".", dir.join(format!("self{i:02}"))).unwrap();
    }
    std::os::unix::fs::symlink(elsewhere.join("outside"), dir.join("outside")).unwrap();
    let app = router(reload_state(&dir, Deadlines::default()));
    let answer = reload(&app).await;
    assert_eq!(names(&answer["loaded"]), ["lego"], "{answer}");
    assert!(reason_of(&answer, "outside").contains("a link out of the models folder"), "{answer}");
    assert_eq!(answer["skipped"].as_array().unwrap().len(), 1, "{answer}");
    std::fs::remove_dir_all(&dir).unwrap();
    std::fs::remove_dir_all(&elsewhere).unwrap();
}

/// 70 manifests quoting 200 kB each, and one of 2 MiB: the answer lists 64 folders, each reason
/// clipped, counts the rest, and the oversized manifest is refused by its size.
#[tokio::test]
async fn skip_reasons_are_clipped_and_the_list_is_bounded() {
    let dir = scratch("amplify");
    for i in 0..70 {
        let bundle = dir.join(format!("b{i:02}"));
        write_bundle(&bundle, 1.0).unwrap();
        edit_manifest(&bundle, |m| m["variant"] = "x".repeat(200_000).into());
    }
    write_bundle(&dir.join("a-huge"), 1.0).unwrap();
    edit_manifest(&dir.join("a-huge"), |m| m["provenance"]["padding"] = "y".repeat(2 << 20).into());
    let app = router(reload_state(&dir, Deadlines::default()));
    let got = send(app.clone(), raw_to("POST", "/v1/models/reload", "application/json", vec![], &[])).await;
    assert!(got.2.len() < 200_000, "the answer is {} bytes", got.2.len());
    let answer = json_of(&got);
    let skipped = answer["skipped"].as_array().unwrap();
    assert_eq!((skipped.len(), answer["skipped_more"].as_u64()), (64, Some(7)), "{answer}");
    assert!(skipped.iter().all(|s| s["reason"].as_str().unwrap().len() < 1100), "{answer}");
    assert!(reason_of(&answer, "a-huge").contains("more than the 1048576"), "{answer}");
    assert!(reason_of(&answer, "b00").contains("unknown variant \"xxxx"), "{answer}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A bundle refused for what it holds is not read again on the next reload while its files are
/// unchanged; rewritten, it is read again and loads.
#[tokio::test]
async fn a_refused_bundle_is_not_hashed_again_until_it_changes() {
    let dir = scratch("remembered");
    write_bundle(&dir.join("lego"), 1.0).unwrap();
    std::fs::write(dir.join("lego/renderer.onnx"), "a graph of other bytes").unwrap();
    let app = router(reload_state(&dir, Deadlines::default()));
    let first = reload(&app).await;
    assert!(reason_of(&first, "lego").contains("sha256 of renderer.onnx"), "{first}");
    assert!(!reason_of(&first, "lego").contains("not read again"), "{first}");
    let second = reload(&app).await;
    assert!(reason_of(&second, "lego").contains("sha256 of renderer.onnx"), "{second}");
    assert!(reason_of(&second, "lego").contains("not read again"), "{second}");

    std::fs::remove_dir_all(dir.join("lego")).unwrap();
    write_bundle(&dir.join("lego"), 1.0).unwrap();
    let third = reload(&app).await;
    assert_eq!(names(&third["loaded"]), ["lego"], "{third}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A model whose warm-up misses its deadline is not served, and remembered as refused; its
/// graph run (60 s) is ended at the deadline, so the executor serves the next request and
/// /readyz stays ready, where before the run held the executor for the rest of its minute.
#[tokio::test]
async fn a_warm_up_past_its_deadline_is_ended_and_not_served() {
    let dir = scratch("warmup");
    write_bundle(&dir.join("slow"), 1.0).unwrap();
    edit_manifest(&dir.join("slow"), |m| m["provenance"]["delay_ms"] = 60_000.into());
    let deadlines = Deadlines { warm_up: Duration::from_secs(1), ..Deadlines::default() };
    let app = router(reload_state(&dir, deadlines));
    let answer = reload(&app).await;
    assert!(answer["loaded"].as_array().unwrap().is_empty(), "{answer}");
    assert!(reason_of(&answer, "slow").contains("did not finish within 1 s"), "{answer}");
    let listed = json_of(&send(app.clone(), get("/v1/models", &[])).await);
    assert_eq!(names(&listed["models"]), ["first"]);
    // Due well before the slow run's minute would end.
    let render = multipart_with("/v1/render", &request_json(32), 32, &[("x-scnerf-deadline-ms", "20000")]);
    let got = send(app.clone(), render).await;
    assert_eq!(got.0, 200, "{}", String::from_utf8_lossy(&got.2));
    assert_eq!(send(app.clone(), get("/readyz", &[])).await.0, 200);
    let again = reload(&app).await;
    assert!(reason_of(&again, "slow").ends_with("(unchanged since it was refused: not read again)"), "{again}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A client that hangs up while its reload warms a model up does not cut the load short: the
/// model is loaded and listed (no slot of the executor is left holding sessions of a model
/// nobody serves).
#[tokio::test]
async fn a_reload_whose_client_leaves_mid_warm_up_still_serves_the_model() {
    let dir = scratch("hangup");
    write_bundle(&dir.join("lego"), 1.0).unwrap();
    edit_manifest(&dir.join("lego"), |m| m["provenance"]["delay_ms"] = 100.into());
    let state: AppState = reload_state(&dir, Deadlines::default());
    let app = router(state.clone());
    let request = raw_to("POST", "/v1/models/reload", "application/json", vec![], &[]);
    let client = tokio::spawn(send(app.clone(), request));
    while state.pipeline().executor().stats().admitted == 0 {
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    client.abort();
    loop {
        let listed = json_of(&send(app.clone(), get("/v1/models", &[])).await);
        if names(&listed["models"]) == ["first", "lego"] {
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A new model's graphs are held against the memory budget while its sessions are made, as a
/// request's memory is: with the budget taken by others, the load is refused, not squeezed in.
#[tokio::test]
async fn a_new_model_waits_for_room_in_the_budget_like_a_request() {
    let dir = scratch("lease");
    write_bundle(&dir.join("lego"), 1.0).unwrap();
    let budget = MemoryBudget { total: 100_000, reserved: 0 };
    let executor = ExecutorOptions { memory: budget, ..ExecutorOptions::with_capacity(8) };
    let models = vec![FakeModel::new("first", 1.0)];
    let state = models_state_with(models, None, Some(&dir), Default::default(), executor).unwrap();
    let held = state.pipeline().executor().lease(99_900).unwrap();
    let answer = reload(&router(state)).await;
    assert!(answer["loaded"].as_array().unwrap().is_empty(), "{answer}");
    assert!(reason_of(&answer, "lego").starts_with("not enough memory now to load it"), "{answer}");
    drop(held);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A loaded model's free text from its manifest (`provenance.source_kind`) is echoed clipped.
#[tokio::test]
async fn a_loaded_models_manifest_text_is_echoed_clipped() {
    let dir = scratch("echo");
    write_bundle(&dir.join("lego"), 1.0).unwrap();
    edit_manifest(&dir.join("lego"), |m| m["provenance"]["source_kind"] = "z".repeat(100_000).into());
    let app = router(reload_state(&dir, Deadlines::default()));
    let answer = reload(&app).await;
    let source = answer["loaded"][0]["source"].as_str().unwrap();
    assert!(source.starts_with("zzz") && source.chars().count() <= 1001, "{} characters", source.len());
    std::fs::remove_dir_all(&dir).unwrap();
}
