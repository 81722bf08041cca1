"""The house's floors: nodes and CLI on top, then the message bridge and file I/O, then
the core, then the config. No import runs back up a floor, nothing in the product imports
the benchmarks, and the built wheel carries no benchmark module."""
import ast
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / 'ekf_vo'

#: floor of each room (top-level subpackage or module of ekf_vo); higher imports lower
FLOORS = {'cli': 0, 'config': 0, 'core': 1, 'bridge': 2, 'io': 2, 'ros': 3, 'tools': 4}


def _room(module: str) -> str:
    """'ekf_vo.core.ekf' -> 'core'."""
    parts = module.split('.')
    return parts[1] if len(parts) > 1 else ''


def _imports(path: Path) -> list[str]:
    """Absolute names of every module `path` imports (relative imports resolved)."""
    module = '.'.join(path.relative_to(REPO).with_suffix('').parts)
    package = module if path.name == '__init__.py' else module.rpartition('.')[0]
    package = package.removesuffix('.__init__')
    names = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split('.')[:len(package.split('.')) - node.level + 1]
                target = '.'.join(base + ([node.module] if node.module else []))
                if node.module is None:
                    names += [f'{target}.{a.name}' for a in node.names]
                else:
                    names.append(target)
            else:
                names.append(node.module)
    return names


def _product_files() -> list[Path]:
    return sorted(PACKAGE.rglob('*.py'))


def test_every_room_has_a_floor():
    rooms = {_room('.'.join(p.relative_to(REPO).with_suffix('').parts))
             for p in _product_files()} - {'__init__'}
    assert rooms <= set(FLOORS), f'rooms without a floor: {rooms - set(FLOORS)}'


def test_no_import_runs_back_up_a_floor():
    upward = []
    for path in _product_files():
        own = _room('.'.join(path.relative_to(REPO).with_suffix('').parts))
        if own not in FLOORS:
            continue
        for name in _imports(path):
            if name.startswith('ekf_vo.') and _room(name) in FLOORS and \
                    FLOORS[_room(name)] > FLOORS[own]:
                upward.append(f'{path.relative_to(REPO)} imports {name}')
    assert not upward, '\n'.join(upward)


def test_the_product_never_imports_the_benchmarks_or_the_tests():
    bad = [f'{p.relative_to(REPO)}: {n}' for p in _product_files() for n in _imports(p)
           if n.split('.')[0] in ('bench', 'test')]
    assert not bad, bad


def test_the_bridge_and_io_do_not_import_rclpy():
    bad = [f'{p.relative_to(REPO)}: {n}' for room in ('bridge', 'io', 'core')
           for p in (PACKAGE / room).rglob('*.py') for n in _imports(p)
           if n.split('.')[0] == 'rclpy']
    assert not bad, bad


@pytest.mark.slow
def test_the_wheel_carries_no_benchmark_module(tmp_path):
    proc = subprocess.run([sys.executable, '-m', 'pip', 'wheel', '--no-deps',
                           '--no-build-isolation', '-q', '-w', str(tmp_path), str(REPO)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    wheel, = tmp_path.glob('ekf_vo-*.whl')
    names = zipfile.ZipFile(wheel).namelist()
    assert any(n.startswith('ekf_vo/core/') for n in names)
    # python packages of the wheel (data_files such as the launch file live in .data/)
    tops = {n.split('/')[0] for n in names if n.endswith('.py') and '.data/' not in n}
    assert tops == {'ekf_vo'}, f'the wheel installs more than ekf_vo: {tops}'
    assert not [n for n in names if '/bench/' in n or n.startswith('bench/')]
