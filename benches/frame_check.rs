//! What the SHA-256 check costs that every frame passes before processing
//! uses it (`RunFrames`, `docs/architecture.md`, "What the journal
//! guarantees"), beside what reading the frame costs anyway.
//!
//! `cargo bench --bench frame_check -- RUN…` (`scripts/bench-rectify.sh`
//! runs it on each run it rectifies). For each run directory: every
//! journaled frame is read once into memory (then from the page cache, as
//! rectification reads it); the SHA-256 of all of them, and all of them
//! read, checked and decoded as `rigd process rectify` reads them, are timed
//! on one thread, the faster of three passes each. Prints one line per run:
//! `RUN FRAMES HASH_MS_PER_FRAME IMAGE_MS_PER_FRAME`.

use std::path::PathBuf;
use std::time::Instant;

use rigd::postprocess::frames::RunFrames;
use rigd::store::sha256_hex;

const PASSES: usize = 3;

fn best_of(mut pass: impl FnMut()) -> f64 {
    (0..PASSES)
        .map(|_| {
            let start = Instant::now();
            pass();
            start.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min)
}

fn main() {
    // `cargo bench` passes `--bench`; everything else is a run directory.
    let runs: Vec<PathBuf> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with("--"))
        .map(PathBuf::from)
        .collect();
    if runs.is_empty() {
        eprintln!("usage: cargo bench --bench frame_check -- RUN…");
        std::process::exit(2);
    }
    for root in runs {
        let run = match RunFrames::open(&root) {
            Ok(run) => run,
            Err(e) => {
                eprintln!("{}: {e}", root.display());
                std::process::exit(1);
            }
        };
        let bytes: Vec<Vec<u8>> = run
            .entries
            .iter()
            .map(|e| std::fs::read(root.join(&e.file)).unwrap_or_default())
            .collect();
        let n = bytes.len().max(1) as f64;
        let hash_s = best_of(|| {
            for b in &bytes {
                std::hint::black_box(sha256_hex(b));
            }
        });
        let image_s = best_of(|| {
            for e in &run.entries {
                if let Err(err) = run.image(e) {
                    eprintln!("{}: {err}", root.display());
                    std::process::exit(1);
                }
            }
        });
        println!(
            "{} {} {:.3} {:.3}",
            root.display(),
            bytes.len(),
            1e3 * hash_s / n,
            1e3 * image_s / n
        );
    }
}
