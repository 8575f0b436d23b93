//! A capture's size checked against the limits before any of its photos is decoded: the views'
//! sizes are known from the capture's files and the images' headers (fitted to
//! `--max-source-pixels`), and so are the scene's memory estimate and what it would hold in the
//! scene cache. Without this, photos larger than the limit were decoded, undistorted and
//! resized one by one before the scene was refused for its client's share of the cache.

use std::sync::Arc;

use scnerf_capture::readers::CapturedView;

use crate::cache::SceneCache;
use crate::error::ApiError;
use crate::models::Model;
use crate::request::check_depth_range;

/// The model a capture is read for, and the cache it goes to.
pub struct CaptureLimits {
    model: Arc<Model>,
    scenes: Arc<SceneCache>,
}

impl CaptureLimits {
    pub fn new(model: &Arc<Model>, scenes: &Arc<SceneCache>) -> CaptureLimits {
        CaptureLimits { model: model.clone(), scenes: scenes.clone() }
    }

    /// Refuses the views a scene is made of (each at the size it is sent at) when their scene
    /// could never be admitted (422 naming the sizes) or never fit its client's share of the
    /// cache (422), and a depth range validation would refuse (422 naming `near` or `far`), as
    /// storing it would, but before anything is decoded.
    pub(super) fn check<'a>(
        &self,
        views: impl IntoIterator<Item = &'a CapturedView>,
        (near, far): (f64, f64),
    ) -> Result<(), ApiError> {
        check_depth_range(near, far)?;
        let views: Vec<&CapturedView> = views.into_iter().collect();
        let Some(first) = views.first() else { return Ok(()) };
        let scene = self.model.pipeline.check_scene_size(first.camera.width, first.camera.height, views.len())?;
        Ok(self.scenes.check_fits(scene)?)
    }
}
