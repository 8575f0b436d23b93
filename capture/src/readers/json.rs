//! JSON files of captures, read with the guards a file from a client needs.

use std::path::Path;

use crate::error::{Error, Result};
use crate::files::Files;

/// A JSON file (a transforms file, a camera path), refused with a message naming it when it is not
/// JSON, repeats a key within an object, or holds more than [`MAX_JSON_VALUES`] values. The
/// checks run over the text before the document is built: `serde_json::Value` takes 16-32 times
/// the text's size for arrays of small numbers, and its maps keep the last of duplicate keys.
pub fn read_json(fs: &dyn Files, path: &Path) -> Result<serde_json::Value> {
    let text = fs.read_text(path)?;
    json_check::check(&text).map_err(|e| Error::dataset(path, format!("invalid JSON: {e}")))?;
    serde_json::from_str(&text).map_err(|e| Error::dataset(path, format!("invalid JSON: {e}")))
}

/// Most values (numbers, strings, arrays, objects...) a JSON file of a capture may hold: a
/// transforms file of 10,000 frames holds about 300,000.
pub const MAX_JSON_VALUES: usize = 1 << 19;

mod json_check {
    use std::collections::HashSet;
    use std::fmt;
    use std::hash::{BuildHasher, RandomState};

    use serde::de::{DeserializeSeed, Deserializer, MapAccess, SeqAccess, Visitor};

    use super::MAX_JSON_VALUES;

    /// Walks the document without building it: counts its values and, per object, the hashes
    /// of its keys (8 bytes a key, whatever its length).
    pub(super) fn check(text: &str) -> Result<(), serde_json::Error> {
        let mut de = serde_json::Deserializer::from_str(text);
        let mut walk = Walk { values: 0, keys: RandomState::new() };
        (&mut walk).deserialize(&mut de)?;
        de.end()
    }

    struct Walk {
        values: usize,
        keys: RandomState,
    }

    impl Walk {
        fn count<E: serde::de::Error>(&mut self) -> Result<(), E> {
            self.values += 1;
            if self.values > MAX_JSON_VALUES {
                return Err(E::custom(format_args!("more than {MAX_JSON_VALUES} values")));
            }
            Ok(())
        }
    }

    impl<'de> DeserializeSeed<'de> for &mut Walk {
        type Value = ();

        fn deserialize<D: Deserializer<'de>>(self, d: D) -> Result<(), D::Error> {
            d.deserialize_any(self)
        }
    }

    /// Reads a key (without copying it when the text holds it unescaped) into the hashes of the
    /// keys of its object, refusing one seen before.
    struct KeySeed<'a> {
        hasher: &'a RandomState,
        seen: &'a mut HashSet<u64>,
    }

    impl<'de> DeserializeSeed<'de> for KeySeed<'_> {
        type Value = ();

        fn deserialize<D: Deserializer<'de>>(self, d: D) -> Result<(), D::Error> {
            d.deserialize_str(self)
        }
    }

    impl<'de> Visitor<'de> for KeySeed<'_> {
        type Value = ();

        fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
            f.write_str("a key")
        }

        fn visit_str<E: serde::de::Error>(self, key: &str) -> Result<(), E> {
            if !self.seen.insert(self.hasher.hash_one(key)) {
                let shown: String = key.chars().take(64).collect();
                return Err(E::custom(format_args!("key {shown:?} appears twice in one object")));
            }
            Ok(())
        }
    }

    impl<'de> Visitor<'de> for &mut Walk {
        type Value = ();

        fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
            f.write_str("any JSON value")
        }

        fn visit_bool<E: serde::de::Error>(self, _: bool) -> Result<(), E> {
            self.count()
        }

        fn visit_i64<E: serde::de::Error>(self, _: i64) -> Result<(), E> {
            self.count()
        }

        fn visit_u64<E: serde::de::Error>(self, _: u64) -> Result<(), E> {
            self.count()
        }

        fn visit_f64<E: serde::de::Error>(self, _: f64) -> Result<(), E> {
            self.count()
        }

        fn visit_str<E: serde::de::Error>(self, _: &str) -> Result<(), E> {
            self.count()
        }

        fn visit_unit<E: serde::de::Error>(self) -> Result<(), E> {
            self.count()
        }

        fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<(), A::Error> {
            self.count()?;
            while seq.next_element_seed(&mut *self)?.is_some() {}
            Ok(())
        }

        fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<(), A::Error> {
            self.count()?;
            let (hasher, mut seen) = (self.keys.clone(), HashSet::new());
            while map.next_key_seed(KeySeed { hasher: &hasher, seen: &mut seen })?.is_some() {
                map.next_value_seed(&mut *self)?;
            }
            Ok(())
        }
    }
}

/// A JSON number, or an error naming the file and the field.
pub(super) fn json_f64(value: &serde_json::Value, path: &Path, field: &str) -> Result<f64> {
    value.as_f64().ok_or_else(|| Error::dataset(path, format!("{field} is not a number: {value}")))
}

/// A 4x4 (or 3x4, completed with [0 0 0 1]) row-major matrix from JSON.
pub(super) fn json_matrix4(value: &serde_json::Value, path: &Path, field: &str) -> Result<nalgebra::Matrix4<f64>> {
    let bad = || Error::dataset(path, format!("{field} must be a finite 4x4 (or 3x4) matrix"));
    let rows = value.as_array().ok_or_else(bad)?;
    if rows.len() != 3 && rows.len() != 4 {
        return Err(bad());
    }
    let mut m = nalgebra::Matrix4::identity();
    for (r, row) in rows.iter().enumerate() {
        let row = row.as_array().filter(|row| row.len() == 4).ok_or_else(bad)?;
        for (c, v) in row.iter().enumerate() {
            m[(r, c)] = v.as_f64().filter(|v| v.is_finite()).ok_or_else(bad)?;
        }
    }
    Ok(m)
}
