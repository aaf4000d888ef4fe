//! Hand-written configuration files, read one way: profiles, peers files,
//! plans, the daemon's configuration and scenes. A file is read bounded
//! ([`crate::read`]), past a byte order mark, and parsed as TOML (or JSON,
//! for a `.json` file); an error names the file, the key that is wrong
//! (`devices.rail.limits`, `peer[1].url`) and what was expected, with the
//! line, on one line, never quoting the file.

use std::fmt;
use std::path::Path;

use serde::de::DeserializeOwned;

use crate::read::{read_text, strip_bom};

/// A configuration file that cannot be used: where, which key, and what is
/// wrong or was expected.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub struct ConfigError {
    /// The file's path as given (or another name for text not from a file).
    pub file: String,
    /// The dotted key the error is about (`devices.rail.limits`); empty when
    /// it concerns the whole file (it cannot be read, a syntax error).
    pub key: String,
    /// What is wrong and what was expected, on one line, with the line of
    /// the file where the parser knows it.
    pub message: String,
}

impl ConfigError {
    /// The key and the message, for an error that names the file its own
    /// way.
    pub fn detail(&self) -> String {
        if self.key.is_empty() {
            self.message.clone()
        } else {
            format!("{}: {}", self.key, self.message)
        }
    }
}

impl fmt::Display for ConfigError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: {}", self.file, self.detail())
    }
}

/// The two formats a configuration file may be written in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    /// TOML, the format of every hand-written file rigd reads.
    Toml,
    /// JSON, which plans may also be written in.
    Json,
}

impl Format {
    /// JSON for a `.json` file, TOML otherwise.
    pub fn of(path: &Path) -> Format {
        if path
            .extension()
            .is_some_and(|x| x.eq_ignore_ascii_case("json"))
        {
            Format::Json
        } else {
            Format::Toml
        }
    }
}

/// Reads the file at `path` (at most `limit` bytes, a regular file) and
/// parses it as `T` in `format` ([`Format::of`] the path, where either is
/// allowed).
pub fn load<T: DeserializeOwned>(
    path: &Path,
    limit: u64,
    format: Format,
) -> Result<T, ConfigError> {
    let file = path.display().to_string();
    let text = read_text(path, limit).map_err(|e| ConfigError {
        file: file.clone(),
        key: String::new(),
        message: e.reason.to_string(),
    })?;
    parse(&text, &file, format)
}

/// Parses `text` as `T`; `file` names it in errors.
pub fn parse<T: DeserializeOwned>(
    text: &str,
    file: &str,
    format: Format,
) -> Result<T, ConfigError> {
    let text = strip_bom(text);
    let error = |key: String, message: String| {
        let (key, message) = with_nested_path(key, &message);
        ConfigError {
            file: file.to_string(),
            key: if key == "." { String::new() } else { key },
            // The parsers' messages can span lines; an operator's error is one.
            message: message.trim().replace('\n', "; "),
        }
    };
    match format {
        Format::Toml => {
            let value =
                serde_path_to_error::deserialize(toml::Deserializer::new(text)).map_err(|e| {
                    let key = e.path().to_string();
                    let inner = e.into_inner();
                    let line = inner
                        .span()
                        .map(|s| format!(" (line {})", line_of(text, s.start)))
                        .unwrap_or_default();
                    error(key, format!("{}{line}", inner.message().trim()))
                })?;
            // toml's deserializer fills a fixed-size array (`[u32; 2]`)
            // from the first elements of a longer one and drops the rest;
            // read again from its value tree, which refuses them, naming
            // the key (without a line: the tree has no spans).
            let table: toml::Table =
                toml::from_str(text).map_err(|e| error(String::new(), e.message().to_string()))?;
            serde_path_to_error::deserialize::<_, T>(table).map_err(|e| {
                let key = e.path().to_string();
                error(key, e.into_inner().to_string())
            })?;
            Ok(value)
        }
        Format::Json => {
            let mut de = serde_json::Deserializer::from_str(text);
            let value = serde_path_to_error::deserialize(&mut de).map_err(|e| {
                let key = e.path().to_string();
                error(key, e.into_inner().to_string())
            })?;
            de.end().map_err(|e| error(String::new(), e.to_string()))?;
            Ok(value)
        }
    }
}

/// Marks the path inside a nested error's message; a control character,
/// so that no parser's or validator's message starts with it.
const NESTED: char = '\u{1f}';

/// An error at `path` (`limits.min`, `joints[1].name`) inside a value that
/// was read whole before it could be typed: a table whose type one of its
/// keys decides. Such a value's inner keys are beyond the loader's path
/// tracking, so the error carries them, and the loader appends them to the
/// key it names.
pub fn nested_error<E: serde::de::Error>(path: &str, message: impl fmt::Display) -> E {
    E::custom(format_args!("{NESTED}{path}{NESTED}{message}"))
}

/// The key and message of an error: a nested error's path appended to
/// `key`, and its message without the path.
fn with_nested_path(key: String, message: &str) -> (String, String) {
    let Some(rest) = message.strip_prefix(NESTED) else {
        return (key, message.to_string());
    };
    let Some((path, message)) = rest.split_once(NESTED) else {
        return (key, message.to_string());
    };
    let key = match key.as_str() {
        "" | "." => path.to_string(),
        _ if path.starts_with('[') => format!("{key}{path}"),
        _ => format!("{key}.{path}"),
    };
    (key, message.to_string())
}

/// The 1-based line of byte `at` in `text`.
fn line_of(text: &str, at: usize) -> usize {
    text.as_bytes()[..at.min(text.len())]
        .iter()
        .filter(|&&b| b == b'\n')
        .count()
        + 1
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, serde::Deserialize, PartialEq)]
    #[serde(deny_unknown_fields)]
    struct Rig {
        name: String,
        #[serde(default)]
        axes: Vec<Axis>,
    }

    #[derive(Debug, serde::Deserialize, PartialEq)]
    #[serde(deny_unknown_fields)]
    struct Axis {
        steps: u32,
    }

    #[derive(Debug, serde::Deserialize, PartialEq)]
    struct Frame {
        size: [u32; 2],
        #[serde(default)]
        inner: Option<Frame2>,
    }

    #[derive(Debug, serde::Deserialize, PartialEq)]
    struct Frame2 {
        at: [f64; 2],
    }

    /// A fixed-size array takes exactly its length, in TOML as in JSON:
    /// toml's own deserializer would drop the extra elements.
    #[test]
    fn a_fixed_size_array_takes_exactly_its_length() {
        let ok = parse::<Frame>("size = [640, 480]\n", "f.toml", Format::Toml).expect("two");
        assert_eq!(ok.size, [640, 480]);
        for (text, format, key) in [
            ("size = [640, 480, 3]\n", Format::Toml, "size"),
            ("size = [640]\n", Format::Toml, "size"),
            (
                "size = [1, 2]\n[inner]\nat = [1.0, 2.0, 3.0]\n",
                Format::Toml,
                "inner.at",
            ),
            ("{\"size\": [640, 480, 3]}", Format::Json, "size"),
        ] {
            let e = parse::<Frame>(text, "f", format).expect_err(text);
            assert_eq!(e.key, key, "{text}: {e}");
            assert!(
                e.message.contains("length") || e.message.contains("trailing"),
                "{e}"
            );
        }
    }

    #[test]
    fn errors_name_the_file_the_key_and_the_line() {
        let e = parse::<Rig>(
            "name = \"r\"\n[[axes]]\nsteps = -1\n",
            "r.toml",
            Format::Toml,
        )
        .expect_err("negative steps");
        assert_eq!(
            (e.file.as_str(), e.key.as_str()),
            ("r.toml", "axes[0].steps")
        );
        assert!(e.message.contains("line 3"), "{e}");
        let e = parse::<Rig>(
            "{\"name\": \"r\", \"axes\": [{\"step\": 1}]}",
            "r.json",
            Format::Json,
        )
        .expect_err("unknown key");
        assert_eq!(e.key, "axes[0].step");
        assert!(e.message.contains("`step`"), "{e}");
        assert!(e.to_string().starts_with("r.json: axes[0].step: "), "{e}");
    }

    /// A value read whole before it is typed reports the key inside it,
    /// appended to the key the loader tracked, in TOML and in JSON.
    #[test]
    fn a_nested_error_s_path_extends_the_key() {
        #[derive(Debug)]
        struct Whole;
        impl<'de> serde::Deserialize<'de> for Whole {
            fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Whole, D::Error> {
                let _ = <serde::de::IgnoredAny as serde::Deserialize>::deserialize(d)?;
                Err(nested_error("limits[1].min", "expected a number"))
            }
        }
        #[derive(Debug, serde::Deserialize)]
        struct Outer {
            #[allow(dead_code)]
            axes: Vec<Whole>,
        }
        let e = parse::<Outer>("[[axes]]\nx = 1\n", "r.toml", Format::Toml).expect_err("nested");
        assert_eq!(e.key, "axes[0].limits[1].min", "{e}");
        assert!(e.message.starts_with("expected a number"), "{e}");
        let e = parse::<Outer>("{\"axes\": [{}]}", "r.json", Format::Json).expect_err("nested");
        assert_eq!(e.key, "axes[0].limits[1].min", "{e}");
        let e = parse::<Whole>("x = 1", "r.toml", Format::Toml).expect_err("at the top");
        assert_eq!(e.key, "limits[1].min", "{e}");
        assert!(!e.to_string().contains(NESTED), "{e}");
    }

    #[test]
    fn a_whole_file_error_has_no_key_and_never_quotes_the_file() {
        let e =
            parse::<Rig>("root:x:0:0:secret\n", "/etc/passwd", Format::Toml).expect_err("not TOML");
        assert_eq!(e.key, "");
        assert!(!e.to_string().contains("secret"), "{e}");
        let e = parse::<Rig>("{\"name\": \"r\"} secret", "r.json", Format::Json)
            .expect_err("trailing text");
        assert!(!e.to_string().contains("secret"), "{e}");
    }

    #[test]
    fn a_byte_order_mark_is_read_past_and_the_extension_picks_the_format() {
        let rig: Rig = parse("\u{feff}name = \"r\"", "r.toml", Format::Toml).expect("BOM");
        assert_eq!(rig.name, "r");
        assert_eq!(Format::of(Path::new("plan.JSON")), Format::Json);
        assert_eq!(Format::of(Path::new("plan.toml")), Format::Toml);
        assert_eq!(Format::of(Path::new("plan")), Format::Toml);
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("r.json");
        std::fs::write(&path, "{\"name\": \"j\"}").expect("write");
        assert_eq!(
            load::<Rig>(&path, 1024, Format::of(&path))
                .expect("load")
                .name,
            "j"
        );
        let e =
            load::<Rig>(&dir.path().join("none.toml"), 1024, Format::Toml).expect_err("missing");
        assert!(e.file.ends_with("none.toml") && e.key.is_empty(), "{e}");
    }
}
