//! The peers file of `rigd serve --peers FILE`: the other rigs' daemons and
//! their tokens, read and checked before the daemon starts.
//!
//! ```toml
//! [[peer]]
//! name = "msra"                       # shown in the dashboard: unique, a-z 0-9 -
//! url = "http://192.168.1.21:8080"    # that rig's `rigd serve --listen` address
//! token_file = "msra.token"           # or token = "…"; relative to this file
//! ```

use std::path::{Path, PathBuf};
use std::sync::Arc;

use serde::Deserialize;

/// Longest peer name.
pub const MAX_NAME: usize = 32;

/// Another rig's daemon, as the peers file names it.
#[derive(Clone)]
pub struct Peer {
    /// Its name in the dashboard and in `/api/v1/peers/{name}/…`: 1 to 32
    /// characters of `a-z`, `0-9` and `-`.
    pub name: String,
    /// The base URL of its `rigd serve`, `http://HOST:PORT` (with a path
    /// prefix if a proxy puts it under one), without a trailing `/`.
    pub url: String,
    token: Arc<str>,
}

impl std::fmt::Debug for Peer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Peer")
            .field("name", &self.name)
            .field("url", &self.url)
            .field("token", &"…")
            .finish()
    }
}

/// What is wrong with one peer.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PeerError {
    /// The name is empty, too long or has other characters than `a-z`,
    /// `0-9` and `-` (or starts with `-`).
    #[error("name `{0}`: expected 1 to 32 characters of a-z, 0-9 and `-`, not starting with `-`")]
    Name(String),
    /// The URL is not the `http://HOST:PORT` address of a daemon.
    #[error("url `{url}`: {why}")]
    Url {
        /// The URL as given.
        url: String,
        /// What is wrong with it.
        why: String,
    },
    /// Neither or both of `token` and `token_file` are given.
    #[error("give exactly one of `token` and `token_file`")]
    TokenChoice,
    /// The token file cannot be read, or holds no usable token.
    #[error("token file {}: {why}", path.display())]
    TokenFile {
        /// The token file, resolved against the peers file's directory.
        path: PathBuf,
        /// What is wrong with it.
        why: String,
    },
    /// The inline `token` is no usable token.
    #[error("token: {0}")]
    Token(&'static str),
}

/// Why a peers file is refused. Every variant names the file; a peer's
/// fault also names the peer and its entry (1 is the first `[[peer]]`).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PeersError {
    /// The file cannot be read: missing, not a regular file, too large.
    #[error("peers file {}: {why}", file.display())]
    Read {
        /// The peers file.
        file: PathBuf,
        /// Why: `cannot read:` and the operating system's error, or what
        /// is wrong with the file.
        why: String,
    },
    /// The file is not TOML of the expected shape (an unknown or missing
    /// key, a wrong type).
    #[error("peers file {}: {why}", file.display())]
    Syntax {
        /// The peers file.
        file: PathBuf,
        /// The key, what is wrong and the line.
        why: String,
    },
    /// The file lists no `[[peer]]`.
    #[error("peers file {}: no [[peer]] entries", file.display())]
    Empty {
        /// The peers file.
        file: PathBuf,
    },
    /// One entry is unusable.
    #[error("peers file {}: peer `{name}` (entry {entry}): {error}", file.display())]
    Peer {
        /// The peers file.
        file: PathBuf,
        /// The entry, counted from 1.
        entry: usize,
        /// The peer's name, as given.
        name: String,
        /// What is wrong with it.
        error: PeerError,
    },
    /// Two entries have the same name.
    #[error("peers file {}: peer `{name}` (entries {first} and {second}): the name is used twice", file.display())]
    Duplicate {
        /// The peers file.
        file: PathBuf,
        /// The name used twice.
        name: String,
        /// The first entry with it, counted from 1.
        first: usize,
        /// The second.
        second: usize,
    },
}

impl Peer {
    /// A peer from its name, URL and token, each checked: the name as
    /// [`Peer::name`] says, an `http://` URL with a host and port and no
    /// query, a token of one line of at least 16 visible characters.
    pub fn new(name: &str, url: &str, token: &str) -> Result<Peer, PeerError> {
        check_name(name)?;
        let url = base_url(url)?;
        let token = crate::server::auth::usable_secret(token).map_err(PeerError::Token)?;
        Ok(Peer {
            name: name.to_string(),
            url,
            token: token.into(),
        })
    }

    /// The peer's API token, sent as `Authorization: Bearer <token>` on
    /// every request to it.
    pub fn token(&self) -> &str {
        &self.token
    }
}

fn check_name(name: &str) -> Result<(), PeerError> {
    let ok = !name.is_empty()
        && name.len() <= MAX_NAME
        && !name.starts_with('-')
        && name
            .chars()
            .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '-');
    if ok {
        Ok(())
    } else {
        Err(PeerError::Name(name.chars().take(64).collect()))
    }
}

/// `http://HOST:PORT[/prefix]` without a trailing `/`, or why not.
fn base_url(url: &str) -> Result<String, PeerError> {
    let bad = |why: &str| PeerError::Url {
        url: url.chars().take(200).collect(),
        why: why.to_string(),
    };
    let uri: axum::http::Uri = url
        .trim()
        .parse()
        .map_err(|e: axum::http::uri::InvalidUri| bad(&format!("not a URL ({e})")))?;
    match uri.scheme_str() {
        Some("http") => {}
        Some("https") => {
            return Err(bad(
                "https is not supported: `rigd serve` speaks plain HTTP; give its http:// address",
            ))
        }
        _ => {
            return Err(bad(
                "expected http://HOST:PORT, the peer's `rigd serve` address",
            ))
        }
    }
    let authority = uri
        .authority()
        .filter(|a| !a.host().is_empty())
        .ok_or_else(|| bad("no host"))?;
    if authority.as_str().contains('@') {
        return Err(bad(
            "no user or password in the URL: the token goes in `token` or `token_file`",
        ));
    }
    if uri.query().is_some() {
        return Err(bad("no query: just the daemon's address"));
    }
    let path = uri.path().trim_end_matches('/');
    Ok(format!("http://{authority}{path}"))
}

/// One `[[peer]]` as written.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Entry {
    name: String,
    url: String,
    #[serde(default)]
    token: Option<String>,
    #[serde(default)]
    token_file: Option<PathBuf>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct PeersFile {
    #[serde(default)]
    peer: Vec<Entry>,
}

/// Reads and checks a peers file: TOML with one `[[peer]]` table per
/// peer (`name`, `url`, and `token` or `token_file`; a relative
/// `token_file` is relative to the peers file). Errors name the file, and
/// the peer where one is at fault.
pub fn load(file: &Path) -> Result<Vec<Peer>, PeersError> {
    let text = rigd_core::read::read_text(file, rigd_core::read::TEXT_LIMIT).map_err(|e| {
        PeersError::Read {
            file: file.to_path_buf(),
            why: e.reason.to_string(),
        }
    })?;
    parse(&text, file)
}

/// [`load`] on text already read; `file` names it in errors and anchors
/// relative token files.
pub fn parse(text: &str, file: &Path) -> Result<Vec<Peer>, PeersError> {
    let parsed: PeersFile = rigd_core::config::parse(
        text,
        &file.display().to_string(),
        rigd_core::config::Format::Toml,
    )
    .map_err(|e| {
        let at = key_name(&e.key, &e.message);
        PeersError::Syntax {
            file: file.to_path_buf(),
            why: if at.is_empty() {
                e.message
            } else {
                format!("{at}: {}", e.message)
            },
        }
    })?;
    if parsed.peer.is_empty() {
        return Err(PeersError::Empty {
            file: file.to_path_buf(),
        });
    }
    let dir = file.parent().unwrap_or(Path::new("."));
    let mut peers: Vec<Peer> = Vec::with_capacity(parsed.peer.len());
    for (i, entry) in parsed.peer.into_iter().enumerate() {
        let at_fault = |error: PeerError| PeersError::Peer {
            file: file.to_path_buf(),
            entry: i + 1,
            name: entry.name.chars().take(64).collect(),
            error,
        };
        let token = match (&entry.token, &entry.token_file) {
            (Some(t), None) => t.clone(),
            (None, Some(f)) => {
                let path = dir.join(f);
                let text = rigd_core::read::read_text(&path, rigd_core::read::TEXT_LIMIT).map_err(
                    |e| {
                        at_fault(PeerError::TokenFile {
                            path: path.clone(),
                            why: e.reason.to_string(),
                        })
                    },
                )?;
                crate::server::auth::usable_secret(&text)
                    .map_err(|why| {
                        at_fault(PeerError::TokenFile {
                            path: path.clone(),
                            why: why.to_string(),
                        })
                    })?
                    .to_string()
            }
            _ => return Err(at_fault(PeerError::TokenChoice)),
        };
        let peer = Peer::new(&entry.name, &entry.url, &token).map_err(at_fault)?;
        if let Some(first) = peers.iter().position(|p| p.name == peer.name) {
            return Err(PeersError::Duplicate {
                file: file.to_path_buf(),
                name: peer.name,
                first: first + 1,
                second: i + 1,
            });
        }
        peers.push(peer);
    }
    Ok(peers)
}

/// Where a syntax error is, for a person: `peer[0].tokn` is "[[peer]]
/// entry 1, `tokn`" (the key left out when the message names it).
fn key_name(key: &str, message: &str) -> String {
    if key == "." || key.is_empty() {
        return String::new();
    }
    let Some((index, tail)) = key
        .strip_prefix("peer[")
        .and_then(|rest| rest.split_once(']'))
        .and_then(|(n, tail)| Some((n.parse::<usize>().ok()?, tail.trim_start_matches('.'))))
    else {
        return key.to_string();
    };
    if tail.is_empty() || message.contains(&format!("`{tail}`")) {
        format!("[[peer]] entry {}", index + 1)
    } else {
        format!("[[peer]] entry {}, `{tail}`", index + 1)
    }
}

/// The first name two peers share, if any.
pub fn duplicate_name(peers: &[Peer]) -> Option<&str> {
    peers.iter().enumerate().find_map(|(i, p)| {
        peers[..i]
            .iter()
            .any(|q| q.name == p.name)
            .then_some(p.name.as_str())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const TOKEN: &str = "0123456789abcdef0123";

    fn parse_in(dir: &Path, text: &str) -> Result<Vec<Peer>, PeersError> {
        parse(text, &dir.join("peers.toml"))
    }

    #[test]
    fn a_good_file_with_inline_and_relative_token_files() {
        let dir = tempfile::tempdir().expect("tempdir");
        std::fs::write(dir.path().join("b.token"), format!("{TOKEN}b\n")).expect("write");
        let peers = parse_in(
            dir.path(),
            &format!(
                "[[peer]]\nname = \"msra\"\nurl = \"http://127.0.0.1:8081/\"\ntoken = \"{TOKEN}\"\n\n\
                 [[peer]]\nname = \"bonn-2\"\nurl = \"http://rig-b.lab:8080/rigd\"\ntoken_file = \"b.token\"\n"
            ),
        )
        .expect("valid");
        assert_eq!(peers.len(), 2);
        assert_eq!(peers[0].name, "msra");
        assert_eq!(peers[0].url, "http://127.0.0.1:8081");
        assert_eq!(peers[0].token(), TOKEN);
        assert_eq!(peers[1].url, "http://rig-b.lab:8080/rigd");
        assert_eq!(peers[1].token(), format!("{TOKEN}b"));
        assert!(
            !format!("{:?}", peers[0]).contains(TOKEN),
            "tokens stay out of logs"
        );
        assert_eq!(duplicate_name(&peers), None);
    }

    #[test]
    fn bad_files_name_the_file_the_peer_and_the_fault() {
        let dir = tempfile::tempdir().expect("tempdir");
        let one = |name: &str, url: &str, token: &str| {
            format!("[[peer]]\nname = \"{name}\"\nurl = \"{url}\"\n{token}\n")
        };
        let tok = format!("token = \"{TOKEN}\"");
        let cases: Vec<(String, &str)> = vec![
            (
                format!(
                    "{}{}",
                    one("a", "http://h:1", &tok),
                    one("a", "http://h:2", &tok)
                ),
                "peer `a` (entries 1 and 2): the name is used twice",
            ),
            (
                one("a", "http://h:1", ""),
                "peer `a` (entry 1): give exactly one of `token` and `token_file`",
            ),
            (
                one("a", "http://h:1", &format!("{tok}\ntoken_file = \"x\"")),
                "give exactly one of `token` and `token_file`",
            ),
            (
                one("a", "http://h:1", &format!("{tok}\ntokn = 1")),
                "[[peer]] entry 1: unknown field `tokn`",
            ),
            (
                one("A b", "http://h:1", &tok),
                "peer `A b` (entry 1): name `A b`: expected 1 to 32 characters",
            ),
            (one("a", "https://h:1", &tok), "https is not supported"),
            (one("a", "ftp://h:1", &tok), "expected http://HOST:PORT"),
            (one("a", "http://h:1/?x=1", &tok), "no query"),
            (one("a", "http://u:p@h:1", &tok), "no user or password"),
            (
                one("a", "http://h:1", "token = \"short\""),
                "token: expected one line",
            ),
            (
                one("a", "http://h:1", "token_file = \"missing.token\""),
                "missing.token",
            ),
            ("".to_string(), "no [[peer]] entries"),
            (
                "[[peers]]\nname = \"a\"\n".to_string(),
                "unknown field `peers`",
            ),
            (
                "[[peer]]\nname = \"a\"\n".to_string(),
                "[[peer]] entry 1: missing field `url`",
            ),
            (
                "[[peer]]\nname = 3\n".to_string(),
                "[[peer]] entry 1, `name`: invalid type",
            ),
        ];
        for (text, want) in cases {
            let err = parse_in(dir.path(), &text).expect_err(&text).to_string();
            assert!(err.starts_with("peers file "), "{err}");
            assert!(err.contains("peers.toml"), "{err}");
            assert!(err.contains(want), "{text}\n→ {err}\nwanted {want}");
            assert!(!err.contains('\n'), "one line: {err}");
        }
        let err = load(&dir.path().join("nope.toml")).expect_err("missing");
        assert!(err.to_string().contains("nope.toml: cannot read"), "{err}");
    }
}
