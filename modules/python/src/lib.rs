//! `dnm._dnm`: the module SDK's runtime for modules written in Python (the `dnm` package wraps
//! it). One implementation of the protocol: a Python module runs in the Rust SDK's module
//! process loop ([`dnm_module::run_dynamic`]), which waits for its inputs with the GIL released
//! and calls the module's `step` with it held.
//!
//! Inputs are handed to Python on the producer's shared-memory sample itself (no copy; valid
//! for the step): a bytes input as a read-only numpy array made with numpy's C API (an image
//! shaped from its header), a message as a read-only `memoryview` its class decodes. Outputs
//! are loaned in shared memory and handed as writable `memoryview`s to fill in place, then
//! sent. An exception in `step` ends the process
//! with its traceback, which the DNM reports in the module's exit event before it applies the
//! restart policy.

use std::collections::BTreeMap;
use std::os::raw::c_char;

use dnm_module::protocol::Launch;
use dnm_module::{Io, ModuleError, Setup, Stepper};
use dnm_netlist::{KindSpec, MessageType, ParamValue};
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyList;

/// A read-only (or, with `writable`, writable) memoryview of `len` bytes at `ptr`.
///
/// # Safety
/// The memory must stay valid (mapped) for as long as Python may use the view; the caller
/// documents for how long its contents mean anything.
unsafe fn memoryview(
    py: Python<'_>,
    ptr: *const u8,
    len: usize,
    writable: bool,
) -> PyResult<Bound<'_, PyAny>> {
    let flags = if writable {
        pyo3::ffi::PyBUF_WRITE
    } else {
        pyo3::ffi::PyBUF_READ
    };
    // SAFETY: the caller keeps the memory valid; a null result is turned into the exception
    // Python set.
    unsafe {
        let view = pyo3::ffi::PyMemoryView_FromMemory(
            ptr as *mut c_char,
            len as pyo3::ffi::Py_ssize_t,
            flags,
        );
        Bound::from_owned_ptr_or_err(py, view)
    }
}

/// A read-only numpy array on `bytes`, made with numpy's C API (no Python code runs): `uint8`
/// of shape `(len,)`, or with `image` and a header that fits, `(height, width, 3)` on the
/// pixels after it with the header's row step.
///
/// # Safety
/// As [`memoryview`]: the memory stays mapped while Python may use the array, beyond the
/// borrow of `bytes`.
unsafe fn array<'py>(py: Python<'py>, bytes: &[u8], image: bool) -> PyResult<Bound<'py, PyAny>> {
    use dnm_rover::msgs::{IMAGE_HEADER, ImageLayout};
    use numpy::npyffi::{
        NPY_ARRAY_ALIGNED, NPY_ARRAY_C_CONTIGUOUS, NPY_TYPES, NpyTypes, PY_ARRAY_API, npy_intp,
    };
    let (data, mut dims, mut strides, nd) = match image.then(|| ImageLayout::of(bytes)).flatten() {
        Some(l) => (
            bytes[IMAGE_HEADER..].as_ptr(),
            [l.height as npy_intp, l.width as npy_intp, 3],
            [l.step as npy_intp, 3, 1],
            3,
        ),
        None => (
            bytes.as_ptr(),
            [bytes.len() as npy_intp, 0, 0],
            [1, 0, 0],
            1,
        ),
    };
    let flags = if nd == 1 {
        NPY_ARRAY_C_CONTIGUOUS | NPY_ARRAY_ALIGNED
    } else {
        NPY_ARRAY_ALIGNED
    };
    // The array's base: a read-only view of the sample, so that numpy refuses to make the
    // array writable whatever its version (numpy 1.x let an array with no base be).
    // SAFETY: as this function's.
    let base = unsafe { memoryview(py, bytes.as_ptr(), bytes.len(), false)? };
    // SAFETY: `dims` and `strides` describe memory inside `bytes` (`ImageLayout::of` checked
    // the rows fit); without the WRITEABLE flag Python cannot write it; the result (a new
    // reference, or null with Python's exception set) is owned, and the base's reference is
    // given to it (PyArray_SetBaseObject steals it, also when it fails).
    unsafe {
        let a = PY_ARRAY_API.PyArray_New(
            py,
            PY_ARRAY_API.get_type_object(py, NpyTypes::PyArray_Type),
            nd,
            dims.as_mut_ptr(),
            NPY_TYPES::NPY_UBYTE as std::os::raw::c_int,
            strides.as_mut_ptr(),
            data as *mut std::os::raw::c_void,
            1,
            flags,
            std::ptr::null_mut(),
        );
        let a = Bound::from_owned_ptr_or_err(py, a)?;
        if PY_ARRAY_API.PyArray_SetBaseObject(py, a.as_ptr().cast(), base.into_ptr()) < 0 {
            return Err(PyErr::fetch(py));
        }
        Ok(a)
    }
}

fn module_error(e: ModuleError) -> PyErr {
    PyRuntimeError::new_err(e.to_string())
}

/// What `step` is given: the step's inputs and outputs, valid only during the step.
#[pyclass(unsendable, module = "dnm._dnm")]
struct RawIo {
    io: *mut Io<'static>,
    /// Outputs loaned in this step and not sent (their arrays are locked when it ends).
    loaned: Vec<usize>,
}

impl RawIo {
    fn io(&mut self) -> PyResult<&mut Io<'static>> {
        // SAFETY: `io` is set only for the duration of the `step` call that created this object
        // (and cleared before the `Io` it points to goes away); a null pointer is refused.
        unsafe { self.io.as_mut() }.ok_or_else(|| {
            PyRuntimeError::new_err(
                "this `io` belongs to a step that has ended: use it only inside `step`",
            )
        })
    }
}

type Received<'py> = Option<(Bound<'py, PyAny>, u64, u64, u64)>;

#[pymethods]
impl RawIo {
    /// CLOCK_MONOTONIC time at the start of the step, ns.
    fn now_ns(&mut self) -> PyResult<u64> {
        Ok(self.io()?.now_ns())
    }

    /// The task the step runs under.
    fn task(&mut self) -> PyResult<Option<String>> {
        Ok(self.io()?.task().map(str::to_string))
    }

    /// The newest sample of input `index`, new or not.
    fn latest<'py>(&mut self, py: Python<'py>, index: usize) -> PyResult<Received<'py>> {
        let Some((h, bytes)) = self.io()?.latest_raw(index) else {
            return Ok(None);
        };
        let (ptr, len) = (bytes.as_ptr(), bytes.len());
        // SAFETY: the sample is held by the module's subscriber until a newer one replaces it,
        // after this step at the earliest; the segment stays mapped while the process runs.
        let view = unsafe { memoryview(py, ptr, len, false)? };
        Ok(Some((view, h.stamp_ns, h.seq, ptr as u64)))
    }

    /// The newest sample of a message input `index` not read yet, as a read-only view its
    /// class decodes: the hot path of `io.read` for messages.
    fn take_view<'py>(
        &mut self,
        py: Python<'py>,
        index: usize,
    ) -> PyResult<Option<Bound<'py, PyAny>>> {
        let Some((_, bytes)) = self.io()?.take_raw(index) else {
            return Ok(None);
        };
        // SAFETY: as in `latest`.
        unsafe { memoryview(py, bytes.as_ptr(), bytes.len(), false) }.map(Some)
    }

    /// A bytes input `index` as a read-only numpy array on its sample (an image's `(height,
    /// width, 3)` with `image`): the newest sample not read yet (the hot path of `io.read`),
    /// or with `latest` the newest, new or not.
    fn array<'py>(
        &mut self,
        py: Python<'py>,
        index: usize,
        image: bool,
        latest: bool,
    ) -> PyResult<Option<Bound<'py, PyAny>>> {
        let io = self.io()?;
        let got = if latest {
            io.latest_raw(index)
        } else {
            io.take_raw(index)
        };
        let Some((_, bytes)) = got else {
            return Ok(None);
        };
        // SAFETY: as in `latest`.
        unsafe { array(py, bytes, image) }.map(Some)
    }

    /// Sends `data` on output `index` (copied once into shared memory).
    fn write(&mut self, index: usize, data: &[u8]) -> PyResult<()> {
        self.io()?.write_raw(index, data).map_err(module_error)
    }

    /// Loans `len` zeroed bytes of shared memory on output `index`: (writable view, address).
    fn loan<'py>(
        &mut self,
        py: Python<'py>,
        index: usize,
        len: usize,
    ) -> PyResult<(Bound<'py, PyAny>, u64)> {
        if !self.loaned.contains(&index) {
            self.loaned.push(index);
        }
        let buf = self.io()?.loan_raw(index, len).map_err(module_error)?;
        let ptr = buf.as_mut_ptr();
        // SAFETY: the loaned sample stays in the output until it is sent or the step ends;
        // the segment stays mapped while the process runs.
        let view = unsafe { memoryview(py, ptr, len, true)? };
        Ok((view, ptr as u64))
    }

    /// Sends what was loaned on output `index`.
    fn send(&mut self, index: usize) -> PyResult<()> {
        self.loaned.retain(|&i| i != index);
        self.io()?.send_loaned(index).map_err(module_error)
    }
}

/// What the module's constructor is given: its name, parameters and ports.
#[pyclass(unsendable, module = "dnm._dnm")]
struct RawSetup {
    setup: *mut Setup<'static>,
}

impl RawSetup {
    fn setup(&self) -> PyResult<&Setup<'static>> {
        // SAFETY: set only while the constructor runs, cleared before the `Setup` goes away.
        unsafe { self.setup.as_ref() }.ok_or_else(|| {
            PyRuntimeError::new_err("this `setup` belongs to a constructor that has returned")
        })
    }
}

#[pymethods]
impl RawSetup {
    fn name(&self) -> PyResult<String> {
        Ok(self.setup()?.name().to_string())
    }

    /// The parameter's value (given in the netlist, else its default).
    fn param<'py>(&self, py: Python<'py>, name: &str) -> PyResult<Bound<'py, PyAny>> {
        let v = self.setup()?.param(name).map_err(module_error)?;
        Ok(match v {
            ParamValue::Int(i) => i.into_pyobject(py)?.into_any(),
            ParamValue::Float(f) => f.into_pyobject(py)?.into_any(),
            ParamValue::Bool(b) => b.into_pyobject(py)?.to_owned().into_any(),
            ParamValue::String(s) => s.into_pyobject(py)?.into_any(),
        })
    }

    /// (index, message type as JSON) of port `name`.
    fn port(&self, name: &str, input: bool) -> PyResult<(usize, String)> {
        let (index, spec) = self.setup()?.port(name, input).map_err(module_error)?;
        let json = serde_json::to_string(&spec.message)
            .map_err(|e| PyValueError::new_err(e.to_string()))?;
        Ok((index, json))
    }
}

/// A Python module object, stepped by the runtime: its `step(io)` is called with the GIL,
/// with the same `io` each step (its `raw_io` pointing at that step's `Io` for the call only).
struct PyStepper {
    stepped: Py<PyAny>,
    step: Py<PyAny>,
    io: Option<Py<PyAny>>,
    raw: Py<RawIo>,
}

impl PyStepper {
    fn new(py: Python<'_>, stepped: Py<PyAny>) -> PyResult<Self> {
        Ok(Self {
            step: stepped.getattr(py, "step")?,
            stepped,
            io: None,
            raw: Py::new(
                py,
                RawIo {
                    io: std::ptr::null_mut(),
                    loaned: Vec::new(),
                },
            )?,
        })
    }
}

/// A Python exception as its traceback reads.
fn traceback(py: Python<'_>, e: &PyErr) -> String {
    // The `dnm` package formats it where the exception is caught, with its frames.
    if let Ok(text) = e
        .value(py)
        .getattr("__dnm_traceback__")
        .and_then(|t| t.extract::<String>())
    {
        return text;
    }
    let formatted = py
        .import("traceback")
        .and_then(|tb| {
            // Its frames travel beside the exception until it is raised again in Python.
            let frames = e.traceback(py).map(|t| t.into_any());
            tb.call_method1(
                "format_exception",
                (
                    e.get_type(py),
                    e.value(py),
                    frames.unwrap_or_else(|| py.None().into_bound(py)),
                ),
            )
        })
        .and_then(|lines| lines.cast_into::<PyList>().map_err(PyErr::from))
        .map(|lines| {
            lines
                .iter()
                .filter_map(|l| l.extract::<String>().ok())
                .collect::<String>()
        });
    formatted
        .unwrap_or_else(|_| e.to_string())
        .trim_end()
        .to_string()
}

impl PyStepper {
    /// Hands the module's `_bind(raw_io)` the object each step's `Io` goes through.
    fn bind(mut self, py: Python<'_>) -> PyResult<Self> {
        self.stepped
            .call_method1(py, "_bind", (self.raw.clone_ref(py),))?;
        self.io = Some(self.stepped.getattr(py, "io")?);
        Ok(self)
    }
}

impl Stepper for PyStepper {
    fn step_io(&mut self, io: &mut Io<'_>) -> Result<(), ModuleError> {
        Python::attach(|py| {
            self.raw.borrow_mut(py).io = (io as *mut Io<'_>).cast::<Io<'static>>();
            let result = match &self.io {
                Some(obj) => self.step.call1(py, (obj.clone_ref(py),)),
                None => Err(PyRuntimeError::new_err("the module's `io` is not bound")),
            };
            let loaned = {
                let mut raw = self.raw.borrow_mut(py);
                raw.io = std::ptr::null_mut();
                let open = !raw.loaned.is_empty();
                raw.loaned.clear();
                open
            };
            // What was loaned and not sent went back to the pool: its arrays turn read-only.
            let closed = match (&self.io, loaned) {
                (Some(obj), true) => obj.call_method0(py, "_end_step").map(|_| ()),
                _ => Ok(()),
            };
            result
                .and(closed)
                .map_err(|e| ModuleError::Fatal(traceback(py, &e)))
        })
    }
}

/// Runs a Python module process: `launch` as the DNM gave it, `spec` the kind's declaration
/// (JSON), `factory(raw_setup)` builds the module object. Returns when the DNM stops it.
#[pyfunction]
fn run(py: Python<'_>, launch: &str, spec: &str, factory: Py<PyAny>) -> PyResult<()> {
    let launch: Launch = serde_json::from_str(launch)
        .map_err(|e| PyValueError::new_err(format!("bad launch description: {e}")))?;
    let spec: KindSpec = serde_json::from_str(spec)
        .map_err(|e| PyValueError::new_err(format!("bad kind declaration: {e}")))?;
    dnm_module::init_logging();
    let mut make = |setup: &mut Setup<'_>| -> Result<Box<dyn Stepper>, ModuleError> {
        Python::attach(|py| {
            let raw = Py::new(
                py,
                RawSetup {
                    setup: (setup as *mut Setup<'_>).cast::<Setup<'static>>(),
                },
            )
            .map_err(|e| ModuleError::Fatal(traceback(py, &e)))?;
            let built = factory.call1(py, (raw.clone_ref(py),));
            raw.borrow_mut(py).setup = std::ptr::null_mut();
            let module = built.map_err(|e| ModuleError::Fatal(traceback(py, &e)))?;
            let stepper = PyStepper::new(py, module)
                .and_then(|s| s.bind(py))
                .map_err(|e| ModuleError::Fatal(traceback(py, &e)))?;
            Ok(Box::new(stepper) as Box<dyn Stepper>)
        })
    };
    // The loop waits for inputs without the GIL; it takes it for each step.
    py.detach(|| dnm_module::run_dynamic(&launch, spec, &mut make))
        .map_err(|e| PyRuntimeError::new_err(e.to_string()))
}

/// One frame of the offline protocol: a 4-byte little-endian length, a JSON header of that
/// length, then the payloads the header lists, back to back.
fn read_frame<R: std::io::Read>(
    r: &mut R,
) -> std::io::Result<Option<(serde_json::Value, Vec<u8>)>> {
    let mut len = [0u8; 4];
    match r.read_exact(&mut len) {
        Ok(()) => {}
        Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => return Ok(None),
        Err(e) => return Err(e),
    }
    let mut head = vec![0u8; u32::from_le_bytes(len) as usize];
    r.read_exact(&mut head)?;
    let head: serde_json::Value = serde_json::from_slice(&head)?;
    let total: u64 = head["payload_bytes"].as_u64().unwrap_or(0);
    // Samples of at most a few MiB each come this way: a larger frame is not the check's.
    if total > 1 << 30 {
        return Err(std::io::ErrorKind::InvalidData.into());
    }
    let mut body = vec![0u8; total as usize];
    r.read_exact(&mut body)?;
    Ok(Some((head, body)))
}

fn write_frame(
    w: &mut impl std::io::Write,
    head: &serde_json::Value,
    body: &[u8],
) -> std::io::Result<()> {
    let head = serde_json::to_vec(head)?;
    w.write_all(&(head.len() as u32).to_le_bytes())?;
    w.write_all(&head)?;
    w.write_all(body)?;
    w.flush()
}

/// Steps a Python module without a DNM for the determinism check (`dnm replay --check MODULE
/// --exec FILE`), serving the check over standard input and output: each request sets and
/// clears inputs, sets the task and steps the module once (the SDK's `Offline`); the answer is
/// what it wrote, or the traceback of its exception.
#[pyfunction]
fn offline(py: Python<'_>, launch: &str, spec: &str, factory: Py<PyAny>) -> PyResult<()> {
    use serde_json::json;
    let launch: Launch = serde_json::from_str(launch)
        .map_err(|e| PyValueError::new_err(format!("bad launch description: {e}")))?;
    let spec: KindSpec = serde_json::from_str(spec)
        .map_err(|e| PyValueError::new_err(format!("bad kind declaration: {e}")))?;
    let io_err = |e: std::io::Error| PyRuntimeError::new_err(format!("the check's pipe: {e}"));
    let mut setup = Setup::new(&launch.module, &spec, &launch.params);
    let raw = Py::new(
        py,
        RawSetup {
            setup: (&mut setup as *mut Setup<'_>).cast::<Setup<'static>>(),
        },
    )?;
    let built = factory.call1(py, (raw.clone_ref(py),));
    raw.borrow_mut(py).setup = std::ptr::null_mut();
    let mut module = PyStepper::new(py, built?)?.bind(py)?;
    let mut offline = dnm_module::Offline::new(&spec, None);
    let (mut stdin, mut stdout) = (std::io::stdin(), std::io::stdout().lock());
    while let Some((head, body)) = py.detach(|| read_frame(&mut stdin)).map_err(io_err)? {
        offline.set_task(head["task"].as_str());
        for i in head["clear"].as_array().into_iter().flatten() {
            offline.clear_input(i.as_u64().unwrap_or(u64::MAX) as usize);
        }
        let mut at = 0usize;
        for s in head["set"].as_array().into_iter().flatten() {
            let field = |i: usize| s.get(i).and_then(|v| v.as_u64()).unwrap_or(0);
            let len = field(3) as usize;
            let bytes = body.get(at..at + len).unwrap_or_default().to_vec();
            at += len;
            offline.set_input(field(0) as usize, field(1), field(2), bytes);
        }
        let now = head["now_ns"].as_u64().unwrap_or(0);
        let (answer, out) = match offline.step(&mut module, now) {
            Ok(written) => {
                let list: Vec<_> = written
                    .iter()
                    .map(|(i, _, b)| json!([i, b.len()]))
                    .collect();
                let out: Vec<u8> = written.into_iter().flat_map(|(_, _, b)| b).collect();
                (
                    json!({"ok": true, "outputs": list, "payload_bytes": out.len()}),
                    out,
                )
            }
            Err(e) => (
                json!({"ok": false, "error": e.to_string(), "payload_bytes": 0}),
                Vec::new(),
            ),
        };
        write_frame(&mut stdout, &answer, &out).map_err(io_err)?;
    }
    Ok(())
}

/// Checks a kind declaration (JSON) and returns it as the DNM reads it.
#[pyfunction]
fn check_kind(spec: &str) -> PyResult<String> {
    let spec: KindSpec = serde_json::from_str(spec)
        .map_err(|e| PyValueError::new_err(format!("bad kind declaration: {e}")))?;
    // Names as a netlist takes them, so a kind is refused where it is declared.
    let named = std::iter::once(("kind", &spec.name))
        .chain(spec.inputs.iter().map(|p| ("input", &p.name)))
        .chain(spec.outputs.iter().map(|p| ("output", &p.name)))
        .chain(spec.params.iter().map(|p| ("parameter", &p.name)));
    for (what, name) in named {
        dnm_netlist::valid_name(name).map_err(|why| {
            PyValueError::new_err(format!("kind `{}`: {what} name `{name}` {why}", spec.name))
        })?;
    }
    serde_json::to_string(&spec).map_err(|e| PyValueError::new_err(e.to_string()))
}

/// The message types of the SDK and of Beetle-One, by short name, as JSON (variable-size ones
/// with a `max_bytes` of 0: a port declares its own).
#[pyfunction]
fn message_types() -> PyResult<String> {
    use dnm_module::msg as sdk;
    use dnm_module::msg::{BytesMessage, Message};
    use dnm_rover::msgs as rover;
    let mut all: BTreeMap<&str, MessageType> = BTreeMap::new();
    all.insert("Tick", sdk::Tick::message_type());
    all.insert("PairReading", sdk::PairReading::message_type());
    all.insert("Scalar", sdk::Scalar::message_type());
    all.insert("Blob", sdk::Blob::message_type(0));
    all.insert("Twist", rover::Twist::message_type());
    all.insert("WheelCommand", rover::WheelCommand::message_type());
    all.insert("MotorState", rover::MotorState::message_type());
    all.insert("WorldState", rover::WorldState::message_type());
    all.insert("EncoderTicks", rover::EncoderTicks::message_type());
    all.insert("Imu", rover::Imu::message_type());
    all.insert("BatteryState", rover::BatteryState::message_type());
    all.insert("Range", rover::Range::message_type());
    all.insert("Odometry", rover::Odometry::message_type());
    all.insert("Progress", rover::Progress::message_type());
    all.insert("WatchdogState", rover::WatchdogState::message_type());
    all.insert("Image", rover::Image::message_type(0));
    all.insert("Telemetry", rover::Telemetry::message_type(0));
    serde_json::to_string(&all).map_err(|e| PyValueError::new_err(e.to_string()))
}

#[pymodule]
fn _dnm(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<RawIo>()?;
    m.add_class::<RawSetup>()?;
    m.add_function(wrap_pyfunction!(run, m)?)?;
    m.add_function(wrap_pyfunction!(offline, m)?)?;
    m.add_function(wrap_pyfunction!(check_kind, m)?)?;
    m.add_function(wrap_pyfunction!(message_types, m)?)?;
    Ok(())
}
