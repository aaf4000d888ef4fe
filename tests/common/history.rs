//! A large run history made cheaply, for the run-list tests, the browser
//! test and the history benchmark: one real run's record (run.json,
//! state.json, journal, manifest; never its frames) copied under many ids
//! with varied samples, plans, states and start times.

use std::path::Path;

use serde_json::Value;

/// Samples the copies cycle through (mixed case, for the search).
pub const SAMPLES: [&str; 5] = ["Felt", "wool", "Corduroy", "felt-blue", "Leather"];
/// Plan names the copies cycle through.
pub const PLANS: [&str; 3] = ["mini", "dome", "grid"];
/// States the copies cycle through.
pub const STATES: [&str; 3] = ["completed", "aborted", "failed"];

/// One copy: what its run list entry must say.
#[derive(Debug, Clone)]
pub struct Cloned {
    pub id: String,
    pub sample: String,
    pub plan: String,
    pub state: String,
    pub started_at: String,
}

/// Copy `i`'s start: one an hour from 2026-01-01 00:00 UTC, two copies
/// sharing each second (so the id decides their order).
fn started_at(i: usize) -> String {
    let t = std::time::UNIX_EPOCH
        + std::time::Duration::from_secs(1_767_225_600 + (i as u64 / 2) * 3600);
    humantime::format_rfc3339_seconds(t).to_string()
}

/// Copies the record of the run directory `src` into `runs_dir` as `n`
/// runs: copy `i` has sample `SAMPLES[i % 5]`, plan `PLANS[i % 3]`, state
/// `STATES[i % 3 / …]` (see the code), and starts at [`started_at`]`(i)`.
pub fn clone_runs(src: &Path, runs_dir: &Path, n: usize) -> Vec<Cloned> {
    let read = |f: &str| std::fs::read(src.join(f)).ok();
    let run: Value =
        serde_json::from_slice(&read("run.json").expect("run.json")).expect("run.json parses");
    let state: Value = serde_json::from_slice(&read("state.json").expect("state.json"))
        .expect("state.json parses");
    let journal = read("journal.ndjson");
    let manifest = read("manifest.json");
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        let sample = SAMPLES[i % SAMPLES.len()];
        let plan = PLANS[i % PLANS.len()];
        // Not in step with the plans, so that every pair occurs.
        let st = STATES[(i / 3) % STATES.len()];
        let started = started_at(i);
        let id = format!(
            "{}-{}-{plan}-{i}",
            started.replace(['-', ':'], ""),
            sample.replace('-', "_")
        );
        let dir = runs_dir.join(&id);
        std::fs::create_dir_all(&dir).expect("create run dir");
        let mut r = run.clone();
        r["sample"] = Value::from(sample);
        r["started_at"] = Value::from(started.clone());
        r["plan"]["name"] = Value::from(plan);
        std::fs::write(dir.join("run.json"), serde_json::to_vec(&r).expect("json"))
            .expect("write run.json");
        let mut s = state.clone();
        s["state"] = Value::from(st);
        std::fs::write(
            dir.join("state.json"),
            serde_json::to_vec(&s).expect("json"),
        )
        .expect("write state.json");
        if let Some(j) = &journal {
            std::fs::write(dir.join("journal.ndjson"), j).expect("write journal");
        }
        if let Some(m) = &manifest {
            std::fs::write(dir.join("manifest.json"), m).expect("write manifest");
        }
        out.push(Cloned {
            id,
            sample: sample.into(),
            plan: plan.into(),
            state: st.into(),
            started_at: started,
        });
    }
    out
}

/// The copies in the list's order: newest first, then id descending.
pub fn newest_first(runs: &[Cloned]) -> Vec<Cloned> {
    let mut v = runs.to_vec();
    v.sort_by(|a, b| b.started_at.cmp(&a.started_at).then(b.id.cmp(&a.id)));
    v
}
