//! The cache's bytes count against the executor's memory budget as they are held (its limit is
//! not set aside up front), and the executor reclaims idle entries to admit a request: least
//! recently used volumes first, then scenes, of any owner, among those no request is using
//! (evicting one in use would free nothing until that request ends).

use std::sync::Arc;

use super::{SceneCache, SceneKey, VolumeKey};
use crate::backend::Reclaim;

impl Reclaim for SceneCache {
    fn held(&self) -> u64 {
        self.lock().stats.bytes as u64
    }

    fn reclaim(&self, bytes: u64) -> u64 {
        let mut inner = self.lock();
        let start = inner.stats.bytes;
        let freed = |inner: &super::Inner| (start - inner.stats.bytes) as u64;
        let idle_volumes: Vec<VolumeKey> =
            inner.volume_lru.values().filter(|k| Arc::strong_count(&inner.volumes[*k].volume) == 1).cloned().collect();
        for key in idle_volumes {
            if freed(&inner) >= bytes {
                return freed(&inner);
            }
            inner.remove_volume(&key);
            inner.stats.volume_evictions += 1;
        }
        let idle_scenes: Vec<SceneKey> =
            inner.scene_lru.values().filter(|k| Arc::strong_count(&inner.scenes[*k].scene) == 1).cloned().collect();
        for key in idle_scenes {
            if freed(&inner) >= bytes {
                break;
            }
            inner.remove_scene(&key);
            inner.stats.evictions += 1;
        }
        freed(&inner)
    }
}
