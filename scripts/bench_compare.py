"""Run one benchmark script on two checkouts side by side, alternating, and compare row by row.

A redesign must not slow anything down, and these machines are noisy: a figure measured on one
checkout in the morning and on another in the afternoon says little. This runs the same
benchmark script of each checkout in turn (before, after, before, after, ...) in one invocation,
each run in its own process with that checkout first on ``PYTHONPATH``, reads the JSON each run
writes, and reports for every row and timing field the median over the rounds and the ratio
after / before (< 1: the new checkout is faster).

    python scripts/bench_compare.py --before ../base --rounds 3 bench_linear.py -- --repeats 5

Rows are matched by their non-float fields (names, batch sizes, devices); timing fields are the
float fields whose names end in ``_us``, ``_s`` or start with ``seconds_per`` / ``us_per``
(correctness fields such as ``max_diff`` are reported as the largest value seen). Peers that a
benchmark runs in its own process (dynamax, filterpy) run in both checkouts' runs alike; their
rows compare a peer with itself, which shows how much the machine drifted.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import environment, table, write_json


def _is_timing(name: str) -> bool:
    if name.endswith("_per_s"):  # a rate (sequence_steps_per_s), not a time
        return False
    return name.endswith(("_us", "_s")) or name.startswith(("seconds_per", "us_per"))


def _key(row: dict[str, Any]) -> tuple[tuple[str, Any], ...]:
    return tuple(
        (k, v)
        for k, v in sorted(row.items())
        if not isinstance(v, float) and not isinstance(v, dict)
    )


def _rows(out: Path) -> list[dict[str, Any]]:
    """The ``rows`` of the one JSON file a benchmark run wrote into ``out`` (searched below it)."""
    found = [p for p in sorted(out.rglob("*.json")) if "rows" in json.loads(p.read_text())]
    if not found:
        raise SystemExit(f"bench_compare: no JSON with 'rows' under {out}")
    rows: list[dict[str, Any]] = []
    for p in found:
        rows += [dict(r, _file=p.name) for r in json.loads(p.read_text())["rows"]]
    return rows


def run_once(checkout: Path, script: str, args: list[str], out: Path) -> list[dict[str, Any]]:
    """One run of ``checkout/scripts/<script>`` with that checkout's package; its rows."""
    env = dict(os.environ, PYTHONPATH=str(checkout))
    cmd = [sys.executable, str(checkout / "scripts" / script), *args, "--out", str(out)]
    subprocess.run(cmd, env=env, check=True, cwd=checkout, stdout=subprocess.DEVNULL)
    return _rows(out)


def _commit(checkout: Path) -> str:
    """The checkout's commit (short hash, ``+dirty`` with uncommitted changes), not its path."""
    git = ["git", "-C", str(checkout)]
    head = subprocess.run([*git, "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    dirty = subprocess.run([*git, "status", "--porcelain"], capture_output=True, text=True)
    return head.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")


def compare(
    runs: dict[str, list[list[dict[str, Any]]]],
) -> list[dict[str, Any]]:
    """Per row and timing field: the median of each side and after / before."""
    merged: dict[tuple[Any, ...], dict[str, dict[str, list[float]]]] = {}
    for side, side_runs in runs.items():
        for rows in side_runs:
            for row in rows:
                fields = merged.setdefault(_key(row), {})
                for name, value in row.items():
                    if isinstance(value, float) and _is_timing(name):
                        fields.setdefault(name, {"before": [], "after": []})[side].append(value)
    out = []
    for key, fields in merged.items():
        label = " ".join(f"{k}={v}" for k, v in key if k != "_file" and v is not None)
        for name, sides in fields.items():
            if not sides["before"] or not sides["after"]:
                continue
            b, a = statistics.median(sides["before"]), statistics.median(sides["after"])
            out.append(
                {
                    "row": label,
                    "field": name,
                    "before": b,
                    "after": a,
                    "after_over_before": a / b if b > 0 else None,
                }
            )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--before", type=Path, required=True, help="the checkout to compare against")
    ap.add_argument("--after", type=Path, default=Path(__file__).resolve().parents[1])
    ap.add_argument("--rounds", type=int, default=3, help="runs of each checkout, alternating")
    ap.add_argument("--out", type=Path, default=Path("out/bench_compare"))
    ap.add_argument("script", help="benchmark script name under scripts/, e.g. bench_linear.py")
    ap.add_argument("args", nargs=argparse.REMAINDER, help="arguments after -- go to the script")
    a = ap.parse_args()
    args = a.args[1:] if a.args[:1] == ["--"] else a.args
    checkouts = {"before": a.before.resolve(), "after": a.after.resolve()}
    runs: dict[str, list[list[dict[str, Any]]]] = {"before": [], "after": []}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(a.rounds):
            for side, checkout in checkouts.items():
                out = Path(tmp) / f"{side}-{r}"
                print(f"round {r + 1}/{a.rounds}: {side} ({_commit(checkout)})", flush=True)
                runs[side].append(run_once(checkout, a.script, args, out))
    result = compare(runs)
    rows = [[r["row"], r["field"], r["before"], r["after"], r["after_over_before"]] for r in result]
    print(table(["row", "field", "before", "after", "after/before"], rows))
    write_json(
        a.out / f"{Path(a.script).stem}_compare.json",
        {
            "script": a.script,
            "args": args,
            "rounds": a.rounds,
            "checkouts": {k: _commit(v) for k, v in checkouts.items()},
            "rows": result,
            "environment": environment(),
        },
    )


if __name__ == "__main__":
    main()
