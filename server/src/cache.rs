//! Scene cache: scenes (every view decoded, cameras, near/far, background) kept by id, and, per
//! scene, the encoder features and encoding volume of each triple of views a render used, so
//! that further views from the same triple cost only the renderer.
//!
//! One byte budget for both, shared fairly among owners (tokens): each owner has a share of it
//! (`CacheConfig::per_owner_bytes`, by default an equal share among the configured tokens; the
//! whole cache without auth, where every client is the one anonymous owner). When room is
//! needed, expired scenes go first; then, among the entries that may go, the least recently used
//! *volume* (a few seconds of CPU to build again from the cached views) before the least recently
//! used *scene* with its volumes (its client must upload it again). Which entries may go, in turn:
//! 1. the owner's own, when it would hold more than its share;
//! 2. those of owners holding more than their share, while they do;
//! 3. the owner's own (when shares add up to more than the cache).
//!
//! So an owner never pushes another below its share: one token uploading scene after scene
//! evicts its own. A scene also expires after an idle time-to-live (every render extends it).
//! Entries are `Arc`s: evicting what a request is rendering frees it when that request ends.
//!
//! Ids are the client's (`PUT /v1/scenes/{id}`) or random (`POST`), and are namespaced by owner:
//! two tokens may hold scenes of the same id without seeing each other's.
//!
//! Time is passed in (`now`) rather than read here, so tests can drive expiry without sleeping.

use std::collections::{BTreeMap, HashMap};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime};

use crate::pipeline::views::Views;
use crate::pipeline::Scene;

/// Who created a scene: a digest of the bearer token (never the token), or `None` when auth is
/// off. A scene is only visible to the same owner.
pub type Owner = Option<[u8; 32]>;

/// Longest scene id.
pub const MAX_ID_LEN: usize = 64;

/// What `is_valid_id` accepts, as the API document's pattern (which cannot say "not `.` or
/// `..`").
pub const ID_PATTERN: &str = "^[A-Za-z0-9._-]{1,64}$";

/// A scene id: 1 to 64 characters of `A-Z a-z 0-9 . _ -`, not `.` or `..` (which do not survive
/// as path segments). Random ids are 32 lowercase hex digits (128 bits, a UUID v4): without auth
/// such an id is a capability.
pub fn is_valid_id(id: &str) -> bool {
    (1..=MAX_ID_LEN).contains(&id.len())
        && id.bytes().all(|b| b.is_ascii_alphanumeric() || b"._-".contains(&b))
        && id != "."
        && id != ".."
}

/// A fresh random id.
pub fn random_id() -> String {
    uuid::Uuid::new_v4().simple().to_string()
}

/// A scene as cached: its views and, for a scene of exactly the model's view count, the volume
/// of those views in upload order, built when it was created (as scenes always were).
#[derive(Debug)]
pub struct CachedScene {
    pub views: Views,
    pub background: [f32; 3],
    fixed: Option<Arc<Scene>>,
    key: SceneKey,
    /// Tells a scene from an earlier one of the same id (replaced meanwhile).
    serial: u64,
}

impl CachedScene {
    fn bytes(&self) -> usize {
        // The fixed volume shares the views' images.
        self.views.bytes() + self.fixed.as_ref().map_or(0, |s| s.bytes() - 4 * s.images.len())
    }

    fn is_fixed(&self, sources: &[usize]) -> bool {
        self.fixed.is_some() && sources.iter().copied().eq(0..self.views.len())
    }
}

/// What a new scene brings to the cache.
pub struct NewScene {
    pub views: Views,
    /// The volume of the views in upload order, when built at creation.
    pub volume: Option<Scene>,
    pub background: [f32; 3],
}

#[derive(Debug, Clone, Copy)]
pub struct CacheConfig {
    pub max_bytes: usize,
    pub ttl: Duration,
    /// Each owner's share of `max_bytes`; `None`: an equal share among the owners the server
    /// knows (`SceneCache::new`).
    pub per_owner_bytes: Option<usize>,
}

impl Default for CacheConfig {
    fn default() -> Self {
        CacheConfig { max_bytes: 2 << 30, ttl: Duration::from_secs(600), per_owner_bytes: None }
    }
}

impl CacheConfig {
    /// Each owner's share among `owners` (the configured tokens; 0 without auth: one pool).
    fn share(&self, owners: usize) -> usize {
        self.per_owner_bytes.unwrap_or(self.max_bytes / owners.max(1)).min(self.max_bytes)
    }
}

#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct CacheStats {
    /// Scenes held.
    pub entries: usize,
    /// Everything held: scenes and their volumes.
    pub bytes: usize,
    pub hits: u64,
    pub misses: u64,
    pub evictions: u64,
    pub expirations: u64,
    /// Volumes of triples held (a 3-view scene's own volume is part of the scene).
    pub volumes: usize,
    pub volume_bytes: usize,
    /// Renders whose triple's volume was cached, and those that built it.
    pub volume_hits: u64,
    pub volume_misses: u64,
    pub volume_evictions: u64,
}

/// Why a scene is not cached.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum NoRoom {
    /// Larger than its owner's share: it never fits.
    #[error("the scene needs {needed} bytes but a client may hold at most {max} bytes of cached scenes")]
    TooLarge { needed: usize, max: usize },
    /// It fits the owner's share, but the other owners hold no more than theirs (possible only
    /// when the shares add up to more than the cache): room comes as their scenes expire.
    #[error("the scene cache is full: the other clients hold their shares of it")]
    Full,
}

#[derive(Debug, Clone, PartialEq, Eq, Hash)]
struct SceneKey {
    owner: Owner,
    id: String,
}

/// A scene's serial and the views of a triple, in volume order.
type VolumeKey = (u64, Vec<usize>);

struct SceneEntry {
    scene: Arc<CachedScene>,
    bytes: usize,
    expires: Instant,
    /// Position in `Inner::scene_lru` (larger = used more recently).
    tick: u64,
}

struct VolumeEntry {
    volume: Arc<Scene>,
    owner: Owner,
    bytes: usize,
    tick: u64,
}

#[derive(Default)]
struct Inner {
    scenes: HashMap<SceneKey, SceneEntry>,
    volumes: HashMap<VolumeKey, VolumeEntry>,
    /// tick -> key, oldest first.
    scene_lru: BTreeMap<u64, SceneKey>,
    volume_lru: BTreeMap<u64, VolumeKey>,
    /// Bytes held per owner (scenes and their volumes).
    held: HashMap<Owner, usize>,
    next_tick: u64,
    next_serial: u64,
    stats: CacheStats,
}

pub struct SceneCache {
    config: CacheConfig,
    /// Each owner's share of `config.max_bytes`.
    share: usize,
    inner: Mutex<Inner>,
}

/// A cache hit: the scene and when it now expires.
pub struct Hit {
    pub scene: Arc<CachedScene>,
    pub expires_at: SystemTime,
}

/// A stored scene: its id, its expiry, and whether it replaced one of the same id.
#[derive(Debug)]
pub struct Stored {
    pub id: String,
    pub expires_at: SystemTime,
    pub replaced: bool,
}

impl SceneCache {
    /// `owners`: how many tokens the server accepts (0 without auth), for the default share.
    pub fn new(config: CacheConfig, owners: usize) -> SceneCache {
        SceneCache { config, share: config.share(owners), inner: Mutex::new(Inner::default()) }
    }

    pub fn config(&self) -> CacheConfig {
        self.config
    }

    /// A poisoned lock only means another request panicked mid-update; the maps stay usable.
    fn lock(&self) -> std::sync::MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Refuses a scene of `bytes` that its owner's share could not hold (before it is decoded).
    pub fn check_fits(&self, bytes: u64) -> Result<(), NoRoom> {
        let needed = usize::try_from(bytes).unwrap_or(usize::MAX);
        match needed > self.share {
            true => Err(NoRoom::TooLarge { needed, max: self.share }),
            false => Ok(()),
        }
    }

    /// Stores a scene under `id` (replacing `owner`'s scene of that id) or a fresh random id,
    /// making room as the module doc says.
    pub fn insert(&self, id: Option<String>, owner: Owner, new: NewScene, now: Instant) -> Result<Stored, NoRoom> {
        let key = SceneKey { owner, id: id.unwrap_or_else(random_id) };
        let mut inner = self.lock();
        let serial = inner.next_serial;
        inner.next_serial += 1;
        let scene = CachedScene {
            views: new.views,
            background: new.background,
            fixed: new.volume.map(Arc::new),
            key: key.clone(),
            serial,
        };
        let bytes = scene.bytes();
        if bytes > self.share {
            return Err(NoRoom::TooLarge { needed: bytes, max: self.share });
        }
        inner.purge_expired(now);
        let replaced = inner.remove_scene(&key);
        if !inner.make_room(&key.owner, bytes, None, self.share, self.config.max_bytes) {
            return Err(NoRoom::Full);
        }
        let expires = now + self.config.ttl;
        let tick = inner.tick();
        inner.scene_lru.insert(tick, key.clone());
        inner.scenes.insert(key.clone(), SceneEntry { scene: Arc::new(scene), bytes, expires, tick });
        inner.charge(&key.owner, bytes as isize);
        inner.stats.entries = inner.scenes.len();
        Ok(Stored { id: key.id, expires_at: wall_clock(expires, now), replaced })
    }

    /// Looks a scene up for `owner`, marks it recently used and extends its life by the TTL.
    /// Unknown, expired and other owners' scenes are all `None` (a miss).
    pub fn get(&self, id: &str, owner: &Owner, now: Instant) -> Option<Hit> {
        let mut inner = self.lock();
        inner.purge_expired(now);
        let key = SceneKey { owner: *owner, id: id.to_string() };
        let Some(old_tick) = inner.scenes.get(&key).map(|e| e.tick) else {
            inner.stats.misses += 1;
            return None;
        };
        inner.scene_lru.remove(&old_tick);
        let tick = inner.tick();
        inner.scene_lru.insert(tick, key.clone());
        inner.stats.hits += 1;
        let entry = inner.scenes.get_mut(&key).expect("looked up above");
        entry.tick = tick;
        entry.expires = now + self.config.ttl;
        Some(Hit { scene: entry.scene.clone(), expires_at: wall_clock(entry.expires, now) })
    }

    /// Deletes `owner`'s scene and its volumes; false when there is no such (live) scene.
    pub fn remove(&self, id: &str, owner: &Owner, now: Instant) -> bool {
        let mut inner = self.lock();
        inner.purge_expired(now);
        inner.remove_scene(&SceneKey { owner: *owner, id: id.to_string() })
    }

    /// The volume of `scene`'s views `sources` (volume order), when cached; marks it recently
    /// used. Counted as a volume hit or miss.
    pub fn volume(&self, scene: &CachedScene, sources: &[usize]) -> Option<Arc<Scene>> {
        let mut inner = self.lock();
        let found = if scene.is_fixed(sources) {
            scene.fixed.clone()
        } else {
            inner.touch_volume(&(scene.serial, sources.to_vec()))
        };
        match found {
            Some(_) => inner.stats.volume_hits += 1,
            None => inner.stats.volume_misses += 1,
        }
        found
    }

    /// Keeps a volume built for `scene`'s views `sources`, if the scene is still cached and the
    /// two fit in the budget together; other volumes, then other scenes, make room.
    pub fn insert_volume(&self, scene: &CachedScene, sources: Vec<usize>, volume: Arc<Scene>) {
        let mut inner = self.lock();
        let Some(scene_bytes) =
            inner.scenes.get(&scene.key).filter(|e| e.scene.serial == scene.serial).map(|e| e.bytes)
        else {
            return; // deleted, replaced or evicted while the volume was built
        };
        let key = (scene.serial, sources);
        let bytes = volume.bytes();
        if scene.is_fixed(&key.1) || inner.volumes.contains_key(&key) || scene_bytes + bytes > self.share {
            return;
        }
        let owner = scene.key.owner;
        if !inner.make_room(&owner, bytes, Some(&scene.key), self.share, self.config.max_bytes) {
            return;
        }
        let tick = inner.tick();
        inner.volume_lru.insert(tick, key.clone());
        inner.volumes.insert(key, VolumeEntry { volume, owner, bytes, tick });
        inner.charge(&owner, bytes as isize);
        inner.stats.volume_bytes += bytes;
        inner.stats.volumes = inner.volumes.len();
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
    fn tick(&mut self) -> u64 {
        let t = self.next_tick;
        self.next_tick += 1;
        t
    }

    fn touch_volume(&mut self, key: &VolumeKey) -> Option<Arc<Scene>> {
        let old = self.volumes.get(key)?.tick;
        self.volume_lru.remove(&old);
        let tick = self.tick();
        self.volume_lru.insert(tick, key.clone());
        let entry = self.volumes.get_mut(key)?;
        entry.tick = tick;
        Some(entry.volume.clone())
    }

    /// Adds `bytes` (negative: frees them) to what `owner` holds and to the total.
    fn charge(&mut self, owner: &Owner, bytes: isize) {
        let held = self.held.entry(*owner).or_default();
        *held = held.saturating_add_signed(bytes);
        if *held == 0 {
            self.held.remove(owner);
        }
        self.stats.bytes = self.stats.bytes.saturating_add_signed(bytes);
    }

    fn held_by(&self, owner: &Owner) -> usize {
        self.held.get(owner).copied().unwrap_or(0)
    }

    fn remove_volume(&mut self, key: &VolumeKey) {
        if let Some(entry) = self.volumes.remove(key) {
            self.volume_lru.remove(&entry.tick);
            self.charge(&entry.owner, -(entry.bytes as isize));
            self.stats.volume_bytes -= entry.bytes;
            self.stats.volumes = self.volumes.len();
        }
    }

    /// Removes a scene and its volumes; false when there was none.
    fn remove_scene(&mut self, key: &SceneKey) -> bool {
        let Some(entry) = self.scenes.remove(key) else { return false };
        self.scene_lru.remove(&entry.tick);
        self.charge(&key.owner, -(entry.bytes as isize));
        self.stats.entries = self.scenes.len();
        let serial = entry.scene.serial;
        let own: Vec<VolumeKey> = self.volumes.keys().filter(|k| k.0 == serial).cloned().collect();
        for k in &own {
            self.remove_volume(k);
        }
        true
    }

    /// Evicts until `owner`'s `bytes` more fit in `max`, from whom the module doc says, never
    /// `keep`; false when they cannot fit so.
    fn make_room(&mut self, owner: &Owner, bytes: usize, keep: Option<&SceneKey>, share: usize, max: usize) -> bool {
        while self.stats.bytes + bytes > max {
            let over_share = self.held_by(owner) + bytes > share;
            let others_over: Vec<Owner> =
                self.held.iter().filter(|(o, held)| *o != owner && **held > share).map(|(o, _)| *o).collect();
            let evicted = (over_share && self.evict(&[*owner], keep))
                || self.evict(&others_over, keep)
                || self.evict(&[*owner], keep);
            if !evicted {
                return false;
            }
        }
        true
    }

    /// Evicts the least recently used volume of `owners`, else their least recently used scene
    /// but `keep`; false when they have nothing to evict.
    fn evict(&mut self, owners: &[Owner], keep: Option<&SceneKey>) -> bool {
        let volume = self.volume_lru.values().find(|k| owners.contains(&self.volumes[*k].owner)).cloned();
        if let Some(key) = volume {
            self.remove_volume(&key);
            self.stats.volume_evictions += 1;
            return true;
        }
        let scene = self.scene_lru.values().find(|k| owners.contains(&k.owner) && Some(*k) != keep).cloned();
        let Some(key) = scene else { return false };
        self.remove_scene(&key);
        self.stats.evictions += 1;
        true
    }

    fn purge_expired(&mut self, now: Instant) {
        let expired: Vec<SceneKey> =
            self.scenes.iter().filter(|(_, e)| e.expires <= now).map(|(k, _)| k.clone()).collect();
        for key in expired {
            self.remove_scene(&key);
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

    fn zeros<D: Dimension>(shape: impl ShapeBuilder<Dim = D>) -> ArcArray<f32, D> {
        ArcArray::zeros(shape)
    }

    /// `n` views of one float each.
    fn views(n: usize) -> Views {
        Views { images: zeros((n, 1, 1, 1)), cameras: vec![crate::testing::camera(); n], near: 1.0, far: 2.0 }
    }

    /// A triple's scene holding `floats` f32 values in its volume (plus 3 image and 1 feature).
    fn volume(floats: usize) -> Scene {
        Scene {
            images: zeros((3, 1, 1, 1)),
            features: zeros((1, 1, 1, 1)),
            volume: zeros((1, 1, 1, 1, floats)),
            intrinsics: zeros((1, 3, 3)),
            extrinsics: zeros((1, 4, 4)),
            near: 1.0,
            far: 2.0,
        }
    }

    /// A 3-view scene with its volume of `floats` floats: 4 (3 + 1 + floats) bytes.
    fn three_views(floats: usize) -> NewScene {
        NewScene { views: views(3), volume: Some(volume(floats)), background: [0.0; 3] }
    }

    /// A capture of `n` views, `4 n` bytes, no volume yet.
    fn capture(n: usize) -> NewScene {
        NewScene { views: views(n), volume: None, background: [0.0; 3] }
    }

    fn cache(max_bytes: usize, ttl_secs: u64) -> SceneCache {
        SceneCache::new(CacheConfig { max_bytes, ttl: Duration::from_secs(ttl_secs), per_owner_bytes: None }, 0)
    }

    fn put(c: &SceneCache, new: NewScene, now: Instant) -> String {
        c.insert(None, None, new, now).unwrap().id
    }

    #[test]
    fn ids_are_validated() {
        let c = cache(1 << 20, 60);
        let id = put(&c, three_views(10), Instant::now());
        assert!(is_valid_id(&id) && id.len() == 32, "{id}");
        for good in ["a", "my-scene_2.v1", &"x".repeat(64), &id.to_uppercase()] {
            assert!(is_valid_id(good), "{good}");
        }
        for bad in ["", ".", "..", "../etc/passwd", "a/b", "a b", "é", &"x".repeat(65)] {
            assert!(!is_valid_id(bad), "{bad}");
        }
    }

    #[test]
    fn evicts_least_recently_used_by_bytes() {
        // Each scene is (3 + 1 + 1000) floats = 4016 bytes; room for two.
        let c = cache(9000, 60);
        let now = Instant::now();
        let a = put(&c, three_views(1000), now);
        let b = put(&c, three_views(1000), now);
        assert!(c.get(&a, &None, now).is_some()); // a is now the most recently used
        let d = put(&c, three_views(1000), now);
        assert!(c.get(&b, &None, now).is_none(), "b was least recently used");
        assert!(c.get(&a, &None, now).is_some());
        assert!(c.get(&d, &None, now).is_some());
        let s = c.stats();
        assert_eq!((s.entries, s.bytes, s.evictions), (2, 2 * 4016, 1));
        assert_eq!((s.hits, s.misses), (3, 1));
    }

    #[test]
    fn refuses_a_scene_larger_than_the_cache() {
        let c = cache(100, 60);
        let err = c.insert(None, None, three_views(1000), Instant::now()).unwrap_err();
        assert_eq!(err, NoRoom::TooLarge { needed: 4016, max: 100 });
        assert_eq!(c.stats().entries, 0);
    }

    #[test]
    fn idle_scenes_expire_and_use_extends_life() {
        let c = cache(1 << 20, 10);
        let t0 = Instant::now();
        let a = put(&c, three_views(10), t0);
        let b = put(&c, three_views(10), t0);
        assert!(c.get(&a, &None, t0 + Duration::from_secs(8)).is_some()); // a now lives to t0+18
        assert!(c.get(&b, &None, t0 + Duration::from_secs(10)).is_none(), "b expired at t0+10");
        assert!(c.get(&a, &None, t0 + Duration::from_secs(17)).is_some());
        c.purge_expired(t0 + Duration::from_secs(60));
        let s = c.stats();
        assert_eq!((s.entries, s.bytes, s.expirations), (0, 0, 2));
    }

    #[test]
    fn scenes_are_private_to_their_owner_and_ids_are_namespaced() {
        let c = cache(1 << 20, 60);
        let now = Instant::now();
        let (alice, bob) = (Some([1u8; 32]), Some([2u8; 32]));
        let id = c.insert(None, alice, three_views(10), now).unwrap().id;
        assert!(c.get(&id, &bob, now).is_none());
        assert!(c.get(&id, &None, now).is_none());
        assert!(!c.remove(&id, &bob, now));
        // Bob names a scene with Alice's id: a scene of his own, hers unchanged.
        let stored = c.insert(Some(id.clone()), bob, capture(5), now).unwrap();
        assert!(!stored.replaced);
        assert_eq!(c.get(&id, &alice, now).unwrap().scene.views.len(), 3);
        assert_eq!(c.get(&id, &bob, now).unwrap().scene.views.len(), 5);
        assert!(c.remove(&id, &alice, now));
        assert!(c.get(&id, &alice, now).is_none());
        assert!(!c.remove(&id, &alice, now));
        assert!(c.get(&id, &bob, now).is_some());
    }

    #[test]
    fn a_named_scene_is_replaced_with_its_volumes() {
        let c = cache(1 << 20, 60);
        let now = Instant::now();
        let first = c.insert(Some("tabletop".into()), None, capture(4), now).unwrap();
        assert_eq!((first.id.as_str(), first.replaced), ("tabletop", false));
        let old = c.get("tabletop", &None, now).unwrap().scene;
        c.insert_volume(&old, vec![0, 1, 2], Arc::new(volume(100)));
        assert_eq!(c.stats().volumes, 1);
        let second = c.insert(Some("tabletop".into()), None, capture(6), now).unwrap();
        assert!(second.replaced);
        let s = c.stats();
        assert_eq!((s.entries, s.volumes, s.bytes, s.volume_bytes), (1, 0, 4 * 6, 0));
        let new = c.get("tabletop", &None, now).unwrap().scene;
        assert_eq!(new.views.len(), 6);
        assert!(c.volume(&new, &[0, 1, 2]).is_none(), "the old scene's volume is gone");
        // A volume still being built for the replaced scene is not kept.
        c.insert_volume(&old, vec![0, 1, 2], Arc::new(volume(100)));
        assert_eq!(c.stats().volumes, 0);
    }

    #[test]
    fn volumes_are_kept_per_triple_and_counted() {
        let c = cache(1 << 20, 60);
        let now = Instant::now();
        let id = put(&c, capture(8), now);
        let scene = c.get(&id, &None, now).unwrap().scene;
        assert!(c.volume(&scene, &[0, 1, 2]).is_none());
        c.insert_volume(&scene, vec![0, 1, 2], Arc::new(volume(100)));
        assert!(c.volume(&scene, &[0, 1, 2]).is_some());
        assert!(c.volume(&scene, &[1, 0, 2]).is_none(), "another reference: another volume");
        let s = c.stats();
        assert_eq!((s.volume_hits, s.volume_misses, s.volumes), (1, 2, 1));
        assert_eq!((s.volume_bytes, s.bytes), (4 * 104, 4 * 104 + 4 * 8));
        // A 3-view scene's own volume is part of it: a hit, never stored twice.
        let id3 = put(&c, three_views(10), now);
        let three = c.get(&id3, &None, now).unwrap().scene;
        assert!(c.volume(&three, &[0, 1, 2]).is_some());
        c.insert_volume(&three, vec![0, 1, 2], Arc::new(volume(100)));
        assert_eq!(c.stats().volumes, 1);
        assert!(c.remove(&id, &None, now));
        assert_eq!((c.stats().volumes, c.stats().volume_bytes), (0, 0), "volumes go with their scene");
    }

    /// Many triples of one capture: the bytes held never exceed the budget, the oldest volumes
    /// go first, and the capture itself stays.
    #[test]
    fn the_bound_holds_with_many_triples() {
        let max = 4 * (20 + 3 * 104); // the capture and three volumes
        let c = cache(max, 60);
        let now = Instant::now();
        let id = put(&c, capture(20), now);
        let scene = c.get(&id, &None, now).unwrap().scene;
        for i in 0..18 {
            c.insert_volume(&scene, vec![i, i + 1, i + 2], Arc::new(volume(100)));
            assert!(c.stats().bytes <= max, "after triple {i}: {:?}", c.stats());
        }
        let s = c.stats();
        assert_eq!((s.entries, s.volumes, s.volume_evictions, s.evictions), (1, 3, 15, 0));
        assert!(c.volume(&scene, &[17, 18, 19]).is_some() && c.volume(&scene, &[14, 15, 16]).is_none());
        // A volume that cannot fit beside its scene is not kept (and evicts nothing).
        c.insert_volume(&scene, vec![0, 2, 4], Arc::new(volume(10_000)));
        assert_eq!(c.stats().volumes, 3);
    }

    #[test]
    fn volumes_are_evicted_before_scenes() {
        // Room for three captures and a volume, less one byte.
        let c = cache(4 * (3 * 8 + 104) - 1, 60);
        let now = Instant::now();
        let a = put(&c, capture(8), now);
        let b = put(&c, capture(8), now);
        let scene_a = c.get(&a, &None, now).unwrap().scene;
        c.insert_volume(&scene_a, vec![0, 1, 2], Arc::new(volume(100)));
        // A third capture needs room: a's volume goes, both scenes stay.
        let d = put(&c, capture(8), now);
        assert!([&a, &b, &d].iter().all(|id| c.get(id, &None, now).is_some()));
        let s = c.stats();
        assert_eq!((s.volumes, s.volume_evictions, s.evictions), (0, 1, 0));
        // Another volume for a evicts the least recently used other scene (b), never a itself.
        let _ = c.get(&d, &None, now);
        c.insert_volume(&scene_a, vec![0, 1, 2], Arc::new(volume(100)));
        assert!(c.get(&b, &None, now).is_none() && c.get(&a, &None, now).is_some());
        assert_eq!(c.stats().evictions, 1);
    }

    fn shared_cache(scenes: usize, per_owner_scenes: Option<usize>, owners: usize) -> SceneCache {
        let config = CacheConfig {
            max_bytes: scenes * SCENE,
            ttl: Duration::from_secs(60),
            per_owner_bytes: per_owner_scenes.map(|n| n * SCENE),
        };
        SceneCache::new(config, owners)
    }

    /// Bytes of `three_views(1000)`.
    const SCENE: usize = 4016;

    fn put_as(c: &SceneCache, owner: Owner, now: Instant) -> Result<String, NoRoom> {
        c.insert(None, owner, three_views(1000), now).map(|s| s.id)
    }

    /// The probe's sequence: B caches three scenes and renders them; A then uploads scene after
    /// scene. A evicts its own, and B keeps all of its scenes (within its share).
    #[test]
    fn one_owner_cannot_evict_another_within_its_share() {
        let (a, b) = (Some([1u8; 32]), Some([2u8; 32]));
        let c = shared_cache(8, None, 2); // an equal share: 4 scenes each
        let now = Instant::now();
        let bs: Vec<String> = (0..3).map(|_| put_as(&c, b, now).unwrap()).collect();
        assert!(bs.iter().all(|id| c.get(id, &b, now).is_some()));
        let as_: Vec<String> = (0..20).map(|_| put_as(&c, a, now).unwrap()).collect();
        assert!(bs.iter().all(|id| c.get(id, &b, now).is_some()), "B's scenes stay");
        // A has its share and the room B leaves: its five latest scenes.
        let kept: Vec<bool> = as_.iter().map(|id| c.get(id, &a, now).is_some()).collect();
        assert_eq!(kept, [vec![false; 15], vec![true; 5]].concat());
        assert_eq!((c.stats().bytes, c.stats().evictions), (8 * SCENE, 15));
    }

    /// An owner holding more than its share (the cache had room) gives back its excess, least
    /// recently used first, down to its share and no further.
    #[test]
    fn an_owner_over_its_share_gives_back_the_excess() {
        let (a, b) = (Some([1u8; 32]), Some([2u8; 32]));
        let c = shared_cache(8, None, 2);
        let now = Instant::now();
        let bs: Vec<String> = (0..8).map(|_| put_as(&c, b, now).unwrap()).collect();
        let _ = c.get(&bs[0], &b, now); // B's first is now its most recently used
        for _ in 0..6 {
            put_as(&c, a, now).unwrap();
        }
        let kept: Vec<bool> = bs.iter().map(|id| c.get(id, &b, now).is_some()).collect();
        assert_eq!(kept, [true, false, false, false, false, true, true, true], "B keeps 4: its share");
    }

    /// Shares configured to add up to more than the cache: a scene that fits its owner's share
    /// but would push another owner below its own is refused, not cached at that owner's cost.
    #[test]
    fn shares_larger_than_the_cache_refuse_rather_than_evict_others() {
        let (a, b, d) = (Some([1u8; 32]), Some([2u8; 32]), Some([4u8; 32]));
        let c = shared_cache(8, Some(6), 3);
        let now = Instant::now();
        let bs: Vec<String> = (0..6).map(|_| put_as(&c, b, now).unwrap()).collect();
        let ds: Vec<String> = (0..2).map(|_| put_as(&c, d, now).unwrap()).collect();
        assert_eq!(put_as(&c, a, now), Err(NoRoom::Full));
        // D, within its share, makes room from its own scenes.
        let d3 = put_as(&c, d, now).unwrap();
        assert!(c.get(&ds[0], &d, now).is_none() && c.get(&d3, &d, now).is_some());
        assert!(bs.iter().all(|id| c.get(id, &b, now).is_some()));
        // A scene larger than a share is refused before anything else.
        assert_eq!(c.check_fits(7 * SCENE as u64), Err(NoRoom::TooLarge { needed: 7 * SCENE, max: 6 * SCENE }));
    }

    #[test]
    fn formats_rfc3339() {
        let t = SystemTime::UNIX_EPOCH + Duration::from_millis(1_767_225_600_123);
        assert_eq!(rfc3339(t), "2026-01-01T00:00:00.123Z");
    }
}
