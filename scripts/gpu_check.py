"""Every CUDA test and GPU figure of the project from one call (issue 25), or its CPU dry run.

Steps, each a subprocess with its own time limit (the limits add up to under 8 minutes; a step
that would start with less than its minimum left is skipped, so the whole check stays inside
``--budget`` seconds):

========== ======================================================================================
pytest     ``pytest -m cuda`` over the test files that carry the ``cuda`` marker (JUnit XML,
           summarised as JSON)
filter     ``bench_filter.py --gpu-only``: re-entry CKF, float32, batch 1 and 10^4 (eager,
           compiled, CUDA graph); dynamax side by side if it is importable, else a row saying so
parallel   ``bench_parallel.py --device cuda``: T = 10^4 and 10^5, n = 4, parallel vs sequential
gp         ``bench_gp_filter.py --gpu-only``: GP-CKF, S = 2000, batch 10^4, the exact and the
           sparse (SVGP) predictor, compiled + CUDA graph
ray        ``bench_ray.py --components-only --device cuda``: the per-recording device cost of the
           README's scaling model (batch 10^4); empty Ray tasks only where Ray is installed
calibrate  ``bench_calibrate.py --device cuda``: likelihood-training iterations (forward +
           gradient), eager
========== ======================================================================================

Everything lands under ``--out``: each step's JSON (``<step>/...json``), its log (``<step>.log``)
and ``summary.json`` (every step: status ``ok``/``failed``/``timeout``/``skipped``, seconds, key
figure, reason, and the step's JSON embedded), and one table is printed. A failed or timed-out
step is reported and the others still run; the exit code is 1 if any step failed (or, without
``--dry-run``, if there is no CUDA device).

``--dry-run`` runs the same plumbing on the CPU at tiny sizes (seconds per step): the CUDA tests
are collected and skipped, the benchmarks run their CPU rows or ``--device cpu``. The default
test suite runs it (tests/scripts/test_gpu_check.py), so the script cannot rot between lent GPUs.

Running it on the lent GPU machine (one call)
---------------------------------------------
That machine reaches no network: nothing can be installed from a registry there. Its image holds
a CUDA build of torch (2.11 with CUDA 13 when last seen; the pinned ``torch==2.13.0`` of
``make setup`` cannot be fetched there, and its CUDA wheel is far over the 64 MiB a call may
carry), gpytorch, numpy, scipy, matplotlib, pytest and JAX. The few pure-Python wheels it lacks
(dynamax and its dependencies, about 8 MB) travel with the call. Once, here, in the repository
root (``.whl/`` is git-ignored):

    python scripts/gpu_check.py --download-wheels .whl

then one device call with ``carry=[".whl"]`` and ``timeout_s=540`` (the check itself is capped at
450 s by ``--budget``; this leaves room for the machine's start and, within the 15 minutes of
device time, for a second, shorter call):

    W=$PWD/.whl/site; python3 -m pip install -q --no-index --no-deps --no-compile --target $W .whl/*.whl; export PYTHONPATH=$W; PYTHONUNBUFFERED=1 python3 scripts/gpu_check.py --out out/gpu_check; rc=$?; cp out/gpu_check/summary.json $OUT/; tar czf $OUT/gpu_check.tgz out/gpu_check; exit $rc

(``summary.json`` holds every figure; the archive adds the logs.) On a CUDA machine with network
access, install from the pinned versions and run it through make:

    make setup PIP_TORCH_ARGS="--index-url https://download.pytorch.org/whl/cu126"
    make gpu-check

On a CPU:

    python scripts/gpu_check.py --dry-run --out out/gpu_check
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import signal
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = ROOT / "scripts"
sys.path.insert(0, str(SCRIPTS))
from _common import table, write_json  # noqa: E402

#: overall cap on the steps' time limits (seconds): under 8 minutes
BUDGET_S = 450.0
#: a step is not started with less than this left of the budget (seconds)
MIN_START_S = 20.0
#: pure-Python wheels the lent GPU machine lacks (``--download-wheels``); its image has the rest
WHEELS = [
    "dynamax==1.0.3",
    "tensorflow-probability==0.25.0",
    "fastprogress==1.0.3",
    "decorator==5.3.1",
    "gast==0.7.0",
    "dm-tree==0.1.10",
]


@dataclass
class Step:
    """One subprocess of the check: its command (full and dry-run), where it writes its JSON,
    its time limit, and how to read a key figure from that JSON."""

    name: str
    what: str
    full: list[str]
    dry: list[str] | None  # None: skipped in the dry run (CUDA only)
    json_name: str
    limit_s: float
    key: Callable[[dict[str, Any]], str]
    notes: list[str] = field(default_factory=list)  # said in the reason column (full run)
    dry_note: str = ""  # what the dry run leaves out


@dataclass
class Outcome:
    name: str
    what: str
    status: str  # ok | failed | timeout | skipped
    seconds: float = 0.0
    key: str = ""
    reason: str = ""
    json: str | None = None
    result: Any = None
    returncode: int | None = None
    log: str | None = None


# --------------------------------------------------------------------------- key figures
def _fmt(x: Any) -> str:
    return f"{x:.3g}" if isinstance(x, int | float) else str(x)


def _key_pytest(res: dict[str, Any]) -> str:
    return f"{res['passed']} passed, {res['failed']} failed, {res['skipped']} skipped"


def _key_filter(res: dict[str, Any]) -> str:
    rows = [r for r in res["rows"] if not r["name"].startswith(("dynamax", "filterpy"))]
    if not rows:
        return "no torchfilt rows"
    big = max(r["batch"] for r in rows)
    best = max((r for r in rows if r["batch"] == big), key=lambda r: r["sequence_steps_per_s"])
    out = f"batch {big} {best['device']}: {_fmt(best['sequence_steps_per_s'])} seq-steps/s"
    if "ratio_to_dynamax" in best:
        out += f", {_fmt(best['ratio_to_dynamax'])}x dynamax"
    return f"{out}; dynamax: {res.get('dynamax')}"


def _key_parallel(res: dict[str, Any]) -> str:
    r = max(res["rows"], key=lambda r: (r["T"], -r["n"]))
    return f"T {r['T']} n {r['n']} {r['device']}: parallel {_fmt(r['speedup'])}x sequential"


def _key_gp(res: dict[str, Any]) -> str:
    gpu = res["gpu"]
    if not isinstance(gpu, dict) or "rows" not in gpu.get("filter", {}):
        return str(gpu)[:80]
    flt = gpu["filter"]
    parts = [f"{r['predictor']}: {_fmt(r['sequence_steps_per_s'])}" for r in flt["rows"]]
    return f"S {flt['S']} batch {flt['batch']} seq-steps/s: " + "; ".join(parts)


def _key_ray(res: dict[str, Any]) -> str:
    return (
        f"{res.get('device', 'cpu')} batch {res['batch']}: CKF "
        f"{_fmt(res['ckf_only_s_per_recording'] * 1e6)} us/recording, local path "
        f"{_fmt(res['local_path_s_per_recording'] * 1e3)} ms/recording"
    )


def _key_calibrate(res: dict[str, Any]) -> str:
    rows = [r for r in res["rows"] if "error" not in r]
    return (
        "; ".join(
            f"{r['device']} {'compiled' if r['compiled'] else 'eager'}: "
            f"{_fmt(r['seconds_per_iteration'])} s/iteration"
            for r in rows
        )
        or "no rows"
    )


# --------------------------------------------------------------------------- the steps
def cuda_test_files() -> list[str]:
    """The test files that carry the ``cuda`` marker (others need not import on the GPU
    machine, whose image may lack their optional dependencies)."""
    return sorted(
        str(p.relative_to(ROOT))
        for p in (ROOT / "tests").rglob("test_*.py")
        if "mark.cuda" in p.read_text()
    )


def steps(out: Path, *, ray: bool) -> list[Step]:
    """The steps in order of importance (the budget may cut the last ones)."""
    py = [sys.executable]

    def script(name: str, flags: str) -> list[str]:  # each step writes under out/<step name>
        folder = {"bench_gp_filter": "gp", "bench_parallel": "parallel", "bench_ray": "ray"}
        step = folder.get(name, name.removeprefix("bench_"))
        return [*py, str(SCRIPTS / f"{name}.py"), "--out", str(out / step), *flags.split()]

    pytest_ = [*py, "-m", "pytest", "-m", "cuda", "-q", "-p", "no:cacheprovider", "-rfEs"]
    pytest_ += ["--junitxml", str(out / "pytest" / "junit.xml")]
    ray_full = "--components-only --device cuda --recordings 10000 --batch-sizes 10000 --repeats 1"
    ray_dry = "--components-only --device cpu --recordings 4 --steps 12 --batch-sizes 4 --repeats 1"
    ray_dry += " --no-empty-tasks"
    ray_notes = []
    dynamax = importlib.util.find_spec("dynamax") is not None
    filter_notes = [] if dynamax else ["dynamax not importable: no side-by-side row"]
    if not ray:
        ray_full += " --no-empty-tasks"
        ray_notes.append("empty Ray tasks not timed: ray is not installed")
    return [
        Step(
            "pytest",
            "pytest -m cuda",
            [*pytest_, *cuda_test_files()],
            [*pytest_, "tests/test_cuda.py"],
            "pytest/pytest.json",
            150,
            _key_pytest,
            dry_note="dry run: tests/test_cuda.py collected, skipped without CUDA",
        ),
        Step(
            "filter",
            "bench_filter GPU rows (re-entry, batch 1, 10^4)",
            script("bench_filter", "--gpu-only --gpu-batches 1 10000 --repeats 3"),
            script(
                "bench_filter", "--batch 2 --linear-batch 2 --repeats 1 --no-compile --no-dynamax"
            ),
            "filter/results.json",
            100,
            _key_filter,
            filter_notes,
            dry_note="dry run: CPU rows at batch 2 (the GPU rows need CUDA)",
        ),
        Step(
            "parallel",
            "bench_parallel (T = 10^4, 10^5, n = 4)",
            script("bench_parallel", "--device cuda --steps 10000 100000 --dims 4 --repeats 1"),
            script("bench_parallel", "--device cpu --steps 32 --dims 2 --repeats 1"),
            "parallel/bench_parallel.json",
            90,
            _key_parallel,
            dry_note="dry run: CPU, T = 32",
        ),
        Step(
            "gp",
            "bench_gp_filter GPU (S = 2000, batch 10^4, exact + SVGP)",
            script(
                "bench_gp_filter",
                "--gpu-only --gpu-quick --no-svgp --gpu-forms exact sparse --gpu-S 2000 "
                "--gpu-batch 10000 --device cuda",
            ),
            script(
                "bench_gp_filter",
                "--gpu-only --no-svgp --gpu-forms exact --gpu-S 24 --gpu-batch 3 --repeats 1 "
                "--device cpu --threads 1 --force-gpu-section",
            ),
            "gp/results.json",
            120,
            _key_gp,
            dry_note="dry run: CPU, S = 24, batch 3, exact only, eager",
        ),
        Step(
            "ray",
            "bench_ray --components-only (device cost per recording)",
            script("bench_ray", ray_full),
            script("bench_ray", ray_dry),
            "ray/bench_ray_components.json",
            90,
            _key_ray,
            ray_notes,
            dry_note="dry run: CPU, 4 recordings, no Ray tasks",
        ),
        Step(
            "calibrate",
            "bench_calibrate (likelihood-training iterations)",
            script("bench_calibrate", "--device cuda --repeats 2 --no-compile"),
            script(
                "bench_calibrate",
                "--device cpu --samples 30 --windows 2 --steps 12 --repeats 1 --no-compile",
            ),
            "calibrate/bench_calibrate.json",
            75,
            _key_calibrate,
            dry_note="dry run: CPU, S = 30, 2 windows",
        ),
    ]


# --------------------------------------------------------------------------- running
def run_limited(cmd: list[str], log: Path, limit_s: float) -> tuple[int | None, float]:
    """Run ``cmd`` in its own process group with its output in ``log``; kill the group at
    ``limit_s``. Returns the exit code (``None`` on timeout) and the wall time."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH")) if p)
    log.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with log.open("w") as fh:
        fh.write("$ " + " ".join(cmd) + "\n")
        fh.flush()
        proc = subprocess.Popen(
            cmd, cwd=ROOT, env=env, stdout=fh, stderr=subprocess.STDOUT, start_new_session=True
        )
        try:
            rc: int | None = proc.wait(timeout=limit_s)
        except subprocess.TimeoutExpired:
            rc = None
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    return rc, time.perf_counter() - t0


def junit_summary(xml: Path) -> dict[str, Any]:
    """Counts and the failing tests of a pytest JUnit XML file."""
    root = ET.parse(xml).getroot()
    cases = list(root.iter("testcase"))
    res: dict[str, Any] = {"passed": 0, "failed": 0, "skipped": 0, "tests": []}
    for c in cases:
        name = f"{c.get('classname')}::{c.get('name')}"
        outcome, msg = "passed", ""
        for tag, kind in (("failure", "failed"), ("error", "failed"), ("skipped", "skipped")):
            el = c.find(tag)
            if el is not None:
                lines = (el.get("message") or "").splitlines()
                outcome, msg = kind, lines[0][:300] if lines else ""
                break
        res[outcome] += 1
        res["tests"].append({"test": name, "outcome": outcome, "message": msg})
    return res


def row_errors(payload: Any) -> list[str]:
    """The errors a benchmark recorded in its JSON (``errors`` lists, ``error`` strings)."""
    found: list[str] = []
    if isinstance(payload, dict):
        for k, v in payload.items():
            if k == "errors" and isinstance(v, list):
                found += [str(e) for e in v]
            elif k == "error" and isinstance(v, str):
                found.append(v)
            else:
                found += row_errors(v)
    elif isinstance(payload, list):
        for v in payload:
            found += row_errors(v)
    return found


def run_step(step: Step, out: Path, cmd: list[str], limit_s: float, dry_run: bool) -> Outcome:
    """Run one step and read its JSON; any failure is an outcome, never an exception."""
    log = out / f"{step.name}.log"
    res = Outcome(step.name, step.what, "ok", log=str(log.relative_to(out)))
    print(f"[{step.name}] {step.what} (limit {limit_s:.0f} s) ...", flush=True)
    rc, res.seconds = run_limited(cmd, log, limit_s)
    res.returncode = rc
    path = out / step.json_name
    if step.name == "pytest" and (out / "pytest" / "junit.xml").exists():
        write_json(path, junit_summary(out / "pytest" / "junit.xml"))
    if path.exists():
        res.json = step.json_name
        try:
            res.result = json.loads(path.read_text())
            res.key = step.key(res.result)
        except Exception as e:  # a JSON the key reader cannot read is reported, not fatal
            res.key = f"(unreadable: {type(e).__name__}: {e})"[:120]
    if rc is None:
        res.status, res.reason = "timeout", f"killed after {limit_s:.0f} s"
    elif rc != 0:
        res.status, res.reason = "failed", f"exit code {rc}; last lines in {res.log}"
        if step.name == "pytest" and isinstance(res.result, dict):
            bad = [t for t in res.result["tests"] if t["outcome"] == "failed"]
            if bad:
                res.reason = f"{len(bad)} failed, first: {bad[0]['test']}: {bad[0]['message']}"
    elif res.json is None:
        res.status, res.reason = "failed", f"wrote no {step.json_name}"
    elif errors := row_errors(res.result):
        res.status, res.reason = "failed", f"{len(errors)} row error(s), first: {errors[0]}"
    notes = [step.dry_note] if dry_run and step.dry_note else step.notes
    if notes and not res.reason:
        res.reason = "; ".join(notes)
    print(f"[{step.name}] {res.status} in {res.seconds:.1f} s {res.key}", flush=True)
    return res


def run_all(out: Path, *, dry_run: bool, budget_s: float, cuda: bool) -> list[Outcome]:
    """Every step in turn, inside ``budget_s`` seconds in all."""
    ray = importlib.util.find_spec("ray") is not None
    t0 = time.perf_counter()
    outcomes = []
    for step in steps(out, ray=ray):
        cmd = step.dry if dry_run else step.full
        left = budget_s - (time.perf_counter() - t0)
        if cmd is None:
            outcomes.append(Outcome(step.name, step.what, "skipped", reason="CUDA only"))
        elif not dry_run and not cuda:
            reason = "no CUDA device (run with --dry-run on a CPU)"
            outcomes.append(Outcome(step.name, step.what, "skipped", reason=reason))
        elif left < MIN_START_S:
            reason = f"budget: {max(left, 0):.0f} s of {budget_s:.0f} s left"
            outcomes.append(Outcome(step.name, step.what, "skipped", reason=reason))
        else:
            outcomes.append(run_step(step, out, cmd, min(step.limit_s, left), dry_run))
    return outcomes


def environment_summary() -> dict[str, Any]:
    import torch

    info: dict[str, Any] = {
        "python": sys.version.split()[0],
        "torch": torch.__version__,
        "torch_cuda": torch.version.cuda,
        "device": torch.cuda.get_device_name() if torch.cuda.is_available() else None,
    }
    for name in ("jax", "dynamax", "ray", "gpytorch"):
        info[name] = "installed" if importlib.util.find_spec(name) else "not installed"
    return info


def download_wheels(folder: Path) -> int:
    """``pip download`` the wheels of :data:`WHEELS` for the GPU machine's Python (3.12,
    x86-64), without their dependencies (the machine's image has the others)."""
    cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:"]
    cmd += ["--python-version", "3.12", "--implementation", "cp", "-d", str(folder)]
    for plat in ("manylinux_2_28", "manylinux_2_27", "manylinux_2_24", "manylinux_2_17"):
        cmd += ["--platform", f"{plat}_x86_64"]
    cmd += ["--platform", "any"]
    return subprocess.call([*cmd, *WHEELS])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--out", type=Path, default=Path("out/gpu_check"))
    ap.add_argument("--dry-run", action="store_true", help="CPU, tiny sizes, CUDA steps skipped")
    ap.add_argument("--budget", type=float, default=BUDGET_S, help="seconds for all the steps")
    ap.add_argument(
        "--download-wheels", type=Path, default=None, metavar="DIR",
        help="download the wheels the GPU machine lacks into DIR and exit",
    )  # fmt: skip
    args = ap.parse_args(argv)
    if args.download_wheels is not None:
        return download_wheels(args.download_wheels)
    import torch

    cuda = torch.cuda.is_available()
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    outcomes = run_all(out, dry_run=args.dry_run, budget_s=args.budget, cuda=cuda)
    failed = [o for o in outcomes if o.status in ("failed", "timeout")]
    summary = {
        "check": "gpu_check",
        "dry_run": args.dry_run,
        "cuda": cuda,
        "environment": environment_summary(),
        "budget_s": args.budget,
        "seconds": time.perf_counter() - t0,
        "failed": len(failed),
        "steps": [o.__dict__ for o in outcomes],
    }
    write_json(out / "summary.json", summary)
    print()
    print(
        table(
            ["step", "status", "seconds", "key figure", "reason"],
            [[o.name, o.status, o.seconds, o.key, o.reason] for o in outcomes],
            fmt="{:.1f}",
        )
    )
    print(f"wrote {out / 'summary.json'}")
    if not args.dry_run and not cuda:
        print("no CUDA device: nothing was checked (use --dry-run on a CPU)")
        return 1
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
