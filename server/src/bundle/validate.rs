//! The checks of a manifest that need no graph file: format, variant, hyper-parameters, and each
//! graph's declared inputs and outputs against the contract.

use sha2::{Digest, Sha256};

use super::contract::check_declared_io;
use super::graphs::{GraphKind, VolumeBuild, VolumeTail, GUIDED_GRAPHS};
use super::manifest::{Manifest, ModelConfig, FORMAT_VERSION, VARIANTS};

/// A bundle's id: its variant and the start of a sha256 over every graph's name and sha256, in
/// the names' order, one `name=sha256` line each: a bundle any of whose graphs changed is a new
/// model (its graphs hold their weights: `onnx_data.rs`). The exporter derives it the same way
/// (`scnerf_export.export.manifest.model_id`); the committed manifests hold both to it.
pub fn model_id<'a>(variant: &str, graphs: impl IntoIterator<Item = (&'a str, &'a str)>) -> String {
    let mut graphs: Vec<(&str, &str)> = graphs.into_iter().collect();
    graphs.sort_unstable();
    let mut hasher = Sha256::new();
    for (name, sha256) in graphs {
        hasher.update(format!("{name}={sha256}\n"));
    }
    format!("scnerf-{variant}-{}", hex::encode(&hasher.finalize()[..6]))
}

impl Manifest {
    /// The id this manifest's variant and graphs give (what `model_id` must say).
    pub fn expected_model_id(&self) -> String {
        model_id(&self.variant, self.graphs.iter().map(|(name, g)| (name.as_str(), g.sha256.as_str())))
    }
}

/// Checks everything in the manifest that does not need the graph files.
pub fn validate_manifest(m: &Manifest) -> Result<ModelConfig, String> {
    if m.format_version != FORMAT_VERSION {
        return Err(format!(
            "format_version is {}, this server reads format_version {FORMAT_VERSION}",
            m.format_version
        ));
    }
    if !VARIANTS.contains(&m.variant.as_str()) {
        return Err(format!("unknown variant \"{}\" (known: {})", m.variant, VARIANTS.join(", ")));
    }
    let config: ModelConfig =
        serde_json::from_value(serde_json::Value::Object(m.config.clone())).map_err(|e| format!("config: {e}"))?;
    validate_config(&config)?;
    for name in m.graphs.keys() {
        if !GraphKind::ALL.iter().any(|k| k.name() == name) {
            return Err(format!(
                "graphs.{name}: unknown graph (expected encoder, volume or cost_slab and volume_net or cost_conv and \
                 volume_net, renderer, and renderer_guide and renderer_fine)"
            ));
        }
    }
    for kind in VolumeBuild::of(&m.graphs)?.bundle_graphs() {
        let entry = m.graphs.get(kind.name()).ok_or_else(|| format!("graphs.{kind}: missing"))?;
        check_declared_io(kind, entry, &config)?;
        if kind == GraphKind::VolumeNet && VolumeTail::of(&entry.outputs)? == VolumeTail::Server {
            config
                .activation_slope
                .ok_or("config.activation_slope: missing (volume_net.onnx leaves G2's last step to the server)")?;
        }
    }
    validate_guided(m, &config)?;
    let expected_id = m.expected_model_id();
    if m.model_id != expected_id {
        return Err(format!("model_id is \"{}\", expected \"{expected_id}\"", m.model_id));
    }
    Ok(config)
}

/// Guided sampling's graphs and policy come together, and the heads the guide returns are the
/// heads the fine renderer reads.
fn validate_guided(m: &Manifest, config: &ModelConfig) -> Result<(), String> {
    let present = GUIDED_GRAPHS.map(|k| m.graphs.contains_key(k.name()));
    let Some(policy) = &m.guided else {
        return match present.iter().any(|&p| p) {
            true => Err("graphs.renderer_guide and graphs.renderer_fine need the manifest's guided policy".into()),
            false => Ok(()),
        };
    };
    if !present.iter().all(|&p| p) {
        return Err("guided: needs graphs.renderer_guide and graphs.renderer_fine".into());
    }
    policy.validate(config.samples)?;
    for kind in GUIDED_GRAPHS {
        check_declared_io(kind, &m.graphs[kind.name()], config)?;
    }
    let heads =
        |names: Vec<&String>| -> Vec<String> { names.into_iter().filter(|n| n.ends_with("_heads")).cloned().collect() };
    let given = heads(m.graphs["renderer_guide"].outputs.iter().map(|t| &t.name).collect());
    let read = heads(m.graphs["renderer_fine"].inputs.iter().map(|t| &t.name).collect());
    if given != read {
        return Err(format!("graphs.renderer_fine reads the heads {read:?}, graphs.renderer_guide gives {given:?}"));
    }
    let index = m.graphs["renderer_fine"].inputs.iter().any(|t| t.name == "head_index");
    if index == read.is_empty() {
        return Err("graphs.renderer_fine: head_index goes with the rectifiers' heads".into());
    }
    Ok(())
}

fn validate_config(c: &ModelConfig) -> Result<(), String> {
    let positive = [
        ("views", c.views),
        ("feature_channels", c.feature_channels),
        ("volume_channels", c.volume_channels),
        ("depth_planes", c.depth_planes),
        ("samples", c.samples),
        ("image_multiple", c.image_multiple),
    ];
    for (name, value) in positive {
        if value == 0 {
            return Err(format!("config.{name} must be > 0"));
        }
    }
    // Features live at 1/4 resolution, so padded sources must divide by 4.
    if !c.image_multiple.is_multiple_of(4) {
        return Err(format!("config.image_multiple = {} is not a multiple of 4", c.image_multiple));
    }
    if c.depth_planes < 2 {
        return Err("config.depth_planes must be >= 2".into());
    }
    Ok(())
}
