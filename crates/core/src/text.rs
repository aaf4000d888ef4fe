//! Text files people write by hand: configuration, profiles, plans and
//! scenes, as editors save them.

/// `text` without a leading UTF-8 byte order mark (U+FEFF). Some editors
/// (Notepad among them) start every file they save with one, and neither
/// TOML nor JSON allows it, so each loader of a hand-written file passes
/// its text through here first.
pub fn strip_bom(text: &str) -> &str {
    text.strip_prefix('\u{feff}').unwrap_or(text)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_a_leading_mark_goes() {
        assert_eq!(strip_bom("\u{feff}a = 1"), "a = 1");
        assert_eq!(strip_bom("a = 1"), "a = 1");
        assert_eq!(strip_bom("a = \"\u{feff}\""), "a = \"\u{feff}\"");
        assert_eq!(strip_bom(""), "");
    }
}
