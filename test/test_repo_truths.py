"""What the repository tells a new user is true: no reference leaves the repository, the
make targets the README names exist, quick benchmarks do not overwrite committed results,
and the README's account of run_all matches its sections."""
import re
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
USER_FACING = ['README.md', 'ekf_vo', 'docs', 'config', 'launch', 'rviz', 'requirements.txt',
               'requirements-test.txt', 'requirements-robot.txt', 'package.xml', 'setup.py']


def _files():
    for name in USER_FACING:
        path = REPO / name
        yield from (sorted(p for p in path.rglob('*') if p.is_file() and '__pycache__'
                           not in p.parts) if path.is_dir() else [path])


def test_nothing_user_facing_points_outside_the_repository():
    bad = [f'{p.relative_to(REPO)}:{k}' for p in _files()
           for k, line in enumerate(p.read_text(errors='replace').splitlines(), 1)
           if '../shared' in line or 'METHOD.md' in line or 'ROS_NOTES' in line]
    assert not bad, bad


def test_every_make_target_has_a_rule():
    make = (REPO / 'Makefile').read_text()
    phony = re.search(r'^\.PHONY:(.*)$', make, re.M).group(1).split()
    for target in phony:
        # -B: as if everything were out of date, so an up-to-date venv still shows its
        # recipe; a target without one says 'Nothing to be done' even then
        r = subprocess.run(['make', '-n', '-B', target], cwd=REPO, capture_output=True,
                           text=True)
        assert r.returncode == 0 and 'Nothing to be done' not in r.stdout + r.stderr, \
            f'make {target}: {r.stdout}{r.stderr}'
    readme = (REPO / 'README.md').read_text()
    for target in re.findall(r'`make ([\w-]+)`', readme):
        assert target in phony, f'README names make {target}, the Makefile has no such rule'


def test_bench_quick_writes_to_an_ignored_folder():
    make = (REPO / 'Makefile').read_text()
    rule = re.search(r'^bench-quick:.*\n((?:\t.*\n)+)', make, re.M).group(1)
    out = re.search(r'--out (\S+)', rule).group(1)
    assert not out.startswith('bench/results'), 'bench-quick overwrites the committed report'
    r = subprocess.run(['git', 'check-ignore', '-q', f'{out}/report.md'], cwd=REPO)
    assert r.returncode == 0, f'{out} is not ignored by git'


def test_readme_lists_exactly_the_sections_run_all_runs():
    source = (REPO / 'bench' / 'run_all.py').read_text()
    sections = re.search(r'SECTIONS = \(([^)]*)\)', source).group(1)
    sections = set(re.findall(r"'(\w+)'", sections))
    row = next(line for line in (REPO / 'README.md').read_text().splitlines()
               if line.startswith('| `bench.run_all'))
    listed = set(re.search(r'the sections ([\w, ]+):', row).group(1).replace(' ', '').split(','))
    assert listed == sections
