//! TUM trajectory files: `timestamp tx ty tz qx qy qz qw` per line, `#` comments.

use std::path::Path;

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};

use crate::DatasetError;
use crate::eval::Trajectory;
use crate::tum::parse_timestamp_ns;

/// Values on a TUM trajectory line.
const FIELDS: usize = 8;
/// A quaternion with a smaller squared norm cannot be normalised meaningfully.
const MIN_QUATERNION_NORM_SQUARED: f64 = 1e-12;

/// Reads a TUM trajectory file with timestamps in seconds (evo's reading); errors
/// name the file and the line.
pub fn read_tum(path: &Path) -> Result<Trajectory, DatasetError> {
    parse_tum(&read(path)?, path)
}

/// Reads a TUM trajectory file with exact nanosecond timestamps (ground truth,
/// the server's trajectories); errors name the file and the line.
pub fn read_tum_ns(path: &Path) -> Result<Vec<(u64, Isometry3<f64>)>, DatasetError> {
    parse_tum_ns(&read(path)?, path)
}

fn read(path: &Path) -> Result<String, DatasetError> {
    std::fs::read_to_string(path).map_err(|source| DatasetError::Read { path: path.to_owned(), source })
}

/// Parses the text of a TUM trajectory file; `path` only labels errors.
///
/// Blank lines and lines starting with `#` are skipped, fields are separated by
/// any whitespace, quaternions are normalised (evo does the same), and the poses
/// keep the file's order (association handles unsorted timestamps like evo).
pub fn parse_tum(text: &str, path: &Path) -> Result<Trajectory, DatasetError> {
    parse_with(text, path, |field| field.parse::<f64>().ok().filter(|x| x.is_finite()))
}

/// [`parse_tum`] with the timestamps as exact nanoseconds ([`parse_timestamp_ns`]).
pub fn parse_tum_ns(text: &str, path: &Path) -> Result<Vec<(u64, Isometry3<f64>)>, DatasetError> {
    parse_with(text, path, parse_timestamp_ns)
}

fn parse_with<T>(text: &str, path: &Path, timestamp: impl Fn(&str) -> Option<T>) -> Result<Vec<(T, Isometry3<f64>)>, DatasetError> {
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    let mut poses = Vec::new();
    for (index, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let parse_error = |message: String| DatasetError::Parse { path: path.to_owned(), line: index + 1, message };
        let fields: Vec<&str> = line.split_whitespace().collect();
        if fields.len() != FIELDS {
            return Err(parse_error(format!("expected {FIELDS} values (timestamp tx ty tz qx qy qz qw), found {}", fields.len())));
        }
        let t = timestamp(fields[0]).ok_or_else(|| parse_error(format!("`{}` is not a timestamp", fields[0])))?;
        let mut v = [0.0f64; FIELDS];
        for (slot, field) in v.iter_mut().zip(&fields).skip(1) {
            *slot = field
                .parse::<f64>()
                .ok()
                .filter(|x| x.is_finite())
                .ok_or_else(|| parse_error(format!("`{field}` is not a finite number")))?;
        }
        let q = Quaternion::new(v[7], v[4], v[5], v[6]);
        if q.norm_squared() < MIN_QUATERNION_NORM_SQUARED {
            return Err(parse_error("the quaternion is zero".into()));
        }
        let pose = Isometry3::from_parts(Translation3::new(v[1], v[2], v[3]), UnitQuaternion::from_quaternion(q));
        poses.push((t, pose));
    }
    if poses.is_empty() {
        return Err(DatasetError::Empty { path: path.to_owned() });
    }
    Ok(poses)
}

/// Formats poses as a TUM trajectory (timestamps with 6 decimals, values with 9).
pub fn format_tum(trajectory: &[(f64, Isometry3<f64>)]) -> String {
    let mut out = String::from(HEADER);
    for (t, pose) in trajectory {
        let p = pose.translation.vector;
        let q = pose.rotation.quaternion();
        out.push_str(&format!("{t:.6}"));
        push_values(&mut out, [p.x, p.y, p.z], [q.i, q.j, q.k, q.w]);
    }
    out
}

/// The header line of a TUM trajectory file.
pub const HEADER: &str = "# timestamp tx ty tz qx qy qz qw\n";

/// Appends one TUM trajectory line: the exact nanosecond timestamp as seconds with
/// 9 decimals, the translation, and the rotation as a quaternion `x y z w`.
pub fn push_line_ns(out: &mut String, timestamp_ns: u64, translation: [f64; 3], rotation_xyzw: [f64; 4]) {
    out.push_str(&format!("{}.{:09}", timestamp_ns / 1_000_000_000, timestamp_ns % 1_000_000_000));
    push_values(out, translation, rotation_xyzw);
}

/// Formats poses with nanosecond timestamps as a TUM trajectory ([`push_line_ns`]).
pub fn format_tum_ns(trajectory: &[(u64, Isometry3<f64>)]) -> String {
    let mut out = String::from(HEADER);
    for (t, pose) in trajectory {
        let (p, q) = (pose.translation.vector, pose.rotation.quaternion());
        push_line_ns(&mut out, *t, [p.x, p.y, p.z], [q.i, q.j, q.k, q.w]);
    }
    out
}

fn push_values(out: &mut String, [x, y, z]: [f64; 3], [qx, qy, qz, qw]: [f64; 4]) {
    out.push_str(&format!(" {x:.9} {y:.9} {z:.9} {qx:.9} {qy:.9} {qz:.9} {qw:.9}\n"));
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<Trajectory, DatasetError> {
        parse_tum(text, Path::new("traj.txt"))
    }

    #[test]
    fn parses_comments_blank_lines_and_normalises_quaternions() {
        let t = parse("# header\n\n1.5 1 2 3 0 0 0 2\n  \n2.5 0 0 0 0 0 1 1\n").unwrap();
        assert_eq!(t.len(), 2);
        assert_eq!(t[0].0, 1.5);
        assert_eq!(t[0].1.translation.vector, nalgebra::Vector3::new(1.0, 2.0, 3.0));
        assert!((t[0].1.rotation.angle()).abs() < 1e-15);
        assert!((t[1].1.rotation.angle() - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
    }

    #[test]
    fn errors_name_file_and_line() {
        let e = parse("# c\n1 0 0 0 0 0 0 1\n2 0 0 0 0 0 1\n").unwrap_err().to_string();
        assert!(e.contains("traj.txt:3") && e.contains("expected 8 values"), "{e}");
        let e = parse("1 0 0 0 0 0 0 1\n\n2 0 x 0 0 0 0 1\n").unwrap_err().to_string();
        assert!(e.contains("traj.txt:3") && e.contains("`x`"), "{e}");
        let e = parse("1 0 0 nan 0 0 0 1\n").unwrap_err().to_string();
        assert!(e.contains("traj.txt:1") && e.contains("finite"), "{e}");
        let e = parse("1 0 0 0 0 0 0 0\n").unwrap_err().to_string();
        assert!(e.contains("traj.txt:1") && e.contains("quaternion"), "{e}");
        let e = parse("# only a comment\n").unwrap_err().to_string();
        assert!(e.contains("traj.txt") && e.contains("no poses"), "{e}");
    }

    #[test]
    fn nanosecond_timestamps_are_exact_and_round_trip() {
        let text = "1305031229.528748 1 2 3 0 0 0 1\n";
        let t = parse_tum_ns(text, Path::new("gt.txt")).unwrap();
        assert_eq!(t[0].0, 1_305_031_229_528_748_000);
        let written = format_tum_ns(&t);
        assert_eq!(
            written,
            "# timestamp tx ty tz qx qy qz qw\n1305031229.528748000 1.000000000 2.000000000 3.000000000 0.000000000 0.000000000 0.000000000 1.000000000\n"
        );
        assert_eq!(parse_tum_ns(&written, Path::new("gt.txt")).unwrap()[0].0, t[0].0);
        let e = parse_tum_ns("1.x 0 0 0 0 0 0 1\n", Path::new("gt.txt")).unwrap_err().to_string();
        assert!(e.contains("gt.txt:1") && e.contains("not a timestamp"), "{e}");
    }

    #[test]
    fn format_round_trips() {
        let t = parse("1.25 1 2 3 0.1 0.2 0.3 0.9\n").unwrap();
        let back = parse(&format_tum(&t)).unwrap();
        assert_eq!(back[0].0, 1.25);
        assert!((back[0].1.translation.vector - t[0].1.translation.vector).norm() < 1e-9);
        assert!(back[0].1.rotation.angle_to(&t[0].1.rotation) < 1e-8);
    }
}
