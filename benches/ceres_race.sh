#!/usr/bin/env bash
# The race against the Ceres peer (issue 34): hall campaigns of 2 400, 4 800 and
# 24 000 readings made by ltcal's own simulator (benches/data/race-halls.toml),
# then, interleaved for ROUNDS rounds, the peer's whole process and `ltcal run` of
# an import + calibrate pipeline (benches/data/race-calibrate.toml, the peer's 7
# parameters free) on each, every ltcal run into a fresh results folder (no cache).
# Prints per size the medians — the peer's own solve time (its stdout) and its
# whole process, ltcal's `calibrate` stage (run.json) and its whole process — the
# ratios ltcal / Ceres, and χ² of both with their relative difference (≤ 1e-7);
# then the ratios paired round by round (each ltcal run against the peer's run
# of the same round), their median and range.
#
# usage (from the repository root, after `cargo build --release`):
#     benches/ceres_race.sh [ROUNDS (default 7)] [WORK (default /tmp/ltcal-ceres-race)]
# The peer is built into WORK from ../shared/peers (override: CERES_PEER_DIR, or
# CERES_PEER=path/to/binary); without Debian's libceres-dev the race is skipped.
set -eu
repo=$(cd "$(dirname "$0")/.." && pwd)
rounds=${1:-7}
work=${2:-/tmp/ltcal-ceres-race}
ltcal=${LTCAL:-$repo/target/release/ltcal}
peers=${CERES_PEER_DIR:-$repo/../shared/peers}
peer=${CERES_PEER:-$work/calibrate_bundle_ceres}
mkdir -p "$work"

[ -x "$ltcal" ] || { echo "ceres_race: no $ltcal (run cargo build --release first)" >&2; exit 2; }
if [ ! -x "$peer" ]; then
  if [ ! -f /usr/include/ceres/ceres.h ]; then
    echo "ceres_race: skipped — Ceres is not installed (apt-get install -y libceres-dev)" >&2
    exit 0
  fi
  [ -f "$peers/build_ceres_peer.sh" ] || { echo "ceres_race: no peer at $peers (set CERES_PEER_DIR)" >&2; exit 2; }
  bash "$peers/build_ceres_peer.sh" "$peer" >/dev/null
fi

# The campaigns (cached by ltcal after the first time).
(cd "$work" && "$ltcal" run "$repo/benches/data/race-halls.toml" --results "$work/results" -q)

python3 - "$ltcal" "$peer" "$repo/benches/data/race-calibrate.toml" "$work" "$rounds" <<'PY'
import json, re, shutil, statistics, subprocess, sys, time
ltcal, peer, pipeline, work, rounds = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4], int(sys.argv[5])
sizes = ["hall-2400", "hall-4800", "hall-24000"]
t = {s: {k: [] for k in ("ceres_solve", "ceres_proc", "ltcal_stage", "ltcal_proc")} for s in sizes}
chi2 = {}

def ceres(s):
    t0 = time.perf_counter()
    p = subprocess.run([peer, f"{work}/{s}/campaign"], capture_output=True, text=True, check=True)
    t[s]["ceres_proc"].append(time.perf_counter() - t0)
    t[s]["ceres_solve"].append(float(re.search(r": ([0-9.]+) s,", p.stdout).group(1)))
    chi2.setdefault(s, {})["ceres"] = float(re.search(r" chi2 ([0-9.eE+-]+) ", p.stderr).group(1))

def ours(s):
    out = f"{work}/runs/{s}"
    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    p = subprocess.run([ltcal, "run", pipeline, "--results", out, "-q"], cwd=f"{work}/{s}",
                       capture_output=True, text=True)
    if p.returncode != 0:
        sys.exit(f"ceres_race: ltcal run failed on {s}:\n{p.stderr}")
    t[s]["ltcal_proc"].append(time.perf_counter() - t0)
    run = json.load(open(f"{out}/race-calibrate/run.json"))
    t[s]["ltcal_stage"].append(next(x["seconds"] for x in run["stages"] if x["stage"] == "calibration"))
    fit = subprocess.run([ltcal, "show", pipeline, "calibration.fit", "--results", out, "--format", "json"],
                         cwd=f"{work}/{s}", capture_output=True, text=True, check=True).stdout
    chi2.setdefault(s, {})["ltcal"] = json.loads(fit)[0]["chi2"]

for r in range(rounds):
    for s in sizes:
        # alternate who goes first, so neither always runs on a warm cache
        for f in ((ceres, ours) if r % 2 == 0 else (ours, ceres)):
            f(s)

med = lambda xs: statistics.median(xs)
print(f"{rounds} interleaved rounds, medians (s); ratios ltcal / Ceres")
print("| campaign | readings | Ceres solve | Ceres process | ltcal `calibrate` stage | ltcal process | χ² Ceres | χ² ltcal | rel. diff |")
print("|---|---|---|---|---|---|---|---|---|")
worst = 0.0
for s in sizes:
    m = {k: med(v) for k, v in t[s].items()}
    c, l = chi2[s]["ceres"], chi2[s]["ltcal"]
    rel = abs(c - l) / abs(c)
    worst = max(worst, rel)
    print(f"| {s} | {s.split('-')[1]} | {m['ceres_solve']:.3f} | {m['ceres_proc']:.3f} | "
          f"{m['ltcal_stage']:.3f} ({m['ltcal_stage'] / m['ceres_solve']:.2f}×) | "
          f"{m['ltcal_proc']:.3f} ({m['ltcal_proc'] / m['ceres_proc']:.2f}×) | {c:.10f} | {l:.10f} | {rel:.1e} |")
# The same ratios taken round by round — each of ltcal's runs against the
# peer's run of the same round, moments apart — then their median and range:
# a VM's load drifting over the minutes moves both sides of a pair alike,
# where it moves the two medians above apart.
print()
print("Paired within each round: median (min–max) of ltcal / Ceres")
print("| campaign | stage / solve | process / process |")
print("|---|---|---|")
for s in sizes:
    def paired(a, b):
        q = sorted(x / y for x, y in zip(t[s][a], t[s][b]))
        return f"{med(q):.2f}× ({q[0]:.2f}–{q[-1]:.2f})"
    print(f"| {s} | {paired('ltcal_stage', 'ceres_solve')} | {paired('ltcal_proc', 'ceres_proc')} |")
if worst > 1e-7:
    print(f"ceres_race: χ² differs by {worst:.1e} relative (> 1e-7)", file=sys.stderr)
    sys.exit(1)
PY
