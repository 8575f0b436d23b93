//! Scene cache: built scenes (padded images, features, encoding volume, cameras, near/far,
//! background) kept by id, so that further views of the same sources cost only the renderer.
//!
//! Bounded two ways: total bytes (least recently used scenes are evicted to make room) and an
//! idle time-to-live (a scene not rendered for `ttl` expires; every render extends it). Entries
//! are `Arc`s: evicting a scene that a request is rendering frees it when that request ends.
//!
//! Time is passed in (`now`) rather than read here, so tests can drive expiry without sleeping.

use std::collections::{BTreeMap, HashMap};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime};

use crate::pipeline::Scene;

/// Who created a scene: a digest of the bearer token (never the token), or `None` when auth is
/// off. A scene is only visible to the same owner.
pub type Owner = Option<[u8; 32]>;

/// Scene ids are 128 random bits (UUID v4) as 32 lowercase hex digits: unguessable, so without
/// auth an id is a capability.
pub fn is_valid_id(id: &str) -> bool {
    id.len() == 32 && id.bytes().all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
}

/// What a cached scene holds besides the tensors.
#[derive(Debug)]
pub struct CachedScene {
    pub scene: Scene,
    pub background: [f32; 3],
    owner: Owner,
}

#[derive(Debug, Clone, Copy)]
pub struct CacheConfig {
    pub max_bytes: usize,
    pub ttl: Duration,
}

impl Default for CacheConfig {
    fn default() -> Self {
        CacheConfig { max_bytes: 2 << 30, ttl: Duration::from_secs(600) }
    }
}

#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct CacheStats {
    pub entries: usize,
    pub bytes: usize,
    pub hits: u64,
    pub misses: u64,
    pub evictions: u64,
    pub expirations: u64,
}

#[derive(Debug, thiserror::Error, PartialEq, Eq)]
#[error("the scene needs {needed} bytes but the scene cache holds at most {max} bytes")]
pub struct SceneTooLarge {
    pub needed: usize,
    pub max: usize,
}

struct Entry {
    scene: Arc<CachedScene>,
    bytes: usize,
    expires: Instant,
    /// Position in `Inner::lru` (larger = used more recently).
    tick: u64,
}

#[derive(Default)]
struct Inner {
    entries: HashMap<String, Entry>,
    /// tick -> id, oldest first.
    lru: BTreeMap<u64, String>,
    next_tick: u64,
    stats: CacheStats,
}

pub struct SceneCache {
    config: CacheConfig,
    inner: Mutex<Inner>,
}

/// A cache hit: the scene and when it now expires.
pub struct Hit {
    pub scene: Arc<CachedScene>,
    pub expires_at: SystemTime,
}

impl SceneCache {
    pub fn new(config: CacheConfig) -> SceneCache {
        SceneCache { config, inner: Mutex::new(Inner::default()) }
    }

    pub fn config(&self) -> CacheConfig {
        self.config
    }

    /// A poisoned lock only means another request panicked mid-update; the maps stay usable.
    fn lock(&self) -> std::sync::MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Stores a scene under a fresh id, evicting expired and then least recently used scenes to
    /// make room. Returns the id and the wall-clock expiry.
    pub fn insert(
        &self,
        scene: Scene,
        background: [f32; 3],
        owner: Owner,
        now: Instant,
    ) -> Result<(String, SystemTime), SceneTooLarge> {
        let bytes = scene.bytes();
        if bytes > self.config.max_bytes {
            return Err(SceneTooLarge { needed: bytes, max: self.config.max_bytes });
        }
        let id = uuid::Uuid::new_v4().simple().to_string();
        let mut inner = self.lock();
        inner.purge_expired(now);
        while inner.stats.bytes + bytes > self.config.max_bytes && inner.evict_oldest() {}
        let expires = now + self.config.ttl;
        let tick = inner.touch_tick();
        inner.lru.insert(tick, id.clone());
        let scene = Arc::new(CachedScene { scene, background, owner });
        inner.entries.insert(id.clone(), Entry { scene, bytes, expires, tick });
        inner.stats.bytes += bytes;
        inner.stats.entries = inner.entries.len();
        Ok((id, wall_clock(expires, now)))
    }

    /// Looks a scene up for `owner`, marks it recently used and extends its life by the TTL.
    /// Unknown, expired and other owners' scenes are all `None` (a miss).
    pub fn get(&self, id: &str, owner: &Owner, now: Instant) -> Option<Hit> {
        let mut inner = self.lock();
        inner.purge_expired(now);
        let ttl = self.config.ttl;
        let inner = &mut *inner;
        let Some(entry) = inner.entries.get_mut(id).filter(|e| e.scene.owner == *owner) else {
            inner.stats.misses += 1;
            return None;
        };
        inner.lru.remove(&entry.tick);
        let tick = inner.next_tick;
        inner.next_tick += 1; // (not touch_tick: `entry` borrows `entries`)
        entry.tick = tick;
        entry.expires = now + ttl;
        inner.lru.insert(tick, id.to_string());
        inner.stats.hits += 1;
        Some(Hit { scene: entry.scene.clone(), expires_at: wall_clock(entry.expires, now) })
    }

    /// Deletes `owner`'s scene; false when there is no such (live) scene.
    pub fn remove(&self, id: &str, owner: &Owner, now: Instant) -> bool {
        let mut inner = self.lock();
        inner.purge_expired(now);
        let owned = inner.entries.get(id).is_some_and(|e| e.scene.owner == *owner);
        if owned {
            inner.remove(id);
        }
        owned
    }

    /// Drops expired scenes (also done on every access; call periodically to free memory of an
    /// idle server).
    pub fn purge_expired(&self, now: Instant) {
        self.lock().purge_expired(now);
    }

    pub fn stats(&self) -> CacheStats {
        self.lock().stats
    }
}

impl Inner {
    fn touch_tick(&mut self) -> u64 {
        let t = self.next_tick;
        self.next_tick += 1;
        t
    }

    fn remove(&mut self, id: &str) -> Option<Entry> {
        let entry = self.entries.remove(id)?;
        self.lru.remove(&entry.tick);
        self.stats.bytes -= entry.bytes;
        self.stats.entries = self.entries.len();
        Some(entry)
    }

    /// Evicts the least recently used scene; false when the cache is empty.
    fn evict_oldest(&mut self) -> bool {
        let Some(id) = self.lru.values().next().cloned() else { return false };
        self.remove(&id);
        self.stats.evictions += 1;
        true
    }

    fn purge_expired(&mut self, now: Instant) {
        let expired: Vec<String> =
            self.entries.iter().filter(|(_, e)| e.expires <= now).map(|(id, _)| id.clone()).collect();
        for id in expired {
            self.remove(&id);
            self.stats.expirations += 1;
        }
    }
}

/// The wall-clock time of a monotonic instant (for `expires_at` in responses).
fn wall_clock(at: Instant, now: Instant) -> SystemTime {
    SystemTime::now() + at.saturating_duration_since(now)
}

/// RFC 3339 UTC with milliseconds, e.g. `2026-01-01T12:00:00.000Z`.
pub fn rfc3339(t: SystemTime) -> String {
    humantime::format_rfc3339_millis(t).to_string()
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::{ArcArray, Dimension, ShapeBuilder};

    /// A scene holding `floats` f32 values in its volume (plus one each in images and features).
    fn scene(floats: usize) -> Scene {
        fn zeros<D: Dimension>(shape: impl ShapeBuilder<Dim = D>) -> ArcArray<f32, D> {
            ArcArray::zeros(shape)
        }
        Scene {
            images: zeros((1, 1, 1, 1)),
            features: zeros((1, 1, 1, 1)),
            volume: zeros((1, 1, 1, 1, floats)),
            intrinsics: zeros((1, 3, 3)),
            extrinsics: zeros((1, 4, 4)),
            near: 1.0,
            far: 2.0,
        }
    }

    fn cache(max_bytes: usize, ttl_secs: u64) -> SceneCache {
        SceneCache::new(CacheConfig { max_bytes, ttl: Duration::from_secs(ttl_secs) })
    }

    #[test]
    fn ids_are_hex_and_validated() {
        let c = cache(1 << 20, 60);
        let (id, _) = c.insert(scene(10), [0.0; 3], None, Instant::now()).unwrap();
        assert!(is_valid_id(&id), "{id}");
        assert!(!is_valid_id("../etc/passwd"));
        assert!(!is_valid_id(&id.to_uppercase()));
        assert!(!is_valid_id(&id[1..]));
    }

    #[test]
    fn evicts_least_recently_used_by_bytes() {
        // Each scene is (1 + 1 + 1000) floats = 4008 bytes; room for two.
        let c = cache(9000, 60);
        let now = Instant::now();
        let (a, _) = c.insert(scene(1000), [0.0; 3], None, now).unwrap();
        let (b, _) = c.insert(scene(1000), [0.0; 3], None, now).unwrap();
        assert!(c.get(&a, &None, now).is_some()); // a is now the most recently used
        let (d, _) = c.insert(scene(1000), [0.0; 3], None, now).unwrap();
        assert!(c.get(&b, &None, now).is_none(), "b was least recently used");
        assert!(c.get(&a, &None, now).is_some());
        assert!(c.get(&d, &None, now).is_some());
        let s = c.stats();
        assert_eq!((s.entries, s.bytes, s.evictions), (2, 2 * 4008, 1));
        assert_eq!((s.hits, s.misses), (3, 1));
    }

    #[test]
    fn refuses_a_scene_larger_than_the_cache() {
        let c = cache(100, 60);
        let err = c.insert(scene(1000), [0.0; 3], None, Instant::now()).unwrap_err();
        assert_eq!(err, SceneTooLarge { needed: 4008, max: 100 });
        assert_eq!(c.stats().entries, 0);
    }

    #[test]
    fn idle_scenes_expire_and_use_extends_life() {
        let c = cache(1 << 20, 10);
        let t0 = Instant::now();
        let (a, _) = c.insert(scene(10), [0.0; 3], None, t0).unwrap();
        let (b, _) = c.insert(scene(10), [0.0; 3], None, t0).unwrap();
        assert!(c.get(&a, &None, t0 + Duration::from_secs(8)).is_some()); // a now lives to t0+18
        assert!(c.get(&b, &None, t0 + Duration::from_secs(10)).is_none(), "b expired at t0+10");
        assert!(c.get(&a, &None, t0 + Duration::from_secs(17)).is_some());
        c.purge_expired(t0 + Duration::from_secs(60));
        let s = c.stats();
        assert_eq!((s.entries, s.bytes, s.expirations), (0, 0, 2));
    }

    #[test]
    fn scenes_are_private_to_their_owner() {
        let c = cache(1 << 20, 60);
        let now = Instant::now();
        let alice = Some([1u8; 32]);
        let bob = Some([2u8; 32]);
        let (id, _) = c.insert(scene(10), [0.0; 3], alice, now).unwrap();
        assert!(c.get(&id, &bob, now).is_none());
        assert!(c.get(&id, &None, now).is_none());
        assert!(!c.remove(&id, &bob, now));
        assert!(c.get(&id, &alice, now).is_some());
        assert!(c.remove(&id, &alice, now));
        assert!(c.get(&id, &alice, now).is_none());
        assert!(!c.remove(&id, &alice, now));
    }

    #[test]
    fn formats_rfc3339() {
        let t = SystemTime::UNIX_EPOCH + Duration::from_millis(1_767_225_600_123);
        assert_eq!(rfc3339(t), "2026-01-01T00:00:00.123Z");
    }
}
