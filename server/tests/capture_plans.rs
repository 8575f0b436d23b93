//! `POST /v1/captures/plan`: what a client sends of a capture folder, from its listing (the
//! viewer and the Python client ask it instead of choosing themselves). Images by extension in
//! any case, hidden files never, `images_1` no set, a pick by the limit and by `downscale`, the
//! resize `POST /v1/captures` would make, every dataset format's plan uploaded as it says, and
//! bad listings refused naming the entry.

mod common;

use axum::Router;
use common::*;
use scnerf_server::http::{router, ServiceOptions};
use scnerf_server::request::Limits;
use scnerf_server::testing::{bundle, png, state_with_options, FakeRunner};
use serde_json::{json, Value};

const PLAN: &str = "/v1/captures/plan";

fn app(limits: Limits) -> Router {
    let b = bundle("scnerf", "near_far");
    let runner = FakeRunner::new(&b);
    router(state_with_options(b, runner, limits, ServiceOptions::default(), 8))
}

fn with_limit(max_source_pixels: u64) -> Router {
    app(Limits { max_source_pixels, ..Limits::default() })
}

async fn ask(app: &Router, body: &Value) -> Value {
    let got = send(app.clone(), json_to(PLAN, body, &[])).await;
    assert_eq!(got.0, 200, "{}", String::from_utf8_lossy(&got.2));
    json_of(&got)
}

fn strings(v: &Value) -> Vec<&str> {
    v.as_array().unwrap().iter().map(|s| s.as_str().unwrap()).collect()
}

fn paths(v: &Value) -> Vec<&str> {
    v.as_array().unwrap().iter().map(|f| f["path"].as_str().unwrap()).collect()
}

/// An LLFF capture as distributed, its names as phones and tools spell them, with what a folder
/// also holds (a Finder file, a hidden image, notes) and an `images_1` that is no set.
const LLFF: [&str; 12] = [
    "poses_bounds.npy",
    "images/IMG_0000.JPG",
    "images/IMG_0001.jpeg",
    "images_4/IMG_0000.Png",
    "images_4/IMG_0001.PNG",
    "images_8/IMG_0000.png",
    "images_8/IMG_0001.png",
    "images_1/IMG_0000.JPG",
    ".DS_Store",
    "images_4/._IMG_0000.Png",
    "notes.md",
    "sparse/0/cameras.BIN",
];

fn llff_sizes() -> Value {
    json!([
        {"path": "images/IMG_0000.JPG", "width": 4032, "height": 3024},
        {"path": "images_4/IMG_0000.Png", "width": 1008, "height": 756},
        {"path": "images_8/IMG_0000.png", "width": 504, "height": 378},
        {"path": "images_1/IMG_0000.JPG", "width": 640, "height": 480},
    ])
}

#[tokio::test]
async fn a_listing_is_asked_for_its_first_images_sizes_then_planned() {
    let app = with_limit(1 << 20);
    let first = ask(&app, &json!({"files": LLFF})).await;
    // one image a folder, hidden ones never, in listing order; nothing else decided yet
    assert_eq!(
        strings(&first["sizes_needed"]),
        ["images/IMG_0000.JPG", "images_4/IMG_0000.Png", "images_8/IMG_0000.png", "images_1/IMG_0000.JPG"]
    );
    assert_eq!((first["send"].as_array().unwrap().len(), first["image_set"].is_null()), (0, true));

    let plan = ask(&app, &json!({"files": LLFF, "sizes": llff_sizes()})).await;
    assert_eq!(plan["sizes_needed"], json!([]));
    assert_eq!((plan["format"].as_str(), plan["image_set"].as_str()), (Some("llff"), Some("images_4")));
    assert_eq!(
        plan["image_sets"],
        json!([{"folder": "images", "factor": 1, "width": 4032, "height": 3024},
               {"folder": "images_4", "factor": 4, "width": 1008, "height": 756},
               {"folder": "images_8", "factor": 8, "width": 504, "height": 378}]),
        "images_1 is no set"
    );
    assert_eq!(
        paths(&plan["send"]),
        [
            "poses_bounds.npy",
            "images_4/IMG_0000.Png",
            "images_4/IMG_0001.PNG",
            "images_1/IMG_0000.JPG",
            "sparse/0/cameras.BIN"
        ]
    );
    assert!(plan["send"].as_array().unwrap().iter().all(|f| f.get("resize").is_none()), "{plan}");
    let left_out: Vec<(&str, &str)> = plan["left_out"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| (f["path"].as_str().unwrap(), f["reason"].as_str().unwrap()))
        .collect();
    assert_eq!(
        left_out,
        [
            ("images/IMG_0000.JPG", "other_image_set"),
            ("images/IMG_0001.jpeg", "other_image_set"),
            ("images_8/IMG_0000.png", "other_image_set"),
            ("images_8/IMG_0001.png", "other_image_set"),
            (".DS_Store", "hidden"),
            ("images_4/._IMG_0000.Png", "hidden"),
            ("notes.md", "not_capture_file"),
        ]
    );
    let notes = strings(&plan["notes"]);
    assert_eq!(
        notes[0],
        "image set: images_4 (1008x756) of images (4032x3024), images_4 (1008x756), images_8 (504x378): the largest \
         within the server's limit of 1048576 pixels per source view (downscale N picks another)"
    );
    assert!(notes[1].starts_with("not sent: notes.md, neither images"), "{notes:?}");

    // downscale picks the set whatever the limit; one the capture lacks is refused naming those it has
    let eight = ask(&app, &json!({"files": LLFF, "sizes": llff_sizes(), "downscale": 8})).await;
    assert_eq!(eight["image_set"], "images_8");
    assert_eq!(paths(&eight["send"])[1..3], ["images_8/IMG_0000.png", "images_8/IMG_0001.png"]);
    let full = ask(&app, &json!({"files": LLFF, "sizes": llff_sizes(), "downscale": 1})).await;
    let over = &full["send"][1];
    assert_eq!(over["path"], "images/IMG_0000.JPG");
    assert_eq!(over["resize"], json!({"from": {"width": 4032, "height": 3024}, "to": {"width": 1182, "height": 886}}));
    let got =
        send(app.clone(), json_to(PLAN, &json!({"files": LLFF, "sizes": llff_sizes(), "downscale": 2}), &[])).await;
    assert_error(&got, 422, "invalid_request", Some("downscale"));
    assert!(json_of(&got)["error"]["message"].as_str().unwrap().contains("no images_2 folder; the capture has images"));
}

/// An LLFF capture of the fixtures' images (8x6) with `images_2/` (4x3) beside them.
fn llff_with_two_sets() -> Vec<(String, Vec<u8>)> {
    let mut files = files_of(&datasets().join("llff"));
    files.extend((0..4).map(|i| (format!("images_2/IMG_000{i}.png"), png(4, 3, [40 * i as u8, 90, 160, 255]))));
    files
}

/// Plans `files` as a client does: the listing, then the sizes asked for, read from the images.
async fn plan_of(app: &Router, files: &[(String, Vec<u8>)], downscale: Option<u32>) -> Value {
    let names: Vec<&str> = files.iter().map(|(n, _)| n.as_str()).collect();
    let mut body = json!({"files": names});
    if let Some(n) = downscale {
        body["downscale"] = json!(n);
    }
    let first = ask(app, &body).await;
    let sizes: Vec<Value> = strings(&first["sizes_needed"])
        .into_iter()
        .map(|path| {
            let bytes = &files.iter().find(|(n, _)| n == path).unwrap().1;
            let header = scnerf_capture::images::read_header(std::io::Cursor::new(bytes)).unwrap();
            json!({"path": path, "width": header.width, "height": header.height})
        })
        .collect();
    body["sizes"] = json!(sizes);
    let plan = ask(app, &body).await;
    assert_eq!(plan["sizes_needed"], json!([]), "{plan}");
    plan
}

async fn post_capture(app: &Router, files: &[(String, Vec<u8>)], plan: &Value) -> Value {
    let send = paths(&plan["send"]);
    let parts: Vec<(&str, Option<&str>, &str, &[u8])> = files
        .iter()
        .filter(|(n, _)| send.contains(&n.as_str()))
        .map(|(name, data)| ("file", Some(name.as_str()), "application/octet-stream", data.as_slice()))
        .collect();
    assert_eq!(parts.len(), send.len(), "every file the plan sends is listed");
    let (ctype, body) = scnerf_e2e::multipart(&parts);
    let got = send_capture(app, ctype, body).await;
    assert_eq!(got.0, 201, "{}", String::from_utf8_lossy(&got.2));
    json_of(&got)
}

async fn send_capture(app: &Router, ctype: String, body: Vec<u8>) -> Got {
    send(app.clone(), raw_to("POST", "/v1/captures", &ctype, body, &[])).await
}

/// The plan picks the set and the resize `POST /v1/captures` makes of the same files: by the
/// limit, by `downscale`, and when no set fits (the smallest, resized as the server resizes).
#[tokio::test]
async fn the_plan_is_what_post_captures_reads() {
    let files = llff_with_two_sets();
    for (limit, downscale, set, width) in [
        (47, None, "images_2", 4),
        (1 << 20, None, "images", 8),
        (1 << 20, Some(2), "images_2", 4),
        (11, None, "images_2", 3),
    ] {
        let app = with_limit(limit);
        let plan = plan_of(&app, &files, downscale).await;
        assert_eq!(plan["image_set"], set, "{plan}");
        let created = post_capture(&app, &files, &plan).await;
        assert_eq!(created["image_set"], set, "{created}");
        assert_eq!(created["cameras"][0]["width"], width, "{created}");
        assert!(!created["warnings"].to_string().contains("not read"), "only the set planned was sent: {created}");
        if limit == 11 {
            let note = "4 images of 4x3 exceed the server's limit of 11 pixels per source view: resizing them to 3x2";
            let notes = strings(&plan["notes"]);
            assert!(notes[0].ends_with("the smallest; none is within the server's limit of 11 pixels per source view"));
            assert_eq!(notes[1], note, "{plan}");
            assert!(created["warnings"].to_string().contains(note), "the server says the same: {created}");
            let resize = json!({"from": {"width": 4, "height": 3}, "to": {"width": 3, "height": 2}});
            assert!(plan["send"]
                .as_array()
                .unwrap()
                .iter()
                .filter(|f| f["path"].as_str().unwrap().ends_with(".png"))
                .all(|f| f["resize"] == resize));
        }
    }
}

/// Every format's fixture, planned and sent as planned, becomes a scene: the plan leaves out
/// nothing a reader needs (COLMAP's binary model among them).
#[tokio::test]
async fn every_formats_plan_uploads() {
    let app = app(Limits::default());
    for (folder, named, format) in [
        ("blender", Some("blender"), "blender"),
        ("nerfstudio", None, "nerfstudio"),
        ("llff", Some("llff"), "llff"),
        ("colmap", Some("colmap"), "colmap"),
        ("colmap_binary", Some("colmap"), "colmap"),
        ("dtu", Some("dtu"), "dtu"),
    ] {
        let mut files = files_of(&datasets().join(folder));
        files.retain(|(n, _)| n != "expected.json");
        let plan = plan_of(&app, &files, None).await;
        assert_eq!(plan["format"].as_str(), named, "{folder}: {plan}");
        assert_eq!(plan["left_out"], json!([]), "{folder}: {plan}");
        let created = post_capture(&app, &files, &plan).await;
        assert_eq!(created["format"], format, "{folder}");
    }
}

#[tokio::test]
async fn bad_listings_get_4xx_naming_the_field() {
    let app = with_limit(1 << 20);
    let refused = |body: Value, status: u16, field: &'static str| {
        let app = app.clone();
        async move {
            let got = send(app, json_to(PLAN, &body, &[])).await;
            let code = match status {
                400 => "malformed_request",
                413 => "payload_too_large",
                _ => "invalid_request",
            };
            assert_error(&got, status, code, Some(field));
            json_of(&got)["error"]["message"].as_str().unwrap().to_string()
        }
    };
    // malformed: 400 naming the field
    refused(json!({}), 400, "files").await;
    refused(json!({"files": "images/a.png"}), 400, "files").await;
    refused(json!({"files": ["a.json", 7]}), 400, "files[1]").await;
    refused(
        json!({"files": ["a.json"], "sizes": [{"path": "a.png", "width": -1, "height": 2}]}),
        400,
        "sizes[0].width",
    )
    .await;
    refused(json!({"files": ["a.json"], "sizes": [{"path": "a.png", "width": 1}]}), 400, "sizes[0].height").await;
    refused(json!({"files": ["a.json"], "downscale": 0}), 400, "downscale").await;
    refused(json!({"files": ["a.json"], "recursive": true}), 400, "recursive").await;
    // what cannot be planned: 422 naming the entry
    let llff = |extra: &str| json!({"files": ["poses_bounds.npy", "images/a.png", extra]});
    assert!(refused(json!({"files": []}), 422, "files").await.contains("no files"));
    assert!(refused(llff("../b.png"), 422, "files[2]").await.contains("not a relative path inside the capture folder"));
    assert!(refused(llff("/etc/passwd"), 422, "files[2]").await.contains("not a relative path"));
    assert!(refused(llff("./images/a.png"), 422, "files[2]").await.contains("listed twice (files[1]"));
    let sized = |path: &str, width: u32| {
        json!({"files": ["poses_bounds.npy", "images/a.png", ".b.png", "c.txt"],
               "sizes": [{"path": "images/a.png", "width": 4, "height": 3}, {"path": path, "width": width, "height": 3}]})
    };
    assert!(refused(sized("images/z.png", 4), 422, "sizes[1]").await.contains("not in `files`"));
    assert!(refused(sized(".b.png", 4), 422, "sizes[1]").await.contains("not an image of the capture"));
    assert!(refused(sized("c.txt", 4), 422, "sizes[1]").await.contains("not an image of the capture"));
    assert!(refused(sized("images/a.png", 4), 422, "sizes[1]").await.contains("given twice"));
    assert!(refused(sized("images/a.png", 0), 422, "sizes[1]").await.contains("no pixels"));
    let message = refused(json!({"files": ["images/a.png", "images/b.png"]}), 422, "files").await;
    assert!(message.starts_with("cannot tell the dataset format"), "{message}");
    let message = refused(json!({"files": [".DS_Store", "notes.md"]}), 422, "files").await;
    assert!(message.contains("none of the 2 files is an image"), "{message}");

    // bounded: a listing is a JSON document of at most --max-json-bytes, --max-json-depth deep
    let small = app_with_json_limit(4096);
    let many: Vec<String> = (0..1000).map(|i| format!("images/IMG_{i:04}.JPG")).collect();
    let got = send(small.clone(), json_to(PLAN, &json!({"files": many}), &[])).await;
    assert_error(&got, 413, "payload_too_large", Some("body"));
    let deep = format!("{{\"files\": {}{}}}", "[".repeat(100), "]".repeat(100));
    let got = send(app.clone(), raw_to("POST", PLAN, "application/json", deep.into_bytes(), &[])).await;
    assert_error(&got, 400, "malformed_request", Some("body"));
    let got = send(app.clone(), raw_to("POST", PLAN, "text/plain", b"{}".to_vec(), &[])).await;
    assert_error(&got, 415, "unsupported_media_type", Some("content-type"));
    let got = send(app.clone(), raw_to("POST", PLAN, "application/json", b"{\"files\": [".to_vec(), &[])).await;
    assert_error(&got, 400, "malformed_request", Some("files"));
}

fn app_with_json_limit(max_json_bytes: usize) -> Router {
    app(Limits { max_json_bytes, ..Limits::default() })
}

#[tokio::test]
async fn the_plan_is_behind_the_token() {
    let app = two_token_app();
    let body = json!({"files": ["transforms.json", "images/a.png"]});
    assert_error(&send(app.clone(), json_to(PLAN, &body, &[])).await, 401, "unauthorized", Some("authorization"));
    let got = send(app, json_to(PLAN, &body, &[("authorization", &bearer(ALICE))])).await;
    assert_eq!(got.0, 200, "{}", String::from_utf8_lossy(&got.2));
}
