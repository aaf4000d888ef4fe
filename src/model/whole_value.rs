//! Typing a table that was read whole first (a device, whose `kind` decides
//! its type; the simulator's `[sim]` keys), with the strictness the file's
//! own parser has: serde-value's deserializer fills a fixed-size array
//! (`resolution = [w, h]`) from the first elements of a longer one and
//! drops the rest unseen, so the value typed is compared with the value
//! given, and an array given more elements than it keeps is refused.

use serde::de::{DeserializeOwned, Error};
use serde::Serialize;
use serde_value::{Value, ValueDeserializer};

/// `value` as a `T`, or the path of the key at fault (`.` for the whole
/// value; `intrinsics.resolution`, `joints[1].name`) and why.
pub fn typed<T: DeserializeOwned + Serialize, E: Error>(value: Value) -> Result<T, (String, E)> {
    let typed: T = serde_path_to_error::deserialize(ValueDeserializer::<E>::new(value.clone()))
        .map_err(|e| (e.path().to_string(), e.into_inner()))?;
    // A value that does not serialize back cannot be compared; every
    // type read this way serializes (a run keeps its profile).
    if let Ok(kept) = serde_value::to_value(&typed) {
        let mut path = String::new();
        if let Some((given, held)) = longer_array(&value, &kept, &mut path) {
            let expected = format!("an array of length {held}");
            return Err((path, E::invalid_length(given, &expected.as_str())));
        }
    }
    Ok(typed)
}

/// The first array in `given` longer than the same key's in `kept`: the
/// lengths, with `path` set to its key.
fn longer_array(given: &Value, kept: &Value, path: &mut String) -> Option<(usize, usize)> {
    match (bare(given), bare(kept)) {
        (Value::Seq(g), Value::Seq(k)) => {
            if g.len() > k.len() {
                return Some((g.len(), k.len()));
            }
            let at = path.len();
            for (i, (g, k)) in g.iter().zip(k).enumerate() {
                path.push_str(&format!("[{i}]"));
                if let Some(found) = longer_array(g, k, path) {
                    return Some(found);
                }
                path.truncate(at);
            }
            None
        }
        (Value::Map(g), Value::Map(k)) => {
            let at = path.len();
            for (key, g) in g {
                let (Value::String(name), Some(k)) = (key, k.get(key)) else {
                    continue;
                };
                if !path.is_empty() {
                    path.push('.');
                }
                path.push_str(name);
                if let Some(found) = longer_array(g, k, path) {
                    return Some(found);
                }
                path.truncate(at);
            }
            None
        }
        _ => None,
    }
}

/// `value` without the wrappers serialization adds (`Some`, newtypes).
fn bare(value: &Value) -> &Value {
    match value {
        Value::Option(Some(inner)) | Value::Newtype(inner) => bare(inner),
        other => other,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde::Deserialize;

    #[derive(Debug, Serialize, Deserialize)]
    struct Camera {
        resolution: [u32; 2],
        #[serde(default)]
        joints: Vec<Joint>,
    }

    #[derive(Debug, Serialize, Deserialize)]
    struct Joint {
        range: [f64; 2],
    }

    fn value(toml: &str) -> Value {
        let table: toml::Table = toml::from_str(toml).expect("toml");
        serde_value::to_value(table).expect("value")
    }

    #[test]
    fn an_array_longer_than_its_type_holds_is_refused_naming_its_key() {
        let ok: Camera = typed::<_, serde_value::DeserializerError>(value(
            "resolution = [640, 480]\njoints = [{ range = [0.0, 1.0] }]",
        ))
        .expect("exact lengths");
        assert_eq!(ok.resolution, [640, 480]);
        for (toml, key, given) in [
            ("resolution = [640, 480, 3]", "resolution", 3),
            (
                "resolution = [1, 2]\njoints = [{ range = [0.0, 1.0] }, { range = [0.0, 1.0, 2.0, 3.0] }]",
                "joints[1].range",
                4,
            ),
        ] {
            let (path, e) =
                typed::<Camera, serde_value::DeserializerError>(value(toml)).expect_err(toml);
            assert_eq!(path, key, "{toml}");
            let message = e.to_string().to_lowercase();
            assert!(
                message.contains(&format!("invalid length {given}")),
                "{message}"
            );
        }
        // Shorter is refused by the deserializer itself.
        let (path, _) = typed::<Camera, serde_value::DeserializerError>(value("resolution = [1]"))
            .expect_err("short");
        assert_eq!(path, "resolution");
    }
}
