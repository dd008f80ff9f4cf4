"""The GPU check's dry run (scripts/gpu_check.py --dry-run) runs on the CPU: every step is listed,
a skipped one says why, and each step that ran wrote JSON that parses."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from script_support import load_script

ROOT = Path(__file__).resolve().parents[2]
STEPS = ["pytest", "filter", "parallel", "gp", "ray", "calibrate"]


def test_gpu_check_dry_run(tmp_path):
    out = tmp_path / "gpu_check"
    proc = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "gpu_check.py"), "--dry-run", "--out", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        # the budget only guards the GPU run; here the dry run must not depend on timing
        timeout=900,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["dry_run"] is True
    steps = {s["name"]: s for s in summary["steps"]}
    assert list(steps) == STEPS
    for step in steps.values():
        assert step["status"] in ("ok", "skipped"), step
        if step["status"] == "skipped":
            assert step["reason"]
            continue
        assert step["json"] is not None, step
        payload = json.loads((out / step["json"]).read_text())
        assert payload == step["result"]
        assert step["key"] and not step["key"].startswith("(unreadable")
    assert steps["pytest"]["result"]["failed"] == 0
    assert "step" in proc.stdout and "summary.json" in proc.stdout


def test_gpu_check_lists_the_cuda_test_files():
    files = load_script("gpu_check").cuda_test_files()
    assert "tests/test_cuda.py" in files
    assert "tests/scripts/test_gpu_check.py" not in files
