//! Reading the text files other tools write (camera files, `transforms.json`, TOML): UTF-8, with
//! or without the byte-order mark Windows editors (Notepad, PowerShell's `Out-File`) put at the
//! start. Rust's and serde's parsers take a mark for content ("expected value at line 1 column 1"
//! on a JSON file that looks right), so it is dropped here; any other text is kept as it is.

use anyhow::{anyhow, Context, Result};
use std::path::Path;

/// The UTF-8 encoding of U+FEFF, the byte-order mark.
const BOM: &str = "\u{feff}";

/// The file's text without a leading byte-order mark; errors name the file (and, for text that
/// is not UTF-8, the byte where it stops being so).
pub fn read(path: &Path) -> Result<String> {
    let bytes = std::fs::read(path).with_context(|| format!("{}: cannot read", path.display()))?;
    let mut text = String::from_utf8(bytes).map_err(|e| {
        anyhow!(
            "{}: not UTF-8 text (byte {} is not valid UTF-8)",
            path.display(),
            e.utf8_error().valid_up_to()
        )
    })?;
    if text.starts_with(BOM) {
        text.drain(..BOM.len());
    }
    Ok(text)
}

#[cfg(test)]
mod tests {
    #[test]
    fn a_byte_order_mark_is_dropped_and_bad_utf8_named() {
        let dir = std::env::temp_dir().join(format!("xscale-text-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("a.json");
        std::fs::write(&p, b"\xef\xbb\xbf{\"a\": 1}\n").unwrap();
        assert_eq!(super::read(&p).unwrap(), "{\"a\": 1}\n");
        std::fs::write(&p, "\u{feff}\u{feff}x").unwrap();
        assert_eq!(super::read(&p).unwrap(), "\u{feff}x", "only the first mark");
        std::fs::write(&p, b"ok\n\xe9t\xe9").unwrap();
        let e = format!("{:#}", super::read(&p).unwrap_err());
        assert!(e.contains("a.json: not UTF-8 text (byte 3"), "{e}");
        let e = format!("{:#}", super::read(&dir.join("none")).unwrap_err());
        assert!(e.contains("none: cannot read"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
