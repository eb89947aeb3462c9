//! `ltcal._ltcal`, the extension module under the `ltcal` Python package
//! (python/ltcal/__init__.py holds the API users call, its docstrings and
//! keyword arguments; this module takes positional arguments only).
//!
//! Built without PyO3's `macros` feature, on purpose: its proc-macro crate
//! turns on features of `syn` that the root package's build does not, which
//! would give every proc macro — and so serde, polars and nearly every
//! dependency — a second build. With plain functions (`PyCFunction`) the
//! wheel reuses what `cargo test --release` compiled. Each function releases
//! the GIL while Rust works, catches panics ([`api::caught`]) and raises
//! the package's exceptions (python/ltcal/_errors.py).

mod api;

use pyo3::exceptions::PyTypeError;
use pyo3::ffi;
use pyo3::prelude::*;
use pyo3::types::{PyBytes, PyCFunction, PyDict, PyList, PyTuple};
use std::path::PathBuf;

/// Python-facing result of one native function.
type Out = PyResult<Py<PyAny>>;

static mut MODULE_DEF: ffi::PyModuleDef = ffi::PyModuleDef {
    m_base: ffi::PyModuleDef_HEAD_INIT,
    m_name: c"ltcal._ltcal".as_ptr(),
    m_doc: c"ltcal's native functions; use the `ltcal` package.".as_ptr(),
    m_size: -1,
    m_methods: std::ptr::null_mut(),
    m_slots: std::ptr::null_mut(),
    m_traverse: None,
    m_clear: None,
    m_free: None,
};

/// The module's entry point, which `import ltcal._ltcal` calls with the GIL
/// held.
///
/// # Safety
/// Called by the interpreter only, once, with the GIL held.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn PyInit__ltcal() -> *mut ffi::PyObject {
    // SAFETY: the interpreter holds the GIL while it initialises a module.
    let py = unsafe { Python::assume_attached() };
    // SAFETY: MODULE_DEF lives for the whole process, as CPython requires,
    // and only the interpreter touches it after this call.
    let made = unsafe { ffi::PyModule_Create2(&raw mut MODULE_DEF, ffi::PYTHON_ABI_VERSION) };
    // SAFETY: a new reference or null with the error set.
    let module = unsafe { Bound::from_owned_ptr_or_err(py, made) };
    match module.and_then(|m| add_functions(&m).map(|()| m)) {
        Ok(m) => m.into_ptr(),
        Err(e) => {
            e.restore(py);
            std::ptr::null_mut()
        }
    }
}

fn add_functions(m: &Bound<'_, PyAny>) -> PyResult<()> {
    let py = m.py();
    let add = |name: &'static std::ffi::CStr, f: fn(&Bound<'_, PyTuple>) -> Out| -> PyResult<()> {
        let func = PyCFunction::new_closure(
            py,
            Some(name),
            None,
            move |args: &Bound<'_, PyTuple>, _: Option<&Bound<'_, PyDict>>| f(args),
        )?;
        m.setattr(name.to_str().expect("ASCII names"), func)
    };
    add(c"run", run)?;
    add(c"table", table)?;
    add(c"diagnose", diagnose)?;
    add(c"read_campaign", read_campaign)?;
    add(c"write_campaign", write_campaign)?;
    add(c"_panic", panic_for_tests)?;
    Ok(())
}

fn arg<'py, T: FromPyObjectOwned<'py>>(args: &Bound<'py, PyTuple>, i: usize) -> PyResult<T> {
    args.get_item(i)?
        .extract::<T>()
        .map_err(|e| PyTypeError::new_err(format!("argument {i}: {}", Into::<PyErr>::into(e))))
}

fn path(args: &Bound<'_, PyTuple>, i: usize) -> PyResult<PathBuf> {
    Ok(PathBuf::from(arg::<String>(args, i)?))
}

/// The package's exception for `e` (python/ltcal/_errors.py).
fn raise(py: Python<'_>, e: api::Error) -> PyErr {
    let make = || -> PyResult<PyErr> {
        let errors = py.import("ltcal._errors")?;
        Ok(match e {
            api::Error::Input(problems) => {
                let list = PyList::empty(py);
                for p in &problems {
                    let d = PyDict::new(py);
                    d.set_item("message", &p.message)?;
                    d.set_item("file", &p.file)?;
                    d.set_item("line", p.line)?;
                    match &p.column_name {
                        Some(name) => d.set_item("column", name)?,
                        None => d.set_item("column", p.column)?,
                    }
                    d.set_item("table", &p.table)?;
                    d.set_item("row", p.row)?;
                    list.append(d)?;
                }
                PyErr::from_value(errors.getattr("InputError")?.call_method1("_of", (list,))?)
            }
            api::Error::Other(message) => {
                PyErr::from_value(errors.getattr("LtcalError")?.call1((message,))?)
            }
        })
    };
    make().unwrap_or_else(|e| e)
}

/// Runs `work` with the GIL released, a panic caught.
fn detached<T: Send>(py: Python<'_>, work: impl FnOnce() -> api::Result<T> + Send) -> PyResult<T> {
    py.detach(|| match api::caught(|| Ok(work())) {
        Ok(r) => r,
        Err(e) => Err(e),
    })
    .map_err(|e| raise(py, e))
}

fn target(args: &Bound<'_, PyTuple>) -> PyResult<api::Target> {
    Ok(api::Target {
        pipeline: path(args, 0)?,
        set: arg(args, 1)?,
        name: arg(args, 2)?,
        results: path(args, 3)?,
    })
}

/// run(pipeline, set, name, results, jobs, executor, keep_going, progress)
/// → the run report as JSON. `progress(done, total, unit)` is called every
/// 100 ms from this thread (with the GIL), `unit` "point" for a sweep and
/// "stage" otherwise; Ctrl-C stops the run (what is under way finishes and
/// is cached; a second Ctrl-C stops waiting for it) and raises
/// KeyboardInterrupt.
fn run(args: &Bound<'_, PyTuple>) -> Out {
    let py = args.py();
    let t = target(args)?;
    let jobs: Option<usize> = arg(args, 4)?;
    let executor: String = arg(args, 5)?;
    let keep_going: bool = arg(args, 6)?;
    let progress: Option<Py<PyAny>> = arg::<Option<Bound<PyAny>>>(args, 7)?.map(Bound::unbind);
    let mut stopped: Option<PyErr> = None;
    let out = detached(py, || {
        let mut poll = |done: usize, total: usize, unit: &'static str| {
            Python::attach(|py| {
                let r = py.check_signals().and_then(|()| match &progress {
                    Some(f) => f.call1(py, (done, total, unit)).map(drop),
                    None => Ok(()),
                });
                r.map_err(|e| stopped = Some(e)).is_ok()
            })
        };
        api::run(&t, jobs, &executor, keep_going, &mut poll)
    });
    if let Some(e) = stopped {
        return Err(e);
    }
    Ok(out?.into_pyobject(py)?.into_any().unbind())
}

/// table(pipeline, set, name, results, "stage.table") → (parquet bytes, stale or None)
fn table(args: &Bound<'_, PyTuple>) -> Out {
    let py = args.py();
    let t = target(args)?;
    let name: String = arg(args, 4)?;
    let (bytes, stale) = detached(py, || api::table(&t, &name))?;
    Ok((PyBytes::new(py, &bytes), stale)
        .into_pyobject(py)?
        .into_any()
        .unbind())
}

fn tables_out<'py>(py: Python<'py>, tables: &[(String, Vec<u8>)]) -> PyResult<Bound<'py, PyList>> {
    let list = PyList::empty(py);
    for (name, bytes) in tables {
        list.append((name, PyBytes::new(py, bytes)))?;
    }
    Ok(list)
}

/// diagnose(campaign, out, effects, folds, mc_draws, seed, model, hypotheses, from_tables)
/// → (verdict, [(table, parquet bytes)], [file names])
fn diagnose(args: &Bound<'_, PyTuple>) -> Out {
    let py = args.py();
    let campaign = path(args, 0)?;
    let out = path(args, 1)?;
    let o = api::DiagnoseOptions {
        effects: arg(args, 2)?,
        folds: arg(args, 3)?,
        mc_draws: arg(args, 4)?,
        seed: arg(args, 5)?,
        model: arg(args, 6)?,
        hypotheses: arg::<Option<String>>(args, 7)?.map(PathBuf::from),
    };
    let from_tables: bool = arg(args, 8)?;
    let d = detached(py, || api::diagnose(&campaign, &out, o, from_tables))?;
    Ok((d.verdict, tables_out(py, &d.tables)?, d.files)
        .into_pyobject(py)?
        .into_any()
        .unbind())
}

/// read_campaign(folder) → ([(table, parquet bytes)], meta JSON)
fn read_campaign(args: &Bound<'_, PyTuple>) -> Out {
    let py = args.py();
    let dir = path(args, 0)?;
    let (tables, meta) = detached(py, || api::read_campaign(&dir))?;
    Ok((tables_out(py, &tables)?, meta)
        .into_pyobject(py)?
        .into_any()
        .unbind())
}

/// write_campaign(folder, [(table, parquet bytes)], meta JSON, overwrite)
fn write_campaign(args: &Bound<'_, PyTuple>) -> Out {
    let py = args.py();
    let dir = path(args, 0)?;
    let mut tables = Vec::new();
    for item in args.get_item(1)?.try_iter()? {
        let item = item?;
        let name: String = item.get_item(0)?.extract()?;
        let bytes = item.get_item(1)?.cast::<PyBytes>()?.as_bytes().to_vec();
        tables.push((name, bytes));
    }
    let meta: String = arg(args, 2)?;
    let overwrite: bool = arg(args, 3)?;
    detached(py, || api::write_campaign(&dir, &tables, &meta, overwrite))?;
    Ok(py.None())
}

/// A panic on purpose, for the test that no panic crosses into Python.
fn panic_for_tests(args: &Bound<'_, PyTuple>) -> Out {
    let py = args.py();
    detached(py, || -> api::Result<()> {
        panic!("provoked by ltcal._ltcal._panic")
    })?;
    Ok(py.None())
}
