//! `GET /api/v1/runs` over a history of many runs: pages and cursors, every
//! filter, the refusals of bad queries, and the run index
//! (`DATA/runs-index.json`) as a cache that never outweighs the run
//! directories.

use crate::common;

use std::path::Path;

use common::history::{clone_runs, newest_first, Cloned};
use common::http::{run_body, small_plan, start_in, Srv};
use serde_json::{json, Value};

const FAST: f64 = 20_000.0;

/// Which copies a query must list.
type Keep = Box<dyn Fn(&Cloned) -> bool>;

/// One real run in `data`, then `n` copies of its record; returns them.
async fn history(data: &Path, n: usize) -> Vec<Cloned> {
    let mut s = start_in(data, FAST).await;
    let (status, v) = s
        .post("/api/v1/runs", Some(run_body("seed", small_plan(1))))
        .await;
    assert_eq!(status, 201, "{v}");
    let id = v["id"].as_str().expect("id").to_string();
    s.wait_ended(&id, "completed").await;
    s.shutdown().await;
    let runs = data.join("runs");
    let copies = clone_runs(&runs.join(&id), &runs, n);
    // Only the copies: their fields are known.
    std::fs::remove_dir_all(runs.join(&id)).expect("remove the seed run");
    copies
}

/// Every page of `query` (which must not hold `limit` or `cursor`) at
/// `limit` runs a page; checks `total` on each page.
async fn all_pages(s: &Srv, query: &str, limit: usize) -> Vec<Value> {
    let mut out = Vec::new();
    let mut cursor: Option<String> = None;
    let mut total = None;
    for _ in 0..10_000 {
        let mut url = format!("/api/v1/runs?limit={limit}{query}");
        if let Some(c) = &cursor {
            url.push_str(&format!("&cursor={c}"));
        }
        let (status, page) = s.get(&url).await;
        assert_eq!(status, 200, "{url}: {page}");
        let runs = page["runs"].as_array().expect("runs");
        assert!(runs.len() <= limit, "{url}: {} runs", runs.len());
        let t = page["total"].as_u64().expect("total");
        assert_eq!(*total.get_or_insert(t), t, "total changed between pages");
        out.extend(runs.iter().cloned());
        match page["next"].as_str() {
            Some(c) => {
                assert!(!runs.is_empty(), "a next page after an empty one");
                cursor = Some(c.to_string());
            }
            None => {
                assert_eq!(out.len() as u64, t, "{query}: pages hold `total` runs");
                return out;
            }
        }
    }
    panic!("{query}: no last page");
}

fn ids(runs: &[Value]) -> Vec<String> {
    runs.iter()
        .map(|r| r["id"].as_str().expect("id").to_string())
        .collect()
}

fn want_ids(runs: &[Cloned], keep: impl Fn(&Cloned) -> bool) -> Vec<String> {
    newest_first(runs)
        .into_iter()
        .filter(|r| keep(r))
        .map(|r| r.id)
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn runs_page_pages_and_filters() {
    let dir = tempfile::tempdir().expect("tempdir");
    let runs = history(dir.path(), 123).await;
    let mut s = start_in(dir.path(), FAST).await;

    // The first page: 50 by default, the newest first.
    let (status, first) = s.get("/api/v1/runs").await;
    assert_eq!(status, 200, "{first}");
    assert_eq!(first["runs"].as_array().map(Vec::len), Some(50));
    assert_eq!(first["total"], 123);
    assert_eq!(first["active"], Value::Null);
    assert!(first["next"].is_string(), "{}", first["next"]);
    let all = want_ids(&runs, |_| true);
    assert_eq!(ids(first["runs"].as_array().expect("runs")), all[..50]);
    let (_, five) = s.get("/api/v1/runs?limit=5").await;
    assert_eq!(ids(five["runs"].as_array().expect("runs")), all[..5]);
    let (_, every) = s.get("/api/v1/runs?limit=1000").await;
    assert_eq!(ids(every["runs"].as_array().expect("runs")), all);
    assert_eq!(every["next"], Value::Null);

    // Paging over everything: each run once, in order, whatever the size
    // (7 does not divide 123; runs share start seconds across pages).
    for limit in [1, 7, 50, 123, 200] {
        assert_eq!(ids(&all_pages(&s, "", limit).await), all, "limit {limit}");
    }

    // Every filter, alone and together, paged.
    let profile = first["runs"][0]["profile"]
        .as_str()
        .expect("profile")
        .to_string();
    let cases: Vec<(String, Keep)> = vec![
        (
            "&sample=FELT".into(),
            Box::new(|r| r.sample.to_lowercase().contains("felt")),
        ),
        (
            "&sample=eat".into(),
            Box::new(|r| r.sample.to_lowercase().contains("eat")),
        ),
        ("&state=aborted".into(), Box::new(|r| r.state == "aborted")),
        ("&plan=dome".into(), Box::new(|r| r.plan == "dome")),
        ("&plan=Dome".into(), Box::new(|_| false)),
        (format!("&profile={profile}"), Box::new(|_| true)),
        ("&profile=nope".into(), Box::new(|_| false)),
        // Dates: from a day's midnight, to a day's end.
        (
            "&from=2026-01-02".into(),
            Box::new(|r| r.started_at.as_str() >= "2026-01-02"),
        ),
        (
            "&to=2026-01-02".into(),
            Box::new(|r| r.started_at.as_str() < "2026-01-03"),
        ),
        // Date-times, inclusive at both ends, with an offset.
        (
            "&from=2026-01-01T05:00:00Z&to=2026-01-01T10:00:00%2B01:00".into(),
            Box::new(|r| {
                ("2026-01-01T05:00:00Z"..="2026-01-01T09:00:00Z").contains(&r.started_at.as_str())
            }),
        ),
        (
            "&sample=felt&state=failed&plan=grid&from=2026-01-01&to=2026-01-03".into(),
            Box::new(|r| {
                r.sample.to_lowercase().contains("felt")
                    && r.state == "failed"
                    && r.plan == "grid"
                    && r.started_at.as_str() < "2026-01-04"
            }),
        ),
        // An empty filter is no filter.
        ("&sample=&state=&plan=".into(), Box::new(|_| true)),
    ];
    for (query, keep) in &cases {
        let want = want_ids(&runs, keep);
        let got = ids(&all_pages(&s, query, 4).await);
        assert_eq!(got, want, "{query}");
        let (_, page) = s.get(&format!("/api/v1/runs?limit=3{query}")).await;
        assert_eq!(page["total"], want.len(), "{query}");
    }
    // The filtered runs are the runs as listed, fields and all.
    let (_, one) = s.get("/api/v1/runs?limit=1&state=failed").await;
    let r = &one["runs"][0];
    let id = r["id"].as_str().expect("id");
    let (_, direct) = s.get(&format!("/api/v1/runs/{id}")).await;
    assert_eq!(r, &direct);
    assert_eq!(r["state"], "failed");

    // A cursor outlives the daemon: a restart on the same data directory
    // takes it.
    let cursor = first["next"].as_str().expect("next").to_string();
    let (_, before) = s.get(&format!("/api/v1/runs?cursor={cursor}")).await;
    s.shutdown().await;
    let mut s = start_in(dir.path(), FAST).await;
    let (status, after) = s.get(&format!("/api/v1/runs?cursor={cursor}")).await;
    assert_eq!(status, 200, "{after}");
    assert_eq!(ids(after["runs"].as_array().expect("runs")), all[50..100]);
    assert_eq!(before["runs"], after["runs"]);
    s.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn runs_page_refuses_bad_queries() {
    let dir = tempfile::tempdir().expect("tempdir");
    history(dir.path(), 3).await;
    let mut s = start_in(dir.path(), FAST).await;
    // A cursor of another data directory (the same runs, copied).
    let other_dir = tempfile::tempdir().expect("tempdir");
    crate::common::copy_dir(&dir.path().join("runs"), &other_dir.path().join("runs"));
    let mut other = start_in(other_dir.path(), FAST).await;
    let (_, page) = other.get("/api/v1/runs?limit=1").await;
    let foreign = page["next"].as_str().expect("next").to_string();
    other.shutdown().await;
    let (_, page) = s.get("/api/v1/runs?limit=1").await;
    let own = page["next"].as_str().expect("next").to_string();
    let (status, _) = s.get(&format!("/api/v1/runs?limit=1&cursor={own}")).await;
    assert_eq!(status, 200);

    let cases = [
        ("limit=0", "limit"),
        ("limit=1001", "limit"),
        ("limit=1000000000", "limit"),
        ("limit=-1", "limit"),
        ("limit=abc", "limit"),
        ("limit=99999999999999999999999", "limit"),
        ("cursor=%21%21not-base64", "cursor"),
        ("cursor=Zm9vYmFy", "cursor"),
        (&format!("cursor={}", &own[..own.len() - 3]), "cursor"),
        (&format!("cursor={foreign}"), "another daemon"),
        ("state=done", "state"),
        ("state=Completed", "state"),
        ("from=yesterday", "from"),
        ("from=2026-02-30", "from"),
        ("to=2026-12-01T25:00:00Z", "to"),
        ("to=2026-12-01T08:00:00", "to"),
        ("from=%FF%FE", ""),
    ];
    for (query, names) in cases {
        let url = format!("/api/v1/runs?{query}");
        let (status, ct, bytes) = s.get_bytes(&url).await;
        let body: Value = serde_json::from_slice(&bytes).unwrap_or(Value::Null);
        assert_eq!(status, 400, "{url}: {body}");
        assert!(ct.starts_with("application/json"), "{url}: {ct}");
        assert_eq!(body["error"], "bad_request", "{url}: {body}");
        let detail = body["detail"].as_str().unwrap_or("");
        assert!(
            !detail.is_empty() && detail.contains(names),
            "{url}: {detail}"
        );
    }
    s.shutdown().await;
}

/// The run's view after a fresh start with no index at all: what its
/// directory says.
async fn truth(data: &Path, id: &str) -> Value {
    let _ = std::fs::remove_file(data.join("runs-index.json"));
    let mut s = start_in(data, FAST).await;
    let (status, v) = s.get(&format!("/api/v1/runs/{id}")).await;
    assert_eq!(status, 200, "{v}");
    s.shutdown().await;
    v
}

fn read_index(data: &Path) -> Value {
    let bytes = std::fs::read(data.join("runs-index.json")).expect("runs-index.json");
    serde_json::from_slice(&bytes).expect("the index parses")
}

fn write_index(data: &Path, index: &Value) {
    std::fs::write(
        data.join("runs-index.json"),
        serde_json::to_vec(index).expect("json"),
    )
    .expect("write the index");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn run_index_is_a_cache_the_run_directories_outweigh() {
    let dir = tempfile::tempdir().expect("tempdir");
    let data = dir.path();
    let runs = history(data, 12).await;
    let newest = newest_first(&runs);
    let (a, b, c) = (&newest[0].id, &newest[1].id, &newest[2].id);

    // The index is written at start-up and lists every run as its
    // directory does.
    let mut s = start_in(data, FAST).await;
    let (_, listed) = s.get("/api/v1/runs?limit=1000").await;
    s.shutdown().await;
    let index = read_index(data);
    assert_eq!(index["runs"].as_object().map(|o| o.len()), Some(12));
    let mut s = start_in(data, FAST).await;
    let (_, again) = s.get("/api/v1/runs?limit=1000").await;
    s.shutdown().await;
    assert_eq!(listed, again, "a start from the index lists the same");

    // Tampered entries of runs whose directories then changed: the
    // directories win.
    let mut index = read_index(data);
    for id in [a, b, c] {
        index["runs"][id]["view"]["sample"] = json!("TAMPERED");
        index["runs"][id]["view"]["state"] = json!("completed");
        index["runs"][id]["view"]["steps_done"] = json!(999);
    }
    write_index(data, &index);
    // a: its state rewritten as rigd writes it (a new file, renamed over).
    let state_path = data.join("runs").join(a).join("state.json");
    let mut st: Value =
        serde_json::from_slice(&std::fs::read(&state_path).expect("state")).expect("parses");
    st["reason"] = json!("aborted by operator (edited)");
    st["state"] = json!("aborted");
    let tmp = state_path.with_extension("tmp");
    std::fs::write(&tmp, serde_json::to_vec(&st).expect("json")).expect("write");
    std::fs::rename(&tmp, &state_path).expect("rename");
    // b: a frame line appended to its journal, in place.
    let journal = data.join("runs").join(b).join("journal.ndjson");
    let line = std::fs::read_to_string(&journal)
        .expect("journal")
        .lines()
        .next()
        .expect("a line")
        .replace("\"index\":0", "\"index\":1");
    let mut f = std::fs::OpenOptions::new()
        .append(true)
        .open(&journal)
        .expect("open journal");
    std::io::Write::write_all(&mut f, format!("{line}\n").as_bytes()).expect("append");
    drop(f);
    // c: its run record replaced by one of the same size, its time set
    // back to what it was (only the change time and the inode tell).
    let run_path = data.join("runs").join(c).join("run.json");
    let before = std::fs::metadata(&run_path).expect("stat");
    let text = std::fs::read_to_string(&run_path).expect("run.json");
    let edited = text.replacen("\"operator\":\"tester\"", "\"operator\":\"TESTER\"", 1);
    assert_ne!(text, edited);
    std::fs::write(&run_path, edited).expect("write run.json");
    std::fs::File::options()
        .write(true)
        .open(&run_path)
        .and_then(|f| f.set_modified(before.modified()?))
        .expect("set mtime");

    let mut s = start_in(data, FAST).await;
    let mut seen = Vec::new();
    for id in [a, b, c] {
        let (_, v) = s.get(&format!("/api/v1/runs/{id}")).await;
        seen.push(v);
    }
    s.shutdown().await;
    assert_eq!(seen[0]["state"], "aborted");
    assert_eq!(seen[2]["operator"], "TESTER");
    for (id, v) in [a, b, c].into_iter().zip(&seen) {
        assert_ne!(v["sample"], "TAMPERED", "{id}");
        assert_eq!(v, &truth(data, id).await, "{id}");
    }

    // A run the index says completed but whose directory was being driven
    // (state.json says running) is read, and marked interrupted.
    let mut s = start_in(data, FAST).await;
    s.shutdown().await;
    let state_path = data.join("runs").join(a).join("state.json");
    let mut st: Value =
        serde_json::from_slice(&std::fs::read(&state_path).expect("state")).expect("parses");
    st["state"] = json!("running");
    st["reason"] = Value::Null;
    std::fs::write(&state_path, serde_json::to_vec(&st).expect("json")).expect("write");
    let mut s = start_in(data, FAST).await;
    let (_, v) = s.get(&format!("/api/v1/runs/{a}")).await;
    assert_eq!(v["state"], "interrupted", "{v}");
    s.shutdown().await;
    // Even with a tampered entry whose stamp matches: a cached active run
    // is never taken as it is.
    let mut index = read_index(data);
    index["runs"][a]["view"]["state"] = json!("running");
    write_index(data, &index);
    let mut s = start_in(data, FAST).await;
    let (_, v) = s.get(&format!("/api/v1/runs/{a}")).await;
    assert_eq!(v["state"], "interrupted", "{v}");
    s.shutdown().await;

    // A corrupt, foreign or truncated index is ignored and written anew.
    let mut foreign = read_index(data);
    foreign["format"] = json!("rigd-runs-index/999");
    for bad in [
        b"{torn".to_vec(),
        serde_json::to_vec(&foreign).expect("json"),
        b"".to_vec(),
        serde_json::to_vec(&json!({"format": "rigd-runs-index/1", "runs": 3})).expect("json"),
    ] {
        std::fs::write(data.join("runs-index.json"), &bad).expect("write");
        let mut s = start_in(data, FAST).await;
        let (status, list) = s.get("/api/v1/runs?limit=1000").await;
        s.shutdown().await;
        assert_eq!(status, 200);
        assert_eq!(list["total"], 12);
        let index = read_index(data);
        assert_eq!(index["format"], "rigd-runs-index/1");
        assert_eq!(index["runs"].as_object().map(|o| o.len()), Some(12));
    }
    // A run removed from runs/ leaves the index too.
    std::fs::remove_dir_all(data.join("runs").join(c)).expect("remove");
    let mut s = start_in(data, FAST).await;
    let (_, list) = s.get("/api/v1/runs?limit=1000").await;
    s.shutdown().await;
    assert_eq!(list["total"], 11);
    assert!(read_index(data)["runs"].get(c.as_str()).is_none());
}

/// A run started through the API shows on the first page and, once ended,
/// in the index.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn runs_page_shows_a_new_run_first_and_indexes_it() {
    let dir = tempfile::tempdir().expect("tempdir");
    history(dir.path(), 60).await;
    let mut s = start_in(dir.path(), FAST).await;
    let (status, v) = s
        .post("/api/v1/runs", Some(run_body("Fresh", small_plan(1))))
        .await;
    assert_eq!(status, 201, "{v}");
    let id = v["id"].as_str().expect("id").to_string();
    let ended = s.wait_ended(&id, "completed").await;
    let (_, first) = s.get("/api/v1/runs?limit=2").await;
    assert_eq!(first["runs"][0]["id"], id.as_str(), "{first}");
    assert_eq!(first["total"], 61);
    let (_, found) = s.get("/api/v1/runs?sample=fres").await;
    assert_eq!(ids(found["runs"].as_array().expect("runs")), [id.as_str()]);
    s.shutdown().await;
    let index = read_index(dir.path());
    assert_eq!(index["runs"][&id]["view"]["state"], "completed");
    let mut s = start_in(dir.path(), FAST).await;
    let (_, again) = s.get(&format!("/api/v1/runs/{id}")).await;
    s.shutdown().await;
    for k in ["id", "sample", "state", "steps_done", "finished_at"] {
        assert_eq!(again[k], ended[k], "{k}");
    }
}
