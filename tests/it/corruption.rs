//! Damage to a run directory, one kind at a time, met by every command that
//! reads a run: each refuses naming the damage (exit 2), repairs it (a
//! resume retakes what is missing or damaged), or fills a damaged frame
//! from its neighbours and flags it. None exits 0 with output made from a
//! damaged frame as if it were measured, and none that only reads changes
//! the run.

use std::path::{Path, PathBuf};
use std::process::Output;
use std::sync::OnceLock;

use serde_json::{json, Value};

use crate::common::{assert_complete_run, rigd};
use rigd::store::{sha256_hex, FrameEntry, JOURNAL_FILE, MANIFEST_FILE, STATE_FILE};

/// 3 views × 3 lights on the Bonn rig: 9 frames.
const PLAN: &str = r#"{"name": "nine",
  "lights": [{"theta_deg": 30, "phi_deg": 0}, {"theta_deg": 45, "phi_deg": 120},
             {"theta_deg": 60, "phi_deg": 240}],
  "views": [{"theta_deg": 0, "phi_deg": 0}, {"theta_deg": 30, "phi_deg": 90},
            {"theta_deg": 45, "phi_deg": 200}]}"#;
const IMAGES: usize = 9;
/// Rectification small enough to take a moment.
const RECTIFY: [&str; 4] = ["--size", "64", "--final", "32"];

/// The captured (and rectified) runs every test copies before damaging
/// them: the Bonn 3 × 3 at 320×240, the smallest frame its markers
/// register, and the VirTex lamps plan (a camera at the pole, so
/// photometric stereo applies) at 64×48.
struct Bases {
    bonn: PathBuf,
    virtex: PathBuf,
}

fn bases() -> &'static Bases {
    static BASES: OnceLock<Bases> = OnceLock::new();
    BASES.get_or_init(|| {
        // One folder per test process: the test runner may run these
        // tests in several processes at once. Folders of processes that
        // have ended are removed.
        let all = Path::new(env!("CARGO_TARGET_TMPDIR")).join("corruption-bases");
        for entry in std::fs::read_dir(&all).into_iter().flatten().flatten() {
            let pid = entry.file_name();
            if !Path::new("/proc").join(&pid).exists() {
                let _ = std::fs::remove_dir_all(entry.path());
            }
        }
        let dir = all.join(std::process::id().to_string());
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("base folder");
        let plan = dir.join("nine.json");
        std::fs::write(&plan, PLAN).expect("plan");
        let bonn = dir.join("bonn");
        ok(&run_cmd(&[
            "run",
            "--sim",
            "--frame-size",
            "320x240",
            "--progress",
            "none",
            "--sample",
            "base",
            "--plan",
            path(&plan),
            "--out",
            path(&bonn),
        ]));
        let mut args = vec!["process", "rectify", path(&bonn)];
        args.extend(RECTIFY);
        ok(&run_cmd(&args));
        let virtex = dir.join("virtex");
        ok(&run_cmd(&[
            "run",
            "--sim",
            "--profile",
            "virtex-photometric-stereo",
            "--frame-size",
            "64x48",
            "--progress",
            "none",
            "--out",
            path(&virtex),
        ]));
        Bases { bonn, virtex }
    })
}

fn path(p: &Path) -> &str {
    p.to_str().expect("a UTF-8 path")
}

fn run_cmd(args: &[&str]) -> Output {
    rigd().args(args).output().expect("spawn rigd")
}

fn text(out: &Output) -> String {
    format!(
        "exit {:?}\n{}{}",
        out.status.code(),
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    )
}

fn ok(out: &Output) {
    assert!(out.status.success(), "{}", text(out));
    assert!(!text(out).contains("panicked"), "{}", text(out));
}

/// Exit 2 with every one of `names` in the message, and no panic.
fn refused(out: &Output, what: &str, names: &[&str]) {
    let t = text(out);
    assert_eq!(out.status.code(), Some(2), "{what}: {t}");
    assert!(!t.contains("panicked"), "{what}: {t}");
    for n in names {
        assert!(t.contains(n), "{what}: `{n}` is not named: {t}");
    }
}

/// A copy of `base` at `to` (`cp -a`, so the frames keep their bytes).
fn copy_run(base: &Path, to: &Path) -> PathBuf {
    let status = std::process::Command::new("cp")
        .arg("-a")
        .arg(base)
        .arg(to)
        .status()
        .expect("cp");
    assert!(status.success());
    to.to_path_buf()
}

/// The journal's lines, each with its newline.
fn journal_lines(run: &Path) -> Vec<String> {
    std::fs::read_to_string(run.join(JOURNAL_FILE))
        .expect("journal")
        .split_inclusive('\n')
        .map(str::to_string)
        .collect()
}

fn write_journal(run: &Path, lines: &[String]) {
    std::fs::write(run.join(JOURNAL_FILE), lines.concat()).expect("write journal");
}

fn entries(run: &Path) -> Vec<FrameEntry> {
    journal_lines(run)
        .iter()
        .map(|l| serde_json::from_str(l).expect("a journal line"))
        .collect()
}

fn entry(run: &Path, index: usize) -> FrameEntry {
    entries(run)
        .into_iter()
        .find(|e| e.index == index)
        .expect("the image's line")
}

/// Where a DNG frame's one uncompressed strip lies: (offset, bytes).
fn strip(bytes: &[u8]) -> (usize, usize) {
    let u16_at = |o: usize| u16::from_le_bytes([bytes[o], bytes[o + 1]]) as usize;
    let u32_at = |o: usize| {
        u32::from_le_bytes([bytes[o], bytes[o + 1], bytes[o + 2], bytes[o + 3]]) as usize
    };
    assert_eq!(&bytes[..2], b"II", "a little-endian TIFF");
    let ifd = u32_at(4);
    let (mut offset, mut len) = (None, None);
    for k in 0..u16_at(ifd) {
        let e = ifd + 2 + 12 * k;
        match u16_at(e) {
            273 => offset = Some(u32_at(e + 8)),
            279 => len = Some(u32_at(e + 8)),
            _ => {}
        }
    }
    (offset.expect("StripOffsets"), len.expect("StripByteCounts"))
}

/// Rewrites image `index`'s frame (a DNG of 16-bit samples) with `damage`
/// applied to its samples: a valid file that decodes, with other values
/// than were measured.
fn damage_frame(run: &Path, index: usize, damage: fn(&mut [u16], usize, u8)) {
    let e = entry(run, index);
    let file = run.join(&e.file);
    let mut bytes = std::fs::read(&file).expect("frame");
    let (offset, len) = strip(&bytes);
    assert_eq!(len, 2 * (e.width * e.height) as usize, "16-bit samples");
    let mut samples: Vec<u16> = bytes[offset..offset + len]
        .chunks_exact(2)
        .map(|c| u16::from_le_bytes([c[0], c[1]]))
        .collect();
    damage(&mut samples, e.width as usize, e.bit_depth);
    for (c, s) in bytes[offset..offset + len]
        .chunks_exact_mut(2)
        .zip(&samples)
    {
        c.copy_from_slice(&s.to_le_bytes());
    }
    assert_ne!(sha256_hex(&bytes), e.sha256);
    std::fs::write(&file, bytes).expect("write frame");
}

/// One flipped bit per pixel of a 40×40 block in the middle.
fn flip_bits(samples: &mut [u16], width: usize, _depth: u8) {
    let height = samples.len() / width;
    for y in height / 2 - 20..height / 2 + 20 {
        for x in width / 2 - 20..width / 2 + 20 {
            samples[y * width + x] ^= 1 << 3;
        }
    }
}

/// Two thirds of the frame at full scale.
fn burn(samples: &mut [u16], _width: usize, depth: u8) {
    let full = ((1u32 << depth) - 1) as u16;
    let n = samples.len() * 2 / 3;
    for s in &mut samples[..n] {
        *s = full;
    }
}

fn swap_frames(run: &Path, a: usize, b: usize) {
    let (fa, fb) = (run.join(entry(run, a).file), run.join(entry(run, b).file));
    let tmp = fa.with_extension("swap");
    std::fs::rename(&fa, &tmp).expect("rename");
    std::fs::rename(&fb, &fa).expect("rename");
    std::fs::rename(&tmp, &fb).expect("rename");
}

/// The bytes of the files a reader must leave alone.
fn record_files(run: &Path) -> Vec<(PathBuf, Option<Vec<u8>>)> {
    let mut files: Vec<PathBuf> = [JOURNAL_FILE, MANIFEST_FILE, STATE_FILE, "run.json"]
        .iter()
        .map(|f| run.join(f))
        .collect();
    let mut frames: Vec<PathBuf> = std::fs::read_dir(run.join("frames"))
        .expect("frames")
        .map(|e| e.expect("entry").path())
        .collect();
    frames.sort();
    files.extend(frames);
    files
        .into_iter()
        .map(|p| {
            let bytes = std::fs::read(&p).ok();
            (p, bytes)
        })
        .collect()
}

fn assert_untouched(run: &Path, before: &[(PathBuf, Option<Vec<u8>>)], what: &str) {
    let after = record_files(run);
    assert_eq!(before.len(), after.len(), "{what}: files came or went");
    for ((p, a), (_, b)) in before.iter().zip(&after) {
        assert!(a == b, "{what} changed {}", p.display());
    }
}

fn index_json(run: &Path) -> Value {
    let bytes =
        std::fs::read(run.join("processed/normtextures/index.json")).expect("normtexture index");
    serde_json::from_slice(&bytes).expect("index parses")
}

/// The commands that process a rectified run, each named for messages.
fn process(run: &Path, out: &Path) -> Vec<(&'static str, Output)> {
    let r = path(run);
    let utia = out.join("utia");
    let zip = out.join("ubo.zip");
    let mut rectify = vec!["process", "rectify", r];
    rectify.extend(RECTIFY);
    vec![
        ("rectify", run_cmd(&rectify)),
        ("btf", run_cmd(&["process", "btf", "--components", "2", r])),
        (
            "export utia",
            run_cmd(&["export", r, "--format", "utia", "--out", path(&utia)]),
        ),
        (
            "export ubo2003",
            run_cmd(&["export", r, "--format", "ubo2003", "--out", path(&zip)]),
        ),
    ]
}

/// The run as a pause leaves it: state.json `paused`, no manifest, nothing
/// processed; so that a resume may repair it.
fn as_paused(run: &Path) {
    let state = json!({"state": "paused", "reason": "paused by operator",
                       "physical_s": 1.0, "updated_at": "2026-01-01T00:00:00Z"});
    std::fs::write(run.join(STATE_FILE), state.to_string()).expect("state");
    std::fs::remove_file(run.join(MANIFEST_FILE)).expect("manifest");
    let _ = std::fs::remove_dir_all(run.join("processed"));
}

fn resume(run: &Path) -> Output {
    run_cmd(&["run", "--resume", path(run), "--progress", "log"])
}

/// Frames whose bytes are not what was measured are filled from their
/// slot's nearest lights and flagged `damaged` in the index, or refused;
/// never registered as if measured. A resume retakes them.
#[test]
fn damaged_frames_are_never_used_as_measured() {
    let b = bases();
    let scratch = tempfile::tempdir().expect("tempdir");
    // What is done to the Bonn run's frames, and to the VirTex run's.
    type Damage = fn(&Path, &[usize]);
    let cases: [(&str, Damage, &[usize], &[usize]); 3] = [
        (
            "bit flips",
            |r, i| damage_frame(r, i[0], flip_bits),
            &[4],
            &[1],
        ),
        (
            "two frames swapped",
            |r, i| swap_frames(r, i[0], i[1]),
            &[1, 2],
            &[0, 2],
        ),
        (
            "a burnt frame",
            |r, i| damage_frame(r, i[0], burn),
            &[7],
            &[2],
        ),
    ];
    for (what, damage, damaged, damaged_ps) in cases {
        let dir = scratch.path().join(what.replace(' ', "-"));
        std::fs::create_dir_all(&dir).expect("case folder");
        let run = copy_run(&b.bonn, &dir.join("run"));
        damage(&run, damaged);
        let before = record_files(&run);
        let outs = process(&run, &dir);
        assert_untouched(&run, &before, what);
        for (cmd, out) in &outs {
            ok(out);
            let _ = cmd;
        }
        let rectify = text(&outs[0].1);
        assert!(rectify.contains("damaged"), "{what}: {rectify}");
        let index = index_json(&run);
        let frames = index["frames"].as_array().expect("frames");
        assert_eq!(frames.len(), IMAGES, "{what}: {index}");
        for f in frames {
            let i = f["index"].as_u64().expect("index") as usize;
            let from: Vec<u64> = f["interpolated_from"]
                .as_array()
                .map(|a| a.iter().filter_map(Value::as_u64).collect())
                .unwrap_or_default();
            for d in damaged {
                assert!(
                    !from.contains(&(*d as u64)),
                    "{what}: frame {i} filled from damaged frame {d}: {f}"
                );
            }
            if damaged.contains(&i) {
                assert_eq!(f["damaged"], true, "{what}: {f}");
                assert_eq!(f["method"], "interpolated", "{what}: {f}");
                let problem = f["problem"].as_str().unwrap_or_default();
                assert!(problem.contains("SHA-256"), "{what}: {f}");
            } else {
                assert_ne!(f["damaged"], true, "{what}: {f}");
            }
        }
        let summary = &index["summary"];
        assert_eq!(
            summary["frames_damaged"],
            damaged.len(),
            "{what}: {summary}"
        );

        // Photometric stereo reads the frames themselves: it refuses.
        let ps_run = copy_run(&b.virtex, &dir.join("virtex"));
        damage(&ps_run, damaged_ps);
        let frame = entry(&ps_run, damaged_ps[0]).file;
        let out = run_cmd(&[
            "process",
            "photometric-stereo",
            path(&ps_run),
            "--out",
            path(&dir.join("ps")),
        ]);
        refused(&out, what, &[&frame, "SHA-256"]);
        assert!(!dir.join("ps/normals.npy").exists(), "{what}");

        // A resume of the run (paused, not completed) retakes them.
        let paused = copy_run(&b.bonn, &dir.join("paused"));
        as_paused(&paused);
        damage(&paused, damaged);
        let out = resume(&paused);
        ok(&out);
        assert!(
            text(&out).contains(&format!("retaking {} frames", damaged.len())),
            "{what}: {}",
            text(&out)
        );
        assert_complete_run(&paused, IMAGES);
    }
}

/// A journal line cut in the middle, a line twice, a journal cut short:
/// the processing steps refuse a journal they cannot trust (naming the
/// line, or both counts), read a line twice as one image, and a resume
/// repairs each.
#[test]
fn journal_damage_is_refused_or_repaired() {
    let b = bases();
    let scratch = tempfile::tempdir().expect("tempdir");

    // A line cut in the middle of the journal.
    let run = copy_run(&b.bonn, &scratch.path().join("torn"));
    let mut lines = journal_lines(&run);
    let half = lines[4].len() / 2;
    lines[4] = format!("{}\n", &lines[4][..half]);
    write_journal(&run, &lines);
    let before = record_files(&run);
    for (cmd, out) in process(&run, scratch.path()) {
        refused(&out, cmd, &[JOURNAL_FILE, "line 5"]);
    }
    assert_untouched(&run, &before, "a torn line");

    // A line twice: one image, read once.
    let run = copy_run(&b.bonn, &scratch.path().join("twice"));
    let mut lines = journal_lines(&run);
    lines.push(lines[2].clone());
    write_journal(&run, &lines);
    let before = record_files(&run);
    for (cmd, out) in process(&run, scratch.path()) {
        assert!(out.status.success(), "{cmd}: {}", text(&out));
        if cmd == "rectify" {
            let t = text(&out);
            assert!(t.contains("9 frames (3 views × 3 lights)"), "{t}");
        }
    }
    assert_untouched(&run, &before, "a line twice");
    assert_eq!(
        index_json(&run)["frames"].as_array().map(Vec::len),
        Some(IMAGES)
    );

    // A journal cut short of its manifest.
    let run = copy_run(&b.bonn, &scratch.path().join("cut"));
    let lines = journal_lines(&run);
    write_journal(&run, &lines[..5]);
    let before = record_files(&run);
    let outputs = scratch.path().join("cut-outputs");
    std::fs::create_dir_all(&outputs).expect("outputs");
    for (cmd, out) in process(&run, &outputs) {
        refused(&out, cmd, &[JOURNAL_FILE, MANIFEST_FILE, "5", "9"]);
    }
    assert!(!outputs.join("utia").exists(), "export wrote a partial run");
    assert!(
        !outputs.join("ubo.zip").exists(),
        "export wrote a partial run"
    );
    assert_untouched(&run, &before, "a cut journal");
    let ps_run = copy_run(&b.virtex, &scratch.path().join("virtex-cut"));
    let lines = journal_lines(&ps_run);
    write_journal(&ps_run, &lines[..lines.len() - 1]);
    let out = run_cmd(&[
        "process",
        "photometric-stereo",
        path(&ps_run),
        "--out",
        path(&scratch.path().join("ps")),
    ]);
    refused(&out, "photometric-stereo", &[JOURNAL_FILE, MANIFEST_FILE]);

    // A completed run is not resumed, whatever its journal says.
    let out = resume(&run);
    refused(&out, "resume", &["already completed"]);

    // A paused run with each of these is repaired by a resume: the lines
    // it cannot use are set aside, what they held is retaken, and each
    // image ends with exactly one line.
    type Damage = fn(&mut Vec<String>);
    let damages: [(&str, Damage); 4] = [
        ("a torn line", |l| {
            l[4] = format!("{}\n", &l[4][..l[4].len() / 2])
        }),
        ("a line twice", |l| l.push(l[2].clone())),
        ("a cut journal", |l| l.truncate(5)),
        ("a torn last line", |l| {
            let last = l.len() - 1;
            l[last] = l[last][..l[last].len() / 2].to_string();
        }),
    ];
    for (what, damage) in damages {
        let run = copy_run(
            &b.bonn,
            &scratch
                .path()
                .join(format!("paused-{}", what.replace(' ', "-"))),
        );
        as_paused(&run);
        let mut lines = journal_lines(&run);
        damage(&mut lines);
        write_journal(&run, &lines);
        let out = resume(&run);
        ok(&out);
        assert_complete_run(&run, IMAGES);
        let _ = what;
    }
}

/// A manifest cut short, garbage or empty is named, and nothing is
/// processed from its run.
#[test]
fn a_damaged_manifest_is_refused() {
    let b = bases();
    let scratch = tempfile::tempdir().expect("tempdir");
    let full = std::fs::read(b.bonn.join(MANIFEST_FILE)).expect("manifest");
    let cases: [(&str, Vec<u8>); 3] = [
        ("cut", full[..full.len() / 2].to_vec()),
        ("garbage", b"garbage\n".to_vec()),
        ("empty", Vec::new()),
    ];
    for (what, bytes) in cases {
        let dir = scratch.path().join(what);
        std::fs::create_dir_all(&dir).expect("case folder");
        let run = copy_run(&b.bonn, &dir.join("run"));
        std::fs::write(run.join(MANIFEST_FILE), &bytes).expect("manifest");
        let before = record_files(&run);
        for (cmd, out) in process(&run, &dir) {
            refused(&out, &format!("{what} manifest, {cmd}"), &[MANIFEST_FILE]);
        }
        assert_untouched(&run, &before, what);
        assert!(!dir.join("utia").exists(), "{what}");
    }
    // A completed run whose manifest is gone is damaged too.
    let run = copy_run(&b.bonn, &scratch.path().join("gone"));
    std::fs::remove_file(run.join(MANIFEST_FILE)).expect("remove manifest");
    for (cmd, out) in process(&run, scratch.path()) {
        refused(&out, cmd, &[MANIFEST_FILE]);
    }
}

/// A tmpfs holding a copy of a run, remounted read-only: readers must
/// read it without writing anything.
struct ReadOnlyCopy {
    dir: tempfile::TempDir,
}

impl ReadOnlyCopy {
    fn of(base: &Path, prepare: impl Fn(&Path)) -> ReadOnlyCopy {
        let dir = tempfile::tempdir().expect("tempdir");
        let mount = |opts: &str| {
            let status = std::process::Command::new("mount")
                .args(["-t", "tmpfs", "-o", opts, "tmpfs"])
                .arg(dir.path())
                .status()
                .expect("spawn mount");
            assert!(
                status.success(),
                "mount failed: this test needs root (CI and scripts/test.sh run as root)"
            );
        };
        mount("size=16m");
        let copy = ReadOnlyCopy { dir };
        copy_run(base, &copy.run());
        prepare(&copy.run());
        let status = std::process::Command::new("mount")
            .args(["-o", "remount,ro"])
            .arg(copy.dir.path())
            .status()
            .expect("spawn mount");
        assert!(status.success(), "remount ro failed");
        copy
    }

    fn run(&self) -> PathBuf {
        self.dir.path().join("run")
    }
}

impl Drop for ReadOnlyCopy {
    fn drop(&mut self) {
        let _ = std::process::Command::new("umount")
            .arg("-l")
            .arg(self.dir.path())
            .status();
    }
}

/// A run on a read-only filesystem, its journal with a torn last line (a
/// writer killed mid-append): export and photometric stereo (into another
/// folder) read it; rectify and btf, which write into the run, fail naming
/// what they could not write; nothing panics.
#[test]
fn a_read_only_run_is_read_without_writing() {
    let b = bases();
    let scratch = tempfile::tempdir().expect("tempdir");
    let tear = |run: &Path| {
        let mut lines = journal_lines(run);
        lines.push("{\"index\": 9, \"trig".into());
        write_journal(run, &lines);
    };
    let ro = ReadOnlyCopy::of(&b.bonn, tear);
    let run = ro.run();
    let before = record_files(&run);
    let utia = scratch.path().join("utia");
    ok(&run_cmd(&[
        "export",
        path(&run),
        "--format",
        "utia",
        "--out",
        path(&utia),
    ]));
    let exported = std::fs::read_dir(&utia).expect("utia").count();
    assert!(exported > 0);
    let mut rectify = vec!["process", "rectify", path(&run)];
    rectify.extend(RECTIFY);
    for (cmd, args) in [
        ("rectify", rectify),
        (
            "btf",
            vec!["process", "btf", "--components", "2", path(&run)],
        ),
    ] {
        let out = run_cmd(&args);
        let t = text(&out);
        assert!(
            !out.status.success(),
            "{cmd} wrote into a read-only run: {t}"
        );
        assert!(!t.contains("panicked"), "{cmd}: {t}");
        assert!(t.contains("Read-only file system"), "{cmd}: {t}");
        assert!(
            t.contains("processed"),
            "{cmd} does not name the folder: {t}"
        );
    }
    assert_untouched(&run, &before, "reading a read-only run");

    let ro = ReadOnlyCopy::of(&b.virtex, tear);
    let run = ro.run();
    let ps = scratch.path().join("ps");
    ok(&run_cmd(&[
        "process",
        "photometric-stereo",
        path(&run),
        "--out",
        path(&ps),
    ]));
    assert!(ps.join("normals.npy").exists());
}

/// The daemon lists runs with a damaged journal or manifest saying so, and
/// refuses to process them, naming the damage; a run with a damaged frame
/// is processed with the frame filled and flagged.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_daemon_names_damage_and_refuses_to_process_it() {
    use crate::common::http::start_in;
    let b = bases();
    let data = tempfile::tempdir().expect("tempdir");
    let runs = data.path().join("runs");
    std::fs::create_dir_all(&runs).expect("runs");
    let id = |what: &str| format!("20260101T000000Z-{what}-nine");
    let cut = copy_run(&b.bonn, &runs.join(id("cut")));
    let lines = journal_lines(&cut);
    write_journal(&cut, &lines[..5]);
    let garbage = copy_run(&b.bonn, &runs.join(id("garbage")));
    std::fs::write(garbage.join(MANIFEST_FILE), b"garbage").expect("manifest");
    let flipped = copy_run(&b.bonn, &runs.join(id("flipped")));
    damage_frame(&flipped, 4, flip_bits);
    let _ = std::fs::remove_dir_all(flipped.join("processed"));

    let mut s = start_in(data.path(), 200.0).await;
    let options = json!({"steps": ["rectify"], "rectify": {"size": 64, "final": 32}});
    for (what, names) in [
        ("cut", &[JOURNAL_FILE, MANIFEST_FILE, "5", "9"][..]),
        ("garbage", &[MANIFEST_FILE][..]),
    ] {
        let (status, v) = s.get(&format!("/api/v1/runs/{}", id(what))).await;
        assert_eq!(status, 200, "{v}");
        let problem = v["last_error"].as_str().unwrap_or_default();
        for n in names {
            assert!(problem.contains(n), "{what}: `{n}` not in {v}");
        }
        let (status, v) = s
            .post(
                &format!("/api/v1/runs/{}/process", id(what)),
                Some(options.clone()),
            )
            .await;
        assert!(status == 422 || status == 400, "{what}: {status} {v}");
        let detail = v["detail"].as_str().unwrap_or_default();
        for n in names {
            assert!(detail.contains(n), "{what}: `{n}` not in {v}");
        }
    }
    let process = format!("/api/v1/runs/{}/process", id("flipped"));
    let (status, v) = s.post(&process, Some(options)).await;
    assert!(status == 202 || status == 200, "{status} {v}");
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
    loop {
        let (_, job) = s.get(&process).await;
        match job["state"].as_str() {
            Some("done") => break,
            Some("failed") => panic!("{job}"),
            _ => {}
        }
        assert!(std::time::Instant::now() < deadline, "{job}");
        tokio::time::sleep(std::time::Duration::from_millis(50)).await;
    }
    s.shutdown().await;
    let index = index_json(&flipped);
    let f = &index["frames"][4];
    assert_eq!(
        (f["index"].as_u64(), &f["damaged"]),
        (Some(4), &json!(true)),
        "{f}"
    );
}

/// The engine's next event.
async fn next_event(
    events: &mut tokio::sync::broadcast::Receiver<rigd::engine::RunEvent>,
) -> rigd::engine::EventKind {
    use tokio::sync::broadcast::error::RecvError;
    loop {
        match events.recv().await {
            Ok(ev) => return ev.kind,
            Err(RecvError::Lagged(_)) => continue,
            Err(e) => panic!("events: {e}"),
        }
    }
}

/// The next state the engine moves to, and why.
async fn next_state(
    events: &mut tokio::sync::broadcast::Receiver<rigd::engine::RunEvent>,
) -> (rigd::model::run_state::RunState, String) {
    loop {
        if let rigd::engine::EventKind::State { to, reason, .. } = next_event(events).await {
            return (to, reason.unwrap_or_default());
        }
    }
}

/// A journal line that vanishes while the run is captured (as one did when
/// a reader cut what it took for a torn tail) keeps the run from
/// completing: it pauses naming the image, and a resume retakes it.
#[tokio::test(start_paused = true)]
async fn a_run_completes_only_with_every_image_in_its_journal() {
    use rigd::engine::command::Command;
    use rigd::engine::launch::{prepare_new, NewRun};
    use rigd::engine::PausePolicy;
    use rigd::model::run_state::RunState;
    use rigd::rig::sim::SimulatedRig;
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("run");
    let plan = crate::common::tiny_plan(tmp.path());
    let p = prepare_new(
        NewRun {
            profile: rigd::model::profile::Profile::load("bonn-gonioreflectometer")
                .expect("profile"),
            profile_source: "<embedded bonn-gonioreflectometer>".into(),
            plan: path(&plan).into(),
            sample: "lost-line".into(),
            operator: None,
            notes: None,
            exposure_s: None,
            exposure_policy: None,
            frame_size: Some([16, 16]),
            out: out.clone(),
            simulated: true,
            order: None,
        },
        Some(&SimulatedRig::new(vec![])),
        rigd_core::Clock::virtual_time(),
        PausePolicy::Wait,
    )
    .await
    .expect("prepare");
    let mut events = p.handle.events.subscribe();
    let commands = p.handle.commands.clone();
    let engine = tokio::spawn(p.engine.run());
    // Paused after a frame or two, the first image's line disappears.
    loop {
        if let rigd::engine::EventKind::Step { .. } = next_event(&mut events).await {
            break;
        }
    }
    commands.send(Command::Pause).await.expect("send");
    loop {
        if let (RunState::Paused, _) = next_state(&mut events).await {
            break;
        }
    }
    let lines = journal_lines(&out);
    assert!(!lines.is_empty(), "no frame before the pause");
    let kept: Vec<String> = lines
        .iter()
        .filter(|l| !l.starts_with("{\"index\":0,"))
        .cloned()
        .collect();
    assert_eq!(kept.len() + 1, lines.len(), "{lines:?}");
    write_journal(&out, &kept);
    commands.send(Command::Resume).await.expect("send");
    let reason = loop {
        match next_state(&mut events).await {
            (RunState::Paused, reason) => break reason,
            (RunState::Completed, _) => panic!("completed without image 0 in its journal"),
            _ => {}
        }
    };
    assert!(
        reason.contains("image 0") || reason.contains("images 0"),
        "{reason}"
    );
    assert!(reason.contains(JOURNAL_FILE), "{reason}");
    commands.send(Command::Resume).await.expect("send");
    let outcome = engine.await.expect("join").expect("engine");
    assert_eq!(outcome.state, RunState::Completed, "{:?}", outcome.reason);
    assert_complete_run(&out, 4);
}
