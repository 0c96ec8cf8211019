"""flake8 at 99 columns over every package, test, benchmark and script (as ament_flake8 would)."""

from pathlib import Path
import subprocess
import sys

ROOT = Path(__file__).resolve().parents[1]


def test_flake8_clean():
    result = subprocess.run(
        [sys.executable, '-m', 'flake8', '--max-line-length', '99',
         '--exclude', '.venv,build,install,log,demo_output', '.'],
        cwd=ROOT, capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr
