//! `stillmap-client eval` against real evo on the same files: the real TUM ground
//! truth as reference, and an estimate derived from it (ground truth at the
//! rgb.txt timestamps, moved rigidly, with deterministic noise).
//!
//! evo comes from `$STILLMAP_EVO_BIN` or `<workspace>/.deps/evo/bin`
//! (`deploy/install-deps.sh` installs it); without it this test fails.

use std::path::{Path, PathBuf};
use std::process::Command;

use nalgebra::{Isometry3, Vector3};
use serde_json::Value;
use stillmap_dataset::trajectory::{format_tum, read_tum};

/// Largest accepted difference between our statistics and evo's.
const TOLERANCE: f64 = 1e-4;
/// Our default association window, passed to evo explicitly (its default is 0.01).
const T_MAX_DIFF: &str = "0.02";
const STATS: [&str; 6] = ["rmse", "mean", "median", "std", "min", "max"];
/// Noise of the derived estimate: translation (m) and rotation (rad), per axis.
const TRANSLATION_NOISE_M: f64 = 0.01;
const ROTATION_NOISE_RAD: f64 = 0.01;

fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn tum_dir() -> PathBuf {
    let dir = stillmap_dataset::shared::fr1_rpy();
    assert!(dir.join("groundtruth.txt").exists(), "TUM clip not found at {} (set TUM)", dir.display());
    dir
}

fn evo_bin() -> PathBuf {
    let dir = std::env::var_os("STILLMAP_EVO_BIN").map(PathBuf::from).unwrap_or_else(|| workspace().join(".deps/evo/bin"));
    assert!(
        dir.join("evo_ape").exists() && dir.join("evo_rpe").exists(),
        "evo not found in {}: run deploy/install-deps.sh (or set STILLMAP_EVO_BIN to a folder with evo_ape, evo_rpe, python)",
        dir.display()
    );
    dir
}

/// SplitMix64: a fixed, portable pseudo-random sequence in [-1, 1).
struct Noise(u64);

impl Noise {
    fn next(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        (z >> 11) as f64 / (1u64 << 52) as f64 - 1.0
    }

    fn vector(&mut self, scale: f64) -> Vector3<f64> {
        Vector3::new(self.next(), self.next(), self.next()) * scale
    }
}

/// The ground truth nearest each rgb.txt timestamp, moved by a rigid transform, with
/// noise; plus two poses long after the ground truth ends (left unassociated).
fn write_estimate(tum: &Path, out: &Path) {
    let gt = read_tum(&tum.join("groundtruth.txt")).expect("ground truth");
    let rgb = stillmap_dataset::tum::read_list(&tum.join("rgb.txt")).expect("rgb.txt");
    let stamps: Vec<f64> = rgb.iter().map(|(t, _)| *t as f64 * 1e-9).collect();
    let moved = Isometry3::new(Vector3::new(0.8, -0.4, 1.5), Vector3::new(0.2, -0.5, 0.9));
    let mut noise = Noise(0x5717_1A4D);
    let mut estimate = Vec::new();
    for &t in &stamps {
        let nearest = gt.iter().min_by(|a, b| (a.0 - t).abs().total_cmp(&(b.0 - t).abs())).expect("poses");
        let jitter = Isometry3::new(noise.vector(TRANSLATION_NOISE_M), noise.vector(ROTATION_NOISE_RAD));
        estimate.push((t, moved * nearest.1 * jitter));
    }
    let last = estimate.last().expect("rgb stamps").1;
    let end = gt.last().expect("poses").0;
    estimate.extend([(end + 1.0, last), (end + 2.0, last)]);
    std::fs::write(out, format_tum(&estimate)).expect("write estimate");
}

/// Runs evo (`evo_ape` or `evo_rpe`) and returns its statistics plus `count`.
fn evo(bin: &Path, home: &Path, tool: &str, gt: &Path, est: &Path, args: &[&str], zip: &Path) -> Value {
    let output = Command::new(bin.join(tool))
        .arg("tum")
        .args([gt, est])
        .args(args)
        .args(["--t_max_diff", T_MAX_DIFF, "--no_warnings", "--save_results"])
        .arg(zip)
        .env("MPLBACKEND", "Agg")
        // Fresh default settings: the user's ~/.evo must not change the results.
        .env("HOME", home)
        .output()
        .expect("run evo");
    assert!(output.status.success(), "{tool} {args:?} failed: {}", String::from_utf8_lossy(&output.stderr));
    let script = "import io, json, sys, zipfile\n\
                  import numpy as np\n\
                  z = zipfile.ZipFile(sys.argv[1])\n\
                  stats = json.loads(z.read('stats.json'))\n\
                  stats['count'] = len(np.load(io.BytesIO(z.read('error_array.npy'))))\n\
                  print(json.dumps(stats))";
    let output = Command::new(bin.join("python")).args(["-c", script]).arg(zip).output().expect("run evo's python");
    assert!(output.status.success(), "reading {}: {}", zip.display(), String::from_utf8_lossy(&output.stderr));
    serde_json::from_slice(&output.stdout).expect("evo stats JSON")
}

/// Runs `stillmap-client eval` and returns its JSON report.
fn ours(gt: &Path, est: &Path, args: &[&str], json: &Path) -> Value {
    let output = Command::new(env!("CARGO_BIN_EXE_stillmap-client"))
        .args(["eval"])
        .args(args.iter().take(1))
        .args([gt, est])
        .args(&args[1..])
        .arg("--json")
        .arg(json)
        .output()
        .expect("run stillmap-client");
    assert!(output.status.success(), "eval {args:?} failed: {}", String::from_utf8_lossy(&output.stderr));
    serde_json::from_str(&std::fs::read_to_string(json).expect("our JSON")).expect("our JSON parses")
}

struct Case {
    name: &'static str,
    ours: &'static [&'static str],
    evo_tool: &'static str,
    evo: &'static [&'static str],
    /// `translation` or `rotation` in our report.
    section: &'static str,
}

const CASES: [Case; 7] = [
    Case {
        name: "APE trans, SE(3) align",
        ours: &["ape", "--align", "--relation", "trans"],
        evo_tool: "evo_ape",
        evo: &["-a", "-r", "trans_part"],
        section: "translation",
    },
    Case {
        name: "APE rot, origin align",
        ours: &["ape", "--align-origin", "--relation", "rot"],
        evo_tool: "evo_ape",
        evo: &["--align_origin", "-r", "angle_deg"],
        section: "rotation",
    },
    Case {
        name: "APE trans, not aligned",
        ours: &["ape", "--relation", "trans"],
        evo_tool: "evo_ape",
        evo: &["-r", "trans_part"],
        section: "translation",
    },
    Case {
        name: "RPE trans, delta 1",
        ours: &["rpe", "--delta", "1", "--relation", "trans"],
        evo_tool: "evo_rpe",
        evo: &["--delta", "1", "--delta_unit", "f", "-r", "trans_part"],
        section: "translation",
    },
    Case {
        name: "RPE rot, delta 1",
        ours: &["rpe", "--delta", "1", "--relation", "rot"],
        evo_tool: "evo_rpe",
        evo: &["--delta", "1", "--delta_unit", "f", "-r", "angle_deg"],
        section: "rotation",
    },
    Case {
        name: "RPE trans, delta 10, aligned",
        ours: &["rpe", "--delta", "10", "--align", "--relation", "trans"],
        evo_tool: "evo_rpe",
        evo: &["--delta", "10", "--delta_unit", "f", "-a", "-r", "trans_part"],
        section: "translation",
    },
    Case {
        name: "RPE rot, delta 10",
        ours: &["rpe", "--delta", "10", "--relation", "rot"],
        evo_tool: "evo_rpe",
        evo: &["--delta", "10", "--delta_unit", "f", "-r", "angle_deg"],
        section: "rotation",
    },
];

#[test]
fn eval_matches_evo_on_real_tum_ground_truth() {
    let bin = evo_bin();
    let tum = tum_dir();
    let dir = std::env::temp_dir().join(format!("stillmap-evo-parity-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let (gt, est) = (tum.join("groundtruth.txt"), dir.join("estimate.txt"));
    write_estimate(&tum, &est);

    let mut worst = (0.0f64, "");
    let mut failures = Vec::new();
    for (i, case) in CASES.iter().enumerate() {
        let report = ours(&gt, &est, case.ours, &dir.join(format!("ours{i}.json")));
        let reference = evo(&bin, &dir, case.evo_tool, &gt, &est, case.evo, &dir.join(format!("evo{i}.zip")));
        let stats = &report[case.section];
        println!("{}: {} errors (ours) / {} (evo)", case.name, stats["count"], reference["count"]);
        if stats["count"] != reference["count"] {
            failures.push(format!("{}: count {} vs evo {}", case.name, stats["count"], reference["count"]));
        }
        for key in STATS {
            let (a, b) = (stats[key].as_f64().unwrap_or(f64::NAN), reference[key].as_f64().unwrap_or(f64::NAN));
            let diff = (a - b).abs();
            println!("  {key:<6} ours {a:.9}  evo {b:.9}  diff {diff:.2e}");
            if diff.is_nan() || diff > TOLERANCE {
                failures.push(format!("{}: {key} {a} vs evo {b}", case.name));
            }
            if diff > worst.0 {
                worst = (diff, case.name);
            }
        }
    }
    println!("worst difference {:.2e} ({})", worst.0, worst.1);
    assert!(failures.is_empty(), "differences above {TOLERANCE}:\n{}", failures.join("\n"));

    // The plot renders (PNG signature) with the default output.
    let png = dir.join("plot.png");
    let output = Command::new(env!("CARGO_BIN_EXE_stillmap-client"))
        .args(["eval", "ape"])
        .args([&gt, &est])
        .args(["--align", "--plot"])
        .arg(&png)
        .output()
        .expect("run stillmap-client");
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let table = String::from_utf8_lossy(&output.stdout);
    assert!(table.contains("translation (m)") && table.contains("rotation (deg)"), "{table}");
    let bytes = std::fs::read(&png).expect("plot written");
    assert!(bytes.starts_with(b"\x89PNG\r\n\x1a\n") && bytes.len() > 10_000, "not a PNG");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn eval_errors_are_one_line_naming_the_file_and_line() {
    let dir = std::env::temp_dir().join(format!("stillmap-eval-errors-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let bad = dir.join("bad.txt");
    std::fs::write(&bad, "# header\n1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 1\n").expect("write");
    let good = dir.join("good.txt");
    std::fs::write(&good, "1.0 0 0 0 0 0 0 1\n").expect("write");
    for args in [vec![&good, &bad], vec![&bad, &good]] {
        let output = Command::new(env!("CARGO_BIN_EXE_stillmap-client")).args(["eval", "ape"]).args(args).output().expect("run");
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert_eq!(output.status.code(), Some(1), "{stderr}");
        assert_eq!(stderr.lines().count(), 1, "{stderr}");
        assert!(stderr.contains("bad.txt:3") && stderr.contains("expected 8 values"), "{stderr}");
    }
    let output = Command::new(env!("CARGO_BIN_EXE_stillmap-client"))
        .args(["eval", "ape"])
        .args([&good, &dir.join("missing.txt")])
        .output()
        .expect("run");
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("missing.txt") && stderr.lines().count() == 1, "{stderr}");
    let _ = std::fs::remove_dir_all(&dir);
}
