use std::time::Duration;

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
        source_sizes: vec![(1, 1); 3],
        near: 1.0,
        far: 2.0,
    }
}

/// A 3-view scene with its volume of `floats` floats: 4 (3 + 1 + floats) bytes.
fn three_views(floats: usize) -> NewScene {
    NewScene { views: views(3), volume: Some(volume(floats)), background: [0.0; 3], model: "m".into() }
}

/// A capture of `n` views, `4 n` bytes, no volume yet.
fn capture(n: usize) -> NewScene {
    NewScene { views: views(n), volume: None, background: [0.0; 3], model: "m".into() }
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
