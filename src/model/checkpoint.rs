//! Model ↔ tensors (SPEC §6): checkpoints, batches and dumps as safetensors files.
//!
//! - Checkpoint: every parameter tensor of the layout (f32, names and shapes as
//!   [`ParamLayout`]), `grid_h.scales` `[L]` f32 and `grid_h.offsets` `[L+1]` u32 (same for
//!   `grid_d`), header metadata `format` = [`FORMAT`], `config` (the [`ModelConfig`] as TOML) and
//!   `normalization` (JSON `{"center":[..],"extent":[..]}`, f64). Loading uses the SAVED scale
//!   table (`HashGrid::with_scales`) and checks the saved offsets against it. Other tensors in the
//!   file (e.g. the trainer's `adam.*`) are ignored by [`Checkpoint::from_tensor_file`].
//!   A vertex-featurization model (the Fig. 2b baseline) has `vertex.features` [V, Z] instead
//!   of `grid_h.*`, plus `vertex.faces` [T, 3] u32 (the mesh's triangles, see `model/vertex.rs`).
//! - Batch: `batch.positions` `[N,S,3]` f64, `batch.valid` `[N,S]` u8, `batch.dirs` `[N,3]` f32,
//!   `batch.view` `[N]` i32, `batch.target` `[N,3]` f32.
//! - Dump ([`dump`]): the checkpoint and batch tensors copied in, every intermediate `fwd.*`,
//!   `loss` [] and every gradient `grad.*`, in the dtype of the instantiation (f64 or f32). Rows
//!   of invalid sub-samples are zero (they are never evaluated).

use crate::io::tensors::{DType, RawTensor, Tensor, TensorFile};
use crate::model::batch::Batch;
use crate::model::config::ModelConfig;
use crate::model::hashgrid::HashGrid;
use crate::model::hfm::{Forward, Hfm};
use crate::model::params::{Grads, ParamLayout};
use crate::model::sh::SH_DIM;
use crate::model::Real;
use anyhow::{bail, ensure, Context, Result};
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::path::Path;

/// Version string in every checkpoint / dump header (`format`).
pub const FORMAT: &str = "xscale-1";

/// World → normalised coordinates (SPEC §4.1): the scene's type, saved as JSON metadata.
pub use crate::scene::Normalization;

/// A model with its parameters (f32, the training precision) and normalisation.
#[derive(Clone, Debug)]
pub struct Checkpoint {
    pub model: Hfm,
    /// `[model.layout.total]`.
    pub params: Vec<f32>,
    pub normalization: Normalization,
    /// Mesh refinement (`[model.refine] enabled`, `model/refine.rs`, `refine/`): the offset field's
    /// parameters and the per-vertex offsets eval/render apply to the training mesh.
    pub refine: Option<crate::model::refine::RefineParams>,
}

/// A freshly initialised checkpoint: `n_train_views` appearance rows (zero), parameters from
/// `seed` (see [`Hfm::init_params`]).
pub fn init_checkpoint(
    cfg: &ModelConfig,
    seed: u64,
    normalization: Normalization,
    n_train_views: usize,
) -> Result<Checkpoint> {
    init_checkpoint_for_mesh(cfg, seed, normalization, n_train_views, None)
}

/// [`init_checkpoint`] with the scene's mesh, which a vertex-featurization model needs (its
/// table gets one row per vertex, `cfg.vertex_count` is set from it); ignored by a hash model.
pub fn init_checkpoint_for_mesh(
    cfg: &ModelConfig,
    seed: u64,
    normalization: Normalization,
    n_train_views: usize,
    mesh: Option<&crate::scene::Mesh>,
) -> Result<Checkpoint> {
    let mut cfg = cfg.clone();
    cfg.appearance_views = if cfg.appearance_dim > 0 {
        u32::try_from(n_train_views).context("too many training views")?
    } else {
        0
    };
    let model = if cfg.featurization.is_hash() {
        Hfm::new(&cfg)?
    } else {
        let mesh = mesh.context("the vertex featurization needs the scene's mesh")?;
        cfg.vertex_count = u32::try_from(mesh.vertices.len()).context("too many vertices")?;
        Hfm::with_vertex(&cfg, mesh.triangles.clone().into())?
    };
    // On huge pages: the tables are read and updated at random entries every step.
    let params = crate::memhint::copied(&model.init_params(seed));
    let refine = if cfg.refine.enabled {
        let mesh = mesh.context("[model.refine] needs the scene's mesh")?;
        Some(crate::model::refine::RefineParams::zeros(
            &cfg.refine,
            mesh.vertices.len(),
        ))
    } else {
        None
    };
    Ok(Checkpoint {
        model,
        params,
        normalization,
        refine,
    })
}

/// Write every tensor of a layout from a flat buffer, names prefixed by `prefix` (e.g. `""`,
/// `"grad."`, `"adam.m."`).
pub fn layout_to_tensors<R: Real>(
    file: &mut TensorFile,
    layout: &ParamLayout,
    prefix: &str,
    data: &[R],
) -> Result<()> {
    for t in &layout.tensors {
        file.insert(
            format!("{prefix}{}", t.name),
            tensor_of(t.shape.clone(), &data[t.range()])?,
        );
    }
    Ok(())
}

/// Read every tensor of a layout (f32, exact shapes) into a flat buffer (on huge pages, as the
/// training loop wants its parameters).
pub fn layout_from_tensors(
    file: &TensorFile,
    layout: &ParamLayout,
    prefix: &str,
) -> Result<Vec<f32>> {
    layout_from(file, &BTreeMap::new(), layout, prefix)
}

/// [`layout_from_tensors`] taking the tensors in `raw` (left in a mapped file) from there.
fn layout_from(
    file: &TensorFile,
    raw: &BTreeMap<String, RawTensor>,
    layout: &ParamLayout,
    prefix: &str,
) -> Result<Vec<f32>> {
    // Tables stored by their stepped rows (`Checkpoint::to_tensor_file_stepped`), checked first
    // and completed as the buffer is written (no whole copy of the table in between).
    let mut stepped: BTreeMap<String, SteppedTable> = BTreeMap::new();
    for t in &layout.tensors {
        let name = format!("{prefix}{}", t.name);
        if !raw.contains_key(&name)
            && !file.tensors.contains_key(&name)
            && file.tensors.contains_key(&format!("{name}.mask"))
        {
            let s = SteppedTable::from_file(file, &name, &t.shape)?;
            stepped.insert(name, s);
        }
    }
    // Every tensor checked first, then the buffer written once, in parallel pieces on huge
    // pages (a zero fill followed by a copy on one thread was a third of `render`'s load).
    let mut parts: Vec<(usize, usize, Source)> = Vec::with_capacity(layout.tensors.len());
    let mut at = 0;
    for t in &layout.tensors {
        let name = format!("{prefix}{}", t.name);
        let (len, data) = match (raw.get(&name), stepped.get(&name)) {
            (Some(r), _) => {
                file.check_type(&name, (r.dtype, &r.shape), DType::F32, &t.shape)?;
                (r.data.len() / 4, Source::Bytes(r.data))
            }
            (None, Some(s)) => (t.len, Source::Stepped(s)),
            (None, None) => {
                let d = &file.get_checked(&name, DType::F32, &t.shape)?.data;
                (d.len() / 4, Source::Bytes(d))
            }
        };
        ensure!(
            t.offset == at && len == t.len,
            "{}: tensor {name}: {len} elements at element {}, the layout has {} elements at {at}",
            file.label(),
            t.offset,
            t.len
        );
        parts.push((t.offset, len, data));
        at += t.len;
    }
    ensure!(
        at == layout.total,
        "parameter layout: tensors cover {at} of {} elements",
        layout.total
    );
    Ok(crate::memhint::built(layout.total, |at, piece| {
        // The first tensor ending after `at`, then on until the piece is written.
        let mut k = parts.partition_point(|&(o, len, _)| o + len <= at);
        let mut i = 0;
        while i < piece.len() {
            let (o, len, ref src) = parts[k];
            let from = at + i - o;
            let n = (len - from).min(piece.len() - i);
            let out = &mut piece[i..i + n];
            match src {
                Source::Bytes(d) => {
                    for (x, c) in out.iter_mut().zip(d[from * 4..].chunks_exact(4)) {
                        x.write(f32::from_le_bytes(c.try_into().unwrap()));
                    }
                }
                Source::Stepped(s) => s.fill(from, out),
            }
            i += n;
            k += 1;
        }
    }))
}

/// Where a parameter tensor's values come from when the buffer is written.
enum Source<'a> {
    /// Little-endian f32 bytes (a mapped or read tensor).
    Bytes(&'a [u8]),
    /// A table stored by its stepped rows.
    Stepped(&'a SteppedTable<'a>),
}

/// The feature tables a model file may store by their stepped rows only, with the tensor id
/// their initial values are drawn with (`Purpose::InitTable`, SPEC §5.1).
const STEPPED_TABLES: [(&str, u64); 2] = [
    ("grid_h.table", crate::model::hfm::TENSOR_ID_GRID_H),
    ("grid_d.table", crate::model::hfm::TENSOR_ID_GRID_D),
];

/// Whether a table of `rows` rows of `row_len` f32s, `kept` of which Adam stepped, is stored by
/// those rows ([`Checkpoint::to_tensor_file_stepped`]): when that saves at least
/// [`ROWS_MIN_SAVING`] of the whole table's bytes (the rows left out less the mask's
/// `ceil(rows/8)` bytes).
pub fn stores_by_rows(rows: usize, kept: usize, row_len: usize) -> bool {
    let whole = rows * row_len * 4;
    let by_rows = kept * row_len * 4 + rows.div_ceil(8);
    row_len > 0 && kept < rows && by_rows as f64 <= (1.0 - ROWS_MIN_SAVING) * whole as f64
}

/// The least fraction of a table's bytes that storing it by its stepped rows must save
/// ([`stores_by_rows`]). A loader draws every row left out again (a hash per element) and
/// reads every kept row through the mask, where a whole table is a copy from the mapped file:
/// measured on `synth small`'s trained model (both tables ~⅓ unstepped; `docs/runs.md`), that
/// costs about 14 instructions per byte saved, and the more so the fewer rows are left out (each
/// kept element costs ~8 instructions through the mask against ~1 copied): a quarter keeps
/// tables most of whose bytes would be mask and kept rows whole.
pub const ROWS_MIN_SAVING: f64 = 0.25;

/// A table stored by its stepped rows (`<name>.mask` U8 `[ceil(rows/8)]`, `<name>.kept` F32
/// `[k, …]`, header `init_seed`), checked: a row not kept is its initial value
/// (`hashgrid::init_value` of the seed, the table's tensor id and the flat element index), a
/// kept row the stored one.
struct SteppedTable<'a> {
    /// The table's initial values (seed from the header, the table's tensor id).
    init: crate::model::hashgrid::TableInit,
    row_len: usize,
    mask: &'a [u8],
    /// Kept rows before byte i of the mask.
    rank: Vec<u32>,
    /// The kept rows' little-endian f32 bytes.
    kept: &'a [u8],
}

impl<'a> SteppedTable<'a> {
    /// Errors name the file, the tensor and what was expected.
    fn from_file(file: &'a TensorFile, name: &str, shape: &[usize]) -> Result<Self> {
        let label = file.label();
        let Some(&(_, id)) = STEPPED_TABLES.iter().find(|(n, _)| *n == name) else {
            bail!("{label}: tensor {name}: only grid_h.table and grid_d.table may be stored by their stepped rows ({name}.mask)");
        };
        let rows = shape[0];
        let row_len: usize = shape[1..].iter().product();
        let mask_name = format!("{name}.mask");
        let mask = &file
            .get_checked(&mask_name, DType::U8, &[rows.div_ceil(8)])?
            .data;
        let mut rank = Vec::with_capacity(mask.len());
        let mut n = 0u32;
        for &b in mask.iter() {
            rank.push(n);
            n += b.count_ones();
        }
        if let Some(&last) = mask.last().filter(|_| rows % 8 != 0) {
            ensure!(
                last >> (rows % 8) == 0,
                "{label}: tensor {mask_name}: a bit set beyond the table's {rows} rows"
            );
        }
        let mut kept_shape = shape.to_vec();
        kept_shape[0] = n as usize;
        let kept_name = format!("{name}.kept");
        let kept = &file
            .get_checked(&kept_name, DType::F32, &kept_shape)
            .with_context(|| {
                format!("{label}: {kept_name} holds one row per bit set in {mask_name}")
            })?
            .data;
        let seed: u64 = file.meta("init_seed")?.parse().with_context(|| {
            format!("{label}: header metadata \"init_seed\" (the seed {name}'s rows left out are drawn from) is not an integer")
        })?;
        Ok(SteppedTable {
            init: crate::model::hashgrid::TableInit::new(seed, id),
            row_len,
            mask,
            rank,
            kept,
        })
    }

    /// Elements `from..from + out.len()` of the whole table: a kept row copied, any other drawn
    /// again. Whole rows in one pass (a row's mask bit read once), a part row at either end.
    fn fill(&self, from: usize, out: &mut [std::mem::MaybeUninit<f32>]) {
        let rl = self.row_len;
        let end = from + out.len();
        // Rows r0..r1 lie whole in the piece, a part row before them and one after (within one
        // row when the piece spans no whole row).
        let (r0, r1) = (from.div_ceil(rl), end / rl);
        let head_end = (r0 * rl).min(end);
        let (a, rest) = out.split_at_mut(head_end - from);
        self.fill_part(from, a);
        let (mid, tail) = rest.split_at_mut(r1.saturating_sub(r0) * rl);
        self.fill_part(head_end + mid.len(), tail);
        if mid.is_empty() {
            return;
        }
        let (byte, bit) = (self.mask[r0 / 8], r0 % 8);
        let k = self.rank[r0 / 8] as usize + (byte & ((1u8 << bit) - 1)).count_ones() as usize;
        let kept = &self.kept[k * rl * 4..];
        // The row length a constant where it is one of the presets' (the features per entry):
        // a row's elements unrolled.
        match rl {
            1 => self.fill_rows::<1>(r0, kept, mid),
            2 => self.fill_rows::<2>(r0, kept, mid),
            4 => self.fill_rows::<4>(r0, kept, mid),
            8 => self.fill_rows::<8>(r0, kept, mid),
            _ => {
                let mut kept = kept.chunks_exact(4);
                for (r, dst) in (r0..).zip(mid.chunks_exact_mut(rl)) {
                    if self.mask[r / 8] >> (r % 8) & 1 == 1 {
                        for (x, v) in dst.iter_mut().zip(kept.by_ref()) {
                            x.write(f32::from_le_bytes(v.try_into().unwrap()));
                        }
                    } else {
                        self.draw(r * rl, dst);
                    }
                }
            }
        }
    }

    /// Whole rows `r0..` of `N` elements into `out`, `kept` starting at the first kept row
    /// among them.
    fn fill_rows<const N: usize>(
        &self,
        r0: usize,
        kept: &[u8],
        out: &mut [std::mem::MaybeUninit<f32>],
    ) {
        let mut kept = kept.chunks_exact(4 * N);
        for (r, dst) in (r0..).zip(out.chunks_exact_mut(N)) {
            if self.mask[r / 8] >> (r % 8) & 1 == 1 {
                let src = kept.next().unwrap();
                for c in 0..N {
                    dst[c].write(f32::from_le_bytes(
                        src[4 * c..4 * c + 4].try_into().unwrap(),
                    ));
                }
            } else {
                for (c, x) in dst.iter_mut().enumerate() {
                    x.write(self.init.value((r * N + c) as u64));
                }
            }
        }
    }

    /// Initial values of elements `e..e + out.len()`.
    fn draw(&self, e: usize, out: &mut [std::mem::MaybeUninit<f32>]) {
        for (e, x) in (e as u64..).zip(out.iter_mut()) {
            x.write(self.init.value(e));
        }
    }

    /// Elements `from..from + out.len()`, all within one row.
    fn fill_part(&self, from: usize, out: &mut [std::mem::MaybeUninit<f32>]) {
        let Some(r) = (!out.is_empty()).then_some(from / self.row_len) else {
            return;
        };
        let byte = self.mask[r / 8];
        if byte >> (r % 8) & 1 == 1 {
            let below = (byte & ((1u8 << (r % 8)) - 1)).count_ones() as usize;
            let at = (self.rank[r / 8] as usize + below) * self.row_len + from % self.row_len;
            let src = &self.kept[at * 4..(at + out.len()) * 4];
            for (x, v) in out.iter_mut().zip(src.chunks_exact(4)) {
                x.write(f32::from_le_bytes(v.try_into().unwrap()));
            }
        } else {
            self.draw(from, out);
        }
    }
}

/// A model file's tables stored by their stepped rows (`<name>.kept`, `<name>.mask`, header
/// `init_seed`; [`Checkpoint::to_tensor_file_stepped`]) rebuilt whole in place, as the loader
/// completes them (the same values, bit for bit): `<name>` of shape `[rows, …]` (rows from
/// `<grid>.offsets`) instead of the two, and `init_seed` dropped once no table needs it. Every
/// other tensor and key is left as it is; a file without such a table is unchanged. Returns
/// the tables rebuilt. Errors name the file, the tensor and what was expected.
pub fn whole_tables(file: &mut TensorFile) -> Result<Vec<String>> {
    let label = file.label();
    let mut whole = Vec::new();
    for (name, _) in STEPPED_TABLES {
        if file.tensors.contains_key(name) || !file.tensors.contains_key(&format!("{name}.mask")) {
            continue;
        }
        let grid = name.split('.').next().unwrap_or(name);
        let offsets = file
            .get(&format!("{grid}.offsets"))
            .with_context(|| format!("{label}: {name} is stored by its stepped rows"))?;
        ensure!(
            offsets.dtype == DType::U32 && offsets.shape.len() == 1 && offsets.shape[0] > 0,
            "{label}: tensor {grid}.offsets is {} {:?}, expected U32 [levels + 1]",
            offsets.dtype,
            offsets.shape
        );
        let rows = *offsets.to_u32()?.last().unwrap() as usize;
        let kept = file
            .get(&format!("{name}.kept"))
            .with_context(|| format!("{label}: {name} is stored by its stepped rows"))?;
        let mut shape = kept.shape.clone();
        ensure!(
            shape.len() >= 2,
            "{label}: tensor {name}.kept has shape {shape:?}, expected [k, features]"
        );
        shape[0] = rows;
        let len: usize = shape.iter().product();
        let table = SteppedTable::from_file(file, name, &shape)?;
        let values = crate::memhint::built(len, |at, piece| table.fill(at, piece));
        let t = Tensor::f32(shape, &values)?;
        file.tensors.remove(&format!("{name}.kept"));
        file.tensors.remove(&format!("{name}.mask"));
        file.insert(name, t);
        whole.push(name.to_string());
    }
    if !STEPPED_TABLES
        .iter()
        .any(|(n, _)| file.tensors.contains_key(&format!("{n}.mask")))
    {
        file.metadata.remove("init_seed");
    }
    Ok(whole)
}

/// A tensor in the dtype of `R` (F64 or F32).
pub fn tensor_of<R: Real>(shape: Vec<usize>, data: &[R]) -> Result<Tensor> {
    let dtype = if R::DTYPE == "F64" {
        DType::F64
    } else {
        DType::F32
    };
    Tensor::from_bytes(dtype, shape, crate::io::tensors::le_bytes(data))
}

fn grid_tensors(file: &mut TensorFile, name: &str, g: &HashGrid) -> Result<()> {
    file.insert(
        format!("{name}.scales"),
        Tensor::f32(vec![g.scales.len()], &g.scales)?,
    );
    file.insert(
        format!("{name}.offsets"),
        Tensor::u32(vec![g.offsets.len()], &g.offsets)?,
    );
    Ok(())
}

fn grid_from(
    file: &TensorFile,
    name: &str,
    cfg: &crate::model::config::GridConfig,
) -> Result<HashGrid> {
    let l = cfg.levels as usize;
    let scales = file
        .get_checked(&format!("{name}.scales"), DType::F32, &[l])?
        .to_f32()?;
    let g = HashGrid::with_scales(cfg, scales).with_context(|| format!("{name}.scales"))?;
    let offsets = file
        .get_checked(&format!("{name}.offsets"), DType::U32, &[l + 1])?
        .to_u32()?;
    ensure!(
        offsets == g.offsets,
        "{name}.offsets {:?} disagree with the ones the saved scales and config give {:?}",
        offsets,
        g.offsets
    );
    Ok(g)
}

impl Checkpoint {
    /// All tensors and the header metadata of the checkpoint.
    pub fn to_tensor_file(&self) -> Result<TensorFile> {
        let mut f = TensorFile::new();
        f.set_meta("format", FORMAT);
        f.set_meta("config", toml::to_string(&self.model.cfg)?);
        f.set_meta("normalization", serde_json::to_string(&self.normalization)?);
        layout_to_tensors(&mut f, &self.model.layout, "", &self.params)?;
        if let Some(r) = &self.refine {
            r.to_tensors(&mut f)?;
        }
        if let Some(vt) = &self.model.vertex {
            let faces: Vec<u32> = vt.faces.iter().flatten().copied().collect();
            f.insert(
                "vertex.faces",
                Tensor::u32(vec![vt.faces.len(), 3], &faces)?,
            );
            return Ok(f);
        }
        grid_tensors(&mut f, "grid_h", &self.model.grid_h)?;
        if let Some(g) = &self.model.grid_d {
            grid_tensors(&mut f, "grid_d", g)?;
        }
        Ok(f)
    }

    /// [`Checkpoint::to_tensor_file`] with a feature table (`grid_h.table`, `grid_d.table`) of
    /// which fewer than half the rows were stepped stored by those rows only: `<name>.mask`
    /// (U8 `[ceil(rows/8)]`, bit `r mod 8` of byte `⌊r/8⌋` set iff row r is stored),
    /// `<name>.kept` (F32 `[k, …]`, the stored rows, ascending) and header `init_seed` = `seed`.
    /// A row never stepped still holds its initial value (Adam leaves a row with a zero
    /// gradient untouched and the grids have no L2, SPEC §4.8), which a loader draws again from
    /// the seed: the parameters load back bit for bit. `stepped(name)` gives a table's stepped
    /// rows, ascending (`AdamState::stepped_rows`); `seed` must be the one the model was
    /// initialised with (`train.seed`).
    pub fn to_tensor_file_stepped(
        &self,
        seed: u64,
        stepped: &dyn Fn(&str) -> Result<Vec<u32>>,
    ) -> Result<TensorFile> {
        let mut f = self.to_tensor_file()?;
        let mut any = false;
        for (name, _) in STEPPED_TABLES {
            let Some(t) = self.model.layout.get(name) else {
                continue;
            };
            let rows = t.shape[0];
            let row_len = t.len.checked_div(rows).unwrap_or(0);
            let kept = stepped(name)?;
            if !stores_by_rows(rows, kept.len(), row_len) {
                continue;
            }
            let data = &self.params[t.range()];
            let mut values = Vec::with_capacity(kept.len() * row_len);
            let mut mask = vec![0u8; rows.div_ceil(8)];
            for &r in &kept {
                let r = r as usize;
                values.extend_from_slice(&data[r * row_len..(r + 1) * row_len]);
                mask[r / 8] |= 1 << (r % 8);
            }
            let mut shape = t.shape.clone();
            shape[0] = kept.len();
            f.tensors.remove(name);
            f.insert(format!("{name}.kept"), Tensor::f32(shape, &values)?);
            f.insert(
                format!("{name}.mask"),
                Tensor::from_bytes(DType::U8, vec![mask.len()], mask)?,
            );
            any = true;
        }
        if any {
            f.set_meta("init_seed", seed.to_string());
        }
        Ok(f)
    }

    /// A digest of the parameters (every f32's bits, in layout order; 16 hex digits), which
    /// pairs a run's optimizer state with the model it was saved with
    /// (`train/state.rs`). Hashed in fixed chunks combined in order: the same on any thread
    /// count.
    pub fn params_digest(&self) -> String {
        const CHUNK: usize = 1 << 16;
        let mix = crate::rng::fmix;
        let chunks: Vec<u64> = self
            .params
            .par_chunks(CHUNK)
            .map(|c| {
                c.chunks(2).fold(0x9E37_79B9_7F4A_7C15u64, |h, p| {
                    let w =
                        p[0].to_bits() as u64 | (p.get(1).map_or(0, |x| x.to_bits()) as u64) << 32;
                    mix(h ^ w).wrapping_add(w)
                })
            })
            .collect();
        let h = chunks
            .iter()
            .fold(self.params.len() as u64, |h, &c| mix(h ^ c));
        format!("{h:016x}")
    }

    /// Rebuild from a tensor file (saved scales, checked shapes); errors name the file/tensor.
    pub fn from_tensor_file(file: &TensorFile) -> Result<Checkpoint> {
        Self::from_tensors(file, &BTreeMap::new())
    }

    /// [`Checkpoint::from_tensor_file`] with the tensors in `raw` left in a mapped file
    /// ([`Checkpoint::read_model`]).
    fn from_tensors(file: &TensorFile, raw: &BTreeMap<String, RawTensor>) -> Result<Checkpoint> {
        let head = Head::of(file)?;
        Self::from_head(file, raw, head)
    }

    /// The rest of [`Checkpoint::from_tensors`] once its header is read.
    fn from_head(
        file: &TensorFile,
        raw: &BTreeMap<String, RawTensor>,
        head: Head,
    ) -> Result<Checkpoint> {
        let Head {
            label,
            cfg,
            normalization,
        } = head;
        let model = if cfg.featurization.is_hash() {
            let grid_h = grid_from(file, "grid_h", &cfg.grid_h).with_context(|| label.clone())?;
            let grid_d = if cfg.deform.enabled {
                Some(grid_from(file, "grid_d", &cfg.deform.grid).with_context(|| label.clone())?)
            } else {
                None
            };
            Hfm::with_grids(&cfg, grid_h, grid_d).with_context(|| label.clone())?
        } else {
            let t = file.get("vertex.faces").with_context(|| label.clone())?;
            ensure!(
                t.dtype == DType::U32 && t.shape.len() == 2 && t.shape[1] == 3,
                "{label}: vertex.faces is {} {:?}, expected U32 [T, 3]",
                t.dtype,
                t.shape
            );
            let faces: Vec<[u32; 3]> = t
                .to_u32()?
                .chunks_exact(3)
                .map(|c| [c[0], c[1], c[2]])
                .collect();
            Hfm::with_vertex(&cfg, faces.into()).with_context(|| label.clone())?
        };
        let params = layout_from(file, raw, &model.layout, "")?;
        let finite = params
            .par_chunks(1 << 16)
            .all(|c| c.iter().all(|v| v.is_finite()));
        if let Some(i) = (!finite)
            .then(|| params.iter().position(|v| !v.is_finite()))
            .flatten()
        {
            let t = model
                .layout
                .tensors
                .iter()
                .find(|t| t.range().contains(&i))
                .unwrap();
            bail!(
                "{label}: tensor {} element {} is not finite",
                t.name,
                i - t.offset
            );
        }
        let refine = if cfg.refine.enabled {
            Some(crate::model::refine::RefineParams::from_tensors(
                file,
                &cfg.refine,
                &label,
            )?)
        } else {
            None
        };
        Ok(Checkpoint {
            model,
            params,
            normalization,
            refine,
        })
    }

    pub fn save(&self, path: impl AsRef<Path>) -> Result<()> {
        self.to_tensor_file()?.write_atomic(path)
    }

    /// The model of a checkpoint file ([`Checkpoint::read_model_tensors`]).
    pub fn load(path: impl AsRef<Path>) -> Result<Checkpoint> {
        Ok(Checkpoint::read_model(path)?.0)
    }

    /// The model of a checkpoint file and the file's metadata: [`Checkpoint::load`] reading
    /// the hash tables straight from the mapped file into the parameter buffer (the same
    /// values as through [`Checkpoint::read_model_tensors`], one copy fewer).
    pub fn read_model(path: impl AsRef<Path>) -> Result<(Checkpoint, BTreeMap<String, String>)> {
        TensorFile::with_mapped(
            path,
            |name| !name.starts_with("adam."),
            |name| name == "grid_h.table" || name == "grid_d.table",
            |f, raw| Ok((Checkpoint::from_tensors(&f, raw)?, f.metadata)),
        )
    }

    /// [`Checkpoint::read_model`] running `meanwhile` on a thread of its own while the tables
    /// are decoded: it is given the header (model configuration, normalisation) and the
    /// metadata, read first, and can load and prepare what does not need the parameters (a
    /// scene, its BVH), so that work overlaps the tables' copy. A checkpoint whose header is
    /// refused does not run `meanwhile`; a refused table is reported before what `meanwhile`
    /// returns is looked at.
    pub fn read_model_while<T: Send>(
        path: impl AsRef<Path>,
        meanwhile: impl FnOnce(&Head, &BTreeMap<String, String>) -> T + Send,
    ) -> Result<(Checkpoint, BTreeMap<String, String>, T)> {
        TensorFile::with_mapped(
            path,
            |name| !name.starts_with("adam."),
            |name| name == "grid_h.table" || name == "grid_d.table",
            |f, raw| {
                let head = Head::of(&f)?;
                let (ck, other) = std::thread::scope(|sc| {
                    let (h, m) = (head.clone(), &f.metadata);
                    let other = sc.spawn(move || meanwhile(&h, m));
                    let ck = Checkpoint::from_head(&f, raw, head);
                    (ck, other.join())
                });
                let other = other.unwrap_or_else(|e| std::panic::resume_unwind(e));
                Ok((ck?, f.metadata, other))
            },
        )
    }

    /// A checkpoint file's tensors and metadata without a training checkpoint's Adam state
    /// (`adam.*`, `AdamState::save`: three quarters of the file), which a model does not need.
    pub fn read_model_tensors(path: impl AsRef<Path>) -> Result<TensorFile> {
        TensorFile::read_only(path, |name| !name.starts_with("adam."))
    }
}

/// What a checkpoint's header says before any tensor is read: its model configuration and
/// normalisation (checked), and the name errors give it.
#[derive(Clone, Debug)]
pub struct Head {
    pub label: String,
    pub cfg: ModelConfig,
    pub normalization: Normalization,
}

impl Head {
    fn of(file: &TensorFile) -> Result<Head> {
        let label = file
            .source
            .as_ref()
            .map_or("<in-memory checkpoint>".to_string(), |p| {
                p.display().to_string()
            });
        if let Some(kind) = file_kind(file).filter(|&k| k != CHECKPOINT) {
            let swapped = if kind == BATCH {
                " (--checkpoint and --batch swapped?)"
            } else {
                ""
            };
            bail!("{label}: not a checkpoint: this file is {kind}{swapped}");
        }
        let format = file.meta("format")?;
        if format != FORMAT {
            bail!("{label}: format is {format:?}, expected {FORMAT:?}");
        }
        let cfg: ModelConfig = toml::from_str(file.meta("config")?).with_context(|| {
            format!("{label}: header metadata \"config\" is not a model config")
        })?;
        let norm_text = file.meta("normalization")?;
        let normalization: Normalization = serde_json::from_str(norm_text).with_context(|| {
            format!("{label}: header metadata \"normalization\" is not {{\"center\":[x,y,z],\"extent\":[x,y,z]}}")
        })?;
        let [c, e] = [normalization.center, normalization.extent];
        ensure!(
            c.is_finite() && e.is_finite() && e.min_element() > 0.0,
            "{label}: normalization (header metadata) has center [{}, {}, {}] and extent [{}, {}, {}]: every value must be finite and every extent > 0",
            c.x, c.y, c.z, e.x, e.y, e.z
        );
        Ok(Head {
            label,
            cfg,
            normalization,
        })
    }
}

const CHECKPOINT: &str = "a checkpoint (`xscale init`/`train`)";
const BATCH: &str = "a batch (`xscale batch`)";
const OPTIMIZER: &str = "a run's optimizer state (`RUN/optimizer.safetensors`, read to resume; the model is `RUN/checkpoint.safetensors`)";
/// Header key of an optimizer state file: the digest of the model it belongs to
/// ([`Checkpoint::params_digest`], `train/state.rs`).
pub const OPTIMIZER_KEY: &str = "model_digest";

/// Which of xscale's tensor files this is, from its tensor names (`None`: none of them), so a
/// file given in another's place is named as what it is rather than by a missing key.
fn file_kind(file: &TensorFile) -> Option<&'static str> {
    let has = |prefix: &str| file.tensors.keys().any(|k| k.starts_with(prefix));
    if file.metadata.contains_key(OPTIMIZER_KEY) {
        Some(OPTIMIZER)
    } else if has("fwd.") || has("grad.") {
        Some("a dump (`xscale dump`)")
    } else if has("grid_h.") || has("vertex.") || has("shader.") {
        Some(CHECKPOINT)
    } else if has("batch.") {
        Some(BATCH)
    } else {
        None
    }
}

/// Insert a batch's tensors.
pub fn batch_to_tensors(file: &mut TensorFile, batch: &Batch) -> Result<()> {
    let n = batch.n_pixels();
    let s = batch.samples_per_pixel();
    let pos: Vec<f64> = batch.positions.iter().flatten().copied().collect();
    file.insert("batch.positions", Tensor::f64(vec![n, s, 3], &pos)?);
    file.insert("batch.valid", Tensor::u8(vec![n, s], &batch.valid)?);
    let dirs: Vec<f32> = batch.dirs.iter().flatten().copied().collect();
    file.insert("batch.dirs", Tensor::f32(vec![n, 3], &dirs)?);
    file.insert("batch.view", Tensor::i32(vec![n], &batch.view)?);
    let tgt: Vec<f32> = batch.target.iter().flatten().copied().collect();
    file.insert("batch.target", Tensor::f32(vec![n, 3], &tgt)?);
    if !batch.footprint.is_empty() {
        // Pixel footprints (SPEC §6.3): read only by the footprint level weighting (§4.10).
        file.insert("batch.footprint", Tensor::f32(vec![n], &batch.footprint)?);
    }
    if !batch.triangle.is_empty() {
        // Vertex featurization only (not part of SPEC §6's hash-model batch).
        file.insert("batch.triangle", Tensor::u32(vec![n, s], &batch.triangle)?);
        let bary: Vec<f64> = batch.bary.iter().flatten().copied().collect();
        file.insert("batch.bary", Tensor::f64(vec![n, s, 2], &bary)?);
    }
    Ok(())
}

/// Read and validate a batch.
pub fn batch_from_tensors(file: &TensorFile) -> Result<Batch> {
    let label = file
        .source
        .as_ref()
        .map_or("<in-memory batch>".to_string(), |p| p.display().to_string());
    if !file.tensors.contains_key("batch.positions") && file_kind(file) == Some(CHECKPOINT) {
        bail!(
            "{label}: not a batch: this file is {CHECKPOINT} (--checkpoint and --batch swapped?)"
        );
    }
    let pt = file.get("batch.positions")?;
    ensure!(
        pt.shape.len() == 3 && pt.shape[2] == 3 && pt.dtype == DType::F64,
        "{label}: batch.positions is {} {:?}, expected F64 [N, S, 3]",
        pt.dtype,
        pt.shape
    );
    let (n, s) = (pt.shape[0], pt.shape[1]);
    let pos = pt.to_f64()?;
    let valid = file
        .get_checked("batch.valid", DType::U8, &[n, s])?
        .to_u8()?;
    let dirs = file
        .get_checked("batch.dirs", DType::F32, &[n, 3])?
        .to_f32()?;
    let view = file.get_checked("batch.view", DType::I32, &[n])?.to_i32()?;
    let target = file
        .get_checked("batch.target", DType::F32, &[n, 3])?
        .to_f32()?;
    let b = Batch {
        positions: pos.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect(),
        valid,
        dirs: dirs.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect(),
        view,
        target: target.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect(),
        ..Batch::default()
    };
    let mut b = b;
    if file.tensors.contains_key("batch.footprint") {
        b.footprint = file
            .get_checked("batch.footprint", DType::F32, &[n])?
            .to_f32()?;
    }
    if file.tensors.contains_key("batch.triangle") {
        b.triangle = file
            .get_checked("batch.triangle", DType::U32, &[n, s])?
            .to_u32()?;
        let bary = file
            .get_checked("batch.bary", DType::F64, &[n, s, 2])?
            .to_f64()?;
        b.bary = bary.chunks_exact(2).map(|c| [c[0], c[1]]).collect();
    }
    b.validate().with_context(|| label.clone())?;
    Ok(b)
}

impl Batch {
    pub fn save(&self, path: impl AsRef<Path>) -> Result<()> {
        let mut f = TensorFile::new();
        f.set_meta("format", FORMAT);
        batch_to_tensors(&mut f, self)?;
        f.write_atomic(path)
    }

    pub fn load(path: impl AsRef<Path>) -> Result<Batch> {
        batch_from_tensors(&TensorFile::read(path)?)
    }
}

/// Expand per-valid-sub-sample rows (`get(chunk)` `[v, width]`) to `[N*S, width]` with zero
/// rows for invalid sub-samples.
fn expand<R: Real>(
    fwd: &Forward<R>,
    n_s: usize,
    width: usize,
    get: impl Fn(&crate::model::hfm::ChunkFwd<R>) -> &[R],
) -> Vec<R> {
    let mut out = vec![R::ZERO; n_s * width];
    for ch in &fwd.chunks {
        let src = get(ch);
        for (r, j) in ch.samples.clone().enumerate() {
            let k = fwd.sample_index[j];
            out[k * width..(k + 1) * width].copy_from_slice(&src[r * width..(r + 1) * width]);
        }
    }
    out
}

/// Concatenate per-pixel chunk rows.
fn concat<R: Real>(
    fwd: &Forward<R>,
    get: impl Fn(&crate::model::hfm::ChunkFwd<R>) -> &[R],
) -> Vec<R> {
    fwd.chunks
        .iter()
        .flat_map(|c| get(c).iter().copied())
        .collect()
}

/// Evaluate a checkpoint on a batch in precision `R` and return the dump: inputs, every
/// intermediate, the loss and every gradient (SPEC §6). An f64 dump also carries the `kink.*`
/// tensors at [`kink::DEFAULT_THRESHOLD`](crate::model::kink::DEFAULT_THRESHOLD) (see
/// [`dump_with`]).
pub fn dump<R: Real>(ckpt: &Checkpoint, batch: &Batch) -> Result<TensorFile> {
    let kinks = (R::DTYPE == "F64").then_some(crate::model::kink::DEFAULT_THRESHOLD);
    dump_with::<R>(ckpt, batch, kinks)
}

/// [`dump`] with the kink threshold given: `Some(t)` adds `kink.margin` `[N]` (each pixel's
/// smallest relative distance to a ReLU or L1 kink), `kink.threshold` `[]`, `kink.pixels` `[K]`
/// (the pixels with margin ≤ t, as floats) and, when K > 0, `kink.slack.<grad tensor>` for every
/// `grad.*` tensor: how far a correct backend on the other side of those kinks may be
/// (`model/kink.rs`; `xscale compare` adds it to the tolerance, `docs/oracle.md` §7).
pub fn dump_with<R: Real>(
    ckpt: &Checkpoint,
    batch: &Batch,
    kink_threshold: Option<f64>,
) -> Result<TensorFile> {
    let model = &ckpt.model;
    let params: Vec<R> = ckpt.params.iter().map(|&v| R::from_f32(v)).collect();
    let fwd = model.forward(&params, batch)?;
    let mut grads = Grads::<R>::new(&model.layout);
    model.backward(&params, batch, &fwd, &mut grads);

    let mut f = ckpt.to_tensor_file()?;
    f.set_meta("precision", R::DTYPE.to_ascii_lowercase());
    batch_to_tensors(&mut f, batch)?;
    let n = batch.n_pixels();
    let s = batch.samples_per_pixel();
    let lf = model.feat_dim();
    f.insert(
        if model.vertex.is_some() {
            "fwd.vertex"
        } else {
            "fwd.grid_h"
        },
        tensor_of(vec![n, s, lf], &expand(&fwd, n * s, lf, |c| &c.grid_h))?,
    );
    if let (Some(gd), Some(mlp)) = (&model.grid_d, &model.deform) {
        let ld = gd.out_dim();
        f.insert(
            "fwd.grid_d",
            tensor_of(vec![n, s, ld], &expand(&fwd, n * s, ld, |c| &c.grid_d))?,
        );
        f.insert(
            "fwd.deform",
            tensor_of(vec![n, s, lf], &expand(&fwd, n * s, lf, |c| &c.deform.out))?,
        );
        for (i, l) in mlp.layers[..mlp.layers.len() - 1].iter().enumerate() {
            let w = l.out_dim;
            f.insert(
                format!("fwd.deform_hidden.{i}"),
                tensor_of(
                    vec![n, s, w],
                    &expand(&fwd, n * s, w, |c| &c.deform.hidden[i]),
                )?,
            );
        }
    }
    f.insert(
        "fwd.pooled",
        tensor_of(vec![n, lf], &concat(&fwd, |c| &c.pooled))?,
    );
    f.insert(
        "fwd.sh",
        tensor_of(vec![n, SH_DIM], &concat(&fwd, |c| &c.sh))?,
    );
    let din = model.shader.in_dim();
    f.insert(
        "fwd.shader_in",
        tensor_of(vec![n, din], &concat(&fwd, |c| &c.shader_in))?,
    );
    for (i, l) in model.shader.layers[..model.shader.layers.len() - 1]
        .iter()
        .enumerate()
    {
        f.insert(
            format!("fwd.shader_hidden.{i}"),
            tensor_of(vec![n, l.out_dim], &concat(&fwd, |c| &c.shader.hidden[i]))?,
        );
    }
    f.insert(
        "fwd.logits",
        tensor_of(vec![n, 3], &concat(&fwd, |c| &c.shader.out))?,
    );
    f.insert("fwd.rgb", tensor_of(vec![n, 3], &concat(&fwd, |c| &c.rgb))?);
    f.insert("loss", tensor_of(vec![], &[R::from_f64(fwd.loss)])?);
    layout_to_tensors(&mut f, &model.layout, "grad.", &grads.params)?;
    f.insert(
        "grad.batch.positions",
        tensor_of(vec![n, s, 3], &grads.positions)?,
    );
    f.insert("grad.batch.dirs", tensor_of(vec![n, 3], &grads.dirs)?);
    if let Some(t) = kink_threshold {
        let kinks = crate::model::kink::Kinks::find(model, &params, batch, &fwd, t);
        let pixels: Vec<f64> = kinks.pixels().iter().map(|&p| p as f64).collect();
        f.insert("kink.margin", Tensor::f64(vec![n], &kinks.margin)?);
        f.insert("kink.threshold", Tensor::f64(vec![], &[t])?);
        f.insert("kink.pixels", Tensor::f64(vec![pixels.len()], &pixels)?);
        if !pixels.is_empty() {
            // f32, rounded up: a bound stays a bound, and the file grows by half as much.
            let up = |v: &[R]| -> Vec<f32> {
                v.iter()
                    .map(|x| {
                        let (x, y) = (x.to_f64(), x.to_f64() as f32);
                        if (y as f64) < x {
                            // next float up (y ≥ 0 here: a slack is a sum of magnitudes)
                            f32::from_bits(y.to_bits() + 1)
                        } else {
                            y
                        }
                    })
                    .collect()
            };
            let slack = kinks.slack(model, &params, batch, &fwd, &grads);
            for t in &model.layout.tensors {
                f.insert(
                    format!("kink.slack.grad.{}", t.name),
                    Tensor::f32(t.shape.clone(), &up(&slack.params[t.range()]))?,
                );
            }
            f.insert(
                "kink.slack.grad.batch.positions",
                Tensor::f32(vec![n, s, 3], &up(&slack.positions))?,
            );
            f.insert(
                "kink.slack.grad.batch.dirs",
                Tensor::f32(vec![n, 3], &up(&slack.dirs))?,
            );
        }
    }
    Ok(f)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The storage rule at its edges: 1000 rows of 2 f32s (8000 bytes; the mask 125) are
    /// stored by rows when at most 734 rows stepped (5997 bytes ≤ ¾ of 8000), whole above;
    /// never for a table every row of which stepped, nor for an empty row.
    #[test]
    fn stores_by_rows_when_it_saves_a_quarter() {
        assert_eq!(ROWS_MIN_SAVING, 0.25);
        assert!(stores_by_rows(1000, 0, 2));
        assert!(stores_by_rows(1000, 734, 2));
        assert!(!stores_by_rows(1000, 735, 2));
        assert!(!stores_by_rows(1000, 1000, 2));
        assert!(!stores_by_rows(1000, 0, 0));
        // Bytes, not the fraction of rows: a mask costs more beside short rows.
        assert!(stores_by_rows(64, 47, 1) != stores_by_rows(64, 47, 8));
    }

    /// A table stored by its stepped rows is completed element for element whatever the pieces
    /// the loader writes it in: rows of 3, 2 and 1 (part rows at either end, the constant and
    /// the general row length), every kept/left-out pattern of a mask byte.
    #[test]
    fn stepped_table_fill_matches_every_piece() {
        for (row_len, shape) in [(3usize, vec![37usize, 3]), (2, vec![37, 2]), (1, vec![37])] {
            let rows = 37usize;
            let kept: Vec<usize> = (0..rows).filter(|r| (r * 7 + r / 5) % 3 != 0).collect();
            let mut mask = vec![0u8; rows.div_ceil(8)];
            let mut values = Vec::new();
            for &r in &kept {
                mask[r / 8] |= 1 << (r % 8);
                values.extend((0..row_len).map(|c| (r * 10 + c) as f32 + 0.5));
            }
            let mut kshape = shape.clone();
            kshape[0] = kept.len();
            let mut f = TensorFile::new();
            f.insert("grid_d.table.kept", Tensor::f32(kshape, &values).unwrap());
            f.insert(
                "grid_d.table.mask",
                Tensor::from_bytes(DType::U8, vec![mask.len()], mask).unwrap(),
            );
            f.set_meta("init_seed", "11");
            let t = SteppedTable::from_file(&f, "grid_d.table", &shape).unwrap();
            let want: Vec<u32> = (0..rows * row_len)
                .map(|j| {
                    let (r, c) = (j / row_len, j % row_len);
                    if kept.contains(&r) {
                        ((r * 10 + c) as f32 + 0.5).to_bits()
                    } else {
                        let id = crate::model::hfm::TENSOR_ID_GRID_D;
                        crate::model::hashgrid::init_value(11, id, j as u64).to_bits()
                    }
                })
                .collect();
            let n = rows * row_len;
            for from in 0..n {
                for len in [0, 1, 2, 5, 17, n - from] {
                    let len = len.min(n - from);
                    let mut out = vec![std::mem::MaybeUninit::<f32>::uninit(); len];
                    t.fill(from, &mut out);
                    // SAFETY: `fill` wrote every element (what is checked).
                    let got: Vec<u32> = out
                        .iter()
                        .map(|x| unsafe { x.assume_init() }.to_bits())
                        .collect();
                    assert_eq!(got, want[from..from + len], "row {row_len}, {from}+{len}");
                }
            }
        }
    }

    fn tiny_ckpt() -> Checkpoint {
        let norm = Normalization {
            center: glam::DVec3::new(1.25, -3.0, 1e6 + 0.1),
            extent: glam::DVec3::new(2.0, 0.5, 3.000001),
        };
        init_checkpoint(&ModelConfig::tiny(), 7, norm, 3).unwrap()
    }

    /// The normalisation survives save → load → save bit for bit. (serde_json's default float
    /// parser is not correctly rounded: 3.8783797363020547 came back 1 ulp off and a resumed run
    /// wrote different metadata; the `float_roundtrip` feature fixes it.)
    #[test]
    fn normalization_metadata_roundtrips_exactly() {
        let mut rng = 0x9E37_79B9_7F4A_7C15u64;
        let mut vals = vec![
            3.8783797363020547,
            0.1,
            1e6 + 0.1,
            200.000001,
            20.74016173978561,
        ];
        for _ in 0..2000 {
            rng = rng
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            vals.push(f64::from_bits((rng >> 2) & 0x3FFF_FFFF_FFFF_FFFF) % 1e7);
        }
        for w in vals.chunks(3).filter(|w| w.len() == 3) {
            let n = Normalization {
                center: glam::DVec3::new(w[0], w[1], w[2]),
                extent: glam::DVec3::new(w[2], w[1], w[0]),
            };
            let back: Normalization =
                serde_json::from_str(&serde_json::to_string(&n).unwrap()).unwrap();
            assert_eq!(back, n, "{}", serde_json::to_string(&n).unwrap());
        }
    }

    #[test]
    fn checkpoint_roundtrip_exact() {
        let c = tiny_ckpt();
        let bytes = c.to_tensor_file().unwrap().to_bytes().unwrap();
        let back =
            Checkpoint::from_tensor_file(&TensorFile::from_bytes(&bytes, "mem").unwrap()).unwrap();
        assert_eq!(back.model.cfg, c.model.cfg);
        assert_eq!(back.model.layout, c.model.layout);
        assert_eq!(back.normalization, c.normalization);
        assert!(back
            .params
            .iter()
            .zip(&c.params)
            .all(|(a, b)| a.to_bits() == b.to_bits()));
        assert_eq!(back.model.grid_h.scales, c.model.grid_h.scales);
        // Deterministic bytes.
        assert_eq!(bytes, back.to_tensor_file().unwrap().to_bytes().unwrap());
        // SPEC §6 names.
        let f = c.to_tensor_file().unwrap();
        for name in [
            "grid_h.table",
            "grid_h.scales",
            "grid_h.offsets",
            "grid_d.table",
            "deform.layers.0.weight",
            "deform.layers.1.weight",
            "shader.layers.0.weight",
            "shader.layers.1.weight",
            "appearance.codes",
        ] {
            assert!(f.tensors.contains_key(name), "{name}");
        }
        assert_eq!(f.tensors["appearance.codes"].shape, vec![3, 2]);
    }

    #[test]
    fn loading_uses_saved_scales() {
        let c = tiny_ckpt();
        let mut f = c.to_tensor_file().unwrap();
        let mut s = c.model.grid_h.scales.clone();
        s[1] = f32::from_bits(s[1].to_bits() - 1); // an ulp lower: same resolution
        f.insert("grid_h.scales", Tensor::f32(vec![s.len()], &s).unwrap());
        let back = Checkpoint::from_tensor_file(&f).unwrap();
        assert_eq!(back.model.grid_h.scales, s);
    }

    #[test]
    fn switched_off_parts_have_no_tensors() {
        let mut cfg = ModelConfig::tiny();
        cfg.deform.enabled = false;
        cfg.appearance_dim = 0;
        let c = init_checkpoint(&cfg, 1, Normalization::unit(), 5).unwrap();
        let f = c.to_tensor_file().unwrap();
        assert!(f.tensors.keys().all(|k| !k.starts_with("grid_d")
            && !k.starts_with("deform")
            && !k.starts_with("appearance")));
        Checkpoint::from_tensor_file(&f).unwrap();
    }

    #[test]
    fn bad_checkpoints_are_named_errors() {
        let c = tiny_ckpt();
        let good = c.to_tensor_file().unwrap();
        let mut f = good.clone();
        f.tensors.remove("shader.layers.1.weight");
        let e = format!("{:#}", Checkpoint::from_tensor_file(&f).unwrap_err());
        assert!(e.contains("shader.layers.1.weight"), "{e}");
        let mut f = good.clone();
        f.set_meta("format", "xscale-0");
        assert!(format!("{:#}", Checkpoint::from_tensor_file(&f).unwrap_err()).contains("format"));
        let mut f = good.clone();
        f.insert(
            "grid_h.offsets",
            Tensor::u32(vec![5], &[0, 1, 2, 3, 4]).unwrap(),
        );
        assert!(
            format!("{:#}", Checkpoint::from_tensor_file(&f).unwrap_err())
                .contains("grid_h.offsets")
        );
        let mut f = good.clone();
        f.insert(
            "appearance.codes",
            Tensor::f32(vec![2, 2], &[0.0; 4]).unwrap(),
        );
        assert!(
            format!("{:#}", Checkpoint::from_tensor_file(&f).unwrap_err())
                .contains("appearance.codes")
        );
        let mut f = good.clone();
        let mut w = f.tensors["shader.layers.0.weight"].to_f32().unwrap();
        w[3] = f32::NAN;
        f.insert(
            "shader.layers.0.weight",
            Tensor::f32(vec![16, 26], &w).unwrap(),
        );
        let e = format!("{:#}", Checkpoint::from_tensor_file(&f).unwrap_err());
        assert!(e.contains("shader.layers.0.weight element 3"), "{e}");
        let mut f = good;
        f.set_meta("normalization", "{\"center\":[0,0]}");
        assert!(
            format!("{:#}", Checkpoint::from_tensor_file(&f).unwrap_err())
                .contains("normalization")
        );
    }

    #[test]
    fn batch_roundtrip_and_validation() {
        let b = Batch::random(3, 20, 4, 3, 0.3);
        let mut f = TensorFile::new();
        batch_to_tensors(&mut f, &b).unwrap();
        let bytes = f.to_bytes().unwrap();
        let back = batch_from_tensors(&TensorFile::from_bytes(&bytes, "mem").unwrap()).unwrap();
        assert_eq!(back, b);
        let mut bad = b.clone();
        for j in 0..4 {
            bad.valid[5 * 4 + j] = 0;
        }
        let mut f = TensorFile::new();
        batch_to_tensors(&mut f, &bad).unwrap();
        let e = format!("{:#}", batch_from_tensors(&f).unwrap_err());
        assert!(e.contains("pixel 5"), "{e}");
    }

    /// A batch given as the checkpoint, or the other way round, is named as what it is.
    #[test]
    fn a_file_of_another_kind_is_named() {
        let mut batch = TensorFile::new();
        batch_to_tensors(&mut batch, &Batch::random(3, 4, 4, 3, 0.3)).unwrap();
        let e = format!("{:#}", Checkpoint::from_tensor_file(&batch).unwrap_err());
        assert!(
            e.contains("not a checkpoint") && e.contains("a batch") && e.contains("swapped"),
            "{e}"
        );
        let ckpt = tiny_ckpt().to_tensor_file().unwrap();
        let e = format!("{:#}", batch_from_tensors(&ckpt).unwrap_err());
        assert!(
            e.contains("not a batch") && e.contains("a checkpoint"),
            "{e}"
        );
        let mut dump = ckpt.clone();
        dump.insert("grad.grid_h.table", Tensor::f32(vec![1], &[0.0]).unwrap());
        let e = format!("{:#}", Checkpoint::from_tensor_file(&dump).unwrap_err());
        assert!(e.contains("a dump") && !e.contains("swapped"), "{e}");
    }

    #[test]
    fn dump_has_every_tensor_and_agrees_with_the_model() {
        let c = tiny_ckpt();
        let b = Batch::random(4, 300, 4, 3, 0.3);
        let d = dump::<f64>(&c, &b).unwrap();
        let n = 300;
        let shapes: &[(&str, &[usize])] = &[
            ("fwd.grid_h", &[n, 4, 8]),
            ("fwd.grid_d", &[n, 4, 4]),
            ("fwd.deform", &[n, 4, 8]),
            ("fwd.deform_hidden.0", &[n, 4, 8]),
            ("fwd.pooled", &[n, 8]),
            ("fwd.sh", &[n, 16]),
            ("fwd.shader_in", &[n, 26]),
            ("fwd.shader_hidden.0", &[n, 16]),
            ("fwd.logits", &[n, 3]),
            ("fwd.rgb", &[n, 3]),
            ("loss", &[]),
            (
                "grad.grid_h.table",
                &c.model.layout.get("grid_h.table").unwrap().shape,
            ),
            ("grad.appearance.codes", &[3, 2]),
            ("grad.batch.positions", &[n, 4, 3]),
            ("grad.batch.dirs", &[n, 3]),
            ("batch.positions", &[n, 4, 3]),
            ("shader.layers.0.weight", &[16, 26]),
        ];
        for (name, shape) in shapes {
            let t = d.get(name).unwrap();
            assert_eq!(&t.shape[..], *shape, "{name}");
        }
        for t in &c.model.layout.tensors {
            assert!(
                d.tensors.contains_key(&format!("grad.{}", t.name)),
                "grad.{}",
                t.name
            );
        }
        assert_eq!(d.get("fwd.rgb").unwrap().dtype, DType::F64);
        // Invalid rows are zero; valid rows of F_H are not.
        let gh = d.get_f64("fwd.grid_h").unwrap();
        let gp = d.get_f64("grad.batch.positions").unwrap();
        for k in 0..n * 4 {
            let row = &gh[k * 8..(k + 1) * 8];
            if b.valid[k] == 0 {
                assert!(row.iter().all(|&v| v == 0.0));
                assert!(gp[k * 3..k * 3 + 3].iter().all(|&v| v == 0.0));
            } else {
                assert!(row.iter().any(|&v| v != 0.0));
            }
        }
        // Independent recomputation of rgb and loss from the dumped logits (σ, L1 mean).
        let logits = d.get_f64("fwd.logits").unwrap();
        let rgb = d.get_f64("fwd.rgb").unwrap();
        let mut l = 0.0;
        for i in 0..n * 3 {
            let s = 1.0 / (1.0 + (-logits[i]).exp());
            assert!((s - rgb[i]).abs() < 1e-15);
            l += (s - b.target[i / 3][i % 3] as f64).abs();
        }
        let loss = d.get_f64("loss").unwrap()[0];
        assert!((l / (3 * n) as f64 - loss).abs() < 1e-14);
        // ξ starts at zero: the deformation delta is exactly zero at initialisation.
        assert!(d.get_f64("fwd.deform").unwrap().iter().all(|&v| v == 0.0));
        // f32 dump agrees with the f64 one to f32 accuracy.
        let d32 = dump::<f32>(&c, &b).unwrap();
        assert_eq!(d32.get("fwd.rgb").unwrap().dtype, DType::F32);
        let rgb32 = d32.get_f64("fwd.rgb").unwrap();
        assert!(rgb.iter().zip(&rgb32).all(|(a, b)| (a - b).abs() < 1e-5));
    }
}
