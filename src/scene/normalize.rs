//! The f64 normalisation of SPEC §4.1: the mesh's bounding box mapped to `[0,1]^3`.

use super::Mesh;
use glam::DVec3;

/// How the bounding box maps to `[0,1]^3` (SPEC §4.1).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum NormalizeMode {
    /// Per-axis extent, as the official code. Written `peraxis`; `per-axis` is read too.
    #[default]
    #[serde(alias = "per-axis")]
    PerAxis,
    /// The largest axis extent for all three axes.
    Isotropic,
}

/// `x_n = (x - center) / extent + 0.5` (SPEC §4.1), all in f64. Serialised (checkpoint metadata
/// `normalization`) as JSON `{"center":[x,y,z],"extent":[x,y,z]}`.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Normalization {
    pub center: DVec3,
    pub extent: DVec3,
}

impl Normalization {
    /// The identity map of `[0,1]^3` (center 0.5, extent 1).
    pub fn unit() -> Normalization {
        Normalization {
            center: DVec3::splat(0.5),
            extent: DVec3::ONE,
        }
    }

    /// `center = (min+max)/2`, `extent = max-min+1e-6` per axis (or the largest for all).
    pub fn from_mesh(mesh: &Mesh, mode: NormalizeMode) -> Normalization {
        let (lo, hi) = mesh.bbox();
        let center = (lo + hi) * 0.5;
        let e = hi - lo + DVec3::splat(1e-6);
        let extent = match mode {
            NormalizeMode::PerAxis => e,
            NormalizeMode::Isotropic => DVec3::splat(e.max_element()),
        };
        Normalization { center, extent }
    }

    #[inline]
    pub fn to_normalized(&self, x: DVec3) -> DVec3 {
        (x - self.center) / self.extent + DVec3::splat(0.5)
    }

    #[inline]
    pub fn from_normalized(&self, x: DVec3) -> DVec3 {
        (x - DVec3::splat(0.5)) * self.extent + self.center
    }
}
