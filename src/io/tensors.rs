//! Owned tensors and safetensors files (SPEC §6).
//!
//! This file owns the on-disk tensor format of every checkpoint, batch and dump: a thin layer over
//! the `safetensors` crate that
//! - keeps tensors as owned little-endian bytes with a small dtype set (`F64, F32, U32, I32, U8`),
//! - reads a whole file, validated by the `safetensors` crate (header, offsets, sizes), with every
//!   error naming the file (and the tensor),
//! - writes the standard format (8-byte little-endian header length, JSON header with the string
//!   metadata under `__metadata__`, padded with spaces to a multiple of 8, then the raw data), so
//!   PyTorch / NumPy / JAX `safetensors.*.load_file` read it,
//! - writes **byte-identical** files for identical content. The header is written here rather than
//!   by `safetensors::serialize`, because that function keeps the metadata in a `HashMap` whose
//!   iteration order (and hence the header bytes) changes from run to run. Layout: the header lists
//!   `__metadata__` (keys sorted) first, then the tensors in data order; data is ordered by element
//!   size descending (8, 4, 1 bytes), then by name — the same order the `safetensors` crate uses,
//!   which keeps every tensor aligned to its element size inside the data section,
//! - writes atomically: a temporary file in the destination directory, `fsync`, `rename`, then an
//!   `fsync` of the directory (Unix), so a crash leaves either the old file or the new one.
//!
//! Constructors check that the data length matches the shape and return `Result` (never panic).
//! A shape `[]` is a scalar with one element (`numel` = product of an empty shape = 1).

use anyhow::{anyhow, bail, Context, Result};
use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};

/// Element types this project stores. Names follow safetensors (`"F64"`, `"F32"`, …).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum DType {
    F64,
    F32,
    U32,
    I32,
    U8,
}

impl DType {
    /// Bytes per element.
    pub fn size(self) -> usize {
        match self {
            DType::F64 => 8,
            DType::F32 | DType::U32 | DType::I32 => 4,
            DType::U8 => 1,
        }
    }

    /// The safetensors spelling (`"F32"`, …).
    pub fn name(self) -> &'static str {
        match self {
            DType::F64 => "F64",
            DType::F32 => "F32",
            DType::U32 => "U32",
            DType::I32 => "I32",
            DType::U8 => "U8",
        }
    }

    /// True for F64 and F32.
    pub fn is_float(self) -> bool {
        matches!(self, DType::F64 | DType::F32)
    }

    fn from_safetensors(d: safetensors::Dtype) -> Option<DType> {
        use safetensors::Dtype as S;
        Some(match d {
            S::F64 => DType::F64,
            S::F32 => DType::F32,
            S::U32 => DType::U32,
            S::I32 => DType::I32,
            S::U8 => DType::U8,
            _ => return None,
        })
    }
}

impl std::fmt::Display for DType {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// An owned tensor: dtype, shape (row-major, C order) and little-endian element bytes.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Tensor {
    pub dtype: DType,
    pub shape: Vec<usize>,
    /// Little-endian element bytes, row-major; `data.len() == numel() * dtype.size()`.
    pub data: Vec<u8>,
}

/// Number of elements of a shape (1 for the scalar shape `[]`); `None` on overflow.
fn shape_numel(shape: &[usize]) -> Option<usize> {
    shape.iter().try_fold(1usize, |acc, &d| acc.checked_mul(d))
}

/// The little-endian bytes of a slice of plain numbers: one copy on a little-endian machine (each
/// element's bytes then reversed on a big-endian one).
pub fn le_bytes<T: bytemuck::Pod>(values: &[T]) -> Vec<u8> {
    let mut b = bytemuck::cast_slice::<T, u8>(values).to_vec();
    if cfg!(target_endian = "big") {
        for c in b.chunks_exact_mut(std::mem::size_of::<T>()) {
            c.reverse();
        }
    }
    b
}

macro_rules! typed_constructor_and_accessor {
    ($ctor:ident, $acc:ident, $into:ident, $t:ty, $variant:ident) => {
        #[doc = concat!("A ", stringify!($variant), " tensor; error if `values.len()` is not the product of `shape`.")]
        pub fn $ctor(shape: Vec<usize>, values: &[$t]) -> Result<Tensor> {
            Self::check_len(&shape, values.len(), DType::$variant)?;
            Ok(Tensor {
                dtype: DType::$variant,
                shape,
                data: le_bytes(values),
            })
        }

        #[doc = concat!("The elements as `", stringify!($t), "`; error unless the dtype is ", stringify!($variant), ".")]
        pub fn $acc(&self) -> Result<Vec<$t>> {
            let mut out = vec![<$t>::default(); self.data.len() / std::mem::size_of::<$t>()];
            self.$into(&mut out)?;
            Ok(out)
        }

        #[doc = concat!("[`Tensor::", stringify!($acc), "`] written into `out` (no intermediate vector); error unless the dtype is ", stringify!($variant), " and `out` has one slot per element.")]
        pub fn $into(&self, out: &mut [$t]) -> Result<()> {
            self.expect_dtype(DType::$variant)?;
            const SIZE: usize = std::mem::size_of::<$t>();
            if out.len() * SIZE != self.data.len() {
                bail!(
                    "tensor of shape {:?} has {} elements, expected {}",
                    self.shape,
                    self.data.len() / SIZE,
                    out.len()
                );
            }
            for (o, c) in out.iter_mut().zip(self.data.chunks_exact(SIZE)) {
                *o = <$t>::from_le_bytes(c.try_into().unwrap());
            }
            Ok(())
        }
    };
}

impl Tensor {
    /// A tensor from raw little-endian bytes; error if the byte count does not match the shape.
    pub fn from_bytes(dtype: DType, shape: Vec<usize>, data: Vec<u8>) -> Result<Tensor> {
        Self::check_bytes(dtype, &shape, data.len())?;
        Ok(Tensor { dtype, shape, data })
    }

    /// Error unless `bytes` is the byte count of a `dtype` tensor of `shape`.
    fn check_bytes(dtype: DType, shape: &[usize], bytes: usize) -> Result<()> {
        let n =
            shape_numel(shape).ok_or_else(|| anyhow!("shape {shape:?} has too many elements"))?;
        if n.checked_mul(dtype.size()) != Some(bytes) {
            bail!(
                "{dtype} tensor of shape {shape:?} needs {n} elements ({} bytes), got {bytes} bytes",
                n.saturating_mul(dtype.size()),
            );
        }
        Ok(())
    }

    fn check_len(shape: &[usize], len: usize, dtype: DType) -> Result<()> {
        match shape_numel(shape) {
            Some(n) if n == len => Ok(()),
            Some(n) => bail!("{dtype} tensor of shape {shape:?} needs {n} elements, got {len}"),
            None => bail!("shape {shape:?} has too many elements"),
        }
    }

    fn expect_dtype(&self, want: DType) -> Result<()> {
        if self.dtype != want {
            bail!(
                "tensor of shape {:?} is {}, expected {}",
                self.shape,
                self.dtype,
                want
            );
        }
        Ok(())
    }

    typed_constructor_and_accessor!(f32, to_f32, copy_f32_into, f32, F32);
    typed_constructor_and_accessor!(u32, to_u32, copy_u32_into, u32, U32);
    typed_constructor_and_accessor!(i32, to_i32, copy_i32_into, i32, I32);
    typed_constructor_and_accessor!(u8, to_u8, copy_u8_into, u8, U8);

    /// An F64 tensor; error if `values.len()` is not the product of `shape`.
    pub fn f64(shape: Vec<usize>, values: &[f64]) -> Result<Tensor> {
        Self::check_len(&shape, values.len(), DType::F64)?;
        Ok(Tensor {
            dtype: DType::F64,
            shape,
            data: le_bytes(values),
        })
    }

    /// A scalar (shape `[]`) F32 tensor, e.g. `loss`.
    pub fn scalar_f32(v: f32) -> Tensor {
        Tensor {
            dtype: DType::F32,
            shape: vec![],
            data: v.to_le_bytes().to_vec(),
        }
    }

    /// A scalar (shape `[]`) F64 tensor.
    pub fn scalar_f64(v: f64) -> Tensor {
        Tensor {
            dtype: DType::F64,
            shape: vec![],
            data: v.to_le_bytes().to_vec(),
        }
    }

    /// The elements as f64: F64 as stored, F32 widened exactly. Other dtypes are an error
    /// (use [`Tensor::to_f64_any`] to widen integers too).
    pub fn to_f64(&self) -> Result<Vec<f64>> {
        match self.dtype {
            DType::F64 => Ok(self
                .data
                .chunks_exact(8)
                .map(|c| f64::from_le_bytes(c.try_into().unwrap()))
                .collect()),
            DType::F32 => Ok(self.to_f32()?.into_iter().map(f64::from).collect()),
            _ => bail!(
                "tensor of shape {:?} is {}, expected F64 or F32",
                self.shape,
                self.dtype
            ),
        }
    }

    /// The elements as f64 whatever the dtype (every supported dtype widens exactly).
    pub fn to_f64_any(&self) -> Vec<f64> {
        match self.dtype {
            DType::F64 | DType::F32 => self.to_f64().unwrap(),
            DType::U32 => self.to_u32().unwrap().into_iter().map(f64::from).collect(),
            DType::I32 => self.to_i32().unwrap().into_iter().map(f64::from).collect(),
            DType::U8 => self.data.iter().map(|&b| f64::from(b)).collect(),
        }
    }

    /// Number of elements (1 for a scalar).
    pub fn numel(&self) -> usize {
        self.data.len() / self.dtype.size()
    }
}

/// What is wrong with `bytes`, in words, for the `safetensors` crate's error `e` (its names, such
/// as `MetadataIncompleteBuffer`, say nothing to a user).
fn explain(e: &safetensors::SafeTensorError, bytes: &[u8]) -> String {
    use safetensors::SafeTensorError as E;
    let len = bytes.len();
    let header = bytes
        .get(..8)
        .map(|b| u64::from_le_bytes(b.try_into().unwrap()));
    let too_long = |n: u64| {
        format!(
            "its first 8 bytes give a header length of {n} bytes, larger than the file ({len} bytes)"
        )
    };
    match e {
        E::HeaderTooSmall => format!(
            "the file is {len} bytes long, too short for the 8-byte header length a safetensors file starts with"
        ),
        E::HeaderTooLarge | E::InvalidHeaderLength => match header {
            // Text or another format: its first bytes read as an absurd length.
            Some(n) if n > len as u64 - 8 && n > 100_000_000 => too_long(n),
            Some(n) if n > len as u64 - 8 => format!("truncated header: {}", too_long(n)),
            Some(n) => format!(
                "its first 8 bytes give a header length of {n} bytes, more than the 100 MB safetensors allows"
            ),
            None => e.to_string(),
        },
        E::InvalidHeader(u) => format!("its header is not UTF-8 text ({u})"),
        E::InvalidHeaderStart => "its header does not start with `{`".to_string(),
        E::InvalidHeaderDeserialization(j) | E::JsonError(j) => {
            format!("its header is not a safetensors JSON header: {j}")
        }
        E::MetadataIncompleteBuffer => {
            let n = header.unwrap_or(0);
            let data = len as u64 - 8 - n;
            match declared_data_bytes(bytes, n) {
                Some(d) if d > data => format!(
                    "truncated: its header declares {d} bytes of tensor data, but only {data} bytes follow the header"
                ),
                Some(d) => format!(
                    "{} bytes of extra data after the {d} bytes of tensor data its header declares",
                    data - d
                ),
                None => "the tensor data does not match the size its header declares".to_string(),
            }
        }
        E::InvalidOffset(name) => format!(
            "tensor {name}: its data_offsets do not start where the previous tensor's data ends (they must cover the data in order, without gaps)"
        ),
        E::TensorInvalidInfo => {
            "a tensor's data_offsets do not span its shape times its dtype's size".to_string()
        }
        E::ValidationOverflow => {
            "a tensor's shape has more elements than can be addressed (overflow)".to_string()
        }
        E::TensorNotFound(name) => format!("no tensor {name}"),
        E::InvalidTensorView(d, shape, n) => {
            format!("a {d} tensor of shape {shape:?} cannot hold {n} bytes")
        }
        E::MisalignedSlice => "a tensor does not end on a byte boundary".to_string(),
        E::IoError(io) => io.to_string(),
    }
}

/// The bytes of tensor data the JSON header of `bytes` (of length `n`) declares: the largest
/// end offset.
fn declared_data_bytes(bytes: &[u8], n: u64) -> Option<u64> {
    let text = std::str::from_utf8(bytes.get(8..8 + n as usize)?).ok()?;
    let v: serde_json::Value = serde_json::from_str(text).ok()?;
    v.as_object()?
        .iter()
        .filter(|(k, _)| *k != "__metadata__")
        .filter_map(|(_, t)| t.get("data_offsets")?.get(1)?.as_u64())
        .max()
        .or(Some(0))
}

/// A tensor left in a mapped file ([`TensorFile::with_mapped`]): its little-endian bytes, of
/// the length its dtype and shape need.
#[derive(Clone, Debug)]
pub struct RawTensor<'a> {
    pub dtype: DType,
    pub shape: Vec<usize>,
    pub data: &'a [u8],
}

/// From this many bytes a tensor read from a file is copied in parallel, onto huge pages
/// ([`crate::memhint::copied`]).
const PARALLEL_COPY_BYTES: usize = 4 << 20;

/// A safetensors file in memory: string metadata (`__metadata__`) and named tensors.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TensorFile {
    pub metadata: BTreeMap<String, String>,
    pub tensors: BTreeMap<String, Tensor>,
    /// Where the file was read from (used in error messages); `None` for a file built in memory.
    pub source: Option<PathBuf>,
}

impl TensorFile {
    /// An empty file.
    pub fn new() -> TensorFile {
        TensorFile::default()
    }

    pub(crate) fn label(&self) -> String {
        match &self.source {
            Some(p) => p.display().to_string(),
            None => "<in-memory tensor file>".to_string(),
        }
    }

    /// Read and validate a safetensors file. Errors name the file (and the tensor).
    pub fn read(path: impl AsRef<Path>) -> Result<TensorFile> {
        Self::read_only(path, |_| true)
    }

    /// [`TensorFile::read`] keeping only the tensors whose name `keep` accepts: the others are
    /// validated like every tensor (their offsets against the file's length) but never read
    /// from disk or copied: the file is memory-mapped, so only the kept tensors' pages are read
    /// (a model loaded to render or score skips the Adam state, three quarters of a training
    /// checkpoint).
    pub fn read_only(path: impl AsRef<Path>, keep: impl Fn(&str) -> bool) -> Result<TensorFile> {
        Self::with_mapped(path, keep, |_| false, |f, _| Ok(f))
    }

    /// [`TensorFile::read_only`] leaving the kept tensors `defer` accepts in the mapped file:
    /// `with(file, raw)` gets the file of the other kept tensors and the deferred ones' bytes by
    /// name (validated like every tensor), read while the map lives. A model loaded to render
    /// copies its hash tables once, straight into its parameter buffer, instead of into a
    /// tensor first (that copy's fresh pages were half of `render`'s load time).
    pub fn with_mapped<T>(
        path: impl AsRef<Path>,
        keep: impl Fn(&str) -> bool,
        defer: impl Fn(&str) -> bool,
        with: impl FnOnce(TensorFile, &BTreeMap<String, RawTensor>) -> Result<T>,
    ) -> Result<T> {
        let path = path.as_ref();
        let file = std::fs::File::open(path)
            .with_context(|| format!("{}: cannot read", path.display()))?;
        // SAFETY: the map is read while this function runs and dropped before it returns; every
        // kept tensor is copied out of it (the deferred ones by `with`, which cannot keep a
        // borrow of them). Mapping is undefined behaviour only if another process changes the
        // file in place meanwhile: xscale never does (files are written to a temporary name and
        // renamed over, `io/atomic.rs`, which leaves a mapped file's bytes as they were). A file
        // that cannot be mapped (an empty file, a pipe) is read instead.
        let map = unsafe { memmap2::Mmap::map(&file) };
        let read;
        let bytes: &[u8] = match &map {
            Ok(m) => m,
            Err(_) => {
                read = std::fs::read(path)
                    .with_context(|| format!("{}: cannot read", path.display()))?;
                &read
            }
        };
        let (mut f, raw) = Self::from_bytes_only(bytes, &path.display().to_string(), keep, defer)?;
        f.source = Some(path.to_path_buf());
        with(f, &raw)
    }

    /// Parse a safetensors byte buffer; `label` names it in error messages.
    pub fn from_bytes(bytes: &[u8], label: &str) -> Result<TensorFile> {
        Ok(Self::from_bytes_only(bytes, label, |_| true, |_| false)?.0)
    }

    /// [`TensorFile::from_bytes`] keeping only the tensors `keep` accepts, those `defer` accepts
    /// left in `bytes` (checked, not copied).
    fn from_bytes_only<'a>(
        bytes: &'a [u8],
        label: &str,
        keep: impl Fn(&str) -> bool,
        defer: impl Fn(&str) -> bool,
    ) -> Result<(TensorFile, BTreeMap<String, RawTensor<'a>>)> {
        let invalid = |e| {
            anyhow!(
                "{label}: not a valid safetensors file: {}",
                explain(&e, bytes)
            )
        };
        let (_, meta) = safetensors::SafeTensors::read_metadata(bytes).map_err(invalid)?;
        let st = safetensors::SafeTensors::deserialize(bytes).map_err(invalid)?;
        let metadata: BTreeMap<String, String> = meta
            .metadata()
            .as_ref()
            .map(|m| m.iter().map(|(k, v)| (k.clone(), v.clone())).collect())
            .unwrap_or_default();
        let mut tensors = BTreeMap::new();
        let mut raw = BTreeMap::new();
        for (name, view) in st.iter() {
            let dtype = DType::from_safetensors(view.dtype()).ok_or_else(|| {
                anyhow!(
                    "{label}: tensor {name}: dtype {} is not supported (expected F64, F32, U32, I32 or U8)",
                    view.dtype()
                )
            })?;
            if !keep(name) {
                continue;
            }
            if defer(name) {
                let shape = view.shape().to_vec();
                Tensor::check_bytes(dtype, &shape, view.data().len())
                    .with_context(|| format!("{label}: tensor {name}"))?;
                let (data, shape) = (view.data(), shape);
                raw.insert(name.to_string(), RawTensor { dtype, shape, data });
                continue;
            }
            // A large tensor (a hash table) is copied in parallel pieces onto huge pages: one
            // thread copying it into fresh 4 KiB pages was most of the time `render` took to
            // load a `small` checkpoint (docs/changelog.md).
            let data = if view.data().len() >= PARALLEL_COPY_BYTES {
                crate::memhint::copied(view.data())
            } else {
                view.data().to_vec()
            };
            let t = Tensor::from_bytes(dtype, view.shape().to_vec(), data)
                .with_context(|| format!("{label}: tensor {name}"))?;
            tensors.insert(name.to_string(), t);
        }
        let file = TensorFile {
            metadata,
            tensors,
            source: None,
        };
        Ok((file, raw))
    }

    /// Insert (or replace) a tensor.
    pub fn insert(&mut self, name: impl Into<String>, t: Tensor) {
        self.tensors.insert(name.into(), t);
    }

    /// Set a metadata string.
    pub fn set_meta(&mut self, key: impl Into<String>, value: impl Into<String>) {
        self.metadata.insert(key.into(), value.into());
    }

    /// A metadata string; error names the file and the key.
    pub fn meta(&self, key: &str) -> Result<&str> {
        self.metadata.get(key).map(String::as_str).ok_or_else(|| {
            anyhow!(
                "{}: header metadata has no key \"{key}\" (keys: {})",
                self.label(),
                list_some(self.metadata.keys())
            )
        })
    }

    /// A tensor by name; error "missing tensor X in FILE" listing a few names present.
    pub fn get(&self, name: &str) -> Result<&Tensor> {
        self.tensors.get(name).ok_or_else(|| {
            anyhow!(
                "missing tensor {name} in {} (it has {} tensors: {})",
                self.label(),
                self.tensors.len(),
                list_some(self.tensors.keys())
            )
        })
    }

    /// A tensor by name, checked to have exactly this dtype and shape.
    pub fn get_checked(&self, name: &str, dtype: DType, shape: &[usize]) -> Result<&Tensor> {
        let t = self.get(name)?;
        self.check_type(name, (t.dtype, &t.shape), dtype, shape)?;
        Ok(t)
    }

    /// Error (naming this file and tensor `name`) unless `found` (dtype, shape) is `dtype` of
    /// `shape`: [`TensorFile::get_checked`]'s check, also for a tensor left in the mapped file
    /// ([`RawTensor`]).
    pub(crate) fn check_type(
        &self,
        name: &str,
        found: (DType, &[usize]),
        dtype: DType,
        shape: &[usize],
    ) -> Result<()> {
        if found.0 != dtype || found.1 != shape {
            bail!(
                "{}: tensor {name} is {} {:?}, expected {} {:?}",
                self.label(),
                found.0,
                found.1,
                dtype,
                shape
            );
        }
        Ok(())
    }

    /// `get(name)?.to_f32()` with the file and tensor named in errors.
    pub fn get_f32(&self, name: &str) -> Result<Vec<f32>> {
        self.get(name)?
            .to_f32()
            .with_context(|| format!("{}: tensor {name}", self.label()))
    }
    /// `get(name)?.to_f64()` (F64, or F32 widened exactly) with the file and tensor named in errors.
    pub fn get_f64(&self, name: &str) -> Result<Vec<f64>> {
        self.get(name)?
            .to_f64()
            .with_context(|| format!("{}: tensor {name}", self.label()))
    }
    /// `get(name)?.to_u32()` with the file and tensor named in errors.
    pub fn get_u32(&self, name: &str) -> Result<Vec<u32>> {
        self.get(name)?
            .to_u32()
            .with_context(|| format!("{}: tensor {name}", self.label()))
    }
    /// `get(name)?.to_i32()` with the file and tensor named in errors.
    pub fn get_i32(&self, name: &str) -> Result<Vec<i32>> {
        self.get(name)?
            .to_i32()
            .with_context(|| format!("{}: tensor {name}", self.label()))
    }
    /// `get(name)?.to_u8()` with the file and tensor named in errors.
    pub fn get_u8(&self, name: &str) -> Result<Vec<u8>> {
        self.get(name)?
            .to_u8()
            .with_context(|| format!("{}: tensor {name}", self.label()))
    }

    /// Data order: element size descending, then name (keeps every tensor aligned).
    fn data_order(&self) -> Vec<(&String, &Tensor)> {
        let mut v: Vec<_> = self.tensors.iter().collect();
        v.sort_by(|(na, ta), (nb, tb)| {
            tb.dtype
                .size()
                .cmp(&ta.dtype.size())
                .then_with(|| na.cmp(nb))
        });
        v
    }

    /// The header bytes (JSON padded with spaces to a multiple of 8), deterministic.
    fn header(&self) -> Result<Vec<u8>> {
        let mut h = String::from("{");
        let mut first = true;
        if !self.metadata.is_empty() {
            h.push_str("\"__metadata__\":{");
            for (i, (k, v)) in self.metadata.iter().enumerate() {
                if i > 0 {
                    h.push(',');
                }
                h.push_str(&serde_json::to_string(k)?);
                h.push(':');
                h.push_str(&serde_json::to_string(v)?);
            }
            h.push('}');
            first = false;
        }
        let mut offset = 0usize;
        for (name, t) in self.data_order() {
            if name == "__metadata__" {
                bail!("a tensor may not be named __metadata__");
            }
            if t.data.len() != shape_numel(&t.shape).unwrap_or(usize::MAX) * t.dtype.size() {
                bail!(
                    "tensor {name}: {} bytes do not match {} shape {:?}",
                    t.data.len(),
                    t.dtype,
                    t.shape
                );
            }
            if !first {
                h.push(',');
            }
            first = false;
            let end = offset + t.data.len();
            h.push_str(&serde_json::to_string(name)?);
            h.push_str(&format!(
                ":{{\"dtype\":\"{}\",\"shape\":{},\"data_offsets\":[{offset},{end}]}}",
                t.dtype.name(),
                serde_json::to_string(&t.shape)?
            ));
            offset = end;
        }
        h.push('}');
        let mut bytes = h.into_bytes();
        let padded = bytes.len().next_multiple_of(8);
        bytes.resize(padded, b' ');
        Ok(bytes)
    }

    /// Write the standard safetensors byte stream to `w`.
    pub fn write_to(&self, w: &mut impl Write) -> Result<()> {
        let header = self.header()?;
        w.write_all(&(header.len() as u64).to_le_bytes())?;
        w.write_all(&header)?;
        for (_, t) in self.data_order() {
            w.write_all(&t.data)?;
        }
        Ok(())
    }

    /// The whole file as bytes (identical content → identical bytes).
    pub fn to_bytes(&self) -> Result<Vec<u8>> {
        let mut v = Vec::new();
        self.write_to(&mut v)?;
        Ok(v)
    }

    /// Write atomically ([`crate::io::atomic::write_atomic`], durable): temp file in the same
    /// directory, fsync, rename over `path`, fsync the directory. On error the temp file is removed
    /// and `path` is untouched.
    pub fn write_atomic(&self, path: impl AsRef<Path>) -> Result<()> {
        crate::io::atomic::write_atomic(path.as_ref(), true, |tmp| {
            let file = std::fs::File::create(tmp)
                .with_context(|| format!("{}: cannot create", tmp.display()))?;
            let mut w = std::io::BufWriter::with_capacity(1 << 20, file);
            self.write_to(&mut w)
                .with_context(|| format!("{}: write failed", tmp.display()))?;
            w.flush()
                .with_context(|| format!("{}: write failed", tmp.display()))
        })
    }
}

/// "a, b, c, … (+N more)" for error messages.
fn list_some<'a>(names: impl Iterator<Item = &'a String>) -> String {
    let all: Vec<&String> = names.collect();
    if all.is_empty() {
        return "none".to_string();
    }
    let shown: Vec<&str> = all.iter().take(8).map(|s| s.as_str()).collect();
    let mut s = shown.join(", ");
    if all.len() > 8 {
        s.push_str(&format!(", … (+{} more)", all.len() - 8));
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> TensorFile {
        let mut f = TensorFile::new();
        f.set_meta("format", "xscale-1");
        f.set_meta("config", "a = 1\n\"quoted\" = \"x\"\n");
        f.set_meta("normalization", "{\"center\":[0.5,0.5,0.5]}");
        f.insert("b.u8", Tensor::u8(vec![3], &[1, 2, 3]).unwrap());
        f.insert(
            "a.f32",
            Tensor::f32(vec![2, 2], &[1.0, -2.5, f32::NAN, 1e-30]).unwrap(),
        );
        f.insert(
            "c.f64",
            Tensor::f64(vec![3], &[0.1, -0.0, f64::INFINITY]).unwrap(),
        );
        f.insert("d.u32", Tensor::u32(vec![2], &[7, u32::MAX]).unwrap());
        f.insert("e.i32", Tensor::i32(vec![1, 2], &[-7, i32::MIN]).unwrap());
        f.insert("loss", Tensor::scalar_f32(0.25));
        f.insert("empty", Tensor::f32(vec![0, 3], &[]).unwrap());
        f
    }

    #[test]
    fn length_mismatch_is_an_error() {
        let e = Tensor::f32(vec![2, 3], &[1.0; 5]).unwrap_err().to_string();
        assert!(e.contains("needs 6 elements, got 5"), "{e}");
        assert!(Tensor::from_bytes(DType::F64, vec![2], vec![0; 15]).is_err());
    }

    #[test]
    fn bytes_roundtrip_and_parse_by_safetensors_crate() {
        let f = sample();
        let bytes = f.to_bytes().unwrap();
        let header_len = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
        assert_eq!(header_len % 8, 0, "header padded to 8 bytes");
        assert_eq!(bytes[8], b'{');
        // The reference parser accepts it and sees the same tensors and metadata.
        let st = safetensors::SafeTensors::deserialize(&bytes).unwrap();
        assert_eq!(st.len(), f.tensors.len());
        let v = st.tensor("a.f32").unwrap();
        assert_eq!(v.dtype(), safetensors::Dtype::F32);
        assert_eq!(v.shape(), &[2, 2]);
        assert_eq!(v.data(), &f.tensors["a.f32"].data[..]);
        let (_, m) = safetensors::SafeTensors::read_metadata(&bytes).unwrap();
        let m = m.metadata().clone().unwrap();
        assert_eq!(m["config"], f.metadata["config"]);
        // Our reader gets the same back (bit for bit, NaN included).
        let g = TensorFile::from_bytes(&bytes, "mem").unwrap();
        assert_eq!(g, f);
        assert!(g.get_f32("a.f32").unwrap()[2].is_nan());
        assert_eq!(
            g.get_f64("c.f64").unwrap()[1].to_bits(),
            (-0.0f64).to_bits()
        );
        assert_eq!(g.get("loss").unwrap().numel(), 1);
        assert_eq!(g.get("empty").unwrap().numel(), 0);
    }

    #[test]
    fn data_is_aligned_to_element_size() {
        let bytes = sample().to_bytes().unwrap();
        let (n, m) = safetensors::SafeTensors::read_metadata(&bytes).unwrap();
        for (_, info) in m.tensors() {
            let elem = info.dtype.bitsize() / 8;
            assert_eq!((8 + n + info.data_offsets.0) % elem, 0);
        }
    }

    #[test]
    fn identical_content_gives_identical_bytes() {
        let a = sample().to_bytes().unwrap();
        // Build the same content in a different insertion order.
        let s = sample();
        let mut f = TensorFile::new();
        for (k, v) in s.metadata.iter().rev() {
            f.set_meta(k.clone(), v.clone());
        }
        for (k, v) in s.tensors.iter().rev() {
            f.insert(k.clone(), v.clone());
        }
        assert_eq!(a, f.to_bytes().unwrap());
    }

    #[test]
    fn reads_file_written_by_safetensors_crate() {
        let vals = [1.0f32, 2.0, 3.0];
        let data: Vec<u8> = vals.iter().flat_map(|v| v.to_le_bytes()).collect();
        let view =
            safetensors::tensor::TensorView::new(safetensors::Dtype::F32, vec![3], &data).unwrap();
        let mut meta = std::collections::HashMap::new();
        meta.insert("format".to_string(), "x".to_string());
        let bytes = safetensors::serialize([("w", view)], Some(meta)).unwrap();
        let f = TensorFile::from_bytes(&bytes, "mem").unwrap();
        assert_eq!(f.get_f32("w").unwrap(), vals);
        assert_eq!(f.meta("format").unwrap(), "x");
    }

    #[test]
    fn read_only_keeps_the_accepted_tensors_and_still_checks_the_file() {
        let dir = std::env::temp_dir().join(format!("xscale-tensors-only-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("ck.safetensors");
        sample().write_atomic(&p).unwrap();
        let all = TensorFile::read(&p).unwrap();
        let some = TensorFile::read_only(&p, |n| n != "c.f64" && n != "b.u8").unwrap();
        let names: Vec<&String> = some.tensors.keys().collect();
        let expected: Vec<&String> = all
            .tensors
            .keys()
            .filter(|n| *n != "c.f64" && *n != "b.u8")
            .collect();
        assert!(expected.len() + 2 == all.tensors.len() && names == expected);
        for n in names {
            assert_eq!(some.tensors[n], all.tensors[n], "{n}");
        }
        assert_eq!(some.metadata, all.metadata);
        assert!(format!("{:#}", some.get("c.f64").unwrap_err()).contains("missing tensor c.f64"));
        // A truncated file is refused whatever is kept.
        let bytes = std::fs::read(&p).unwrap();
        let q = dir.join("trunc.safetensors");
        std::fs::write(&q, &bytes[..bytes.len() - 3]).unwrap();
        let e = format!("{:#}", TensorFile::read_only(&q, |_| false).unwrap_err());
        assert!(e.contains("trunc.safetensors"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn errors_name_file_and_tensor() {
        let dir = std::env::temp_dir().join(format!("xscale-tensors-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("m.safetensors");
        sample().write_atomic(&p).unwrap();
        let f = TensorFile::read(&p).unwrap();
        let e = f.get("nope").unwrap_err().to_string();
        assert!(
            e.contains("missing tensor nope in") && e.contains("m.safetensors"),
            "{e}"
        );
        assert!(e.contains("a.f32"), "{e}");
        let e = format!("{:#}", f.get_u32("a.f32").unwrap_err());
        assert!(e.contains("a.f32") && e.contains("expected U32"), "{e}");
        let e = format!("{:#}", f.meta("nokey").unwrap_err());
        assert!(e.contains("nokey") && e.contains("m.safetensors"), "{e}");
        assert!(f
            .get_checked("a.f32", DType::F32, &[4])
            .unwrap_err()
            .to_string()
            .contains("expected F32 [4]"));
        // Truncated file.
        let bytes = std::fs::read(&p).unwrap();
        let q = dir.join("trunc.safetensors");
        std::fs::write(&q, &bytes[..bytes.len() - 3]).unwrap();
        let e = format!("{:#}", TensorFile::read(&q).unwrap_err());
        assert!(e.contains("trunc.safetensors"), "{e}");
        // Garbage / too short / missing.
        std::fs::write(&q, b"abc").unwrap();
        assert!(format!("{:#}", TensorFile::read(&q).unwrap_err()).contains("trunc.safetensors"));
        let e = format!("{:#}", TensorFile::read(dir.join("absent")).unwrap_err());
        assert!(e.contains("absent"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn unsupported_dtype_is_an_error_naming_tensor() {
        let data = [0u8; 4];
        let view =
            safetensors::tensor::TensorView::new(safetensors::Dtype::F16, vec![2], &data).unwrap();
        let bytes = safetensors::serialize([("half", view)], None).unwrap();
        let e = TensorFile::from_bytes(&bytes, "h.st")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("h.st") && e.contains("half") && e.contains("F16"),
            "{e}"
        );
    }

    #[test]
    fn write_atomic_replaces_and_leaves_no_temp() {
        let dir = std::env::temp_dir().join(format!("xscale-atomic-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("ck.safetensors");
        std::fs::write(&p, b"old").unwrap();
        let f = sample();
        f.write_atomic(&p).unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), f.to_bytes().unwrap());
        let names: Vec<_> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(names.len(), 1, "{names:?}");
        // Writing into a missing directory fails and names the path.
        let e = format!(
            "{:#}",
            f.write_atomic(dir.join("no/such/x.st")).unwrap_err()
        );
        assert!(e.contains("no/such"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
