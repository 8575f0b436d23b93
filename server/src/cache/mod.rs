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
//! two tokens may hold scenes of the same id without seeing each other's. A scene belongs to the
//! model it was created with (`CachedScene::model`); an id names one scene, so one model: a PUT
//! of the id with another model replaces it. Volumes are keyed by their scene's serial, so by
//! its model too.
//!
//! Time is passed in (`now`, from a `Clock`) rather than read here, so tests can drive expiry
//! without sleeping.

mod clock;
mod ids;
mod reclaim;
pub mod shares;

use std::collections::{BTreeMap, HashMap};
use std::sync::{Arc, Mutex};
use std::time::{Instant, SystemTime};

pub use clock::Clock;
#[cfg(any(test, feature = "testing"))]
pub use clock::ManualClock;
pub use ids::{is_valid_id, random_id, ID_PATTERN, MAX_ID_LEN};
pub use shares::{CacheConfig, NoRoom, Owner};

use crate::pipeline::scene::Scene;
use crate::pipeline::views::Views;

/// A scene as cached: its views and, for a scene of exactly the model's view count, the volume
/// of those views in upload order, built when it was created (as scenes always were).
#[derive(Debug)]
pub struct CachedScene {
    pub views: Views,
    pub background: [f32; 3],
    /// The model whose graphs built its volumes: a scene belongs to one model, and its renders
    /// use it (its volumes mean nothing to another model's renderer).
    pub model: Arc<str>,
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
    pub model: Arc<str>,
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
            model: new.model,
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

#[cfg(test)]
mod tests;
