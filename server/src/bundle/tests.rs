use super::load::verify_file;
use super::*;
use sha2::Digest;
use std::path::Path;

pub(crate) fn sample_manifest() -> Manifest {
    let renderer_sha = "ab".repeat(32);
    let json = serde_json::json!({
        "format_version": 1,
        "model_id": "set below",
        "variant": "scnerf",
        "config": {"views": 3, "feature_channels": 32, "volume_channels": 8, "depth_planes": 128,
                   "samples": 128, "pad": 24, "image_multiple": 32, "depth_norm": "near_far"},
        "graphs": {
            "encoder": {"file": "encoder.onnx", "sha256": "00",
                "inputs": [{"name": "images", "shape": [3, 3, "H", "W"], "dtype": "float32"}],
                "outputs": [{"name": "features", "shape": [3, 32, "h", "w"], "dtype": "float32"}]},
            "volume": {"file": "volume.onnx", "sha256": "00",
                "inputs": [{"name": "features", "shape": [3, 32, "h", "w"], "dtype": "float32"},
                           {"name": "images", "shape": [3, 3, "H", "W"], "dtype": "float32"},
                           {"name": "projections", "shape": [3, 4, 4], "dtype": "float32"},
                           {"name": "depth_planes", "shape": [128], "dtype": "float32"}],
                "outputs": [{"name": "volume", "shape": [1, 8, 128, "Hp", "Wp"], "dtype": "float32"}]},
            "renderer": {"file": "renderer.onnx", "sha256": renderer_sha,
                "inputs": [{"name": "ray_origins", "shape": ["R", 3], "dtype": "float32"},
                           {"name": "ray_directions", "shape": ["R", 3], "dtype": "float32"},
                           {"name": "near_far", "shape": [2], "dtype": "float32"},
                           {"name": "depth_range", "shape": [2], "dtype": "float32"},
                           {"name": "volume", "shape": [1, 8, 128, "Hp", "Wp"], "dtype": "float32"},
                           {"name": "images", "shape": [3, 3, "H", "W"], "dtype": "float32"},
                           {"name": "features", "shape": [3, 32, "h", "w"], "dtype": "float32"},
                           {"name": "intrinsics", "shape": [3, 3, 3], "dtype": "float32"},
                           {"name": "extrinsics", "shape": [3, 4, 4], "dtype": "float32"}],
                "outputs": [{"name": "rgb", "shape": ["R", 3], "dtype": "float32"},
                            {"name": "depth", "shape": ["R"], "dtype": "float32"},
                            {"name": "opacity", "shape": ["R"], "dtype": "float32"}]}
        },
        "provenance": {"source_checkpoint": "x", "source_sha256": "y", "exporter_version": "0.1.0",
                       "training": null, "metrics": null, "created": "2026-01-01T00:00:00Z"}
    });
    let mut manifest: Manifest = serde_json::from_value(json).unwrap();
    manifest.model_id = manifest.expected_model_id();
    manifest
}

#[test]
fn sample_manifest_is_valid() {
    let c = validate_manifest(&sample_manifest()).unwrap();
    assert_eq!(c.views, 3);
    assert_eq!(c.depth_norm, DepthNorm::NearFar);
}

#[test]
fn refuses_wrong_format_version() {
    let mut m = sample_manifest();
    m.format_version = 2;
    assert!(validate_manifest(&m).unwrap_err().contains("format_version"));
}

#[test]
fn the_band_rule_is_the_manifests_when_it_names_one() {
    let mut json = serde_json::to_value(sample_manifest()).unwrap();
    let rule = |json: &serde_json::Value| serde_json::from_value::<Manifest>(json.clone()).map(|m| m.band);
    assert_eq!(rule(&json).unwrap(), None);
    json["band"] = serde_json::json!({"fill": "always"});
    assert_eq!(rule(&json).unwrap(), Some(BandPolicy { fill: BandRule::Always }));
    json["band"] = serde_json::json!({"fill": "sometimes"});
    assert!(rule(&json).unwrap_err().to_string().contains("sometimes"));
}

#[test]
fn refuses_unknown_variant() {
    let mut m = sample_manifest();
    m.variant = "nerf".into();
    assert!(validate_manifest(&m).unwrap_err().contains("unknown variant"));
}

#[test]
fn refuses_unknown_input_name() {
    let mut m = sample_manifest();
    m.graphs.get_mut("renderer").unwrap().inputs[0].name = "origins".into();
    let e = validate_manifest(&m).unwrap_err();
    assert!(e.contains("\"origins\"") && e.contains("does not know"), "{e}");
}

#[test]
fn refuses_missing_required_input() {
    let mut m = sample_manifest();
    m.graphs.get_mut("volume").unwrap().inputs.remove(2);
    let e = validate_manifest(&m).unwrap_err();
    assert!(e.contains("\"projections\" is missing"), "{e}");
}

#[test]
fn accepts_missing_optional_input() {
    let mut m = sample_manifest();
    m.graphs.get_mut("renderer").unwrap().inputs.retain(|t| t.name != "features" && t.name != "depth_range");
    validate_manifest(&m).unwrap();
}

#[test]
fn refuses_wrong_shape_and_dtype() {
    let mut m = sample_manifest();
    m.graphs.get_mut("encoder").unwrap().outputs[0].shape[1] = Dim::Fixed(16);
    let e = validate_manifest(&m).unwrap_err();
    assert!(e.contains("graphs.encoder.outputs[0] \"features\": shape is [3, 16, \"h\", \"w\"]"), "{e}");
    let mut m = sample_manifest();
    m.graphs.get_mut("encoder").unwrap().inputs[0].dtype = "float16".into();
    assert!(validate_manifest(&m).unwrap_err().contains("dtype is float16"));
}

#[test]
fn refuses_view_count_inconsistent_with_config() {
    let mut m = sample_manifest();
    m.config.insert("views".into(), serde_json::json!(2));
    let e = validate_manifest(&m).unwrap_err();
    assert!(e.contains("shape is [3, 3"), "{e}");
}

#[test]
fn refuses_wrong_model_id() {
    let mut m = sample_manifest();
    m.model_id = "scnerf-scnerf-000000000000".into();
    assert!(validate_manifest(&m).unwrap_err().contains("model_id"));
}

/// The id covers every graph: a bundle whose encoder alone changed, with the id its renderer
/// gave, is refused; the ids of two bundles that differ in one graph differ.
#[test]
fn the_model_id_covers_every_graph() {
    let m = sample_manifest();
    let mut other = m.clone();
    other.graphs.get_mut("encoder").unwrap().sha256 = "11".into();
    let e = validate_manifest(&other).unwrap_err();
    assert!(e.contains(&format!("expected \"{}\"", other.expected_model_id())), "{e}");
    assert_ne!(other.expected_model_id(), m.model_id);
    // One line `name=sha256` per graph, in the names' order (docs/bundle.md).
    let listing: String = m.graphs.iter().map(|(name, g)| format!("{name}={}\n", g.sha256)).collect();
    let digest = hex::encode(sha2::Sha256::digest(listing));
    assert_eq!(m.model_id, format!("scnerf-scnerf-{}", &digest[..12]));
}

/// The manifest of a bundle that builds its volume slab by slab (`scnerf-export split-volume`).
fn slab_manifest() -> Manifest {
    let mut m = sample_manifest();
    let volume = m.graphs.remove("volume").unwrap();
    let t = |name: &str, shape: serde_json::Value| {
        serde_json::from_value::<TensorSpec>(serde_json::json!({"name": name, "shape": shape, "dtype": "float32"}))
            .unwrap()
    };
    let mut inputs = volume.inputs.clone();
    inputs[3] = t("depth_planes", serde_json::json!(["Dh"]));
    inputs.push(t("plane_inside", serde_json::json!(["Dh"])));
    let conv0 = |planes: serde_json::Value| t("conv0", serde_json::json!([1, 8, planes, "Hp", "Wp"]));
    let graph = |file: &str, inputs, outputs| GraphEntry { file: file.into(), sha256: "00".into(), inputs, outputs };
    m.graphs.insert("cost_slab".into(), graph("cost_slab.onnx", inputs, vec![conv0(serde_json::json!("Ds"))]));
    m.graphs.insert("volume_net".into(), graph("volume_net.onnx", vec![conv0(serde_json::json!(128))], volume.outputs));
    m.model_id = m.expected_model_id();
    m
}

/// The manifest of a bundle whose volume the server's plane sweep starts (`scnerf-export
/// export`): `cost_conv` on the sweep's cost (41 channels: 3 views' images and 32 features).
fn sweep_manifest() -> Manifest {
    let mut m = slab_manifest();
    let slab = m.graphs.remove("cost_slab").unwrap();
    let cost = serde_json::json!({"name": "cost", "shape": [1, 41, "Dh", "Hp", "Wp"], "dtype": "float32"});
    let inputs = vec![serde_json::from_value(cost).unwrap()];
    m.graphs.insert("cost_conv".into(), GraphEntry { file: "cost_conv.onnx".into(), inputs, ..slab });
    m.model_id = m.expected_model_id();
    m
}

#[test]
fn accepts_each_way_to_build_the_volume_but_not_a_mix() {
    let m = slab_manifest();
    validate_manifest(&m).unwrap();
    assert_eq!(VolumeBuild::of(&m.graphs), Ok(VolumeBuild::Slabs));
    assert_eq!(VolumeBuild::of(&sample_manifest().graphs), Ok(VolumeBuild::Whole));
    let m = sweep_manifest();
    validate_manifest(&m).unwrap();
    assert_eq!(VolumeBuild::of(&m.graphs), Ok(VolumeBuild::Sweep));
    assert_eq!(
        VolumeBuild::Sweep.bundle_graphs().iter().map(|k| k.name()).collect::<Vec<_>>(),
        ["encoder", "cost_conv", "volume_net", "renderer"]
    );
    let mut half = slab_manifest();
    half.graphs.remove("volume_net");
    assert!(validate_manifest(&half).unwrap_err().contains("not a mix"));
    let mut both = slab_manifest();
    both.graphs.insert("volume".into(), sample_manifest().graphs["volume"].clone());
    assert!(validate_manifest(&both).unwrap_err().contains("not a mix"));
    let mut mixed = sweep_manifest();
    mixed.graphs.insert("cost_slab".into(), slab_manifest().graphs["cost_slab"].clone());
    assert!(validate_manifest(&mixed).unwrap_err().contains("not a mix"));
    let mut wrong = slab_manifest();
    wrong.graphs.get_mut("cost_slab").unwrap().inputs.pop();
    assert!(validate_manifest(&wrong).unwrap_err().contains("\"plane_inside\" is missing"));
    // The cost has 3 channels per view's image, then the features.
    let mut wrong = sweep_manifest();
    wrong.graphs.get_mut("cost_conv").unwrap().inputs[0].shape[1] = Dim::Fixed(32);
    let e = validate_manifest(&wrong).unwrap_err();
    assert!(e.contains("\"cost\": shape is [1, 32, \"Dh\", \"Hp\", \"Wp\"], the pipeline expects [1, 41,"), "{e}");
}

/// `volume_net` outputs the volume, or the parts of G2's last step with the slope in the config.
#[test]
fn volume_net_outputs_the_volume_or_the_parts_of_its_last_step() {
    let spec = |name: &str, shape: serde_json::Value| -> TensorSpec {
        serde_json::from_value(serde_json::json!({"name": name, "shape": shape, "dtype": "float32"})).unwrap()
    };
    let parts = vec![
        spec("phases", serde_json::json!([1, 64, 64, "Hp/2", "Wp/2"])),
        spec("skip_affine", serde_json::json!([2, 8])),
        spec("phases_affine", serde_json::json!([2, 8])),
    ];
    let with_outputs = |outputs: Vec<TensorSpec>, slope: Option<f64>| {
        let mut m = sweep_manifest();
        m.graphs.get_mut("volume_net").unwrap().outputs = outputs;
        if let Some(slope) = slope {
            m.config.insert("activation_slope".into(), serde_json::json!(slope));
        }
        m
    };
    let volume = sweep_manifest().graphs["volume_net"].outputs.clone();
    assert_eq!(VolumeTail::of(&volume), Ok(VolumeTail::Graph));
    let server = with_outputs(parts.clone(), Some(0.01));
    assert_eq!(validate_manifest(&server).unwrap().activation_slope, Some(0.01));
    assert_eq!(VolumeTail::of(&server.graphs["volume_net"].outputs), Ok(VolumeTail::Server));
    let e = validate_manifest(&with_outputs(parts.clone(), None)).unwrap_err();
    assert!(e.contains("config.activation_slope: missing"), "{e}");
    let e = validate_manifest(&with_outputs(parts[..2].to_vec(), Some(0.01))).unwrap_err();
    assert!(e.contains("graphs.volume_net.outputs: \"volume\", or \"phases\""), "{e}");
    let e = validate_manifest(&with_outputs([volume, parts.clone()].concat(), Some(0.01))).unwrap_err();
    assert!(e.contains("graphs.volume_net.outputs: \"volume\", or \"phases\""), "{e}");
    let mut odd = parts;
    odd[0].shape[2] = Dim::Fixed(128);
    let e = validate_manifest(&with_outputs(odd, Some(0.01))).unwrap_err();
    assert!(e.contains("\"phases\": shape is [1, 64, 128,"), "{e}");
}

#[test]
fn refuses_missing_graph_and_config_key() {
    let mut m = sample_manifest();
    m.graphs.remove("volume");
    assert!(validate_manifest(&m).unwrap_err().contains("graphs.volume: missing"));
    let mut m = sample_manifest();
    m.config.remove("samples");
    assert!(validate_manifest(&m).unwrap_err().contains("samples"));
}

#[test]
fn file_hash_mismatch_names_the_file() {
    let dir = std::env::temp_dir().join(format!("scnerf-bundle-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("encoder.onnx"), b"not a graph").unwrap();
    let entry = sample_manifest().graphs["encoder"].clone();
    let e = verify_file(&dir, GraphKind::Encoder, &entry, &|| Ok(())).unwrap_err();
    assert!(e.contains("sha256 of encoder.onnx is"), "{e}");
    let mut escaping = entry;
    escaping.file = "../x.onnx".into();
    assert!(verify_file(&dir, GraphKind::Encoder, &escaping, &|| Ok(())).unwrap_err().contains("inside the bundle"));
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn signature_check() {
    let declared = &sample_manifest().graphs["renderer"].outputs;
    let mut actual: Vec<ActualTensor> = declared
        .iter()
        .map(|s| ActualTensor {
            name: s.name.clone(),
            shape: s
                .shape
                .iter()
                .map(|d| match d {
                    Dim::Fixed(n) => Some(*n),
                    Dim::Named(_) => None,
                })
                .collect(),
            dtype: "float32".into(),
        })
        .collect();
    check_signature(GraphKind::Renderer, "output", declared, &actual).unwrap();
    actual[0].shape[0] = Some(4096);
    let e = check_signature(GraphKind::Renderer, "output", declared, &actual).unwrap_err();
    assert!(e.contains("renderer.onnx output \"rgb\": graph shape [4096, 3]"), "{e}");
    actual[0].shape[0] = None;
    actual.push(ActualTensor { name: "extra".into(), shape: vec![], dtype: "float32".into() });
    let e = check_signature(GraphKind::Renderer, "output", declared, &actual).unwrap_err();
    assert!(e.contains("\"extra\": present in the graph"), "{e}");
}

/// The contract as tests/fixtures/rules/graph_contract.json writes it: per graph, its inputs and
/// outputs by name (the order of the manifest's lists does not matter to the server).
fn contract_json(c: &ModelConfig) -> serde_json::Map<String, serde_json::Value> {
    let side = |tensors: Vec<super::contract::Expected>| -> serde_json::Value {
        tensors
            .into_iter()
            .map(|t| (t.name.to_string(), serde_json::json!({"required": t.required, "shape": t.shape})))
            .collect()
    };
    GraphKind::ALL
        .into_iter()
        .map(|kind| {
            let (inputs, outputs) = super::contract::expected_io(kind, c);
            (kind.name().to_string(), serde_json::json!({"inputs": side(inputs), "outputs": side(outputs)}))
        })
        .collect()
}

#[test]
fn contract_is_the_fixtures() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../tests/fixtures/rules/graph_contract.json");
    let fixture: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    let configs = fixture["configs"].as_array().unwrap();
    assert!(configs.len() >= 2, "the default bundle's config and another");
    for case in configs {
        let config: ModelConfig = serde_json::from_value(case["config"].clone()).unwrap();
        let by_name = |tensors: &serde_json::Value| -> serde_json::Value {
            let tensors = tensors.as_array().unwrap().iter();
            tensors
                .map(|t| {
                    (
                        t["name"].as_str().unwrap().to_string(),
                        serde_json::json!({"required": t["required"], "shape": t["shape"]}),
                    )
                })
                .collect()
        };
        let want: serde_json::Map<String, serde_json::Value> = case["graphs"]
            .as_object()
            .unwrap()
            .iter()
            .map(|(graph, io)| {
                (
                    graph.clone(),
                    serde_json::json!({"inputs": by_name(&io["inputs"]), "outputs": by_name(&io["outputs"])}),
                )
            })
            .collect();
        let got = contract_json(&config);
        for graph in want.keys().chain(got.keys()) {
            assert_eq!(got.get(graph), want.get(graph), "{}: {graph}", case["name"]);
        }
    }
}

/// A copy of the parity bundle whose renderer also declares a tensor kept in `weights.bin`
/// (protobuf merges a model appended to another): its hash matches the manifest, yet the
/// server will not hand it to ONNX Runtime (which would map `weights.bin`).
#[test]
fn a_graph_with_external_data_is_refused_before_onnx_runtime_sees_it() {
    let fixture = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../tests/fixtures/parity/bundle"));
    let dir = std::env::temp_dir().join(format!("scnerf-external-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    for entry in std::fs::read_dir(fixture).unwrap() {
        let path = entry.unwrap().path();
        std::fs::copy(&path, dir.join(path.file_name().unwrap())).unwrap();
    }
    let mut graph = std::fs::read(dir.join("renderer.onnx")).unwrap();
    graph.extend(super::onnx_data::tests::model_with_external_tensor("extra"));
    std::fs::write(dir.join("renderer.onnx"), &graph).unwrap();
    std::fs::write(dir.join("weights.bin"), [0u8; 64]).unwrap();
    let mut manifest: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("manifest.json")).unwrap()).unwrap();
    let sha = sha256_file(&dir.join("renderer.onnx")).unwrap();
    manifest["graphs"]["renderer"]["sha256"] = sha.clone().into();
    let mut manifest: Manifest = serde_json::from_value(manifest).unwrap();
    manifest.model_id = manifest.expected_model_id();
    std::fs::write(dir.join("manifest.json"), serde_json::to_vec(&manifest).unwrap()).unwrap();

    let bundle = Bundle::load(&dir).unwrap();
    assert!(bundle.read_graph(GraphKind::Encoder).is_ok());
    let e = bundle.read_graph(GraphKind::Renderer).unwrap_err();
    assert!(
        e.starts_with("graphs.renderer: tensor \"extra\" keeps its data in an external file (\"weights.bin\")"),
        "{e}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}
