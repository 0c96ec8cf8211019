"""
ament_flake8 and ament_pep257 over the Python files no package's own linter test covers.

Every ament_python package runs ament_flake8 and ament_pep257 on itself (``test/test_flake8.py``,
``test/test_pep257.py``, as ``ros2 pkg create`` writes them). This test applies the same
configurations (ament_flake8's own: 99 columns, Google import order, the flake8 plugins of a
stock Jazzy install; ament_pep257's default convention) to the workspace-level tests,
benchmarks, scripts and examples, so there is one configuration for the whole tree.
"""

from pathlib import Path

from ament_flake8.main import main_with_errors
from ament_pep257.main import main as pep257_main
import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = sorted(p.parent.name for p in ROOT.glob('*/package.xml'))
OUTSIDE_PACKAGES = ['tests', 'bench', 'scripts', 'examples', 'conftest.py']


def test_every_package_runs_the_ament_linters():
    python_packages = [p for p in PACKAGES if (ROOT / p / 'setup.py').is_file()]
    assert python_packages
    for package in python_packages:
        for linter in ('flake8', 'pep257'):
            assert (ROOT / package / 'test' / f'test_{linter}.py').is_file(), (package, linter)


@pytest.mark.flake8
@pytest.mark.linter
def test_flake8_outside_packages(monkeypatch):
    monkeypatch.chdir(ROOT)
    paths = [p for p in OUTSIDE_PACKAGES if (ROOT / p).exists()]
    rc, errors = main_with_errors(argv=paths)
    assert rc == 0, 'Found %d code style errors / warnings:\n%s' % (len(errors), '\n'.join(errors))


@pytest.mark.linter
@pytest.mark.pep257
def test_pep257_outside_packages(monkeypatch):
    monkeypatch.chdir(ROOT)
    assert pep257_main(argv=[p for p in OUTSIDE_PACKAGES[:-1] if (ROOT / p).exists()]) == 0
