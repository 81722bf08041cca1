"""Shared helpers of the benchmarks: data location, JSON output."""
from __future__ import annotations

import json
import os
import platform
from pathlib import Path
from typing import Any

import numpy as np

#: ../shared/data relative to the repository root (overridable for other checkouts)
SHARED_DATA = Path(os.environ.get(
    'EKF_VO_SHARED_DATA', Path(__file__).resolve().parents[1].parent / 'shared' / 'data'))


def shared_data(name: str) -> Path | None:
    """Path of a folder of ../shared/data, or None when absent (a user's fresh clone)."""
    path = SHARED_DATA / name
    return path if path.is_dir() else None


def machine() -> str:
    return f'{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}'


def to_jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    return obj


def write_json(path: Path, data: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(to_jsonable(data), indent=1))


def overrides_or_report(items: list[str], prog: str) -> dict[str, Any] | None:
    """`--set NAME=VALUE ...` as VoConfig overrides, or None after one line on stderr
    (`prog: why`) for a malformed or unknown one."""
    import sys
    from ekf_vo.tools.run import parse_overrides
    try:
        return parse_overrides(items)
    except ValueError as exc:
        print(f'{prog}: {exc}', file=sys.stderr)
        return None


def pyplot(out: Path):
    """matplotlib.pyplot on the file-only Agg backend; creates `out` for the plots."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    out.mkdir(parents=True, exist_ok=True)
    return plt


def section_main(argv: list[str] | None, doc: str, run, name: str, summarize=print) -> int:
    """The CLI of one benchmark section: `--quick`, `--out`; writes `<name>.json`."""
    import argparse
    parser = argparse.ArgumentParser(description=doc.split('\n')[0])
    parser.add_argument('--quick', action='store_true')
    parser.add_argument('--out', type=Path, default=Path('bench/results'))
    args = parser.parse_args(argv)
    res = run(args.quick, args.out)
    write_json(args.out / f'{name}.json', res)
    summarize(res)
    return 0
