//! Triangle meshes of depth maps, as binary PLY files that MeshLab, Blender, Open3D or trimesh
//! open.
//!
//! One vertex per pixel with a depth and a normal; two triangles per 2×2 block of valid pixels
//! (one where exactly three are valid), counter-clockwise seen from the camera. Orthographic
//! depth (height z in pixel units) gives vertices (x, y, z) with x = column − (W−1)/2 and
//! y = (H−1)/2 − row; perspective depth d gives the camera-frame points d·K⁻¹(u, v, 1) with y up
//! and z towards the viewer (so the object lies at negative z).

use crate::camera::Intrinsics;
use crate::error::Result;
use crate::grid::{NormalMap, ScalarMap};

/// A mesh ready to be written.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Mesh {
    /// Vertex positions.
    pub vertices: Vec<[f32; 3]>,
    /// Vertex normals (unit).
    pub normals: Vec<[f32; 3]>,
    /// Triangles as vertex indices.
    pub triangles: Vec<[u32; 3]>,
}

impl Mesh {
    /// The mesh of `depth` with per-vertex `normals` (scaled to unit length); orthographic when
    /// `camera` is `None`.
    ///
    /// # Errors
    /// [`crate::Error::DimensionMismatch`] when the maps differ in size.
    pub fn from_depth(
        depth: &ScalarMap,
        normals: &NormalMap,
        camera: Option<&Intrinsics>,
    ) -> Result<Self> {
        depth.check_same_size(normals, "normals vs depth")?;
        let (w, h) = (depth.width(), depth.height());
        let mut index = vec![u32::MAX; w * h];
        let mut mesh = Mesh::default();
        for r in 0..h {
            for c in 0..w {
                let i = r * w + c;
                let (d, n) = (depth.data()[i], normals.data()[i]);
                if !d.is_finite() || !n.iter().all(|v| v.is_finite()) {
                    continue;
                }
                let p = match camera {
                    None => [
                        c as f32 - (w as f32 - 1.0) / 2.0,
                        (h as f32 - 1.0) / 2.0 - r as f32,
                        d,
                    ],
                    Some(k) => k
                        .unproject(c as f64, r as f64, f64::from(d))
                        .map(|v| v as f32),
                };
                index[i] = mesh.vertices.len() as u32;
                mesh.vertices.push(p);
                // Unit, whatever the map's lengths (integration reads directions too).
                let n = crate::ps::normals::unit_length(&n);
                mesh.normals.push([n.x, n.y, n.z]);
            }
        }
        for r in 0..h.saturating_sub(1) {
            for c in 0..w.saturating_sub(1) {
                let i = r * w + c;
                // a b   (image layout, row r above row r + 1)
                // c d
                let (a, b, cc, d) = (index[i], index[i + 1], index[i + w], index[i + w + 1]);
                let ok = |v: u32| v != u32::MAX;
                match (ok(a), ok(b), ok(cc), ok(d)) {
                    (true, true, true, true) => {
                        mesh.triangles.push([a, cc, b]);
                        mesh.triangles.push([b, cc, d]);
                    }
                    (true, true, true, false) => mesh.triangles.push([a, cc, b]),
                    (true, true, false, true) => mesh.triangles.push([a, d, b]),
                    (true, false, true, true) => mesh.triangles.push([a, cc, d]),
                    (false, true, true, true) => mesh.triangles.push([b, cc, d]),
                    _ => {}
                }
            }
        }
        Ok(mesh)
    }

    /// The mesh as a binary little-endian PLY file.
    pub fn to_ply(&self) -> Vec<u8> {
        let header = format!(
            "ply\nformat binary_little_endian 1.0\ncomment written by photostereo\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nproperty float nx\nproperty float ny\nproperty float nz\nelement face {}\nproperty list uchar int vertex_indices\nend_header\n",
            self.vertices.len(),
            self.triangles.len()
        );
        let mut out =
            Vec::with_capacity(header.len() + self.vertices.len() * 24 + self.triangles.len() * 13);
        out.extend_from_slice(header.as_bytes());
        for (p, n) in self.vertices.iter().zip(&self.normals) {
            for v in p.iter().chain(n) {
                out.extend_from_slice(&v.to_le_bytes());
            }
        }
        for t in &self.triangles {
            out.push(3);
            for v in t {
                out.extend_from_slice(&(*v as i32).to_le_bytes());
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::Grid;
    use nalgebra::Vector3;

    #[test]
    fn triangles_face_the_camera_and_skip_holes() {
        let mut depth = Grid::from_fn(4, 3, |x, y| (x + y) as f32);
        *depth.at_mut(3, 2) = f32::NAN;
        let normals = Grid::new(4, 3, Vector3::z());
        let m = Mesh::from_depth(&depth, &normals, None).unwrap();
        assert_eq!(m.vertices.len(), 11);
        // 6 blocks, one with a missing corner: 5·2 + 1 triangles.
        assert_eq!(m.triangles.len(), 11);
        for t in &m.triangles {
            let [a, b, c] = t.map(|i| m.vertices[i as usize]);
            let cross = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]);
            assert!(cross > 0.0, "clockwise triangle {t:?}");
        }
        let ply = m.to_ply();
        let header_end = ply.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
        assert_eq!(ply.len() - header_end, 11 * 24 + 11 * 13);
    }

    /// A map of vectors scaled by an albedo gives the mesh unit vertex normals (their
    /// directions); unit ones are kept bit for bit.
    #[test]
    fn vertex_normals_are_unit_whatever_the_map_s_lengths() {
        let depth = Grid::new(2, 1, 1.0f32);
        let unit = Vector3::new(0.6f32, 0.0, 0.8);
        let normals = Grid::from_vec(2, 1, vec![unit * 0.05, unit]).unwrap();
        let m = Mesh::from_depth(&depth, &normals, None).unwrap();
        for n in &m.normals {
            let v = Vector3::from(*n);
            assert!((v - unit).norm() < 1e-6, "{n:?}");
        }
        assert_eq!(m.normals[1], [unit.x, unit.y, unit.z]);
    }
}
