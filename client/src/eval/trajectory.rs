//! TUM trajectory files: `timestamp tx ty tz qx qy qz qw` per line, `#` comments.

use std::path::Path;

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};

use super::{EvalError, Trajectory};

/// Values on a TUM trajectory line.
const FIELDS: usize = 8;
/// A quaternion with a smaller squared norm cannot be normalised meaningfully.
const MIN_QUATERNION_NORM_SQUARED: f64 = 1e-12;

/// Reads a TUM trajectory file; errors name the file and the line.
pub fn read_tum(path: &Path) -> Result<Trajectory, EvalError> {
    let text = std::fs::read_to_string(path).map_err(|source| EvalError::Read { path: path.to_owned(), source })?;
    parse_tum(&text, path)
}

/// Parses the text of a TUM trajectory file; `path` only labels errors.
///
/// Blank lines and lines starting with `#` are skipped, fields are separated by
/// any whitespace, quaternions are normalised (evo does the same), and the poses
/// keep the file's order (association handles unsorted timestamps like evo).
pub fn parse_tum(text: &str, path: &Path) -> Result<Trajectory, EvalError> {
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    let mut poses = Vec::new();
    for (index, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let parse_error = |message: String| EvalError::Parse { path: path.to_owned(), line: index + 1, message };
        let fields: Vec<&str> = line.split_whitespace().collect();
        if fields.len() != FIELDS {
            return Err(parse_error(format!("expected {FIELDS} values (timestamp tx ty tz qx qy qz qw), found {}", fields.len())));
        }
        let mut v = [0.0f64; FIELDS];
        for (slot, field) in v.iter_mut().zip(&fields) {
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
        poses.push((v[0], pose));
    }
    if poses.is_empty() {
        return Err(EvalError::Empty { path: path.to_owned() });
    }
    Ok(poses)
}

/// Formats poses as a TUM trajectory (timestamps with 6 decimals, values with 9).
pub fn format_tum(trajectory: &[(f64, Isometry3<f64>)]) -> String {
    let mut out = String::from("# timestamp tx ty tz qx qy qz qw\n");
    for (t, pose) in trajectory {
        let p = pose.translation.vector;
        let q = pose.rotation.quaternion();
        out.push_str(&format!("{t:.6} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9}\n", p.x, p.y, p.z, q.i, q.j, q.k, q.w));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<Trajectory, EvalError> {
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
    fn format_round_trips() {
        let t = parse("1.25 1 2 3 0.1 0.2 0.3 0.9\n").unwrap();
        let back = parse(&format_tum(&t)).unwrap();
        assert_eq!(back[0].0, 1.25);
        assert!((back[0].1.translation.vector - t[0].1.translation.vector).norm() < 1e-9);
        assert!(back[0].1.rotation.angle_to(&t[0].1.rotation) < 1e-8);
    }
}
