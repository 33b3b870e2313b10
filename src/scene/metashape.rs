//! Agisoft Metashape's camera export (`File → Export → Export Cameras…`, "Agisoft XML"): the tool
//! the paper's GigaNVS poses come from ("calculated by Agisoft Metashape", §5). A scene dir holds
//! `cameras.xml` (or a single other `*.xml` export), the photos in `images/` and the mesh.
//!
//! ```text
//! <document version="…">
//!   <chunk label="…">
//!     <sensors> <sensor id="0" type="frame">
//!         <resolution width="W" height="H"/>
//!         <calibration class="adjusted"> <f/> <cx/> <cy/> <b1/> <b2/> <k1/>…<k4/> <p1/> <p2/> </calibration>
//!     </sensor> </sensors>
//!     <components> <component id="0"> <transform> <rotation/> <translation/> <scale/> </transform> … </components>
//!     <cameras> [<group>] <camera id="0" sensor_id="0" component_id="0" label="IMG_0001">
//!         <transform>16 numbers, camera → component, row-major</transform> </camera> … </cameras>
//!     <transform> <rotation/> <translation/> <scale/> </transform>   (chunk → world; version 1.x)
//!     <reference>LOCAL_CS[…] | GEOGCS[…] | PROJCS[…]</reference>
//! ```
//!
//! Cameras (x right, y down, z forward: OpenCV's axes) are placed in the chunk's world frame: a
//! camera's transform, then its component's similarity `x → s·R·x + t` (Metashape 2), then the
//! chunk's (Metashape 1), each where present. A georeferenced chunk's world frame is geocentric
//! (EPSG:4978); the mesh must be exported in that frame (see [`georeference_note`]).
//!
//! Intrinsics (the manual's Appendix C): `u = W/2 + cx + x'(f + b1) + y'·b2`, `v = H/2 + cy +
//! y'·f`, with `(x', y')` the distorted point of [`Distortion::Brown`] (frame sensors) or of the
//! equidistant fisheye plane (fisheye sensors, [`Distortion::ThinPrismFisheye`] without prism
//! terms). Metashape's P1 multiplies `r² + 2x²`, which is OpenCV's `p2`: the two are swapped on
//! reading. Views are sorted by photo file name, as the other layouts' are.

use super::camera::Intrinsics;
use super::transforms::not_a_rotation;
use super::{Distortion, View};
use anyhow::{anyhow, bail, Result};
use glam::{DMat3, DVec3};
use roxmltree::Node;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// The export's usual file name.
pub const FILE: &str = "cameras.xml";

/// The Metashape export in `dir`: `cameras.xml`, else the only `*.xml` there that is an Agisoft
/// document (its text holds `<document` and `<chunk`).
pub fn find(dir: &Path) -> Option<PathBuf> {
    let named = dir.join(FILE);
    if named.is_file() {
        return Some(named);
    }
    let mut found: Vec<PathBuf> = std::fs::read_dir(dir)
        .ok()?
        .flatten()
        .map(|e| e.path())
        .filter(|p| {
            p.is_file()
                && p.extension().is_some_and(|e| e.eq_ignore_ascii_case("xml"))
                && is_agisoft_xml(p)
        })
        .collect();
    (found.len() == 1).then(|| found.pop().unwrap())
}

/// Whether the file's first 64 KB look like an Agisoft XML document.
fn is_agisoft_xml(p: &Path) -> bool {
    use std::io::Read;
    let mut head = Vec::new();
    let ok = std::fs::File::open(p)
        .and_then(|f| f.take(1 << 16).read_to_end(&mut head))
        .is_ok();
    let text = String::from_utf8_lossy(&head);
    ok && text.contains("<document") && text.contains("<chunk")
}

/// What [`load`] read: the views and what the user should know (cameras left out, the frame).
pub struct Loaded {
    pub views: Vec<View>,
    pub notes: Vec<String>,
}

/// `x → s·R·x + t`.
#[derive(Clone, Copy, Debug)]
struct Similarity {
    r: DMat3,
    t: DVec3,
    s: f64,
}

impl Similarity {
    /// Whether two similarities are the same to rounding (the same one written twice).
    fn same_as(&self, o: &Similarity) -> bool {
        let tol = 1e-9;
        (self.s - o.s).abs() <= tol * self.s.abs().max(o.s.abs())
            && (self.r - o.r)
                .to_cols_array()
                .iter()
                .all(|d| d.abs() <= tol)
            && (self.t - o.t).length() <= tol * self.t.length().max(o.t.length()).max(1.0)
    }

    /// A camera→frame pose `(R_c, c)` carried into this similarity's target frame.
    fn apply(&self, (r_c, c): (DMat3, DVec3)) -> (DMat3, DVec3) {
        (self.r * r_c, self.s * (self.r * c) + self.t)
    }
}

/// The XML file and its text, for messages that name a line.
struct Source<'a> {
    path: &'a Path,
    doc: &'a roxmltree::Document<'a>,
}

impl Source<'_> {
    fn at(&self, n: Node) -> String {
        let pos = self.doc.text_pos_at(n.range().start);
        format!("{}:{}", self.path.display(), pos.row)
    }

    /// The numbers in an element's text.
    fn numbers(&self, n: Node, count: usize) -> Result<Vec<f64>> {
        let text = n.text().unwrap_or("");
        let v: Vec<f64> = text
            .split_whitespace()
            .map(|w| {
                w.parse::<f64>().map_err(|_| {
                    anyhow!(
                        "{}: <{}>: '{w}' is not a number",
                        self.at(n),
                        n.tag_name().name()
                    )
                })
            })
            .collect::<Result<_>>()?;
        if v.len() != count || v.iter().any(|x| !x.is_finite()) {
            bail!(
                "{}: <{}>: expected {count} finite numbers, found '{}'",
                self.at(n),
                n.tag_name().name(),
                text.trim()
            );
        }
        Ok(v)
    }

    /// The value of child `<name>` of `n`, or `None` when there is none.
    fn child_number(&self, n: Node, name: &str) -> Result<Option<f64>> {
        child(n, name)
            .map(|c| self.numbers(c, 1).map(|v| v[0]))
            .transpose()
    }

    /// An attribute parsed as a number.
    fn attr_number(&self, n: Node, name: &str) -> Result<f64> {
        let v = n.attribute(name).ok_or_else(|| {
            anyhow!(
                "{}: <{}> has no {name} attribute",
                self.at(n),
                n.tag_name().name()
            )
        })?;
        v.trim().parse::<f64>().map_err(|_| {
            anyhow!(
                "{}: <{}> {name}=\"{v}\" is not a number",
                self.at(n),
                n.tag_name().name()
            )
        })
    }

    /// A `<transform>` of rotation / translation / scale children (each optional), or of 16
    /// numbers (a 4×4 similarity, row-major).
    fn similarity(&self, n: Node) -> Result<Similarity> {
        if n.children().any(|c| c.is_element()) {
            let r = match child(n, "rotation") {
                Some(c) => row_major(&self.numbers(c, 9)?),
                None => DMat3::IDENTITY,
            };
            let t = match child(n, "translation") {
                Some(c) => DVec3::from_slice(&self.numbers(c, 3)?),
                None => DVec3::ZERO,
            };
            // Finite (`numbers` checks it), so `<= 0` is the whole test.
            let s = self.child_number(n, "scale")?.unwrap_or(1.0);
            if s <= 0.0 {
                bail!("{}: <scale> {s}: expected a positive number", self.at(n));
            }
            if let Some(what) = not_a_rotation(&r, 1e-6) {
                bail!("{}: <rotation> {what}", self.at(n));
            }
            return Ok(Similarity { r, t, s });
        }
        let (r_s, t) = self.matrix(n)?;
        let det = r_s.determinant();
        if det <= 0.0 {
            bail!(
                "{}: <transform> has determinant {det}: not a similarity",
                self.at(n)
            );
        }
        let s = det.cbrt();
        let r = r_s * (1.0 / s);
        if let Some(what) = not_a_rotation(&r, 1e-6) {
            bail!(
                "{}: <transform>: its 3×3 part over its scale {what}",
                self.at(n)
            );
        }
        Ok(Similarity { r, t, s })
    }

    /// A 4×4 row-major `<transform>`: its upper 3×3 and its translation; the last row must be
    /// `0 0 0 1`.
    fn matrix(&self, n: Node) -> Result<(DMat3, DVec3)> {
        let m = self.numbers(n, 16)?;
        if m[12..] != [0.0, 0.0, 0.0, 1.0] {
            bail!(
                "{}: <transform>: the last row must be 0 0 0 1, found {:?}",
                self.at(n),
                &m[12..]
            );
        }
        let r = row_major(&[m[0], m[1], m[2], m[4], m[5], m[6], m[8], m[9], m[10]]);
        Ok((r, DVec3::new(m[3], m[7], m[11])))
    }
}

fn row_major(v: &[f64]) -> DMat3 {
    DMat3::from_cols_array(&[v[0], v[3], v[6], v[1], v[4], v[7], v[2], v[5], v[8]])
}

fn child<'a, 'i>(n: Node<'a, 'i>, name: &str) -> Option<Node<'a, 'i>> {
    n.children().find(|c| c.has_tag_name(name))
}

/// A `<sensor>`'s intrinsics from its adjusted calibration (else its only one); `Ok(None)` for a
/// sensor without calibration (its cameras were not aligned).
fn sensor(src: &Source, n: Node) -> Result<Option<Intrinsics>> {
    let at = src.at(n);
    let kind = n.attribute("type").unwrap_or("frame");
    if kind != "frame" && kind != "fisheye" {
        bail!(
            "{at}: sensor type '{kind}' is not supported (frame and fisheye are); export the photos undistorted from Metashape instead"
        );
    }
    let calibs: Vec<Node> = n
        .children()
        .filter(|c| c.has_tag_name("calibration"))
        .collect();
    let Some(&cal) = calibs
        .iter()
        .find(|c| c.attribute("class") == Some("adjusted"))
        .or(calibs.first())
    else {
        return Ok(None);
    };
    let (w, h) = resolution(src, n, cal, &at)?;
    let (fx, fy, cx, cy, skew_px) = focal(src, cal, w, h)?;
    Ok(Some(Intrinsics {
        width: w as u32,
        height: h as u32,
        fx,
        fy,
        cx,
        cy,
        distortion: distortion(src, cal, kind == "fisheye", fx, skew_px)?,
    }))
}

/// A calibration's `<resolution>` (else its sensor's): width and height, whole and positive.
fn resolution(src: &Source, sensor: Node, cal: Node, at: &str) -> Result<(f64, f64)> {
    let res = child(cal, "resolution")
        .or_else(|| child(sensor, "resolution"))
        .ok_or_else(|| anyhow!("{at}: sensor has no <resolution width=… height=…>"))?;
    let (w, h) = (
        src.attr_number(res, "width")?,
        src.attr_number(res, "height")?,
    );
    if !(w >= 1.0
        && h >= 1.0
        && w.fract() == 0.0
        && h.fract() == 0.0
        && w.max(h) <= u32::MAX as f64)
    {
        bail!(
            "{}: resolution {w}×{h}: expected positive whole numbers",
            src.at(res)
        );
    }
    Ok((w, h))
}

/// A calibration's number `<name>`, 0 when absent.
fn number_or_zero(src: &Source, cal: Node, name: &str) -> Result<f64> {
    Ok(src.child_number(cal, name)?.unwrap_or(0.0))
}

/// `(fx, fy, principal point, skew in pixels)` of a calibration of a `w`×`h` sensor. Metashape
/// and PhotoScan from 1.4 (document 1.4.0 on) write `f`, `b1`, `b2` and cx, cy from the image
/// centre; PhotoScan before 1.4 wrote `fx`, `fy`, `skew` and cx, cy from the image corner, in
/// pixels.
fn focal(src: &Source, cal: Node, w: f64, h: f64) -> Result<(f64, f64, f64, f64, f64)> {
    let get = |name: &str| number_or_zero(src, cal, name);
    if let Some(f) = src.child_number(cal, "f")? {
        let (b1, b2) = (get("b1")?, get("b2")?);
        if !(f + b1 > 0.0 && f > 0.0) {
            bail!(
                "{}: focal length f = {f}, b1 = {b1}: expected f > 0 and f + b1 > 0",
                src.at(cal)
            );
        }
        return Ok((f + b1, f, 0.5 * w + get("cx")?, 0.5 * h + get("cy")?, b2));
    }
    let need = |name: &str| -> Result<f64> {
        src.child_number(cal, name)?.ok_or_else(|| {
            anyhow!(
                "{}: calibration has no <f> (nor the <fx>, <fy>, <cx>, <cy> of PhotoScan before 1.4): no <{name}>",
                src.at(cal)
            )
        })
    };
    let (fx, fy) = (need("fx")?, need("fy")?);
    let (cx, cy) = (need("cx")?, need("cy")?);
    if !(fx > 0.0 && fy > 0.0) {
        bail!(
            "{}: focal lengths fx = {fx}, fy = {fy}: expected positive numbers",
            src.at(cal)
        );
    }
    // Agisoft documented this form's tangential terms both ways round (Agisoft Lens' manual: P2
    // with r² + 2x², OpenCV's order; PhotoScan's Appendix C: P1 with it).
    for name in ["p1", "p2"] {
        if get(name)? != 0.0 {
            bail!(
                "{}: <{name}> in a calibration of PhotoScan before 1.4 (<fx>, <fy>): Agisoft's manuals disagree on which term it multiplies, so xscale does not guess; export the cameras from PhotoScan 1.4 or Metashape (which write <f>), or the photos undistorted",
                src.at(cal)
            );
        }
    }
    Ok((fx, fy, cx, cy, get("skew")?))
}

/// A calibration's lens distortion: Brown's (frame sensors; none when every term is zero) or the
/// equidistant fisheye's, with skew `skew_px` (pixels) of focal length `fx`.
fn distortion(src: &Source, cal: Node, fisheye: bool, fx: f64, skew_px: f64) -> Result<Distortion> {
    let get = |name: &str| number_or_zero(src, cal, name);
    for extra in ["p3", "p4"] {
        if get(extra)? != 0.0 {
            bail!(
                "{}: <{extra}> is not supported (k1…k4, p1, p2, b1, b2 are); export the photos undistorted from Metashape instead",
                src.at(cal)
            );
        }
    }
    let k = [get("k1")?, get("k2")?, get("k3")?, get("k4")?];
    // Metashape's P1 goes with r² + 2x² (OpenCV's p2), its P2 with 2xy (OpenCV's p1).
    let (p1, p2) = (get("p2")?, get("p1")?);
    let skew = skew_px / fx;
    Ok(if fisheye {
        if skew_px != 0.0 {
            bail!(
                "{}: a fisheye sensor with skew (b2) {skew_px} is not supported",
                src.at(cal)
            );
        }
        Distortion::ThinPrismFisheye {
            k,
            p1,
            p2,
            sx1: 0.0,
            sy1: 0.0,
        }
    } else if k == [0.0; 4] && p1 == 0.0 && p2 == 0.0 && skew == 0.0 {
        Distortion::None
    } else {
        Distortion::Brown { k, p1, p2, skew }
    })
}

/// The photo of a camera label in `images`: the label itself when it names a file there (labels
/// may keep their extension, or be a path below `images`), else the label with one of the usual
/// extensions; a label that is a path elsewhere (Metashape can label a camera with its photo's
/// full path) by its file name, likewise. Never a file outside `images`.
fn find_photo(images: &Path, label: &str) -> Option<PathBuf> {
    let within = |name: &str| -> Option<PathBuf> {
        let rel = Path::new(name);
        if name.is_empty()
            || rel.is_absolute()
            || name.contains('\\')
            || rel
                .components()
                .any(|c| !matches!(c, std::path::Component::Normal(_)))
        {
            return None;
        }
        let direct = images.join(name);
        if direct.is_file() {
            return Some(direct);
        }
        super::mvsnet::find_image(images, name)
    };
    within(label).or_else(|| {
        let base = label.rsplit(['/', '\\']).next()?;
        (base != label).then(|| within(base)).flatten()
    })
}

/// Load the views of Metashape export `xml` with photos in `images`.
pub fn load(xml: &Path, images: &Path) -> Result<Loaded> {
    let text = crate::io::text::read(xml)?;
    let doc = roxmltree::Document::parse(&text)
        .map_err(|e| anyhow!("{}: not well-formed XML: {e}", xml.display()))?;
    let src = Source {
        path: xml,
        doc: &doc,
    };
    let chunk = the_chunk(&src)?;
    if !images.is_dir() {
        bail!(
            "{}: photo folder not found (the cameras are in {})",
            images.display(),
            xml.display()
        );
    }
    let sensors = Sensors::read(&src, chunk);
    let placement = Placement::read(&src, chunk)?;
    let cameras = child(chunk, "cameras")
        .ok_or_else(|| anyhow!("{}: the chunk has no <cameras>", src.at(chunk)))?;
    let mut left = LeftOut::default();
    let mut views = Vec::new();
    for cam in cameras.descendants().filter(|c| c.has_tag_name("camera")) {
        if let Some(v) = read_camera(&src, cam, &sensors, &placement, images, &mut left)? {
            views.push(v);
        }
    }
    views.sort_by(|a, b| a.name.cmp(&b.name));
    let left = left.reasons();
    if views.is_empty() {
        bail!(
            "{}: no camera to read{}",
            xml.display(),
            if left.is_empty() {
                String::new()
            } else {
                format!(": {}", left.join(", "))
            }
        );
    }
    let mut notes = Vec::new();
    if !left.is_empty() {
        notes.push(format!(
            "{}: {} cameras read, left out: {}",
            xml.display(),
            views.len(),
            left.join(", ")
        ));
    }
    let georeferenced = child(chunk, "reference")
        .and_then(|r| r.text())
        .is_some_and(|t| !t.trim_start().starts_with("LOCAL_CS"));
    if georeferenced && placement.placed() {
        notes.push(georeference_note(xml));
    }
    Ok(Loaded { views, notes })
}

/// The document's one `<chunk>` (an export of several is refused: which was meant is not known).
fn the_chunk<'a, 'i>(src: &Source<'a>) -> Result<Node<'a, 'i>>
where
    'a: 'i,
{
    let xml = src.path;
    let root = src.doc.root_element();
    if !root.has_tag_name("document") {
        bail!(
            "{}: the root element is <{}>, expected <document> (an Agisoft XML camera export)",
            xml.display(),
            root.tag_name().name()
        );
    }
    let chunks: Vec<Node> = root
        .children()
        .filter(|c| c.has_tag_name("chunk"))
        .collect();
    match chunks.as_slice() {
        [c] => Ok(*c),
        [] => bail!("{}: no <chunk> in the document", xml.display()),
        _ => bail!(
            "{}: {} chunks ({}); export the cameras of one chunk",
            xml.display(),
            chunks.len(),
            chunks
                .iter()
                .map(|c| format!("'{}'", c.attribute("label").unwrap_or("?")))
                .collect::<Vec<_>>()
                .join(", ")
        ),
    }
}

/// The chunk's sensors: each one's intrinsics, or why it has none we can use (a sensor no read
/// camera uses may be of a kind xscale does not model), and the slave sensors of a multi-camera
/// system (a `master_id` other than their own id, or a `<location>` / `<rotation>` offset from
/// the master).
struct Sensors<'a> {
    intrinsics: HashMap<&'a str, Result<Option<Intrinsics>>>,
    slaves: Vec<&'a str>,
}

impl<'a> Sensors<'a> {
    fn read(src: &Source, chunk: Node<'a, '_>) -> Sensors<'a> {
        let mut out = Sensors {
            intrinsics: HashMap::new(),
            slaves: Vec::new(),
        };
        for s in child(chunk, "sensors")
            .into_iter()
            .flat_map(|s| s.children().filter(|c| c.has_tag_name("sensor")))
        {
            let id = s.attribute("id").unwrap_or("");
            if s.attribute("master_id").is_some_and(|m| m != id)
                || child(s, "location").is_some()
                || child(s, "rotation").is_some()
            {
                out.slaves.push(id);
            }
            out.intrinsics.insert(id, sensor(src, s));
        }
        out
    }
}

/// What places the chunk's cameras in its world frame: each component's similarity (Metashape
/// 2), the chunk's (PhotoScan and Metashape 1.x before components).
struct Placement<'a> {
    components: HashMap<&'a str, Similarity>,
    chunk: Option<Similarity>,
}

impl<'a> Placement<'a> {
    fn read(src: &Source, chunk: Node<'a, '_>) -> Result<Placement<'a>> {
        let mut components: HashMap<&str, Similarity> = HashMap::new();
        for c in child(chunk, "components")
            .into_iter()
            .flat_map(|s| s.children().filter(|c| c.has_tag_name("component")))
        {
            if let Some(t) = child(c, "transform") {
                components.insert(c.attribute("id").unwrap_or(""), src.similarity(t)?);
            }
        }
        let chunk_transform = match child(chunk, "transform") {
            Some(t) => Some((src.similarity(t)?, t)),
            None => None,
        };
        // A file with both has them mean the same placement (applying both would place the
        // cameras twice) or something not documented.
        let chunk = match chunk_transform {
            Some((ch, _)) if components.values().all(|c| c.same_as(&ch)) => Some(ch),
            Some((_, t)) => bail!(
                "{}: the chunk's <transform> differs from its components' <transform>s: whether the cameras are placed by one, the other or both is not documented, so xscale does not guess; export the cameras of a chunk with one of them",
                src.at(t)
            ),
            None => None,
        };
        Ok(Placement { components, chunk })
    }

    /// Whether anything places the cameras (else they stand in the chunk's own frame).
    fn placed(&self) -> bool {
        self.chunk.is_some() || !self.components.is_empty()
    }

    /// The similarity that places camera `cam` (labelled `label`, `at` in the file): its
    /// component's, else the chunk's; never both (they are one when both).
    fn of(&self, cam: Node, at: &str, label: &str) -> Result<Option<&Similarity>> {
        Ok(match cam.attribute("component_id") {
            Some(id) => self.components.get(id).or(self.chunk.as_ref()),
            None if self.chunk.is_none() && !self.components.is_empty() => bail!(
                "{at}: camera '{label}' has no component_id, but the chunk's components are placed by their <transform>s: which one places it is not known"
            ),
            None => self.chunk.as_ref(),
        })
    }
}

/// Cameras [`load`] left out, by cause.
#[derive(Default)]
struct LeftOut {
    unaligned: usize,
    disabled: usize,
    uncalibrated: usize,
    slaves: usize,
}

impl LeftOut {
    /// `N why` for each cause with cameras.
    fn reasons(&self) -> Vec<String> {
        [
            (self.unaligned, "not aligned (no <transform>)"),
            (self.disabled, "disabled"),
            (self.uncalibrated, "on a sensor without calibration"),
            (
                self.slaves,
                "slave cameras of a multi-camera system (placed by their master camera and their sensor's offset, which xscale does not compose)",
            ),
        ]
        .iter()
        .filter(|(n, _)| *n > 0)
        .map(|(n, why)| format!("{n} {why}"))
        .collect()
    }
}

/// The view of `<camera>` `cam`, or `None` when it is left out (counted in `left`).
fn read_camera(
    src: &Source,
    cam: Node,
    sensors: &Sensors,
    placement: &Placement,
    images: &Path,
    left: &mut LeftOut,
) -> Result<Option<View>> {
    let at = src.at(cam);
    let label = cam
        .attribute("label")
        .ok_or_else(|| anyhow!("{at}: <camera> has no label"))?;
    if matches!(cam.attribute("enabled"), Some("false" | "0")) {
        left.disabled += 1;
        return Ok(None);
    }
    let Some(t) = child(cam, "transform") else {
        left.unaligned += 1;
        return Ok(None);
    };
    let sensor_id = cam
        .attribute("sensor_id")
        .ok_or_else(|| anyhow!("{at}: camera '{label}' has no sensor_id"))?;
    // A slave camera of a multi-camera system: Metashape places it by its master camera and
    // its sensor's offset, which xscale does not compose.
    if sensors.slaves.contains(&sensor_id)
        || cam
            .attribute("master_id")
            .is_some_and(|m| Some(m) != cam.attribute("id"))
    {
        left.slaves += 1;
        return Ok(None);
    }
    let intr = match sensors.intrinsics.get(sensor_id) {
        None => {
            bail!("{at}: camera '{label}': sensor {sensor_id} is not among the chunk's <sensors>")
        }
        Some(Err(e)) => bail!("{e:#}"),
        Some(Ok(None)) => {
            left.uncalibrated += 1;
            return Ok(None);
        }
        Some(Ok(Some(i))) => i,
    };
    let (r_c, c) = src.matrix(t)?;
    if let Some(what) = not_a_rotation(&r_c, 1e-6) {
        bail!("{at}: camera '{label}': the rotation of its <transform> {what}");
    }
    let mut pose = (r_c, c);
    if let Some(sim) = placement.of(cam, &at, label)? {
        pose = sim.apply(pose);
    }
    let photo = find_photo(images, label).ok_or_else(|| {
        anyhow!(
            "{at}: no photo for camera '{label}': tried {}/{label} and {label}.{{{}}} (a label that is a path: its file name)",
            images.display(),
            super::mvsnet::IMAGE_EXTS.join(",")
        )
    })?;
    let rotation = pose.0.transpose();
    Ok(Some(View {
        name: photo
            .strip_prefix(images)
            .unwrap_or(&photo)
            .to_string_lossy()
            .to_string(),
        camera: intr.posed(rotation, -(rotation * pose.1)),
        image_path: photo,
    }))
}

/// What a georeferenced chunk's frame means for the mesh.
fn georeference_note(xml: &Path) -> String {
    format!(
        "{}: the chunk is georeferenced, so its cameras stand in its world frame, geocentric \
         coordinates (EPSG:4978): export the mesh in that coordinate system ('WGS 84 geocentric' \
         in Metashape's Export Model, no shift), not in a geographic or projected one",
        xml.display()
    )
}
