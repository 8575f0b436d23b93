//! Scene ids: what a client may name a scene, and the random ids the server gives.

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
