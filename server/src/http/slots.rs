//! Slots for requests in flight: the server's total and each client's share of it.

use std::net::IpAddr;
use std::sync::Arc;

use tokio::sync::{OwnedSemaphorePermit, Semaphore};

use super::connections::{AddressGuard, PerAddress};
use crate::error::ApiError;

/// Slots for requests being handled: `total` in all, `per_client` (0: any) per peer address.
pub struct Slots {
    total: Arc<Semaphore>,
    clients: PerAddress,
}

/// A taken slot, given back when dropped.
pub struct Slot {
    _total: OwnedSemaphorePermit,
    _client: Option<AddressGuard>,
}

impl Slots {
    pub fn new(total: usize, per_client: usize) -> Slots {
        Slots { total: Arc::new(Semaphore::new(total.max(1))), clients: PerAddress::new(per_client) }
    }

    /// `client`: the peer address (`None` in-process, where there is no peer to tell apart).
    /// The client's own cap is checked first, so that the client holding many slots is the one
    /// told (429), not the others (503).
    pub fn acquire(&self, client: Option<IpAddr>) -> Result<Slot, ApiError> {
        let client = match client {
            Some(ip) => self.clients.enter(ip).ok_or_else(|| ApiError::TooManyRequests {
                message: format!("this client already has {} requests in flight", self.clients.cap()),
                retry_after_secs: 1,
            })?,
            None => None,
        };
        let total = self.total.clone().try_acquire_owned().map_err(|_| ApiError::Unavailable {
            message: "server busy: too many requests in flight".into(),
            retry_after_secs: 1,
        })?;
        Ok(Slot { _total: total, _client: client })
    }
}
