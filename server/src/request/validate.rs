//! Validation: the parsed request against the bundle's configuration and the limits. Cheap
//! whole-request checks come first, then the cameras (converted to the canonical form), then
//! the images' presence; every refusal names the field.

use super::cameras::{MAX_WORLD_EXTENT, MIN_NEAR};
use super::{
    Limits, OutputKind, OutputSet, RenderRequest, SceneRequest, SourceSpec, TargetRequest, ValidRequest, ValidScene,
    ValidSource, ValidTarget,
};
use crate::bundle::ModelConfig;
use crate::camera::CanonicalCamera;
use crate::error::ApiError;
use crate::request::Sampling;

impl RenderRequest {
    /// Checks the request against the bundle and the limits and converts the cameras.
    pub fn validate(self, config: &ModelConfig, limits: &Limits) -> Result<ValidRequest, ApiError> {
        // Cheap whole-request checks first, then the target, then the (costlier) sources.
        if self.scene.sources.len() != config.views {
            return Err(ApiError::invalid(
                "sources",
                format!("this model takes exactly {} source views, got {}", config.views, self.scene.sources.len()),
            ));
        }
        let background = self.scene.validate_header()?;
        let view = self.view.validate(limits)?;
        let scene = self.scene.validate_sources(background, limits)?;
        Ok(ValidRequest { scene, view })
    }
}

impl SceneRequest {
    /// A scene holds from the model's view count (3, rendered from as they are) up to
    /// `max_scene_views` (a capture, from which each render picks 3).
    pub fn validate(self, config: &ModelConfig, limits: &Limits) -> Result<ValidScene, ApiError> {
        let (count, range) = (self.sources.len(), config.views..=limits.max_scene_views.max(config.views));
        if !range.contains(&count) {
            return Err(ApiError::invalid(
                "sources",
                format!("a scene holds {} to {} source views, got {count}", range.start(), range.end()),
            ));
        }
        let background = self.validate_header()?;
        self.validate_sources(background, limits)
    }

    /// Depth range and background: everything but the view count, cameras and images.
    fn validate_header(&self) -> Result<[f32; 3], ApiError> {
        check_depth_range(self.near, self.far)?;
        check_background(self.background.as_deref())
    }

    fn validate_sources(self, background: [f32; 3], limits: &Limits) -> Result<ValidScene, ApiError> {
        let mut sources: Vec<ValidSource> = Vec::with_capacity(self.sources.len());
        for (i, source) in self.sources.into_iter().enumerate() {
            let first = sources.first().map(|s| &s.camera);
            sources.push(validate_source(i, source, first, limits)?);
        }
        Ok(ValidScene { sources, near: self.near, far: self.far, background })
    }
}

/// Source `i`: its camera (the same size as the first source's, `first`), its size limit and
/// its image.
fn validate_source(
    i: usize,
    source: SourceSpec,
    first: Option<&CanonicalCamera>,
    limits: &Limits,
) -> Result<ValidSource, ApiError> {
    let field = format!("sources[{i}].camera");
    let camera = source.camera.canonicalize(&field)?;
    if let Some(first) = first.filter(|f| (f.width, f.height) != (camera.width, camera.height)) {
        return Err(ApiError::invalid(
            format!("{field}.width"),
            format!(
                "all source views must have the same size: source 0 is {}x{}, source {i} is {}x{}",
                first.width, first.height, camera.width, camera.height
            ),
        ));
    }
    let pixels = u64::from(camera.width) * u64::from(camera.height);
    if pixels > limits.max_source_pixels {
        return Err(ApiError::invalid(
            format!("{field}.width"),
            format!(
                "source view of {}x{} exceeds the limit of {} pixels",
                camera.width, camera.height, limits.max_source_pixels
            ),
        ));
    }
    let image = source.image.ok_or_else(|| ApiError::malformed(source.image_field.clone(), "missing source image"))?;
    Ok(ValidSource { camera, image, image_field: source.image_field })
}

impl TargetRequest {
    pub fn validate(self, limits: &Limits) -> Result<ValidTarget, ApiError> {
        let outputs = output_set(self.outputs.as_deref())?;
        let target = self.target.canonicalize("target")?;
        let target_pixels = u64::from(target.width) * u64::from(target.height);
        if target_pixels > limits.max_target_pixels {
            return Err(ApiError::invalid(
                "target.width",
                format!(
                    "target view of {}x{} exceeds the limit of {} pixels",
                    target.width, target.height, limits.max_target_pixels
                ),
            ));
        }
        let sampling = self.sampling.as_deref().map(sampling_of).transpose()?;
        Ok(ValidTarget { target, outputs, sources: self.sources, sampling })
    }
}

/// A sampling by name: 422 naming `sampling` for any other.
fn sampling_of(name: &str) -> Result<Sampling, ApiError> {
    Sampling::parse(name).ok_or_else(|| {
        let known: Vec<&str> = Sampling::ALL.iter().map(|s| s.name()).collect();
        ApiError::invalid("sampling", format!("unknown sampling \"{name}\" (expected {})", known.join(" or ")))
    })
}

/// The outputs asked for (`None`: RGB only); each at most once.
fn output_set(kinds: Option<&[OutputKind]>) -> Result<OutputSet, ApiError> {
    let Some(kinds) = kinds else { return Ok(OutputSet::RGB) };
    if kinds.is_empty() {
        return Err(ApiError::invalid("outputs", "outputs must name at least one of rgb, depth, opacity"));
    }
    let mut set = OutputSet { rgb: false, depth: false, opacity: false };
    for (i, k) in kinds.iter().enumerate() {
        let slot = match k {
            OutputKind::Rgb => &mut set.rgb,
            OutputKind::Depth => &mut set.depth,
            OutputKind::Opacity => &mut set.opacity,
        };
        if *slot {
            return Err(ApiError::invalid(format!("outputs[{i}]"), "output listed twice"));
        }
        *slot = true;
    }
    Ok(set)
}

/// A scene's `near` and `far` (422 naming the field): finite, within the world's extent, and
/// ordered in f32 as well, the precision they are rendered in.
pub fn check_depth_range(near: f64, far: f64) -> Result<(), ApiError> {
    if !near.is_finite() || near <= 0.0 {
        return Err(ApiError::invalid("near", "near must be a finite number > 0"));
    }
    if near < MIN_NEAR {
        return Err(ApiError::invalid("near", format!("near must be at least {MIN_NEAR:e}")));
    }
    if !far.is_finite() {
        return Err(ApiError::invalid("far", "far must be a finite number"));
    }
    if far > MAX_WORLD_EXTENT {
        return Err(ApiError::invalid("far", format!("far must be at most {MAX_WORLD_EXTENT:e}")));
    }
    if near >= far {
        return Err(ApiError::invalid("far", format!("near ({near}) must be smaller than far ({far})")));
    }
    // The renderer samples depths in f32: a range that is empty there renders NaN.
    if near as f32 >= far as f32 {
        return Err(ApiError::invalid(
            "far",
            format!("near ({near}) and far ({far}) are equal in 32-bit floating point, the precision depths are rendered in"),
        ));
    }
    Ok(())
}

fn check_background(bg: Option<&[f64]>) -> Result<[f32; 3], ApiError> {
    let Some(bg) = bg else { return Ok([0.0; 3]) };
    if bg.len() != 3 {
        return Err(ApiError::invalid("background", format!("background must be 3 numbers (RGB), got {}", bg.len())));
    }
    if bg.iter().any(|v| !(0.0..=1.0).contains(v)) {
        return Err(ApiError::invalid("background", "background components must be in [0, 1]"));
    }
    Ok([bg[0] as f32, bg[1] as f32, bg[2] as f32])
}
