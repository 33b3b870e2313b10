//! Triangle meshes: load OBJ (via `tobj`, f64 positions) and PLY (own parser: `ascii`,
//! `binary_little_endian`, `binary_big_endian`), write PLY (binary little-endian, double
//! coordinates) and OBJ (shortest round-trip decimal). SPEC §3.
//!
//! Loading rules:
//! - Vertex coordinates must be finite; NaN/Inf is an error naming the file and the line (ASCII
//!   PLY, OBJ) or the vertex index (binary PLY).
//! - Polygons are fan-triangulated `(v0, vi, vi+1)`.
//! - Degenerate triangles are dropped and counted in [`MeshStats::dropped_degenerate`]: a
//!   repeated vertex index, or zero area in f64, meaning `|e1 × e2| <= 4ε·|e1|·|e2|` (the sine of
//!   the corner angle is below rounding level; this covers coincident and collinear corners).
//! - Face indices out of range, truncated files, element counts that disagree with the data and
//!   malformed headers are errors naming the file and the line or element.

use anyhow::{anyhow, bail, Context, Result};
use glam::DVec3;
use std::fs;
use std::io::{BufWriter, Write};
use std::path::Path;

/// A triangle mesh in world coordinates (f64, so georeferenced scenes keep their precision).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    pub vertices: Vec<DVec3>,
    /// Counter-clockwise or not: ray casting is two-sided.
    pub triangles: Vec<[u32; 3]>,
}

impl Mesh {
    /// Axis-aligned bounding box (min, max) of the vertices.
    pub fn bbox(&self) -> (DVec3, DVec3) {
        self.vertices.iter().fold(
            (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
            |(lo, hi), v| (lo.min(*v), hi.max(*v)),
        )
    }

    /// Length of the bounding-box diagonal.
    pub fn diagonal(&self) -> f64 {
        let (lo, hi) = self.bbox();
        (hi - lo).length()
    }

    /// Unit area-weighted vertex normals: the normalised sum of the normals `(b−a)×(c−a)` of the
    /// triangles using each vertex (zero for vertices no triangle uses).
    pub fn vertex_normals(&self) -> Vec<DVec3> {
        let mut n = vec![DVec3::ZERO; self.vertices.len()];
        for t in &self.triangles {
            let [a, b, c] = t.map(|i| self.vertices[i as usize]);
            let f = (b - a).cross(c - a);
            for &i in t {
                n[i as usize] += f;
            }
        }
        n.iter().map(|v| v.normalize_or_zero()).collect()
    }
}

/// What loading a mesh did besides producing it.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct MeshStats {
    /// Triangles dropped because they repeat an index or have zero area.
    pub dropped_degenerate: usize,
    /// Faces read from the file (before triangulation).
    pub faces: usize,
    /// Faces with more than 3 corners that were fan-triangulated.
    pub polygons_triangulated: usize,
    /// Faces with fewer than 3 corners (also counted in `dropped_degenerate`).
    pub short_faces: usize,
    /// OBJ: `v` lines in the file (tobj keeps only the vertices a face uses).
    pub vertex_lines: usize,
}

/// Load a mesh, dispatching on the extension (`.ply`, `.obj`, case-insensitive).
pub fn load_mesh(path: &Path) -> Result<(Mesh, MeshStats)> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(|e| e.to_ascii_lowercase());
    let (mesh, stats) = match ext.as_deref() {
        Some("ply") => load_ply(path)?,
        Some("obj") => load_obj(path)?,
        _ => bail!(
            "{}: unknown mesh format (expected a .ply or .obj file)",
            path.display()
        ),
    };
    if mesh.triangles.is_empty() {
        bail!(
            "{}: the mesh has no (non-degenerate) triangles ({} vertices, {} faces read, {} degenerate dropped){}",
            path.display(),
            mesh.vertices.len().max(stats.vertex_lines),
            stats.faces,
            stats.dropped_degenerate,
            if stats.faces == 0 { "; is it a point cloud?" } else { "" }
        );
    }
    Ok((mesh, stats))
}

/// True if the triangle is degenerate (see the module doc).
fn is_degenerate(v: &[DVec3], t: [u32; 3]) -> bool {
    if t[0] == t[1] || t[1] == t[2] || t[0] == t[2] {
        return true;
    }
    let (a, b, c) = (v[t[0] as usize], v[t[1] as usize], v[t[2] as usize]);
    let (e1, e2) = (b - a, c - a);
    let cross = e1.cross(e2).length();
    cross <= 4.0 * f64::EPSILON * e1.length() * e2.length()
}

/// Fan-triangulate one face (indices already range-checked) into `out`, updating `stats`.
fn push_face(vertices: &[DVec3], face: &[u32], out: &mut Vec<[u32; 3]>, stats: &mut MeshStats) {
    stats.faces += 1;
    if face.len() < 3 {
        stats.short_faces += 1;
        stats.dropped_degenerate += 1;
        return;
    }
    if face.len() > 3 {
        stats.polygons_triangulated += 1;
    }
    for i in 1..face.len() - 1 {
        let t = [face[0], face[i], face[i + 1]];
        if is_degenerate(vertices, t) {
            stats.dropped_degenerate += 1;
        } else {
            out.push(t);
        }
    }
}

// ---------------------------------------------------------------------------------------------
// OBJ
// ---------------------------------------------------------------------------------------------

/// Load an OBJ with `tobj` (triangulated, faces indexing positions only, so texture coordinates
/// and normals do not split vertices; materials are not read). All models are merged. tobj is built with `use_f64`, so coordinates are exact.
/// Note: tobj re-indexes vertices in order of first use by a face and drops unreferenced ones.
/// Polylines (`l`) and points (`p`) are not surface and are left out (tobj would make triangles
/// of an `l` line with three or more vertices); `f` lines with fewer than three corners are
/// counted as short faces, as in a PLY.
fn load_obj(path: &Path) -> Result<(Mesh, MeshStats)> {
    let bytes = fs::read(path).with_context(|| format!("{}: cannot read", path.display()))?;
    let mut stats = MeshStats::default();
    let text = obj_surface_lines(&String::from_utf8_lossy(&bytes), &mut stats);
    // tobj's own errors carry no line number: on any failure, re-scan the file ourselves to
    // name the line (bad numbers, non-finite coordinates, indices out of range).
    // One index per corner into the positions (not GPU_LOAD_OPTIONS's single index, which makes
    // a vertex per (position, texture coordinate, normal) triple: a textured export's corners
    // each have their own `vt`, and the mesh came apart into a triangle soup).
    let options = tobj::LoadOptions {
        single_index: false,
        ..tobj::GPU_LOAD_OPTIONS
    };
    let loaded = tobj::load_obj_buf(&mut std::io::Cursor::new(text.as_bytes()), &options, |_| {
        Ok(Default::default())
    });
    let (models, _materials) = match loaded {
        Ok(x) => x,
        Err(e) => {
            obj_diagnose(path)?;
            bail!("{}: cannot load OBJ: {e}", path.display());
        }
    };
    let any_non_finite = models
        .iter()
        .any(|m| m.mesh.positions.iter().any(|v| !v.is_finite()));
    if any_non_finite {
        obj_diagnose(path)?;
    }
    let mut mesh = Mesh::default();
    for m in &models {
        let base = mesh.vertices.len();
        let p = &m.mesh.positions;
        if p.len() % 3 != 0 || m.mesh.indices.len() % 3 != 0 {
            bail!(
                "{}: model '{}': malformed positions/indices from the OBJ parser",
                path.display(),
                m.name
            );
        }
        for (k, c) in p.chunks_exact(3).enumerate() {
            let v = DVec3::new(c[0], c[1], c[2]);
            if !v.is_finite() {
                bail!(
                    "{}: model '{}': vertex {k}: coordinate is not finite ({v})",
                    path.display(),
                    m.name
                );
            }
            mesh.vertices.push(v);
        }
        let nv = (mesh.vertices.len() - base) as u32;
        for (k, t) in m.mesh.indices.chunks_exact(3).enumerate() {
            if t.iter().any(|&i| i >= nv) {
                bail!(
                    "{}: model '{}': triangle {k}: vertex index out of range",
                    path.display(),
                    m.name
                );
            }
            let face = [t[0] + base as u32, t[1] + base as u32, t[2] + base as u32];
            push_face(&mesh.vertices, &face, &mut mesh.triangles, &mut stats);
        }
    }
    Ok((mesh, stats))
}

/// The OBJ text with its `l` and `p` lines, and `f` lines of fewer than three corners (counted
/// in `stats`), blanked; the line count stays, so tobj's and our line numbers agree.
fn obj_surface_lines(text: &str, stats: &mut MeshStats) -> String {
    let mut out = String::with_capacity(text.len());
    for line in text.lines() {
        let mut tok = line.split_whitespace();
        let keep = match tok.next() {
            Some("l") | Some("p") => false,
            Some("v") => {
                stats.vertex_lines += 1;
                true
            }
            Some("f") if tok.count() < 3 => {
                stats.faces += 1;
                stats.short_faces += 1;
                stats.dropped_degenerate += 1;
                false
            }
            _ => true,
        };
        if keep {
            out.push_str(line);
        }
        out.push('\n');
    }
    out
}

/// Scan an OBJ for `v` lines with missing/non-numeric/non-finite coordinates and `f` lines with
/// out-of-range indices, to report them with a line number.
fn obj_diagnose(path: &Path) -> Result<()> {
    let text = fs::read(path).with_context(|| format!("{}: cannot read", path.display()))?;
    let text = String::from_utf8_lossy(&text);
    let mut nv: i64 = 0;
    for (ln, line) in text.lines().enumerate() {
        let ln = ln + 1;
        let mut tok = line.split_whitespace();
        match tok.next() {
            Some("v") => {
                nv += 1;
                for axis in ["x", "y", "z"] {
                    let s = tok.next().ok_or_else(|| {
                        anyhow!(
                            "{}: line {ln}: vertex {}: missing {axis} coordinate",
                            path.display(),
                            nv - 1
                        )
                    })?;
                    let x: f64 = s.parse().map_err(|_| {
                        anyhow!(
                            "{}: line {ln}: vertex {}: {axis} coordinate '{s}' is not a number",
                            path.display(),
                            nv - 1
                        )
                    })?;
                    if !x.is_finite() {
                        bail!(
                            "{}: line {ln}: vertex {}: {axis} coordinate is {s} (must be finite)",
                            path.display(),
                            nv - 1
                        );
                    }
                }
            }
            Some("f") => {
                for s in tok {
                    let first = s.split('/').next().unwrap_or("");
                    let i: i64 = first.parse().map_err(|_| {
                        anyhow!(
                            "{}: line {ln}: face index '{s}' is not an integer",
                            path.display()
                        )
                    })?;
                    // OBJ indices are 1-based; negative ones count back from the last vertex.
                    let ok = if i > 0 { i <= nv } else { i < 0 && -i <= nv };
                    if !ok {
                        bail!(
                            "{}: line {ln}: face index {i} out of range (1..={nv} vertices defined so far)",
                            path.display()
                        );
                    }
                }
            }
            _ => {}
        }
    }
    Ok(())
}

/// Write an OBJ: `v x y z` with Rust's `{}` for f64 (shortest string that parses back to the
/// same value) and 1-based `f a b c`.
pub fn write_obj(path: &Path, mesh: &Mesh) -> Result<()> {
    crate::io::atomic::write_atomic(path, false, |tmp| write_obj_to(tmp, path, mesh))
}

/// [`write_obj`]'s body: writes `tmp`, names `path` in errors.
fn write_obj_to(tmp: &Path, path: &Path, mesh: &Mesh) -> Result<()> {
    let f = fs::File::create(tmp).with_context(|| format!("{}: cannot create", path.display()))?;
    let mut w = BufWriter::new(f);
    let err = |e: std::io::Error| anyhow!("{}: write failed: {e}", path.display());
    writeln!(w, "# written by xscale").map_err(err)?;
    for v in &mesh.vertices {
        writeln!(w, "v {} {} {}", v.x, v.y, v.z).map_err(err)?;
    }
    for t in &mesh.triangles {
        writeln!(w, "f {} {} {}", t[0] + 1, t[1] + 1, t[2] + 1).map_err(err)?;
    }
    w.flush().map_err(err)?;
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// PLY
// ---------------------------------------------------------------------------------------------

/// Write a binary little-endian PLY: `double x,y,z` vertices and `uchar`-counted `uint`
/// `vertex_indices` triangles. Lossless for f64 coordinates.
pub fn write_ply(path: &Path, mesh: &Mesh) -> Result<()> {
    crate::io::atomic::write_atomic(path, false, |tmp| write_ply_to(tmp, path, mesh))
}

/// [`write_ply`]'s body: writes `tmp`, names `path` in errors.
fn write_ply_to(tmp: &Path, path: &Path, mesh: &Mesh) -> Result<()> {
    let f = fs::File::create(tmp).with_context(|| format!("{}: cannot create", path.display()))?;
    let mut w = BufWriter::new(f);
    let err = |e: std::io::Error| anyhow!("{}: write failed: {e}", path.display());
    write!(
        w,
        "ply\nformat binary_little_endian 1.0\ncomment written by xscale\n\
         element vertex {}\nproperty double x\nproperty double y\nproperty double z\n\
         element face {}\nproperty list uchar uint vertex_indices\nend_header\n",
        mesh.vertices.len(),
        mesh.triangles.len()
    )
    .map_err(err)?;
    for v in &mesh.vertices {
        for c in [v.x, v.y, v.z] {
            w.write_all(&c.to_le_bytes()).map_err(err)?;
        }
    }
    for t in &mesh.triangles {
        w.write_all(&[3u8]).map_err(err)?;
        for i in t {
            w.write_all(&i.to_le_bytes()).map_err(err)?;
        }
    }
    w.flush().map_err(err)?;
    Ok(())
}

/// PLY scalar types.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    fn parse(s: &str) -> Option<Scalar> {
        Some(match s {
            "char" | "int8" => Scalar::I8,
            "uchar" | "uint8" => Scalar::U8,
            "short" | "int16" => Scalar::I16,
            "ushort" | "uint16" => Scalar::U16,
            "int" | "int32" => Scalar::I32,
            "uint" | "uint32" => Scalar::U32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return None,
        })
    }
    fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }
    fn is_float(self) -> bool {
        matches!(self, Scalar::F32 | Scalar::F64)
    }
    /// Decode from exactly `size()` bytes.
    fn read(self, b: &[u8], big: bool) -> f64 {
        macro_rules! rd {
            ($t:ty, $n:expr) => {{
                let a: [u8; $n] = b[..$n].try_into().unwrap();
                (if big {
                    <$t>::from_be_bytes(a)
                } else {
                    <$t>::from_le_bytes(a)
                }) as f64
            }};
        }
        match self {
            Scalar::I8 => b[0] as i8 as f64,
            Scalar::U8 => b[0] as f64,
            Scalar::I16 => rd!(i16, 2),
            Scalar::U16 => rd!(u16, 2),
            Scalar::I32 => rd!(i32, 4),
            Scalar::U32 => rd!(u32, 4),
            Scalar::F32 => rd!(f32, 4),
            Scalar::F64 => rd!(f64, 8),
        }
    }
}

#[derive(Clone, Debug)]
enum PropKind {
    Scalar(Scalar),
    List { count: Scalar, item: Scalar },
}

#[derive(Clone, Debug)]
struct Property {
    name: String,
    kind: PropKind,
}

#[derive(Clone, Debug)]
struct Element {
    name: String,
    count: usize,
    props: Vec<Property>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum PlyFormat {
    Ascii,
    BinaryLe,
    BinaryBe,
}

struct Header {
    format: PlyFormat,
    elements: Vec<Element>,
    /// Byte offset of the body.
    body: usize,
    /// Number of header lines (the body's first ASCII line is `lines + 1`).
    lines: usize,
}

fn parse_header(path: &Path, data: &[u8]) -> Result<Header> {
    let p = path.display();
    let mut pos = 0usize;
    let mut line_no = 0usize;
    let mut format = None;
    let mut elements: Vec<Element> = Vec::new();
    loop {
        let end = data[pos..]
            .iter()
            .position(|&c| c == b'\n')
            .ok_or_else(|| {
                anyhow!("{p}: bad PLY header: no 'end_header' line (file truncated?)")
            })?;
        let raw = &data[pos..pos + end];
        pos += end + 1;
        line_no += 1;
        let line = std::str::from_utf8(raw)
            .map_err(|_| anyhow!("{p}: line {line_no}: bad PLY header: not text"))?
            .trim_end_matches('\r');
        let tok: Vec<&str> = line.split_whitespace().collect();
        if line_no == 1 {
            if line.trim() != "ply" {
                bail!("{p}: line 1: bad PLY header: expected 'ply', found '{line}'");
            }
            continue;
        }
        let bad = |what: &str| anyhow!("{p}: line {line_no}: bad PLY header: {what} in '{line}'");
        match tok.first().copied() {
            None => continue,
            Some("comment") | Some("obj_info") => continue,
            Some("format") => {
                if tok.len() != 3 {
                    return Err(bad("expected 'format <kind> 1.0'"));
                }
                format = Some(match tok[1] {
                    "ascii" => PlyFormat::Ascii,
                    "binary_little_endian" => PlyFormat::BinaryLe,
                    "binary_big_endian" => PlyFormat::BinaryBe,
                    _ => return Err(bad("unknown format")),
                });
            }
            Some("element") => {
                if tok.len() != 3 {
                    return Err(bad("expected 'element <name> <count>'"));
                }
                let count: usize = tok[2]
                    .parse()
                    .map_err(|_| bad("element count is not a non-negative integer"))?;
                elements.push(Element {
                    name: tok[1].to_string(),
                    count,
                    props: Vec::new(),
                });
            }
            Some("property") => {
                let el = elements
                    .last_mut()
                    .ok_or_else(|| bad("'property' before any 'element'"))?;
                let prop = if tok.get(1) == Some(&"list") {
                    if tok.len() != 5 {
                        return Err(bad(
                            "expected 'property list <count type> <item type> <name>'",
                        ));
                    }
                    let count =
                        Scalar::parse(tok[2]).ok_or_else(|| bad("unknown list count type"))?;
                    let item =
                        Scalar::parse(tok[3]).ok_or_else(|| bad("unknown list item type"))?;
                    if count.is_float() {
                        return Err(bad("list count type must be an integer type"));
                    }
                    Property {
                        name: tok[4].to_string(),
                        kind: PropKind::List { count, item },
                    }
                } else {
                    if tok.len() != 3 {
                        return Err(bad("expected 'property <type> <name>'"));
                    }
                    let s = Scalar::parse(tok[1]).ok_or_else(|| bad("unknown property type"))?;
                    Property {
                        name: tok[2].to_string(),
                        kind: PropKind::Scalar(s),
                    }
                };
                el.props.push(prop);
            }
            Some("end_header") => break,
            Some(_) => return Err(bad("unknown keyword")),
        }
    }
    let format = format.ok_or_else(|| anyhow!("{p}: bad PLY header: no 'format' line"))?;
    Ok(Header {
        format,
        elements,
        body: pos,
        lines: line_no,
    })
}

/// Where the interesting properties of the vertex and face elements are.
struct Layout {
    /// Property index of x, y, z in the vertex element.
    xyz: [usize; 3],
    /// Property index of the index list in the face element (if there is a face element).
    face_list: Option<usize>,
}

fn layout(path: &Path, h: &Header) -> Result<Layout> {
    let p = path.display();
    let vertex = h
        .elements
        .iter()
        .find(|e| e.name == "vertex")
        .ok_or_else(|| anyhow!("{p}: bad PLY header: no 'element vertex'"))?;
    let mut xyz = [usize::MAX; 3];
    for (k, axis) in ["x", "y", "z"].iter().enumerate() {
        xyz[k] = vertex
            .props
            .iter()
            .position(|pr| pr.name == *axis)
            .ok_or_else(|| anyhow!("{p}: bad PLY header: vertex has no property '{axis}'"))?;
        if matches!(vertex.props[xyz[k]].kind, PropKind::List { .. }) {
            bail!("{p}: bad PLY header: vertex property '{axis}' is a list");
        }
    }
    let face_list = match h.elements.iter().find(|e| e.name == "face") {
        None => None,
        Some(face) => {
            let i = face
                .props
                .iter()
                .position(|pr| pr.name == "vertex_indices" || pr.name == "vertex_index")
                .ok_or_else(|| {
                    anyhow!("{p}: bad PLY header: face has no list property 'vertex_indices' or 'vertex_index'")
                })?;
            match face.props[i].kind {
                PropKind::List { item, .. } if !item.is_float() => {}
                _ => bail!(
                    "{p}: bad PLY header: face property '{}' must be a list of integers",
                    face.props[i].name
                ),
            }
            Some(i)
        }
    };
    Ok(Layout { xyz, face_list })
}

/// The vertices of a PLY file, faces or none (a point cloud such as nerfstudio's
/// `sparse_pc.ply`); the reader refuses non-finite coordinates.
pub fn load_ply_points(path: &Path) -> Result<Vec<DVec3>> {
    Ok(load_ply(path)?.0.vertices)
}

fn load_ply(path: &Path) -> Result<(Mesh, MeshStats)> {
    let data = fs::read(path).with_context(|| format!("{}: cannot read", path.display()))?;
    let h = parse_header(path, &data)?;
    let lay = layout(path, &h)?;
    match h.format {
        PlyFormat::Ascii => load_ply_ascii(path, &data, &h, &lay),
        PlyFormat::BinaryLe => load_ply_binary(path, &data, &h, &lay, false),
        PlyFormat::BinaryBe => load_ply_binary(path, &data, &h, &lay, true),
    }
}

/// Vertex coordinate `axis` (0..3) read as `v`, which must be finite; `at` builds the row's
/// place (`line 12: vertex 3`) only on failure.
#[inline]
fn finite_coordinate(path: &Path, at: impl Fn() -> String, axis: usize, v: f64) -> Result<f64> {
    if !v.is_finite() {
        bail!(
            "{}: {}: coordinate {} is {v} (must be finite)",
            path.display(),
            at(),
            ["x", "y", "z"][axis]
        );
    }
    Ok(v)
}

/// Range-check a face index; `where_` builds the error location only on failure.
#[inline]
fn check_index(path: &Path, where_: impl Fn() -> String, i: f64, nv: usize) -> Result<u32> {
    if !(i >= 0.0 && i < nv as f64) || i.fract() != 0.0 {
        bail!(
            "{}: {}: vertex index {i} out of range (0..{nv})",
            path.display(),
            where_()
        );
    }
    Ok(i as u32)
}

/// A PLY file's rows assembled into a mesh. Faces listed before the vertex element wait until
/// the vertices are read (the degenerate-triangle test needs them).
#[derive(Default)]
struct PlyMesh {
    mesh: Mesh,
    stats: MeshStats,
    faces_pending: Vec<Vec<u32>>,
    vertex_seen: bool,
}

impl PlyMesh {
    fn face(&mut self, face: &[u32]) {
        if self.vertex_seen {
            push_face(
                &self.mesh.vertices,
                face,
                &mut self.mesh.triangles,
                &mut self.stats,
            );
        } else {
            self.faces_pending.push(face.to_vec());
        }
    }

    /// The vertex element has been read: triangulate the faces that were waiting.
    fn vertices_done(&mut self) {
        self.vertex_seen = true;
        for f in std::mem::take(&mut self.faces_pending) {
            push_face(
                &self.mesh.vertices,
                &f,
                &mut self.mesh.triangles,
                &mut self.stats,
            );
        }
    }
}

fn load_ply_ascii(path: &Path, data: &[u8], h: &Header, lay: &Layout) -> Result<(Mesh, MeshStats)> {
    let p = path.display();
    let body = std::str::from_utf8(&data[h.body..])
        .map_err(|_| anyhow!("{p}: ASCII PLY body is not valid UTF-8 text"))?;
    let mut lines = body.lines().enumerate().map(|(i, l)| (i + h.lines + 1, l));
    let mut out = PlyMesh::default();
    let mut face_buf: Vec<u32> = Vec::new();
    let nv_decl = declared_vertices(h);
    for el in &h.elements {
        let is_vertex = el.name == "vertex";
        let is_face = el.name == "face";
        for k in 0..el.count {
            // Next non-blank line.
            let Some((ln, line)) = lines.find(|(_, l)| !l.trim().is_empty()) else {
                bail!(
                    "{p}: truncated: file ends in element '{}' at {} {k} of {} declared",
                    el.name,
                    el.name,
                    el.count
                );
            };
            let mut vals = [0.0f64; 3];
            face_buf.clear();
            let row = AsciiRow {
                path,
                el,
                k,
                ln,
                tokens: line.split_whitespace().collect(),
            };
            row.read(lay, nv_decl, &mut vals, &mut face_buf)?;
            if is_vertex {
                out.mesh.vertices.push(DVec3::from_array(vals));
            }
            if is_face {
                out.face(&face_buf);
            }
        }
        if is_vertex {
            out.vertices_done();
        }
    }
    if let Some((ln, _)) = lines.find(|(_, l)| !l.trim().is_empty()) {
        bail!("{p}: line {ln}: extra data after the last declared element (element counts in the header too small?)");
    }
    Ok((out.mesh, out.stats))
}

/// The vertex count the header declares (0 without a vertex element).
fn declared_vertices(h: &Header) -> usize {
    h.elements
        .iter()
        .find(|e| e.name == "vertex")
        .map(|e| e.count)
        .unwrap_or(0)
}

/// Row `k` of element `el` of an ASCII PLY, at file line `ln`, split into its values.
struct AsciiRow<'a> {
    path: &'a Path,
    el: &'a Element,
    k: usize,
    ln: usize,
    tokens: Vec<&'a str>,
}

impl AsciiRow<'_> {
    /// The row's vertex coordinates into `vals` and its face's indices (checked against `nv`
    /// vertices) into `face`, where `lay` says they are; every value must be a number and the
    /// row must hold exactly the header's properties.
    fn read(
        &self,
        lay: &Layout,
        nv: usize,
        vals: &mut [f64; 3],
        face: &mut Vec<u32>,
    ) -> Result<()> {
        let (p, el, k, ln) = (self.path.display(), self.el, self.k, self.ln);
        let is_vertex = el.name == "vertex";
        let is_face = el.name == "face";
        let mut t = 0usize;
        for (pi, prop) in el.props.iter().enumerate() {
            let mut next = |count: bool| -> Result<f64> {
                let v = self.value(t, &prop.name, count);
                t += 1;
                v
            };
            match prop.kind {
                PropKind::Scalar(_) => {
                    let v = next(false)?;
                    if is_vertex {
                        if let Some(axis) = lay.xyz.iter().position(|&x| x == pi) {
                            let at = || format!("line {ln}: vertex {k}");
                            vals[axis] = finite_coordinate(self.path, at, axis, v)?;
                        }
                    }
                }
                PropKind::List { .. } => {
                    let n = next(true)?;
                    if n.is_nan() || n < 0.0 || n.fract() != 0.0 {
                        bail!("{p}: line {ln}: {} {k}: bad list count {n}", el.name);
                    }
                    let take_face = is_face && lay.face_list == Some(pi);
                    for _ in 0..n as usize {
                        let v = next(false)?;
                        if take_face {
                            face.push(check_index(
                                self.path,
                                || format!("line {ln}: face {k}"),
                                v,
                                nv,
                            )?);
                        }
                    }
                }
            }
        }
        if t != self.tokens.len() {
            bail!(
                "{p}: line {ln}: {} {k}: {} values, expected {t} (header and data disagree)",
                el.name,
                self.tokens.len()
            );
        }
        Ok(())
    }

    /// Value `t` of the row, a number, for property `name` (its list's count with `count`).
    fn value(&self, t: usize, name: &str, count: bool) -> Result<f64> {
        let (p, el, k, ln) = (self.path.display(), self.el, self.k, self.ln);
        let what = || {
            if count {
                format!("{name} count")
            } else {
                name.to_string()
            }
        };
        let s = self.tokens.get(t).ok_or_else(|| {
            anyhow!(
                "{p}: line {ln}: {} {k}: too few values (missing {}; header count or data wrong?)",
                el.name,
                what()
            )
        })?;
        s.parse::<f64>().map_err(|_| {
            anyhow!(
                "{p}: line {ln}: {} {k}: '{s}' is not a number ({})",
                el.name,
                what()
            )
        })
    }
}

fn load_ply_binary(
    path: &Path,
    data: &[u8],
    h: &Header,
    lay: &Layout,
    big: bool,
) -> Result<(Mesh, MeshStats)> {
    let p = path.display();
    let mut body = BinaryBody {
        path,
        data,
        pos: h.body,
        big,
    };
    let mut out = PlyMesh::default();
    let nv_decl = declared_vertices(h);
    let mut face_buf: Vec<u32> = Vec::new();
    for el in &h.elements {
        let is_vertex = el.name == "vertex";
        let is_face = el.name == "face";
        if is_vertex {
            out.mesh.vertices.reserve(el.count.min(data.len() / 12));
        }
        // Fast path: an element of scalars only is a fixed-size record (vertices, usually).
        let scalars: Option<Vec<Scalar>> = el
            .props
            .iter()
            .map(|pr| match pr.kind {
                PropKind::Scalar(s) => Some(s),
                PropKind::List { .. } => None,
            })
            .collect();
        if let Some(types) = scalars {
            body.fixed_records(el, &types, lay, &mut out)?;
            continue;
        }
        for k in 0..el.count {
            let mut vals = [0.0f64; 3];
            face_buf.clear();
            body.row(el, k, lay, nv_decl, &mut vals, &mut face_buf)?;
            if is_vertex {
                out.mesh.vertices.push(DVec3::from_array(vals));
            }
            if is_face {
                out.face(&face_buf);
            }
        }
        if is_vertex {
            out.vertices_done();
        }
    }
    // Tolerate a trailing newline some writers add; anything more means the counts are wrong.
    let rest = &data[body.pos..];
    if rest.iter().any(|c| !c.is_ascii_whitespace()) {
        bail!(
            "{p}: {} bytes of extra data after the last declared element (element counts in the header too small?)",
            rest.len()
        );
    }
    Ok((out.mesh, out.stats))
}

/// A binary PLY's body as it is read: the bytes, the position reached, the byte order.
struct BinaryBody<'a> {
    path: &'a Path,
    data: &'a [u8],
    pos: usize,
    big: bool,
}

impl BinaryBody<'_> {
    /// Row `k` of element `el` (one with lists): its vertex coordinates into `vals` and its
    /// face's indices (checked against `nv` vertices) into `face`, where `lay` says they are;
    /// other lists are skipped.
    fn row(
        &mut self,
        el: &Element,
        k: usize,
        lay: &Layout,
        nv: usize,
        vals: &mut [f64; 3],
        face: &mut Vec<u32>,
    ) -> Result<()> {
        let p = self.path.display();
        let is_vertex = el.name == "vertex";
        let is_face = el.name == "face";
        for (pi, prop) in el.props.iter().enumerate() {
            match prop.kind {
                PropKind::Scalar(s) => {
                    let v = self.read(s, el, k, &prop.name)?;
                    if is_vertex {
                        if let Some(axis) = lay.xyz.iter().position(|&x| x == pi) {
                            let at = || format!("vertex {k}");
                            vals[axis] = finite_coordinate(self.path, at, axis, v)?;
                        }
                    }
                }
                PropKind::List { count, item } => {
                    let n = self.read(count, el, k, &prop.name)?;
                    if n < 0.0 {
                        bail!("{p}: {} {k}: negative list count {n}", el.name);
                    }
                    let n = n as usize;
                    if is_face && lay.face_list == Some(pi) {
                        for _ in 0..n {
                            let v = self.read(item, el, k, &prop.name)?;
                            face.push(check_index(self.path, || format!("face {k}"), v, nv)?);
                        }
                    } else {
                        self.skip_list(n, item, el, k, &prop.name)?;
                    }
                }
            }
        }
        Ok(())
    }

    /// Binary PLY fast path: an element of scalars only (vertices, usually) is `count`
    /// fixed-size records of `types`; read past them, keeping a vertex element's coordinates.
    fn fixed_records(
        &mut self,
        el: &Element,
        types: &[Scalar],
        lay: &Layout,
        out: &mut PlyMesh,
    ) -> Result<()> {
        let (path, data, pos, big) = (self.path, self.data, self.pos, self.big);
        let p = path.display();
        let mut offs = Vec::with_capacity(types.len());
        let mut rec = 0usize;
        for t in types {
            offs.push(rec);
            rec += t.size();
        }
        // Overflow-checked: a declared count near usize::MAX / rec must be an error, not a wrap.
        let end = rec.checked_mul(el.count).and_then(|n| pos.checked_add(n));
        if end.is_none_or(|e| e > data.len()) {
            let k = (data.len() - pos) / rec.max(1);
            bail!(
                "{p}: truncated: file ends inside {} {k} of {} declared",
                el.name,
                el.count
            );
        }
        if el.name == "vertex" {
            for k in 0..el.count {
                let r = &data[pos + k * rec..pos + (k + 1) * rec];
                let mut v = [0f64; 3];
                for (axis, (c, &pi)) in v.iter_mut().zip(&lay.xyz).enumerate() {
                    let x = types[pi].read(&r[offs[pi]..], big);
                    *c = finite_coordinate(path, || format!("vertex {k}"), axis, x)?;
                }
                out.mesh.vertices.push(DVec3::from_array(v));
            }
            out.vertices_done();
        }
        self.pos = pos + rec * el.count;
        Ok(())
    }

    /// The next value, of type `s` (row `k` of `el`, property `prop` in errors).
    fn read(&mut self, s: Scalar, el: &Element, k: usize, prop: &str) -> Result<f64> {
        let n = s.size();
        if self.pos + n > self.data.len() {
            bail!(
                "{}: truncated: file ends inside {} {k} of {} declared (property '{prop}')",
                self.path.display(),
                el.name,
                el.count
            );
        }
        let v = s.read(&self.data[self.pos..self.pos + n], self.big);
        self.pos += n;
        Ok(v)
    }

    /// Past a list of `n` values of type `item` (overflow-checked: the count is read from the
    /// file).
    fn skip_list(
        &mut self,
        n: usize,
        item: Scalar,
        el: &Element,
        k: usize,
        list: &str,
    ) -> Result<()> {
        let end = n
            .checked_mul(item.size())
            .and_then(|b| self.pos.checked_add(b));
        match end {
            Some(e) if e <= self.data.len() => {
                self.pos = e;
                Ok(())
            }
            _ => bail!(
                "{}: truncated: file ends inside {} {k} of {} declared (list '{list}')",
                self.path.display(),
                el.name,
                el.count
            ),
        }
    }
}

pub use super::remesh::{decimate, decimate_report, subdivide, DecimateReport};
