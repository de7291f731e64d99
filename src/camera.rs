//! Camera models: orthographic (the default) and the pinhole camera of intrinsics K.
//!
//! Pixel (u, v) is column u, row v, both from 0 at the first pixel's centre. For a pinhole camera
//! with K = [[f_x, 0, c_x], [0, f_y, c_y], [0, 0, 1]], a point at depth d (distance along the
//! optical axis) seen at (u, v) is, in the camera frame (x right, y up, z towards the viewer),
//! P = d · ((u − c_x)/f_x, −(v − c_y)/f_y, −1).

use crate::error::{Error, Result};
use std::path::Path;

/// Pinhole intrinsics in pixels.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Intrinsics {
    /// Focal length along u (columns).
    pub fx: f64,
    /// Focal length along v (rows).
    pub fy: f64,
    /// Principal point, column.
    pub cx: f64,
    /// Principal point, row.
    pub cy: f64,
}

impl Intrinsics {
    /// From a row-major 3×3 matrix K (normalised so that K₂₂ = 1).
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] for a skewed or non-finite matrix, non-positive focal lengths, or
    /// a last row other than (0, 0, k).
    pub fn from_matrix(k: [[f64; 3]; 3]) -> Result<Self> {
        if !k.iter().flatten().all(|v| v.is_finite()) {
            return Err(Error::param("camera", "K has non-finite entries"));
        }
        let s = k[2][2];
        if k[2][0] != 0.0 || k[2][1] != 0.0 || s <= 0.0 || k[1][0] != 0.0 {
            return Err(Error::param(
                "camera",
                "K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]",
            ));
        }
        if k[0][1] != 0.0 {
            return Err(Error::param(
                "camera",
                "skewed intrinsics (K[0][1] ≠ 0) are not supported",
            ));
        }
        let (fx, fy) = (k[0][0] / s, k[1][1] / s);
        if fx <= 0.0 || fy <= 0.0 {
            return Err(Error::param(
                "camera",
                format!("focal lengths {fx}, {fy} must be > 0"),
            ));
        }
        Ok(Intrinsics {
            fx,
            fy,
            cx: k[0][2] / s,
            cy: k[1][2] / s,
        })
    }

    /// Reads K from a text file of 9 numbers (three rows of three, as `numpy.savetxt` writes).
    ///
    /// # Errors
    /// [`Error::Io`] when unreadable; [`Error::InvalidParameter`] naming the file when it does not
    /// hold a valid K.
    pub fn from_file(path: &Path) -> Result<Self> {
        let text = crate::io::input::read_text(path)?;
        let values: Vec<f64> = text
            .split(|c: char| c.is_whitespace() || c == ',' || c == ';' || c == '[' || c == ']')
            .filter(|t| !t.is_empty())
            .map(|t| t.parse::<f64>())
            .collect::<std::result::Result<_, _>>()
            .map_err(|e| Error::param("camera", format!("{}: {e}", path.display())))?;
        if values.len() != 9 {
            return Err(Error::param(
                "camera",
                format!(
                    "{}: {} numbers, a 3×3 matrix K needs 9",
                    path.display(),
                    values.len()
                ),
            ));
        }
        let k = [
            [values[0], values[1], values[2]],
            [values[3], values[4], values[5]],
            [values[6], values[7], values[8]],
        ];
        Intrinsics::from_matrix(k)
            .map_err(|e| Error::param("camera", format!("{}: {e}", path.display())))
    }

    /// The 3-D point (camera frame) seen at pixel (u, v) at depth `d`.
    pub fn unproject(&self, u: f64, v: f64, d: f64) -> [f64; 3] {
        [
            d * (u - self.cx) / self.fx,
            -d * (v - self.cy) / self.fy,
            -d,
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_numpy_savetxt_layout() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("K.txt");
        std::fs::write(
            &p,
            "3.772077471010729823e+03 0.000000000000000000e+00 3.058750000000000000e+02\n0 3.759005431071329895e+03 2.551250000000000000e+02\n0 0 1\n",
        )
        .unwrap();
        let k = Intrinsics::from_file(&p).unwrap();
        assert!((k.fx - 3772.077).abs() < 1e-3 && (k.cy - 255.125).abs() < 1e-9);
        std::fs::write(&p, "1 0 0\n0 1 0\n").unwrap();
        assert!(
            Intrinsics::from_file(&p)
                .unwrap_err()
                .to_string()
                .contains("9")
        );
        assert!(
            Intrinsics::from_matrix([[1.0, 0.1, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]).is_err()
        );
    }
}
