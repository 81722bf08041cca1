"""Run a benchmark the way a developer does: `python -m bench.<name>` from the repository
root (bench/ is not installed, and the tests do not import it)."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]


def run_benchmark(name: str, *args: str, timeout: float = 1800.0
                  ) -> subprocess.CompletedProcess:
    """`python -m bench.<name> ARGS` in the repository root; output captured."""
    return subprocess.run([sys.executable, '-m', f'bench.{name}', *args], cwd=REPO,
                          capture_output=True, text=True, timeout=timeout)


def benchmark_json(name: str, json_path: Path, *args: str) -> dict[str, Any]:
    """Run a benchmark that writes its result to `--json JSON_PATH`; returns the result."""
    proc = run_benchmark(name, *args, '--json', str(json_path))
    assert proc.returncode == 0, f'bench.{name} failed:\n{proc.stdout}\n{proc.stderr}'
    return json.loads(Path(json_path).read_text())
