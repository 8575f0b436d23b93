//! Mutation fuzzing of request decoding on a stable toolchain: valid requests in each wire form
//! (JSON with base64 images, multipart, protobuf; render, scene and scene-render bodies) are
//! mutated (bit flips, boundary bytes, inserted, deleted, duplicated and truncated ranges,
//! numbers swapped for extreme ones) and fed to the parsers and the validation. Any panic fails
//! the test and prints the seed and the case number that reproduce it.
//!
//! CI runs a few thousand cases; the long run is
//! `SCNERF_FUZZ_CASES=1000000 cargo test -p scnerf-server --test fuzz -- --nocapture`
//! (`SCNERF_FUZZ_SEED` picks another sequence).

mod common;

use axum::body::Body;
use axum::http::Request;
use common::{b64, images, multipart_body, proto_request, BOUNDARY};
use prost::Message;
use scnerf_proto::v1 as pb;
use scnerf_server::bundle::ModelConfig;
use scnerf_server::http::body::{read_render_request, read_scene_request};
use scnerf_server::http::negotiate::RequestFormat;
use scnerf_server::request::{ImageMode, Limits, RenderRequest, SceneRequest, TargetRequest};
use scnerf_server::testing::{bundle, request_json};
use serde_json::json;

/// xorshift64*: small, fast and reproducible from its seed.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }

    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

const EXTREMES: [&[u8]; 12] =
    [b"1e400", b"-0", b"1e-400", b"NaN", b"18446744073709551616", b"-1", b"0", b"1e308", b"\"", b"[", b"{", b"null"];

fn mutate(rng: &mut Rng, seed: &[u8]) -> Vec<u8> {
    let mut data = seed.to_vec();
    for _ in 0..1 + rng.below(4) {
        let len = data.len().max(1);
        let at = rng.below(len);
        match rng.below(8) {
            0 => {
                if let Some(b) = data.get_mut(at) {
                    *b ^= 1 << rng.below(8);
                }
            }
            1 => {
                if let Some(b) = data.get_mut(at) {
                    *b = [0x00, 0xff, 0x7f, 0x80, b'"', b'{', b'[', b'9'][rng.below(8)];
                }
            }
            2 => {
                let n = 1 + rng.below(16);
                let bytes: Vec<u8> = (0..n).map(|_| rng.next() as u8).collect();
                data.splice(at.min(data.len())..at.min(data.len()), bytes);
            }
            3 => {
                let end = (at + 1 + rng.below(64)).min(data.len());
                data.drain(at.min(end)..end);
            }
            4 => {
                let end = (at + 1 + rng.below(256)).min(data.len());
                let copy = data[at.min(end)..end].to_vec();
                data.splice(at.min(data.len())..at.min(data.len()), copy);
            }
            5 => data.truncate(at),
            6 => {
                // Replace a run of digits (a JSON number) with an extreme token.
                if let Some(start) = (at..data.len()).find(|&i| data[i].is_ascii_digit()) {
                    let end = (start..data.len()).find(|&i| !data[i].is_ascii_digit()).unwrap_or(data.len());
                    data.splice(start..end, EXTREMES[rng.below(EXTREMES.len())].iter().copied());
                }
            }
            _ => {
                // A varint of 10 bytes (2^63 and beyond) where protobuf expects a length.
                let at = at.min(data.len());
                data.splice(at..at, [0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0x01]);
            }
        }
    }
    data
}

/// The seeds: one valid body per decoder.
struct Seeds {
    json_render: Vec<u8>,
    json_scene: Vec<u8>,
    json_target: Vec<u8>,
    multipart_render: Vec<u8>,
    proto_render: Vec<u8>,
    proto_scene: Vec<u8>,
    proto_target: Vec<u8>,
}

fn seeds() -> Seeds {
    let request = request_json(32);
    let imgs = images(32);
    let mut inline = request.clone();
    for (i, img) in imgs.iter().enumerate() {
        inline["sources"][i]["image"] = json!(b64(img));
    }
    let (scene, _) = scnerf_e2e::split_request(&inline);
    let target = json!({"target": request["target"], "outputs": ["rgb", "depth"]});
    let request_bytes = serde_json::to_vec(&request).unwrap();
    let proto = pb::RenderRequest { outputs: vec!["rgb".into(), "opacity".into()], ..proto_request(&request, &imgs) };
    let proto_scene = pb::SceneRequest {
        sources: proto.sources.clone(),
        near: 2.0,
        far: 6.0,
        background: vec![0.5, 0.5, 0.5],
        ..Default::default()
    };
    let proto_target =
        pb::SceneRenderRequest { target: proto.target.clone(), outputs: vec!["depth".into()], ..Default::default() };
    Seeds {
        json_render: serde_json::to_vec(&inline).unwrap(),
        json_scene: serde_json::to_vec(&scene).unwrap(),
        json_target: serde_json::to_vec(&target).unwrap(),
        multipart_render: multipart_body(&[
            ("request", &request_bytes),
            ("source_0", &imgs[0]),
            ("source_1", &imgs[1]),
            ("source_2", &imgs[2]),
        ]),
        proto_render: proto.encode_to_vec(),
        proto_scene: proto_scene.encode_to_vec(),
        proto_target: proto_target.encode_to_vec(),
    }
}

fn request(body: Vec<u8>, content_type: &str) -> Request<Body> {
    Request::post("/v1/render").header("content-type", content_type).body(Body::from(body)).unwrap()
}

/// Decodes and validates one input with the decoder `which`: the status it would answer.
fn exercise(which: usize, data: Vec<u8>, config: &ModelConfig, limits: &Limits, rt: &tokio::runtime::Runtime) -> u16 {
    let multipart = format!("multipart/form-data; boundary={BOUNDARY}");
    let outcome = match which {
        0 => RenderRequest::from_json(&data, ImageMode::Inline, limits)
            .and_then(|r| r.validate(config, limits).map(drop)),
        1 => {
            SceneRequest::from_json(&data, ImageMode::Inline, limits).and_then(|r| r.validate(config, limits).map(drop))
        }
        2 => TargetRequest::from_json(&data, limits).and_then(|r| r.validate(limits).map(drop)),
        3 => rt
            .block_on(read_render_request(RequestFormat::Multipart, request(data, &multipart), limits))
            .and_then(|r| r.validate(config, limits).map(drop)),
        4 => RenderRequest::from_protobuf(&data, limits).and_then(|r| r.validate(config, limits).map(drop)),
        5 => rt
            .block_on(read_scene_request(RequestFormat::Protobuf, request(data, "application/x-protobuf"), limits))
            .and_then(|r| r.validate(config, limits).map(drop)),
        _ => TargetRequest::from_protobuf(&data).and_then(|r| r.validate(limits).map(drop)),
    };
    outcome.map_or_else(|e| e.status().as_u16(), |()| 200)
}

const DECODERS: [&str; 7] = [
    "json render",
    "json scene",
    "json view",
    "multipart render",
    "protobuf render",
    "protobuf scene",
    "protobuf view",
];

#[test]
fn mutated_requests_never_panic_the_decoders() {
    let cases: u64 = std::env::var("SCNERF_FUZZ_CASES").ok().and_then(|v| v.parse().ok()).unwrap_or(3000);
    let seed: u64 = std::env::var("SCNERF_FUZZ_SEED").ok().and_then(|v| v.parse().ok()).unwrap_or(0x5eed);
    let s = seeds();
    let inputs = [
        &s.json_render,
        &s.json_scene,
        &s.json_target,
        &s.multipart_render,
        &s.proto_render,
        &s.proto_scene,
        &s.proto_target,
    ];
    let config = bundle("scnerf", "near_far").config;
    let limits = Limits::default();
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
    let mut rng = Rng(seed | 1);
    let started = std::time::Instant::now();
    // Per decoder: how many inputs got each status (200: accepted), to see what the runs reach.
    let mut statuses = vec![std::collections::BTreeMap::<u16, u64>::new(); inputs.len()];
    for case in 0..cases {
        let which = (case % inputs.len() as u64) as usize;
        let data = mutate(&mut rng, inputs[which]);
        let outcome =
            std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| exercise(which, data, &config, &limits, &rt)));
        let status = outcome.unwrap_or_else(|_| panic!("seed {seed}, case {case} ({}) panicked", DECODERS[which]));
        assert!(status < 500, "seed {seed}, case {case} ({}): {status}", DECODERS[which]);
        *statuses[which].entry(status).or_default() += 1;
    }
    eprintln!(
        "{cases} mutated requests decoded without a panic or a 5xx in {:.1} s (seed {seed})",
        started.elapsed().as_secs_f64()
    );
    for (name, counts) in DECODERS.iter().zip(&statuses) {
        eprintln!("  {name}: {counts:?}");
    }
}

#[test]
fn the_seeds_are_valid_requests() {
    let s = seeds();
    let config = bundle("scnerf", "near_far").config;
    let limits = Limits::default();
    RenderRequest::from_json(&s.json_render, ImageMode::Inline, &limits).unwrap().validate(&config, &limits).unwrap();
    SceneRequest::from_json(&s.json_scene, ImageMode::Inline, &limits).unwrap().validate(&config, &limits).unwrap();
    TargetRequest::from_json(&s.json_target, &limits).unwrap().validate(&limits).unwrap();
    RenderRequest::from_protobuf(&s.proto_render, &limits).unwrap().validate(&config, &limits).unwrap();
    SceneRequest::from_protobuf(&s.proto_scene, &limits).unwrap().validate(&config, &limits).unwrap();
    TargetRequest::from_protobuf(&s.proto_target).unwrap().validate(&limits).unwrap();
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
    let multipart = format!("multipart/form-data; boundary={BOUNDARY}");
    rt.block_on(read_render_request(RequestFormat::Multipart, request(s.multipart_render, &multipart), &limits))
        .unwrap()
        .validate(&config, &limits)
        .unwrap();
}
