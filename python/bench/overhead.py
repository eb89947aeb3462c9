"""The Python package's overhead over the command line (README, "From Python").

    python python/bench/overhead.py [RUNS]     # from the repository's root

1. A cached run of pipelines/synthetic-validation.toml: `ltcal run -q` (the
   built binary target/release/ltcal, a process each time) against
   `ltcal.run(...)` in a warm interpreter, and against a fresh interpreter
   doing `import ltcal; ltcal.run(...)`.
2. Loading a 100 000-row table (python/bench/table-100k.toml's
   `measure.readings`) into pandas with `Run.table`.

Medians over RUNS (default 7) after one warm-up; the results go to a
temporary folder, apart from the committed results/.
"""

import statistics
import subprocess
import sys
import tempfile
import time

import ltcal

RUNS = int(sys.argv[1]) if len(sys.argv) > 1 else 7
PIPELINE = "pipelines/synthetic-validation.toml"
results = tempfile.mkdtemp(prefix="ltcal-bench-")


def median_ms(f):
    f()  # warm-up: fills the cache, pages the files in
    times = []
    for _ in range(RUNS):
        t = time.perf_counter()
        f()
        times.append(time.perf_counter() - t)
    return statistics.median(times) * 1000


def cli():
    subprocess.run(
        ["target/release/ltcal", "run", PIPELINE, "-q", "--results", results],
        check=True,
        capture_output=True,
    )


def fresh_python():
    code = f"import ltcal; ltcal.run({PIPELINE!r}, results={results!r})"
    subprocess.run([sys.executable, "-c", code], check=True, capture_output=True)


def import_only():
    subprocess.run([sys.executable, "-c", "import ltcal"], check=True, capture_output=True)


cli_ms = median_ms(cli)
py_ms = median_ms(lambda: ltcal.run(PIPELINE, results=results))
fresh_ms = median_ms(fresh_python)
import_ms = median_ms(import_only)
print(f"cached run of {PIPELINE}, median of {RUNS}:")
print(f"  ltcal run (CLI process)           {cli_ms:7.1f} ms")
print(f"  ltcal.run (warm interpreter)      {py_ms:7.1f} ms  ({py_ms - cli_ms:+.1f} ms)")
print(f"  python -c 'import ltcal; run'     {fresh_ms:7.1f} ms  ({fresh_ms - cli_ms:+.1f} ms)")
print(f"  of which python -c 'import ltcal'  {import_ms:7.1f} ms  (the interpreter's start, the extension's load)")

big = ltcal.run("python/bench/table-100k.toml", results=results)
rows = len(big.table("measure.readings"))
load_ms = median_ms(lambda: big.table("measure.readings"))
print(f"Run.table of a {rows}-row table into pandas, median of {RUNS}: {load_ms:.1f} ms")
