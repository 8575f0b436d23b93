//! Model names: a bundle folder's name, in Unicode NFC, so that two spellings of one name
//! (`café` composed or decomposed) are one model, and without control characters, since a name
//! is sent as it is in the `x-scnerf-model` header, in answers and in logs (a folder whose name
//! holds one is skipped, with the reason, rather than served without its header).

use std::path::Path;

use unicode_normalization::UnicodeNormalization;

use crate::error::ApiError;

/// `name` in NFC.
pub fn normalized(name: &str) -> String {
    name.nfc().collect()
}

/// Why the folder `dir`'s name cannot name a model, if it cannot.
pub fn check_folder(dir: &Path) -> Result<(), String> {
    let Some(name) = dir.file_name() else { return Ok(()) };
    match name.to_string_lossy().chars().find(|c| c.is_control()) {
        Some(c) => Err(format!(
            "the folder's name holds the control character {}: a model's name is sent in headers and logs as \
             it is; rename the folder",
            c.escape_default()
        )),
        None => Ok(()),
    }
}

/// The name a request gives (its `"model"`), normalised as served names are; 422 naming the
/// field for one with a control character, which no served name has.
pub fn requested(name: &str) -> Result<String, ApiError> {
    if name.chars().any(char::is_control) {
        return Err(ApiError::invalid("model", "a model's name holds no control characters"));
    }
    Ok(normalized(name))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_nfc_and_hold_no_control_characters() {
        let (composed, decomposed) = ("caf\u{e9}", "cafe\u{301}");
        assert_eq!(normalized(decomposed), composed);
        assert_eq!(requested(decomposed).unwrap(), composed);
        assert!(check_folder(Path::new("/srv/models/caf\u{e9}")).is_ok());
        let err = check_folder(Path::new("/srv/models/lego\nINFO forged")).unwrap_err();
        assert!(err.contains("\\n") && !err.contains('\n'), "{err}");
        assert_eq!(requested("lego\n").unwrap_err().field(), Some("model"));
    }
}
