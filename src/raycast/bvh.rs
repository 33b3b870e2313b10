//! The scene's ray tracer: a BVH built once per scene by obvhs 0.4 in the local frame of SPEC
//! §4.1, traversed by our own 8-wide packet traversal with the watertight test of `triangle.rs`,
//! and a final f64 refinement of the hit on the chosen triangle.
//!
//! ## Build
//! Vertices are moved to the local frame in f64 (`v - normalization.center`) and only then cast
//! to f32, so a scene at (5e5, 4e6, 300) keeps the precision of one at the origin. obvhs builds a
//! BVH2 ([`BuildPreset`] picks its `BvhBuildParams` preset, leaves of ≤ 4 triangles); we collapse
//! it into a [`WIDTH`] = 8-wide BVH (each node holds the boxes of up to 8 children,
//! structure-of-arrays, 256 bytes) and store the triangles' f32 vertices in leaf order. The f64
//! vertices used by the refinement are renumbered in order of first use along the leaf order, so
//! a hit's vertices sit in memory near those of the triangles traced just before. obvhs is used
//! for construction only: its traversal floors `tmin` at 1e-4 (CWBVH), its triangle test is not
//! watertight (`docs/notes.md`, section 3), and it has no packet traversal.
//!
//! ## Traversal
//! Rays are traced in packets of up to [`MAX_LANES`] = 16 ([`Packet`], structure of arrays;
//! `cast.rs` sends 4×4 sub-samples, i.e. 2×2 pixels at γ = 2). Lanes are grouped by dominant axis
//! and direction signs (so near/far slab planes are fixed per group); a full packet whose lanes
//! all agree (camera rays, almost always) is recognised four lanes at a time and traced as it is.
//! Each group is one traversal:
//! - **Nodes**: one *interval* box test for the whole group against all 8 children at once (one
//!   AVX operation per step, runtime-detected with `is_x86_feature_detected!`; two SSE halves
//!   otherwise). Per axis the group's smallest/largest origin and inverse direction bound every
//!   lane's slab distances (below), so a child is skipped only if no lane can hit it. Children
//!   are visited front-to-back by that lower bound of their entry distance.
//! - **Leaves**: every triangle is tested against the group's lanes in chunks of 8 (AVX) or 4
//!   (SSE), bit-identical to the scalar test; with a shared origin (camera rays) the vertex
//!   translation is one scalar subtraction per vertex.
//!
//! The interval test replaced per-lane box tests: it costs the same for 16 lanes as for one,
//! and at 2×2 pixels the group's frustum is narrow enough that it visits few extra boxes. On the
//! 1.3M-triangle bench scene the traversal alone runs at ~18 Mrays/s on one core, about 6.7×
//! obvhs's own `Bvh2::ray_traverse` with the same watertight closure.
//!
//! ## Conservative boxes (why the closest hit is exact)
//! All node boxes are recomputed here from the f32 vertices (exact min/max) and padded by
//! `PAD_REL · S` (S = largest |local coordinate|), which covers the lateral error of the
//! watertight test (≈ 8·2⁻²⁴·D at distance D) for cameras up to ~30·S from the centre. The slab
//! test is pbrt's robust one (far distance scaled by `1 + 2⁻¹⁹` ≥ 1 + 2γ₃), and a box is culled
//! only when its entry distance exceeds the current closest distance times the same factor.
//! For one lane i the slab distances are `fl(fl(b - o_i) · inv_i)`; rounding is monotone, so
//! `fl(b - o)` is monotone in `o` and `fl(r · inv)` in `r` and in `inv` (one sign per group), and
//! `fl(1/d)` is monotone in `d`. The group's extreme slab distances are therefore products of
//! the extreme operands (`GroupBounds`): the interval test's lower bound of the entry distance
//! is ≤ every lane's, its upper bound of the exit distance ≥ every lane's, and it never culls a
//! box that the per-lane test would visit for some lane.
//! Hence every triangle the f32 test accepts with a distance not above the final closest one
//! is visited, and the result is the lexicographic minimum of `(t_f32, triangle id)` over all
//! accepted triangles: it does not depend on the BVH preset, the traversal order or the packet
//! a ray is traced in (tested against an f32 brute force, bit for bit, for random packets and
//! camera packets, with and without AVX).
//!
//! ## Refinement
//! The f32 traversal only picks the triangle. `t`, barycentrics and the hit point are then
//! recomputed in f64 (Möller–Trumbore) on that triangle's f64 local-frame vertices from the
//! f64 origin and direction: the normalised hit position is accurate to ~1e-15 relative to the
//! extent (the triangle choice itself can differ from the exact one only within ~1e-7·D of an
//! edge, where both neighbours give nearly the same point).

#![allow(clippy::needless_range_loop)]

pub use super::packet::{Packet, MAX_LANES};
#[cfg(target_arch = "x86_64")]
use super::simd::F8;
use super::simd::{Lanes, Mask, F4};
use super::triangle::{intersect_lanes, permutation, ray_axis, RayLanes};
use super::Hit;
use crate::scene::{Mesh, Normalization};
use anyhow::{bail, Result};
use glam::{DVec3, Vec3A};
use obvhs::{bvh2::Bvh2, triangle::Triangle, BvhBuildParams};
use std::time::Duration;

/// Which obvhs `BvhBuildParams` preset builds the BVH2 that is collapsed to our 8-wide BVH. The hits
/// do not depend on it (see the module docs); only build time and tracing speed do.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum BuildPreset {
    /// `BvhBuildParams::fast_build()` with at most 4 triangles per leaf.
    Fast,
    /// `BvhBuildParams::medium_build()` with at most 4 triangles per leaf (the default).
    #[default]
    Medium,
}

impl BuildPreset {
    /// Every preset the crate uses (the tests check each one).
    pub const ALL: [BuildPreset; 2] = [BuildPreset::Fast, BuildPreset::Medium];

    /// The obvhs parameters.
    pub fn params(self) -> BvhBuildParams {
        let base = match self {
            BuildPreset::Fast => BvhBuildParams::fast_build(),
            BuildPreset::Medium => BvhBuildParams::medium_build(),
        };
        BvhBuildParams {
            max_prims_per_leaf: 4,
            ..base
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            BuildPreset::Fast => "fast",
            BuildPreset::Medium => "medium",
        }
    }
}

/// Box padding relative to the largest |local coordinate| (see the module docs).
pub const PAD_REL: f64 = 1.0 / 65536.0;
/// Slack factor on far distances in the slab test: 1 + 2⁻¹⁹ (≥ pbrt's 1 + 2γ₃ ≈ 1 + 3.6e-7).
const SLAB_SCALE: f32 = 1.0 + 1.0 / 524288.0;

/// Leaf references: bit 31 set, bits 27..31 = count-1 (1..=16 triangles), bits 0..27 = first.
const LEAF_BIT: u32 = 1 << 31;
const LEAF_MAX: usize = 16;
const MAX_TRIANGLES: usize = 1 << 27;
/// Memory a mesh's BVH takes to build, per triangle (checked before building). Measured: peak RSS
/// of `xscale cast --scene fixtures/tiny --no-images --gamma 1 --mesh M` with the `synth --preset
/// cross` mesh subdivided once and twice (2.1 M and 8.4 M triangles): 343 and 339 bytes per
/// triangle, the loaded mesh included; rounded up.
pub const BVH_BYTES_PER_TRIANGLE: u64 = 384;

#[inline(always)]
fn leaf_ref(first: usize, count: usize) -> u32 {
    debug_assert!((1..=LEAF_MAX).contains(&count) && first < MAX_TRIANGLES);
    LEAF_BIT | (((count - 1) as u32) << 27) | first as u32
}

/// Children per node.
pub const WIDTH: usize = 8;

/// A [`WIDTH`]-wide node: `b[0]` = child minima, `b[1]` = child maxima, `[axis][child]`
/// (224 bytes, padded to four cache lines). Empty child slots have min = +inf, max = -inf (never
/// hit).
#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
struct Node {
    b: [[[f32; WIDTH]; 3]; 2],
    child: [u32; WIDTH],
}

impl Node {
    fn empty() -> Node {
        Node {
            b: [[[f32::INFINITY; WIDTH]; 3], [[f32::NEG_INFINITY; WIDTH]; 3]],
            child: [0; WIDTH],
        }
    }
}

/// Reusable traversal scratch (the stack). One per thread.
#[derive(Default)]
pub struct Scratch {
    stack: Vec<(u32, f32)>,
}

/// The BVH and the f64 local-frame mesh of one scene.
pub struct Tracer {
    nodes: Vec<Node>,
    root: Option<u32>,
    /// Triangle vertices in the local frame (f32), in leaf order.
    tris: Vec<[[f32; 3]; 3]>,
    /// Leaf order → index into `Mesh::triangles`.
    tri_ids: Vec<u32>,
    /// f64 local-frame vertices (for the refinement), renumbered in order of first use along
    /// the leaf order, and each leaf-order triangle's three indices into them: a hit's vertices
    /// then sit near those of the triangles traced just before (fewer cache misses).
    verts: Vec<DVec3>,
    tri_verts: Vec<[u32; 3]>,
    /// Optional anchor vertices (indexed like `verts`; empty: none): hit positions are reported
    /// at the anchor triangle's point with the hit's barycentrics ([`Tracer::anchored`]).
    anchor: Vec<DVec3>,
    /// Mesh triangle → leaf-order index.
    leaf_of: Vec<u32>,
    normalization: Normalization,
    preset: BuildPreset,
    stack_capacity: usize,
    build_time: Duration,
    avx: bool,
}

struct Builder<'a> {
    bvh2: &'a Bvh2,
    tris32: &'a [[[f32; 3]; 3]],
    pad: f64,
    nodes: Vec<Node>,
    tris: Vec<[[f32; 3]; 3]>,
    tri_ids: Vec<u32>,
    max_depth: usize,
}

type Bounds = ([f32; 3], [f32; 3]);

fn union(a: Bounds, b: Bounds) -> Bounds {
    (
        std::array::from_fn(|i| a.0[i].min(b.0[i])),
        std::array::from_fn(|i| a.1[i].max(b.1[i])),
    )
}

const EMPTY_BOUNDS: Bounds = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);

impl Builder<'_> {
    fn padded(&self, (lo, hi): Bounds) -> Bounds {
        (
            lo.map(|x| (x as f64 - self.pad) as f32),
            hi.map(|x| (x as f64 + self.pad) as f32),
        )
    }

    /// A leaf (or a small subtree of leaves when there are more than 16 primitives).
    fn leaf(&mut self, prims: &[u32], depth: usize) -> (u32, Bounds) {
        self.max_depth = self.max_depth.max(depth);
        if prims.len() <= LEAF_MAX {
            let first = self.tris.len();
            let mut b = EMPTY_BOUNDS;
            for &p in prims {
                let t = self.tris32[p as usize];
                for v in t {
                    b = union(b, (v, v));
                }
                self.tris.push(t);
                self.tri_ids.push(p);
            }
            return (leaf_ref(first, prims.len()), b);
        }
        let slot = self.nodes.len();
        self.nodes.push(Node::empty());
        let chunk = prims.len().div_ceil(WIDTH);
        let mut total = EMPTY_BOUNDS;
        for (i, part) in prims.chunks(chunk).enumerate() {
            let (r, b) = self.leaf(part, depth + 1);
            self.set_child(slot, i, r, b);
            total = union(total, b);
        }
        (slot as u32, total)
    }

    fn set_child(&mut self, slot: usize, i: usize, r: u32, b: Bounds) {
        let (lo, hi) = self.padded(b);
        let n = &mut self.nodes[slot];
        for a in 0..3 {
            n.b[0][a][i] = lo[a];
            n.b[1][a][i] = hi[a];
        }
        n.child[i] = r;
    }

    fn node(&mut self, idx: usize, depth: usize) -> (u32, Bounds) {
        let n = self.bvh2.nodes[idx];
        if n.is_leaf() {
            let (f, c) = (n.first_index as usize, n.prim_count as usize);
            let prims = &self.bvh2.primitive_indices[f..f + c];
            return self.leaf(prims, depth);
        }
        self.max_depth = self.max_depth.max(depth);
        // Collapse: open the largest inner child until there are WIDTH children.
        let mut kids: Vec<usize> = vec![n.first_index as usize, n.first_index as usize + 1];
        while kids.len() < WIDTH {
            let best = kids
                .iter()
                .enumerate()
                .filter(|(_, &k)| !self.bvh2.nodes[k].is_leaf())
                .max_by(|a, b| {
                    let ha = self.bvh2.nodes[*a.1].aabb().half_area();
                    let hb = self.bvh2.nodes[*b.1].aabb().half_area();
                    ha.total_cmp(&hb)
                })
                .map(|(i, _)| i);
            let Some(i) = best else { break };
            let k = kids.remove(i);
            let f = self.bvh2.nodes[k].first_index as usize;
            kids.insert(i, f + 1);
            kids.insert(i, f);
        }
        let slot = self.nodes.len();
        self.nodes.push(Node::empty());
        let mut total = EMPTY_BOUNDS;
        for (i, &k) in kids.iter().enumerate() {
            let (r, b) = self.node(k, depth + 1);
            self.set_child(slot, i, r, b);
            total = union(total, b);
        }
        (slot as u32, total)
    }
}

impl Tracer {
    /// Build with the default preset.
    pub fn new(mesh: &Mesh, normalization: &Normalization) -> Result<Tracer> {
        Tracer::with_preset(mesh, normalization, BuildPreset::default())
    }

    /// Build with a given obvhs preset. Errors on out-of-range vertex indices, non-finite
    /// vertices or more than 2^27 triangles.
    pub fn with_preset(
        mesh: &Mesh,
        normalization: &Normalization,
        preset: BuildPreset,
    ) -> Result<Tracer> {
        let start = std::time::Instant::now();
        if mesh.triangles.len() >= MAX_TRIANGLES {
            bail!(
                "mesh has {} triangles; the tracer supports fewer than 2^27",
                mesh.triangles.len()
            );
        }
        // obvhs allocates its build arrays with an unwrap: short of memory, every command
        // that casts rays panicked in a dependency (`bytemuck … unwrap() on an Err value`, exit
        // 101; with RUST_BACKTRACE=1 it hung printing the backtrace). Refuse first, in words.
        crate::sysmem::check_fits(
            mesh.triangles.len() as f64 * BVH_BYTES_PER_TRIANGLE as f64,
            &format!("the ray-casting BVH of the mesh's {} triangles", mesh.triangles.len()),
            "free memory, or cast against a mesh with fewer triangles (xscale decimate --ratio R, then --mesh)",
        )?;
        let nv = mesh.vertices.len();
        for (i, t) in mesh.triangles.iter().enumerate() {
            if let Some(&k) = t.iter().find(|&&k| k as usize >= nv) {
                bail!("mesh triangle {i}: vertex index {k} out of range ({nv} vertices)");
            }
        }
        let verts: Vec<DVec3> = mesh
            .vertices
            .iter()
            .map(|v| *v - normalization.center)
            .collect();
        if let Some(i) = verts.iter().position(|v| !v.is_finite()) {
            bail!("mesh vertex {i}: coordinate is not finite");
        }
        let s = verts
            .iter()
            .fold(0.0f64, |m, v| m.max(v.abs().max_element()));
        let pad = PAD_REL * s.max(f64::MIN_POSITIVE);
        let v32: Vec<[f32; 3]> = verts
            .iter()
            .map(|v| [v.x as f32, v.y as f32, v.z as f32])
            .collect();
        let tris32: Vec<[[f32; 3]; 3]> = mesh
            .triangles
            .iter()
            .map(|t| t.map(|k| v32[k as usize]))
            .collect();

        let mut tracer = Tracer {
            nodes: Vec::new(),
            root: None,
            tris: Vec::new(),
            tri_ids: Vec::new(),
            verts: Vec::new(),
            tri_verts: Vec::new(),
            anchor: Vec::new(),
            leaf_of: Vec::new(),
            normalization: *normalization,
            preset,
            stack_capacity: 4,
            build_time: Duration::ZERO,
            avx: avx_detected(),
        };
        if !tris32.is_empty() {
            let otris: Vec<Triangle> = tris32
                .iter()
                .map(|t| Triangle {
                    v0: Vec3A::from_array(t[0]),
                    v1: Vec3A::from_array(t[1]),
                    v2: Vec3A::from_array(t[2]),
                })
                .collect();
            let bvh2 = obvhs::bvh2::builder::build_bvh2_from_tris(
                &otris,
                preset.params(),
                &mut Duration::default(),
            );
            drop(otris);
            let mut b = Builder {
                bvh2: &bvh2,
                tris32: &tris32,
                pad,
                nodes: Vec::with_capacity(tris32.len() / 4 + 1),
                tris: Vec::with_capacity(tris32.len()),
                tri_ids: Vec::with_capacity(tris32.len()),
                max_depth: 0,
            };
            let (root, _) = b.node(0, 0);
            tracer.root = Some(root);
            tracer.stack_capacity = (WIDTH - 1) * (b.max_depth + 2) + WIDTH;
            tracer.nodes = b.nodes;
            tracer.tris = b.tris;
            tracer.tri_ids = b.tri_ids;
        }
        tracer.renumber(&mesh.triangles, &verts)?;
        tracer.build_time = start.elapsed();
        Ok(tracer)
    }

    /// Fill `verts`, `tri_verts` and `leaf_of` from the leaf order (`tri_ids`).
    fn renumber(&mut self, triangles: &[[u32; 3]], verts: &[DVec3]) -> Result<()> {
        // A pre-splitting obvhs preset could reference a triangle from several leaves; the
        // presets of `BuildPreset` do not.
        if self.tri_ids.len() != triangles.len() {
            bail!(
                "BVH leaves reference {} triangles, the mesh has {}: each must be in exactly one leaf",
                self.tri_ids.len(),
                triangles.len()
            );
        }
        let mut new_index = vec![u32::MAX; verts.len()];
        self.leaf_of = vec![u32::MAX; triangles.len()];
        self.tri_verts = Vec::with_capacity(triangles.len());
        for (j, &id) in self.tri_ids.iter().enumerate() {
            // Equal counts and no repeat: every triangle is in exactly one leaf.
            if self.leaf_of[id as usize] != u32::MAX {
                bail!("BVH leaves reference triangle {id} twice");
            }
            self.leaf_of[id as usize] = j as u32;
            let t = triangles[id as usize].map(|k| {
                let n = &mut new_index[k as usize];
                if *n == u32::MAX {
                    *n = self.verts.len() as u32;
                    self.verts.push(verts[k as usize]);
                }
                *n
            });
            self.tri_verts.push(t);
        }
        Ok(())
    }

    /// This tracer reporting every hit at the point of `base` (same triangles, other vertex
    /// positions, e.g. the training mesh of a refined one: `[model.refine] anchored`) with the
    /// hit's barycentrics, instead of at the hit itself. Distances, triangles, barycentrics and
    /// footprints stay those of the traced mesh.
    /// `base` must have the traced mesh's triangles (in the same order).
    pub fn anchored(mut self, base: &Mesh) -> Result<Tracer> {
        let nv = base.vertices.len();
        if base.triangles.len() != self.tri_ids.len()
            || base.triangles.iter().flatten().any(|&k| k as usize >= nv)
            || base.vertices.iter().any(|v| !v.is_finite())
        {
            bail!("the anchor mesh must have the traced mesh's triangles and finite vertices");
        }
        let triangles = &base.triangles;
        let mut anchor = vec![DVec3::ZERO; self.verts.len()];
        for (j, &id) in self.tri_ids.iter().enumerate() {
            let t = triangles[id as usize];
            for c in 0..3 {
                anchor[self.tri_verts[j][c] as usize] =
                    base.vertices[t[c] as usize] - self.normalization.center;
            }
        }
        self.anchor = anchor;
        Ok(self)
    }

    /// The anchor point (local frame) of barycentrics `(u, v)` in leaf-order triangle `j`, if
    /// the tracer is [`Tracer::anchored`].
    #[inline]
    pub fn anchor_point(&self, j: u32, u: f64, v: f64) -> Option<DVec3> {
        if self.anchor.is_empty() {
            return None;
        }
        let [a, b, c] = self.tri_verts[j as usize].map(|k| self.anchor[k as usize]);
        Some(a * (1.0 - u - v) + b * u + c * v)
    }

    pub fn normalization(&self) -> &Normalization {
        &self.normalization
    }
    pub fn preset(&self) -> BuildPreset {
        self.preset
    }
    pub fn triangle_count(&self) -> usize {
        self.leaf_of.len()
    }
    pub fn node_count(&self) -> usize {
        self.nodes.len()
    }
    /// Wall time of [`Tracer::with_preset`].
    pub fn build_time(&self) -> Duration {
        self.build_time
    }
    /// A scratch sized for this BVH.
    pub fn scratch(&self) -> Scratch {
        Scratch {
            stack: Vec::with_capacity(self.stack_capacity),
        }
    }

    /// The f64 local-frame vertices of a mesh triangle.
    #[inline]
    pub fn triangle_local(&self, tri: u32) -> [DVec3; 3] {
        self.leaf_local(self.leaf_of[tri as usize])
    }

    /// The f64 local-frame vertices of the triangle at leaf-order index `j`
    /// ([`Tracer::trace_leaves`]).
    #[inline]
    pub fn leaf_local(&self, j: u32) -> [DVec3; 3] {
        let [a, b, c] = self.tri_verts[j as usize];
        [
            self.verts[a as usize],
            self.verts[b as usize],
            self.verts[c as usize],
        ]
    }

    /// The mesh triangle at leaf-order index `j`.
    #[inline]
    pub fn leaf_triangle(&self, j: u32) -> u32 {
        self.tri_ids[j as usize]
    }

    /// Unit geometric normal of a mesh triangle (f64; zero for a degenerate triangle).
    #[inline]
    pub fn triangle_normal(&self, tri: u32) -> DVec3 {
        let [a, b, c] = self.triangle_local(tri);
        (b - a).cross(c - a).normalize_or_zero()
    }

    /// Closest hit of a world-space ray (`dir` need not be unit; `Hit::t` is the distance along
    /// the normalised direction). `None` for a miss or a zero/non-finite direction.
    pub fn closest_hit(&self, origin_world: DVec3, dir: DVec3) -> Option<Hit> {
        let d = dir.normalize_or_zero();
        if d == DVec3::ZERO || !origin_world.is_finite() {
            return None;
        }
        let o = origin_world - self.normalization.center;
        let mut p = Packet::default();
        p.set(0, o.as_vec3().to_array(), d.as_vec3().to_array());
        let mut s = self.scratch();
        let (tri, t) = self.trace(&p, &mut s)[0]?;
        Some(self.refine(o, d, tri, t))
    }

    /// Refine a hit of triangle `tri` in f64 (module docs). `o` is the local-frame origin, `d`
    /// the unit direction, `t32` the f32 distance of the traversal (used only if the ray lies in
    /// the triangle's plane, where the f64 intersection is undefined).
    pub fn refine(&self, o: DVec3, d: DVec3, tri: u32, t32: f32) -> Hit {
        self.refine_with_sec(o, d, tri, t32).0
    }

    /// [`Tracer::refine`] and `1/|cos θ_n|` (θ_n: the angle between the ray and the triangle's
    /// normal), which is `≥ 1`, or +inf when the ray lies in the plane or the triangle is
    /// degenerate. MT's determinant is `-d·(e1×e2)`, so `|cos θ_n| = |det| / |e1×e2|`: no
    /// normalised normal, and no division beyond MT's `1/det`.
    #[inline]
    pub fn refine_with_sec(&self, o: DVec3, d: DVec3, tri: u32, t32: f32) -> (Hit, f64) {
        self.refine_with_sec_at(o, d, self.triangle_local(tri), tri, t32)
    }

    /// [`Tracer::refine_with_sec`] given the triangle's vertices (`triangle_local(tri)`), so a
    /// caller can fetch the vertices of many hits first and overlap their cache misses.
    #[inline]
    pub fn refine_with_sec_at(
        &self,
        o: DVec3,
        d: DVec3,
        [a, b, c]: [DVec3; 3],
        tri: u32,
        t32: f32,
    ) -> (Hit, f64) {
        let (e1, e2) = (b - a, c - a);
        let p = d.cross(e2);
        let det = e1.dot(p);
        let s = o - a;
        let q = s.cross(e1);
        let inv = 1.0 / det;
        let (t, u, v) = (e2.dot(q) * inv, s.dot(p) * inv, d.dot(q) * inv);
        let nn = e1.cross(e2).length();
        let sec = if nn > 0.0 && det != 0.0 {
            (nn * inv.abs()).max(1.0)
        } else {
            f64::INFINITY
        };
        if det != 0.0 && t.is_finite() && t > 0.0 && u.is_finite() && v.is_finite() {
            let h = Hit {
                t,
                triangle: tri,
                u,
                v,
            };
            return (h, sec);
        }
        (self.refine_in_plane(o, d, tri, t32), sec)
    }

    /// The ray lies in the triangle's plane, where the f64 intersection is undefined: keep the
    /// f32 distance and project for barycentrics.
    #[cold]
    fn refine_in_plane(&self, o: DVec3, d: DVec3, tri: u32, t32: f32) -> Hit {
        let [a, b, c] = self.triangle_local(tri);
        let (e1, e2) = (b - a, c - a);
        let t = t32 as f64;
        let w = o + t * d - a;
        let (d00, d01, d11) = (e1.dot(e1), e1.dot(e2), e2.dot(e2));
        let (d20, d21) = (w.dot(e1), w.dot(e2));
        let den = d00 * d11 - d01 * d01;
        let (u, v) = if den != 0.0 {
            ((d11 * d20 - d01 * d21) / den, (d00 * d21 - d01 * d20) / den)
        } else {
            (0.0, 0.0)
        };
        Hit {
            t,
            triangle: tri,
            u,
            v,
        }
    }

    /// Whether the 8-lane AVX traversal is used (detected at build; see [`Tracer::set_avx`]).
    pub fn avx(&self) -> bool {
        self.avx
    }

    /// Use (if the CPU has it) or avoid the AVX traversal. Results are bit-identical either way;
    /// this exists so tests can check that. Returns whether AVX is now used.
    pub fn set_avx(&mut self, enable: bool) -> bool {
        self.avx = enable && avx_detected();
        self.avx
    }

    /// Trace up to [`MAX_LANES`] local-frame f32 rays. Lane i: `(mesh triangle id, f32 distance)`
    /// of the closest hit (the lexicographic minimum of `(t, id)`, see the module docs) or `None`.
    pub fn trace(&self, p: &Packet, scratch: &mut Scratch) -> [Option<(u32, f32)>; MAX_LANES] {
        self.trace_leaves(p, scratch)
            .map(|h| h.map(|(j, t)| (self.tri_ids[j as usize], t)))
    }

    /// [`Tracer::trace`] with the hit triangle as its leaf-order index (see
    /// [`Tracer::leaf_triangle`], [`Tracer::leaf_local`]).
    /// Lanes are grouped by dominant axis and direction signs; each group is one traversal with
    /// one interval box test per node for the whole group, and triangle tests in SIMD chunks of
    /// 8 lanes with AVX, else 4 with SSE.
    pub fn trace_leaves(
        &self,
        p: &Packet,
        scratch: &mut Scratch,
    ) -> [Option<(u32, f32)>; MAX_LANES] {
        let mut best_t = [f32::INFINITY; MAX_LANES];
        let mut best_leaf = [u32::MAX; MAX_LANES];
        let Some(root) = self.root else {
            return [None; MAX_LANES];
        };
        if let Some(kz) = uniform_axis(p) {
            // Every lane valid and in one group (camera packets, almost always): trace `p` as it is.
            let (k, shared) = (permutation(kz), shared_origin(p));
            self.trace_group_dispatch(root, p, k, shared, &mut best_t, &mut best_leaf, scratch);
        } else {
            self.trace_groups(root, p, &mut best_t, &mut best_leaf, scratch);
        }
        std::array::from_fn(|i| (best_leaf[i] != u32::MAX).then(|| (best_leaf[i], best_t[i])))
    }

    /// [`Tracer::trace_leaves`] of a packet that is not one full group: lanes grouped by key
    /// (dominant axis, direction signs), one traversal per group.
    fn trace_groups(
        &self,
        root: u32,
        p: &Packet,
        best_t: &mut [f32; MAX_LANES],
        best_leaf: &mut [u32; MAX_LANES],
        scratch: &mut Scratch,
    ) {
        let mut keys = [0u32; MAX_LANES];
        let mut todo = 0u32;
        for i in 0..MAX_LANES {
            if p.active >> i & 1 != 0 {
                let d = p.dir(i);
                if let Some(kz) = ray_axis(p.origin(i), d) {
                    keys[i] = kz as u32
                        | (d[0].is_sign_negative() as u32) << 2
                        | (d[1].is_sign_negative() as u32) << 3
                        | (d[2].is_sign_negative() as u32) << 4;
                    todo |= 1 << i;
                }
            }
        }
        if todo == 0 {
            return;
        }
        let lead0 = todo.trailing_zeros() as usize;
        let o0 = p.origin(lead0).map(f32::to_bits);
        let shared =
            (0..MAX_LANES).all(|i| todo >> i & 1 == 0 || p.origin(i).map(f32::to_bits) == o0);
        let mut g = *p;
        while todo != 0 {
            let lead = todo.trailing_zeros() as usize;
            let mut group = 0u32;
            for i in 0..MAX_LANES {
                if todo >> i & 1 != 0 && keys[i] == keys[lead] {
                    group |= 1 << i;
                }
            }
            todo &= !group;
            // Every other lane holds the lead ray: all lanes are then valid rays of the group
            // (those lanes are never reported), and bounds over all lanes are the group's.
            g.active = group;
            for i in 0..MAX_LANES {
                let src = if group >> i & 1 != 0 { i } else { lead };
                g.copy_lane_from(i, p, src);
            }
            let k = permutation(keys[lead] as usize & 3);
            self.trace_group_dispatch(root, &g, k, shared, best_t, best_leaf, scratch);
        }
    }

    /// [`Tracer::trace_group`] with the lane width of this CPU and the shared-origin flag.
    // A hot kernel (inner loop of a step): its arguments are the buffers and sizes it works on,
    // llm.c style; kept as they are rather than re-measure its speed behind a struct.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn trace_group_dispatch(
        &self,
        root: u32,
        g: &Packet,
        k: [usize; 3],
        shared: bool,
        bt: &mut [f32; MAX_LANES],
        bi: &mut [u32; MAX_LANES],
        scratch: &mut Scratch,
    ) {
        let st = &mut scratch.stack;
        #[cfg(target_arch = "x86_64")]
        if self.avx {
            // SAFETY: `self.avx` is only true when the CPU reports AVX.
            unsafe {
                if shared {
                    self.trace_group_avx::<true>(root, g, k, bt, bi, st)
                } else {
                    self.trace_group_avx::<false>(root, g, k, bt, bi, st)
                }
            };
            return;
        }
        if shared {
            self.trace_group_sse::<true>(root, g, k, bt, bi, st);
        } else {
            self.trace_group_sse::<false>(root, g, k, bt, bi, st);
        }
    }

    #[inline(never)]
    fn trace_group_sse<const SHARED: bool>(
        &self,
        root: u32,
        g: &Packet,
        k: [usize; 3],
        best_t: &mut [f32; MAX_LANES],
        best_leaf: &mut [u32; MAX_LANES],
        stack: &mut Vec<(u32, f32)>,
    ) {
        self.trace_group::<F4, SHARED>(root, g, k, best_t, best_leaf, stack)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx")]
    #[inline(never)]
    unsafe fn trace_group_avx<const SHARED: bool>(
        &self,
        root: u32,
        g: &Packet,
        k: [usize; 3],
        best_t: &mut [f32; MAX_LANES],
        best_leaf: &mut [u32; MAX_LANES],
        stack: &mut Vec<(u32, f32)>,
    ) {
        self.trace_group::<F8, SHARED>(root, g, k, best_t, best_leaf, stack)
    }

    /// One traversal of a group: the lanes `g.active` share the permutation `k` and the
    /// direction signs, and every other lane holds a copy of one of them. Nodes are tested once
    /// for the whole group (interval test), triangles in chunks of `L::N` lanes. `SHARED`: all
    /// rays have the same origin (camera rays); vertex translations are then scalar (same IEEE
    /// results).
    #[inline(always)]
    fn trace_group<L: Lanes, const SHARED: bool>(
        &self,
        root: u32,
        g: &Packet,
        k: [usize; 3],
        best_t: &mut [f32; MAX_LANES],
        best_leaf: &mut [u32; MAX_LANES],
        stack: &mut Vec<(u32, f32)>,
    ) {
        let n = L::N;
        let active = g.active;
        let chunks = (32 - active.leading_zeros() as usize).div_ceil(n);
        let first = RayLanes::<L>::new(g, 0, k);
        let mut rl: [RayLanes<'_, L>; MAX_LANES / 4] = [first; MAX_LANES / 4];
        for (c, r) in rl.iter_mut().enumerate().take(chunks).skip(1) {
            *r = RayLanes::<L>::new(g, c * n, k);
        }
        let ia = GroupBounds::new::<SHARED>(g);
        // The group's closest distances, -inf in the other lanes (they never bound a box).
        let mut bt = [f32::NEG_INFINITY; MAX_LANES];
        for i in 0..MAX_LANES {
            if active >> i & 1 != 0 {
                bt[i] = best_t[i];
            }
        }
        let tmax_hi_of = |bt: &[f32; MAX_LANES]| {
            let mut m = L::load(bt);
            for c in 1..MAX_LANES / n {
                m = m.max(L::load(&bt[c * n..]));
            }
            m.hmax()
        };
        let mut tmax_hi = tmax_hi_of(&bt);

        stack.clear();
        stack.push((root, 0.0));
        while let Some((mut r, tn_entry)) = stack.pop() {
            if tn_entry > tmax_hi * SLAB_SCALE {
                continue;
            }
            loop {
                if r & LEAF_BIT != 0 {
                    if self.leaf_hits::<L, SHARED>(r, &rl[..chunks], active, &mut bt, best_leaf) {
                        tmax_hi = tmax_hi_of(&bt);
                    }
                    break;
                }
                match visit_children::<L>(&self.nodes[r as usize], &ia, tmax_hi, stack) {
                    Some(c) => r = c,
                    None => break,
                }
            }
        }
        for i in 0..MAX_LANES {
            if active >> i & 1 != 0 {
                best_t[i] = bt[i];
            }
        }
    }

    /// Test the triangles of leaf `r` against the group's active lanes (`rl[c]`: lanes
    /// `c·L::N ..`), keeping each lane's closest hit in `bt` / `best_leaf`; whether one changed.
    #[inline(always)]
    fn leaf_hits<L: Lanes, const SHARED: bool>(
        &self,
        r: u32,
        rl: &[RayLanes<'_, L>],
        active: u32,
        bt: &mut [f32; MAX_LANES],
        best_leaf: &mut [u32; MAX_LANES],
    ) -> bool {
        let n = L::N;
        let lane_mask = (1u32 << n) - 1;
        let first = (r & (MAX_TRIANGLES as u32 - 1)) as usize;
        let count = ((r >> 27) & 15) as usize + 1;
        let mut changed = false;
        for j in first..first + count {
            for (c, rlc) in rl.iter().enumerate() {
                let ca = (active >> (c * n)) & lane_mask;
                if ca == 0 {
                    continue;
                }
                let (hits, t) = intersect_lanes::<L, SHARED>(rlc, &self.tris[j], ca);
                if hits != 0 {
                    let mut ta = [0.0f32; MAX_LANES];
                    t.store(&mut ta);
                    let mut h = hits;
                    while h != 0 {
                        let i = h.trailing_zeros() as usize;
                        h &= h - 1;
                        let l = c * n + i;
                        // Ties go to the smaller mesh id (module docs; the ids are only read
                        // then). No hit yet ranks as (inf, u32::MAX): an f32 distance can
                        // overflow to inf.
                        let b = best_leaf[l];
                        if ta[i] < bt[l]
                            || (ta[i] == bt[l]
                                && (b == u32::MAX || self.tri_ids[j] < self.tri_ids[b as usize]))
                        {
                            bt[l] = ta[i];
                            best_leaf[l] = j as u32;
                            changed = true;
                        }
                    }
                }
            }
        }
        changed
    }
}

/// The children of node `nd` some lane of the group can hit (interval test of the whole group
/// against all children at once, module docs: a child is skipped only if no lane can hit it):
/// all but the nearest pushed on `stack` (nearest last), the nearest returned to descend into;
/// `None` when there is none.
#[inline(always)]
fn visit_children<L: Lanes>(
    nd: &Node,
    ia: &GroupBounds,
    tmax_hi: f32,
    stack: &mut Vec<(u32, f32)>,
) -> Option<u32> {
    let (lo, mut bits) = ia.test::<L>(nd, tmax_hi);
    let mut hit = [(0u32, 0.0f32); WIDTH];
    let mut nh = 0;
    while bits != 0 {
        let c = bits.trailing_zeros() as usize;
        bits &= bits - 1;
        hit[nh] = (nd.child[c], lo[c]);
        nh += 1;
    }
    match nh {
        0 => None,
        1 => Some(hit[0].0),
        _ => {
            // Sort by entry distance, nearest last (insertion sort, ≤ WIDTH); push all but the
            // nearest, descend into it.
            for a in 1..nh {
                let x = hit[a];
                let mut b = a;
                while b > 0 && hit[b - 1].1 < x.1 {
                    hit[b] = hit[b - 1];
                    b -= 1;
                }
                hit[b] = x;
            }
            stack.extend_from_slice(&hit[..nh - 1]);
            Some(hit[nh - 1].0)
        }
    }
}

const ALL_LANES: u32 = u32::MAX >> (32 - MAX_LANES);

/// When every lane of `p` is active and a valid ray ([`ray_axis`] is `Some`), and all lanes share
/// the dominant axis and the direction signs (one traversal group): that axis. Exactly the
/// per-lane [`ray_axis`] / `dominant_axis` decisions, four lanes at a time.
#[inline]
fn uniform_axis(p: &Packet) -> Option<usize> {
    if p.active != ALL_LANES {
        return None;
    }
    let (mut ok, mut k0, mut k1) = (0u32, 0u32, 0u32);
    let mut sign = [0u32; 3];
    let (zero, inf) = (F4::splat(0.0), F4::splat(f32::INFINITY));
    for c in 0..MAX_LANES / 4 {
        let lanes = |x: &[f32; MAX_LANES]| F4::load(&x[c * 4..]);
        let d = [lanes(&p.dir[0]), lanes(&p.dir[1]), lanes(&p.dir[2])];
        let a = d.map(F4::abs);
        // Finite: |x| < inf (false for NaN), for the direction and the origin.
        let mut fin = a[0].lt(inf).and(a[1].lt(inf)).and(a[2].lt(inf));
        for o in &p.origin {
            fin = fin.and(lanes(o).abs().lt(inf));
        }
        // The dominant component is nonzero iff the largest |component| is.
        let nonzero = a[0].max(a[1]).max(a[2]).gt(zero);
        let sh = 4 * c;
        ok |= fin.and(nonzero).bits() << sh;
        k0 |= a[1].le(a[0]).and(a[2].le(a[0])).bits() << sh;
        k1 |= a[2].le(a[1]).bits() << sh;
        for (s, x) in sign.iter_mut().zip(&d) {
            *s |= x.sign_bits() << sh;
        }
    }
    let uniform = |m: u32| m == 0 || m == ALL_LANES;
    if ok != ALL_LANES || !sign.iter().all(|&m| uniform(m)) {
        return None;
    }
    match (k0, k1) {
        (ALL_LANES, _) => Some(0),
        (0, ALL_LANES) => Some(1),
        (0, 0) => Some(2),
        _ => None,
    }
}

/// Whether every lane of a full packet has lane 0's origin, bit for bit.
#[inline]
fn shared_origin(p: &Packet) -> bool {
    (0..3).all(|a| {
        let o0 = p.origin[a][0];
        let s0 = if o0.is_sign_negative() { 0xF } else { 0 };
        (0..MAX_LANES / 4).all(|c| {
            let o = F4::load(&p.origin[a][c * 4..]);
            o.eq(F4::splat(o0)).bits() == 0xF && o.sign_bits() == s0
        })
    })
}

/// The interval bounds of a traversal group for the box test (module docs, "Interval box
/// test"): per axis the smallest and largest origin coordinate and inverse direction over the
/// active lanes, and which box side is the near one.
struct GroupBounds {
    /// `[axis]`: smallest / largest origin coordinate (equal for a shared origin).
    o_lo: [f32; 3],
    o_hi: [f32; 3],
    /// `[axis]`: smallest / largest 1/d (±f32::MAX for a zero component).
    i_lo: [f32; 3],
    i_hi: [f32; 3],
    /// `[axis]`: 1 when the direction is negative (the near plane is the box maximum).
    near: [usize; 3],
    shared: bool,
}

impl GroupBounds {
    /// Bounds over every lane of `g` (its lanes outside the group hold copies of a group ray).
    fn new<const SHARED: bool>(g: &Packet) -> Self {
        // Four lanes at a time (the lanes are finite, so SSE min/max are the plain ones).
        let mut o_lo = [f32::INFINITY; 3];
        let mut o_hi = [f32::NEG_INFINITY; 3];
        let mut d_lo = [f32::INFINITY; 3];
        let mut d_hi = [f32::NEG_INFINITY; 3];
        for a in 0..3 {
            let lanes = |x: &[f32; MAX_LANES], c: usize| F4::load(&x[4 * c..]);
            let (mut dl, mut dh) = (lanes(&g.dir[a], 0), lanes(&g.dir[a], 0));
            let (mut ol, mut oh) = (lanes(&g.origin[a], 0), lanes(&g.origin[a], 0));
            for c in 1..MAX_LANES / 4 {
                let (d, o) = (lanes(&g.dir[a], c), lanes(&g.origin[a], c));
                (dl, dh) = (dl.min(d), dh.max(d));
                (ol, oh) = (ol.min(o), oh.max(o));
            }
            (d_lo[a], d_hi[a]) = (dl.hmin(), dh.hmax());
            (o_lo[a], o_hi[a]) = (ol.hmin(), oh.hmax());
        }
        // 1/d, with ±f32::MAX for a zero component (the slab products then never see 0·inf).
        // The group's components share their sign, where fl(1/d) is monotone decreasing (the
        // clamp keeps it so): the extreme inverses are those of the extreme components.
        let inv = |d: f32| {
            let x = 1.0 / d;
            if x.is_finite() {
                x
            } else {
                f32::MAX.copysign(d)
            }
        };
        GroupBounds {
            o_lo,
            o_hi,
            i_lo: d_hi.map(inv),
            i_hi: d_lo.map(inv),
            near: std::array::from_fn(|a| g.dir[a][0].is_sign_negative() as usize),
            shared: SHARED,
        }
    }

    /// Lower bounds of the entry distance over the group for the children of `nd`, and the
    /// children some lane may hit (bit c; `tmax_hi`: the largest current closest distance),
    /// `L::N` children at a time.
    #[inline(always)]
    fn test<L: Lanes>(&self, nd: &Node, tmax_hi: f32) -> ([f32; WIDTH], u32) {
        let mut lo_out = [0.0f32; WIDTH];
        let mut mask = 0u32;
        let s = L::splat;
        for h in (0..WIDTH).step_by(L::N) {
            let mut lo = s(0.0);
            let mut hi = s(tmax_hi);
            for a in 0..3 {
                let bn = L::load(&nd.b[self.near[a]][a][h..]);
                let bf = L::load(&nd.b[1 - self.near[a]][a][h..]);
                let (il, ih) = (s(self.i_lo[a]), s(self.i_hi[a]));
                // fl(b - o) is monotone in o and fl(r · i) in r and i: the group's extreme slab
                // distances are products of the extreme operands.
                let (n_lo, f_hi) = if self.shared {
                    let (rn, rf) = (bn - s(self.o_lo[a]), bf - s(self.o_lo[a]));
                    ((rn * il).min(rn * ih), (rf * il).max(rf * ih))
                } else {
                    let (rn0, rn1) = (bn - s(self.o_hi[a]), bn - s(self.o_lo[a]));
                    let (rf0, rf1) = (bf - s(self.o_hi[a]), bf - s(self.o_lo[a]));
                    (
                        (rn0 * il).min(rn0 * ih).min((rn1 * il).min(rn1 * ih)),
                        (rf0 * il).max(rf0 * ih).max((rf1 * il).max(rf1 * ih)),
                    )
                };
                lo = lo.max(n_lo);
                hi = hi.min(f_hi);
            }
            lo.store(&mut lo_out[h..]);
            mask |= lo.le(hi * s(SLAB_SCALE)).bits() << h;
        }
        (lo_out, mask)
    }
}

fn avx_detected() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::is_x86_feature_detected!("avx")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::raycast::triangle::dominant_axis;

    /// The four-lane `uniform_axis` / `shared_origin` agree with the scalar per-lane decisions,
    /// on packets built from a small set of awkward components (ties, ±0, subnormals, inf, NaN).
    #[test]
    fn uniform_axis_matches_scalar_keys() {
        let vals = [
            0.5f32,
            -0.5,
            0.0,
            -0.0,
            1e-40,
            0.3,
            -0.3,
            f32::INFINITY,
            f32::NAN,
        ];
        let mut s = 0x2545f4914f6cdd1du64;
        let mut next = |n: usize| {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s % n as u64) as usize
        };
        let mut seen = [0usize; 4];
        for case in 0..20_000 {
            let mut p = Packet::default();
            // Mostly one direction repeated (the uniform case), sometimes a few lanes changed.
            let base = [vals[next(7)], vals[next(7)], vals[next(7)]];
            let origin = [1.0f32, -2.0, if case % 5 == 0 { -0.0 } else { 0.0 }];
            for i in 0..MAX_LANES {
                let mut d = base;
                if next(4) == 0 {
                    d[next(3)] = vals[next(vals.len())];
                }
                let mut o = origin;
                if case % 7 == 0 && next(8) == 0 {
                    o[2] = if o[2].is_sign_negative() { 0.0 } else { -0.0 };
                }
                p.set(i, o, d);
            }
            if case % 11 == 0 {
                p.active &= !(1 << next(MAX_LANES));
            }
            // Scalar decision.
            let key = |i: usize| {
                let d = p.dir(i);
                ray_axis(p.origin(i), d).map(|kz| {
                    debug_assert_eq!(kz, dominant_axis(d));
                    (kz, d.map(f32::is_sign_negative))
                })
            };
            let k0 = key(0);
            let want =
                (p.active == ALL_LANES && k0.is_some() && (0..MAX_LANES).all(|i| key(i) == k0))
                    .then(|| k0.unwrap().0);
            assert_eq!(uniform_axis(&p), want, "case {case}: {p:?}");
            seen[want.map_or(3, |k| k)] += 1;
            let o0 = p.origin(0).map(f32::to_bits);
            let shared = (0..MAX_LANES).all(|i| p.origin(i).map(f32::to_bits) == o0);
            if p.origin(0).iter().all(|x| x.is_finite()) {
                assert_eq!(shared_origin(&p), shared, "case {case}");
            }
        }
        assert!(seen.iter().all(|&n| n > 100), "cases per outcome {seen:?}");
    }
}
