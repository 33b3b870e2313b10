//! `xscale._xscale`: the Python binding of the xscale oracle (PyO3 + rust-numpy).
//!
//! Every function here validates its arrays (type, dtype, C layout, shape, finiteness where the
//! model requires it) and then calls the SAME Rust function the command-line tool calls — no
//! second implementation: `HashGrid::forward` and its backward passes, `sh_forward`, `Mlp`,
//! `pool_forward`, `level_weights`, the loss, `appearance_*`, and `checkpoint::dump_with` for the
//! whole model step. Inputs are read in place (no copy) when they are NumPy arrays of the right
//! dtype and C-contiguous; anything else is a `TypeError` (not an array, wrong dtype) or a
//! `ValueError` (layout, shape, values) with the message naming the argument — the Rust errors'
//! own messages for everything the library checks. Results are new arrays.
//!
//! Computation runs without the GIL, in the module's own rayon pool (`set_num_threads`), inside
//! `catch_unwind`: a Rust panic (a bug) becomes a `RuntimeError`, never an abort of the
//! interpreter. Results are bit-identical for any thread count (SPEC §5), as in the CLI.
//!
//! The Python package `xscale` (python/xscale/) wraps this module.

use numpy::{
    Element, PyArray1, PyArrayDescrMethods, PyArrayDyn, PyArrayMethods, PyReadonlyArrayDyn,
    PyUntypedArray, PyUntypedArrayMethods,
};
use pyo3::exceptions::{PyRuntimeError, PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use xscale::io::tensors::{DType, Tensor, TensorFile};
use xscale::model::checkpoint::Checkpoint;
use xscale::model::config::{GridConfig, LossKind, PositionMode};
use xscale::model::hashgrid::{HashGrid, Touched};
use xscale::model::mlp::{Mlp, MlpActs};
use xscale::model::{hfm, level_weight, loss, mlp, sh, Real};

// ---------------------------------------------------------------------------------------------
// Errors, threads, the compute wrapper

fn value_error(e: impl std::fmt::Display) -> PyErr {
    PyValueError::new_err(e.to_string())
}

fn type_error(e: impl std::fmt::Display) -> PyErr {
    PyTypeError::new_err(e.to_string())
}

static POOL: Mutex<Option<Arc<rayon::ThreadPool>>> = Mutex::new(None);
/// Wall time of the last computation (the Rust call alone, without argument checking and array
/// conversion), for the call-overhead benchmark.
static LAST_NS: AtomicU64 = AtomicU64::new(0);

fn default_threads() -> usize {
    std::env::var("XSCALE_THREADS")
        .ok()
        .and_then(|s| s.trim().parse::<usize>().ok())
        .filter(|&n| n > 0)
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |c| c.get()))
}

fn build_pool(n: usize) -> PyResult<Arc<rayon::ThreadPool>> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(n)
        .thread_name(|i| format!("xscale-{i}"))
        .build()
        .map(Arc::new)
        .map_err(|e| PyRuntimeError::new_err(format!("cannot start {n} threads: {e}")))
}

fn pool() -> PyResult<Arc<rayon::ThreadPool>> {
    let mut g = POOL.lock().unwrap_or_else(|p| p.into_inner());
    if g.is_none() {
        *g = Some(build_pool(default_threads())?);
    }
    Ok(g.as_ref().unwrap().clone())
}

/// Worker threads of every later call (0 = one per core). Results never depend on it.
#[pyfunction]
fn set_num_threads(n: usize) -> PyResult<()> {
    let cores = std::thread::available_parallelism().map_or(1, |c| c.get());
    let n = if n == 0 { cores } else { n.min(4 * cores) };
    let p = build_pool(n)?;
    *POOL.lock().unwrap_or_else(|p| p.into_inner()) = Some(p);
    Ok(())
}

/// Worker threads the calls use (default: `XSCALE_THREADS`, else one per core).
#[pyfunction]
fn get_num_threads() -> PyResult<usize> {
    Ok(pool()?.current_num_threads())
}

/// Seconds the last call spent in the Rust computation itself (what a call costs beyond it is
/// the binding's overhead: argument checks, array conversion, the GIL).
#[pyfunction]
fn _last_kernel_seconds() -> f64 {
    LAST_NS.load(Ordering::Relaxed) as f64 * 1e-9
}

fn panic_text(p: &(dyn std::any::Any + Send)) -> String {
    if let Some(s) = p.downcast_ref::<&str>() {
        s.to_string()
    } else if let Some(s) = p.downcast_ref::<String>() {
        s.clone()
    } else {
        "panic".into()
    }
}

/// Run `f` without the GIL, in the module's thread pool, a panic caught and turned into a
/// `RuntimeError`, an `anyhow` error into a `ValueError` with the Rust message.
fn compute<T, F>(py: Python<'_>, f: F) -> PyResult<T>
where
    T: Send,
    F: FnOnce() -> anyhow::Result<T> + Send,
{
    let pool = pool()?;
    let r = py.detach(move || {
        let t0 = std::time::Instant::now();
        let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| pool.install(f)));
        LAST_NS.store(t0.elapsed().as_nanos() as u64, Ordering::Relaxed);
        r
    });
    match r {
        Ok(Ok(v)) => Ok(v),
        Ok(Err(e)) => Err(value_error(format!("{e:#}"))),
        Err(p) => Err(PyRuntimeError::new_err(format!(
            "xscale internal error (a bug; please report it with the call that caused it): {}",
            panic_text(&*p)
        ))),
    }
}

// ---------------------------------------------------------------------------------------------
// Arrays in and out

/// A checked NumPy input: read-only view of a C-contiguous array of `T`.
struct In<'py, T: Element> {
    ro: PyReadonlyArrayDyn<'py, T>,
    shape: Vec<usize>,
}

impl<T: Element> In<'_, T> {
    fn slice(&self) -> &[T] {
        self.ro.as_slice().expect("checked C-contiguous")
    }
}

fn type_name(obj: &Bound<'_, PyAny>) -> String {
    obj.get_type()
        .name()
        .map(|n| n.to_string())
        .unwrap_or_else(|_| "?".into())
}

fn dtype_str(arr: &Bound<'_, PyUntypedArray>) -> String {
    arr.dtype()
        .str()
        .map(|s| s.to_string())
        .unwrap_or_else(|_| "?".into())
}

fn untyped<'a, 'py>(
    obj: &'a Bound<'py, PyAny>,
    what: &str,
) -> PyResult<&'a Bound<'py, PyUntypedArray>> {
    obj.cast::<PyUntypedArray>().map_err(|_| {
        type_error(format!(
            "{what}: expected a numpy.ndarray, got {}",
            type_name(obj)
        ))
    })
}

/// `obj` as an input array of `T` (`tname` names the dtype in errors).
fn input<'py, T: Element>(
    obj: &Bound<'py, PyAny>,
    what: &str,
    tname: &str,
) -> PyResult<In<'py, T>> {
    let py = obj.py();
    let u = untyped(obj, what)?;
    if !u.dtype().is_equiv_to(&numpy::dtype::<T>(py)) {
        return Err(type_error(format!(
            "{what}: dtype {}, expected {tname} (inputs are never converted silently; use .astype(np.{tname}))",
            dtype_str(u)
        )));
    }
    if !u.is_c_contiguous() {
        return Err(value_error(format!(
            "{what}: not C-contiguous (a transposed or sliced view); pass np.ascontiguousarray({what})"
        )));
    }
    let shape = u.shape().to_vec();
    let arr = obj
        .cast::<PyArrayDyn<T>>()
        .map_err(|e| type_error(format!("{what}: {e}")))?;
    let ro = arr
        .try_readonly()
        .map_err(|e| value_error(format!("{what}: {e}")))?;
    Ok(In { ro, shape })
}

/// `f::<f32>(args…, "float32")` or `f::<f64>(args…, "float64")` by a float kind.
macro_rules! dispatch {
    ($kind:expr, $f:ident($($arg:expr),* $(,)?)) => {
        match $kind {
            Fk::F32 => $f::<f32>($($arg,)* "float32"),
            Fk::F64 => $f::<f64>($($arg,)* "float64"),
        }
    };
}

/// Float kind of an array argument (`float32` or `float64`; anything else is a TypeError).
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Fk {
    F32,
    F64,
}

fn float_kind(obj: &Bound<'_, PyAny>, what: &str) -> PyResult<Fk> {
    let py = obj.py();
    let u = untyped(obj, what)?;
    let d = u.dtype();
    if d.is_equiv_to(&numpy::dtype::<f32>(py)) {
        Ok(Fk::F32)
    } else if d.is_equiv_to(&numpy::dtype::<f64>(py)) {
        Ok(Fk::F64)
    } else {
        Err(type_error(format!(
            "{what}: dtype {}, expected float32 or float64",
            dtype_str(u)
        )))
    }
}

fn fk_of_dtype(dtype: &str) -> PyResult<Fk> {
    match dtype {
        "float32" | "f32" | "F32" => Ok(Fk::F32),
        "float64" | "f64" | "F64" => Ok(Fk::F64),
        d => Err(value_error(format!(
            "dtype {d:?}: expected \"float32\" or \"float64\""
        ))),
    }
}

/// Shapes with named axes: each name is bound by the first array that has it.
#[derive(Default)]
struct Dims(BTreeMap<&'static str, (usize, String)>);

/// One axis of a shape pattern: a fixed size or a name.
#[derive(Clone, Copy)]
enum A {
    K(usize),
    N(&'static str),
}

fn fmt_pattern(p: &[A]) -> String {
    let parts: Vec<String> = p
        .iter()
        .map(|a| match a {
            A::K(k) => k.to_string(),
            A::N(n) => n.to_string(),
        })
        .collect();
    format!("({})", parts.join(", "))
}

impl Dims {
    fn check(&mut self, what: &str, shape: &[usize], pattern: &[A]) -> PyResult<()> {
        if shape.len() != pattern.len() {
            return Err(value_error(format!(
                "{what}: shape {shape:?} has {} axes, expected {} {}",
                shape.len(),
                pattern.len(),
                fmt_pattern(pattern)
            )));
        }
        for (i, (&s, a)) in shape.iter().zip(pattern).enumerate() {
            match *a {
                A::K(k) if s != k => {
                    return Err(value_error(format!(
                        "{what}: shape {shape:?}, expected {}: axis {i} is {s}, expected {k}",
                        fmt_pattern(pattern)
                    )))
                }
                A::N(name) => match self.0.get(name) {
                    Some((v, by)) if *v != s => {
                        return Err(value_error(format!(
                            "{what}: shape {shape:?}, expected {}: axis {i} ({name}) is {s}, but {name} = {v} (from {by})",
                            fmt_pattern(pattern)
                        )))
                    }
                    Some(_) => {}
                    None => {
                        self.0.insert(name, (s, what.to_string()));
                    }
                },
                _ => {}
            }
        }
        Ok(())
    }
    fn get(&self, name: &str) -> usize {
        self.0.get(name).map_or(0, |v| v.0)
    }
}

/// A new array of `shape` holding `v`.
fn out<'py, T: Element>(
    py: Python<'py>,
    v: Vec<T>,
    shape: &[usize],
) -> PyResult<Bound<'py, PyAny>> {
    Ok(PyArray1::from_vec(py, v)
        .reshape(shape.to_vec())?
        .into_any())
}

/// Every element finite (positions, directions: what a batch requires, SPEC §6.3).
fn check_finite_f64(what: &str, v: &[f64], width: usize) -> PyResult<()> {
    if let Some(i) = v.iter().position(|x| !x.is_finite()) {
        return Err(value_error(format!(
            "{what}: row {} component {} is {}, expected a finite number",
            i / width,
            i % width,
            v[i]
        )));
    }
    Ok(())
}

fn check_finite_f32(what: &str, v: &[f32], width: usize) -> PyResult<()> {
    if let Some(i) = v.iter().position(|x| !x.is_finite()) {
        return Err(value_error(format!(
            "{what}: row {} component {} is {}, expected a finite number",
            i / width,
            i % width,
            v[i]
        )));
    }
    Ok(())
}

fn points(v: &[f64]) -> &[[f64; 3]] {
    bytemuck::cast_slice(v)
}

fn dirs3(v: &[f32]) -> &[[f32; 3]] {
    bytemuck::cast_slice(v)
}

fn position_mode(s: &str) -> PyResult<PositionMode> {
    match s {
        "f64" => Ok(PositionMode::F64),
        "tcnn" => Ok(PositionMode::Tcnn),
        _ => Err(value_error(format!(
            "mode {s:?}: expected \"f64\" or \"tcnn\" (SPEC §4.2, positions)"
        ))),
    }
}

fn mode_str(m: PositionMode) -> &'static str {
    match m {
        PositionMode::F64 => "f64",
        PositionMode::Tcnn => "tcnn",
    }
}

fn loss_kind(s: &str) -> PyResult<LossKind> {
    match s {
        "l1" => Ok(LossKind::L1),
        "l2" => Ok(LossKind::L2),
        "smooth_l1" => Ok(LossKind::SmoothL1),
        _ => Err(value_error(format!(
            "kind {s:?}: expected \"l1\", \"l2\" or \"smooth_l1\""
        ))),
    }
}

/// `dict` (or None) → JSON text, through Python's json module.
fn to_json(py: Python<'_>, obj: &Bound<'_, PyAny>) -> PyResult<String> {
    py.import("json")?
        .call_method1("dumps", (obj,))?
        .extract::<String>()
}

fn from_json<'py>(py: Python<'py>, text: &str) -> PyResult<Bound<'py, PyAny>> {
    py.import("json")?.call_method1("loads", (text,))
}

/// TOML text → JSON text (configs as Python dicts; Python 3.9 has no tomllib).
#[pyfunction]
fn _toml_to_json(text: &str) -> PyResult<String> {
    let v: toml::Value = toml::from_str(text).map_err(|e| value_error(format!("TOML: {e}")))?;
    serde_json::to_string(&v).map_err(value_error)
}

/// JSON text → TOML text (a config dict saved as a checkpoint's `config`).
#[pyfunction]
fn _json_to_toml(text: &str) -> PyResult<String> {
    let v: serde_json::Value = serde_json::from_str(text).map_err(value_error)?;
    toml::to_string(&v).map_err(|e| value_error(format!("not representable as TOML: {e}")))
}

// ---------------------------------------------------------------------------------------------
// Files as dicts

/// A new array of `shape` from little-endian bytes: one copy into the array's own memory.
fn array_from_le_bytes<'py, T: Element + bytemuck::Pod>(
    py: Python<'py>,
    data: &[u8],
    shape: &[usize],
) -> PyResult<Bound<'py, PyAny>> {
    // SAFETY: the array is uninitialised only until every byte is written just below, before
    // Python can see it.
    let arr = unsafe { PyArrayDyn::<T>::new(py, numpy::ndarray::IxDyn(shape), false) };
    {
        let mut rw = arr
            .try_readwrite()
            .map_err(|e| value_error(format!("{e}")))?;
        let dst = rw.as_slice_mut().map_err(value_error)?;
        bytemuck::cast_slice_mut::<T, u8>(dst).copy_from_slice(data);
    }
    Ok(arr.into_any())
}

fn tensor_to_py<'py>(py: Python<'py>, t: &Tensor) -> PyResult<Bound<'py, PyAny>> {
    if cfg!(target_endian = "little") {
        return match t.dtype {
            DType::F64 => array_from_le_bytes::<f64>(py, &t.data, &t.shape),
            DType::F32 => array_from_le_bytes::<f32>(py, &t.data, &t.shape),
            DType::U32 => array_from_le_bytes::<u32>(py, &t.data, &t.shape),
            DType::I32 => array_from_le_bytes::<i32>(py, &t.data, &t.shape),
            DType::U8 => array_from_le_bytes::<u8>(py, &t.data, &t.shape),
        };
    }
    let e = |e: anyhow::Error| value_error(format!("{e:#}"));
    match t.dtype {
        DType::F64 => out(py, t.to_f64().map_err(e)?, &t.shape),
        DType::F32 => out(py, t.to_f32().map_err(e)?, &t.shape),
        DType::U32 => out(py, t.to_u32().map_err(e)?, &t.shape),
        DType::I32 => out(py, t.to_i32().map_err(e)?, &t.shape),
        DType::U8 => out(py, t.to_u8().map_err(e)?, &t.shape),
    }
}

/// `(tensors, metadata)` dicts of a tensor file.
fn file_to_py<'py>(
    py: Python<'py>,
    f: &TensorFile,
) -> PyResult<(Bound<'py, PyDict>, Bound<'py, PyDict>)> {
    let t = PyDict::new(py);
    for (k, v) in &f.tensors {
        t.set_item(k, tensor_to_py(py, v)?)?;
    }
    let m = PyDict::new(py);
    for (k, v) in &f.metadata {
        m.set_item(k, v)?;
    }
    Ok((t, m))
}

fn tensor_from_py(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<Tensor> {
    let py = obj.py();
    let what = format!("tensor {name:?}");
    let u = untyped(obj, &what)?;
    let d = u.dtype();
    let dtype = if d.is_equiv_to(&numpy::dtype::<f64>(py)) {
        DType::F64
    } else if d.is_equiv_to(&numpy::dtype::<f32>(py)) {
        DType::F32
    } else if d.is_equiv_to(&numpy::dtype::<u32>(py)) {
        DType::U32
    } else if d.is_equiv_to(&numpy::dtype::<i32>(py)) {
        DType::I32
    } else if d.is_equiv_to(&numpy::dtype::<u8>(py)) {
        DType::U8
    } else {
        return Err(type_error(format!(
            "{what}: dtype {}; xscale's files hold float64, float32, uint32, int32 and uint8 \
             (cast half precision to float32, bool to uint8)",
            dtype_str(u)
        )));
    };
    if !u.is_c_contiguous() {
        return Err(value_error(format!("{what}: not C-contiguous")));
    }
    let shape = u.shape().to_vec();
    let bytes: Vec<u8> = match dtype {
        DType::F64 => xscale::io::tensors::le_bytes(input::<f64>(obj, &what, "float64")?.slice()),
        DType::F32 => xscale::io::tensors::le_bytes(input::<f32>(obj, &what, "float32")?.slice()),
        DType::U32 => xscale::io::tensors::le_bytes(input::<u32>(obj, &what, "uint32")?.slice()),
        DType::I32 => xscale::io::tensors::le_bytes(input::<i32>(obj, &what, "int32")?.slice()),
        DType::U8 => input::<u8>(obj, &what, "uint8")?.slice().to_vec(),
    };
    Tensor::from_bytes(dtype, shape, bytes).map_err(|e| value_error(format!("{what}: {e:#}")))
}

fn file_from_py(
    tensors: &Bound<'_, PyDict>,
    metadata: Option<&Bound<'_, PyDict>>,
    label: Option<&str>,
) -> PyResult<TensorFile> {
    let mut f = TensorFile::new();
    for (k, v) in tensors.iter() {
        let name: String = k
            .extract()
            .map_err(|_| type_error("tensor names must be str"))?;
        f.insert(name.clone(), tensor_from_py(&v, &name)?);
    }
    if let Some(m) = metadata {
        for (k, v) in m.iter() {
            let key: String = k
                .extract()
                .map_err(|_| type_error("metadata keys must be str"))?;
            let val: String = v.extract().map_err(|_| {
                type_error(format!(
                    "metadata {key:?}: values must be str (safetensors metadata is text)"
                ))
            })?;
            f.set_meta(key, val);
        }
    }
    f.source = label.map(std::path::PathBuf::from);
    Ok(f)
}

/// Read a safetensors file: `(tensors, metadata)`. Unless `stored`, a model file's tables
/// stored by their stepped rows come back whole, rebuilt by the checkpoint loader's own code
/// (`xscale::model::checkpoint::whole_tables`).
#[pyfunction]
#[pyo3(signature = (path, stored=false))]
fn load<'py>(
    py: Python<'py>,
    path: std::path::PathBuf,
    stored: bool,
) -> PyResult<(Bound<'py, PyDict>, Bound<'py, PyDict>)> {
    let f = compute(py, || {
        let mut f = TensorFile::read(&path)?;
        if !stored {
            xscale::model::checkpoint::whole_tables(&mut f)?;
        }
        Ok(f)
    })?;
    file_to_py(py, &f)
}

/// Write a safetensors file (xscale's byte-identical, atomic writer).
#[pyfunction]
#[pyo3(signature = (path, tensors, metadata=None))]
fn save(
    py: Python<'_>,
    path: std::path::PathBuf,
    tensors: &Bound<'_, PyDict>,
    metadata: Option<&Bound<'_, PyDict>>,
) -> PyResult<()> {
    let f = file_from_py(tensors, metadata, None)?;
    compute(py, || f.write_atomic(&path))
}

// ---------------------------------------------------------------------------------------------
// Hash grid (SPEC §4.2)

/// A multi-resolution hash grid (SPEC §4.2): its geometry (per-level scales, offsets, dense or
/// hashed levels) and the three passes, on NumPy arrays. Construct it from a grid config
/// (`levels`, `features`, `log2_table_size`, `base_resolution`, `per_level_scale`,
/// `interpolation`) and, for a trained model, the checkpoint's saved `scales`.
#[pyclass(name = "HashGrid", module = "xscale", frozen)]
struct PyHashGrid {
    grid: HashGrid,
    mode: PositionMode,
}

impl PyHashGrid {
    fn mode_of(&self, mode: Option<&str>) -> PyResult<PositionMode> {
        mode.map_or(Ok(self.mode), position_mode)
    }

    fn check_table(&self, dims: &mut Dims, what: &str, shape: &[usize]) -> PyResult<()> {
        dims.check(
            what,
            shape,
            &[
                A::K(self.grid.n_entries()),
                A::K(self.grid.cfg.features as usize),
            ],
        )
    }
}

fn grid_forward<R: Real + Element>(
    py: Python<'_>,
    g: &HashGrid,
    table: &Bound<'_, PyAny>,
    pos: &[f64],
    mode: PositionMode,
    active: Option<&[u8]>,
    tname: &str,
) -> PyResult<Py<PyAny>> {
    let t = input::<R>(table, "table", tname)?;
    let (ts, m) = (t.slice(), pos.len() / 3);
    let v = compute(py, || {
        let mut o = vec![R::ZERO; m * g.out_dim()];
        g.forward_active(ts, points(pos), mode, &mut o, active.unwrap_or(&[]));
        Ok(o)
    })?;
    Ok(out(py, v, &[m, g.out_dim()])?.unbind())
}

fn grid_backward_table<R: Real + Element>(
    py: Python<'_>,
    g: &HashGrid,
    pos: &[f64],
    d_out: &Bound<'_, PyAny>,
    mode: PositionMode,
    tname: &str,
) -> PyResult<Py<PyAny>> {
    let d = input::<R>(d_out, "d_out", tname)?;
    let ds = d.slice();
    let v = compute(py, || {
        let mut dt = vec![R::ZERO; g.n_params()];
        let mut touched = Touched::default();
        g.backward_table(points(pos), mode, ds, &mut dt, &mut touched);
        Ok(dt)
    })?;
    Ok(out(py, v, &[g.n_entries(), g.cfg.features as usize])?.unbind())
}

fn grid_backward_points<R: Real + Element>(
    py: Python<'_>,
    g: &HashGrid,
    table: &Bound<'_, PyAny>,
    pos: &[f64],
    d_out: &Bound<'_, PyAny>,
    mode: PositionMode,
    tname: &str,
) -> PyResult<Py<PyAny>> {
    let t = input::<R>(table, "table", tname)?;
    let d = input::<R>(d_out, "d_out", tname)?;
    let (ts, ds, m) = (t.slice(), d.slice(), pos.len() / 3);
    let v = compute(py, || {
        let mut dp = vec![R::ZERO; m * 3];
        g.backward_points(ts, points(pos), mode, ds, &mut dp);
        Ok(dp)
    })?;
    Ok(out(py, v, &[m, 3])?.unbind())
}

#[pymethods]
impl PyHashGrid {
    /// `HashGrid(config=None, *, scales=None, mode="f64", **fields)`: `config` a dict of the
    /// grid's fields (a checkpoint config's `grid_h` or `deform.grid` table), `fields` the same as
    /// keywords; `scales` the saved per-level scales (float32 [L]) — a loader uses them as given;
    /// without them they are computed as tiny-cuda-nn's host code does. `mode`: the default
    /// positions mode of the passes, "f64" or "tcnn" (SPEC §4.2).
    #[new]
    #[pyo3(signature = (config=None, *, scales=None, mode="f64", **fields))]
    fn new(
        py: Python<'_>,
        config: Option<&Bound<'_, PyDict>>,
        scales: Option<&Bound<'_, PyAny>>,
        mode: &str,
        fields: Option<&Bound<'_, PyDict>>,
    ) -> PyResult<Self> {
        let all = PyDict::new(py);
        if let Some(c) = config {
            all.update(c.as_mapping())?;
        }
        if let Some(f) = fields {
            all.update(f.as_mapping())?;
        }
        if !all.contains("interpolation")? {
            all.set_item("interpolation", "linear")?;
        }
        let cfg: GridConfig = serde_json::from_str(&to_json(py, all.as_any())?)
            .map_err(|e| value_error(format!("grid config: {e}")))?;
        xscale::model::hashgrid::validate_config(&cfg)
            .map_err(|e| value_error(format!("{e:#}")))?;
        let grid = match scales {
            Some(s) => {
                let s = input::<f32>(s, "scales", "float32")?;
                Dims::default().check("scales", &s.shape, &[A::K(cfg.levels as usize)])?;
                HashGrid::with_scales(&cfg, s.slice().to_vec())
            }
            None => HashGrid::try_new(&cfg),
        }
        .map_err(|e| value_error(format!("{e:#}")))?;
        Ok(PyHashGrid {
            grid,
            mode: position_mode(mode)?,
        })
    }

    /// Encode M points: `positions` float64 [M, 3] (normalised, finite) → [M, L·F] in the
    /// table's dtype (float32 or float64 [entries, F]). `active` (uint8 [M], optional): point i
    /// evaluates only its first active[i] levels, the others are 0 (footprint level weighting).
    #[pyo3(signature = (table, positions, *, mode=None, active=None))]
    fn forward(
        &self,
        py: Python<'_>,
        table: &Bound<'_, PyAny>,
        positions: &Bound<'_, PyAny>,
        mode: Option<&str>,
        active: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<Py<PyAny>> {
        let mode = self.mode_of(mode)?;
        let mut dims = Dims::default();
        let p = input::<f64>(positions, "positions", "float64")?;
        dims.check("positions", &p.shape, &[A::N("M"), A::K(3)])?;
        check_finite_f64("positions", p.slice(), 3)?;
        let kind = float_kind(table, "table")?;
        self.check_table(&mut dims, "table", untyped(table, "table")?.shape())?;
        let act = match active {
            Some(a) => {
                let a = input::<u8>(a, "active", "uint8")?;
                dims.check("active", &a.shape, &[A::N("M")])?;
                Some(a)
            }
            None => None,
        };
        let acts = act.as_ref().map(|a| a.slice());
        dispatch!(
            kind,
            grid_forward(py, &self.grid, table, p.slice(), mode, acts)
        )
    }

    /// ∂L/∂table [entries, F] (dtype of `d_out`) from `d_out` [M, L·F]: the scatter-add
    /// `d_table[index_k] += weight_k · d_out` over points in order, corners k = 0..7.
    #[pyo3(signature = (positions, d_out, *, mode=None))]
    fn backward_table(
        &self,
        py: Python<'_>,
        positions: &Bound<'_, PyAny>,
        d_out: &Bound<'_, PyAny>,
        mode: Option<&str>,
    ) -> PyResult<Py<PyAny>> {
        let mode = self.mode_of(mode)?;
        let mut dims = Dims::default();
        let p = input::<f64>(positions, "positions", "float64")?;
        dims.check("positions", &p.shape, &[A::N("M"), A::K(3)])?;
        check_finite_f64("positions", p.slice(), 3)?;
        let kind = float_kind(d_out, "d_out")?;
        dims.check(
            "d_out",
            untyped(d_out, "d_out")?.shape(),
            &[A::N("M"), A::K(self.grid.out_dim())],
        )?;
        match kind {
            Fk::F32 => {
                grid_backward_table::<f32>(py, &self.grid, p.slice(), d_out, mode, "float32")
            }
            Fk::F64 => {
                grid_backward_table::<f64>(py, &self.grid, p.slice(), d_out, mode, "float64")
            }
        }
    }

    /// ∂L/∂positions [M, 3] (dtype of `table`, which `d_out` [M, L·F] must share), tiny-cuda-nn's
    /// `dy_dx` (SPEC §4.2 "Backward"); with smoothstep the weight's derivative is 6t(1−t).
    #[pyo3(signature = (table, positions, d_out, *, mode=None))]
    fn backward_positions(
        &self,
        py: Python<'_>,
        table: &Bound<'_, PyAny>,
        positions: &Bound<'_, PyAny>,
        d_out: &Bound<'_, PyAny>,
        mode: Option<&str>,
    ) -> PyResult<Py<PyAny>> {
        let mode = self.mode_of(mode)?;
        let mut dims = Dims::default();
        let p = input::<f64>(positions, "positions", "float64")?;
        dims.check("positions", &p.shape, &[A::N("M"), A::K(3)])?;
        check_finite_f64("positions", p.slice(), 3)?;
        let kind = float_kind(table, "table")?;
        self.check_table(&mut dims, "table", untyped(table, "table")?.shape())?;
        dims.check(
            "d_out",
            untyped(d_out, "d_out")?.shape(),
            &[A::N("M"), A::K(self.grid.out_dim())],
        )?;
        match kind {
            Fk::F32 => grid_backward_points::<f32>(
                py,
                &self.grid,
                table,
                p.slice(),
                d_out,
                mode,
                "float32",
            ),
            Fk::F64 => grid_backward_points::<f64>(
                py,
                &self.grid,
                table,
                p.slice(),
                d_out,
                mode,
                "float64",
            ),
        }
    }

    /// The 8 corners of each point at level `level`: global entry indices (uint32 [M, 8]) and
    /// interpolation weights ([M, 8] in `dtype`), corner k's bit d set = the upper corner along
    /// axis d — the scalar reference a kernel author ports (`HashGrid::corners`).
    #[pyo3(signature = (positions, level, *, mode=None, dtype="float64"))]
    fn corners(
        &self,
        py: Python<'_>,
        positions: &Bound<'_, PyAny>,
        level: usize,
        mode: Option<&str>,
        dtype: &str,
    ) -> PyResult<(Py<PyAny>, Py<PyAny>)> {
        let mode = self.mode_of(mode)?;
        let p = input::<f64>(positions, "positions", "float64")?;
        Dims::default().check("positions", &p.shape, &[A::N("M"), A::K(3)])?;
        check_finite_f64("positions", p.slice(), 3)?;
        if level >= self.grid.cfg.levels as usize {
            return Err(value_error(format!(
                "level {level}: the grid has levels 0..{}",
                self.grid.cfg.levels
            )));
        }
        let pts = points(p.slice());
        let m = pts.len();
        let mut idx = Vec::with_capacity(m * 8);
        fn go<R: Real + Element>(
            py: Python<'_>,
            g: &HashGrid,
            pts: &[[f64; 3]],
            level: usize,
            mode: PositionMode,
            idx: &mut Vec<u32>,
        ) -> PyResult<Py<PyAny>> {
            let mut w = Vec::with_capacity(pts.len() * 8);
            for x in pts {
                let (i, wk) = g.corners::<R>(level, x, mode);
                idx.extend_from_slice(&i);
                w.extend_from_slice(&wk);
            }
            Ok(out(py, w, &[pts.len(), 8])?.unbind())
        }
        let w = match fk_of_dtype(dtype)? {
            Fk::F32 => go::<f32>(py, &self.grid, pts, level, mode, &mut idx)?,
            Fk::F64 => go::<f64>(py, &self.grid, pts, level, mode, &mut idx)?,
        };
        Ok((out(py, idx, &[m, 8])?.unbind(), w))
    }

    /// The initial table, float32 [entries, F]: U(−1e-4, 1e-4) from the counter-based generator
    /// (tensor id 0 for grid H, 1 for grid D; SPEC §4.2).
    #[pyo3(signature = (seed, tensor_id=0))]
    fn init_table(&self, py: Python<'_>, seed: u64, tensor_id: u64) -> PyResult<Py<PyAny>> {
        let g = &self.grid;
        let v = compute(py, || Ok(g.init_table(seed, tensor_id)))?;
        Ok(out(py, v, &[g.n_entries(), g.cfg.features as usize])?.unbind())
    }

    /// The grid's config as a dict.
    #[getter]
    fn config<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        from_json(
            py,
            &serde_json::to_string(&self.grid.cfg).map_err(value_error)?,
        )
    }
    /// The default positions mode ("f64" or "tcnn").
    #[getter]
    fn mode(&self) -> &'static str {
        mode_str(self.mode)
    }
    /// Per-level scales, float32 [L].
    #[getter]
    fn scales(&self, py: Python<'_>) -> PyResult<Py<PyAny>> {
        Ok(out(py, self.grid.scales.clone(), &[self.grid.scales.len()])?.unbind())
    }
    /// First entry of each level and the total, uint32 [L+1].
    #[getter]
    fn offsets(&self, py: Python<'_>) -> PyResult<Py<PyAny>> {
        Ok(out(py, self.grid.offsets.clone(), &[self.grid.offsets.len()])?.unbind())
    }
    /// Grid vertices per axis of each level, uint32 [L].
    #[getter]
    fn resolutions(&self, py: Python<'_>) -> PyResult<Py<PyAny>> {
        Ok(out(
            py,
            self.grid.resolutions.clone(),
            &[self.grid.resolutions.len()],
        )?
        .unbind())
    }
    /// Whether each level is indexed densely (no hashing), list of bool.
    #[getter]
    fn dense(&self) -> Vec<bool> {
        self.grid.dense.clone()
    }
    #[getter]
    fn n_entries(&self) -> usize {
        self.grid.n_entries()
    }
    /// Output width L·F.
    #[getter]
    fn out_dim(&self) -> usize {
        self.grid.out_dim()
    }
    #[getter]
    fn levels(&self) -> u32 {
        self.grid.cfg.levels
    }
    #[getter]
    fn features(&self) -> u32 {
        self.grid.cfg.features
    }
    fn __repr__(&self) -> String {
        let c = &self.grid.cfg;
        format!(
            "HashGrid(levels={}, features={}, log2_table_size={}, base_resolution={}, per_level_scale={}, interpolation={:?}, mode={:?}; {} entries)",
            c.levels,
            c.features,
            c.log2_table_size,
            c.base_resolution,
            c.per_level_scale,
            match c.interpolation {
                xscale::model::config::Interpolation::Linear => "linear",
                xscale::model::config::Interpolation::Smoothstep => "smoothstep",
            },
            mode_str(self.mode),
            self.grid.n_entries()
        )
    }
}

// ---------------------------------------------------------------------------------------------
// SH (SPEC §4.3)

/// SH(d), degree 4: [N, 16] from `dirs` [N, 3] (finite). float32 dirs are widened to `dtype`
/// (default float32) as the model does (`sh_forward`); float64 dirs need dtype float64 and are
/// encoded as given (`sh_forward_one`).
#[pyfunction]
#[pyo3(signature = (dirs, *, dtype=None))]
fn sh_forward(py: Python<'_>, dirs: &Bound<'_, PyAny>, dtype: Option<&str>) -> PyResult<Py<PyAny>> {
    let dk = float_kind(dirs, "dirs")?;
    let ok = match dtype {
        Some(d) => fk_of_dtype(d)?,
        None => dk,
    };
    let mut dims = Dims::default();
    fn enc<R: Real + Element>(py: Python<'_>, d: &[[f32; 3]]) -> PyResult<Py<PyAny>> {
        let v = compute(py, || {
            let mut o = vec![R::ZERO; d.len() * sh::SH_DIM];
            sh::sh_forward(d, &mut o);
            Ok(o)
        })?;
        Ok(out(py, v, &[d.len(), sh::SH_DIM])?.unbind())
    }
    match (dk, ok) {
        (Fk::F32, _) => {
            let d = input::<f32>(dirs, "dirs", "float32")?;
            dims.check("dirs", &d.shape, &[A::N("N"), A::K(3)])?;
            check_finite_f32("dirs", d.slice(), 3)?;
            match ok {
                Fk::F32 => enc::<f32>(py, dirs3(d.slice())),
                Fk::F64 => enc::<f64>(py, dirs3(d.slice())),
            }
        }
        (Fk::F64, Fk::F64) => {
            let d = input::<f64>(dirs, "dirs", "float64")?;
            dims.check("dirs", &d.shape, &[A::N("N"), A::K(3)])?;
            check_finite_f64("dirs", d.slice(), 3)?;
            let ds = points(d.slice());
            let v = compute(py, || {
                let mut o = vec![0.0f64; ds.len() * sh::SH_DIM];
                for (x, r) in ds.iter().zip(o.chunks_exact_mut(sh::SH_DIM)) {
                    sh::sh_forward_one(*x, r);
                }
                Ok(o)
            })?;
            Ok(out(py, v, &[ds.len(), sh::SH_DIM])?.unbind())
        }
        (Fk::F64, Fk::F32) => Err(type_error(
            "dirs: float64 directions with dtype float32 would round them: pass float32 dirs (as batch.dirs) or dtype float64",
        )),
    }
}

/// ∂L/∂dirs [N, 3] (dtype of `d_sh` [N, 16]) through SH(d) (`sh_backward`): dirs float32 (as
/// the model) or float64 with a float64 `d_sh`.
#[pyfunction]
fn sh_backward(
    py: Python<'_>,
    dirs: &Bound<'_, PyAny>,
    d_sh: &Bound<'_, PyAny>,
) -> PyResult<Py<PyAny>> {
    let mut dims = Dims::default();
    let dk = float_kind(dirs, "dirs")?;
    let gk = float_kind(d_sh, "d_sh")?;
    dims.check(
        "d_sh",
        untyped(d_sh, "d_sh")?.shape(),
        &[A::N("N"), A::K(sh::SH_DIM)],
    )?;
    fn bwd<R: Real + Element>(
        py: Python<'_>,
        d: &[[f32; 3]],
        g: &Bound<'_, PyAny>,
        tname: &str,
    ) -> PyResult<Py<PyAny>> {
        let g = input::<R>(g, "d_sh", tname)?;
        let gs = g.slice();
        let v = compute(py, || {
            let mut o = vec![R::ZERO; d.len() * 3];
            sh::sh_backward(d, gs, &mut o);
            Ok(o)
        })?;
        Ok(out(py, v, &[d.len(), 3])?.unbind())
    }
    match (dk, gk) {
        (Fk::F32, _) => {
            let d = input::<f32>(dirs, "dirs", "float32")?;
            dims.check("dirs", &d.shape, &[A::N("N"), A::K(3)])?;
            check_finite_f32("dirs", d.slice(), 3)?;
            match gk {
                Fk::F32 => bwd::<f32>(py, dirs3(d.slice()), d_sh, "float32"),
                Fk::F64 => bwd::<f64>(py, dirs3(d.slice()), d_sh, "float64"),
            }
        }
        (Fk::F64, Fk::F64) => {
            let d = input::<f64>(dirs, "dirs", "float64")?;
            dims.check("dirs", &d.shape, &[A::N("N"), A::K(3)])?;
            check_finite_f64("dirs", d.slice(), 3)?;
            let g = input::<f64>(d_sh, "d_sh", "float64")?;
            let (ds, gs) = (points(d.slice()), g.slice());
            let v = compute(py, || {
                let mut o = vec![0.0f64; ds.len() * 3];
                for ((x, gr), orow) in ds
                    .iter()
                    .zip(gs.chunks_exact(sh::SH_DIM))
                    .zip(o.chunks_exact_mut(3))
                {
                    sh::sh_backward_one(*x, gr, orow);
                }
                Ok(o)
            })?;
            Ok(out(py, v, &[ds.len(), 3])?.unbind())
        }
        (Fk::F64, Fk::F32) => Err(type_error(
            "dirs float64 with d_sh float32: give float32 dirs (as batch.dirs) or a float64 d_sh",
        )),
    }
}

// ---------------------------------------------------------------------------------------------
// MLPs (SPEC §4.6)

/// An MLP's weights (and biases) from Python lists, packed in the Rust layout `[W0, (b0), …]`.
struct Net<R> {
    mlp: Mlp,
    params: Vec<R>,
}

fn net_from_py<R: Real + Element>(
    in_dim: usize,
    weights: &Bound<'_, PyAny>,
    biases: Option<&Bound<'_, PyAny>>,
    tname: &str,
) -> PyResult<Net<R>> {
    let ws: Vec<Bound<'_, PyAny>> = weights
        .try_iter()
        .map_err(|_| type_error("weights: expected a list of arrays [out, in]"))?
        .collect::<PyResult<_>>()?;
    if ws.is_empty() {
        return Err(value_error("weights: an MLP needs at least one layer"));
    }
    let bs: Option<Vec<Bound<'_, PyAny>>> = match biases {
        Some(b) if !b.is_none() => Some(
            b.try_iter()
                .map_err(|_| type_error("biases: expected a list of arrays [out] or None"))?
                .collect::<PyResult<_>>()?,
        ),
        _ => None,
    };
    if let Some(b) = &bs {
        if b.len() != ws.len() {
            return Err(value_error(format!(
                "biases: {} arrays for {} layers",
                b.len(),
                ws.len()
            )));
        }
    }
    let mut dimsv = vec![in_dim];
    let mut wins = Vec::new();
    for (k, w) in ws.iter().enumerate() {
        let what = format!("weights[{k}]");
        let wi = input::<R>(w, &what, tname)?;
        let prev = *dimsv.last().unwrap();
        if wi.shape.len() != 2 || wi.shape[1] != prev {
            return Err(value_error(format!(
                "{what}: shape {:?}, expected (out, {prev}) (W is [out, in], y = W x)",
                wi.shape
            )));
        }
        dimsv.push(wi.shape[0]);
        wins.push(wi);
    }
    let mlp = Mlp::new(&dimsv, bs.is_some());
    let mut params = vec![R::ZERO; mlp.n_params];
    for (k, (l, w)) in mlp.layers.iter().zip(&wins).enumerate() {
        params[l.w_off..l.w_off + l.in_dim * l.out_dim].copy_from_slice(w.slice());
        if let (Some(b_off), Some(bs)) = (l.b_off, &bs) {
            let what = format!("biases[{k}]");
            let bi = input::<R>(&bs[k], &what, tname)?;
            Dims::default().check(&what, &bi.shape, &[A::K(l.out_dim)])?;
            params[b_off..b_off + l.out_dim].copy_from_slice(bi.slice());
        }
    }
    Ok(Net { mlp, params })
}

fn list_of<'py, T: Element>(
    py: Python<'py>,
    arrays: Vec<(Vec<T>, Vec<usize>)>,
) -> PyResult<Bound<'py, PyList>> {
    let items: Vec<Bound<'py, PyAny>> = arrays
        .into_iter()
        .map(|(v, s)| out(py, v, &s))
        .collect::<PyResult<_>>()?;
    PyList::new(py, items)
}

/// Row chunk boundaries `[0, …, rows]` (default one chunk).
fn chunk_bounds(chunks: Option<Vec<usize>>, rows: usize) -> PyResult<Vec<usize>> {
    let c = chunks.unwrap_or_else(|| vec![0, rows]);
    if c.len() < 2 || c[0] != 0 || *c.last().unwrap() != rows || c.windows(2).any(|w| w[1] < w[0]) {
        return Err(value_error(format!(
            "chunks: expected row boundaries [0, …, {rows}] in ascending order, got {c:?}"
        )));
    }
    Ok(c)
}

fn mlp_forward_impl<R: Real + Element>(
    py: Python<'_>,
    x: &Bound<'_, PyAny>,
    weights: &Bound<'_, PyAny>,
    biases: Option<&Bound<'_, PyAny>>,
    tname: &str,
) -> PyResult<(Py<PyAny>, Py<PyAny>)> {
    let mut dims = Dims::default();
    let xi = input::<R>(x, "x", tname)?;
    dims.check("x", &xi.shape, &[A::N("rows"), A::N("in")])?;
    let net = net_from_py::<R>(xi.shape[1], weights, biases, tname)?;
    let rows = xi.shape[0];
    let xs = xi.slice();
    let acts = compute(py, || {
        let wt = net.mlp.transpose_weights(&net.params);
        let mut acts = MlpActs::default();
        net.mlp.forward(&net.params, &wt, xs, rows, &mut acts);
        Ok(acts)
    })?;
    let hidden: Vec<(Vec<R>, Vec<usize>)> = acts
        .hidden
        .into_iter()
        .zip(&net.mlp.layers)
        .map(|(h, l)| (h, vec![rows, l.out_dim]))
        .collect();
    Ok((
        list_of(py, hidden)?.into_any().unbind(),
        out(py, acts.out, &[rows, net.mlp.out_dim()])?.unbind(),
    ))
}

/// `(hidden, out)` of a ReLU MLP on `x` [rows, in] (float32 or float64): `weights` a list of
/// [out, in] arrays, `biases` a list of [out] arrays or None; `hidden` the activations after
/// ReLU of every layer but the last, `out` the last layer's linear output (`Mlp::forward`).
#[pyfunction]
#[pyo3(signature = (x, weights, biases=None))]
fn mlp_forward(
    py: Python<'_>,
    x: &Bound<'_, PyAny>,
    weights: &Bound<'_, PyAny>,
    biases: Option<&Bound<'_, PyAny>>,
) -> PyResult<(Py<PyAny>, Py<PyAny>)> {
    dispatch!(
        float_kind(x, "x")?,
        mlp_forward_impl(py, x, weights, biases)
    )
}

/// The `hidden` list a forward returned, each array checked against `axes` + its layer's width.
fn hidden_from_py<'py, R: Real + Element>(
    hidden: &Bound<'py, PyAny>,
    net: &Net<R>,
    dims: &mut Dims,
    axes: &[A],
    t: &str,
) -> PyResult<Vec<In<'py, R>>> {
    let hs: Vec<Bound<'py, PyAny>> = hidden
        .try_iter()
        .map_err(|_| type_error("hidden: expected the list the forward returned"))?
        .collect::<PyResult<_>>()?;
    let nl = net.mlp.layers.len();
    if hs.len() != nl - 1 {
        return Err(value_error(format!(
            "hidden: {} arrays, the MLP has {} hidden layers",
            hs.len(),
            nl - 1
        )));
    }
    let mut his = Vec::new();
    for (k, h) in hs.iter().enumerate() {
        let what = format!("hidden[{k}]");
        let hi = input::<R>(h, &what, t)?;
        let mut pattern = axes.to_vec();
        pattern.push(A::K(net.mlp.layers[k].out_dim));
        dims.check(&what, &hi.shape, &pattern)?;
        his.push(hi);
    }
    Ok(his)
}

/// `Mlp::backward` over rows `x` with activations `hidden` and output gradient `dy`, per chunk
/// of rows (`bounds`): a fresh parameter-gradient buffer per chunk, the chunks added in order
/// (the model's pixel chunks, SPEC §5); `dx` written row by row. Returns the parameter gradient.
fn chunked_backward<R: Real>(
    net: &Net<R>,
    x: &[R],
    hidden: &[&[R]],
    dy: &[R],
    bounds: &[usize],
    dx: &mut [R],
) -> Vec<R> {
    let (din, dout) = (net.mlp.in_dim(), net.mlp.out_dim());
    let mut dp = vec![R::ZERO; net.mlp.n_params];
    for w in bounds.windows(2) {
        let (a, b) = (w[0], w[1]);
        let acts = MlpActs {
            hidden: hidden
                .iter()
                .zip(&net.mlp.layers)
                .map(|(h, l)| h[a * l.out_dim..b * l.out_dim].to_vec())
                .collect(),
            out: Vec::new(),
        };
        let mut part = vec![R::ZERO; net.mlp.n_params];
        net.mlp.backward(
            &net.params,
            &x[a * din..b * din],
            b - a,
            &acts,
            dy[a * dout..b * dout].to_vec(),
            &mut part,
            Some(&mut dx[a * din..b * din]),
        );
        for (t, p) in dp.iter_mut().zip(&part) {
            *t += *p;
        }
    }
    dp
}

/// An MLP's parameter gradient as Python lists: weights [out, in] and biases [out] (None
/// without biases).
fn grads_to_py<R: Real + Element>(
    py: Python<'_>,
    net: &Net<R>,
    dp: &[R],
) -> PyResult<(Py<PyAny>, Py<PyAny>)> {
    let mut dws = Vec::new();
    let mut dbs = Vec::new();
    for l in &net.mlp.layers {
        dws.push((
            dp[l.w_off..l.w_off + l.in_dim * l.out_dim].to_vec(),
            vec![l.out_dim, l.in_dim],
        ));
        if let Some(b) = l.b_off {
            dbs.push((dp[b..b + l.out_dim].to_vec(), vec![l.out_dim]));
        }
    }
    let dbs = if net.mlp.layers[0].b_off.is_some() {
        list_of(py, dbs)?.into_any().unbind()
    } else {
        py.None()
    };
    Ok((list_of(py, dws)?.into_any().unbind(), dbs))
}

type BwdOut = (Py<PyAny>, Py<PyAny>, Py<PyAny>);

#[allow(clippy::too_many_arguments)]
fn mlp_backward_impl<R: Real + Element>(
    py: Python<'_>,
    x: &Bound<'_, PyAny>,
    weights: &Bound<'_, PyAny>,
    hidden: &Bound<'_, PyAny>,
    d_out: &Bound<'_, PyAny>,
    biases: Option<&Bound<'_, PyAny>>,
    chunks: Option<Vec<usize>>,
    tname: &str,
) -> PyResult<BwdOut> {
    let mut dims = Dims::default();
    let xi = input::<R>(x, "x", tname)?;
    dims.check("x", &xi.shape, &[A::N("rows"), A::N("in")])?;
    let net = net_from_py::<R>(xi.shape[1], weights, biases, tname)?;
    let rows = xi.shape[0];
    let his = hidden_from_py(hidden, &net, &mut dims, &[A::N("rows")], tname)?;
    let d = input::<R>(d_out, "d_out", tname)?;
    dims.check("d_out", &d.shape, &[A::N("rows"), A::K(net.mlp.out_dim())])?;
    let bounds = chunk_bounds(chunks, rows)?;
    let (xs, ds) = (xi.slice(), d.slice());
    let hsl: Vec<&[R]> = his.iter().map(|h| h.slice()).collect();
    let din = net.mlp.in_dim();
    let (dp, dx) = compute(py, || {
        let mut dx = vec![R::ZERO; rows * din];
        let dp = chunked_backward(&net, xs, &hsl, ds, &bounds, &mut dx);
        Ok((dp, dx))
    })?;
    let (dws, dbs) = grads_to_py(py, &net, &dp)?;
    Ok((out(py, dx, &[rows, din])?.unbind(), dws, dbs))
}

/// `(d_x, d_weights, d_biases)` of a ReLU MLP (`Mlp::backward`): `hidden` from
/// [`mlp_forward`], `d_out` = ∂L/∂(last linear output) [rows, out]. `chunks` (row boundaries
/// `[0, …, rows]`): the weight gradients are summed per chunk, then the chunks in order — the
/// model sums its shader per 128-pixel chunk (`xscale.pixel_chunks(N)`); default one chunk.
#[pyfunction]
#[pyo3(signature = (x, weights, hidden, d_out, *, biases=None, chunks=None))]
fn mlp_backward(
    py: Python<'_>,
    x: &Bound<'_, PyAny>,
    weights: &Bound<'_, PyAny>,
    hidden: &Bound<'_, PyAny>,
    d_out: &Bound<'_, PyAny>,
    biases: Option<&Bound<'_, PyAny>>,
    chunks: Option<Vec<usize>>,
) -> PyResult<BwdOut> {
    match float_kind(x, "x")? {
        Fk::F32 => {
            mlp_backward_impl::<f32>(py, x, weights, hidden, d_out, biases, chunks, "float32")
        }
        Fk::F64 => {
            mlp_backward_impl::<f64>(py, x, weights, hidden, d_out, biases, chunks, "float64")
        }
    }
}

/// One linear layer `y = x Wᵀ (+ b)`: [rows, out] (`mlp::linear_forward`, inputs in ascending
/// order, unfused).
#[pyfunction]
#[pyo3(signature = (x, weight, bias=None))]
fn linear_forward(
    py: Python<'_>,
    x: &Bound<'_, PyAny>,
    weight: &Bound<'_, PyAny>,
    bias: Option<&Bound<'_, PyAny>>,
) -> PyResult<Py<PyAny>> {
    fn go<R: Real + Element>(
        py: Python<'_>,
        x: &Bound<'_, PyAny>,
        weight: &Bound<'_, PyAny>,
        bias: Option<&Bound<'_, PyAny>>,
        tname: &str,
    ) -> PyResult<Py<PyAny>> {
        let mut dims = Dims::default();
        let xi = input::<R>(x, "x", tname)?;
        dims.check("x", &xi.shape, &[A::N("rows"), A::N("in")])?;
        let w = input::<R>(weight, "weight", tname)?;
        dims.check("weight", &w.shape, &[A::N("out"), A::N("in")])?;
        let b = match bias {
            Some(b) => {
                let b = input::<R>(b, "bias", tname)?;
                dims.check("bias", &b.shape, &[A::N("out")])?;
                Some(b)
            }
            None => None,
        };
        let (rows, i, o) = (dims.get("rows"), dims.get("in"), dims.get("out"));
        let (xs, ws, bs) = (xi.slice(), w.slice(), b.as_ref().map(|b| b.slice()));
        let v = compute(py, || {
            let mut wt = vec![R::ZERO; i * o];
            for r in 0..o {
                for c in 0..i {
                    wt[c * o + r] = ws[r * i + c];
                }
            }
            let mut y = vec![R::ZERO; rows * o];
            mlp::linear_forward(&wt, bs, xs, rows, i, o, &mut y);
            Ok(y)
        })?;
        Ok(out(py, v, &[rows, o])?.unbind())
    }
    dispatch!(float_kind(x, "x")?, go(py, x, weight, bias))
}

/// `(d_x, d_weight, d_bias)` of one linear layer (`mlp::linear_backward`): d_bias None unless
/// `bias=True`; `chunks` as in [`mlp_backward`].
#[pyfunction]
#[pyo3(signature = (x, weight, d_y, *, bias=false, chunks=None))]
fn linear_backward(
    py: Python<'_>,
    x: &Bound<'_, PyAny>,
    weight: &Bound<'_, PyAny>,
    d_y: &Bound<'_, PyAny>,
    bias: bool,
    chunks: Option<Vec<usize>>,
) -> PyResult<BwdOut> {
    fn go<R: Real + Element>(
        py: Python<'_>,
        x: &Bound<'_, PyAny>,
        weight: &Bound<'_, PyAny>,
        d_y: &Bound<'_, PyAny>,
        bias: bool,
        chunks: Option<Vec<usize>>,
        tname: &str,
    ) -> PyResult<BwdOut> {
        let mut dims = Dims::default();
        let xi = input::<R>(x, "x", tname)?;
        dims.check("x", &xi.shape, &[A::N("rows"), A::N("in")])?;
        let w = input::<R>(weight, "weight", tname)?;
        dims.check("weight", &w.shape, &[A::N("out"), A::N("in")])?;
        let d = input::<R>(d_y, "d_y", tname)?;
        dims.check("d_y", &d.shape, &[A::N("rows"), A::N("out")])?;
        let (rows, i, o) = (dims.get("rows"), dims.get("in"), dims.get("out"));
        let bounds = chunk_bounds(chunks, rows)?;
        let (xs, ws, ds) = (xi.slice(), w.slice(), d.slice());
        let (dx, dw, db) = compute(py, || {
            let mut dx = vec![R::ZERO; rows * i];
            let mut dw = vec![R::ZERO; o * i];
            let mut db = vec![R::ZERO; if bias { o } else { 0 }];
            for c in bounds.windows(2) {
                let (a, b) = (c[0], c[1]);
                let mut pw = vec![R::ZERO; o * i];
                let mut pb = vec![R::ZERO; if bias { o } else { 0 }];
                mlp::linear_backward(
                    ws,
                    &xs[a * i..b * i],
                    &ds[a * o..b * o],
                    b - a,
                    i,
                    o,
                    &mut pw,
                    bias.then_some(&mut pb[..]),
                    Some(&mut dx[a * i..b * i]),
                );
                for (t, p) in dw.iter_mut().zip(&pw) {
                    *t += *p;
                }
                for (t, p) in db.iter_mut().zip(&pb) {
                    *t += *p;
                }
            }
            Ok((dx, dw, db))
        })?;
        Ok((
            out(py, dx, &[rows, i])?.unbind(),
            out(py, dw, &[o, i])?.unbind(),
            if bias {
                out(py, db, &[o])?.unbind()
            } else {
                py.None()
            },
        ))
    }
    dispatch!(float_kind(x, "x")?, go(py, x, weight, d_y, bias, chunks))
}

/// A new array `f(x)` of `x`'s shape (an elementwise op of the model; `out` starts at zero).
fn map1<R: Real + Element>(
    py: Python<'_>,
    x: &Bound<'_, PyAny>,
    what: &str,
    t: &str,
    f: impl FnOnce(&[R], &mut [R]) + Send,
) -> PyResult<Py<PyAny>> {
    let xi = input::<R>(x, what, t)?;
    let xs = xi.slice();
    let v = compute(py, move || {
        let mut o = vec![R::ZERO; xs.len()];
        f(xs, &mut o);
        Ok(o)
    })?;
    Ok(out(py, v, &xi.shape)?.unbind())
}

/// A new array `f(a, b)` for two arrays of one shape (`out` starts at zero).
fn map2<R: Real + Element>(
    py: Python<'_>,
    (a, an): (&Bound<'_, PyAny>, &str),
    (b, bn): (&Bound<'_, PyAny>, &str),
    t: &str,
    f: impl FnOnce(&[R], &[R], &mut [R]) + Send,
) -> PyResult<Py<PyAny>> {
    let ai = input::<R>(a, an, t)?;
    let bi = input::<R>(b, bn, t)?;
    if ai.shape != bi.shape {
        return Err(value_error(format!(
            "{bn}: shape {:?}, {an} has {:?}",
            bi.shape, ai.shape
        )));
    }
    let (as_, bs) = (ai.slice(), bi.slice());
    let v = compute(py, move || {
        let mut o = vec![R::ZERO; as_.len()];
        f(as_, bs, &mut o);
        Ok(o)
    })?;
    Ok(out(py, v, &ai.shape)?.unbind())
}

/// ReLU `max(0, y)` (NaN and −0 pass through), a new array (`mlp::relu_forward`).
#[pyfunction]
fn relu_forward(py: Python<'_>, y: &Bound<'_, PyAny>) -> PyResult<Py<PyAny>> {
    fn go<R: Real + Element>(py: Python<'_>, y: &Bound<'_, PyAny>, t: &str) -> PyResult<Py<PyAny>> {
        map1::<R>(py, y, "y", t, |x, o| {
            o.copy_from_slice(x);
            mlp::relu_forward(o)
        })
    }
    dispatch!(float_kind(y, "y")?, go(py, y))
}

/// `d_y` where the ReLU output `y` is > 0, else 0 (`mlp::relu_backward`), a new array.
#[pyfunction]
fn relu_backward(
    py: Python<'_>,
    y: &Bound<'_, PyAny>,
    d_y: &Bound<'_, PyAny>,
) -> PyResult<Py<PyAny>> {
    fn go<R: Real + Element>(
        py: Python<'_>,
        y: &Bound<'_, PyAny>,
        d: &Bound<'_, PyAny>,
        t: &str,
    ) -> PyResult<Py<PyAny>> {
        map2::<R>(py, (y, "y"), (d, "d_y"), t, |y, d, o| {
            o.copy_from_slice(d);
            mlp::relu_backward(y, o)
        })
    }
    dispatch!(float_kind(y, "y")?, go(py, y, d_y))
}

// ---------------------------------------------------------------------------------------------
// Sigmoid, loss (SPEC §4.6, §4.7)

/// σ(z) = 1/(1+exp(−z)) (`loss::sigmoid_forward`), a new array.
#[pyfunction]
fn sigmoid_forward(py: Python<'_>, z: &Bound<'_, PyAny>) -> PyResult<Py<PyAny>> {
    fn go<R: Real + Element>(py: Python<'_>, z: &Bound<'_, PyAny>, t: &str) -> PyResult<Py<PyAny>> {
        map1::<R>(py, z, "z", t, |z, o| loss::sigmoid_forward(z, o))
    }
    dispatch!(float_kind(z, "z")?, go(py, z))
}

/// ∂L/∂z = d_rgb · rgb(1−rgb) from the sigmoid's output (`loss::sigmoid_backward`).
#[pyfunction]
fn sigmoid_backward(
    py: Python<'_>,
    rgb: &Bound<'_, PyAny>,
    d_rgb: &Bound<'_, PyAny>,
) -> PyResult<Py<PyAny>> {
    fn go<R: Real + Element>(
        py: Python<'_>,
        s: &Bound<'_, PyAny>,
        d: &Bound<'_, PyAny>,
        t: &str,
    ) -> PyResult<Py<PyAny>> {
        map2::<R>(py, (s, "rgb"), (d, "d_rgb"), t, |s, d, o| {
            loss::sigmoid_backward(s, d, o)
        })
    }
    dispatch!(float_kind(rgb, "rgb")?, go(py, rgb, d_rgb))
}

fn rgb_target<'py, R: Real + Element>(
    rgb: &Bound<'py, PyAny>,
    target: &Bound<'py, PyAny>,
    t: &str,
) -> PyResult<(In<'py, R>, In<'py, f32>)> {
    let mut dims = Dims::default();
    let r = input::<R>(rgb, "rgb", t)?;
    dims.check("rgb", &r.shape, &[A::N("N"), A::K(3)])?;
    let tg = input::<f32>(target, "target", "float32")?;
    dims.check("target", &tg.shape, &[A::N("N"), A::K(3)])?;
    if dims.get("N") == 0 {
        return Err(value_error(
            "rgb: no pixels (the loss is a mean over pixels)",
        ));
    }
    check_finite_f32("target", tg.slice(), 3)?;
    Ok((r, tg))
}

/// The loss (SPEC §4.7): mean over pixels and channels of ρ(rgb − target), `rgb` [N, 3]
/// (float32/float64), `target` float32 [N, 3] (as batch.target); summed in f64 per 128-pixel
/// chunk, chunks in order, as the model (`loss::loss_forward`).
#[pyfunction]
#[pyo3(signature = (rgb, target, *, kind="l1", delta=0.01))]
fn loss_forward(
    py: Python<'_>,
    rgb: &Bound<'_, PyAny>,
    target: &Bound<'_, PyAny>,
    kind: &str,
    delta: f64,
) -> PyResult<f64> {
    let k = loss_kind(kind)?;
    fn go<R: Real + Element>(
        py: Python<'_>,
        rgb: &Bound<'_, PyAny>,
        target: &Bound<'_, PyAny>,
        k: LossKind,
        delta: f64,
        t: &str,
    ) -> PyResult<f64> {
        let (r, tg) = rgb_target::<R>(rgb, target, t)?;
        let (rs, ts) = (r.slice(), dirs3(tg.slice()));
        let n = ts.len();
        compute(py, || {
            let mut sum = 0.0f64;
            for (c, tc) in ts.chunks(hfm::PIXEL_CHUNK).enumerate() {
                let p0 = c * hfm::PIXEL_CHUNK;
                sum += loss::loss_forward(k, delta, &rs[p0 * 3..(p0 + tc.len()) * 3], tc);
            }
            Ok(sum / (3 * n) as f64)
        })
    }
    dispatch!(float_kind(rgb, "rgb")?, go(py, rgb, target, k, delta))
}

/// ∂L/∂rgb [N, 3] = ρ′(rgb − target) · (1/(3N)) (`loss::loss_backward`).
#[pyfunction]
#[pyo3(signature = (rgb, target, *, kind="l1", delta=0.01))]
fn loss_backward(
    py: Python<'_>,
    rgb: &Bound<'_, PyAny>,
    target: &Bound<'_, PyAny>,
    kind: &str,
    delta: f64,
) -> PyResult<Py<PyAny>> {
    let k = loss_kind(kind)?;
    fn go<R: Real + Element>(
        py: Python<'_>,
        rgb: &Bound<'_, PyAny>,
        target: &Bound<'_, PyAny>,
        k: LossKind,
        delta: f64,
        t: &str,
    ) -> PyResult<Py<PyAny>> {
        let (r, tg) = rgb_target::<R>(rgb, target, t)?;
        let (rs, ts) = (r.slice(), dirs3(tg.slice()));
        let n = ts.len();
        let v = compute(py, || {
            let scale = R::ONE / R::from_f64((3 * n) as f64);
            let mut d = vec![R::ZERO; n * 3];
            loss::loss_backward(k, delta, rs, ts, scale, &mut d);
            Ok(d)
        })?;
        Ok(out(py, v, &[n, 3])?.unbind())
    }
    dispatch!(float_kind(rgb, "rgb")?, go(py, rgb, target, k, delta))
}

// ---------------------------------------------------------------------------------------------
// Pooling (Eq. 4), level weighting (SPEC §4.10), ξ (Eq. 5), appearance codes (SPEC §4.6)

/// The valid mask [N, S] checked (0/1, ≥ 1 per pixel) → CSR starts [N+1] and the sub-sample
/// indices of the valid rows.
fn valid_rows(valid: &In<'_, u8>) -> PyResult<(Vec<usize>, Vec<usize>)> {
    let (n, s) = (valid.shape[0], valid.shape[1]);
    let v = valid.slice();
    let mut start = Vec::with_capacity(n + 1);
    let mut idx = Vec::new();
    start.push(0);
    for i in 0..n {
        for j in 0..s {
            match v[i * s + j] {
                0 => {}
                1 => idx.push(i * s + j),
                x => {
                    return Err(value_error(format!(
                        "valid: pixel {i} sub-sample {j} is {x}, expected 0 or 1"
                    )))
                }
            }
        }
        if idx.len() == start[i] {
            return Err(value_error(format!(
                "valid: pixel {i} has no valid sub-sample (a batch never holds such a pixel)"
            )));
        }
        start.push(idx.len());
    }
    Ok((start, idx))
}

fn gather<R: Copy>(src: &[R], idx: &[usize], w: usize) -> Vec<R> {
    let mut o = Vec::with_capacity(idx.len() * w);
    for &k in idx {
        o.extend_from_slice(&src[k * w..(k + 1) * w]);
    }
    o
}

fn scatter<R: Real>(rows: &[R], idx: &[usize], w: usize, total: usize) -> Vec<R> {
    let mut o = vec![R::ZERO; total * w];
    for (r, &k) in idx.iter().enumerate() {
        o[k * w..(k + 1) * w].copy_from_slice(&rows[r * w..(r + 1) * w]);
    }
    o
}

/// Eq. 4: `pooled` [N, C] = mean over each pixel's valid sub-samples of `feat` (+ `delta`),
/// `feat`, `delta` [N, S, C], `valid` uint8 [N, S] (`hfm::pool_forward`: the sum in sub-sample
/// order from +0, each term feat+delta rounded first, one division by the count).
#[pyfunction]
#[pyo3(signature = (feat, valid, delta=None))]
fn pool_forward(
    py: Python<'_>,
    feat: &Bound<'_, PyAny>,
    valid: &Bound<'_, PyAny>,
    delta: Option<&Bound<'_, PyAny>>,
) -> PyResult<Py<PyAny>> {
    fn go<R: Real + Element>(
        py: Python<'_>,
        feat: &Bound<'_, PyAny>,
        valid: &Bound<'_, PyAny>,
        delta: Option<&Bound<'_, PyAny>>,
        t: &str,
    ) -> PyResult<Py<PyAny>> {
        let mut dims = Dims::default();
        let f = input::<R>(feat, "feat", t)?;
        dims.check("feat", &f.shape, &[A::N("N"), A::N("S"), A::N("C")])?;
        let v = input::<u8>(valid, "valid", "uint8")?;
        dims.check("valid", &v.shape, &[A::N("N"), A::N("S")])?;
        let d = match delta {
            Some(d) => {
                let d = input::<R>(d, "delta", t)?;
                dims.check("delta", &d.shape, &[A::N("N"), A::N("S"), A::N("C")])?;
                Some(d)
            }
            None => None,
        };
        let (n, c) = (dims.get("N"), dims.get("C"));
        let (start, idx) = valid_rows(&v)?;
        let (fs, ds) = (f.slice(), d.as_ref().map(|d| d.slice()));
        let o = compute(py, || {
            let rows = gather(fs, &idx, c);
            let drows = ds.map(|d| gather(d, &idx, c));
            let mut o = vec![R::ZERO; n * c];
            hfm::pool_forward(&start, &rows, drows.as_deref(), c, &mut o);
            Ok(o)
        })?;
        Ok(out(py, o, &[n, c])?.unbind())
    }
    dispatch!(float_kind(feat, "feat")?, go(py, feat, valid, delta))
}

/// Eq. 4 backward: ∂L/∂feat [N, S, C] = d_pooled / count at every valid sub-sample, 0 at the
/// others (`hfm::pool_backward`); also ∂L/∂delta.
#[pyfunction]
fn pool_backward(
    py: Python<'_>,
    d_pooled: &Bound<'_, PyAny>,
    valid: &Bound<'_, PyAny>,
) -> PyResult<Py<PyAny>> {
    fn go<R: Real + Element>(
        py: Python<'_>,
        dp: &Bound<'_, PyAny>,
        valid: &Bound<'_, PyAny>,
        t: &str,
    ) -> PyResult<Py<PyAny>> {
        let mut dims = Dims::default();
        let d = input::<R>(dp, "d_pooled", t)?;
        dims.check("d_pooled", &d.shape, &[A::N("N"), A::N("C")])?;
        let v = input::<u8>(valid, "valid", "uint8")?;
        dims.check("valid", &v.shape, &[A::N("N"), A::N("S")])?;
        let (n, s, c) = (dims.get("N"), dims.get("S"), dims.get("C"));
        let (start, idx) = valid_rows(&v)?;
        let ds = d.slice();
        let o = compute(py, || {
            let mut rows = vec![R::ZERO; idx.len() * c];
            hfm::pool_backward(&start, ds, c, c, &mut rows);
            Ok(scatter(&rows, &idx, c, n * s))
        })?;
        Ok(out(py, o, &[n, s, c])?.unbind())
    }
    dispatch!(float_kind(d_pooled, "d_pooled")?, go(py, d_pooled, valid))
}

/// Footprint level weights (SPEC §4.10): `(w, active)`, w [N, L] in `dtype` = w(footprint ·
/// scale_l), active uint8 [N] = the number of leading levels with w > 0
/// (`level_weight::level_weights`); `scales` float32 [L], `footprint` float32 [N].
#[pyfunction]
#[pyo3(signature = (scales, footprint, *, dtype="float64"))]
fn level_weights(
    py: Python<'_>,
    scales: &Bound<'_, PyAny>,
    footprint: &Bound<'_, PyAny>,
    dtype: &str,
) -> PyResult<(Py<PyAny>, Py<PyAny>)> {
    let mut dims = Dims::default();
    let s = input::<f32>(scales, "scales", "float32")?;
    dims.check("scales", &s.shape, &[A::N("L")])?;
    let f = input::<f32>(footprint, "footprint", "float32")?;
    dims.check("footprint", &f.shape, &[A::N("N")])?;
    let (nl, n) = (dims.get("L"), dims.get("N"));
    if nl > 255 {
        return Err(value_error("scales: at most 255 levels"));
    }
    let (ss, fs) = (s.slice(), f.slice());
    fn go<R: Real + Element>(
        py: Python<'_>,
        ss: &[f32],
        fs: &[f32],
        nl: usize,
        n: usize,
    ) -> PyResult<(Py<PyAny>, Py<PyAny>)> {
        let (w, act) = compute(py, || {
            let start: Vec<usize> = (0..=n).collect();
            let mut w = vec![R::ZERO; n * nl];
            let mut act = vec![0u8; n];
            level_weight::level_weights(ss, &start, fs, &mut w, &mut act);
            Ok((w, act))
        })?;
        Ok((out(py, w, &[n, nl])?.unbind(), out(py, act, &[n])?.unbind()))
    }
    match fk_of_dtype(dtype)? {
        Fk::F32 => go::<f32>(py, ss, fs, nl, n),
        Fk::F64 => go::<f64>(py, ss, fs, nl, n),
    }
}

/// `x [M, L·F] · w [M, L]` per level (`level_weight::apply_level_weights`): the weighted grid
/// output forward, and the weighted gradient backward. A new array.
#[pyfunction]
fn apply_level_weights(
    py: Python<'_>,
    w: &Bound<'_, PyAny>,
    x: &Bound<'_, PyAny>,
) -> PyResult<Py<PyAny>> {
    fn go<R: Real + Element>(
        py: Python<'_>,
        w: &Bound<'_, PyAny>,
        x: &Bound<'_, PyAny>,
        t: &str,
    ) -> PyResult<Py<PyAny>> {
        let mut dims = Dims::default();
        let wi = input::<R>(w, "w", t)?;
        dims.check("w", &wi.shape, &[A::N("M"), A::N("L")])?;
        let xi = input::<R>(x, "x", t)?;
        dims.check("x", &xi.shape, &[A::N("M"), A::N("LF")])?;
        let (nl, lf) = (dims.get("L"), dims.get("LF"));
        if nl == 0 || lf % nl != 0 {
            return Err(value_error(format!(
                "x: {lf} columns is not a multiple of w's {nl} levels"
            )));
        }
        let ws = wi.slice();
        let mut v = xi.slice().to_vec();
        let v = compute(py, move || {
            level_weight::apply_level_weights(ws, nl, lf / nl, &mut v);
            Ok(v)
        })?;
        Ok(out(py, v, &xi.shape)?.unbind())
    }
    dispatch!(float_kind(x, "x")?, go(py, w, x))
}

/// ξ's input rows `[F_D(x_j), SH(d_n)]` of the valid sub-samples.
fn deform_input<R: Real>(gd: &[R], shs: &[R], start: &[usize], idx: &[usize], ld: usize) -> Vec<R> {
    let din = ld + sh::SH_DIM;
    let mut x = vec![R::ZERO; idx.len() * din];
    for i in 0..start.len() - 1 {
        for r in start[i]..start[i + 1] {
            let k = idx[r];
            x[r * din..r * din + ld].copy_from_slice(&gd[k * ld..(k + 1) * ld]);
            x[r * din + ld..(r + 1) * din]
                .copy_from_slice(&shs[i * sh::SH_DIM..(i + 1) * sh::SH_DIM]);
        }
    }
    x
}

type DeformIn<'py, R> = (In<'py, R>, In<'py, R>, In<'py, u8>, Net<R>, Dims);

fn deform_inputs<'py, R: Real + Element>(
    grid_d: &Bound<'py, PyAny>,
    sh_: &Bound<'py, PyAny>,
    valid: &Bound<'py, PyAny>,
    weights: &Bound<'py, PyAny>,
    biases: Option<&Bound<'py, PyAny>>,
    t: &str,
) -> PyResult<DeformIn<'py, R>> {
    let mut dims = Dims::default();
    let g = input::<R>(grid_d, "grid_d", t)?;
    dims.check("grid_d", &g.shape, &[A::N("N"), A::N("S"), A::N("C")])?;
    let s = input::<R>(sh_, "sh", t)?;
    dims.check("sh", &s.shape, &[A::N("N"), A::K(sh::SH_DIM)])?;
    let v = input::<u8>(valid, "valid", "uint8")?;
    dims.check("valid", &v.shape, &[A::N("N"), A::N("S")])?;
    let net = net_from_py::<R>(dims.get("C") + sh::SH_DIM, weights, biases, t)?;
    Ok((g, s, v, net, dims))
}

/// Eq. 5, ξ forward: `(hidden, delta)` — hidden[i] [N, S, h] after ReLU, delta [N, S, L·F] the
/// linear output — of the MLP `weights` (`biases`) on `[grid_d[n, j], sh[n]]` at every valid
/// sub-sample (invalid rows 0), as the model (`Mlp::forward` on the valid rows).
#[pyfunction]
#[pyo3(signature = (grid_d, sh, valid, weights, biases=None))]
fn deform_forward(
    py: Python<'_>,
    grid_d: &Bound<'_, PyAny>,
    sh: &Bound<'_, PyAny>,
    valid: &Bound<'_, PyAny>,
    weights: &Bound<'_, PyAny>,
    biases: Option<&Bound<'_, PyAny>>,
) -> PyResult<(Py<PyAny>, Py<PyAny>)> {
    fn go<R: Real + Element>(
        py: Python<'_>,
        grid_d: &Bound<'_, PyAny>,
        sh_: &Bound<'_, PyAny>,
        valid: &Bound<'_, PyAny>,
        weights: &Bound<'_, PyAny>,
        biases: Option<&Bound<'_, PyAny>>,
        t: &str,
    ) -> PyResult<(Py<PyAny>, Py<PyAny>)> {
        let (g, s, v, net, dims) = deform_inputs::<R>(grid_d, sh_, valid, weights, biases, t)?;
        let (n, ns, c) = (dims.get("N"), dims.get("S"), dims.get("C"));
        let (start, idx) = valid_rows(&v)?;
        let (gs, ss) = (g.slice(), s.slice());
        let lf = net.mlp.out_dim();
        let (hidden, delta) = compute(py, || {
            let x = deform_input(gs, ss, &start, &idx, c);
            let wt = net.mlp.transpose_weights(&net.params);
            let mut acts = MlpActs::default();
            net.mlp.forward(&net.params, &wt, &x, idx.len(), &mut acts);
            // Back to [N, S, ·] with zero rows for the invalid sub-samples, as the dump.
            let hidden: Vec<(Vec<R>, Vec<usize>)> = acts
                .hidden
                .iter()
                .zip(&net.mlp.layers)
                .map(|(h, l)| (scatter(h, &idx, l.out_dim, n * ns), vec![n, ns, l.out_dim]))
                .collect();
            Ok((hidden, scatter(&acts.out, &idx, lf, n * ns)))
        })?;
        Ok((
            list_of(py, hidden)?.into_any().unbind(),
            out(py, delta, &[n, ns, lf])?.unbind(),
        ))
    }
    dispatch!(
        float_kind(grid_d, "grid_d")?,
        go(py, grid_d, sh, valid, weights, biases)
    )
}

type DeformBwd = (Py<PyAny>, Py<PyAny>, Py<PyAny>, Py<PyAny>);

/// Eq. 5 backward: `(d_grid_d [N, S, C], d_sh [N, 16], d_weights, d_biases)` from `d_delta`
/// [N, S, L·F] (∂L/∂δ = ∂L/∂F_H, i.e. `pool_backward`'s output before level weighting) and
/// `hidden` from [`deform_forward`]. `d_sh` (optional [N, 16], e.g. the shader's part) is what ξ's
/// part is added to, sub-samples in order, as the model accumulates ∂L/∂SH(d); weight gradients
/// are summed per 128-pixel chunk, then the chunks in order (`Mlp::backward`).
#[pyfunction]
#[pyo3(signature = (grid_d, sh, valid, weights, hidden, d_delta, *, biases=None, d_sh=None))]
#[allow(clippy::too_many_arguments)]
fn deform_backward(
    py: Python<'_>,
    grid_d: &Bound<'_, PyAny>,
    sh: &Bound<'_, PyAny>,
    valid: &Bound<'_, PyAny>,
    weights: &Bound<'_, PyAny>,
    hidden: &Bound<'_, PyAny>,
    d_delta: &Bound<'_, PyAny>,
    biases: Option<&Bound<'_, PyAny>>,
    d_sh: Option<&Bound<'_, PyAny>>,
) -> PyResult<DeformBwd> {
    #[allow(clippy::too_many_arguments)]
    fn go<R: Real + Element>(
        py: Python<'_>,
        grid_d: &Bound<'_, PyAny>,
        sh_: &Bound<'_, PyAny>,
        valid: &Bound<'_, PyAny>,
        weights: &Bound<'_, PyAny>,
        hidden: &Bound<'_, PyAny>,
        d_delta: &Bound<'_, PyAny>,
        biases: Option<&Bound<'_, PyAny>>,
        d_sh: Option<&Bound<'_, PyAny>>,
        t: &str,
    ) -> PyResult<DeformBwd> {
        let (g, s, v, net, mut dims) = deform_inputs::<R>(grid_d, sh_, valid, weights, biases, t)?;
        let (n, ns, c) = (dims.get("N"), dims.get("S"), dims.get("C"));
        let lf = net.mlp.out_dim();
        let his = hidden_from_py(hidden, &net, &mut dims, &[A::N("N"), A::N("S")], t)?;
        let dd = input::<R>(d_delta, "d_delta", t)?;
        dims.check("d_delta", &dd.shape, &[A::N("N"), A::N("S"), A::K(lf)])?;
        let dsh0 = match d_sh {
            Some(x) => {
                let x = input::<R>(x, "d_sh", t)?;
                dims.check("d_sh", &x.shape, &[A::N("N"), A::K(sh::SH_DIM)])?;
                Some(x)
            }
            None => None,
        };
        let (start, idx) = valid_rows(&v)?;
        let (gs, ss, dds) = (g.slice(), s.slice(), dd.slice());
        let hsl: Vec<&[R]> = his.iter().map(|h| h.slice()).collect();
        let dsh0 = dsh0.as_ref().map(|x| x.slice());
        let din = c + sh::SH_DIM;
        let (dp, d_gd, d_shv) = compute(py, || {
            let x = deform_input(gs, ss, &start, &idx, c);
            let hid: Vec<Vec<R>> = hsl
                .iter()
                .zip(&net.mlp.layers)
                .map(|(h, l)| gather(h, &idx, l.out_dim))
                .collect();
            let dy = gather(dds, &idx, lf);
            let hid: Vec<&[R]> = hid.iter().map(|h| &h[..]).collect();
            let mut d_din = vec![R::ZERO; idx.len() * din];
            // The model's pixel chunks of 128 (their rows of valid sub-samples).
            let mut bounds: Vec<usize> =
                (0..n).step_by(hfm::PIXEL_CHUNK).map(|p| start[p]).collect();
            bounds.push(idx.len());
            let dp = chunked_backward(&net, &x, &hid, &dy, &bounds, &mut d_din);
            let mut d_gd_rows = vec![R::ZERO; idx.len() * c];
            let mut d_shv = match dsh0 {
                Some(x) => x.to_vec(),
                None => vec![R::ZERO; n * sh::SH_DIM],
            };
            for i in 0..n {
                for r in start[i]..start[i + 1] {
                    let row = &d_din[r * din..(r + 1) * din];
                    d_gd_rows[r * c..(r + 1) * c].copy_from_slice(&row[..c]);
                    for (d, &g) in d_shv[i * sh::SH_DIM..(i + 1) * sh::SH_DIM]
                        .iter_mut()
                        .zip(&row[c..])
                    {
                        *d += g;
                    }
                }
            }
            Ok((dp, scatter(&d_gd_rows, &idx, c, n * ns), d_shv))
        })?;
        let (dws, dbs) = grads_to_py(py, &net, &dp)?;
        Ok((
            out(py, d_gd, &[n, ns, c])?.unbind(),
            out(py, d_shv, &[n, sh::SH_DIM])?.unbind(),
            dws,
            dbs,
        ))
    }
    match float_kind(grid_d, "grid_d")? {
        Fk::F32 => go::<f32>(
            py, grid_d, sh, valid, weights, hidden, d_delta, biases, d_sh, "float32",
        ),
        Fk::F64 => go::<f64>(
            py, grid_d, sh, valid, weights, hidden, d_delta, biases, d_sh, "float64",
        ),
    }
}

fn check_views(view: &[i32], rows: usize) -> PyResult<()> {
    for (i, &v) in view.iter().enumerate() {
        if v < -1 || v >= rows as i32 {
            return Err(value_error(format!(
                "view: pixel {i}: view {v} has no appearance code (the table has {rows} rows; -1 = the mean)"
            )));
        }
    }
    Ok(())
}

/// Each pixel's appearance code [N, A]: its row of `codes` [V, A], or for `view = −1` the mean
/// of all rows (`hfm::appearance_mean`: row order, then one division).
#[pyfunction]
fn appearance_forward(
    py: Python<'_>,
    codes: &Bound<'_, PyAny>,
    view: &Bound<'_, PyAny>,
) -> PyResult<Py<PyAny>> {
    fn go<R: Real + Element>(
        py: Python<'_>,
        codes: &Bound<'_, PyAny>,
        view: &Bound<'_, PyAny>,
        t: &str,
    ) -> PyResult<Py<PyAny>> {
        let mut dims = Dims::default();
        let c = input::<R>(codes, "codes", t)?;
        dims.check("codes", &c.shape, &[A::N("V"), A::N("A")])?;
        let v = input::<i32>(view, "view", "int32")?;
        dims.check("view", &v.shape, &[A::N("N")])?;
        let (nv, a, n) = (dims.get("V"), dims.get("A"), dims.get("N"));
        check_views(v.slice(), nv)?;
        let (cs, vs) = (c.slice(), v.slice());
        let o = compute(py, || {
            let mean = hfm::appearance_mean(cs, a, nv);
            let mut o = vec![R::ZERO; n * a];
            for (i, &vw) in vs.iter().enumerate() {
                let src = if vw >= 0 {
                    &cs[vw as usize * a..(vw as usize + 1) * a]
                } else {
                    &mean[..]
                };
                o[i * a..(i + 1) * a].copy_from_slice(src);
            }
            Ok(o)
        })?;
        Ok(out(py, o, &[n, a])?.unbind())
    }
    dispatch!(float_kind(codes, "codes")?, go(py, codes, view))
}

/// ∂L/∂codes [views, A] from the pixels' code gradients `d_code` [N, A]
/// (`hfm::appearance_backward`: rows in pixel order, then the view −1 pixels' sum / views added
/// to every row).
#[pyfunction]
fn appearance_backward(
    py: Python<'_>,
    d_code: &Bound<'_, PyAny>,
    view: &Bound<'_, PyAny>,
    views: usize,
) -> PyResult<Py<PyAny>> {
    fn go<R: Real + Element>(
        py: Python<'_>,
        d_code: &Bound<'_, PyAny>,
        view: &Bound<'_, PyAny>,
        views: usize,
        t: &str,
    ) -> PyResult<Py<PyAny>> {
        let mut dims = Dims::default();
        let d = input::<R>(d_code, "d_code", t)?;
        dims.check("d_code", &d.shape, &[A::N("N"), A::N("A")])?;
        let v = input::<i32>(view, "view", "int32")?;
        dims.check("view", &v.shape, &[A::N("N")])?;
        let a = dims.get("A");
        check_views(v.slice(), views)?;
        let (ds, vs) = (d.slice(), v.slice());
        let o = compute(py, || {
            let mut o = vec![R::ZERO; views * a];
            hfm::appearance_backward(vs, ds, a, views, &mut o);
            Ok(o)
        })?;
        Ok(out(py, o, &[views, a])?.unbind())
    }
    dispatch!(float_kind(d_code, "d_code")?, go(py, d_code, view, views))
}

// ---------------------------------------------------------------------------------------------
// The whole model

/// A checkpoint's model: its config, parameters and grids, and the whole model step.
#[pyclass(name = "_Model", module = "xscale", frozen)]
struct PyModel {
    ckpt: Checkpoint,
}

fn batch_from_py(tensors: &Bound<'_, PyDict>) -> PyResult<xscale::model::Batch> {
    let f = file_from_py(tensors, None, Some("batch"))?;
    xscale::model::checkpoint::batch_from_tensors(&f).map_err(|e| value_error(format!("{e:#}")))
}

#[pymethods]
impl PyModel {
    /// From a checkpoint's tensors and metadata (what `load` returns), validated as the CLI
    /// validates a checkpoint file.
    #[new]
    #[pyo3(signature = (tensors, metadata, label="checkpoint"))]
    fn new(
        tensors: &Bound<'_, PyDict>,
        metadata: &Bound<'_, PyDict>,
        label: &str,
    ) -> PyResult<Self> {
        let f = file_from_py(tensors, Some(metadata), Some(label))?;
        let ckpt = Checkpoint::from_tensor_file(&f).map_err(|e| value_error(format!("{e:#}")))?;
        Ok(PyModel { ckpt })
    }

    /// The whole model step on a batch (`checkpoint::dump_with`, what `xscale dump` writes):
    /// `(tensors, metadata)` of the dump in `precision` ("f64" or "f32"); `kink_threshold` (f64
    /// only; None = no kink analysis).
    #[pyo3(signature = (batch, precision="f64", kink_threshold=None))]
    fn step<'py>(
        &self,
        py: Python<'py>,
        batch: &Bound<'py, PyDict>,
        precision: &str,
        kink_threshold: Option<f64>,
    ) -> PyResult<(Bound<'py, PyDict>, Bound<'py, PyDict>)> {
        let b = batch_from_py(batch)?;
        self.ckpt
            .model
            .check_batch(&b)
            .map_err(|e| value_error(format!("batch: {e:#}")))?;
        if let Some(t) = kink_threshold {
            if !(0.0..1.0).contains(&t) {
                return Err(value_error(format!(
                    "kink_threshold {t}: expected a number in [0, 1)"
                )));
            }
        }
        let ck = &self.ckpt;
        let f = match fk_of_dtype(precision)? {
            Fk::F64 => compute(py, || {
                xscale::model::checkpoint::dump_with::<f64>(
                    ck,
                    &b,
                    kink_threshold.filter(|&t| t > 0.0),
                )
            })?,
            Fk::F32 => {
                if kink_threshold.is_some_and(|t| t > 0.0) {
                    return Err(value_error(
                        "kink_threshold: the kink analysis is part of the f64 oracle dump",
                    ));
                }
                compute(py, || {
                    xscale::model::checkpoint::dump_with::<f32>(ck, &b, None)
                })?
            }
        };
        file_to_py(py, &f)
    }

    /// The manifest (JSON text) of this model on `batch`: every dump tensor and the switches
    /// (`model::manifest`, as `xscale case` writes it).
    fn manifest(&self, py: Python<'_>, batch: &Bound<'_, PyDict>) -> PyResult<String> {
        let b = batch_from_py(batch)?;
        self.ckpt
            .model
            .check_batch(&b)
            .map_err(|e| value_error(format!("batch: {e:#}")))?;
        let ck = &self.ckpt;
        compute(py, || {
            let m = xscale::model::manifest::manifest_for(ck, &b, &BTreeMap::new())?;
            Ok(serde_json::to_string_pretty(&m)?)
        })
    }

    /// The model config as TOML text.
    #[getter]
    fn config_toml(&self) -> PyResult<String> {
        toml::to_string(&self.ckpt.model.cfg).map_err(value_error)
    }
    /// The normalisation as JSON text.
    #[getter]
    fn normalization_json(&self) -> PyResult<String> {
        serde_json::to_string(&self.ckpt.normalization).map_err(value_error)
    }
    /// Parameter tensors (float32), by name.
    #[getter]
    fn params<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let d = PyDict::new(py);
        for t in &self.ckpt.model.layout.tensors {
            d.set_item(
                &t.name,
                out(py, self.ckpt.params[t.range()].to_vec(), &t.shape)?,
            )?;
        }
        Ok(d)
    }
    /// Grid H, with the checkpoint's saved scales and positions mode.
    #[getter]
    fn grid_h(&self) -> PyHashGrid {
        PyHashGrid {
            grid: self.ckpt.model.grid_h.clone(),
            mode: self.ckpt.model.cfg.positions,
        }
    }
    /// Grid D (None without the deformation).
    #[getter]
    fn grid_d(&self) -> Option<PyHashGrid> {
        self.ckpt.model.grid_d.as_ref().map(|g| PyHashGrid {
            grid: g.clone(),
            mode: self.ckpt.model.cfg.positions,
        })
    }
}

// ---------------------------------------------------------------------------------------------
// compare (`xscale compare`'s rules)

/// Tolerances from a spec: a built-in set's name, or TOML text.
fn tolerances(spec: &str) -> PyResult<xscale::io::compare::Tolerances> {
    if let Some(t) = xscale::io::compare::Tolerances::builtin(spec) {
        return Ok(t);
    }
    if spec.contains('\n') || spec.contains('[') || spec.contains('=') {
        return xscale::io::compare::Tolerances::from_toml(spec, "tolerances")
            .map_err(|e| value_error(format!("{e:#}")));
    }
    Err(value_error(format!(
        "tolerances {spec:?}: not a built-in set ({})",
        xscale::io::compare::builtin_tolerance_names().join(", ")
    )))
}

/// `xscale compare` on two dicts: `(exit_code, table_text, report_json)`. `a` is the reference
/// (the oracle: its kink slack widens the limits), `b` the backend's. `partial`: compare only
/// the tensors `b` has (required rules off).
#[pyfunction]
#[pyo3(signature = (a, b, tolerances_spec, *, a_meta=None, b_meta=None, partial=false, allow_nan=false, kink_slack=true, label_a="oracle", label_b="mine"))]
#[allow(clippy::too_many_arguments)]
fn _compare(
    py: Python<'_>,
    a: &Bound<'_, PyDict>,
    b: &Bound<'_, PyDict>,
    tolerances_spec: &str,
    a_meta: Option<&Bound<'_, PyDict>>,
    b_meta: Option<&Bound<'_, PyDict>>,
    partial: bool,
    allow_nan: bool,
    kink_slack: bool,
    label_a: &str,
    label_b: &str,
) -> PyResult<(u8, String, String)> {
    let mut tol = tolerances(tolerances_spec)?;
    let mut fa = file_from_py(a, a_meta, Some(label_a))?;
    let fb = file_from_py(b, b_meta, Some(label_b))?;
    if allow_nan {
        tol.allow_nan = true;
    }
    if !kink_slack {
        tol.kink_slack = false;
    }
    if partial {
        for r in tol.rules.iter_mut() {
            r.required = false;
        }
        if let Some(d) = tol.default.as_mut() {
            d.required = false;
        }
        tol.strict = false;
        let keep = |k: &str| {
            fb.tensors.contains_key(k)
                || k == "kink.pixels"
                || k == "kink.threshold"
                || k.strip_prefix("kink.slack.")
                    .is_some_and(|n| fb.tensors.contains_key(n))
        };
        fa.tensors.retain(|k, _| keep(k));
        let missing: Vec<&String> = fb
            .tensors
            .keys()
            .filter(|k| !fa.tensors.contains_key(*k))
            .collect();
        if !missing.is_empty() {
            return Err(value_error(format!(
                "not in the oracle: {}",
                missing
                    .iter()
                    .map(|s| s.as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            )));
        }
    }
    let (code, table, json) = compute(py, || {
        let r = xscale::io::compare::compare(&fa, &fb, &tol);
        Ok((
            r.exit_code(),
            r.to_table(),
            xscale::io::compare::report_json(&r)?,
        ))
    })?;
    Ok((code, table, json))
}

/// The TOML text of a built-in tolerance set.
#[pyfunction]
fn tolerance_text(name: &str) -> PyResult<&'static str> {
    xscale::io::compare::builtin_tolerance_text(name).ok_or_else(|| {
        value_error(format!(
            "{name:?}: not a built-in tolerance set ({})",
            xscale::io::compare::builtin_tolerance_names().join(", ")
        ))
    })
}

/// The names of the built-in tolerance sets.
#[pyfunction]
fn tolerance_sets() -> Vec<&'static str> {
    xscale::io::compare::builtin_tolerance_names()
}

/// Run the `xscale` command line in this process (`python -m xscale …`); the exit code. Commands
/// that train install a Ctrl-C handler for the process: call it from a process of its own.
#[pyfunction]
fn _cli(py: Python<'_>, argv: Vec<String>) -> PyResult<u8> {
    Ok(py.detach(move || xscale::cli::exit_code_value(xscale::cli::main_with(argv))))
}

/// For the tests: a Rust panic in a computation (in the calling thread, or in a worker of the
/// pool with `worker=True`) becomes a `RuntimeError`; the interpreter goes on.
#[pyfunction]
#[pyo3(signature = (worker=false))]
fn _panic_for_test(py: Python<'_>, worker: bool) -> PyResult<()> {
    compute(py, move || -> anyhow::Result<()> {
        if worker {
            use rayon::prelude::*;
            (0..64).into_par_iter().for_each(|i| {
                if i == 63 {
                    panic!("deliberate panic in a worker (test)");
                }
            });
        }
        panic!("deliberate panic (test)")
    })
}

#[pymodule]
fn _xscale(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add("PIXEL_CHUNK", hfm::PIXEL_CHUNK)?;
    m.add("SH_DIM", sh::SH_DIM)?;
    m.add(
        "DEFAULT_KINK_THRESHOLD",
        xscale::model::kink::DEFAULT_THRESHOLD,
    )?;
    m.add_class::<PyHashGrid>()?;
    m.add_class::<PyModel>()?;
    m.add_function(wrap_pyfunction!(set_num_threads, m)?)?;
    m.add_function(wrap_pyfunction!(get_num_threads, m)?)?;
    m.add_function(wrap_pyfunction!(_last_kernel_seconds, m)?)?;
    m.add_function(wrap_pyfunction!(_toml_to_json, m)?)?;
    m.add_function(wrap_pyfunction!(_json_to_toml, m)?)?;
    m.add_function(wrap_pyfunction!(load, m)?)?;
    m.add_function(wrap_pyfunction!(save, m)?)?;
    m.add_function(wrap_pyfunction!(sh_forward, m)?)?;
    m.add_function(wrap_pyfunction!(sh_backward, m)?)?;
    m.add_function(wrap_pyfunction!(mlp_forward, m)?)?;
    m.add_function(wrap_pyfunction!(mlp_backward, m)?)?;
    m.add_function(wrap_pyfunction!(linear_forward, m)?)?;
    m.add_function(wrap_pyfunction!(linear_backward, m)?)?;
    m.add_function(wrap_pyfunction!(relu_forward, m)?)?;
    m.add_function(wrap_pyfunction!(relu_backward, m)?)?;
    m.add_function(wrap_pyfunction!(sigmoid_forward, m)?)?;
    m.add_function(wrap_pyfunction!(sigmoid_backward, m)?)?;
    m.add_function(wrap_pyfunction!(loss_forward, m)?)?;
    m.add_function(wrap_pyfunction!(loss_backward, m)?)?;
    m.add_function(wrap_pyfunction!(pool_forward, m)?)?;
    m.add_function(wrap_pyfunction!(pool_backward, m)?)?;
    m.add_function(wrap_pyfunction!(level_weights, m)?)?;
    m.add_function(wrap_pyfunction!(apply_level_weights, m)?)?;
    m.add_function(wrap_pyfunction!(deform_forward, m)?)?;
    m.add_function(wrap_pyfunction!(deform_backward, m)?)?;
    m.add_function(wrap_pyfunction!(appearance_forward, m)?)?;
    m.add_function(wrap_pyfunction!(appearance_backward, m)?)?;
    m.add_function(wrap_pyfunction!(_compare, m)?)?;
    m.add_function(wrap_pyfunction!(tolerance_text, m)?)?;
    m.add_function(wrap_pyfunction!(tolerance_sets, m)?)?;
    m.add_function(wrap_pyfunction!(_cli, m)?)?;
    m.add_function(wrap_pyfunction!(_panic_for_test, m)?)?;
    Ok(())
}
