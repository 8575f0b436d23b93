//! Who holds what in the cache: owners, their shares of its bytes, and the refusal when a scene
//! does not fit.

use std::time::Duration;

/// Who created a scene: a digest of the bearer token (never the token), or `None` when auth is
/// off. A scene is only visible to the same owner.
pub type Owner = Option<[u8; 32]>;

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
    pub(super) fn share(&self, owners: usize) -> usize {
        self.per_owner_bytes.unwrap_or(self.max_bytes / owners.max(1)).min(self.max_bytes)
    }
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
