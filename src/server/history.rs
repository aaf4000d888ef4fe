//! The run history in memory, and how `GET /api/v1/runs` pages through it:
//! filters, newest first, and opaque cursors tied to the data directory.
//!
//! The history keeps its runs in the list's order (a sorted set of
//! `(started_at, id)`), so a page is a walk of the set from the cursor's
//! position: it costs the page, not the history, unless a filter has to
//! count its matches for `total`.

use std::collections::{BTreeSet, HashMap};
use std::path::Path;
use std::time::{Duration, SystemTime};

use super::wire::RunView;
use crate::model::run_state::{RunState, ALL_STATES};

/// Runs per page unless `limit` says otherwise.
pub const DEFAULT_LIMIT: usize = 50;
/// Most runs one page may hold.
pub const MAX_LIMIT: usize = 1000;
/// The file in the data directory that holds its history id: a random
/// value made once, which cursors carry so that a cursor survives a restart
/// of the daemon but is refused by a daemon on another data directory.
pub const HISTORY_ID_FILE: &str = "history-id";
const CURSOR_VERSION: &str = "c1";

/// A run in the history, with what the filters compare precomputed.
#[derive(Debug, Clone)]
struct Entry {
    view: RunView,
    /// `started_at` as a time; None when it does not parse (then no date
    /// filter matches the run).
    started: Option<SystemTime>,
    /// The sample name in lower case, for the case-insensitive search.
    sample_lc: String,
}

impl Entry {
    fn new(view: RunView) -> Entry {
        Entry {
            started: parse_timestamp(&view.started_at),
            sample_lc: view.sample.to_lowercase(),
            view,
        }
    }
}

/// Every run the daemon knows, by id and in the list's order (newest
/// first: `started_at` descending, then id descending).
#[derive(Debug, Default)]
pub struct RunHistory {
    by_id: HashMap<String, Entry>,
    order: BTreeSet<(String, String)>,
}

impl RunHistory {
    /// Adds or replaces the run `view.id`; returns the view it replaced.
    pub fn insert(&mut self, view: RunView) -> Option<RunView> {
        let old = self.by_id.remove(&view.id);
        if let Some(old) = &old {
            self.order
                .remove(&(old.view.started_at.clone(), old.view.id.clone()));
        }
        self.order
            .insert((view.started_at.clone(), view.id.clone()));
        self.by_id.insert(view.id.clone(), Entry::new(view));
        old.map(|e| e.view)
    }

    /// Run `id`'s view.
    pub fn get(&self, id: &str) -> Option<&RunView> {
        self.by_id.get(id).map(|e| &e.view)
    }

    /// Changes run `id`'s view with `f` (keeping the order and the filters'
    /// keys right whatever `f` changes); None when there is no such run.
    pub fn update<R>(&mut self, id: &str, f: impl FnOnce(&mut RunView) -> R) -> Option<R> {
        let mut view = self.by_id.get(id)?.view.clone();
        let r = f(&mut view);
        self.insert(view);
        Some(r)
    }

    /// Whether run `id` is known.
    pub fn contains_key(&self, id: &str) -> bool {
        self.by_id.contains_key(id)
    }

    /// Every run, in no particular order.
    pub fn values(&self) -> impl Iterator<Item = &RunView> {
        self.by_id.values().map(|e| &e.view)
    }

    /// Every run id, in no particular order.
    pub fn keys(&self) -> impl Iterator<Item = &String> {
        self.by_id.keys()
    }

    /// How many runs there are.
    pub fn len(&self) -> usize {
        self.by_id.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.by_id.is_empty()
    }

    /// One page of the runs `q` selects, newest first, after `q.after`.
    pub fn page(&self, q: &HistoryQuery) -> Page {
        let walk: Box<dyn Iterator<Item = &(String, String)>> = match &q.after {
            Some(pos) => Box::new(
                self.order
                    .range::<(String, String), _>(..(pos.started_at.clone(), pos.id.clone()))
                    .rev(),
            ),
            None => Box::new(self.order.iter().rev()),
        };
        let mut runs = Vec::new();
        let mut more = false;
        for (_, id) in walk {
            let Some(e) = self.by_id.get(id) else {
                continue;
            };
            if !q.filter.matches(e) {
                continue;
            }
            if runs.len() == q.limit {
                more = true;
                break;
            }
            runs.push(e.view.clone());
        }
        let total = if q.filter.is_empty() {
            self.by_id.len()
        } else {
            self.by_id.values().filter(|e| q.filter.matches(e)).count()
        };
        let next = match (more, runs.last()) {
            (true, Some(last)) => Some(Position {
                started_at: last.started_at.clone(),
                id: last.id.clone(),
            }),
            _ => None,
        };
        Page { runs, next, total }
    }
}

/// Where a page ends: its last run's sort key.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Position {
    /// The run's `started_at`, as stored.
    pub started_at: String,
    /// The run's id.
    pub id: String,
}

/// One page of the history.
#[derive(Debug)]
pub struct Page {
    /// The page's runs, newest first.
    pub runs: Vec<RunView>,
    /// Where the next page starts; None on the last page.
    pub next: Option<Position>,
    /// How many runs match the filters, on every page.
    pub total: usize,
}

/// What to list: the filters, the page size and where to start.
#[derive(Debug, Clone)]
pub struct HistoryQuery {
    /// Which runs.
    pub filter: RunFilter,
    /// Runs per page, 1..=[`MAX_LIMIT`].
    pub limit: usize,
    /// Start after this run (exclusive); None for the first page.
    pub after: Option<Position>,
}

/// The filters of `GET /api/v1/runs`; each one given must hold.
#[derive(Debug, Clone, Default)]
pub struct RunFilter {
    /// Lower-case text the sample name contains (case-insensitive).
    pub sample: Option<String>,
    /// The run's state.
    pub state: Option<RunState>,
    /// The plan's name, exactly.
    pub plan: Option<String>,
    /// The profile's name, exactly.
    pub profile: Option<String>,
    /// Started at or after this time.
    pub from: Option<SystemTime>,
    /// Started before this time (exclusive).
    pub until: Option<SystemTime>,
}

impl RunFilter {
    fn is_empty(&self) -> bool {
        self.sample.is_none()
            && self.state.is_none()
            && self.plan.is_none()
            && self.profile.is_none()
            && self.from.is_none()
            && self.until.is_none()
    }

    fn matches(&self, e: &Entry) -> bool {
        let v = &e.view;
        if self.state.is_some_and(|s| s != v.state)
            || self.plan.as_ref().is_some_and(|p| *p != v.plan)
            || self.profile.as_ref().is_some_and(|p| *p != v.profile)
            || self
                .sample
                .as_ref()
                .is_some_and(|s| !e.sample_lc.contains(s.as_str()))
        {
            return false;
        }
        if self.from.is_some() || self.until.is_some() {
            let Some(t) = e.started else {
                return false;
            };
            if self.from.is_some_and(|f| t < f) || self.until.is_some_and(|u| t >= u) {
                return false;
            }
        }
        true
    }
}

/// A query parameter that cannot be used; its message names the parameter
/// and says what it takes.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct QueryError(pub String);

/// Reads `limit`: [`DEFAULT_LIMIT`] when absent.
pub fn parse_limit(limit: Option<u64>) -> Result<usize, QueryError> {
    match limit {
        None => Ok(DEFAULT_LIMIT),
        Some(n) if (1..=MAX_LIMIT as u64).contains(&n) => Ok(n as usize),
        Some(n) => Err(QueryError(format!(
            "`limit` must be 1 to {MAX_LIMIT}, not {n}"
        ))),
    }
}

/// Reads `state`: a run state's name.
pub fn parse_state(s: &str) -> Result<RunState, QueryError> {
    ALL_STATES
        .iter()
        .copied()
        .find(|st| st.as_str() == s)
        .ok_or_else(|| {
            let names: Vec<&str> = ALL_STATES.iter().map(|s| s.as_str()).collect();
            QueryError(format!(
                "`state` {:?} is not a run state; one of: {}",
                short(s),
                names.join(", ")
            ))
        })
}

/// Which end of a period a date bound is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Bound {
    /// `from`: the period starts at the date's midnight (UTC), or at the
    /// date-time.
    From,
    /// `to`: the period ends with the date's last second (UTC), or at the
    /// date-time, inclusive.
    To,
}

/// Reads a `from`/`to` bound: an RFC 3339 date (`2026-12-01`, UTC) or
/// date-time (`2026-12-01T08:00:00Z`, `…+02:00`). Returns the time the
/// period starts at (`From`, inclusive) or ends before (`To`, exclusive).
pub fn parse_bound(name: &str, s: &str, bound: Bound) -> Result<SystemTime, QueryError> {
    let bad = || {
        QueryError(format!(
            "`{name}` {:?} is not an RFC 3339 date (2026-12-01) or date-time (2026-12-01T08:00:00Z)",
            short(s)
        ))
    };
    if s.len() == 10 {
        let midnight = parse_timestamp(&format!("{s}T00:00:00Z")).ok_or_else(bad)?;
        return Ok(match bound {
            Bound::From => midnight,
            Bound::To => midnight + Duration::from_secs(86_400),
        });
    }
    let t = parse_timestamp(s).ok_or_else(bad)?;
    Ok(match bound {
        Bound::From => t,
        // Inclusive of the instant itself, to the nanosecond.
        Bound::To => t + Duration::from_nanos(1),
    })
}

/// An RFC 3339 date-time in UTC (`Z`) or with a numeric offset.
fn parse_timestamp(s: &str) -> Option<SystemTime> {
    let s = s.trim();
    if !s.is_ascii() || s.len() < 20 {
        return None;
    }
    if s.ends_with(['Z', 'z']) {
        return humantime::parse_rfc3339_weak(&s[..s.len() - 1]).ok();
    }
    // `±hh:mm` at the end.
    let (base, offset) = s.split_at(s.len() - 6);
    let sign = match offset.as_bytes()[0] {
        b'+' => 1i64,
        b'-' => -1i64,
        _ => return None,
    };
    let (hh, mm) = offset[1..].split_once(':')?;
    if hh.len() != 2 || mm.len() != 2 {
        return None;
    }
    let hh: u64 = hh.parse().ok()?;
    let mm: u64 = mm.parse().ok()?;
    if hh > 23 || mm > 59 {
        return None;
    }
    let local = humantime::parse_rfc3339_weak(base).ok()?;
    let shift = Duration::from_secs(hh * 3600 + mm * 60);
    // Local time minus its offset is UTC.
    if sign > 0 {
        local.checked_sub(shift)
    } else {
        local.checked_add(shift)
    }
}

/// A cursor for `pos` in the history of the data directory with history
/// id `history_id`: base64url of a small versioned text and its check
/// (the start of its SHA-256), so that a cursor cut short or edited is
/// refused rather than read as another position.
pub fn encode_cursor(history_id: &str, pos: &Position) -> String {
    let body = format!(
        "{CURSOR_VERSION}\n{history_id}\n{}\n{}",
        pos.id, pos.started_at
    );
    base64url_encode(format!("{}\n{body}", check_of(&body)).as_bytes())
}

fn check_of(body: &str) -> String {
    use sha2::Digest;
    hex::encode(&sha2::Sha256::digest(body.as_bytes())[..8])
}

/// Reads a cursor made by [`encode_cursor`] for this history id.
pub fn decode_cursor(history_id: &str, cursor: &str) -> Result<Position, QueryError> {
    let malformed = |why: &str| {
        QueryError(format!(
            "`cursor` is malformed ({why}): pass the `next` of the previous page as it is"
        ))
    };
    let bytes = base64url_decode(cursor).ok_or_else(|| malformed("not base64url"))?;
    let text = String::from_utf8(bytes).map_err(|_| malformed("not text"))?;
    let (check, body) = text
        .split_once('\n')
        .ok_or_else(|| malformed("too few parts"))?;
    if check != check_of(body) {
        return Err(malformed("cut short or changed"));
    }
    let mut parts = body.splitn(4, '\n');
    let (Some(version), Some(owner), Some(id), Some(started_at)) =
        (parts.next(), parts.next(), parts.next(), parts.next())
    else {
        return Err(malformed("too few parts"));
    };
    if version != CURSOR_VERSION {
        return Err(malformed("unknown version"));
    }
    if owner != history_id {
        return Err(QueryError(
            "`cursor` comes from another daemon's data directory: start again from the first page"
                .into(),
        ));
    }
    if !super::data_dir::is_valid_id(id) {
        return Err(malformed("no run id"));
    }
    Ok(Position {
        started_at: started_at.to_string(),
        id: id.to_string(),
    })
}

/// The data directory's history id ([`HISTORY_ID_FILE`]), made and stored
/// on first use; a file that does not hold one is replaced (its old cursors
/// then stop working, which is all it is for).
pub fn history_id(data_dir: &Path) -> Result<String, std::io::Error> {
    let path = data_dir.join(HISTORY_ID_FILE);
    match rigd_core::read::read_text(&path, 1024) {
        Ok(s) if is_history_id(s.trim()) => return Ok(s.trim().to_string()),
        Ok(_) => tracing::warn!("{} holds no history id: making a new one", path.display()),
        Err(e) if e.io_kind() == Some(std::io::ErrorKind::NotFound) => {}
        Err(e) => tracing::warn!("{e}; making a new history id"),
    }
    let id = hex::encode(random_bytes());
    rigd_core::atomic::write(&path, format!("{id}\n").as_bytes())?;
    Ok(id)
}

fn is_history_id(s: &str) -> bool {
    s.len() == 32 && s.bytes().all(|b| b.is_ascii_hexdigit())
}

/// 16 random bytes from the operating system; should it have none to
/// give, a hash of the time and the process, which still tells data
/// directories apart in practice.
fn random_bytes() -> [u8; 16] {
    let mut out = [0u8; 16];
    if getrandom::fill(&mut out).is_err() {
        use sha2::Digest;
        let seed = format!("{:?} {}", SystemTime::now(), std::process::id());
        out.copy_from_slice(&sha2::Sha256::digest(seed.as_bytes())[..16]);
    }
    out
}

fn short(s: &str) -> String {
    s.chars().take(64).collect()
}

/// Base64url without padding (RFC 4648 §5).
fn base64url_encode(bytes: &[u8]) -> String {
    use base64::Engine;
    base64::engine::general_purpose::URL_SAFE_NO_PAD.encode(bytes)
}

/// Reads base64url, with or without padding; None for anything else or
/// anything longer than a cursor can be.
fn base64url_decode(s: &str) -> Option<Vec<u8>> {
    use base64::Engine;
    let s = s.trim_end_matches('=');
    if s.len() > 4096 {
        return None;
    }
    base64::engine::general_purpose::URL_SAFE_NO_PAD
        .decode(s)
        .ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base64url_round_trips_and_refuses_other_text() {
        for len in 0..40 {
            let bytes: Vec<u8> = (0..len).map(|i| (i * 37 + 11) as u8).collect();
            let s = base64url_encode(&bytes);
            assert!(!s.contains(['+', '/', '=']), "{s}");
            assert_eq!(base64url_decode(&s), Some(bytes));
        }
        assert_eq!(base64url_encode(b"foobar"), "Zm9vYmFy");
        assert_eq!(base64url_encode(b"fo"), "Zm8");
        assert_eq!(base64url_decode("Zm8="), Some(b"fo".to_vec()));
        for bad in ["a", "ab!c", "Zm9v YmFy", "Zm+v"] {
            assert_eq!(base64url_decode(bad), None, "{bad}");
        }
    }

    #[test]
    fn cursors_round_trip_and_name_their_data_directory() {
        let pos = Position {
            started_at: "2026-12-01T08:00:00Z".into(),
            id: "20261201T080000Z-felt-h1".into(),
        };
        let c = encode_cursor("00112233445566778899aabbccddeeff", &pos);
        assert_eq!(
            decode_cursor("00112233445566778899aabbccddeeff", &c),
            Ok(pos)
        );
        let other = decode_cursor("ffeeddccbbaa99887766554433221100", &c);
        assert!(other.is_err_and(|e| e.0.contains("another daemon")));
        let body = "c1\nx\n../x\nt";
        let traversal = base64url_encode(format!("{}\n{body}", check_of(body)).as_bytes());
        for bad in ["", "!!", "Zm9vYmFy", &traversal, &c[..c.len() - 3], &c[3..]] {
            assert!(decode_cursor("x", bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn dates_and_date_times_bound_periods() {
        let day = parse_bound("from", "2026-12-01", Bound::From).expect("date");
        let end = parse_bound("to", "2026-12-01", Bound::To).expect("date");
        assert_eq!(
            end.duration_since(day).ok(),
            Some(Duration::from_secs(86_400))
        );
        let utc = parse_bound("from", "2026-12-01T08:00:00Z", Bound::From).expect("utc");
        let off = parse_bound("from", "2026-12-01T10:00:00+02:00", Bound::From).expect("offset");
        assert_eq!(utc, off);
        assert_eq!(
            utc.duration_since(day).ok(),
            Some(Duration::from_secs(8 * 3600))
        );
        for bad in [
            "yesterday",
            "2026-13-01",
            "2026-02-30",
            "2026-12-01T25:00:00Z",
            "2026-12-01T08:00:00",
            "20261201",
            "2026-12-01T08:00:00+2:00",
        ] {
            assert!(parse_bound("from", bad, Bound::From).is_err(), "{bad}");
        }
    }

    fn view(id: &str, sample: &str, started_at: &str) -> RunView {
        let meta_free = serde_json::json!({
            "id": id, "sample": sample, "plan": "h1", "profile": "bonn", "operator": null,
            "notes": null, "state": "completed", "reason": null, "last_error": null,
            "active": false, "resumable": false, "steps_done": 0, "steps_total": 0,
            "physical_s": 0.0, "eta_physical_s": null, "eta_wall_s": null, "exposure_s": null,
            "frame_size": null, "started_at": started_at, "updated_at": null, "finished_at": null,
        });
        serde_json::from_value(meta_free).unwrap_or_else(|e| panic!("{e}"))
    }

    #[test]
    fn pages_cover_every_match_once_in_order() {
        let mut h = RunHistory::default();
        for i in 0..25 {
            let t = format!("2026-12-{:02}T00:00:00Z", 1 + i % 10);
            let sample = if i % 3 == 0 { "Felt" } else { "wool" };
            h.insert(view(&format!("r{i:02}"), sample, &t));
        }
        // Replacing keeps one entry per run.
        h.insert(view("r00", "Felt", "2026-12-01T00:00:00Z"));
        assert_eq!(h.len(), 25);
        for filter in [
            RunFilter::default(),
            RunFilter {
                sample: Some("fel".into()),
                ..Default::default()
            },
        ] {
            let mut seen = Vec::new();
            let mut after = None;
            loop {
                let p = h.page(&HistoryQuery {
                    filter: filter.clone(),
                    limit: 4,
                    after: after.take(),
                });
                seen.extend(p.runs.iter().map(|r| (r.started_at.clone(), r.id.clone())));
                match p.next {
                    Some(n) => after = Some(n),
                    None => break,
                }
            }
            let mut want: Vec<(String, String)> = h
                .by_id
                .values()
                .filter(|e| filter.matches(e))
                .map(|e| (e.view.started_at.clone(), e.view.id.clone()))
                .collect();
            want.sort();
            want.reverse();
            assert_eq!(seen, want);
        }
    }
}
